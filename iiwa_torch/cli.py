"""The ``iiwa-torch`` command: forward and inverse kinematics, trajectories, robot tables, a demo.

The entry point is ``iiwa_torch.launch.main``, which sets OpenMP's wait policy before torch loads.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import json
import math
import shutil
import sys
import threading
import time
from importlib.metadata import entry_points
from pathlib import Path

import torch

from . import __version__, robots, so3
from .chain import Chain
from .checks import MissingExtra, check_memory, require
from .dh import DHChain

_F64 = torch.float64
_POS_TOL, _ROT_TOL = 1e-9, 1e-8  # m, rad: the gradient IK's tolerances; a solution missing by more is invalid
# peak memory of `demo` per timed configuration (fk, the LM solve and the 8 analytic branches in
# float64): about 2.9 kB measured from 50,000 to 200,000 configurations, rounded up
DEMO_BYTES_PER_CONFIGURATION = 3_000

_DESCRIPTION = """\
Forward and inverse kinematics, trajectories, robot tables and a demo.
Angles are degrees unless --rad is given; lengths are metres. --json prints one JSON
object for scripts (always metres and radians).

examples:
  iiwa-torch fk 0 0 0 -90 60 0 0 --flange 0.090
  iiwa-torch ik --pose 0.49 0 0.78 90 30 90 --flange 0.090
  iiwa-torch ik --pose 0.5 0.1 0.4                 (position only: 3 numbers)
  iiwa-torch traj --from-q 0 30 0 -60 0 60 0 --to-pose 0.5 0.2 0.6 180 0 180 --gif line.gif
  iiwa-torch robots iiwa14
  iiwa-torch demo
  iiwa-torch view --world '{"spheres": [[0.5, 0, 0.5, 0.1]]}' --capsules
