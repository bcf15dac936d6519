"""The commands ``traj`` (a joint-space quintic or a Cartesian line tracked by IK -> CSV, animation)
and ``demo``."""

from __future__ import annotations

import argparse
import csv
import math
import shutil
import time
from pathlib import Path

import torch

from .. import robots
from ..chain import Chain
from ..checks import check_memory
from ..dh import DHChain
from .arguments import F64, UsageError, chain_of, drawing, joint_angles, pose_of, writable
from .output import pose_summary, print_json, print_pose, say, table

# peak memory of `demo` per timed configuration (fk, the LM solve and the 8 analytic branches in
# float64): about 2.9 kB measured from 50,000 to 200,000 configurations, rounded up
DEMO_BYTES_PER_CONFIGURATION = 3_000


# ---------------------------------------------------------------- traj
def run_traj(args: argparse.Namespace) -> int:
    """``iiwa-torch traj``: the path, its files and summary; 1 if a tracked line misses a pose."""
    from .. import trajectory

    chain = chain_of(args)
    viz = _check_traj_options(args, chain)
    q_start = None if args.from_q is None else joint_angles(chain, args.from_q, args.rad, "--from-q")
    q_end = None if args.to_q is None else joint_angles(chain, args.to_q, args.rad, "--to-q")
    if q_start is not None and q_end is not None:  # joint space: quintic
        duration = args.duration or _auto_duration(chain, trajectory.shortest_duration, q_start, q_end)
        qs = trajectory.jtraj(q_start, q_end, torch.linspace(0, duration, args.steps, dtype=F64)).q
        kind, tracked, line = "joint-space quintic", None, None
    else:  # Cartesian straight line, tracked by IK
        pose0 = chain.fk(q_start) if q_start is not None else pose_of(args.from_pose, args.rad, "--from-pose")
        pose1 = chain.fk(q_end) if q_end is not None else pose_of(args.to_pose, args.rad, "--to-pose")
        if q_start is None:
            q_start = _start_configuration(chain, pose0, args.method)
        line = trajectory.ctraj(pose0, pose1, args.steps, profile="quintic")
        tracked = trajectory.track(chain, line, q_start, method=args.method)
        qs = tracked.q
        duration = args.duration or _auto_duration(chain, trajectory.sampled_duration, qs)
        kind = f"Cartesian line tracked by {args.method} IK"
    times = torch.linspace(0, duration, args.steps, dtype=F64)
    ee = chain.fk(qs)[:, :3, 3]
    written = _write_traj(args, chain, viz, qs, times, ee, ee if line is None else line, duration)
    _report_traj(args, chain, kind, qs, times, duration, tracked, written)
    return 0 if tracked is None or bool(tracked.success.all()) else 1


def _check_traj_options(args: argparse.Namespace, chain: Chain):
    """Check ``traj``'s options before any work and default ``--method``; :mod:`~iiwa_torch.viz` if
    ``--gif`` is given, else None."""
    if args.method is None:  # track's closed forms are the presets' (a URDF arm's would need their mapping)
        args.method = "analytic" if isinstance(chain, DHChain) else "gradient"
    elif args.method == "analytic" and not isinstance(chain, DHChain):
        raise UsageError("traj --method analytic tracks the presets; use --method gradient for a --urdf arm")
    if (args.from_q is None) == (args.from_pose is None) or (args.to_q is None) == (args.to_pose is None):
        raise UsageError("give exactly one of --from-q/--from-pose and one of --to-q/--to-pose")
    if args.steps < 2:
        raise UsageError(f"--steps must be at least 2, got {args.steps}")
    if args.duration is not None and not 0 < args.duration < math.inf:
        raise UsageError(f"--duration must be positive (seconds), got {args.duration:g}")
    if args.size < 1 or (args.fps is not None and args.fps < 1):
        raise UsageError(f"--size and --fps must be positive, got {args.size} and {args.fps}")
    if args.csv:
        writable(args.csv, "--csv")
    if not args.gif:
        return None
    writable(args.gif, "--gif")
    if Path(args.gif).suffix.lower() == ".mp4" and shutil.which("ffmpeg") is None:
        raise UsageError(f"--gif {args.gif}: writing .mp4 needs ffmpeg on the PATH; write a .gif instead")
    return drawing()


