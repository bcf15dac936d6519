"""Small batches (1, 10, 100, 1,000 per call): iiwa-torch against roboticstoolbox and pinocchio, one run.

    python benchmarks/bench_small.py [--quick] [--batches 1 10]

Every call at each batch size, one thread, float64, warm (the median of several timed
repeats after a warm-up call); the peers, which take one problem per call, are timed as a
Python loop over the batch:

- ``fk`` (iiwa 14): ours ``chain.fk(q (B, 7))``; roboticstoolbox's C++ ``ETS.eval``;
  pinocchio ``forwardKinematics`` + ``updateFramePlacements`` on the model of our URDF export
  of the DH table;
- ``jacobian``: ours ``chain.jacobian``; roboticstoolbox ``ETS.jacob0``; pinocchio
  ``computeJointJacobians`` + ``getFrameJacobian`` (world-aligned, at the tool);
- ``ik.solve`` on FK of random configurations within the limits: ours at its defaults
  (0.1 mm / 1 mrad); roboticstoolbox ``ETS.ik_LM`` (C++, the same limits, tol 1e-10 on its
  half squared error: at its default 1e-6 most answers miss 0.1 mm);
- ``analytic.iiwa_solve`` on the same poses (no peer);
- ``analytic.pieper`` on the PUMA 560 (roboticstoolbox's table), all 8 branches per pose;
  roboticstoolbox ``Puma560.ikine_a``, one call per branch;
- ``trajectory.track``: B straight lines of 50 poses (``method="gradient"``); roboticstoolbox
  ``ik_LM`` at each pose, warm-started from the previous answer (tol 1e-15: our track's 1e-7 m
  and 1e-6 rad need it);
- the shipped policy (``train/policies/ppo_iiwa_reach``) on B goals for the env's 50 steps:
  B = 1 in the single gymnasium env (``IiwaReach-v0``), and every B in the batched env.

Every answer is scored by the same code, one ``chain.fk`` of its joint angles: success
(0.1 mm / 1 mrad unless stated) and the share within the joint limits; FK and Jacobians by
their largest difference from ours. Then the crossover: the smallest batch size measured at
which one call of ours takes less than the peer's loop. First-call costs (a fresh process,
imports done, the call timed once, cold) are measured separately, in child processes; with the
compiled kernels (numba installed) also with an empty numba cache, where they compile.
Writes results/small.json and results/small.md (``small_torch`` with ``IIWA_TORCH_NUMBA=0``,
``_quick`` appended with ``--quick``, ``_batch1_10`` with ``--batches 1 10``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch is imported

import numpy as np  # noqa: E402
import torch  # noqa: E402
from common import markdown_table, save, timeit  # noqa: E402

from iiwa_torch import compiled, robots, so3  # noqa: E402
from iiwa_torch.ik import analytic, solve  # noqa: E402
from iiwa_torch.runtime import machine_info  # noqa: E402
from iiwa_torch.trajectory import ctraj, track  # noqa: E402
from iiwa_torch.urdf import to_urdf  # noqa: E402

torch.set_num_threads(1)
F64 = torch.float64
CHAIN = robots.iiwa14()
ROOT = Path(__file__).resolve().parent.parent
POLICY = ROOT / "train" / "policies" / "ppo_iiwa_reach"
BATCHES = (1, 10, 100, 1000)
Q_START = torch.tensor([0.1, 0.5, 0.1, -1.2, 0.2, 0.8, 0.3], dtype=F64)
POS_TOL, ROT_TOL = 1e-4, 1e-3


# ---------------------------------------------------------------------- problems and scoring
def configurations(batch: int, seed: int = 0) -> torch.Tensor:
    return CHAIN.random_q(batch, generator=torch.Generator().manual_seed(seed))


def poses(batch: int) -> torch.Tensor:
    return CHAIN.fk(configurations(batch, seed=1))


def lines(batch: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``batch`` straight lines of 50 poses ``(batch, 50, 4, 4)`` and their start configurations."""
    g = torch.Generator().manual_seed(2)
    q0 = Q_START + 0.2 * torch.randn(batch, 7, generator=g, dtype=F64)
    T0 = CHAIN.fk(q0)
    T1 = T0.clone()
    T1[:, :3, 3] += 0.1 * torch.randn(batch, 3, generator=g, dtype=F64)
    return ctraj(T0, T1, 50), q0