"""


# ---------------------------------------------------------------- output helpers
def _console():
    try:
        from rich.console import Console
    except ImportError:  # rich is an optional extra: fall back to plain text
        return None
    return Console(width=None if sys.stdout.isatty() else 160)  # pipes and files: no 80-column wrap


def _table(title: str, columns: list[str], rows: list[list[str]]) -> None:
    """Print a table with rich if it is installed, else as aligned plain text."""
    console = _console()
    if console is not None:
        from rich.table import Table

        table = Table(title=title, title_justify="left")
        for col in columns:
            table.add_column(col, justify="right")
        for row in rows:
            table.add_row(*row)
        console.print(table)
        return
    widths = [max(len(c), *(len(r[i]) for r in rows)) for i, c in enumerate(columns)]
    print(title)
    for row in [columns, *rows]:
        print("  ".join(cell.rjust(w) for cell, w in zip(row, widths)))


def _say(text: str) -> None:
    console = _console()
    console.print(text, highlight=False) if console is not None else print(text)


def _json(obj) -> None:
    print(json.dumps(obj))


def _fmt(values, digits: int = 4) -> list[str]:
    # round first and add 0.0 so that values like -1e-17 print as 0.0000, never -0.0000
    return [f"{round(v, digits) + 0.0:.{digits}f}" for v in values]


# ---------------------------------------------------------------- argument helpers
def _chain(args: argparse.Namespace) -> Chain:
    """The preset of ``--robot`` (default iiwa14), or the chain of ``--urdf`` up to ``--end-link``."""
    if args.urdf is not None:
        if args.robot is not None or args.flange is not None:
            raise _UsageError("--urdf gives the robot: --robot and --flange apply to the presets only")
        try:
            return robots.from_urdf(args.urdf, end_link=args.end_link)
        except OSError as err:  # a file that exists but cannot be read
            raise _UsageError(f"--urdf {args.urdf}: cannot read it: {err.strerror or err}") from None
        except (ValueError, TypeError) as err:
            raise _UsageError(f"--urdf {args.urdf}: {err}") from None
    if args.end_link is not None:
        raise _UsageError("--end-link applies to --urdf only")
    robot = args.robot or "iiwa14"
    if args.flange is not None:
        if robot not in ("iiwa14", "iiwa7"):
            raise _UsageError(f"--flange applies to the iiwa presets only, not to {robot}")
        return robots.PRESETS[robot](flange=args.flange)
    return robots.PRESETS[robot]()


class _UsageError(Exception):
    """A bad combination of arguments: reported through argparse (exit status 2)."""


def _writable(path: str, option: str) -> Path:
    """``path`` as a Path whose folder exists (else a usage error naming ``option``)."""
    folder = Path(path).resolve().parent
    if not folder.is_dir():
        raise _UsageError(f"{option} {path}: the folder {folder} does not exist")
    return Path(path)


def _viz():
    """The drawing module, after checking (before any work) that matplotlib and Pillow are installed."""
    require("matplotlib", "viz")
    require("PIL", "viz")
    from . import viz

    return viz


def _angles(values: list[float], rad: bool) -> list[float]:
    return list(values) if rad else [math.radians(v) for v in values]


def _q(chain: Chain, values: list[float] | None, rad: bool, name: str) -> torch.Tensor:
    if len(values) != chain.n_joints:
        raise _UsageError(f"{name} needs {chain.n_joints} joint angles for {chain.name}, got {len(values)}")
    return torch.tensor(_angles(values, rad), dtype=_F64)


def _pose(values: list[float], rad: bool, name: str) -> torch.Tensor:
    """``x y z roll pitch yaw`` (6 numbers) or a row-major 4x4 matrix (16 numbers) -> (4, 4)."""
    if any(not math.isfinite(v) for v in values):
        raise _UsageError(f"{name} must be finite numbers, got {values}")
    if len(values) == 16:
        pose = torch.tensor(values, dtype=_F64).reshape(4, 4)
        rot = pose[:3, :3]
        orthonormal = torch.allclose(rot @ rot.T, torch.eye(3, dtype=_F64), atol=1e-6)
        bottom = torch.allclose(pose[3], torch.tensor([0.0, 0, 0, 1], dtype=_F64))
        if not (orthonormal and bottom and torch.linalg.det(rot) > 0):
            raise _UsageError(f"{name}: the 16 numbers are not a homogeneous transform with a rotation part")
        return pose
    if len(values) != 6:
        raise _UsageError(
            f"{name} needs x y z roll pitch yaw (6 numbers) or a 4x4 matrix (16 numbers), got {len(values)}"
        )
    pose = torch.eye(4, dtype=_F64)
    pose[:3, 3] = torch.tensor(values[:3], dtype=_F64)
    pose[:3, :3] = so3.rpy_to_matrix(torch.tensor(_angles(values[3:], rad), dtype=_F64))
    return pose


def _pose_summary(pose: torch.Tensor) -> dict:
    return {
        "pose": pose.tolist(),
        "xyz_m": pose[:3, 3].tolist(),
        "rpy_rad": so3.matrix_to_rpy(pose[:3, :3]).tolist(),
    }


def _print_pose(pose: torch.Tensor, rad: bool, title: str) -> None:
    _table(title, ["", "c1", "c2", "c3", "c4"], [[f"r{i + 1}", *_fmt(row)] for i, row in enumerate(pose.tolist())])
    rpy = so3.matrix_to_rpy(pose[:3, :3]).tolist()
    unit = "rad" if rad else "deg"
    rpy = rpy if rad else [math.degrees(v) for v in rpy]
    _say(f"xyz (m): {' '.join(_fmt(pose[:3, 3].tolist()))}    rpy ({unit}): {' '.join(_fmt(rpy, 3))}")


# ---------------------------------------------------------------- fk
def _fk(args: argparse.Namespace) -> int:
    chain = _chain(args)
    q = _q(chain, args.q, args.rad, "fk")
    pose = chain.fk(q)
    inside = bool(chain.within_limits(q))
    if args.plot:
        viz = _viz()
        _writable(args.plot, "--plot")
        xyz = ", ".join(f"{v:.3f}" for v in pose[:3, 3].tolist())
        title = f"{chain.name}, q = ({_q_text(q)}) deg\nend effector at ({xyz}) m"
        viz.save_png(chain, q, args.plot, frames=True, title=title)
    if args.json:
        _json({"robot": chain.name, "q_rad": q.tolist(), "within_limits": inside, **_pose_summary(pose)})
    else:
        _print_pose(pose, args.rad, f"{chain.name}: end-effector pose (m)")
        if not inside:
            _say("[yellow]warning: q is outside the joint limits[/yellow]")
    if args.plot:
        print(f"picture written to {args.plot}", file=sys.stderr)
    return 0


def _q_text(q: torch.Tensor) -> str:
    return " ".join(f"{math.degrees(v):.0f}" for v in q.tolist())


# ---------------------------------------------------------------- ik
def _ik(args: argparse.Namespace) -> int:
    chain = _chain(args)
    position_only = len(args.pose) == 3
    method = args.method or ("gradient" if position_only or not _has_closed_form(chain) else "analytic")
    if args.psi is not None and (method != "analytic" or chain.n_joints != 7):
        raise _UsageError(f"--psi is the arm angle of the iiwa's analytic IK (7 joints), not of {method} IK "
                          f"on {chain.name} ({chain.n_joints} joints)")
    if position_only:
        if method == "analytic":
            raise _UsageError("a position-only target (3 numbers) needs --method gradient")
        if any(not math.isfinite(v) for v in args.pose):
            raise _UsageError(f"--pose must be finite numbers, got {args.pose}")
        target = torch.tensor(args.pose, dtype=_F64)
        q, valid, label = _ik_gradient(chain, target, args, mode="position")
        pos_err = (chain.position(q) - target).norm(dim=-1)
        rot_err = torch.full_like(pos_err, float("nan"))
    else:
        target = _pose(args.pose, args.rad, "--pose")
        if method == "analytic":
            q, valid, label = _ik_analytic(chain, target, args)
        else:
            q, valid, label = _ik_gradient(chain, target, args)
        pos_vec, rot_vec = so3.pose_error(chain.fk(q), target.expand(q.shape[0], 4, 4))
        pos_err, rot_err = pos_vec.norm(dim=-1), rot_vec.norm(dim=-1)
    args.method = method
    status = 0 if bool(valid.any()) else 1
    why = [
        None if v else _why_invalid(chain, qi, pe, re, args.rad)
        for qi, v, pe, re in zip(q.tolist(), valid.tolist(), pos_err.tolist(), rot_err.tolist())
    ]
    if args.json:
        sols = [
            {"branch": b, "q_rad": qi, "valid": v, "why_invalid": w, "pos_err_m": pe, "rot_err_rad": re}
            for b, qi, v, w, pe, re in zip(label, q.tolist(), valid.tolist(), why, pos_err.tolist(), rot_err.tolist())
        ]
        if position_only:
            for sol in sols:
                sol["rot_err_rad"] = None
        _json({"robot": chain.name, "method": args.method, "target": target.tolist(), "solutions": sols})
        if status:
            print("no valid solution (unreachable or outside the joint limits)", file=sys.stderr)
        return status
    unit = "rad" if args.rad else "deg"
    rows = []
    for b, qi, w, pe, re in zip(label, q.tolist(), why, pos_err.tolist(), rot_err.tolist()):
        shown = qi if args.rad else [math.degrees(x) for x in qi]
        rows.append([b, *_fmt(shown, 2), "no" if w else "yes", f"{pe:.1e}", "-" if math.isnan(re) else f"{re:.1e}"])
    cols = ["branch", *chain.joint_names, "valid", "pos err (m)", "rot err (rad)"]
    _table(f"{chain.name}: IK solutions ({args.method}), joint angles in {unit}", cols, rows)
    for b, w in zip(label, why):
        if w:
            _say(f"{b} invalid: {w}")
    if status:
        print("no valid solution (unreachable or outside the joint limits)", file=sys.stderr)
    return status


def _why_invalid(chain: Chain, q: list[float], pos_err: float, rot_err: float, rad: bool) -> str:
    """Why the solution ``q`` (rad) is invalid: it misses the target (errors in m, rad; NaN: position
    only) beyond the solver tolerances, or joints lie outside their limits (e.g. ``A3 = -180 deg outside +-170``)."""
    if not pos_err <= _POS_TOL or rot_err > _ROT_TOL:
        missed = f"{pos_err:.1e} m" + ("" if math.isnan(rot_err) else f", {rot_err:.1e} rad")
        return f"misses the target by {missed}"
    unit, shown = ("rad", lambda v: f"{round(v, 4):g}") if rad else ("deg", lambda v: f"{round(math.degrees(v), 2):g}")
    outside = []
    for name, v, lo, hi in zip(chain.joint_names, q, *chain.limits.tolist()):
        if not lo <= v <= hi:
            span = f"+-{shown(hi)}" if lo == -hi else f"[{shown(lo)}, {shown(hi)}]"
            outside.append(f"{name} = {shown(v)} {unit} outside {span}")
    return ", ".join(outside) or "outside the joint limits"


def _has_closed_form(chain: Chain) -> bool:
    """Whether ``ik`` can solve ``chain`` in closed form: a preset, or an arm whose joint axes admit one."""
    if isinstance(chain, DHChain):
        return True
    from .ik import analytic

    try:
        analytic.structure(chain)
    except ValueError:
        return False
    return True


def _ik_analytic(chain: Chain, target: torch.Tensor, args) -> tuple[torch.Tensor, torch.Tensor, list[str]]:
    from .ik import analytic

    if not isinstance(chain, DHChain):  # another arm: the closed form its joint axes admit, if any
        try:
            form = analytic.structure(chain).form.value
        except ValueError as err:
            raise _UsageError(f"--method analytic: {err}") from None
        psi = (0.0 if args.psi is None else args.psi if args.rad else math.radians(args.psi)) if chain.n_joints == 7 \
            else None
        sol = analytic.solve(chain, target, psi)
        labels = [f"{form} {k}" for k in range(sol.q.shape[-2])]
        return sol.q.contiguous(), sol.valid, labels
    if chain.n_joints == 7:
        psi = 0.0 if args.psi is None else args.psi if args.rad else math.radians(args.psi)
        sol = analytic.iiwa(chain, target, psi)
    elif chain.n_joints == 6:
        sol = analytic.pieper(chain, target)
    elif chain.n_joints == 3:  # planar: the target's x, y and its rotation about z
        phi = math.atan2(float(target[1, 0]), float(target[0, 0]))
        sol = analytic.planar3r(chain, float(target[0, 3]), float(target[1, 3]), phi)
    else:
        raise _UsageError(f"--method analytic has no closed form for {chain.name}; use --method gradient")
    labels = [f"{'+-'[k >> 2 & 1]}{'+-'[k >> 1 & 1]}{'+-'[k & 1]}" for k in range(sol.q.shape[-2])]
    return sol.q.contiguous(), sol.valid, labels


def _ik_gradient(
    chain: Chain, target: torch.Tensor, args, mode: str = "pose"
) -> tuple[torch.Tensor, torch.Tensor, list[str]]:
    from .ik import solve

    generator = torch.Generator().manual_seed(args.seed)
    result = solve(chain, target, mode=mode, generator=generator, pos_tol=_POS_TOL, rot_tol=_ROT_TOL)
    return result.q[None], result.success[None], ["lm"]


# ---------------------------------------------------------------- traj
def _traj(args: argparse.Namespace) -> int:
    from . import trajectory

    chain = _chain(args)
    if args.method is None:  # track's closed forms are the presets' (a URDF arm's would need their mapping)
        args.method = "analytic" if isinstance(chain, DHChain) else "gradient"
    elif args.method == "analytic" and not isinstance(chain, DHChain):
        raise _UsageError("traj --method analytic tracks the presets; use --method gradient for a --urdf arm")
    if (args.from_q is None) == (args.from_pose is None) or (args.to_q is None) == (args.to_pose is None):
        raise _UsageError("give exactly one of --from-q/--from-pose and one of --to-q/--to-pose")
    if args.steps < 2:
        raise _UsageError(f"--steps must be at least 2, got {args.steps}")
    if args.duration is not None and not 0 < args.duration < math.inf:
        raise _UsageError(f"--duration must be positive (seconds), got {args.duration:g}")
    if args.size < 1 or (args.fps is not None and args.fps < 1):
        raise _UsageError(f"--size and --fps must be positive, got {args.size} and {args.fps}")
    if args.csv:
        _writable(args.csv, "--csv")
    if args.gif:
        _writable(args.gif, "--gif")
        if Path(args.gif).suffix.lower() == ".mp4" and shutil.which("ffmpeg") is None:
            raise _UsageError(f"--gif {args.gif}: writing .mp4 needs ffmpeg on the PATH; write a .gif instead")
        viz = _viz()
    q_start = None if args.from_q is None else _q(chain, args.from_q, args.rad, "--from-q")
    q_end = None if args.to_q is None else _q(chain, args.to_q, args.rad, "--to-q")
    if q_start is not None and q_end is not None:  # joint space: quintic
        duration = args.duration or _auto_duration(chain, trajectory.shortest_duration, q_start, q_end)
        qs = trajectory.jtraj(q_start, q_end, torch.linspace(0, duration, args.steps, dtype=_F64)).q
        kind, worst = "joint-space quintic", None
    else:  # Cartesian straight line, tracked by IK
        pose0 = chain.fk(q_start) if q_start is not None else _pose(args.from_pose, args.rad, "--from-pose")
        pose1 = chain.fk(q_end) if q_end is not None else _pose(args.to_pose, args.rad, "--to-pose")
        if q_start is None:
            q_start = _start_configuration(chain, pose0, args.method)
        path = trajectory.ctraj(pose0, pose1, args.steps, profile="quintic")
        result = trajectory.track(chain, path, q_start, method=args.method)
        qs = result.q
        duration = args.duration or _auto_duration(chain, trajectory.sampled_duration, qs)
        kind, worst = f"Cartesian line tracked by {args.method} IK", result
    times = torch.linspace(0, duration, args.steps, dtype=_F64)
    ee = chain.fk(qs)[:, :3, 3]
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
        viz.animate(chain, qs, args.gif, fps=fps, path=ee if worst is None else path, size=(args.size, args.size))
        written.append(args.gif)
    summary = {
        "robot": chain.name,
        "kind": kind,
        "steps": args.steps,
        "duration_s": duration,
        "max_joint_step_rad": float(qs.diff(dim=0).abs().max()),
        "files": written,
    }
    if worst is not None:
        summary |= {
            "max_pos_err_m": float(worst.pos_err.max()),
            "max_rot_err_rad": float(worst.rot_err.max()),
            "all_success": bool(worst.success.all()),
        }
    if args.json:
        _json(summary | {"q_rad": qs.tolist(), "t_s": times.tolist()})
    else:
        _table(
            f"{chain.name}: {kind}",
            ["quantity", "value"],
            [[k, f"{v:.4g}" if isinstance(v, float) else str(v)] for k, v in summary.items() if k != "files"],
        )
        for file in written:
            _say(f"written: {file}")
    return 0 if worst is None or bool(worst.success.all()) else 1


def _auto_duration(chain: Chain, rule, *args) -> float:
    """The shortest duration within the speed limits (1 s for a chain without limits or no motion)."""
    if chain.velocity_limits is None:
        return 1.0
    return float(rule(chain, *args)) or 1.0


def _start_configuration(chain: Chain, pose: torch.Tensor, method: str) -> torch.Tensor:
    from .ik import analytic, solve

    result = analytic.iiwa_solve(chain, pose) if method == "analytic" and chain.n_joints == 7 else solve(chain, pose)
    if not bool(result.success):
        raise _UsageError("the start pose is not reachable within the joint limits")
    return result.q


# ---------------------------------------------------------------- robots
def _robots(args: argparse.Namespace) -> int:
    if args.name is None:
        chains = [fn() for fn in robots.PRESETS.values()]
        if args.json:
            _json([{"name": c.name, "joints": c.n_joints, "convention": c.convention.value} for c in chains])
            return 0
        rows = [
            [c.name, str(c.n_joints), c.convention.value, "yes" if c.velocity_limits is not None else "no"]
            for c in chains
        ]
        _table(
            "robot presets (iiwa-torch robots NAME for the DH table)", ["name", "joints", "DH", "speed limits"], rows
        )
        return 0
    if args.name not in robots.PRESETS:
        raise _UsageError(f"unknown robot {args.name!r}; presets: {', '.join(robots.PRESETS)}")
    chain = robots.PRESETS[args.name]()
    vel = [None] * chain.n_joints if chain.velocity_limits is None else chain.velocity_limits.tolist()
    lows, highs = chain.limits.tolist()
    if args.json:
        _json(
            {
                "name": chain.name,
                "convention": chain.convention.value,
                "dh_rows_a_alpha_d_offset": chain.dh.tolist(),
                "limits_rad": chain.limits.tolist(),
                "velocity_limits_rad_s": None if chain.velocity_limits is None else vel,
                "tool": chain.tool.tolist(),
            }
        )
        return 0
    rows = []
    for name, (a, al, d, off), lo, hi, v in zip(chain.joint_names, chain.dh.tolist(), lows, highs, vel):
        deg = [math.degrees(x) for x in (al, off, lo, hi)]
        speed = "-" if v is None else f"{math.degrees(v):.0f}"
        rows.append(
            [name, f"{a:.4f}", f"{deg[0]:.0f}", f"{d:.4f}", f"{deg[1]:.0f}", f"{deg[2]:.0f}", f"{deg[3]:.0f}", speed]
        )
    cols = ["joint", "a (m)", "alpha (deg)", "d (m)", "offset (deg)", "min (deg)", "max (deg)", "speed (deg/s)"]
    _table(f"{chain.name}: {chain.convention.value} DH", cols, rows)
    return 0


# ---------------------------------------------------------------- demo
def _demo(args: argparse.Namespace) -> int:
    from . import trajectory
    from .ik import analytic, solve

    if args.batch < 1:
        raise _UsageError(f"--batch must be a positive integer, got {args.batch}")
    check_memory(args.batch * DEMO_BYTES_PER_CONFIGURATION, f"demo --batch {args.batch}")
    viz = None if args.no_gif else _viz()
    torch.set_num_threads(min(2, torch.get_num_threads()))
    say, table = (lambda *a: None, lambda *a: None) if args.json else (_say, _table)

    # 1. The validation pose of Pereira et al. (flange 0.090 m): position (0.490, 0, 0.780).
    say("1. iiwa14 with the flange of Pereira et al. (0.090 m) at q4 = -90 deg, q5 = 60 deg")
    say("   Pereira et al. (and RoboDK): xyz = (0.490, 0, 0.780), R = [[0, 0, 1], [0.866, 0.5, 0], [-0.5, 0.866, 0]]")
    paper = robots.iiwa14(flange=0.090)
    q_val = torch.tensor([0, 0, 0, -math.pi / 2, math.pi / 3, 0, 0], dtype=_F64)
    if not args.json:
        _print_pose(paper.fk(q_val), False, "iiwa-torch: fk")

    # 2. Batched FK and IK timing (each call warmed up on 8 problems first).
    chain = robots.iiwa14()
    n = args.batch
    q = chain.random_q(n, generator=torch.Generator().manual_seed(0))
    fk_ms, poses = _timed(chain.fk, q)
    ik_ms, result = _timed(solve, chain, poses)
    an_ms, sol = _timed(analytic.iiwa, chain, poses, analytic.iiwa_arm_angle(chain, q))
    ik_solved, an_solved = float(result.success.double().mean()), float(sol.valid.any(-1).double().mean())
    rows = [
        ["chain.fk", f"{fk_ms:.1f}", "-"],
        ["ik.solve (gradient, LM)", f"{ik_ms:.1f}", f"{100 * ik_solved:.2f}%"],
        ["ik.analytic.iiwa (8 branches)", f"{an_ms:.1f}", f"{100 * an_solved:.2f}%"],
    ]
    say(f"\n2. {n} random configurations of the iiwa14, float64, {torch.get_num_threads()} torch threads")
    table("batched calls", ["call", "ms", "solved"], rows)

    # 3. A tracked Cartesian line.
    q0 = torch.tensor([0, 30, 0, -80, 0, 70, 0], dtype=_F64).deg2rad()
    pose0 = chain.fk(q0)
    pose1 = pose0.clone()
    pose1[:3, 3] += torch.tensor([0.0, 0.35, -0.15], dtype=_F64)
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
    say("\n3. a straight line of 0.38 m, tracked by the closed-form IK (nearest solution at each step)")
    table(
        "ik along the line",
        ["steps", "max pos err (m)", "max rot err (rad)", "max joint step (deg)", "shortest duration (s)"],
        [
            [
                str(line["steps"]),
                f"{line['max_pos_err_m']:.1e}",
                f"{line['max_rot_err_rad']:.1e}",
                f"{math.degrees(line['max_joint_step_rad']):.2f}",
                f"{duration:.2f}",
            ]
        ],
    )
    files = []
    if viz is not None:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        gif = out / "tracked_line.gif"
        viz.animate(chain, track.q, gif, fps=12, path=path, size=(320, 320))
        files.append(str(gif))
        say(f"animation written to {gif}")
    if args.json:
        timing = {"batch": n, "threads": torch.get_num_threads(), "fk_ms": fk_ms, "ik_solve_ms": ik_ms,
                  "ik_solve_solved": ik_solved, "analytic_ms": an_ms, "analytic_solved": an_solved}  # fmt: skip
        validation = {"robot": paper.name, "q_rad": q_val.tolist(), **_pose_summary(paper.fk(q_val))}
        _json({"validation_pose": validation, "batched_calls": timing, "tracked_line": line, "files": files})
    return 0


def _timed(fn, *args):
    """``(milliseconds, fn(*args))``, after a warm-up call on the first 8 rows of each tensor."""
    fn(*(a[:8] if isinstance(a, torch.Tensor) else a for a in args))
    start = time.perf_counter()
    out = fn(*args)
    return 1e3 * (time.perf_counter() - start), out


def _view(args: argparse.Namespace) -> int:
    require("viser", "viewer")  # before any work
    from . import viewer

    chain = _chain(args)
    q = None if args.q is None else _q(chain, args.q, args.rad, "view")
    world = None if args.world is None else viewer.load_world(args.world)
    if args.policy is not None and args.path is not None:
        raise _UsageError("give at most one of --policy and --path")
    path, dt, goals = None, 0.05, None
    if args.path is not None:
        path, dt = _csv_path(chain, args.path)
    elif args.policy is not None:
        path, dt, goals = _policy_rollouts(chain, args.policy, args.goals, args.seed)
        _say(f"{args.goals} rollouts of {args.policy}: pick one with the playback panel's path slider")
    viewer.show(
        chain, q, host=args.host, port=args.port, world=world, urdf=args.urdf, show_capsules=args.capsules,
        show_frames=args.frames, path=path, dt=dt, goals=goals,
    )  # fmt: skip
    return 0


def _csv_path(chain: Chain, file: str) -> tuple[torch.Tensor, float]:
    """The joint path ``(T, n)`` and time step (s) of a CSV written by ``iiwa-torch traj --csv``."""
    try:
        with open(file, newline="") as f:
            rows = list(csv.DictReader(f))
    except OSError as err:
        raise _UsageError(f"--path {file}: {err.strerror}") from None
    columns = [f"{name}_rad" for name in chain.joint_names]
    if len(rows) < 2 or any(c not in rows[0] for c in ["t_s", *columns]):
        raise _UsageError(f"--path {file}: expected 2+ rows with columns t_s, {', '.join(columns)} (traj --csv)")
    try:
        q = torch.tensor([[float(r[c]) for c in columns] for r in rows], dtype=_F64)
        t = [float(r["t_s"]) for r in rows]
    except ValueError as err:
        raise _UsageError(f"--path {file}: {err}") from None
    return q, (t[-1] - t[0]) / (len(t) - 1)


def _policy_rollouts(chain: Chain, policy: str, n_goals: int, seed: int):
    """``(q (n_goals, T + 1, n), dt s, goal positions (n_goals, 3))`` of a trained policy's rollouts
    on held-out goals, by the training code's playback (the ``iiwa_torch.playback`` entry point:
    ``train.playback.policy_rollouts``)."""
    if n_goals < 1:
        raise _UsageError(f"--goals must be a positive integer, got {n_goals}")
    found = entry_points(group="iiwa_torch.playback", name="policy")
    if not found:
        raise _UsageError("--policy needs iiwa-torch's training code (train/), installed from its repository")
    try:
        robot, q, dt, goals = next(iter(found)).load()(Path(policy), n_goals, seed)
    except FileNotFoundError as err:
        raise _UsageError(f"--policy: {err}") from None
    if robot != chain.name:
        raise _UsageError(f"--policy {policy} drives {robot}, not {chain.name}: use --robot {robot}")
    return q, dt, goals


def _workspace(args: argparse.Namespace) -> int:
    from . import workspace

    if args.plot is None and not args.json:
        raise _UsageError("give --plot PNG (the side view), --json (the extent), or both")
    if args.plot is not None:
        _viz()  # matplotlib is needed: say which extra if it is missing
    chain = _chain(args)
    if args.plot is not None:
        _writable(args.plot, "--plot")
    if args.manipulability:
        if args.plot is None:
            raise _UsageError("--manipulability is drawn with the side view: give --plot too")
        _writable(args.manipulability, "--manipulability")
    if args.samples <= 0 or args.h <= 0:
        raise _UsageError(f"--samples and --h must be positive, got {args.samples} and {args.h}")
    if args.point is None:  # the wrist centre of the presets' spherical wrists; any other arm's flange
        args.point = "wrist" if isinstance(chain, DHChain) and chain.n_joints >= 6 else "flange"
    wrist = args.point == "wrist"
    point = workspace.frame_point(chain, 5) if wrist else None
    if args.plot is not None:
        workspace.plot_workspace(
            chain,
            args.plot,
            manipulability_path=args.manipulability,
            point=point,
            point_label="wrist centre" if wrist else "flange",
            h=args.h,
            n_samples=args.samples,
            datasheet=workspace.DATASHEET.get(chain.name) if wrist else None,
            seed=args.seed,
        )
    if args.json:
        reach = workspace.extent(chain, args.samples, point=point, generator=torch.Generator().manual_seed(args.seed))
        files = [f for f in (args.plot, args.manipulability) if f]
        _json({"robot": chain.name, "point": args.point, "n_samples": args.samples, "z_max_m": reach.z_max,
               "z_min_m": reach.z_min, "r_max_m": reach.r_max, "files": files})  # fmt: skip
        return 0
    _say(f"side view written to {args.plot}")
    if args.manipulability:
        _say(f"manipulability map written to {args.manipulability}")
    return 0


# ---------------------------------------------------------------- parser
def _common_options() -> argparse.ArgumentParser:
    """The options most commands share (the robot, units, output format)."""
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--robot", choices=list(robots.PRESETS), help="robot preset (default iiwa14)")
    common.add_argument("--urdf", metavar="FILE", help="any serial arm from its URDF file instead of a preset")
    common.add_argument("--end-link", metavar="LINK",
                        help="with --urdf: the end effector's link (default: the only leaf)")
    common.add_argument(
        "--flange",
        type=float,
        help="iiwa wrist-to-flange length in m (default 0.126, the datasheet; Pereira et al.: 0.090)",
    )
    common.add_argument("--rad", action="store_true", help="angles in radians (default: degrees)")
    common.add_argument("--json", action="store_true", help="print JSON (metres, radians) instead of tables")
    return common


def _add_fk(sub, common: argparse.ArgumentParser) -> None:
    """The ``fk`` command's options."""
    p = sub.add_parser("fk", parents=[common], help="joint angles -> end-effector pose")
    p.add_argument("q", nargs="+", type=float, help="joint angles (deg unless --rad)")
    p.add_argument("--plot", metavar="PNG", help="also draw the arm to this PNG file")
    p.set_defaults(func=_fk, parser=p)


