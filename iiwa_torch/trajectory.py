"""Trajectories: quintic joint moves (:func:`jtraj`), straight Cartesian lines (:func:`ctraj`),
IK along a path (:func:`track`) and time scaling (:func:`shortest_duration`, :func:`sampled_duration`).

A time argument ``t`` is a step count ``T >= 2`` (a move of unit duration: velocities per unit
time) or an increasing time vector ``(T,)`` / ``(..., T)`` in seconds (velocities in rad/s).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np
import torch

from . import so3
from .chain import Chain, JointKind
from .checks import (
    all_finite,
    broadcast_shapes,
    check_choice,
    check_finite,
    check_float_tensor,
    check_instance,
    check_memory,
    check_positive,
    is_integer,
    is_number,
)
from .collision import Capsules, World, check_world, clearance
from .dh import DHChain

__all__ = [
    "JointTrajectory",
    "TrackResult",
    "Method",
    "Profile",
    "jtraj",
    "ctraj",
    "path_clearance",
    "track",
    "shortest_duration",
    "sampled_duration",
]

Tensor = torch.Tensor
Method = Literal["gradient", "analytic"]
Profile = Literal["linear", "quintic"]

_PEAK_SPEED = 15 / 8  # peak of d/ds (10 s^3 - 15 s^4 + 6 s^5), at s = 1/2
_LOG_STEPS, _ZOOM_STEPS, _ZOOMS = 24, 9, 3  # analytic tracking: arm-angle offsets 1e-6..pi either side, then zooms
_TRACK_ITERATIONS = 50  # LM iterations of the gradient method at each pose
_BRANCH_FIELDS = ("q", "valid", "reachable", "within_limits", "clearance", "collision_free")


@dataclass(frozen=True)
class JointTrajectory:
    """Samples ``(..., T, n)`` of a joint path: ``q`` (rad), ``qd`` (rad/s), ``qdd`` (rad/s^2), per unit
    time when ``t`` was a step count; ``min_clearance (...)`` (m) over the samples when a world was given."""

    q: Tensor
    qd: Tensor
    qdd: Tensor
    min_clearance: Tensor | None = None


@dataclass(frozen=True)
class TrackResult:
    """IK along paths of ``T`` poses: ``q (..., T, n)`` (rad); per pose ``success`` (tolerances met,
    and ``collision_free`` with a world), ``pos_err`` (m), ``rot_err`` (rad); ``max_step (...)``, the
    largest joint change between steps (rad). With a world: ``clearance (..., T)`` (m),
    ``collision_free`` (``clearance >= margin``) and ``min_clearance (...)``; else None."""

    q: Tensor
    success: Tensor
    pos_err: Tensor
    rot_err: Tensor
    max_step: Tensor
    clearance: Tensor | None = None
    collision_free: Tensor | None = None
    min_clearance: Tensor | None = None


def _times(t, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    """``t`` -> normalised times ``s (..., T)`` in [0, 1] and the duration ``(..., 1)``."""
    if is_integer(t):
        if t < 2:
            raise ValueError(f"t as a number of steps must be at least 2, got {t}")
        return torch.linspace(0, 1, int(t), dtype=dtype, device=device), torch.ones(1, dtype=dtype, device=device)
    if isinstance(t, (bool, str, bytes)) or not isinstance(t, (torch.Tensor, np.ndarray, list, tuple, numbers.Real)):
        raise TypeError(f"t must be a number of steps (an integer >= 2) or a time vector (..., T), "
                        f"got {t!r} ({type(t).__name__})")
    t = torch.as_tensor(t, dtype=dtype, device=device)
    if t.ndim == 0 or t.shape[-1] < 2:
        raise ValueError(f"t must be a step count or a time vector of shape (..., T) with T >= 2, got {tuple(t.shape)}")
    if not torch.isfinite(t).all() or not (t.diff(dim=-1) > 0).all():
        raise ValueError("t must be finite and strictly increasing")
    duration = t[..., -1:] - t[..., :1]
    return (t - t[..., :1]) / duration, duration


def jtraj(
    q0: Tensor,
    q1: Tensor,
    t,
    qd0: Tensor | None = None,
    qd1: Tensor | None = None,
    *,
    chain: Chain | None = None,
    world: World | None = None,
    capsules: Capsules | None = None,
) -> JointTrajectory:
    """Quintic from ``q0`` to ``q1`` ``(..., n)`` (rad, broadcast), zero boundary accelerations.

    ``t``: step count or time vector (module doc); ``qd0, qd1``: boundary velocities (default 0).
    With ``chain`` and ``world``, ``min_clearance`` is the smallest clearance over the samples.
    Differentiable. Raises ``ValueError`` for NaN/inf inputs or a duration too short for finite
    velocities.
    """
    _check_jtraj_inputs(q0, q1, qd0, qd1, t, chain, world, capsules)
    s, duration = _times(t, q0.dtype, q0.device)  # (..., T), (..., 1)
    q, qd, qdd = _quintic(q0, q1, qd0, qd1, s, duration)
    if not (all_finite(qd) and all_finite(qdd)):
        raise ValueError(f"t spans {float(duration.min()):g} s, too short for finite velocities and accelerations "
                         f"in {q0.dtype} (or the motion too large)")  # fmt: skip
    lowest = None if world is None else path_clearance(chain, q, world, capsules).amin(-1)
    return JointTrajectory(q=q, qd=qd, qdd=qdd, min_clearance=lowest)


def _check_jtraj_inputs(q0, q1, qd0, qd1, t, chain, world, capsules) -> None:

    check_world(world, 0.0, capsules)
    if (world is None) != (chain is None):
        raise ValueError("jtraj needs both chain= and world= to report the clearance (World() is the floor at z = 0)")
    for name, value in (("q0", q0), ("q1", q1), ("qd0", qd0), ("qd1", qd1)):
        if value is not None:
            check_float_tensor(value, name, "(..., n)")
            if value.ndim == 0:
                raise ValueError(f"{name} must have shape (..., n), got a scalar")
            check_finite(value, name)
    _check_same_kind(("q0", "q1", "qd0", "qd1"), (q0, q1, qd0, qd1))
    named = {name: x.shape for name, x in zip(("q0", "q1", "qd0", "qd1"), (q0, q1, qd0, qd1)) if x is not None}
    ends = broadcast_shapes(named)
    steps = int(t) if is_integer(t) else (t.shape[-1] if isinstance(t, torch.Tensor) and t.ndim else 0)
    if isinstance(t, torch.Tensor) and t.ndim > 1:  # a time vector per path
        broadcast_shapes({"the batch of t (..., T)": t.shape[:-1], "of q0 (..., n)": ends[:-1]})
    # q, qd, qdd (T, *ends) and the three (T, 6) bases with their factors (T each)
    check_memory(steps * (3 * ends.numel() + 24) * q0.element_size(), f"jtraj with {steps} steps")


def _quintic(q0: Tensor, q1: Tensor, qd0, qd1, s: Tensor, duration: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The quintic at normalised times ``s (..., T)`` of a move lasting ``duration (..., 1)`` ->
    ``q, qd, qdd``, each ``(..., T, n)``."""
    shape = torch.broadcast_shapes(*(x.shape for x in (q0, q1, qd0, qd1) if x is not None), duration.shape)
    delta = (q1 - q0).expand(shape)
    v0 = torch.zeros_like(delta) if qd0 is None else (qd0 * duration).expand(shape)  # d q / d s at the ends
    v1 = torch.zeros_like(delta) if qd1 is None else (qd1 * duration).expand(shape)
    # q(s) = q0 + v0 s + c3 s^3 + c4 s^4 + c5 s^5 for s in [0, 1]: a (T, 6) basis times (6, n)
    # coefficients, one matrix product per output instead of Horner's elementwise chain (trajectory.md).
    zero = torch.zeros_like(delta)
    coeffs = torch.stack(
        [
            q0.expand(shape),
            v0,
            zero,
            10 * delta - 6 * v0 - 4 * v1,
            -15 * delta + 8 * v0 + 7 * v1,
            6 * delta - 3 * (v0 + v1),
        ],
        -2,
    )  # (..., 6, n)
    one, nil = torch.ones_like(s), torch.zeros_like(s)
    s2, s3 = s * s, s * s * s
    basis = torch.stack([one, s, s2, s3, s3 * s, s3 * s2], -1)  # (..., T, 6)
    d_basis = torch.stack([nil, one, 2 * s, 3 * s2, 4 * s3, 5 * s3 * s], -1)
    dd_basis = torch.stack([nil, nil, 2 * one, 6 * s, 12 * s2, 20 * s3], -1)
    scale = duration[..., None]  # (..., 1, 1)
    return basis @ coeffs, d_basis @ coeffs / scale, dd_basis @ coeffs / (scale * scale)


