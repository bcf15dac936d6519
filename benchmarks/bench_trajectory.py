"""Trajectories on the iiwa 14: iiwa-torch against roboticstoolbox, one run.

    python benchmarks/bench_trajectory.py [--quick]

- jtraj: 10,000 start/goal pairs x 50 steps; ours in one batched call, roboticstoolbox's
  ``jtraj`` one pair per call (timed on 300 pairs, per pair);
- ctraj: 10,000 pose pairs x 50 steps; ours batched, roboticstoolbox's ``ctraj`` (spatialmath
  ``SE3.interp``) one pair per call;
- tracking one 0.36 m line of 50 poses: ours ``track`` (analytic and gradient) against
  roboticstoolbox ``ETS.ik_LM`` (C++) called at each pose, warm-started from the last answer
  (tol 1e-10, so that it reaches our 1e-6 m), all scored by our FK;
- tracking 256 lines x 30 poses at once (ours; the peer's per-line time scales linearly);
- tracking the one line past a sphere (radius 5 cm, where the untroubled path's elbow passes
  half way) with ``world=``: time, the path's smallest clearance and largest joint step.

Values are checked against the peer where both compute the same thing. Writes
results/trajectory.json and results/trajectory.md.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch is imported

import numpy as np  # noqa: E402
import torch  # noqa: E402
from common import Robot, markdown_table, save, timeit  # noqa: E402

from iiwa_torch import robots, so3  # noqa: E402
from iiwa_torch.collision import World  # noqa: E402
from iiwa_torch.runtime import machine_info  # noqa: E402
from iiwa_torch.trajectory import ctraj, jtraj, path_clearance, track  # noqa: E402

F64 = torch.float64
CHAIN = robots.iiwa14()
Q_START = torch.tensor([0.1, 0.5, 0.1, -1.2, 0.2, 0.8, 0.3], dtype=F64)


def per_call(fn, items, repeats: int) -> float:
    """Median over ``repeats`` of the seconds per item of ``fn`` called on each item in turn."""
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        for item in items:
            fn(item)
        samples.append((time.perf_counter() - start) / len(items))
    return float(np.median(samples))


def _against_peer(pairs: int, ours: float, peer: float, error_name: str, error: float) -> dict:
    """One record: our batched time for ``pairs`` 50-step trajectories, the peer's time per pair."""
    return {
        "pairs": pairs,
        "steps": 50,
        "ours s (batched)": ours,
        "ours us/pair": ours / pairs * 1e6,
        "roboticstoolbox us/pair": peer * 1e6,
        "speed-up": peer / (ours / pairs),
        error_name: float(error),
    }


def bench_jtraj(pairs: int, peer_pairs: int, repeats: int) -> dict:
    import roboticstoolbox as rtb

    g = torch.Generator().manual_seed(0)
    q0, q1 = CHAIN.random_q(2, pairs, generator=g)
    t = torch.linspace(0, 2.0, 50, dtype=F64)
    ours = timeit(lambda: jtraj(q0, q1, t), repeats=repeats, min_time=0.1)
    mine = jtraj(q0[:peer_pairs], q1[:peer_pairs], t)
    a, b, tn = q0.numpy(), q1.numpy(), t.numpy()
    peer = per_call(lambda i: rtb.jtraj(a[i], b[i], tn), range(peer_pairs), repeats)
    ref = np.stack([rtb.jtraj(a[i], b[i], tn).q for i in range(peer_pairs)])
    return _against_peer(pairs, ours, peer, "max |q ours - q rtb| rad", np.abs(mine.q.numpy() - ref).max())