def _add_ik(sub, common: argparse.ArgumentParser) -> None:
    """The ``ik`` command's options."""
    p = sub.add_parser("ik", parents=[common], help="pose -> joint angles (all analytic branches, or gradient)")
    p.add_argument(
        "--pose",
        nargs="+",
        type=float,
        required=True,
        metavar="V",
        help="x y z roll pitch yaw, 16 numbers of a row-major 4x4, or x y z alone (position only)",
    )
    p.add_argument(
        "--method",
        choices=["analytic", "gradient"],
        help="closed form (all branches) or gradient IK (default: analytic; gradient for x y z)",
    )
    p.add_argument("--psi", type=float, help="iiwa arm angle for the analytic solver (default 0)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the gradient solver")
    p.set_defaults(func=_ik, parser=p)


def _add_traj(sub, common: argparse.ArgumentParser) -> None:
    """The ``traj`` command's options."""
    p = sub.add_parser("traj", parents=[common], help="trajectory between configurations or poses -> CSV, animation")
    p.add_argument("--from-q", nargs="+", type=float, metavar="Q", help="start joint angles")
    p.add_argument("--from-pose", nargs="+", type=float, metavar="V", help="start pose: x y z roll pitch yaw, or a 4x4")
    p.add_argument("--to-q", nargs="+", type=float, metavar="Q", help="goal joint angles (a joint-space quintic)")
    p.add_argument("--to-pose", nargs="+", type=float, metavar="V", help="goal pose (a straight line tracked by IK)")
    p.add_argument("--steps", type=int, default=50, help="samples along the trajectory (default 50)")
    p.add_argument("--duration", type=float, help="seconds (default: the shortest within the speed limits)")
    p.add_argument("--method", choices=["analytic", "gradient"],
                   help="IK for Cartesian lines (default: analytic for the presets, gradient for a --urdf arm)")
    p.add_argument("--csv", metavar="FILE", help="write t, joint angles (rad) and end-effector xyz")
    p.add_argument("--gif", metavar="FILE", help="write an animation (.gif, or .mp4 with ffmpeg)")
    p.add_argument("--fps", type=int, help="animation frame rate (default: real time)")
    p.add_argument("--size", type=int, default=360, help="animation size in pixels")
    p.set_defaults(func=_traj, parser=p)


