"""IK on 10,000 random reachable poses: iiwa-torch against its peers, one run.

    python benchmarks/bench_ik.py [--quick] [--robot NAME] [--threads 1 2]

The arm: ``--robot`` takes a preset's name (default iiwa14) or ``panda``, ``xarm6``,
``kuka_iiwa`` (pybullet_data's URDF files, read by ``robots.from_urdf``). The tolerance: a
preset's targets are solved at 0.1 mm / 1 mrad (``solve``'s default), a URDF arm's at
TRAC-IK's 1e-5 m / 1e-5 rad.

Solvers, all on the same targets (FK of seeded random configurations within the limits):
- ours: ``iiwa_torch.ik.solve`` (batched LM), float32, float64 (``precision="auto"``: float32
  iterations, float64 check; and ``"input"``: float64 iterations), 1 and 2 threads, at the
  default 32 seeds;
- pytorch_kinematics ``PseudoInverseIK`` (batched torch, float32; the settings the issue
  measured: 10 retries, 50 iterations, ``early_stopping_any_converged``, regularisation 1e-6)
  and its ``PseudoInverseIKWithSVD`` variant, on the same URDF (a preset's ``to_urdf`` export);
- roboticstoolbox ``ETS.ik_LM`` (C++, one call per target, ``joint_limits=True``) on the same
  arm and limits (a preset's DH table; a URDF arm's file read by roboticstoolbox): a preset's
  at its defaults, tol 1e-7 and tol 1e-10; a URDF arm's at the tolerance that implies ours
  (its residual ``E = |e|^2 / 2``, so tol = 1e-5^2 / 2) with 8, 32 and 100 (its default) searches.

Every answer is scored by the same code: our ``chain.fk`` and ``so3.pose_error`` (after a
check that each peer's FK agrees with ours), success at the solve's tolerance and at 10 times
it, and the share of answers within the joint limits. Then the success/time trade-off
of ours as seeds and iterations vary, and, for a preset, ours with a world: random
collision-free configurations' poses, each with the floor and 3 random spheres near the arm
(clear of that configuration), ``solve(..., world=, margin=0.01)`` scored by FK and
``collision.clearance``. Writes results/ik.json and results/ik.md (``ik_<robot>.*`` for another arm).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch is imported

import numpy as np  # noqa: E402
import torch  # noqa: E402
from common import Clock, Robot, command, machine, markdown_table, save  # noqa: E402

from iiwa_torch import so3  # noqa: E402
from iiwa_torch.collision import World, clearance, robot_capsules  # noqa: E402
from iiwa_torch.ik import solve  # noqa: E402

MARGIN = 0.01  # clearance required with a world, m
ROBOT = CHAIN = None  # set by setup(--robot)
# Success tolerances (m, rad), named: the solve's first (a preset's, else TRAC-IK's), then 10 times it.
TOLERANCES: dict[str, tuple[float, float]] = {}
SOLVE_TOL = {"pos_tol": 1e-4, "rot_tol": 1e-3}


def setup(name: str) -> None:
    """The arm of this run and its tolerances."""
    global ROBOT, CHAIN
    ROBOT = Robot(name)
    CHAIN = ROBOT.chain
    pos, rot = (1e-4, 1e-3) if ROBOT.path is None else (1e-5, 1e-5)
    SOLVE_TOL.update(pos_tol=pos, rot_tol=rot)
    TOLERANCES.clear()
    for p, r in ((pos, rot), (10 * pos, 10 * rot)):
        TOLERANCES[f"{p * 1e3:g}mm/{r * 1e3:g}mrad"] = (p, r)


def score(q: torch.Tensor, target: torch.Tensor) -> dict:
    """One FK for every solver: success at both tolerances and the share within limits."""
    q = q.to(torch.float64)
    pos, rot = so3.pose_error(CHAIN.fk(q), target)
    pos, rot = pos.norm(dim=-1), rot.norm(dim=-1)
    out = {f"success {k}": float(((pos <= p) & (rot <= r)).double().mean()) for k, (p, r) in TOLERANCES.items()}
    out["within limits"] = float(CHAIN.within_limits(q, tol=1e-9).double().mean())
    return out


def ours(target: torch.Tensor, repeats: int, samples: list | None = None, **options) -> dict:
    """Median over ``repeats`` timed calls (after one warm-up), plus any earlier ``samples``
    of the same configuration, which this list collects."""
    options = SOLVE_TOL | options
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
    serial = pk.build_serial_chain_from_urdf(ROBOT.urdf.encode(), ROBOT.end_link).to(dtype=torch.float32)
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
        pos_tolerance=SOLVE_TOL["pos_tol"],
        rot_tolerance=SOLVE_TOL["rot_tol"],
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


def roboticstoolbox(target: torch.Tensor, options: dict) -> dict | None:
    """``ETS.ik_LM(goal, joint_limits=True, **options)`` per target."""
    try:
        import roboticstoolbox  # noqa: F401
    except ImportError:
        return None
    ets = ROBOT.rtb_ets()
    q_check = CHAIN.random_q(64, generator=torch.Generator().manual_seed(1))
    agree = max(float(np.abs(ets.eval(x) - y).max()) for x, y in zip(q_check.numpy(), CHAIN.fk(q_check).numpy()))
    goals = list(target.numpy())
    np.random.seed(0)  # ik_LM draws its restarts from numpy's global generator
    clock = Clock()
    solutions = [ets.ik_LM(g, joint_limits=True, **options) for g in goals]
    seconds = clock.stop()
    q = torch.tensor(np.stack([s[0] for s in solutions]))
    return timing_row(seconds, len(target)) | {"fk max diff vs ours": agree} | score(q, target)


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1,000 targets, fewer repeats (a smoke run)")
    parser.add_argument("--robot", default="iiwa14", help="a preset's name, or panda, xarm6, kuka_iiwa (URDF)")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="thread counts (default 1 2)")
    return parser.parse_args()


def report(rows: dict[str, dict], name: str, row: dict | None) -> None:
    """Print a solver's row and keep it in ``rows`` (a peer that is not installed: ``row`` None)."""
    if row is None:
        print(f"{name}: not installed, skipped", flush=True)
        return
    rows[name] = row
    shown = {k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in row.items()}
    print(f"{name}: {shown}", flush=True)