def _write_traj(args, chain: Chain, viz, qs, times, ee, drawn_path, duration: float) -> list[str]:
    """Write ``--csv`` (t, ``qs (T, n)`` rad, ``ee (T, 3)`` m) and ``--gif`` (with ``drawn_path``
    ``(T, 3)`` or ``(T, 4, 4)``); the files written."""
    written = []
    if args.csv:
        with open(args.csv, "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["t_s", *(f"{n}_rad" for n in chain.joint_names), "x_m", "y_m", "z_m"])
            for t, qi, p in zip(times.tolist(), qs.tolist(), ee.tolist()):
                writer.writerow([f"{t:.6f}", *(f"{v:.9f}" for v in qi), *(f"{v:.9f}" for v in p)])
        written.append(args.csv)
    if args.gif:
        fps = max(1, round((args.steps - 1) / duration)) if args.fps is None else args.fps
        viz.animate(chain, qs, args.gif, fps=fps, path=drawn_path, size=(args.size, args.size))
        written.append(args.gif)
    return written


def _report_traj(args, chain: Chain, kind: str, qs, times, duration: float, tracked, written: list[str]) -> None:
    """``traj``'s summary (with a Cartesian line's tracking errors), as JSON or a table."""
    summary = {
        "robot": chain.name,
        "kind": kind,
        "steps": args.steps,
        "duration_s": duration,
        "max_joint_step_rad": float(qs.diff(dim=0).abs().max()),
        "files": written,
    }
    if tracked is not None:
        summary |= {
            "max_pos_err_m": float(tracked.pos_err.max()),
            "max_rot_err_rad": float(tracked.rot_err.max()),
            "all_success": bool(tracked.success.all()),
        }
    if args.json:
        print_json(summary | {"q_rad": qs.tolist(), "t_s": times.tolist()})
        return
    table(
        f"{chain.name}: {kind}",
        ["quantity", "value"],
        [[k, f"{v:.4g}" if isinstance(v, float) else str(v)] for k, v in summary.items() if k != "files"],
    )
    for file in written:
        say(f"written: {file}")


def _auto_duration(chain: Chain, rule, *args) -> float:
    """The shortest duration within the speed limits (1 s for a chain without limits or no motion)."""
    if chain.velocity_limits is None:
        return 1.0
    return float(rule(chain, *args)) or 1.0


def _start_configuration(chain: Chain, pose: torch.Tensor, method: str) -> torch.Tensor:
    from ..ik import analytic, solve

    result = analytic.iiwa_solve(chain, pose) if method == "analytic" and chain.n_joints == 7 else solve(chain, pose)
    if not bool(result.success):
        raise UsageError("the start pose is not reachable within the joint limits")
    return result.q


# ---------------------------------------------------------------- demo
def run_demo(args: argparse.Namespace) -> int:
    """``iiwa-torch demo``: the validation pose of Pereira et al., batched FK/IK timing, a tracked line."""
    if args.batch < 1:
        raise UsageError(f"--batch must be a positive integer, got {args.batch}")
    check_memory(args.batch * DEMO_BYTES_PER_CONFIGURATION, f"demo --batch {args.batch}")
    viz = None if args.no_gif else drawing()
    torch.set_num_threads(min(2, torch.get_num_threads()))
    quiet = args.json
    validation = _demo_validation_pose(quiet)
    timing = _demo_timing(args.batch, quiet)
    line, q, path = _demo_line(quiet)
    files = []
    if viz is not None:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        gif = out / "tracked_line.gif"
        viz.animate(robots.iiwa14(), q, gif, fps=12, path=path, size=(320, 320))
        files.append(str(gif))
        if not quiet:
            say(f"animation written to {gif}")
    if args.json:
        print_json({"validation_pose": validation, "batched_calls": timing, "tracked_line": line, "files": files})
    return 0


def _demo_validation_pose(quiet: bool) -> dict:
    """1. The validation pose of Pereira et al. (flange 0.090 m); its JSON."""
    if not quiet:
        say("1. iiwa14 with the flange of Pereira et al. (0.090 m) at q4 = -90 deg, q5 = 60 deg")
        say("   Pereira et al. (and RoboDK): xyz = (0.490, 0, 0.780), "
            "R = [[0, 0, 1], [0.866, 0.5, 0], [-0.5, 0.866, 0]]")  # fmt: skip
    paper = robots.iiwa14(flange=0.090)
    q_val = torch.tensor([0, 0, 0, -math.pi / 2, math.pi / 3, 0, 0], dtype=F64)
    if not quiet:
        print_pose(paper.fk(q_val), False, "iiwa-torch: fk")
    return {"robot": paper.name, "q_rad": q_val.tolist(), **pose_summary(paper.fk(q_val))}


def _demo_timing(n: int, quiet: bool) -> dict:
    """2. Batched FK and IK of ``n`` random iiwa14 configurations; the times (ms) and solved fractions."""
    from ..ik import analytic, solve

    chain = robots.iiwa14()
    q = chain.random_q(n, generator=torch.Generator().manual_seed(0))
    fk_ms, poses = _timed(chain.fk, q)
    ik_ms, result = _timed(solve, chain, poses)
    an_ms, sol = _timed(analytic.iiwa, chain, poses, analytic.iiwa_arm_angle(chain, q))
    ik_solved, an_solved = float(result.success.double().mean()), float(sol.valid.any(-1).double().mean())
    if not quiet:
        rows = [
            ["chain.fk", f"{fk_ms:.1f}", "-"],
            ["ik.solve (gradient, LM)", f"{ik_ms:.1f}", f"{100 * ik_solved:.2f}%"],
            ["ik.analytic.iiwa (8 branches)", f"{an_ms:.1f}", f"{100 * an_solved:.2f}%"],
        ]
        say(f"\n2. {n} random configurations of the iiwa14, float64, {torch.get_num_threads()} torch threads")
        table("batched calls", ["call", "ms", "solved"], rows)
    return {"batch": n, "threads": torch.get_num_threads(), "fk_ms": fk_ms, "ik_solve_ms": ik_ms,
            "ik_solve_solved": ik_solved, "analytic_ms": an_ms, "analytic_solved": an_solved}  # fmt: skip


def _demo_line(quiet: bool) -> tuple[dict, torch.Tensor, torch.Tensor]:
    """3. A line tracked by the closed form: its JSON, joint path ``(30, 7)`` and poses ``(30, 4, 4)``."""
    from .. import trajectory

    chain = robots.iiwa14()
    q0 = torch.tensor([0, 30, 0, -80, 0, 70, 0], dtype=F64).deg2rad()
    pose0 = chain.fk(q0)
    pose1 = pose0.clone()
    pose1[:3, 3] += torch.tensor([0.0, 0.35, -0.15], dtype=F64)
    path = trajectory.ctraj(pose0, pose1, 30, profile="quintic")
    track = trajectory.track(chain, path, q0, method="analytic")
    duration = trajectory.sampled_duration(chain, track.q)
    line = {
        "steps": path.shape[0],
        "max_pos_err_m": float(track.pos_err.max()),
        "max_rot_err_rad": float(track.rot_err.max()),
        "max_joint_step_rad": float(track.max_step),
        "shortest_duration_s": float(duration),
    }
    if not quiet:
        say("\n3. a straight line of 0.38 m, tracked by the closed-form IK (nearest solution at each step)")
        table(
            "ik along the line",
            ["steps", "max pos err (m)", "max rot err (rad)", "max joint step (deg)", "shortest duration (s)"],
            [[str(line["steps"]), f"{line['max_pos_err_m']:.1e}", f"{line['max_rot_err_rad']:.1e}",
              f"{math.degrees(line['max_joint_step_rad']):.2f}", f"{duration:.2f}"]],
        )  # fmt: skip
    return line, track.q, path


def _timed(fn, *args):
    """``(milliseconds, fn(*args))``, after a warm-up call on the first 8 rows of each tensor."""
    fn(*(a[:8] if isinstance(a, torch.Tensor) else a for a in args))
    start = time.perf_counter()
    out = fn(*args)
    return 1e3 * (time.perf_counter() - start), out