def _add_robots(sub, common: argparse.ArgumentParser) -> None:
    """The ``robots`` command's options."""
    p = sub.add_parser("robots", help="list presets, or print one's DH table")
    p.add_argument("name", nargs="?", help="a preset name")
    p.add_argument("--json", action="store_true", help="print JSON (metres, radians) instead of tables")
    p.set_defaults(func=_robots, parser=p)


def _add_demo(sub, common: argparse.ArgumentParser) -> None:
    """The ``demo`` command's options."""
    p = sub.add_parser("demo", help="FK at the validation pose, batched FK/IK timing, a tracked line")
    p.add_argument("--out", default="reports/demo", help="directory for the animation (default reports/demo)")
    p.add_argument("--batch", type=int, default=10_000, help="configurations in the timing (default 10000)")
    p.add_argument("--no-gif", action="store_true", help="skip writing the animation")
    p.add_argument("--json", action="store_true", help="print JSON (metres, radians, ms) instead of tables")
    p.set_defaults(func=_demo, parser=p)


def _add_view(sub, common: argparse.ArgumentParser) -> None:
    """The ``view`` command's options."""
    p = sub.add_parser("view", parents=[common], help="browser viewer: joint sliders, pose read-out, IK target")
    p.add_argument("--q", nargs="+", type=float, metavar="Q", help="first configuration (deg unless --rad)")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=int, default=8080, help="port (default 8080; 0: any free one; busy: the next free)")
    p.add_argument(
        "--world", metavar="JSON",
        help='obstacles: a JSON file or text, e.g. \'{"spheres": [[0.5, 0, 0.5, 0.1]]}\' (keys: docs/viewer.md)',
    )  # fmt: skip
    p.add_argument("--capsules", action="store_true", help="draw the robot's collision capsules")
    p.add_argument("--frames", action="store_true", help="draw every link frame")
    p.add_argument("--path", metavar="CSV", help="play back a joint path written by `iiwa-torch traj --csv`")
    p.add_argument("--policy", metavar="DIR", help="play back a policy's rollouts, e.g. train/policies/ppo_iiwa_reach")
    p.add_argument("--goals", type=int, default=4, help="--policy: number of held-out goals (default 4)")
    p.add_argument("--seed", type=int, default=0, help="--policy: goal-set seed (default 0)")
    p.set_defaults(func=_view, parser=p)