def peer_rows(target: torch.Tensor, rows: dict[str, dict]) -> None:
    """pytorch_kinematics' two solvers and roboticstoolbox's ik_LM at each of its settings, into ``rows``."""
    for variant in ("PseudoInverseIK", "PseudoInverseIKWithSVD"):
        report(rows, f"pytorch_kinematics {variant}, float32, 1 thread", pytorch_kinematics(target, variant))
    if ROBOT.path is None:
        rtb_options = [{}, {"tol": 1e-7}, {"tol": 1e-10}]
    else:  # ik_LM's residual is |e|^2 / 2: this tol means |e| <= the smaller of ours
        tol = min(SOLVE_TOL.values()) ** 2 / 2
        rtb_options = [{"tol": tol, "slimit": slimit} for slimit in (8, 32, 100)]
    for options in rtb_options:
        shown = ", ".join(f"{k}={v:g}" for k, v in options.items()) or "defaults"
        report(rows, f"roboticstoolbox ik_LM (C++), {shown}", roboticstoolbox(target, options))


def solver_rows(target: torch.Tensor, repeats: int, threads: list[int]) -> dict[str, dict]:
    """Every solver on ``target``: ours is timed before and after the peers (the medians pool both),
    as the load on a shared machine drifts over the minutes the peers take."""
    # float64 runs twice: precision="auto" (iterations in float32, answer checked in float64)
    # and precision="input" (float64 iterations).
    # A URDF arm's float64 "auto" rows iterate in float32 too: TRAC-IK's 1e-5 is solve's threshold.
    kinds = [(torch.float32, "auto"), (torch.float64, "auto"), (torch.float64, "input")]
    configs = [(n, dtype, precision) for n in threads for dtype, precision in kinds]
    samples = {config: [] for config in configs}
    for n, dtype, precision in configs:
        torch.set_num_threads(n)
        ours(target.to(dtype), (repeats + 1) // 2, samples[n, dtype, precision], precision=precision)
    torch.set_num_threads(1)
    rows: dict[str, dict] = {}
    peer_rows(target, rows)
    for n, dtype, precision in configs:
        torch.set_num_threads(n)
        row = ours(target.to(dtype), (repeats + 1) // 2, samples[n, dtype, precision], precision=precision)
        iterated = "float32 iterations" if precision == "auto" and dtype == torch.float64 else "same-dtype iterations"
        label = f"{str(dtype)[6:]} ({iterated})" if dtype == torch.float64 else "float32"
        report(rows, f"iiwa-torch solve, {label}, {n} thread{'s' if n > 1 else ''}", row)
    torch.set_num_threads(1)
    return rows


def tradeoff_rows(target: torch.Tensor, repeats: int) -> list[dict]:
    """Success/time trade-off of ours (float32, 1 thread) as seeds and iterations vary."""
    tradeoff = []
    for seeds in (1, 2, 4, 8) if ROBOT.path is None else (8, 16, 32, 64):
        for iterations in (8, 12, 16, 24):
            row = ours(target.float(), max(1, repeats // 2), seeds=seeds, iterations=iterations)
            tradeoff.append({"seeds": seeds, "iterations per seed": iterations} | row)
            print(f"trade-off seeds={seeds} iterations={iterations}: {row}", flush=True)
    return tradeoff


def world_rows(count: int, repeats: int) -> dict[str, dict]:
    """Ours with a world (float64 targets, float32 iterations, 1 thread); the solve without the world on
    the same targets shows how often a plain answer collides. (A URDF arm has no preset capsule model: none.)"""
    rows = {}
    if ROBOT.path is None:
        world_target, world = world_problems(count, 7)
        for name, options in (("with world, margin 1 cm", {"world": world, "margin": MARGIN}),
                              ("without world (answers checked against it)", {})):  # fmt: skip
            row = ours(world_target, repeats, **options)
            rows[name] = row | world_score(solve(CHAIN, world_target, **options).q, world_target, world)
    for name, row in rows.items():
        print(f"world: {name}: {row}", flush=True)
    return rows


def solver_table(rows: dict[str, dict]) -> str:
    """Every solver's times, successes and ratios against our fastest 1-thread row, ours first."""
    best_ours = min(
        (r for k, r in rows.items() if k.startswith("iiwa-torch") and k.endswith("1 thread")),
        key=lambda r: r["seconds"],
    )
    tight, loose = TOLERANCES
    headers = ["solver", "per target, wall (ms)", "per target, CPU (ms)", f"success {tight}",
               f"success {loose}", "within limits", "wall vs ours", "CPU vs ours"]  # fmt: skip
    table = []
    for name, row in sorted(rows.items(), key=lambda item: not item[0].startswith("iiwa-torch")):
        if "error" in row:
            table.append([name, "crashed: " + row["error"][:60], "", "", "", "", "", ""])
            continue
        table.append([
            name, f"{row['per target ms']:.4f}", f"{row['per target cpu ms']:.4f}",
            f"{100 * row[f'success {tight}']:.2f}%", f"{100 * row[f'success {loose}']:.2f}%",
            f"{100 * row['within limits']:.2f}%", f"{row['seconds'] / best_ours['seconds']:.1f}x",
            f"{row['cpu seconds'] / best_ours['cpu seconds']:.1f}x",
        ])  # fmt: skip
    return markdown_table(headers, table)


def tradeoff_table(tradeoff: list[dict]) -> str:
    tight = next(iter(TOLERANCES))
    headers = ["seeds", "iterations per seed", "per target, wall (ms)", "per target, CPU (ms)", f"success {tight}"]
    return markdown_table(headers, [
        [r["seeds"], r["iterations per seed"], f"{r['per target ms']:.4f}", f"{r['per target cpu ms']:.4f}",
         f"{100 * r[f'success {tight}']:.2f}%"]
        for r in tradeoff
    ])  # fmt: skip


def world_table(count: int, rows: dict[str, dict]) -> str:
    headers = ["solve", "per target, wall (ms)", "per target, CPU (ms)", "success 0.1 mm / 1 mrad, clear",
               "clearance >= margin", "mean iterations"]  # fmt: skip
    return (
        f"\nOurs with a world: {count:,} poses of random collision-free configurations, each with the floor "
        "and 3 random spheres near the arm (clear of that configuration), margin 1 cm; float64 targets, "
        "float32 iterations, 1 thread; success needs 0.1 mm / 1 mrad by our FK and clearance >= margin by "
        "`collision.clearance`:\n\n"
        + markdown_table(headers, [
            [name, f"{r['per target ms']:.4f}", f"{r['per target cpu ms']:.4f}",
             f"{100 * r['success 0.1mm/1mrad, clear']:.2f}%", f"{100 * r['clear']:.2f}%",
             f"{r['mean iterations']:.1f}"]
            for name, r in rows.items()
        ])
    )  # fmt: skip


def main() -> None:
    args = parse_args()
    setup(args.robot)
    count, repeats = (1_000, 2) if args.quick else (10_000, 5)
    target = CHAIN.fk(CHAIN.random_q(count, generator=torch.Generator().manual_seed(2024)))
    rows = solver_rows(target, repeats, args.threads)
    tradeoff = tradeoff_rows(target, repeats)
    world = world_rows(count, repeats)
    info, run = machine(), command(__file__)
    tight = next(iter(TOLERANCES))
    source = "the DH preset"
    if ROBOT.path is not None:
        source = f"`{ROBOT.path.parent.name}/{ROBOT.path.name}`, end link `{ROBOT.end_link}`"
    markdown = (
        f"IK on {count:,} random reachable {ROBOT.name} poses ({source}; `{run}`), solved at {tight} "
        f"(m and rad: {SOLVE_TOL['pos_tol']:g} / {SOLVE_TOL['rot_tol']:g}). Ours: median of "
        f"{2 * ((repeats + 1) // 2)} runs taken before and after the peers; peers: one run. CPU = process time "
        "(with 2 threads, both threads' time). Ratios against our fastest 1-thread row.\n\n"
        + solver_table(rows)
        + "\nOurs, float32, 1 thread, as seeds and iterations per seed vary:\n\n"
        + tradeoff_table(tradeoff)
        + (world_table(count, world) if world else "")
        + f"\nMachine: {info}\n"
    )
    name = "ik" if args.robot == "iiwa14" else f"ik_{args.robot}"
    name += "_quick" if args.quick else ""
    payload = {"robot": args.robot, "tolerance": SOLVE_TOL, "machine": info, "targets": count, "command": run,
               "solvers": rows, "tradeoff": tradeoff, "world": world}  # fmt: skip
    path = save(name, payload, markdown)
    print(markdown)
    print(f"wrote {path}", file=sys.stderr)


if __name__ == "__main__":
    main()
