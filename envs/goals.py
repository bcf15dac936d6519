"""The reaching task's goals: what is reached (position or pose), the errors, success and reward.

Goals are stored components first, ``(g, ...)``: 3 numbers for a position, 9 for a pose
(the position, then the first two columns of the rotation matrix; the third is their cross
product). :func:`encode_pose_goal` and :func:`decode_pose_goal` are the one place that
layout is written down.
"""

from __future__ import annotations

import math
from enum import Enum

import numpy as np
import torch

from iiwa_torch.checks import broadcast_shapes, check_finite
from iiwa_torch.so3 import check_rigid

from .arrays import NUMPY, TORCH, ArrayOps

__all__ = ["GoalKind", "RewardKind", "GoalRegion", "PANDA_GYM_BOX", "ReachGoals", "encode_pose_goal",
           "decode_pose_goal", "enum_option"]

Tensor = torch.Tensor


class GoalKind(str, Enum):
    """What the end effector must reach: a position, or a position and an orientation."""

    POSITION = "position"
    POSE = "pose"


class RewardKind(str, Enum):
    """``dense``: minus the distance (plus weighted angle for poses); ``sparse``: 0 on success, else -1."""

    DENSE = "dense"
    SPARSE = "sparse"


class GoalRegion(str, Enum):
    """Where goals are drawn. ``joint_limits``: the forward kinematics of configurations drawn within the
    joint limits (collision-free when collisions are checked), so every goal is reachable;
    ``panda_gym``: positions uniform in :data:`PANDA_GYM_BOX`, as panda-gym's Reach task draws them."""

    JOINT_LIMITS = "joint_limits"
    PANDA_GYM = "panda_gym"


#: panda-gym's Reach goals (``goal_range=0.3``: a 0.3 m cube on its table, centred 0.15 m up, its robot's
#: base 0.6 m behind the centre) in the base frame: lower and upper corners, m.
PANDA_GYM_BOX = ((0.45, -0.15, 0.0), (0.75, 0.15, 0.3))


def enum_option(kind: type[Enum], value, name: str):
    """``kind(value)``, or ``ValueError`` naming option ``name`` and the allowed values."""
    try:
        return kind(value)
    except ValueError:
        raise ValueError(f"{name} must be one of {[k.value for k in kind]}, got {value!r}") from None


def encode_pose_goal(pose: Tensor) -> Tensor:
    """Rigid poses ``(..., 4, 4)`` (:func:`iiwa_torch.so3.check_rigid`) -> pose goals ``(..., 9)``:
    position, rotation columns x and y."""
    check_rigid(pose, "pose")
    return _encoded(pose)


def _encoded(pose: Tensor) -> Tensor:
    """:func:`encode_pose_goal` without the check, for the FK's own poses at every step."""
    return torch.cat([pose[..., :3, 3], pose[..., :3, 0], pose[..., :3, 1]], -1)


def _as_goals(goal, name: str, dtype: torch.dtype) -> Tensor:
    """Goals (numpy or torch, any float or int dtype) as a finite tensor of ``dtype``."""
    try:
        g = torch.as_tensor(goal).to(dtype)
    except (TypeError, ValueError, RuntimeError):
        raise TypeError(f"{name} must be a numpy array or tensor of goals, got {goal!r:.60}") from None
    check_finite(g, name)
    return g


def decode_pose_goal(goal) -> Tensor:
    """Pose goals ``(..., 9)`` (numpy or torch) -> poses ``(..., 4, 4)`` float64.

    The two columns are re-orthonormalised (Gram-Schmidt), as observed goals are float32; a zero
    column, or a y column within 1e-6 of x's direction (relative), is a ValueError."""
    g = _as_goals(goal, "goal", torch.float64)
    if g.shape[-1:] != (9,):
        raise ValueError(f"goal must have shape (..., 9) (pose goals), got {tuple(g.shape)}")
    x_norm = g[..., 3:6].norm(dim=-1, keepdim=True)
    x = g[..., 3:6] / x_norm.clamp_min(torch.finfo(torch.float64).tiny)
    y = g[..., 6:9] - (x * g[..., 6:9]).sum(-1, keepdim=True) * x
    y_norm = y.norm(dim=-1, keepdim=True)
    degenerate = (x_norm == 0) | ~(y_norm > 1e-6 * g[..., 6:9].norm(dim=-1, keepdim=True))
    if g.numel() and bool(degenerate.any()):
        index = tuple(degenerate.squeeze(-1).nonzero()[0].tolist())
        raise ValueError(f"goal must hold two non-parallel rotation columns (entries 3:6 and 6:9), got "
                         f"{g[index].tolist()} at index {index}")  # fmt: skip
    y = y / y_norm
    rot = torch.stack([x, y, torch.linalg.cross(x, y)], -1)  # (..., 3, 3)
    pose = torch.zeros(*g.shape[:-1], 4, 4, dtype=torch.float64, device=g.device)
    pose[..., :3, :3], pose[..., :3, 3], pose[..., 3, 3] = rot, g[..., :3], 1.0
    return pose


def _distance_sq(u, w, xp: ArrayOps = TORCH):
    """``(3, ...)`` twice -> ``(...)``: the squared distance, summed over the 3 components in the
    order 0, 1, 2 whatever the layout (3 terms are fewer than a SIMD vector, so torch's
    reduction is a plain sequential loop both for one environment and for a batch:
    bit-identical results; numpy's too). The difference is squared in place: one pass less."""
    return xp.square_(u - w).sum(0)