def bench_ctraj(pairs: int, peer_pairs: int, repeats: int) -> dict:
    import roboticstoolbox as rtb
    from spatialmath import SE3

    g = torch.Generator().manual_seed(1)
    T0, T1 = CHAIN.fk(CHAIN.random_q(2, pairs, generator=g))
    ours = timeit(lambda: ctraj(T0, T1, 50), repeats=repeats, min_time=0.1)
    mine = ctraj(T0[:peer_pairs], T1[:peer_pairs], 50)
    s = np.linspace(0, 1, 50)
    a = [SE3(x, check=False) for x in T0[:peer_pairs].numpy()]
    b = [SE3(x, check=False) for x in T1[:peer_pairs].numpy()]
    peer = per_call(lambda i: rtb.ctraj(a[i], b[i], s=s), range(peer_pairs), repeats)
    ref = np.stack([np.stack(rtb.ctraj(a[i], b[i], s=s).A) for i in range(peer_pairs)])
    return _against_peer(pairs, ours, peer, "max |pose ours - pose rtb|", np.abs(mine.numpy() - ref).max())


def line(q0: torch.Tensor, offset, steps: int) -> torch.Tensor:
    T0 = CHAIN.fk(q0)
    T1 = T0.clone()
    T1[..., :3, 3] += torch.as_tensor(offset, dtype=F64)
    return ctraj(T0, T1, steps)


def score(q: torch.Tensor, path: torch.Tensor) -> dict:
    pos, rot = so3.pose_error(CHAIN.fk(q), path)
    return {
        "max pos err m": float(pos.norm(dim=-1).max()),
        "max rot err rad": float(rot.norm(dim=-1).max()),
        "max joint step rad": float(q.diff(dim=-2).abs().max()),
        "within limits": bool(CHAIN.within_limits(q, tol=1e-9).all()),
    }


def bench_track_one(repeats: int) -> dict:
    path = line(Q_START, [0.0, 0.3, -0.2], 50)
    rows = {}
    for method in ("analytic", "gradient"):
        seconds = timeit(lambda m=method: track(CHAIN, path, Q_START, method=m), repeats=repeats, min_time=0.0)
        rows[f"ours track({method})"] = {"s/line": seconds} | score(track(CHAIN, path, Q_START, method=method).q, path)
    ets = Robot("iiwa14").rtb_ets()
    goals = path.numpy()

    def peer() -> torch.Tensor:
        q, out = Q_START.numpy(), []
        for goal in goals:
            q = ets.ik_LM(goal, q0=q, tol=1e-10)[0]
            out.append(q)
        return torch.tensor(np.stack(out))

    seconds = timeit(peer, repeats=repeats, min_time=0.0)
    rows["roboticstoolbox ik_LM per pose (C++)"] = {"s/line": seconds} | score(peer(), path)
    return rows


def bench_track_batch(lines: int, repeats: int) -> dict:
    g = torch.Generator().manual_seed(2)
    q0 = Q_START + 0.2 * torch.randn(lines, 7, generator=g, dtype=F64)
    path = line(q0, 0.1 * torch.randn(lines, 3, generator=g, dtype=F64), 30)
    rows = {}
    for method in ("analytic", "gradient"):
        seconds = timeit(lambda m=method: track(CHAIN, path, q0, method=m), repeats=repeats, min_time=0.0)
        res = track(CHAIN, path, q0, method=method)
        ok = res.success.all(-1)
        rows[f"ours track({method})"] = {
            "lines": lines,
            "steps": 30,
            "s (all lines)": seconds,
            "ms/line": seconds / lines * 1e3,
            "lines solved": float(ok.double().mean()),
            "solved lines with a step > 0.1 rad": int((res.max_step[ok] > 0.1).sum()),
        }
    return rows