def score(chain, q: torch.Tensor, target: torch.Tensor, pos_tol: float = POS_TOL, rot_tol: float = ROT_TOL) -> dict:
    """One FK for every solver: the share of answers within both tolerances and within the limits."""
    q = torch.as_tensor(q, dtype=F64)
    pos, rot = so3.pose_error(chain.fk(q), target.expand(*q.shape[:-1], 4, 4))
    ok = (pos.norm(dim=-1) <= pos_tol) & (rot.norm(dim=-1) <= rot_tol)
    return {"success": float(ok.double().mean()), "within limits": float(chain.within_limits(q, 1e-9).double().mean())}


# ---------------------------------------------------------------------- peers
def rtb_ets(chain, with_limits: bool = True):
    import roboticstoolbox as rtb

    links = [
        rtb.RevoluteDH(a=a, alpha=al, d=d, offset=o, qlim=[lo, hi] if with_limits else None)
        for (a, al, d, o), lo, hi in zip(chain.dh.tolist(), *chain.limits.tolist())
    ]
    return rtb.DHRobot(links, base=chain.base.numpy(), tool=chain.tool.numpy()).ets()


def pinocchio_model():
    import pinocchio as pin

    model = pin.buildModelFromXML(to_urdf(CHAIN))
    return pin, model, model.createData(), model.getFrameId("tool0")


# ---------------------------------------------------------------------- the rows
def row_fk(batch: int, quick: bool) -> dict:
    q = configurations(batch)
    ours = CHAIN.fk(q)
    out = {"ours": timeit(lambda: CHAIN.fk(q), **TIMING)}
    ets, qs = rtb_ets(CHAIN), q.numpy()
    out["roboticstoolbox ETS.eval"] = timeit(lambda: [ets.eval(x) for x in qs], **TIMING)
    out["rtb max diff"] = float(np.abs(np.stack([ets.eval(x) for x in qs]) - ours.numpy()).max())
    pin, model, data, frame = pinocchio_model()

    def run_pin():
        out = []
        for x in qs:
            pin.forwardKinematics(model, data, x)
            pin.updateFramePlacements(model, data)
            out.append(data.oMf[frame].homogeneous)
        return out

    out["pinocchio forwardKinematics"] = timeit(run_pin, **TIMING)
    out["pinocchio max diff"] = float(np.abs(np.stack(run_pin()) - ours.numpy()).max())
    return out


def row_jacobian(batch: int, quick: bool) -> dict:
    q = configurations(batch)
    ours = CHAIN.jacobian(q)
    out = {"ours": timeit(lambda: CHAIN.jacobian(q), **TIMING)}
    ets, qs = rtb_ets(CHAIN), q.numpy()
    out["roboticstoolbox jacob0"] = timeit(lambda: [ets.jacob0(x) for x in qs], **TIMING)
    out["rtb max diff"] = float(np.abs(np.stack([ets.jacob0(x) for x in qs]) - ours.numpy()).max())
    pin, model, data, frame = pinocchio_model()

    def run_pin():
        out = []
        for x in qs:
            pin.computeJointJacobians(model, data, x)
            pin.updateFramePlacements(model, data)
            out.append(pin.getFrameJacobian(model, data, frame, pin.LOCAL_WORLD_ALIGNED))
        return out

    out["pinocchio computeJointJacobians"] = timeit(run_pin, **TIMING)
    out["pinocchio max diff"] = float(np.abs(np.stack(run_pin()) - ours.numpy()).max())
    return out