class ReachGoals:
    """Goal kind, success thresholds and reward of the reaching task (immutable; options
    validated by :class:`envs.core.ReachTask`).

    Args:
        goal: :class:`GoalKind`. reward: :class:`RewardKind`.
        distance_threshold: success radius, m. orientation_threshold: success angle, rad.
        orientation_weight: metres per radian of orientation error in the dense pose reward.
    """

    def __init__(self, goal: GoalKind, reward: RewardKind, distance_threshold: float,
                 orientation_threshold: float, orientation_weight: float) -> None:
        self.kind, self.reward_kind = goal, reward
        self.distance_threshold = distance_threshold
        self.orientation_threshold = orientation_threshold
        self.orientation_weight = orientation_weight
        #: length of ``achieved_goal`` / ``desired_goal``: 3 (position) or 9 (pose)
        self.size = 3 if goal is GoalKind.POSITION else 9
        # The thresholds as 0-dim float32 tensors (the errors are float32): comparing with a
        # Python float wraps it in a new tensor at every call, more than doubling the op's cost.
        # Chordal threshold: ||R1 - R2||_F = 2 sqrt(2) sin(angle / 2), monotone in the angle.
        chord = 8.0 * math.sin(min(orientation_threshold, math.pi) / 2) ** 2
        limits = (distance_threshold, chord)
        self._thresholds = {TORCH.name: tuple(torch.tensor(t, dtype=torch.float32) for t in limits),
                            NUMPY.name: tuple(map(np.float32, limits))}

    def goal_of(self, chain, q: Tensor, trig: tuple[Tensor, Tensor] | None = None) -> Tensor:
        """Joint angles ``(nj, b)``, batch last -> goal vectors ``(g, b)``: the end-effector
        position (the chain's position-only kernel, which reuses ``trig = (cos q, sin q)`` if
        given), or the pose goal."""
        if self.kind is GoalKind.POSITION:
            return chain.position_batch_last(q, trig)
        return _encoded(chain.fk(q.T)).T.contiguous()

    def goal_of_frame(self, frame: tuple, dtype: torch.dtype) -> Tensor:
        """One end-effector frame ``(x, y, z, p)``, 3-tuples of Python floats
        (the second of :func:`iiwa_torch.kinematics.frame_lists`) -> its goal vector ``(g, 1)`` in ``dtype``
        (float32 or float64): :meth:`goal_of` of one configuration, without a torch op."""
        x, y, _, p = frame
        values = p if self.kind is GoalKind.POSITION else p + x + y  # the layout of encode_pose_goal
        return torch.from_numpy(np.array(values, dtype=np.float32 if dtype == torch.float32 else np.float64)[:, None])

    def errors(self, achieved, desired, xp: ArrayOps = TORCH) -> tuple:
        """Goals ``(g, ...)``, components first -> position distance (m), orientation angle
        (rad; ``None`` for position goals) and success, each ``(...)``. Tensors, or numpy
        arrays with ``xp=NUMPY`` (:mod:`envs.arrays`).

        Each environment's numbers are reduced on their own (over the few components), so
        batched and single calls agree bit for bit (tested): what SB3's checker and HER's
        relabelled rewards rely on.
        """
        position = self.kind is GoalKind.POSITION
        distance_threshold, chord_sq_threshold = self._thresholds[xp.name]
        dist = xp.sqrt_(_distance_sq(achieved, desired, xp) if position else
                        _distance_sq(achieved[:3], desired[:3], xp))
        ok = dist < distance_threshold
        if position:
            return dist, None, ok
        xa, ya, xd, yd = achieved[3:6], achieved[6:9], desired[3:6], desired[6:9]
        # ||Ra - Rd||_F^2 over the three columns (z = x cross y) = 8 sin^2(angle / 2)
        za, zd = xp.cross(xa, ya), xp.cross(xd, yd)
        chord_sq = _distance_sq(xa, xd, xp) + _distance_sq(ya, yd, xp) + _distance_sq(za, zd, xp)
        angle = 2 * xp.asin(xp.at_most(xp.sqrt_(chord_sq / 8), 1.0))
        return dist, angle, ok & (chord_sq < chord_sq_threshold)

    def reward_of(self, dist, angle, ok, xp: ArrayOps = TORCH):
        """The reward of :meth:`errors`' outputs, ``(...)`` in their dtype."""
        if self.reward_kind is RewardKind.SPARSE:
            return xp.like(ok, dist) - 1
        return -dist if angle is None else -(dist + self.orientation_weight * angle)

    def reward(self, achieved: Tensor, desired: Tensor) -> Tensor:
        """Batched reward of goals ``(g, ...)`` (components first) -> ``(...)`` in their dtype."""
        return self.reward_of(*self.errors(achieved, desired))

    def compute_reward(self, achieved_goal, desired_goal) -> np.ndarray:
        """The envs' ``compute_reward``: goals ``(..., g)``, numpy or torch -> ``(...)`` float32 numpy."""
        ag = _as_goals(achieved_goal, "achieved_goal", torch.float32)
        dg = _as_goals(desired_goal, "desired_goal", torch.float32).to(ag.device)
        for g, name in ((ag, "achieved_goal"), (dg, "desired_goal")):
            if g.shape[-1:] != (self.size,):
                raise ValueError(f"{name} must have shape (..., {self.size}), got {tuple(g.shape)}")
        shape = broadcast_shapes({"achieved_goal": ag.shape, "desired_goal": dg.shape})
        ag, dg = ag.expand(shape), dg.expand(shape)  # before the components go first: ranks may differ
        with torch.no_grad():
            return self.reward(ag.movedim(-1, 0), dg.movedim(-1, 0)).numpy(force=True)
