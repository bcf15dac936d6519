"""Random-action env-steps per second: the iiwa reaching envs against panda-gym and FetchReach, one run.

    python benchmarks/bench_env.py [--quick] [--robot panda]

Measured in the same run, each with pre-drawn uniform random actions and a reset when an
episode ends (the vector envs reset themselves):

Every iiwa row checks collisions every step (the default: floor and self-collision, one
batched ``iiwa_torch.collision.clearance`` call per step), except the one marked
``collision='off'`` (the kinematic step alone, for comparison):

- ``IiwaReach-v0`` through ``gymnasium.make`` (one arm per call, with gymnasium's wrappers);
- ``IiwaReachObstacles-v0`` (1-4 random spheres or boxes per env) as a single env and a vector env;
- ``IiwaReachVectorEnv`` (``gymnasium.make_vec``) at N = 1, 256, 4,096, 65,536 arms per call;
  the largest N also on 1 thread, and on 2 threads in child processes with OpenMP's default
  wait policy and with ``OMP_WAIT_POLICY=ACTIVE`` (the policy is read once, when torch
  loads; this script sets ``PASSIVE`` for itself);
- ``envs.sb3.IiwaReachVecEnv`` (the stable-baselines3 VecEnv) at N = 256 and 4,096;
- ``chain.position_batch_last`` alone at N = 1 and the largest N: the floor of a step, which
  is one position-only FK (and ``chain.fk``, the full pose, for comparison);
- panda-gym ``PandaReach-v3`` (PyBullet) and gymnasium-robotics ``FetchReach-v4`` (MuJoCo),
  if installed: ``pip install panda-gym gymnasium-robotics "mujoco<3.3"`` (gymnasium-robotics
  1.4.2 fails with MuJoCo >= 3.3 on this machine).

The vector env's target, 2M env-steps/s at N = 65,536 on 2 cores with collisions checked,
is read on the 2-thread rows of each wait policy (``--quick`` times N = 65,536 too, briefly;
this machine's figures and advice: docs/envs.md).
The two ratios with targets (single env / PandaReach-v3, SB3 VecEnv / vector env at N = 256)
are measured again with the two sides timed in alternation, 7 rounds of 0.5 s each, and
their median reported: on a shared machine a change of load then hits both sides.

``--robot panda`` times the Franka Panda ids instead (``FrankaReach-v0``; the obstacle rows are
``FrankaReach-v0`` with ``obstacles=4``), its own rows' labels unchanged, against the same peers.

Prints a table with the targets of the issue; writes results/env.json and results/env.md
(``env_panda`` with ``--robot panda``).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import warnings

if "--largest-only" not in sys.argv:  # a child times the policy it was given (none: OpenMP's default)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch is imported

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from common import markdown_table, save, timeit  # noqa: E402

import envs  # noqa: E402, F401  (registers the ids)
from envs.sb3 import IiwaReachVecEnv  # noqa: E402
from iiwa_torch.runtime import machine_info  # noqa: E402

VECTOR_SIZES = [1, 256, 4_096, 65_536]
SB3_SIZES = [256, 4_096]
N_ACTIONS = 16  # distinct pre-drawn action batches, cycled
#: --robot -> the reach id and the obstacle id with its options
ROBOT_IDS = {"iiwa": ("IiwaReach-v0", "IiwaReachObstacles-v0", {}),
             "panda": ("FrankaReach-v0", "FrankaReach-v0", {"obstacles": 4})}
ROBOT = sys.argv[sys.argv.index("--robot") + 1] if "--robot" in sys.argv else "iiwa"  # a child reads it too
REACH, OBSTACLES, OBSTACLE_OPTIONS = ROBOT_IDS.get(ROBOT, ROBOT_IDS["iiwa"])


def single_env_runner(env: gym.Env, seed: int = 0):
    """One ``step`` per call, with a ``reset`` when the episode ends."""
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    low, high = env.action_space.low, env.action_space.high
    actions = rng.uniform(low, high, size=(N_ACTIONS, *env.action_space.shape)).astype(env.action_space.dtype)
    state = {"i": 0}

    def step():
        state["i"] = (state["i"] + 1) % N_ACTIONS
        _, _, terminated, truncated, _ = env.step(actions[state["i"]])
        if terminated or truncated:
            env.reset()

    return step


def batched_runner(step_fn, n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1, 1, size=(N_ACTIONS, n, 7)).astype(np.float32)
    state = {"i": 0}

    def step():
        state["i"] = (state["i"] + 1) % N_ACTIONS
        step_fn(actions[state["i"]])

    return step


def alternating_ratios(slow, fast, rounds: int = 7) -> list[float]:
    """Per round, the time of one call of ``slow`` over one call of ``fast``, the two timed in
    alternation (0.5 s each) so that a change of load on this shared machine hits both."""
    return [timeit(slow, min_time=0.5, repeats=1) / timeit(fast, min_time=0.5, repeats=1) for _ in range(rounds)]


def vector_runner(n: int, env_id: str = REACH, **options):
    vec = gym.make_vec(env_id, num_envs=n, **options)
    vec.reset(seed=0)
    return batched_runner(vec.step, n)


def largest_in_child(timing: dict, wait_policy: str | None) -> float:
    """Seconds per step of the vector env at the largest N on 2 threads, timed in a child
    process with ``OMP_WAIT_POLICY=wait_policy`` (``None``: unset, OpenMP's default, which
    spins a while before sleeping). With ``ACTIVE`` OpenMP's threads spin between ops: on an
    otherwise idle machine the fast setting (no op waits for a sleeping thread to wake);
    with another process busy on the cores, by far the slowest (benchmarks/results/busy.md; which is why this
    script itself runs with ``PASSIVE``)."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if wait_policy is not None:
        env["OMP_WAIT_POLICY"] = wait_policy
    child = subprocess.run(
        [sys.executable, __file__, "--largest-only", str(timing["min_time"]), str(timing["repeats"]), "--robot", ROBOT],
        env=env, capture_output=True, text=True, check=True,
    )
    return float(child.stdout.split()[-1])