def bench_track_world(repeats: int) -> dict:
    path = line(Q_START, [0.0, 0.3, -0.2], 50)
    free = track(CHAIN, path, Q_START, method="analytic")
    centre = CHAIN.fk_all(free.q[25])[3, :3, 3]  # the elbow half way
    world = World(floor=0.0, spheres=(centre[None], torch.tensor([0.05], dtype=F64)))
    rows = {}
    for name, kwargs in (
        ("analytic, no world", {"method": "analytic"}),
        ("analytic, world, margin 1 cm", {"method": "analytic", "world": world, "margin": 0.01}),
        ("gradient, world, margin 1 cm", {"method": "gradient", "world": world, "margin": 0.01}),
    ):
        seconds = timeit(lambda k=kwargs: track(CHAIN, path, Q_START, **k), repeats=repeats, min_time=0.0)
        res = track(CHAIN, path, Q_START, **kwargs)
        lowest = path_clearance(CHAIN, res.q, world).amin()
        rows[name] = {"s/line": seconds, "min clearance m": float(lowest)} | score(res.q, path)
    return rows


def markdown(results: dict, quick: bool) -> str:
    """The header (command, machine) and one table per part of ``results``."""
    m = results["machine"]
    md = ["# Trajectory benchmark\n", f"`python benchmarks/bench_trajectory.py{' --quick' if quick else ''}`; "]
    md.append(f"{m['cpu']}, torch {m['torch']}, {m['torch_threads']} threads, load {m['loadavg']}\n\n")
    rows = [
        [name, r["pairs"], f"{r['ours us/pair']:.2f}", f"{r['roboticstoolbox us/pair']:.0f}", f"{r['speed-up']:.0f}x"]
        for name, r in (("jtraj", results["jtraj"]), ("ctraj", results["ctraj"]))
    ]
    md.append(markdown_table(["call (50 steps)", "pairs", "ours us/pair (batched)", "rtb us/pair", "speed-up"], rows))
    md.append("\n")
    rows = [
        [name, f"{r['s/line'] * 1e3:.0f}", f"{r['max pos err m']:.1e}", f"{r['max joint step rad']:.3f}"]
        for name, r in results["track one line"].items()
    ]
    md.append(markdown_table(["tracking one line, 50 poses", "ms", "max pos err (m)", "max joint step (rad)"], rows))
    md.append("\n")
    rows = [
        [
            name,
            r["lines"],
            f"{r['ms/line']:.1f}",
            f"{100 * r['lines solved']:.1f}%",
            r["solved lines with a step > 0.1 rad"],
        ]
        for name, r in results["track many lines"].items()
    ]
    md.append(
        markdown_table(["tracking lines at once, 30 poses", "lines", "ms/line", "solved", "jumps > 0.1 rad"], rows)
    )
    md.append("\n")
    rows = [
        [
            name,
            f"{r['s/line'] * 1e3:.0f}",
            f"{r['min clearance m'] * 1e3:.1f}",
            f"{r['max pos err m']:.1e}",
            f"{r['max joint step rad']:.3f}",
        ]
        for name, r in results["track past a sphere"].items()
    ]
    md.append(
        markdown_table(
            ["one line past a sphere, 50 poses", "ms", "min clearance (mm)", "max pos err (m)", "max joint step (rad)"],
            rows,
        )
    )
    return "".join(md)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smaller batches, fewer repeats (a smoke run)")
    args = parser.parse_args()
    pairs, peer_pairs, lines, repeats = (1_000, 50, 32, 1) if args.quick else (10_000, 300, 256, 3)
    results = {"machine": machine_info()}
    parts = {
        "jtraj": lambda: bench_jtraj(pairs, peer_pairs, repeats),
        "ctraj": lambda: bench_ctraj(pairs, peer_pairs, repeats),
        "track one line": lambda: bench_track_one(repeats),
        "track many lines": lambda: bench_track_batch(lines, repeats),
        "track past a sphere": lambda: bench_track_world(repeats),
    }
    for name, run in parts.items():
        results[name] = run()
        print(name, results[name], flush=True)
    results["machine"]["loadavg_at_end"] = os.getloadavg()
    md = markdown(results, args.quick)
    path = save("trajectory_quick" if args.quick else "trajectory", results, md)
    print(md)
    print(f"written: {path}")


if __name__ == "__main__":
    main()