def _check_same_kind(names: tuple[str, ...], values: tuple) -> None:
    """Raise ``TypeError`` unless the given tensors (``None`` skipped) share one dtype and device."""
    given = [(n, v) for n, v in zip(names, values) if v is not None]
    if len({(v.dtype, v.device) for _, v in given}) > 1:
        raise TypeError(f"{', '.join(n for n, _ in given)} must share one dtype and device, got "
                        + ", ".join(f"{n} {v.dtype} on {v.device}" for n, v in given))


def path_clearance(chain: Chain, q: Tensor, world: World, capsules: Capsules | None = None) -> Tensor:
    """Clearance (m) of each sample of paths ``q (..., T, n) -> (..., T)`` (not between samples);
    the world's batch shape broadcasts with ``(...)``."""
    check_instance(world, World, "world")
    step = world.map_batch(lambda t, k: t.unsqueeze(t.ndim - k))  # a dim for T before the obstacle dims
    return clearance(chain, q, step, capsules)


def ctraj(T0: Tensor, T1: Tensor, t, *, profile: Profile = "linear") -> Tensor:
    """Straight line from pose ``T0`` to ``T1`` ``(..., 4, 4)`` -> ``(..., T, 4, 4)``, differentiable.

    Position on the segment, rotation ``R0 exp(s log(R0^T R1))`` (slerp). ``profile``: ``"linear"``
    (constant rates) or ``"quintic"`` (``s`` follows :func:`jtraj`: starts and stops at rest).
    """
    check_choice(profile, get_args(Profile), "profile")
    so3.check_rigid(T0, "T0")
    so3.check_rigid(T1, "T1")
    _check_same_kind(("T0", "T1"), (T0, T1))
    ends = broadcast_shapes({"T0": T0.shape, "T1": T1.shape})
    if isinstance(t, torch.Tensor) and t.ndim > 1:  # a time vector per path
        broadcast_shapes({"the batch of t (..., T)": t.shape[:-1], "of T0 (..., 4, 4)": ends[:-2]})
    s, _ = _times(t, T0.dtype, T0.device)
    if profile == "quintic":
        zero = torch.zeros(1, dtype=T0.dtype, device=T0.device)
        s = jtraj(zero, torch.ones_like(zero), s).q[..., 0]  # s already spans [0, 1] in unit time
    s = s[..., None]  # (..., T, 1)
    p0, p1 = T0[..., None, :3, 3], T1[..., None, :3, 3]  # (..., 1, 3)
    r0 = T0[..., None, :3, :3]
    w = so3.log(T0[..., :3, :3].transpose(-1, -2) @ T1[..., :3, :3])[..., None, :]  # body-frame rotation vector
    rot = r0 @ so3.exp(s * w)  # (..., T, 3, 3)
    pos = p0 + s * (p1 - p0)  # (..., T, 3)
    top = torch.cat([rot, pos[..., None]], -1)
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=T0.dtype, device=T0.device).expand(*top.shape[:-2], 1, 4)
    return torch.cat([top, bottom], -2)


