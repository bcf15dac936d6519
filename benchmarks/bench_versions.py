"""The iiwa 14's headline calls under two checkouts of iiwa-torch, timed in alternation.

    python benchmarks/bench_versions.py BEFORE AFTER [--rounds 3] [--name any_arm] [--calls clearance]

BEFORE and AFTER are source trees (each put first on ``PYTHONPATH`` of a child process). Each
round runs one child per tree, BEFORE then AFTER, so a change of load on this shared machine
hits both; the table gives each call's median over the rounds (each child's figure is itself
``common.timeit``'s median), 1 thread, the numba kernels as the environment says (default on).
Calls: ``fk`` of one configuration (``(7,)``, one call) and of 100,000, float32 and float64;
``jacobian`` of 10,000 (both dtypes); ``ik.solve`` of 10,000 random reachable poses (float64
targets, ``bench_ik``'s) and of one (``bench_small``'s); ``analytic.iiwa_solve`` of one pose and
``trajectory.track`` of one 50-pose line (``bench_small``'s); a step of the vector env at N =
65,536 with collisions checked. ``--calls clearance`` times (CPU time) ``collision.clearance`` instead, float64
on 1 (``(7,)``), 8 and 32 configurations against the floor and itself, with two spheres and two
boxes besides, and with them again with ``CLEARANCE_NUMPY_BATCH`` set to 0 (the numpy obstacles
off: the torch path); and one single-env step of ``IiwaReach-v0`` and ``IiwaReachObstacles-v0``.
Writes results/<name>.json and .md.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch is imported

from common import machine, markdown_table, save  # noqa: E402

HERE = Path(__file__).resolve().parent
VECTOR_N = 65_536


def child() -> dict:
    """Seconds per call of each measured call, with the iiwa_torch on ``sys.path``."""
    import gymnasium as gym
    import numpy as np
    import torch
    from bench_small import lines, poses
    from common import timeit

    import envs  # noqa: F401  (registers the ids)
    from iiwa_torch import robots, so3
    from iiwa_torch.ik import analytic, solve
    from iiwa_torch.trajectory import track

    torch.set_num_threads(1)
    chain = robots.iiwa14()
    g = torch.Generator().manual_seed(0)
    out = {}
    for dtype in (torch.float32, torch.float64):
        name = str(dtype)[6:]
        one = chain.random_q(1, generator=g, dtype=dtype)[0]
        out[f"fk, 1 (one call), {name}"] = timeit(lambda one=one: chain.fk(one))
        q = chain.random_q(100_000, generator=g, dtype=dtype)
        out[f"fk, 100,000, {name}"] = timeit(lambda q=q: chain.fk(q))
        q = chain.random_q(10_000, generator=g, dtype=dtype)
        out[f"jacobian, 10,000, {name}"] = timeit(lambda q=q: chain.jacobian(q))
    target = chain.fk(chain.random_q(10_000, generator=torch.Generator().manual_seed(2024)))
    out["ik.solve, 10,000, float64"] = timeit(lambda: solve(chain, target), min_time=0.5, repeats=3)
    pos, rot = so3.pose_error(chain.fk(solve(chain, target).q), target)
    out["ik.solve success at 0.1 mm / 1 mrad"] = float(((pos.norm(dim=-1) <= 1e-4) & (rot.norm(dim=-1) <= 1e-3))
                                                       .double().mean())  # fmt: skip
    pose = poses(1)
    out["ik.solve, 1"] = timeit(lambda: solve(chain, pose))
    out["analytic.iiwa_solve, 1"] = timeit(lambda: analytic.iiwa_solve(chain, pose))
    path, q0 = lines(1)
    out["track, one 50-pose line"] = timeit(lambda: track(chain, path, q0))
    vec = gym.make_vec("IiwaReach-v0", num_envs=VECTOR_N)
    vec.reset(seed=0)
    actions = np.random.default_rng(0).uniform(-1, 1, size=(VECTOR_N, 7)).astype(np.float32)
    out["vector env step, N = 65,536, collisions on"] = timeit(lambda: vec.step(actions), min_time=0.5, repeats=3)
    return out


def _obstacles(dtype):
    """Two spheres and two boxes beside the iiwa 14's reach (a world of one set, float64)."""
    import torch

    from iiwa_torch.collision import World

    pose = torch.eye(4, dtype=dtype).repeat(2, 1, 1)
    pose[:, :3, 3] = torch.tensor([[-0.5, 0.2, 0.5], [0.3, -0.5, 0.8]], dtype=dtype)
    return World(floor=0.0, spheres=(torch.tensor([[0.5, 0.0, 0.6], [0.0, 0.5, 0.4]], dtype=dtype),
                                     torch.tensor([0.1, 0.08], dtype=dtype)),
                 boxes=(pose, torch.tensor([[0.1, 0.1, 0.1], [0.05, 0.1, 0.2]], dtype=dtype)))


