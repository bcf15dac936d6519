"""The commands ``fk`` (joint angles -> pose), ``ik`` (pose -> every closed-form branch, or the
gradient IK) and ``robots`` (the presets and their DH tables)."""

from __future__ import annotations

import argparse
import math
import sys

import torch

from .. import robots, so3
from ..chain import Chain
from ..dh import DHChain
from .arguments import (
    F64,
    UsageError,
    chain_of,
    drawing,
    joint_angles,
    joint_scales,
    joint_unit,
    outside_limits,
    pose_of,
    writable,
)
from .output import fmt, pose_summary, print_json, print_pose, say, table

POS_TOL, ROT_TOL = 1e-9, 1e-8  # m, rad: the gradient IK's tolerances; a solution missing by more is invalid


# ---------------------------------------------------------------- fk
def run_fk(args: argparse.Namespace) -> int:
    """``iiwa-torch fk``: the end-effector pose, optionally a picture of the arm."""
    chain = chain_of(args)
    q = joint_angles(chain, args.q, args.rad, "fk")
    pose = chain.fk(q)
    inside = bool(chain.within_limits(q))
    if args.plot:
        viz = drawing()
        writable(args.plot, "--plot")
        xyz = ", ".join(f"{v:.3f}" for v in pose[:3, 3].tolist())
        shown = " ".join(f"{v / k:.3g}" for v, k in zip(q.tolist(), joint_scales(chain, args.rad)))
        title = f"{chain.name}, q = ({shown}) {joint_unit(chain, args.rad)}\nend effector at ({xyz}) m"
        viz.save_png(chain, q, args.plot, frames=True, title=title)
    if args.json:
        print_json({"robot": chain.name, "q_rad": q.tolist(), "within_limits": inside, **pose_summary(pose)})
    else:
        print_pose(pose, args.rad, f"{chain.name}: end-effector pose (m)")
        if not inside:
            say("[yellow]warning: q is outside the joint limits[/yellow]")
    if args.plot:
        print(f"picture written to {args.plot}", file=sys.stderr)
    return 0


# ---------------------------------------------------------------- ik
def run_ik(args: argparse.Namespace) -> int:
    """``iiwa-torch ik``: every solution with its errors and why it is invalid; 1 if none is valid."""
    chain = chain_of(args)
    position_only = len(args.pose) == 3
    method = args.method or ("gradient" if position_only or not _has_closed_form(chain) else "analytic")
    if args.psi is not None and (method != "analytic" or chain.n_joints != 7):
        raise UsageError(f"--psi is the arm angle of the iiwa's analytic IK (7 joints), not of {method} IK "
                         f"on {chain.name} ({chain.n_joints} joints)")  # fmt: skip
    if position_only:
        if method == "analytic":
            raise UsageError("a position-only target (3 numbers) needs --method gradient")
        if any(not math.isfinite(v) for v in args.pose):
            raise UsageError(f"--pose must be finite numbers, got {args.pose}")
        target = torch.tensor(args.pose, dtype=F64)
        q, valid, label = _ik_gradient(chain, target, args, mode="position")
        pos_err = (chain.position(q) - target).norm(dim=-1)
        rot_err = torch.full_like(pos_err, float("nan"))
    else:
        target = pose_of(args.pose, args.rad, "--pose")
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
        print_json({"robot": chain.name, "method": args.method, "target": target.tolist(), "solutions": sols})
    else:
        _print_solutions(chain, args, label, q, why, pos_err, rot_err)
    if status:
        print("no valid solution (unreachable or outside the joint limits)", file=sys.stderr)
    return status