def shortest_duration(chain: Chain, q0: Tensor, q1: Tensor, *, speed_scale: float = 1.0) -> Tensor:
    """Shortest duration (s) ``(...)`` of a rest-to-rest :func:`jtraj` from ``q0`` to ``q1`` ``(..., n)``
    within ``speed_scale * chain.velocity_limits``: ``max_j 15/8 |q1_j - q0_j| / vmax_j``."""
    vmax = _speed_limits(chain, speed_scale, q0=q0, q1=q1)
    return (_PEAK_SPEED * (q1 - q0).abs() / vmax).amax(-1)


def sampled_duration(chain: Chain, q: Tensor, *, speed_scale: float = 1.0) -> Tensor:
    """Shortest duration (s) ``(...)`` of a path sampled at even times, ``q (..., T, n)`` (e.g. from
    :func:`track`), whose finite-difference speeds stay within ``speed_scale * chain.velocity_limits``."""
    vmax = _speed_limits(chain, speed_scale, q=q)
    if q.ndim < 2 or q.shape[-2] < 2:
        raise ValueError(f"q must have shape (..., T, {chain.n_joints}) with T >= 2, got {tuple(q.shape)}")
    dt = (q.diff(dim=-2).abs() / vmax).amax((-2, -1))
    return (q.shape[-2] - 1) * dt


