"""A features extractor for goal-conditioned observations: adds the goal error at several scales.

An MLP fed ``achieved_goal`` and ``desired_goal`` separately must learn to subtract them
before it can act on a millimetre error: a 3 mm difference between two numbers of order
0.5 m is lost next to everything else. This extractor computes ``desired - achieved``
inside the network and appends it clipped at several scales, ``clip(delta / s, -1, 1)``,
so the error is visible both far from the goal (s = 0.3 m) and close to it (s = 3 mm).

Because the difference is computed inside the network, it stays correct when HER relabels
``desired_goal`` in the replay buffer. Keep the goal keys out of ``VecNormalize``
(``norm_obs_keys: [observation]``) so the difference is taken in metres.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor

from envs.goals import decode_pose_goal
from iiwa_torch import so3
from iiwa_torch.ik.dls import dls_step_batch_last


class GoalDeltaExtractor(BaseFeaturesExtractor):
    """Concatenate ``observation``, both goals and ``clip((desired - achieved) / s, -1, 1)`` per scale.

    Args:
        observation_space: a ``Dict`` with ``observation``, ``achieved_goal`` and ``desired_goal`` boxes.
        scales: the scales ``s`` (in the goal's units: metres for positions), all > 0.

    Output: ``(batch, obs_dim + 2 * goal_dim + len(scales) * goal_dim)`` features.
    """

    def __init__(self, observation_space: spaces.Dict, scales: Sequence[float] = (0.3, 0.03, 0.003)):
        keys = ("observation", "achieved_goal", "desired_goal")
        if not isinstance(observation_space, spaces.Dict) or any(k not in observation_space.spaces for k in keys):
            raise TypeError(f"GoalDeltaExtractor needs a Dict observation space with keys {keys}, "
                            f"got {observation_space}")
        if len(scales) == 0 or any(float(s) <= 0 for s in scales):
            raise ValueError(f"scales must be a non-empty list of positive numbers, got {list(scales)}")
        obs_dim = int(observation_space["observation"].shape[0])
        goal_dim = int(observation_space["desired_goal"].shape[0])
        super().__init__(observation_space, obs_dim + (2 + len(scales)) * goal_dim)
        self.register_buffer("inv_scales", 1.0 / torch.tensor([float(s) for s in scales]).unsqueeze(-1))  # (S, 1)

    def forward(self, observations: dict[str, torch.Tensor]) -> torch.Tensor:
        achieved, desired = observations["achieved_goal"], observations["desired_goal"]  # (B, G)
        delta = desired - achieved  # (B, G)
        scaled = (delta.unsqueeze(-2) * self.inv_scales).clamp(-1.0, 1.0).flatten(-2)  # (B, S * G)
        return torch.cat([observations["observation"], achieved, desired, scaled], dim=-1)


NUMPY_ROWS = 16  # hildreth: up to this many rows on the CPU with nothing to differentiate, in numpy


def hildreth(x: torch.Tensor, normal: torch.Tensor, scaled: torch.Tensor, bound: torch.Tensor,
             sweeps: int = 5) -> torch.Tensor:
    """``x (..., n)`` moved as little as possible in a metric ``M`` so that ``normal_k . x >= bound_k``
    for each of K constraints: ``normal (..., K, n)``, ``scaled = M^-1 normal`` (the same for the
    Euclidean metric), ``bound (..., K)``. Hildreth's method: coordinate ascent on the dual, one
    constraint at a time, ``sweeps`` times over (exact after one sweep for one constraint; a zero
    ``normal`` with a negative bound is a constraint that never acts). Differentiable. Up to
    ``NUMPY_ROWS`` rows on the CPU with nothing to differentiate (one env's policy step) the same
    formulas run on numpy views, each op a fraction of a torch op's cost (the sums' rounding may
    differ in the last bit)."""
    given = (x, normal, scaled, bound)
    grad = torch.is_grad_enabled() and any(t.requires_grad for t in given)
    if not grad and all(t.is_cpu for t in given) and x.numel() <= NUMPY_ROWS * x.shape[-1]:
        return torch.from_numpy(_hildreth(*(t.numpy() for t in given), sweeps, np))
    return _hildreth(x, normal, scaled, bound, sweeps, torch)


def _hildreth(x, normal, scaled, bound, sweeps: int, xp):
    """:func:`hildreth` on torch tensors or numpy arrays (``xp``: ``torch`` or ``numpy``)."""
    curvature = (normal * scaled).sum(-1).clip(min=1e-12)  # (..., K)
    multipliers = [xp.zeros_like(curvature[..., 0])] * normal.shape[-2]  # Lagrange's, >= 0
    for _ in range(sweeps):
        for k, m in enumerate(multipliers):
            change = (bound[..., k] - (normal[..., k, :] * x).sum(-1)) / curvature[..., k]
            change = xp.maximum(change, -m)  # a constraint can let go, never pull
            multipliers[k] = m + change
            x = x + scaled[..., k, :] * change[..., None]
    return x


def damper_constraints(distance: torch.Tensor, gradient: torch.Tensor, xi: float, safe: float,
                       influence: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The velocity damper of Faverjon and Tournassoud, linearised, as :func:`hildreth`'s constraints
    on a joint step ``dq`` (rad): each capsule within ``influence`` (m) of something may close at most
    the share ``xi`` of its gap above ``safe`` (m) in one step, ``gradient_k . dq >= -xi (distance_k -
    safe)``. ``distance (B, K)`` (m), ``gradient (B, K, n)`` (m/rad) -> ``normal (B, K, n)`` (zero for
    capsules out of reach) and ``bound (B, K)`` (m)."""
    near = distance < influence
    return torch.where(near[..., None], gradient, 0.0), torch.where(near, -xi * (distance - safe), -1.0)


def velocity_damper(dq: torch.Tensor, jac: torch.Tensor, damping_sq: torch.Tensor, distance: torch.Tensor,
                    gradient: torch.Tensor, xi: float, safe: float, influence: float, sweeps: int = 5) -> torch.Tensor:
    """Joint steps ``dq (B, L, n)`` (rad), one per damping ``damping_sq (L,)``, changed as little as
    possible in the metric ``H = J^T J + damping I`` of the DLS step (``jac (B, m, n)``) to meet
    :func:`damper_constraints` (``distance (B, K)``, ``gradient (B, K, n)``, ``xi``, ``safe``,
    ``influence``), by :func:`hildreth`."""
    n = jac.shape[-1]
    H = (jac.mT @ jac)[:, None] + damping_sq[:, None, None] * torch.eye(n, dtype=jac.dtype, device=jac.device)
    normal, bound = damper_constraints(distance, gradient, xi, safe, influence)
    normal = normal[:, None].expand(-1, dq.shape[1], -1, -1)  # (B, L, K, n)
    return hildreth(dq, normal, torch.linalg.solve(H, normal.mT).mT, bound[:, None], sweeps)


class JointGoalExtractor(GoalDeltaExtractor):
    """:class:`GoalDeltaExtractor` plus joint-space features of the position error, from the robot's Jacobian.

    The network sees the goal error in metres, but acts in joint space, through a Jacobian that
    changes over the workspace and loses rank near the stretched arm. This extractor computes,
    for each damping ``lambda`` (m), the damped-least-squares joint step that would remove the
    position error ``e = desired[:3] - achieved[:3]`` (m):

        dq = J_p^T (J_p J_p^T + lambda^2 I)^-1 e        (rad; J_p: the Jacobian's position rows, m/rad)

    expressed in actions, ``u = dq / max_step`` (``max_step``: rad per step at ``|a| = 1``), and
    shrunk as a whole to ``u / max(1, max_i |u_i|)`` so that it stays in ``[-1, 1]`` with its
    direction kept. It also appends ``J_p^T e / |e|`` (m; the steepest-descent direction, defined
    at any rank), each joint's place within its limits, ``2 (q - lower) / (upper - lower) - 1``,
    and the distance ``|e|`` (m).

    Pose goals (9 numbers: position, then the first two columns of the rotation matrix) use
    the whole Jacobian, its rotation rows weighted by ``w = orientation_weight`` (m/rad), and
    the error ``e = [e_p; w e_r]`` with ``e_r = log(R_desired R_achieved^T)`` (rotation vector
    in the world frame, rad): the same formulas with 6 rows, and ``|e|`` combines both.

    Everything is computed inside the network from the observation, so it stays correct when
    HER relabels ``desired_goal``. It needs the raw observation: its first ``2 nj`` entries are
    ``cos q``, ``sin q`` (``q = atan2(sin q, cos q)``), so train without ``VecNormalize`` (the
    observation entries are all O(1): cosines, sines, velocities in ``[-1, 1]``, metres).

    With ``avoidance`` (``{"xi", "safe", "influence"}``, see :func:`damper_constraints`) and an env
    that observes its clearances (``observe_clearance=True``; ``clearance_rows = (first column, K)``
    of them in ``observation``), every DLS step is first changed by :func:`velocity_damper` to keep
    each capsule clear, then shrunk; and the damper's constraints in actions (``normal * max_step``,
    m, then ``bound``, m) are appended, ``K (nj + 1)`` columns from ``damper_columns[0]``, for a
    policy head that keeps its whole action clear (:class:`train.residual.ResidualDLSPolicy`).

    Args:
        observation_space: a ``Dict`` with ``observation`` (starting with ``cos q, sin q``),
            ``achieved_goal`` and ``desired_goal`` (3 numbers, a position in m, or 9, a pose).
        robot: name of the chain in ``iiwa_torch.robots.PRESETS`` (the env's robot).
        max_step: ``(nj,)`` joint motion per step at full action, rad (the env task's ``max_step``).
        scales: goal-delta scales, m (see :class:`GoalDeltaExtractor`).
        dampings: the ``lambda`` values, m, all > 0.
        orientation_weight: ``w``, m/rad (> 0), for pose goals only.
        clearance_rows: where the capsules' clearances and gradients start in ``observation`` and
            the number K of capsules (filled in from the env by ``train.train``); None: not observed.
        avoidance: the velocity damper's ``xi`` (in (0, 1]), ``safe`` and ``influence`` (m), or None.
        limit_rounds: how many times a DLS step is solved again without the joints it would push
            past their limits (:meth:`shrunk_step`; 0: never).

    Output: ``(batch, GoalDeltaExtractor's features + (len(dampings) + 2) * nj + 1)`` features.
    """

    def __init__(self, observation_space: spaces.Dict, robot: str = "iiwa14",
                 max_step: Sequence[float] | None = None, scales: Sequence[float] = (0.3, 0.03, 0.003),
                 dampings: Sequence[float] = (0.1, 0.01), orientation_weight: float = 0.5,
                 clearance_rows: Sequence[int] | None = None, avoidance: Mapping[str, float] | None = None,
                 limit_rounds: int = 0):
        from iiwa_torch.robots import PRESETS

        super().__init__(observation_space, scales)
        if robot not in PRESETS:
            raise ValueError(f"robot must be one of {sorted(PRESETS)}, got {robot!r}")
        chain = PRESETS[robot]()
        nj = chain.n_joints
        if max_step is None or len(max_step) != nj or any(float(s) <= 0 for s in max_step):
            raise ValueError(f"max_step must be {nj} positive numbers (rad per step), got {max_step!r}")
        if len(dampings) == 0 or any(float(d) <= 0 for d in dampings):
            raise ValueError(f"dampings must be a non-empty list of positive numbers (m), got {list(dampings)}")
        if not float(orientation_weight) > 0:
            raise ValueError(f"orientation_weight must be a positive number (m/rad), got {orientation_weight!r}")
        obs_dim = int(observation_space["observation"].shape[0])
        goal_dim = int(observation_space["desired_goal"].shape[0])
        if obs_dim < 2 * nj or goal_dim not in (3, 9):
            raise ValueError(f"robot {robot!r} has {nj} joints: the observation needs >= {2 * nj} entries "
                             f"(cos q, sin q) and the goal 3 (a position) or 9 (a pose) numbers; got {obs_dim} "
                             f"and {goal_dim}")
        if avoidance is not None:
            if clearance_rows is None:
                raise ValueError("avoidance needs the env's clearances: make the env with observe_clearance=True")
            if set(avoidance) != {"xi", "safe", "influence"} or not 0 < float(avoidance["xi"]) <= 1 \
                    or not 0 <= float(avoidance["safe"]) < float(avoidance["influence"]):
                raise ValueError("avoidance must be {xi: in (0, 1], safe: >= 0, influence: > safe} (m), "
                                 f"got {dict(avoidance)!r}")
            start, k = (int(c) for c in clearance_rows)
            if start < 3 * nj or start + k * (1 + nj) > obs_dim:
                raise ValueError(f"clearance_rows {list(clearance_rows)} lie outside the observation ({obs_dim})")
        if isinstance(limit_rounds, bool) or not isinstance(limit_rounds, int) or limit_rounds < 0:
            raise ValueError(f"limit_rounds must be an int >= 0, got {limit_rounds!r}")
        self.limit_rounds = limit_rounds
        self.avoidance = None if avoidance is None else {key: float(v) for key, v in avoidance.items()}
        self.clearance_rows = None if clearance_rows is None else tuple(int(c) for c in clearance_rows)
        self.pose = goal_dim == 9
        self.orientation_weight = float(orientation_weight)
        self.chain = chain  # float64 buffers; the joint features are computed in float64
        self.nj = nj
        #: columns of the output holding the DLS step (in actions) at the first damping
        self.step_columns = (self._features_dim, self._features_dim + nj)
        self._features_dim += (len(dampings) + 2) * nj + 1
        #: the column of the distance |e| (m)
        self.distance_column = self._features_dim - 1
        #: ``(first column, K)`` of the damper's constraints in actions, or None without avoidance
        self.damper_columns = None
        if avoidance is not None:
            self.damper_columns = (self._features_dim, self.clearance_rows[1])
            self._features_dim += self.clearance_rows[1] * (nj + 1)
        self.register_buffer("max_step", torch.tensor([float(s) for s in max_step], dtype=torch.float64))
        self.register_buffer("damping_sq", torch.tensor([float(d) ** 2 for d in dampings], dtype=torch.float64))

    def shrunk_step(self, q: torch.Tensor, jac: torch.Tensor, error: torch.Tensor) -> torch.Tensor:
        """The DLS step per damping in actions, shrunk into ``[-1, 1]``: ``q (B, nj)`` rad, ``jac (B, k, nj)``,
        ``error (B, k)`` -> ``(B, L, nj)``. With ``limit_rounds``, a joint that the step would push past its
        limit is held still and the step solved again without it, up to that many times (the arm's
        other joints then carry the motion, instead of the step being clamped at the limit)."""
        b, n, m = q.shape[0], self.nj, jac.shape[-2]
        size = len(self.damping_sq)
        # dls_step's layout and kernel, unchecked: the inputs are this network's own
        J = jac.unsqueeze(1).expand(b, size, m, n).reshape(-1, m, n).permute(1, 2, 0)  # (m, nj, B L)
        rhs = error.unsqueeze(1).expand(b, size, m).reshape(-1, m).T[:, None]  # (m, 1, B L)
        damping, tiny = self.damping_sq.repeat(b), torch.finfo(q.dtype).tiny
        dq = dls_step_batch_last(J, rhs, damping, tiny)[:, 0].T.reshape(b, size, n)  # (B, L, nj) rad
        if self.limit_rounds:
            lower, upper = self.chain.limits.to(q.dtype)
            free = torch.ones_like(dq)
            for _ in range(self.limit_rounds):
                step = dq / (dq / self.max_step).abs().amax(-1, keepdim=True).clamp(min=1.0)
                end = q.unsqueeze(1) + step
                blocked = ((end > upper) & (step > 0)) | ((end < lower) & (step < 0))
                if not bool((blocked & (free > 0)).any()):
                    break
                free = free * ~blocked
                dq = dls_step_batch_last(J, rhs, damping, tiny, free.reshape(-1, n).T)[:, 0].T.reshape(b, size, n)
        u = dq / self.max_step
        return u / u.abs().amax(-1, keepdim=True).clamp(min=1.0)

    def joint_features(self, q: torch.Tensor, error: torch.Tensor,
                       clearance: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        """``q (B, nj)`` rad and ``error (B, k)`` -> ``(B, (len(dampings) + 2) * nj + 1)`` float64: the shrunk
        DLS steps in actions per damping, ``J^T e / |e|`` (m), the place within the limits, ``|e|`` (m).

        ``k = 3``: a position error (m), ``J = J_p``; ``k = 6``: ``[e_p; w e_r]`` (m), ``J = [J_p; w J_r]``.
        ``clearance``: the capsules' distances ``(B, K)`` (m) and gradients ``(B, K, nj)`` (m/rad), for
        ``avoidance``."""
        q, e = q.double(), error.double()
        k = e.shape[-1]
        jac = self.chain.jacobian(q)  # (B, 6, nj): m/rad, then rad/rad
        jp = jac[..., :3, :] if k == 3 else torch.cat([jac[..., :3, :], self.orientation_weight * jac[..., 3:, :]], -2)
        u = self.shrunk_step(q, jp, e)  # (B, L, nj) in actions
        if self.avoidance is not None:
            u = velocity_damper(u * self.max_step, jp, self.damping_sq, *clearance, **self.avoidance) / self.max_step
            u = u / u.abs().amax(-1, keepdim=True).clamp(min=1.0)
        distance = e.norm(dim=-1, keepdim=True)  # (B, 1)
        grad = (jp.transpose(-1, -2) @ e.unsqueeze(-1)).squeeze(-1) / distance.clamp(min=1e-6)
        lower, upper = self.chain.limits.to(q.dtype)
        place = 2.0 * (q - lower) / (upper - lower) - 1.0
        return torch.cat([u.flatten(1), grad, place, distance], dim=-1)

    def forward(self, observations: dict[str, torch.Tensor]) -> torch.Tensor:
        base = super().forward(observations)
        obs, nj = observations["observation"], self.nj
        q = torch.atan2(obs[:, nj : 2 * nj], obs[:, :nj])
        desired, achieved = observations["desired_goal"], observations["achieved_goal"]
        error = desired[:, :3] - achieved[:, :3]
        with torch.no_grad():  # no parameters upstream: features only
            if self.pose:
                rot = decode_pose_goal(desired)[:, :3, :3] @ decode_pose_goal(achieved)[:, :3, :3].transpose(-1, -2)
                error = torch.cat([error.double(), self.orientation_weight * so3.log(rot)], -1)
            clearance, damper = None, []
            if self.avoidance is not None:
                start, k = self.clearance_rows
                rows = obs[:, start : start + k * (1 + nj)].double()
                clearance = rows[:, :k], rows[:, k:].reshape(-1, k, nj)
                normal, bound = damper_constraints(*clearance, **self.avoidance)
                damper = [(normal * self.max_step).flatten(1), bound]
            joint = self.joint_features(q, error, clearance)
        return torch.cat([base, joint.to(base.dtype), *(d.to(base.dtype) for d in damper)], dim=-1)