def _print_solutions(chain: Chain, args, label, q, why, pos_err, rot_err) -> None:
    """``ik``'s solutions ``q (m, n)`` rad as a table, then why each invalid one is."""
    scales = joint_scales(chain, args.rad)
    rows = []
    for b, qi, w, pe, re in zip(label, q.tolist(), why, pos_err.tolist(), rot_err.tolist()):
        shown = [fmt([x / k], 2 if k != 1.0 else 4)[0] for x, k in zip(qi, scales)]  # degrees to 0.01, else 1e-4
        rows.append([b, *shown, "no" if w else "yes", f"{pe:.1e}", "-" if math.isnan(re) else f"{re:.1e}"])
    cols = ["branch", *chain.joint_names, "valid", "pos err (m)", "rot err (rad)"]
    table(f"{chain.name}: IK solutions ({args.method}), joints in {joint_unit(chain, args.rad)}", cols, rows)
    for b, w in zip(label, why):
        if w:
            say(f"{b} invalid: {w}")


def _why_invalid(chain: Chain, q: list[float], pos_err: float, rot_err: float, rad: bool) -> str:
    """Why ``q`` (rad) is invalid: it misses the target (m, rad; NaN: position only) beyond the
    tolerances, or e.g. ``A3 = -180 deg outside +-170``."""
    if not pos_err <= POS_TOL or rot_err > ROT_TOL:
        missed = f"{pos_err:.1e} m" + ("" if math.isnan(rot_err) else f", {rot_err:.1e} rad")
        return f"misses the target by {missed}"
    return outside_limits(chain, q, rad) or "outside the joint limits"


def _has_closed_form(chain: Chain) -> bool:
    """Whether ``chain`` is a preset or has joint axes that admit a closed form."""
    if isinstance(chain, DHChain):
        return True
    from ..ik import analytic

    try:
        analytic.structure(chain)
    except ValueError:
        return False
    return True


def _ik_analytic(chain: Chain, target: torch.Tensor, args) -> tuple[torch.Tensor, torch.Tensor, list[str]]:
    from ..ik import analytic

    psi = 0.0 if args.psi is None else args.psi if args.rad else math.radians(args.psi)
    if not isinstance(chain, DHChain):  # another arm: the closed form its joint axes admit, if any
        try:
            found = analytic.structure(chain)
        except ValueError as err:
            raise UsageError(f"--method analytic: {err}") from None
        srs = found.form is analytic.ClosedForm.SRS
        sol = analytic.solve(chain, target, psi if srs else None)
        if srs and args.psi is None and not bool(sol.valid.any()):
            psi = _arm_angle_that_solves(chain, target, found.dh, found.signs)
            sol = sol if psi is None else analytic.solve(chain, target, psi)
        labels = [f"{found.form.value} {k}" for k in range(sol.q.shape[-2])]
        return sol.q.contiguous(), sol.valid, labels
    if chain.n_joints == 7:
        sol = analytic.iiwa(chain, target, psi)
        if args.psi is None and not bool(sol.valid.any()):
            psi = _arm_angle_that_solves(chain, target, chain, torch.ones(7, dtype=F64))
            sol = sol if psi is None else analytic.iiwa(chain, target, psi)
    elif chain.n_joints == 6:
        sol = analytic.pieper(chain, target)
    elif chain.n_joints == 3:  # planar: the target's x, y and its rotation about z
        phi = math.atan2(float(target[1, 0]), float(target[0, 0]))
        sol = analytic.planar3r(chain, float(target[0, 3]), float(target[1, 3]), phi)
    else:
        raise UsageError(f"--method analytic has no closed form for {chain.name}; use --method gradient")
    labels = [f"{'+-'[k >> 2 & 1]}{'+-'[k >> 1 & 1]}{'+-'[k & 1]}" for k in range(sol.q.shape[-2])]
    return sol.q.contiguous(), sol.valid, labels