def _speed_limits(chain: Chain, speed_scale: float, **joint_values: Tensor) -> Tensor:
    """``speed_scale * chain.velocity_limits`` in the dtype of ``joint_values`` (checked first)."""
    check_instance(chain, Chain, "chain")
    for name, q in joint_values.items():
        chain.check_q(q, name)
    dtype = next(iter(joint_values.values())).dtype
    if chain.velocity_limits is None:
        raise ValueError(f"chain {chain.name!r} has no velocity_limits; pass them to Chain to time-scale")
    if not is_number(speed_scale) or not 0 < speed_scale <= 1:
        raise ValueError(f"speed_scale must be a number in (0, 1], got {speed_scale!r}")
    return speed_scale * chain.velocity_limits.to(dtype)


def track(
    chain: Chain,
    poses: Tensor,
    q0: Tensor,
    *,
    method: Method = "gradient",
    pos_tol: float = 1e-7,
    rot_tol: float = 1e-6,
    rest_gain: float = 0.0,
    world: World | None = None,
    margin: float = 0.0,
    capsules: Capsules | None = None,
) -> TrackResult:
    """IK at each pose of paths ``poses (..., T, 4, 4)`` (m), each step started from the last answer.

    ``q0 (..., n)``: the start, normally reaching ``poses[..., 0]``. ``method="gradient"``:
    :func:`iiwa_torch.ik.solve` with one seed, the previous answer (``rest_gain`` pulls the iiwa
    toward ``q0`` in the null space). ``"analytic"``: the closed-form branch nearest the previous
    answer (Pieper for 6R arms; for the iiwa a log-spaced, then zoomed, search of arm angles near
    the last one, else :func:`~iiwa_torch.ik.analytic.iiwa_solve` over the whole circle).
    ``pos_tol, rot_tol``: success tolerances (m, rad). With ``world``, a step must clear
    ``margin`` (m); the analytic method keeps the nearest in-limit solution where none does.
    A large ``max_step`` in the result means a branch switch or a failure along the way.
    """
    batch, options = _check_track(chain, poses, q0, method, pos_tol, rot_tol, rest_gain, world, margin, capsules)
    if method == "gradient":
        q = _track_gradient(chain, poses, q0, batch, options, world, margin, capsules)
    else:
        q = _track_loop(poses, q0, _analytic_stepper(chain, pos_tol, rot_tol, batch, world, margin, capsules))
    return _track_result(chain, q, poses, pos_tol, rot_tol, world, margin, capsules)


def _check_track(chain, poses, q0, method, pos_tol, rot_tol, rest_gain, world, margin, capsules):
    """-> the paths' batch shape, and the gradient method's :class:`~iiwa_torch.ik.SolveOptions` (else None)."""
    from .ik import SolveOptions

    check_instance(chain, Chain, "chain")
    check_choice(method, get_args(Method), "method")
    check_world(world, margin, capsules)
    check_positive(pos_tol, "pos_tol")
    check_positive(rot_tol, "rot_tol")
    if method == "analytic" and rest_gain != 0:  # the gradient solver checks it in [0, 1]
        raise ValueError(f"rest_gain applies to method='gradient' only, got {rest_gain!r} with method='analytic'")
    options = None
    if method == "gradient":  # one seed: the previous answer, no random restart elsewhere
        options = SolveOptions(pos_tol=pos_tol, rot_tol=rot_tol, seeds=1, iterations=_TRACK_ITERATIONS,
                               rest_gain=rest_gain)
    so3.check_rigid(poses, "poses")
    chain.check_q(q0, "q0")
    if poses.ndim < 3 or poses.shape[-3] == 0:
        raise ValueError(f"poses must have shape (..., T, 4, 4) with T >= 1, got {tuple(poses.shape)}")
    try:
        batch = torch.broadcast_shapes(poses.shape[:-3], q0.shape[:-1])
    except RuntimeError:
        raise ValueError(
            f"the batch shapes of poses {tuple(poses.shape)} (..., T, 4, 4) and q0 {tuple(q0.shape)} (..., n) "
            "do not broadcast"
        ) from None
    return batch, options


