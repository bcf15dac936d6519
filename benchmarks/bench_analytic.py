"""Closed-form IK, every branch of 100,000 poses: iiwa-torch against the gradient solver
and roboticstoolbox, one run.

    python benchmarks/bench_analytic.py [--quick]

Measured, float32 and float64, on 100,000 poses from random joint angles within the limits:
``planar3r`` (2 branches), ``pieper`` on the PUMA 560 and the LR Mate 200iC (8 branches),
``iiwa_q3_locked`` (8) and ``iiwa`` with K = 4 arm angles per pose (32). Every reachable
branch is then checked by FK closure (outside the timing). Peers, per pose, in the same run:
roboticstoolbox's analytic ``Puma560.ikine_a`` (one call per branch) and its C++
``ikine_LM`` on the iiwa, and our gradient solver ``iiwa_torch.ik.solve``. Last, the
arm-angle sweep ``iiwa_solve`` on 100,000 reachable poses: its success rate, and for every
miss, whether a 4096-angle sweep or the gradient solver with 64 seeds finds a solution.
And ``iiwa_solve`` in a world (the floor and 3 random spheres near the arm, per pose) on
poses of collision-free configurations: success and ms per pose, every answer checked by
FK and clearance. Writes results/analytic.json and results/analytic.md (``_quick`` with ``--quick``).
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import time

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch is imported

import torch  # noqa: E402
from common import Robot, markdown_table, save, timeit  # noqa: E402

from iiwa_torch import robots  # noqa: E402
from iiwa_torch.collision import World, clearance, robot_capsules  # noqa: E402
from iiwa_torch.ik import analytic, solve  # noqa: E402
from iiwa_torch.runtime import machine_info  # noqa: E402
from iiwa_torch.so3 import pose_error  # noqa: E402

K_PSI = 4  # arm angles per pose for the iiwa
MARGIN = 0.01  # clearance (m) required of the answers in a world, and exceeded by each target configuration
CHUNK = 25_000  # poses per call for the iiwa with K arm angles (bounded memory)


def closure(chain, q, target, reachable) -> tuple[float, float, int]:
    """Max position (m) and rotation (rad) error of the reachable branches, and their count."""
    pos_max, rot_max, count = 0.0, 0.0, 0
    flat_q, flat_ok = q.reshape(q.shape[0], -1, q.shape[-1]), reachable.reshape(q.shape[0], -1)
    for i in range(0, q.shape[0], 10_000):
        qs, ok = flat_q[i : i + 10_000], flat_ok[i : i + 10_000]
        pos, rot = pose_error(chain.fk(qs), target[i : i + 10_000, None].expand(*qs.shape[:-1], 4, 4))
        pos, rot = pos.norm(dim=-1)[ok], rot.norm(dim=-1)[ok]
        if pos.numel():
            pos_max, rot_max = max(pos_max, pos.max().item()), max(rot_max, rot.max().item())
        count += int(ok.sum())
    return pos_max, rot_max, count


def cases(n: int, dtype: torch.dtype):
    """(name, chain, targets, solve) for each closed form; ``solve(target)`` -> AnalyticSolutions."""
    gen = torch.Generator().manual_seed(0)
    out = []

    def targets(chain):
        return chain.fk(chain.random_q(n, generator=gen)).to(dtype)

    planar = robots.planar3r().to(dtype)
    t = targets(robots.planar3r())
    out.append(
        (
            "planar3r",
            planar,
            t,
            lambda x: analytic.planar3r(planar, x[:, 0, 3], x[:, 1, 3], torch.atan2(x[:, 1, 0], x[:, 0, 0])),
        )
    )
    for make in (robots.puma560, robots.lrmate200ic):
        chain = make().to(dtype)
        out.append((f"pieper {chain.name}", chain, targets(make()), lambda x, c=chain: analytic.pieper(c, x)))
    iiwa = robots.iiwa14().to(dtype)
    t = targets(robots.iiwa14())
    out.append(("iiwa_q3_locked", iiwa, t, lambda x: analytic.iiwa_q3_locked(iiwa, x)))
    psi = torch.linspace(-math.pi, math.pi, K_PSI + 1, dtype=dtype)[:-1][None]

    def arm_angles(x):  # K arm angles per pose, in chunks of poses
        parts = [analytic.iiwa(iiwa, x[i : i + CHUNK], psi) for i in range(0, x.shape[0], CHUNK)]
        fields = ("q", "valid", "reachable", "within_limits")
        return analytic.AnalyticSolutions(*(torch.cat([getattr(p, f) for p in parts]) for f in fields))

    out.append((f"iiwa, K={K_PSI} arm angles", iiwa, t, arm_angles))
    return out


def runs(fn, repeats: int) -> list[float]:
    """Seconds of ``repeats`` calls of ``fn`` (after one warm-up call)."""
    fn()
    out = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        out.append(time.perf_counter() - start)
    return out


def bench_closed_forms(n: int, repeats: int) -> list[dict]:
    """Each closed form on ``n`` poses: median and best of ``repeats`` calls (the machine is
    shared: the best is what the code does when it gets the cores), on all torch threads
    and on one, then FK closure."""
    rows = []
    threads = torch.get_num_threads()
    for dtype in (torch.float32, torch.float64):
        for name, chain, target, fn in cases(n, dtype):
            times = runs(lambda fn=fn, target=target: fn(target), repeats)
            seconds, best = statistics.median(times), min(times)
            torch.set_num_threads(1)
            best_1 = min(runs(lambda fn=fn, target=target: fn(target), repeats))
            torch.set_num_threads(threads)
            sol = fn(target)
            branches = sol.reachable.numel()
            pos, rot, count = closure(chain, sol.q, target, sol.reachable)
            rows.append(
                {
                    "solver": name,
                    "dtype": str(dtype).replace("torch.", ""),
                    "poses": n,
                    "branches": branches,
                    "seconds": seconds,
                    "seconds_best": best,
                    "branches_per_s": branches / seconds,
                    "branches_per_s_best": branches / best,
                    "branches_per_s_best_1_thread": branches / best_1,
                    "reachable_fraction": count / branches,
                    "valid_fraction": sol.valid.float().mean().item(),
                    "closure_max_pos_m": pos,
                    "closure_max_rot_rad": rot,
                }
            )
            print(
                f"{name:<26}{rows[-1]['dtype']:<9}{branches:>10,} branches {seconds:8.3f} s "
                f"{branches / seconds / 1e6:6.2f} M/s (best {branches / best / 1e6:5.2f})  "
                f"closure {pos:.1e} m {rot:.1e} rad"
            )
    return rows


def bench_peers(n_rtb: int, n_grad: int) -> dict:
    """Per-pose peers: roboticstoolbox (analytic PUMA, numerical iiwa) and our gradient solver."""
    import roboticstoolbox as rtb
    from spatialmath import SE3

    gen = torch.Generator().manual_seed(1)
    result = {}
    # PUMA 560: rtb's analytic solution, one call per branch (8 configurations per pose).
    puma_rtb = rtb.models.DH.Puma560()
    table = torch.tensor([[link.a, link.alpha, link.d, link.offset] for link in puma_rtb.links], dtype=torch.float64)
    puma = robots.puma560()
    puma = type(puma)(table, limits=puma.limits, name="puma560-rtb")
    target = puma.fk(puma.random_q(n_rtb, generator=gen))
    configs = ("lun", "luf", "ldn", "ldf", "run", "ruf", "rdn", "rdf")
    poses = [SE3(t.numpy(), check=False) for t in target]
    start = time.perf_counter()
    for pose in poses:
        for config in configs:
            puma_rtb.ikine_a(pose, config=config)
    seconds = time.perf_counter() - start
    result["rtb_puma_ikine_a_branches_per_s"] = n_rtb * len(configs) / seconds
    ours = timeit(lambda: analytic.pieper(puma, target), min_time=0.2, repeats=3)
    result["ours_puma_same_poses_branches_per_s"] = n_rtb * 8 / ours

    # iiwa: rtb's C++ Levenberg-Marquardt (ETS), one pose at a time.
    iiwa = robots.iiwa14()
    ets = Robot("iiwa14").rtb_ets()
    target = iiwa.fk(iiwa.random_q(n_rtb, generator=gen))
    start, ok = time.perf_counter(), 0
    for t in target.numpy():
        sol = ets.ikine_LM(t, seed=0)
        ok += bool(sol.success)
    seconds = time.perf_counter() - start
    result["rtb_iiwa_ikine_LM_poses_per_s"] = n_rtb / seconds
    result["rtb_iiwa_ikine_LM_success"] = ok / n_rtb

    # Our gradient solver and the arm-angle sweep, batched, the same poses.
    target = iiwa.fk(iiwa.random_q(n_grad, generator=gen))
    start = time.perf_counter()
    grad = solve(iiwa, target)
    seconds = time.perf_counter() - start
    result["gradient_iiwa_poses_per_s"] = n_grad / seconds
    result["gradient_iiwa_success"] = grad.success.float().mean().item()
    start = time.perf_counter()
    sweep = analytic.iiwa_solve(iiwa, target)
    seconds = time.perf_counter() - start
    result["sweep_iiwa_poses_per_s"] = n_grad / seconds
    result["sweep_iiwa_success"] = sweep.success.float().mean().item()
    result["gradient_misses"] = int((~grad.success).sum())
    result["gradient_misses_solved_by_sweep"] = int((~grad.success & sweep.success).sum())
    result["poses"] = {"rtb": n_rtb, "batched": n_grad}
    for key, value in result.items():
        print(f"{key:<40}{value}")
    return result


def sweep_success(n: int) -> dict:
    """``iiwa_solve`` on ``n`` reachable poses; every miss re-tried with a dense sweep and
    with the gradient solver given 64 seeds (is the miss real?). Also: the poses where a
    plain grid of 16 arm angles has no in-limit branch (narrow feasible arm-angle
    intervals, which ``iiwa_solve`` retries with a finer grid), and how both solvers fare there."""
    iiwa = robots.iiwa14()
    q = iiwa.random_q(n, generator=torch.Generator().manual_seed(2))
    target = iiwa.fk(q)
    start = time.perf_counter()
    res = analytic.iiwa_solve(iiwa, target)
    seconds = time.perf_counter() - start
    missed = (~res.success).nonzero().squeeze(-1)
    out = {
        "poses": n,
        "seconds": seconds,
        "success": res.success.float().mean().item(),
        "missed": missed.tolist(),
        "max_pos_err_m": res.pos_err[res.success].max().item(),
        "max_rot_err_rad": res.rot_err[res.success].max().item(),
    }
    if missed.numel():
        dense = analytic.iiwa_solve(iiwa, target[missed], num_psi=4096)
        grad = solve(iiwa, target[missed], seeds=64, generator=torch.Generator().manual_seed(3))
        out["missed_dense_sweep_success"] = dense.success.tolist()
        out["missed_gradient_64_seeds_success"] = grad.success.tolist()
    grid = torch.linspace(-math.pi, math.pi, 17, dtype=torch.float64)[:-1][None]
    narrow = torch.cat(
        [~analytic.iiwa(iiwa, target[i : i + CHUNK], grid).valid.flatten(-2).any(-1) for i in range(0, n, CHUNK)]
    ).nonzero().squeeze(-1)
    out["grid16_without_valid_branch"] = narrow.numel()
    if narrow.numel():
        grad = solve(iiwa, target[narrow], generator=torch.Generator().manual_seed(4))
        out["grid16_misses_iiwa_solve_success"] = res.success[narrow].float().mean().item()
        out["grid16_misses_gradient_success"] = grad.success.float().mean().item()
    print(
        f"iiwa_solve on {n:,} poses: success {out['success']:.5f} in {seconds:.1f} s, missed {missed.numel()}; "
        f"{narrow.numel()} poses without a valid branch on a 16-angle grid"
    )
    return out


def sphere_worlds(chain, q: torch.Tensor, gen: torch.Generator, spheres: int = 3) -> tuple[World, torch.Tensor]:
    """The floor and ``spheres`` spheres near the arm for each configuration of ``q (N, 7)``:
    each centred off a random point of a random capsule, radius 0.05-0.12 m, its surface
    0.02-0.15 m from that capsule's; redrawn (up to 50 times) until the configuration clears
    the world by more than ``MARGIN``. Returns the world (batch ``(N',)``) and the kept rows."""
    caps = robot_capsules(chain)
    n, dtype = q.shape[0], q.dtype
    frames = chain.fk_all(q)[:, list(caps.frames)]  # (N, K, 4, 4)
    centres = torch.zeros(n, spheres, 3, dtype=dtype)
    radii = torch.zeros(n, spheres, dtype=dtype)
    todo = torch.ones(n, dtype=torch.bool)
    for _ in range(50):
        rows = todo.nonzero().squeeze(-1)
        if not rows.numel():
            break
        m = rows.numel()
        k = torch.randint(len(caps.names), (m, spheres), generator=gen)
        t = torch.rand(m, spheres, 1, generator=gen, dtype=dtype)
        ends = caps.points.to(dtype)[k]  # (m, S, 2, 3)
        local = ends[..., 0, :] + t * (ends[..., 1, :] - ends[..., 0, :])
        frame = frames[rows[:, None], k]  # (m, S, 4, 4)
        point = (frame[..., :3, :3] @ local[..., None])[..., 0] + frame[..., :3, 3]
        direction = torch.nn.functional.normalize(torch.randn(m, spheres, 3, generator=gen, dtype=dtype), dim=-1)
        r = 0.05 + 0.07 * torch.rand(m, spheres, generator=gen, dtype=dtype)
        gap = 0.02 + 0.13 * torch.rand(m, spheres, generator=gen, dtype=dtype)
        centres[rows] = point + direction * (caps.radii.to(dtype)[k] + r + gap)[..., None]
        radii[rows] = r
        world = World(floor=0.0, spheres=(centres[rows], radii[rows]))
        todo[rows] = clearance(chain, q[rows], world) <= MARGIN
    keep = (~todo).nonzero().squeeze(-1)
    return World(floor=0.0, spheres=(centres[keep], radii[keep])), keep


def world_sweep(n: int) -> dict:
    """``iiwa_solve`` with and without a world on ``n`` poses of collision-free configurations
    (self and floor clear by more than ``MARGIN``), each with its own 3 spheres near the arm."""
    iiwa = robots.iiwa14()
    gen = torch.Generator().manual_seed(5)
    q = iiwa.random_q(2 * n, generator=gen)
    q = q[clearance(iiwa, q) > MARGIN][:n]
    world, keep = sphere_worlds(iiwa, q, gen)
    target = iiwa.fk(q[keep])
    start = time.perf_counter()
    plain = analytic.iiwa_solve(iiwa, target)
    plain_s = time.perf_counter() - start
    start = time.perf_counter()
    res = analytic.iiwa_solve(iiwa, target, world=world, margin=MARGIN)
    world_s = time.perf_counter() - start
    pos, rot = pose_error(iiwa.fk(res.q), target)
    recomputed = clearance(iiwa, res.q, world)
    verified = (pos.norm(dim=-1) <= 1e-4) & (rot.norm(dim=-1) <= 1e-3) & (recomputed >= MARGIN)
    out = {
        "poses": int(keep.numel()),
        "margin_m": MARGIN,
        "success": res.success.float().mean().item(),
        "verified_by_fk_and_clearance": int(verified.sum()),
        "success_count": int(res.success.sum()),
        "plain_answer_collides": (clearance(iiwa, plain.q, world) < MARGIN).float().mean().item(),
        "plain_success": plain.success.float().mean().item(),
        "ms_per_pose": world_s / keep.numel() * 1e3,
        "plain_ms_per_pose": plain_s / keep.numel() * 1e3,
    }
    print(
        f"iiwa_solve, floor + 3 spheres, {out['poses']:,} poses: success {out['success']:.4f} "
        f"({out['verified_by_fk_and_clearance']} verified), {out['ms_per_pose']:.3f} ms/pose "
        f"(without the world {out['plain_ms_per_pose']:.3f}; its answers collide on {out['plain_answer_collides']:.3f})"
    )
    return out


def closed_form_table(closed: list[dict]) -> str:
    headers = [
        "solver", "dtype", "branches", "s per call (median)", "M branches/s (median)", "M branches/s (best)",
        "M branches/s (best, 1 thread)", "reachable", "valid", "closure m / rad",
    ]
    rows = [
        [
            r["solver"], r["dtype"], f"{r['branches']:,}", f"{r['seconds']:.3f}", f"{r['branches_per_s'] / 1e6:.2f}",
            f"{r['branches_per_s_best'] / 1e6:.2f}", f"{r['branches_per_s_best_1_thread'] / 1e6:.2f}",
            f"{r['reachable_fraction']:.3f}", f"{r['valid_fraction']:.3f}",
            f"{r['closure_max_pos_m']:.1e} / {r['closure_max_rot_rad']:.1e}",
        ]
        for r in closed
    ]
    return markdown_table(headers, rows)


def peer_table(peers: dict) -> str:
    ratio = [
        ["PUMA 560 branches/s: ours (batched) vs rtb ikine_a (per call)",
         f"{peers['ours_puma_same_poses_branches_per_s']:,.0f}", f"{peers['rtb_puma_ikine_a_branches_per_s']:,.0f}",
         f"**{peers['ours_puma_same_poses_branches_per_s'] / peers['rtb_puma_ikine_a_branches_per_s']:.0f}x**"],
        ["iiwa poses/s: arm-angle sweep vs gradient solver (both batched)",
         f"{peers['sweep_iiwa_poses_per_s']:,.0f}", f"{peers['gradient_iiwa_poses_per_s']:,.0f}",
         f"**{peers['sweep_iiwa_poses_per_s'] / peers['gradient_iiwa_poses_per_s']:.1f}x**"],
        ["iiwa poses/s: arm-angle sweep vs rtb ikine_LM (C++, per pose)",
         f"{peers['sweep_iiwa_poses_per_s']:,.0f}", f"{peers['rtb_iiwa_ikine_LM_poses_per_s']:,.0f}",
         f"**{peers['sweep_iiwa_poses_per_s'] / peers['rtb_iiwa_ikine_LM_poses_per_s']:.0f}x**"],
    ]
    return markdown_table(["comparison", "ours", "peer", "ratio"], ratio)


def success_text(peers: dict, sweep: dict) -> str:
    """The success rates of the sweep, the gradient solver and rtb, and where the sweep missed."""
    return (
        f"Success: sweep {peers['sweep_iiwa_success']:.4f}, gradient {peers['gradient_iiwa_success']:.4f} "
        f"({peers['gradient_misses_solved_by_sweep']} of its {peers['gradient_misses']} misses solved by the sweep), "
        f"rtb ikine_LM {peers['rtb_iiwa_ikine_LM_success']:.3f}. "
        f"iiwa_solve on {sweep['poses']:,} reachable poses: success {sweep['success']:.5f}, "
        f"{len(sweep['missed'])} missed; {sweep['grid16_without_valid_branch']} poses have no in-limit branch on a "
        f"plain 16-angle grid (narrow feasible arm-angle intervals, found by the finer retry: "
        f"success there {sweep.get('grid16_misses_iiwa_solve_success', float('nan')):.3f}, gradient solver "
        f"{sweep.get('grid16_misses_gradient_success', float('nan')):.3f}).\n\n"
    )


def world_table(obstacles: dict) -> str:
    return (
        "In a world (floor + 3 random spheres near the arm per pose, margin "
        f"{obstacles['margin_m'] * 1e3:.0f} mm, poses of collision-free configurations):\n\n"
        + markdown_table(
            ["solver", "poses", "success", "verified (FK + clearance)", "ms per pose", "without the world"],
            [
                [
                    "iiwa_solve(world=...)", f"{obstacles['poses']:,}", f"{obstacles['success']:.4f}",
                    f"{obstacles['verified_by_fk_and_clearance']:,}", f"{obstacles['ms_per_pose']:.3f}",
                    f"{obstacles['plain_ms_per_pose']:.3f} ms, "
                    f"answers colliding {obstacles['plain_answer_collides']:.3f}",
                ]
            ],
        )
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="10,000 poses, fewer repeats (a smoke run)")
    args = parser.parse_args()
    n, repeats = (10_000, 3) if args.quick else (100_000, 7)
    closed = bench_closed_forms(n, repeats)
    peers = bench_peers(n_rtb=50 if args.quick else 300, n_grad=1_000 if args.quick else 10_000)
    sweep = sweep_success(2_000 if args.quick else 100_000)
    obstacles = world_sweep(500 if args.quick else 10_000)
    info = machine_info()
    md = (
        f"Closed-form IK, {n:,} poses (`python benchmarks/bench_analytic.py`):\n\n"
        + closed_form_table(closed)
        + "\nAgainst the peers (same run):\n\n"
        + peer_table(peers)
        + "\n"
        + success_text(peers, sweep)
        + world_table(obstacles)
        + f"\nMachine: {info}\n"
    )
    print(md)
    payload = {"machine": info, "closed_forms": closed, "peers": peers, "sweep": sweep, "world": obstacles}
    path = save("analytic_quick" if args.quick else "analytic", payload, md)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