def row_solve(batch: int, quick: bool) -> dict:
    target = poses(batch)
    out = {"ours": timeit(lambda: solve(CHAIN, target), **TIMING)}
    out["ours score"] = score(CHAIN, solve(CHAIN, target).q, target)
    ets, goals = rtb_ets(CHAIN), target.numpy()

    def peer():
        np.random.seed(0)  # ik_LM draws its restarts from numpy's global generator
        return np.stack([ets.ik_LM(x, tol=1e-10)[0] for x in goals])

    out["roboticstoolbox ik_LM"] = timeit(peer, **TIMING)
    out["rtb score"] = score(CHAIN, peer(), target)
    return out


def row_iiwa_solve(batch: int, quick: bool) -> dict:
    target = poses(batch)
    out = {"ours": timeit(lambda: analytic.iiwa_solve(CHAIN, target), **TIMING)}
    out["ours score"] = score(CHAIN, analytic.iiwa_solve(CHAIN, target).q, target)
    return out


def puma_chains():
    import roboticstoolbox as rtb

    puma_rtb = rtb.models.DH.Puma560()
    table = torch.tensor([[link.a, link.alpha, link.d, link.offset] for link in puma_rtb.links], dtype=F64)
    preset = robots.puma560()
    return puma_rtb, type(preset)(table, limits=preset.limits, name="puma560-rtb")


def row_pieper(batch: int, quick: bool) -> dict:
    from spatialmath import SE3

    puma_rtb, puma = puma_chains()
    target = puma.fk(puma.random_q(batch, generator=torch.Generator().manual_seed(3)))
    out = {"ours": timeit(lambda: analytic.pieper(puma, target), **TIMING)}
    sol = analytic.pieper(puma, target)
    branches = target[:, None].expand(batch, 8, 4, 4)
    out["ours score"] = score(puma, sol.q, branches) | {"valid branches": float(sol.valid.double().mean())}
    configs = ("lun", "luf", "ldn", "ldf", "run", "ruf", "rdn", "rdf")
    goals = [SE3(t.numpy(), check=False) for t in target]

    def peer():
        return [[puma_rtb.ikine_a(goal, config=c) for c in configs] for goal in goals]

    out["roboticstoolbox ikine_a"] = timeit(peer, **TIMING)
    found = peer()
    q = np.stack([[s.q if s.success else np.zeros(6) for s in per] for per in found])
    out["rtb score"] = score(puma, q, branches) | {"valid branches": float(np.mean([[s.success for s in per]
                                                                                    for per in found]))}
    return out


def row_track(batch: int, quick: bool) -> dict:
    path, q0 = lines(batch)
    out = {"ours": timeit(lambda: track(CHAIN, path, q0), **TIMING)}
    res = track(CHAIN, path, q0)
    out["ours score"] = score(CHAIN, res.q, path, 1e-7, 1e-6)
    ets, goals, starts = rtb_ets(CHAIN), path.numpy(), q0.numpy()

    def peer():
        answers = []
        for line, q in zip(goals, starts):
            out = []
            for goal in line:
                q = ets.ik_LM(goal, q0=q, tol=1e-15)[0]
                out.append(q)
            answers.append(np.stack(out))
        return np.stack(answers)

    out["roboticstoolbox ik_LM per pose"] = timeit(peer, **TIMING)
    out["rtb score"] = score(CHAIN, peer(), path, 1e-7, 1e-6)
    return out