def peers() -> dict[str, gym.Env]:
    found = {}
    try:
        import panda_gym  # noqa: F401

        found["panda-gym PandaReach-v3"] = gym.make("PandaReach-v3")
    except ImportError:
        print("panda-gym not installed: skipped")
    try:
        import gymnasium_robotics

        gym.register_envs(gymnasium_robotics)
        env = gym.make("FetchReach-v4")
        env.reset(seed=0)
        found["gymnasium-robotics FetchReach-v4"] = env
    except Exception as exc:  # ImportError, or a MuJoCo version it does not support
        print(f"gymnasium-robotics FetchReach-v4 unavailable: {type(exc).__name__}: {exc}")
    return found


def write_results(args, results: list, checks: dict, panda: float | None, rounds: list, sb3_rounds: list) -> None:
    """The table of ``results`` ``(name, arms per call, s per call)`` and the ``checks`` -> results/env*.md/json."""
    rows = []
    for name, n, seconds in results:
        ratio = "" if panda is None else f"{(n / seconds) * panda:,.1f}x"
        rows.append([name, f"{n:,}", f"{n / seconds:,.0f}", f"{seconds * 1e6:,.1f}", ratio])
    md = f"Arm: `--robot {args.robot}` (the vector and SB3 rows run {REACH}).\n\n"
    md += markdown_table(["env", "arms per call", "env-steps/s", "µs per call", "vs PandaReach-v3"], rows)
    md += "\n" + markdown_table(
        ["target", "measured"], [[k, "n/a" if v is None else f"{v:,.2f}"] for k, v in checks.items()]
    )
    info = machine_info()
    md += f"\nMachine: {info}\n"
    print("\n" + md)
    payload = {
        "machine": info,
        "torch_threads": torch.get_num_threads(),
        "quick": args.quick,
        "results": [
            {"env": name, "num_envs": n, "seconds_per_call": s, "env_steps_per_s": n / s} for name, n, s in results
        ],
        "checks": checks,
        "single_vs_panda_alternating_rounds": rounds,
        "sb3_vs_vector_env_alternating_rounds_n256": sb3_rounds,
    }
    stem = "env" if args.robot == "iiwa" else f"env_{args.robot}"
    path = save(f"{stem}_quick" if args.quick else stem, payload, md)
    print(f"wrote {path}")


class Recorder:
    """The rows of the table, ``(name, arms per call, seconds per call)``, printed as they come."""

    def __init__(self, timing: dict) -> None:
        self.timing, self.results = timing, []

    def report(self, name: str, n: int, seconds: float) -> float:
        self.results.append((name, n, seconds))
        print(f"{name:<40} N={n:>6}  {n / seconds:>14,.0f} env-steps/s  {seconds * 1e6:>10,.1f} us/call", flush=True)
        return seconds

    def record(self, name: str, n: int, fn) -> float:
        return self.report(name, n, timeit(fn, **self.timing))


def time_vector_envs(rec: Recorder) -> tuple[dict, float, str, dict]:
    """The vector env at every N, unchecked at the largest, and the obstacle envs -> seconds per
    step by N, the unchecked step's, the obstacle rows' label and their seconds by N."""
    raw = {n: rec.record("IiwaReachVectorEnv (make_vec)", n, vector_runner(n)) for n in VECTOR_SIZES}
    unchecked = rec.record("IiwaReachVectorEnv (make_vec), collision='off'", VECTOR_SIZES[-1],
                           vector_runner(VECTOR_SIZES[-1], collision="off"))
    label = f"{OBSTACLES}{', obstacles=4' if OBSTACLE_OPTIONS else ''}"
    rec.record(f"{label} (gymnasium.make)", 1, single_env_runner(gym.make(OBSTACLES, **OBSTACLE_OPTIONS)))
    obstacles = {n: rec.record(f"{label} (make_vec)", n, vector_runner(n, OBSTACLES, **OBSTACLE_OPTIONS))
                 for n in (256, 4_096)}
    return raw, unchecked, label, obstacles