def _track_gradient(chain: Chain, poses: Tensor, q0: Tensor, batch: torch.Size, options, world, margin, capsules):
    """The gradient method's joint path ``(..., T, n)``."""
    from .ik import lm_compiled, solve

    poses = poses.expand(*batch, *poses.shape[-3:])  # one path per start when q0 has the larger batch
    if lm_compiled.handles(poses, q0, q0, world, batch.numel()):
        # a few CPU paths: every step of the loop below in one call, the same answers
        return lm_compiled.track_compiled(chain, poses, q0, options)
    rest = q0.to(poses.dtype) if options.rest_gain else None

    def step(pose: Tensor, q_prev: Tensor) -> Tensor:
        return solve(chain, pose, q_prev, rest=rest, world=world, margin=margin, capsules=capsules,
                     options=options).q

    return _track_loop(poses, q0, step)


def _track_loop(poses: Tensor, q0: Tensor, step) -> Tensor:
    """``step(pose (..., 4, 4), q_prev (..., n)) -> q`` at every pose in turn, from ``q0`` -> ``(..., T, n)``."""
    q_prev = q0.to(poses.dtype)
    qs = []
    for k in range(poses.shape[-3]):  # sequential by nature: each step starts from the last
        q_prev = step(poses[..., k, :, :], q_prev)
        qs.append(q_prev)
    return torch.stack(qs, -2)


def _track_result(chain: Chain, q: Tensor, poses: Tensor, pos_tol: float, rot_tol: float, world, margin: float,
                  capsules) -> TrackResult:
    """Score a joint path ``q (..., T, n)`` against ``poses``."""
    pos_vec, rot_vec = so3.pose_error(chain.fk(q), poses)
    pos_err, rot_err = pos_vec.norm(dim=-1), rot_vec.norm(dim=-1)
    steps = q.diff(dim=-2).abs().amax(-1)  # (..., T - 1)
    max_step = steps.amax(-1) if steps.shape[-1] else torch.zeros(q.shape[:-2], dtype=q.dtype, device=q.device)
    success = (pos_err <= pos_tol) & (rot_err <= rot_tol)
    clear = free = lowest = None
    if world is not None:
        clear = path_clearance(chain, q, world, capsules)
        free = clear >= margin
        success, lowest = success & free, clear.amin(-1)
    return TrackResult(q=q, success=success, pos_err=pos_err, rot_err=rot_err, max_step=max_step, clearance=clear,
                       collision_free=free, min_clearance=lowest)