def row_policy(batch: int, quick: bool) -> dict:
    sys.path.insert(0, str(ROOT))
    import gymnasium as gym

    from envs import register_envs
    from train.evaluate import load_policy
    from train.rollout import make_goal_set, policy_actor, rollout

    model, vec_normalize, config = load_policy(POLICY)
    act = policy_actor(model, vec_normalize)
    goals = make_goal_set(config["env_id"], batch, 0, config["hyperparams"].get("env_kwargs"))
    out = {"ours": timeit(lambda: rollout(goals, act), **TIMING)}
    final = rollout(goals, act).distance[-1]
    out["ours score"] = {"success": float((final < 0.01).mean())}
    if batch == 1:  # the single gymnasium env, one goal
        register_envs()
        env = gym.make(config["env_id"], **config["hyperparams"].get("env_kwargs", {}))

        def single():
            obs, _ = env.reset(seed=0)
            for _ in range(50):
                obs, *_ = env.step(act({k: v[None] for k, v in obs.items()})[0])
            return obs

        out["ours, single env"] = timeit(single, **TIMING)
    return out


ROWS = {
    "fk": row_fk,
    "jacobian": row_jacobian,
    "ik.solve": row_solve,
    "analytic.iiwa_solve": row_iiwa_solve,
    "analytic.pieper (PUMA 560)": row_pieper,
    "trajectory.track (50-pose lines)": row_track,
    "shipped policy (50 steps)": row_policy,
}


# ---------------------------------------------------------------------- first calls
def first_call(name: str) -> float:
    """Seconds of the first call of ``name`` at batch 1 in this (fresh) process, its inputs prepared
    beforehand (which may warm other calls: the poses come from ``fk``)."""
    if name == "fk":
        q = configurations(1)
        return _once(lambda: CHAIN.fk(q))
    if name == "jacobian":
        q = configurations(1)
        return _once(lambda: CHAIN.jacobian(q))
    if name == "ik.solve":
        target = poses(1)
        return _once(lambda: solve(CHAIN, target))
    if name == "analytic.iiwa_solve":
        target = poses(1)
        return _once(lambda: analytic.iiwa_solve(CHAIN, target))
    if name == "analytic.pieper (PUMA 560)":
        puma = robots.puma560()
        target = puma.fk(puma.random_q(1, generator=torch.Generator().manual_seed(3)))
        return _once(lambda: analytic.pieper(puma, target))
    if name == "trajectory.track (50-pose lines)":
        path, q0 = lines(1)
        return _once(lambda: track(CHAIN, path, q0))
    raise ValueError(f"no first-call measurement for {name!r}")