def _add_workspace(sub, common: argparse.ArgumentParser) -> None:
    """The ``workspace`` command's options."""
    p = sub.add_parser("workspace", parents=[common], help="reachable set: side-view envelope, manipulability map")
    p.add_argument("--plot", metavar="PNG", help="write the side view (r-z plane) to this PNG")
    p.add_argument("--manipulability", metavar="PNG", help="also write a manipulability map to this PNG")
    p.add_argument(
        "--point", choices=["wrist", "flange"],
        help="the point whose reach is drawn (default: the wrist centre KUKA's datasheet draws, for the presets; "
             "the flange for a --urdf arm)",
    )
    p.add_argument("--h", type=float, default=0.005, help="grid cell size in m (default 0.005)")
    p.add_argument("--samples", type=int, default=1 << 23, help="sampled configurations (default 8388608)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the sampling")
    p.set_defaults(func=_workspace, parser=p)


def _parser() -> argparse.ArgumentParser:
    common = _common_options()
    parser = argparse.ArgumentParser(
        prog="iiwa-torch", description=_DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in (_add_fk, _add_ik, _add_traj, _add_robots, _add_demo, _add_view, _add_workspace):
        add(sub, common)
    return parser


class Elapsed:
    """While a command runs, after ``delay`` s, its elapsed time on stderr: rewritten in place every
    second on a terminal, a line every 30 s otherwise; stdout (tables, ``--json``) is untouched."""

    def __init__(self, name: str, delay: float = 2.0):
        self.name, self.delay = name, delay
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._start = time.monotonic()
        self._shown = False

    def __enter__(self) -> Elapsed:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        if self._shown and sys.stderr.isatty():
            sys.stderr.write("\r\033[K")  # clear the line for what follows
            sys.stderr.flush()

    def _run(self) -> None:
        tty = sys.stderr.isatty()
        if self._stop.wait(self.delay):
            return
        while True:
            self._shown = True
            text = f"iiwa-torch {self.name}: running for {time.monotonic() - self._start:.0f} s"
            sys.stderr.write(f"\r{text}\033[K" if tty else text + "\n")
            sys.stderr.flush()
            if self._stop.wait(1.0 if tty else 30.0):
                return


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    # `view` serves until stopped: no running time over its own messages
    running = contextlib.nullcontext() if args.func is _view else Elapsed(args.parser.prog.split()[-1])
    try:
        with running:
            return args.func(args)
    except (_UsageError, ValueError) as err:  # the library's ValueErrors name the bad input too
        args.parser.error(str(err))  # the subcommand's usage and the message; exit status 2
    except MissingExtra as err:  # one line naming the extra to install
        args.parser.exit(2, f"{args.parser.prog}: error: {err}\n")


if __name__ == "__main__":
    sys.exit(main())