def _nearest(chain: Chain, sol, q_prev: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The branch of ``sol.q (..., B, n)`` nearest ``q_prev (..., n)``: valid ones first, then reachable
    in-limit ones, then other reachable ones (clamped) -> ``q``, its index, valid, reachable and in limits.
    Each turning joint is taken at its turn nearest ``q_prev`` that is within its limits: the closed forms
    return angles in [-pi, pi], and a wrist crossing pi would otherwise flip a whole turn."""
    prev = q_prev[..., None, :]
    near = prev + torch.remainder(sol.q - prev + math.pi, 2 * math.pi) - math.pi
    lo, hi = chain.geometry(sol.q.dtype).limits
    turning = torch.tensor([k is not JointKind.PRISMATIC for k in chain.kinds], device=near.device)
    sol = dataclasses.replace(sol, q=torch.where(turning & (near >= lo) & (near <= hi), near, sol.q))
    dist = (sol.q - prev).square().sum(-1)  # (..., B)
    penalty = 1e6 * (~sol.valid).to(dist.dtype) + 2e6 * (~sol.within_limits).to(dist.dtype)
    key = torch.where(sol.reachable, dist + penalty, torch.full_like(dist, math.inf))
    best = key.argmin(-1)
    q = sol.q.gather(-2, best[..., None, None].expand(*best.shape, 1, chain.n_joints)).squeeze(-2)

    def at_best(mask: Tensor) -> Tensor:
        return mask.expand_as(dist).gather(-1, best[..., None]).squeeze(-1)

    return chain.clamp(q), best, at_best(sol.valid), at_best(sol.reachable & sol.within_limits)


def _near_arm_angle(chain: Chain, pose: Tensor, q_prev: Tensor, world: World | None, margin: float, capsules):
    """iiwa: the solution of ``pose (B, 4, 4)`` nearest ``q_prev (B, 7)`` over arm-angle offsets from 1e-6
    to pi on a log scale, then ``_ZOOMS`` finer rounds (0 in each, so the pick never gets farther).
    Near a shoulder or wrist alignment the nearest solution sits in an arm-angle window of about a
    milliradian, which an even grid misses. -> ``q``, ``found`` (valid), reachable and in limits."""
    from .ik import analytic

    steps = torch.logspace(-6, math.log10(math.pi), _LOG_STEPS, dtype=pose.dtype, device=pose.device)
    offsets = torch.cat([-steps.flip(0), torch.zeros_like(steps[:1]), steps]).expand(pose.shape[0], -1)  # (B, K)
    unit = torch.linspace(-1, 1, _ZOOM_STEPS, dtype=pose.dtype, device=pose.device)
    ratio = steps[1] / steps[0] - 1  # relative spacing of the log grid
    centre = analytic.iiwa_arm_angle(chain, q_prev)
    width = None
    for _ in range(1 + _ZOOMS):
        sol = analytic.iiwa(chain, pose, centre[:, None] + offsets, world=world, margin=margin, capsules=capsules)
        flat = dataclasses.replace(
            sol, **{f: getattr(sol, f).flatten(1, 2) for f in _BRANCH_FIELDS if getattr(sol, f) is not None}
        )
        q, best, found, usable = _nearest(chain, flat, q_prev)
        chosen = offsets.gather(-1, (best // 8)[:, None])  # (B, 1): 8 branches per arm angle
        centre = centre + chosen[:, 0]
        width = ratio * chosen.abs() + 1e-6 if width is None else 2 * width / (_ZOOM_STEPS - 1)
        offsets = unit * width
    return q, found, usable


def _analytic_stepper(
    chain: Chain,
    pos_tol: float,
    rot_tol: float,
    batch: torch.Size,
    world: World | None,
    margin: float,
    capsules: Capsules | None,
):
    from .ik import analytic
    from .ik.analytic.srs_sweep import Obstacles

    if not isinstance(chain, DHChain) or chain.n_joints not in (6, 7):
        raise ValueError(
            f"method='analytic' tracks DH chains of 7-joint iiwa-like arms and 6R spherical-wrist arms; "
            f"{chain.name!r} is a {type(chain).__name__} of {chain.n_joints} joints (use method='gradient')"
        )
    if chain.n_joints == 6:
        return lambda pose, q_prev: _nearest(
            chain, analytic.pieper(chain, pose, world=world, margin=margin, capsules=capsules), q_prev
        )[0]
    obstacles = None if world is None else Obstacles.for_batch(world, margin, capsules, batch)
    rows_world = None if obstacles is None else obstacles.world  # one row per path (or shared)

    def step(pose: Tensor, q_prev: Tensor) -> Tensor:
        target = pose.expand(*batch, 4, 4).reshape(-1, 4, 4)
        q_ref = q_prev.expand(*batch, 7).reshape(-1, 7)
        q, found, usable = _near_arm_angle(chain, target, q_ref, rows_world, margin, capsules)
        if not found.all():  # nothing valid near the last arm angle: the whole circle
            lost = (~found).nonzero().squeeze(-1)
            extra = (
                {}
                if obstacles is None
                else {"world": obstacles.take(lost).world, "margin": margin, "capsules": capsules}
            )
            far = analytic.iiwa_solve(chain, target[lost], q_ref[lost], pos_tol=pos_tol, rot_tol=rot_tol, **extra)
            # keep a colliding near solution rather than jump to another that also fails
            take = far.success | ~usable[lost]
            q = q.index_put((lost,), torch.where(take[:, None], far.q, q[lost]))
        return q.reshape(*batch, 7)

    return step
