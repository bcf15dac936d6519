"""IK on 10,000 random reachable iiwa 14 poses: iiwa-torch against its peers, one run.

    python benchmarks/bench_ik.py [--quick]

Solvers, all on the same targets (FK of seeded random configurations within the limits):
- ours: ``iiwa_torch.ik.solve`` (batched LM), float32, float64 (``precision="auto"``: float32
  iterations, float64 check; and ``"input"``: float64 iterations), 1 and 2 threads;
- pytorch_kinematics ``PseudoInverseIK`` (batched torch, float32; the settings the issue
  measured: 10 retries, 50 iterations, ``early_stopping_any_converged``, regularisation 1e-6)
  and its ``PseudoInverseIKWithSVD`` variant, on the chain loaded from our URDF export;
- roboticstoolbox ``ETS.ik_LM`` (C++, one call per target) at its defaults, tol 1e-7 and tol 1e-10,
  on an ETS built from the same DH table and limits.

Every answer is scored by the same code: our ``chain.fk`` and ``so3.pose_error`` (after a
check that each peer's FK agrees with ours), success at 0.1 mm / 1 mrad and at 1 mm /
10 mrad, and the share of answers within the joint limits. Then the success/time trade-off
of ours as seeds and iterations vary, and ours with a world: random collision-free
configurations' poses, each with the floor and 3 random spheres near the arm (clear of that
configuration), ``solve(..., world=, margin=0.01)`` scored by FK and ``collision.clearance``.
Writes results/ik.json and results/ik.md.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch is imported

import numpy as np  # noqa: E402
import torch  # noqa: E402
from common import markdown_table, save  # noqa: E402

from iiwa_torch import robots, so3  # noqa: E402
from iiwa_torch.collision import World, clearance, robot_capsules  # noqa: E402
from iiwa_torch.ik import solve  # noqa: E402
from iiwa_torch.runtime import machine_info  # noqa: E402
from iiwa_torch.urdf import to_urdf  # noqa: E402

CHAIN = robots.iiwa14()
TOLERANCES = {"0.1mm/1mrad": (1e-4, 1e-3), "1mm/10mrad": (1e-3, 1e-2)}
MARGIN = 0.01  # clearance required with a world, m


def score(q: torch.Tensor, target: torch.Tensor) -> dict:
    """One FK for every solver: success at both tolerances and the share within limits."""
    q = q.to(torch.float64)
    pos, rot = so3.pose_error(CHAIN.fk(q), target)
    pos, rot = pos.norm(dim=-1), rot.norm(dim=-1)
    out = {f"success {k}": float(((pos <= p) & (rot <= r)).double().mean()) for k, (p, r) in TOLERANCES.items()}
    out["within limits"] = float(CHAIN.within_limits(q, tol=1e-9).double().mean())
    return out


class Clock:
    """Wall and CPU (process) seconds of one call. The machine is shared: CPU time is what the
    solver itself used, wall time also holds the waits for the cores."""

    def __init__(self) -> None:
        self.wall, self.cpu = time.perf_counter(), time.process_time()

    def stop(self) -> tuple[float, float]:
        return time.perf_counter() - self.wall, time.process_time() - self.cpu


def ours(target: torch.Tensor, repeats: int, samples: list | None = None, **options) -> dict:
    """Median over ``repeats`` timed calls (after one warm-up), plus any earlier ``samples``
    of the same configuration, which this list collects."""
    result = solve(CHAIN, target, **options)
    samples = [] if samples is None else samples
    for _ in range(repeats):
        clock = Clock()
        result = solve(CHAIN, target, **options)
        samples.append(clock.stop())
    wall, cpu = statistics.median(s[0] for s in samples), statistics.median(s[1] for s in samples)
    row = {"seconds": wall, "cpu seconds": cpu, "per target ms": wall / len(target) * 1e3}
    row["per target cpu ms"] = cpu / len(target) * 1e3
    row["timed runs"] = len(samples)
    row |= score(result.q, target.to(torch.float64))
    row["mean iterations"] = float(result.iterations.double().mean())
    return row


def world_problems(count: int, seed: int) -> tuple[torch.Tensor, World]:
    """Poses of ``count`` random configurations clear of themselves and the floor by MARGIN + 2 cm,
    and per pose 3 spheres (radius 4-10 cm), each beside a random point on a random capsule's
    axis, clear of the whole arm (and the floor) by MARGIN + 1-6 cm: ``(targets, world)``."""
    g = torch.Generator().manual_seed(seed)
    caps = robot_capsules(CHAIN)
    q = CHAIN.random_q(3 * count, generator=g)
    q = q[clearance(CHAIN, q, capsules=caps) >= MARGIN + 0.02][:count]
    frames = CHAIN.fk_all(q)[:, list(caps.frames)]  # (b, K, 4, 4)
    ends = torch.einsum("bkij,kej->bkei", frames[..., :3, :3], caps.points) + frames[:, :, None, :3, 3]
    centres, radii = torch.zeros(count, 3, 3, dtype=torch.float64), torch.zeros(count, 3, dtype=torch.float64)
    for sphere in range(3):
        todo = torch.arange(count)
        while todo.numel():  # rejection: redraw the spheres that touch the arm or the floor
            m = todo.numel()
            k = torch.randint(0, len(caps.names), (m,), generator=g)
            e = ends[todo, k]
            point = e[:, 0] + torch.rand(m, 1, generator=g, dtype=torch.float64) * (e[:, 1] - e[:, 0])
            r = 0.04 + 0.06 * torch.rand(m, generator=g, dtype=torch.float64)
            gap = MARGIN + 0.01 + 0.05 * torch.rand(m, generator=g, dtype=torch.float64)
            u = torch.randn(m, 3, generator=g, dtype=torch.float64)
            c = point + u / u.norm(dim=-1, keepdim=True) * (caps.radii[k] + r + gap)[:, None]
            ok = clearance(CHAIN, q[todo], World(spheres=(c[:, None], r[:, None])), caps) >= MARGIN + 0.01
            ok &= c[:, 2] - r >= MARGIN + 0.01
            centres[todo[ok], sphere], radii[todo[ok], sphere] = c[ok], r[ok]
            todo = todo[~ok]
    return CHAIN.fk(q), World(floor=0.0, spheres=(centres, radii))


def world_score(q: torch.Tensor, target: torch.Tensor, world: World) -> dict:
    """Success at 0.1 mm / 1 mrad (our FK) with a clearance >= MARGIN (``collision.clearance``)."""
    pos, rot = so3.pose_error(CHAIN.fk(q), target)
    clear = clearance(CHAIN, q, world) >= MARGIN
    reached = (pos.norm(dim=-1) <= 1e-4) & (rot.norm(dim=-1) <= 1e-3)
    return {
        "success 0.1mm/1mrad, clear": float((reached & clear).double().mean()),
        "clear": float(clear.double().mean()),
    }


def timing_row(seconds: tuple[float, float], count: int) -> dict:
    wall, cpu = seconds
    return {
        "seconds": wall,
        "cpu seconds": cpu,
        "per target ms": wall / count * 1e3,
        "per target cpu ms": cpu / count * 1e3,
    }


def pytorch_kinematics(target: torch.Tensor, variant: str) -> dict | None:
    try:
        import pytorch_kinematics as pk
    except ImportError:
        return None
    serial = pk.build_serial_chain_from_urdf(to_urdf(CHAIN).encode(), "tool0").to(dtype=torch.float32)
    q_check = CHAIN.random_q(64, generator=torch.Generator().manual_seed(1))
    agree = (serial.forward_kinematics(q_check.float()).get_matrix().double() - CHAIN.fk(q_check)).abs().max()
    solver_cls = getattr(pk, variant)
    solver = solver_cls(
        serial,
        max_iterations=50,
        num_retries=10,
        joint_limits=CHAIN.limits.T.float(),
        early_stopping_any_converged=True,
        early_stopping_no_improvement="all",
        regularlization=1e-6,
        pos_tolerance=1e-4,
        rot_tolerance=1e-3,
        debug=False,
    )
    goal = pk.Transform3d(matrix=target.float())
    torch.manual_seed(0)  # pk samples its retry configurations from torch's global generator
    clock = Clock()
    try:
        sol = solver.solve(goal)
    except RuntimeError as err:  # e.g. a singular matrix in torch.linalg.solve
        return {"error": str(err)[:200], "fk max diff vs ours": float(agree)}
    seconds = clock.stop()
    # best retry per target, by its own error
    err = sol.err_pos.double() + sol.err_rot.double()  # (M, retries)
    best = err.argmin(1)
    q = sol.solutions[torch.arange(len(target)), best]
    return timing_row(seconds, len(target)) | {"fk max diff vs ours": float(agree)} | score(q, target)


def roboticstoolbox(target: torch.Tensor, tol: float | None) -> dict | None:
    try:
        import roboticstoolbox as rtb
    except ImportError:
        return None
    links = [
        rtb.RevoluteDH(a=a, alpha=al, d=d, offset=o, qlim=[lo, hi])
        for (a, al, d, o), lo, hi in zip(CHAIN.dh.tolist(), *CHAIN.limits.tolist())
    ]
    ets = rtb.DHRobot(links, tool=CHAIN.tool.numpy()).ets()
    q_check = CHAIN.random_q(64, generator=torch.Generator().manual_seed(1))
    agree = max(float(np.abs(ets.eval(x) - y).max()) for x, y in zip(q_check.numpy(), CHAIN.fk(q_check).numpy()))
    goals = list(target.numpy())
    options = {} if tol is None else {"tol": tol}
    np.random.seed(0)  # ik_LM draws its restarts from numpy's global generator
    clock = Clock()
    solutions = [ets.ik_LM(g, **options) for g in goals]
    seconds = clock.stop()
    q = torch.tensor(np.stack([s[0] for s in solutions]))
    return timing_row(seconds, len(target)) | {"fk max diff vs ours": agree} | score(q, target)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1,000 targets, fewer repeats (a smoke run)")
    args = parser.parse_args()
    count, repeats = (1_000, 2) if args.quick else (10_000, 5)
    q_true = CHAIN.random_q(count, generator=torch.Generator().manual_seed(2024))
    target = CHAIN.fk(q_true)
    rows: dict[str, dict] = {}

    def report(name: str, row: dict | None) -> None:
        if row is None:
            print(f"{name}: not installed, skipped", flush=True)
            return
        rows[name] = row
        shown = {k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in row.items()}
        print(f"{name}: {shown}", flush=True)

    # Ours is timed before and after the peers (the medians pool both), as the load on a
    # shared machine drifts over the minutes the peers take.
    # float64 runs twice: precision="auto" (iterations in float32, answer checked in float64)
    # and precision="input" (float64 iterations).
    kinds = [(torch.float32, "auto"), (torch.float64, "auto"), (torch.float64, "input")]
    configs = [(threads, dtype, precision) for threads in (1, 2) for dtype, precision in kinds]
    samples = {config: [] for config in configs}
    for threads, dtype, precision in configs:
        torch.set_num_threads(threads)
        ours(target.to(dtype), (repeats + 1) // 2, samples[threads, dtype, precision], precision=precision)
    torch.set_num_threads(1)
    for variant in ("PseudoInverseIK", "PseudoInverseIKWithSVD"):
        report(f"pytorch_kinematics {variant}, float32, 1 thread", pytorch_kinematics(target, variant))
    for tol in (None, 1e-7, 1e-10):
        report(
            f"roboticstoolbox ik_LM (C++), {'defaults' if tol is None else f'tol={tol:g}'}",
            roboticstoolbox(target, tol),
        )
    for threads, dtype, precision in configs:
        torch.set_num_threads(threads)
        row = ours(target.to(dtype), (repeats + 1) // 2, samples[threads, dtype, precision], precision=precision)
        iterated = "float32 iterations" if precision == "auto" and dtype == torch.float64 else "same-dtype iterations"
        label = f"{str(dtype)[6:]} ({iterated})" if dtype == torch.float64 else "float32"
        report(f"iiwa-torch solve, {label}, {threads} thread{'s' if threads > 1 else ''}", row)
    torch.set_num_threads(1)

    # Success/time trade-off of ours (float32, 1 thread) as seeds and iterations vary.
    tradeoff = []
    for seeds in (1, 2, 4, 8):
        for iterations in (8, 12, 16, 24):
            row = ours(target.float(), max(1, repeats // 2), seeds=seeds, iterations=iterations)
            tradeoff.append({"seeds": seeds, "iterations per seed": iterations} | row)
            print(f"trade-off seeds={seeds} iterations={iterations}: {row}", flush=True)

    # With a world (float64 targets, float32 iterations, 1 thread); the solve without the world on
    # the same targets shows how often a plain answer collides.
    world_target, world = world_problems(count, 7)
    world_rows = {}
    for name, options in (("with world, margin 1 cm", {"world": world, "margin": MARGIN}),
                          ("without world (answers checked against it)", {})):  # fmt: skip
        row = ours(world_target, repeats, **options)
        world_rows[name] = row | world_score(solve(CHAIN, world_target, **options).q, world_target, world)
    for name, row in world_rows.items():
        print(f"world: {name}: {row}", flush=True)

    best_ours = min(
        (r for k, r in rows.items() if k.startswith("iiwa-torch") and k.endswith("1 thread")),
        key=lambda r: r["seconds"],
    )
    headers = ["solver", "per target, wall (ms)", "per target, CPU (ms)", "success 0.1 mm / 1 mrad",
               "success 1 mm / 10 mrad", "within limits", "wall vs ours", "CPU vs ours"]  # fmt: skip
    table = []
    for name, row in sorted(rows.items(), key=lambda item: not item[0].startswith("iiwa-torch")):
        if "error" in row:
            table.append([name, "crashed: " + row["error"][:60], "", "", "", "", "", ""])
            continue
        table.append([
            name, f"{row['per target ms']:.4f}", f"{row['per target cpu ms']:.4f}",
            f"{100 * row['success 0.1mm/1mrad']:.2f}%", f"{100 * row['success 1mm/10mrad']:.2f}%",
            f"{100 * row['within limits']:.2f}%", f"{row['seconds'] / best_ours['seconds']:.1f}x",
            f"{row['cpu seconds'] / best_ours['cpu seconds']:.1f}x",
        ])  # fmt: skip
    trade_table = [
        [
            r["seeds"],
            r["iterations per seed"],
            f"{r['per target ms']:.4f}",
            f"{r['per target cpu ms']:.4f}",
            f"{100 * r['success 0.1mm/1mrad']:.2f}%",
        ]
        for r in tradeoff
    ]
    info = machine_info()
    command = "python benchmarks/bench_ik.py" + (" --quick" if args.quick else "")
    markdown = (
        f"IK on {count:,} random reachable iiwa 14 poses (`{command}`). Ours: median of {2 * ((repeats + 1) // 2)} "
        "runs taken before and after the peers; peers: one run. CPU = process time (with 2 threads, both "
        "threads' time). Ratios against our fastest 1-thread row.\n\n"
        + markdown_table(headers, table)
        + "\nOurs, float32, 1 thread, as seeds and iterations per seed vary:\n\n"
        + markdown_table(
            [
                "seeds",
                "iterations per seed",
                "per target, wall (ms)",
                "per target, CPU (ms)",
                "success 0.1 mm / 1 mrad",
            ],
            trade_table,
        )
        + f"\nOurs with a world: {count:,} poses of random collision-free configurations, each with the floor "
        "and 3 random spheres near the arm (clear of that configuration), margin 1 cm; float64 targets, "
        "float32 iterations, 1 thread; success needs 0.1 mm / 1 mrad by our FK and clearance >= margin by "
        "`collision.clearance`:\n\n"
        + markdown_table(
            [
                "solve",
                "per target, wall (ms)",
                "per target, CPU (ms)",
                "success 0.1 mm / 1 mrad, clear",
                "clearance >= margin",
                "mean iterations",
            ],
            [
                [
                    name,
                    f"{r['per target ms']:.4f}",
                    f"{r['per target cpu ms']:.4f}",
                    f"{100 * r['success 0.1mm/1mrad, clear']:.2f}%",
                    f"{100 * r['clear']:.2f}%",
                    f"{r['mean iterations']:.1f}",
                ]
                for name, r in world_rows.items()
            ],
        )  # fmt: skip
        + f"\nMachine: {info}\n"
    )
    name = "ik_quick" if args.quick else "ik"
    path = save(name, {"machine": info, "targets": count, "command": command, "solvers": rows, "tradeoff": tradeoff,
                 "world": world_rows},
                markdown)  # fmt: skip
    print(markdown)
    print(f"wrote {path}", file=sys.stderr)


if __name__ == "__main__":
    main()