def _once(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def first_calls(cache_dir: str | None = None) -> dict:
    """Each call's first-call seconds in a fresh process; with ``cache_dir``, numba's on-disk cache
    is that (empty) directory, so the compiled kernels compile instead of loading."""
    out = {}
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    if cache_dir is not None:
        env["NUMBA_CACHE_DIR"] = cache_dir
    for name in list(ROWS)[:-1]:  # the policy's first call is its model loading, not measured here
        child = subprocess.run([sys.executable, __file__, "--first-call", name], capture_output=True, text=True,
                               check=True, env=env)
        out[name] = float(child.stdout.strip().splitlines()[-1])
    return out


# ---------------------------------------------------------------------- report
def crossover(rows: dict, peer: str) -> int | None:
    """The smallest batch measured at which ours takes less time per call than the peer's loop."""
    for batch, row in sorted(rows.items()):
        if peer in row and row["ours"] < row[peer]:
            return batch
    return None


def fmt_ms(seconds: float | None) -> str:
    if seconds is None:
        return "-"
    return f"{seconds * 1e3:.3f}" if seconds < 1e-2 else f"{seconds * 1e3:.1f}"


def peers_of(row: dict) -> list[str]:
    return [k for k, v in row.items() if k != "ours" and isinstance(v, float) and "diff" not in k]


def markdown(results: dict, command: str) -> str:
    m = results["machine"]
    md = ["# Small batches\n\n", f"`{command}`; ",
          f"{m['cpu']}, torch {m['torch']}, 1 thread, float64, load {m['loadavg']} at the start and "
          f"{m['loadavg_at_end']} at the end. Milliseconds per call (the peers: a loop over the batch). "
          f"Compiled kernels (numba, `iiwa_torch.compiled`): {'on' if results['compiled'] else 'off'}.\n\n"]
    table = []
    for name, by_batch in results["rows"].items():
        for batch, row in by_batch.items():
            peer_cells = [f"{p}: {fmt_ms(row[p])}" for p in peers_of(row)]
            quality = []
            for key, value in row.items():
                if "diff" in key:
                    quality.append(f"{key} {value:.1e}")
                elif key.endswith("score"):
                    quality.append(f"{key.split()[0]} " + ", ".join(f"{k} {v:.3f}" for k, v in value.items()))
            best = min((row[p] for p in peers_of(row) if not p.startswith("ours")), default=None)
            ratio = "-" if best is None else f"{best / row['ours']:.2g}x"
            table.append([name, batch, fmt_ms(row["ours"]), "; ".join(peer_cells) or "-", ratio, "; ".join(quality)])
    md.append(markdown_table(["call", "batch", "ours ms", "peers ms", "fastest peer / ours", "answers"], table))
    md.append("\n## Crossover: smallest batch at which one call of ours beats the peer's loop\n\n")
    rows = []
    for name, by_batch in results["rows"].items():
        for peer in peers_of(next(iter(by_batch.values()))):
            if peer.startswith("ours"):
                continue
            at = crossover(by_batch, peer)
            rows.append([name, peer, at if at is not None else f"> {max(by_batch)} (not within the batches measured)"])
    md.append(markdown_table(["call", "peer", "crossover batch"], rows))
    md.append("\n## First call at batch 1 (a fresh process, inputs prepared, one cold call)\n\n")
    cold = results.get("first call, compiling")
    if cold:
        md.append("With the compiled kernels: the first call in a process loads them from numba's on-disk cache; "
                  "the first ever (an empty cache) compiles them.\n\n")
    md.append(markdown_table(["call", "first call ms", *(["first call, empty numba cache ms"] if cold else []),
                              "warm ms"],
                             [[k, fmt_ms(v), *([fmt_ms(cold[k])] if cold else []),
                               fmt_ms(results["rows"][k][1]["ours"]) if 1 in results["rows"][k] else "-"]
                              for k, v in results["first call"].items()]))
    return "".join(md)


TIMING: dict = {}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer and shorter repeats, batches up to 100")
    parser.add_argument("--batches", type=int, nargs="+", choices=BATCHES, help="only these batch sizes (the file "
                        "name then says which)")
    parser.add_argument("--first-call", help=argparse.SUPPRESS)  # child mode: time one first call
    args = parser.parse_args()
    if args.first_call:
        print(first_call(args.first_call))
        return
    TIMING.update({"min_time": 0.02, "repeats": 3} if args.quick else {"min_time": 0.2, "repeats": 7})
    batches = tuple(args.batches or (BATCHES[:3] if args.quick else BATCHES))
    results = {"machine": machine_info(), "batches": batches, "rows": {}, "compiled": compiled.ENABLED}
    if compiled.ENABLED:
        with tempfile.TemporaryDirectory() as empty:
            results["first call, compiling"] = first_calls(empty)
        print("first call, compiling", results["first call, compiling"], flush=True)
    results["first call"] = first_calls()
    print("first call", results["first call"], flush=True)
    for name, fn in ROWS.items():
        results["rows"][name] = {}
        for batch in batches:
            results["rows"][name][batch] = row = fn(batch, args.quick)
            print(name, batch, json.dumps(row), flush=True)
    results["machine"]["loadavg_at_end"] = list(os.getloadavg())
    md = markdown(results, " ".join(["python benchmarks/bench_small.py", *sys.argv[1:]]))
    name = "small" if compiled.ENABLED else "small_torch"  # IIWA_TORCH_NUMBA=0: the torch paths alone
    name += "_quick" if args.quick else ""
    name += f"_batch{'_'.join(map(str, batches))}" if args.batches else ""
    path = save(name, results, md)
    print(md)
    print(f"written: {path}")


if __name__ == "__main__":
    main()