def time_largest(rec: Recorder) -> dict:
    """Seconds per step at the largest N: on 1 thread, and on 2 threads with other wait policies."""
    largest = {}
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # on a busy machine 2 threads can lose
    largest["1 thread"] = rec.record("IiwaReachVectorEnv (make_vec), 1 thread", VECTOR_SIZES[-1],
                                     vector_runner(VECTOR_SIZES[-1]))
    torch.set_num_threads(threads)
    for policy in (None, "ACTIVE"):
        setting = f"2 threads, OMP_WAIT_POLICY={policy or 'unset'}"
        largest[setting] = rec.report(f"IiwaReachVectorEnv (make_vec), {setting}", VECTOR_SIZES[-1],
                                      largest_in_child(rec.timing, policy))
    return largest


def time_floor(rec: Recorder) -> None:
    """The floor of a step: the kinematics of the batch (float32, as the env's state), which for
    position goals is the position-only kernel; the full pose for comparison."""
    chain = envs.make_task(REACH).robot  # the env's chain, in the state's dtype (float32)
    for n in (1, VECTOR_SIZES[-1]):
        q = chain.random_q(n, generator=torch.Generator().manual_seed(0), dtype=torch.float32)
        rec.record("chain.position alone (the step's floor)", n, lambda q=q: chain.position_batch_last(q.T))
        rec.record("chain.fk alone (full pose)", n, lambda q=q: chain.fk(q))


def time_alternating(single_peer, sb3_runner) -> tuple[list, list]:
    """The two ratios with targets again, timed in alternation: single env / PandaReach-v3 (if
    ``single_peer``) and SB3 VecEnv / vector env at N = 256, 7 rounds each."""
    rounds = []
    if single_peer is not None:
        rounds = alternating_ratios(single_env_runner(single_peer), single_env_runner(gym.make(REACH)))
        print("single env / PandaReach-v3, alternating rounds:", ", ".join(f"{r:.1f}x" for r in rounds))
    vec = gym.make_vec(REACH, num_envs=256)
    vec.reset(seed=0)
    sb3_rounds = alternating_ratios(sb3_runner, batched_runner(vec.step, 256))
    print("SB3 VecEnv / vector env at N=256, alternating rounds:", ", ".join(f"{r:.2f}" for r in sb3_rounds))
    return rounds, sb3_rounds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="small sizes, short timings (a smoke run)")
    parser.add_argument("--largest-only", nargs=2, type=float, metavar=("MIN_TIME", "REPEATS"),
                        help=argparse.SUPPRESS)  # the child process of largest_in_child
    parser.add_argument("--robot", choices=sorted(ROBOT_IDS), default="iiwa", help="the arm whose ids are timed")
    args = parser.parse_args()
    if args.largest_only:
        min_time, repeats = args.largest_only
        print(timeit(vector_runner(VECTOR_SIZES[-1]), min_time=min_time, repeats=int(repeats)))
        return
    warnings.filterwarnings("ignore")
    rec = Recorder({"min_time": 0.05, "repeats": 3} if args.quick else {"min_time": 1.0, "repeats": 5})
    found = peers()
    for name, env in found.items():
        rec.record(name, 1, single_env_runner(env))
    panda = next((s for name, n, s in rec.results if name.startswith("panda-gym")), None)
    single = rec.record(f"{REACH} (gymnasium.make)", 1, single_env_runner(gym.make(REACH)))
    raw, unchecked, obstacle_name, obstacles = time_vector_envs(rec)
    largest = {} if args.quick else time_largest(rec)
    time_floor(rec)
    sb3, sb3_runners = {}, {}
    for n in SB3_SIZES:
        venv = IiwaReachVecEnv(n, REACH, seed=0)
        venv.reset()
        sb3_runners[n] = batched_runner(venv.step, n)
        sb3[n] = rec.record("envs.sb3.IiwaReachVecEnv", n, sb3_runners[n])
    rounds, sb3_rounds = ([], []) if args.quick else time_alternating(found.get("panda-gym PandaReach-v3"),
                                                                      sb3_runners[256])  # fmt: skip
    checks = {
        "single env >= 5x PandaReach-v3 steps/s (collisions checked)": None if panda is None else panda / single,
        "single env vs PandaReach-v3, median of 7 alternating rounds": statistics.median(rounds) if rounds else None,
        "vector env env-steps/s at N=65,536, 2 threads, OMP_WAIT_POLICY=PASSIVE, collisions checked (>= 2M)": (
            65_536 / raw[65_536]
        ),
        "the same with collision='off'": VECTOR_SIZES[-1] / unchecked,
        f"{obstacle_name} vector env env-steps/s at N=4,096": 4_096 / obstacles[4_096],
        **{f"vector env env-steps/s at N=65,536, {setting}": 65_536 / s for setting, s in largest.items()},
        "SB3 VecEnv / vector env time per step at N=256 (target <= 2)": sb3[256] / raw[256],
        "SB3 / vector env at N=256, median of 7 alternating rounds": (
            statistics.median(sb3_rounds) if sb3_rounds else None
        ),
    }
    write_results(args, rec.results, checks, panda, rounds, sb3_rounds)


if __name__ == "__main__":
    main()