def clearance_child() -> dict:
    """``--calls clearance``: CPU seconds per call of each clearance call and env step (1 thread:
    the process's CPU time is the call's, whatever else runs on the cores)."""
    import time
    from functools import partial

    import gymnasium as gym
    import numpy as np
    import torch
    from bench_env import single_env_runner
    from common import timeit as wall_timeit

    import envs  # noqa: F401  (registers the ids)
    from iiwa_torch import collision, robots

    timeit = partial(wall_timeit, clock=time.process_time)

    torch.set_num_threads(1)
    chain = robots.iiwa14()
    q = chain.random_q(32, generator=torch.Generator().manual_seed(0))
    world = _obstacles(torch.float64)
    home = getattr(collision, "cpu_paths", getattr(collision, "small", collision))  # where CLEARANCE_NUMPY_BATCH lives
    out = {}
    for size in (1, 8, 32):
        x = q[0] if size == 1 else q[:size]
        out[f"clearance, self + floor, {size}"] = timeit(lambda x=x: collision.clearance(chain, x))
        out[f"clearance, + 2 spheres + 2 boxes, {size}"] = timeit(lambda x=x: collision.clearance(chain, x, world))
        threshold, home.CLEARANCE_NUMPY_BATCH = home.CLEARANCE_NUMPY_BATCH, 0
        out[f"clearance, + 2 spheres + 2 boxes, {size}, numpy obstacles off"] = timeit(
            lambda x=x: collision.clearance(chain, x, world))
        home.CLEARANCE_NUMPY_BATCH = threshold
    for env_id in ("IiwaReach-v0", "IiwaReachObstacles-v0"):
        out[f"env step, {env_id} (gymnasium.make)"] = timeit(single_env_runner(gym.make(env_id)))
    assert np.isfinite(list(out.values())).all()
    return out


def run_child(tree: str, calls: str) -> dict:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([tree, str(HERE)]))
    done = subprocess.run([sys.executable, __file__, "--child", "--calls", calls], env=env, capture_output=True,
                          text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def fmt(key: str, value: float) -> str:
    if key.startswith(("clearance", "env step")):
        return f"{value * 1e6:,.1f} µs per call"
    if "success" in key:
        return f"{100 * value:.2f}%"
    if key.startswith("vector env"):
        return f"{VECTOR_N / value / 1e6:.2f}M env-steps/s"
    if "1 (one call)" in key:
        return f"{value * 1e6:.1f} µs"
    size = key.split(", ")[1]
    if not size[0].isdigit():  # one line, one env step
        return f"{value * 1e3:.2f} ms per call"
    per = value / int(size.replace(",", ""))
    return f"{per * 1e9:,.0f} ns/config" if key.startswith(("fk", "jacobian")) else f"{per * 1e3:.4f} ms/target"


def markdown(payload: dict) -> str:
    """The table of ``main``'s payload: each call's medians before and after, and the ratio."""
    (before, old_commit), (after, new_commit) = payload["trees"].items()
    medians, info = payload["medians"], payload["machine"]
    calls = "" if payload.get("calls", "headline") == "headline" else f" --calls {payload['calls']}"
    clock = ", CPU time" if calls else ""
    rows = []
    for key, old in medians[before].items():
        new = medians[after][key]
        rows.append([key, fmt(key, old), fmt(key, new), "" if "success" in key else f"{old / new:.2f}x"])
    return (
        f"`python benchmarks/bench_versions.py {before} {after} --rounds {payload['rounds']}{calls}`: the iiwa 14 "
        f"preset's calls under {before} ({old_commit}) and {after} ({new_commit}), one child process per tree and "
        f"round, alternating; medians over the rounds of each child's median (`common.timeit`{clock}), 1 thread in "
        "each child, "
        f"IIWA_TORCH_NUMBA {info['IIWA_TORCH_NUMBA']}. Load (1 min) at each child's start: "
        f"{', '.join(f'{x:.1f}' for x in payload['loads'])}.\n\n"
        + markdown_table(["call", "before", "after", "speed-up (before / after)"], rows)
        + f"\nMachine: {info}\n"
    )


CALLS = {"headline": child, "clearance": clearance_child}  # --calls -> the child's function


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("trees", nargs="*", metavar="TREE", help="BEFORE and AFTER source trees")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--name", default="versions", help="results/<name>.json and .md")
    parser.add_argument("--calls", choices=sorted(CALLS), default="headline", help="which calls to time")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(CALLS[args.calls]()))
        return
    if len(args.trees) != 2:
        parser.error(f"give two source trees, BEFORE and AFTER, got {len(args.trees)}")
    runs: dict[str, list[dict]] = {tree: [] for tree in args.trees}
    loads = []
    for round_ in range(args.rounds):
        for tree in args.trees:
            loads.append(os.getloadavg()[0])
            runs[tree].append(run_child(tree, args.calls))
            print(f"round {round_ + 1}, {tree}: {runs[tree][-1]}", flush=True)
    medians = {tree: {k: statistics.median(r[k] for r in rs) for k in rs[0]} for tree, rs in runs.items()}
    before, after = args.trees
    commits = {
        tree: subprocess.run(["git", "-C", tree, "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
        .stdout.strip()
        for tree in args.trees
    }
    info = machine()
    payload = {"trees": commits, "rounds": args.rounds, "calls": args.calls, "runs": runs, "medians": medians,
               "loads": loads, "machine": info}  # fmt: skip
    md = markdown(payload)
    print(md)
    path = save(args.name, payload, md)
    print(f"wrote {path}", file=sys.stderr)


if __name__ == "__main__":
    main()