def _arm_angle_that_solves(chain: Chain, target: torch.Tensor, dh: DHChain, signs: torch.Tensor) -> float | None:
    """Without ``--psi``, when no branch at psi = 0 is valid: the arm angle (rad, in ``dh``'s terms,
    ``q_dh = signs * q``) of the gradient IK's answer, said on stderr; None if that fails too."""
    from ..ik import analytic, solve

    result = solve(chain, target, pos_tol=POS_TOL, rot_tol=ROT_TOL)
    if not bool(result.success):
        return None
    psi = float(analytic.iiwa_arm_angle(dh, result.q * signs.to(result.q)))
    print(f"no valid branch at psi = 0; psi = {math.degrees(psi):.2f} deg, the arm angle of a gradient IK "
          "solution (--psi sets it)", file=sys.stderr)
    return psi


def _ik_gradient(
    chain: Chain, target: torch.Tensor, args, mode: str = "pose"
) -> tuple[torch.Tensor, torch.Tensor, list[str]]:
    from ..ik import solve

    generator = torch.Generator().manual_seed(args.seed)
    result = solve(chain, target, mode=mode, generator=generator, pos_tol=POS_TOL, rot_tol=ROT_TOL)
    return result.q[None], result.success[None], ["lm"]


# ---------------------------------------------------------------- robots
def run_robots(args: argparse.Namespace) -> int:
    """``iiwa-torch robots [NAME | --urdf FILE]``: the presets, or one preset's DH table, limits and
    speeds, or the joints a URDF file's path gives."""
    if args.urdf is not None or args.end_link is not None:
        if args.name is not None:
            raise UsageError("give a preset NAME or --urdf, not both")
        return _print_joints(chain_of(args), args.json)
    if args.name is None:
        chains = [fn() for fn in robots.PRESETS.values()]
        if args.json:
            print_json([{"name": c.name, "joints": c.n_joints, "convention": c.convention.value} for c in chains])
            return 0
        rows = [
            [c.name, str(c.n_joints), c.convention.value, "yes" if c.velocity_limits is not None else "no"]
            for c in chains
        ]
        table("robot presets (iiwa-torch robots NAME for the DH table)", ["name", "joints", "DH", "speed limits"], rows)
        return 0
    if args.name not in robots.PRESETS:
        raise UsageError(f"unknown robot {args.name!r}; presets: {', '.join(robots.PRESETS)}")
    chain = robots.PRESETS[args.name]()
    vel = [None] * chain.n_joints if chain.velocity_limits is None else chain.velocity_limits.tolist()
    lows, highs = chain.limits.tolist()
    if args.json:
        print_json(
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
    table(f"{chain.name}: {chain.convention.value} DH", cols, rows)
    return 0


def _print_joints(chain: Chain, as_json: bool) -> int:
    """``robots --urdf``: each joint's kind, axis (in its own frame), child link, limits and speed."""
    vel = [None] * chain.n_joints if chain.velocity_limits is None else chain.velocity_limits.tolist()
    lows, highs = ([x if math.isfinite(x) else None for x in row] for row in chain.limits.tolist())  # continuous: None
    columns = (chain.joint_names, chain.kinds, chain.axes.tolist(), chain.link_names, lows, highs, vel)
    if as_json:
        keys = ("name", "kind", "axis", "child_link", "min", "max", "velocity_limit")
        joints = [dict(zip(keys, (n, k.value, *rest))) for n, k, *rest in zip(*columns)]
        print_json({"name": chain.name, "joints": joints, "base": chain.base.tolist(), "tool": chain.tool.tolist()})
        return 0
    rows = []
    for (name, kind, axis, link, lo, hi, v), k in zip(zip(*columns), joint_scales(chain, rad=False)):
        shown = ["-" if x is None else f"{x / k:.4g}" for x in (lo, hi, v)]
        rows.append([name, kind.value, " ".join(f"{x + 0.0:.3g}" for x in axis), link, *shown])
    cols = ["joint", "kind", "axis", "child link", "min", "max", "speed (per s)"]
    table(f"{chain.name}: {chain.n_joints} joints (deg, or m for a prismatic joint)", cols, rows)
    return 0
