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

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor

from envs.goals import decode_pose_goal
from envs.transport import joint_angles
from iiwa_torch import compiled, so3
from iiwa_torch import kinematics as kin
from iiwa_torch.checks import check_bool
from iiwa_torch.ik.dls import dls_step_batch_last, dls_step_numpy


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
        return self.goal_features(observations, torch)

    def goal_features(self, observations: dict, xp=torch):
        """:meth:`forward` on tensors (``xp=torch``) or on numpy arrays (``xp=numpy``)."""
        achieved, desired = observations["achieved_goal"], observations["desired_goal"]  # (B, G)
        delta = desired - achieved  # (B, G)
        inv_scales = self.inv_scales if xp is torch else self.inv_scales.numpy()
        scaled = (delta[..., None, :] * inv_scales).clip(-1.0, 1.0).reshape(delta.shape[0], -1)  # (B, S * G)
        return xp.concatenate([observations["observation"], achieved, desired, scaled], -1)


STEP_BOUNDS = ("shrink", "clip")  # JointGoalExtractor's step_bound
LIMIT_HOLDS = ("still", "limit")  # JointGoalExtractor's limit_hold

NUMPY_ROWS = 16  # up to this many rows on the CPU with nothing to differentiate, in numpy


def numpy_ok(*tensors: torch.Tensor) -> bool:
    """Whether tensors of up to :data:`NUMPY_ROWS` rows (dim 0) may take the numpy paths of this
    module and of :mod:`train.residual`: on the CPU, with nothing to differentiate."""
    return (all(t.is_cpu and t.shape[0] <= NUMPY_ROWS for t in tensors)
            and not (torch.is_grad_enabled() and any(t.requires_grad for t in tensors)))


def shrink(u, xp=torch):
    """``u (..., n)`` (tensor, or numpy array with ``xp=numpy``) divided by ``max(1, max_i |u_i|)``: into
    ``[-1, 1]`` with its direction kept."""
    if xp is np:  # the ufuncs themselves: np.amax and clip wrap them in a few microseconds of Python
        return u / np.maximum(np.maximum.reduce(abs(u), -1), 1.0)[..., None]
    return u / xp.amax(abs(u), -1)[..., None].clip(min=1.0)


def hildreth(x, normal, scaled, bound, sweeps: int = 5):
    """``x (..., n)`` moved as little as possible in a metric ``M`` so that ``normal_k . x >= bound_k``
    for each of K constraints: ``normal (..., K, n)``, ``scaled = M^-1 normal`` (the same for the
    Euclidean metric), ``bound (..., K)``. Hildreth's method: coordinate ascent on the dual, one
    constraint at a time, ``sweeps`` times over (exact after one sweep for one constraint; a zero
    ``normal`` with a negative bound is a constraint that never acts). Differentiable. Numpy arrays
    in, a numpy array out; tensors of up to ``NUMPY_ROWS`` rows (``x.numel() <= NUMPY_ROWS n``) on
    the CPU with nothing to differentiate (one env's policy step) take the same formulas on numpy
    views too, each op a fraction of a torch op's cost (the sums' rounding may differ in the last
    bit; constraints that cannot move ``x`` are skipped and the sweeps stop once one moves nothing,
    which changes no value)."""
    if isinstance(x, np.ndarray):
        return _hildreth(x, normal, scaled, bound, sweeps, np)
    given = (x, normal, scaled, bound)
    grad = torch.is_grad_enabled() and any(t.requires_grad for t in given)
    if not grad and all(t.is_cpu for t in given) and x.numel() <= NUMPY_ROWS * x.shape[-1]:
        return torch.from_numpy(_hildreth(*(t.numpy() for t in given), sweeps, np))
    return _hildreth(x, normal, scaled, bound, sweeps, torch)


def _hildreth(x, normal, scaled, bound, sweeps: int, xp):
    """:func:`hildreth` on torch tensors or numpy arrays (``xp``: ``torch`` or ``numpy``)."""
    acting = range(normal.shape[-2])
    if xp is np:  # a constraint whose scaled normal is zero in every row never moves x: skipped
        acting = np.flatnonzero(scaled.any(-1).reshape(-1, normal.shape[-2]).any(0))
        if not acting.size:
            return x
    curvature = (normal * scaled).sum(-1).clip(min=1e-12)  # (..., K)
    multipliers = {k: xp.zeros_like(curvature[..., 0]) for k in acting}  # Lagrange's, >= 0
    for _ in range(sweeps):
        moved = xp is torch  # numpy: stop after a sweep that moved nothing (the next would repeat it)
        for k, m in multipliers.items():
            change = (bound[..., k] - (normal[..., k, :] * x).sum(-1)) / curvature[..., k]
            change = xp.maximum(change, -m)  # a constraint can let go, never pull
            multipliers[k] = m + change
            x = x + scaled[..., k, :] * change[..., None]
            moved = moved or bool(change.any())
        if not moved:
            break
    return x


def damper_constraints(distance, gradient, xi: float, safe: float, influence: float):
    """The velocity damper of Faverjon and Tournassoud, linearised, as :func:`hildreth`'s constraints
    on a joint step ``dq`` (rad): each capsule within ``influence`` (m) of something may close at most
    the share ``xi`` of its gap above ``safe`` (m) in one step, ``gradient_k . dq >= -xi (distance_k -
    safe)``. ``distance (B, K)`` (m), ``gradient (B, K, n)`` (m/rad), tensors or numpy arrays ->
    ``normal (B, K, n)`` (zero for capsules out of reach) and ``bound (B, K)`` (m)."""
    where = np.where if isinstance(distance, np.ndarray) else torch.where
    near = distance < influence
    return where(near[..., None], gradient, 0.0), where(near, -xi * (distance - safe), -1.0)


def velocity_damper(dq, jac, damping_sq, distance, gradient, xi: float, safe: float, influence: float,
                    sweeps: int = 5):
    """Joint steps ``dq (B, L, n)`` (rad), one per damping ``damping_sq (L,)`` or ``(B, L)``, changed as little as
    possible in the metric ``H = J^T J + damping I`` of the DLS step (``jac (B, m, n)``) to meet
    :func:`damper_constraints` (``distance (B, K)``, ``gradient (B, K, n)``, ``xi``, ``safe``,
    ``influence``), by :func:`hildreth`. Tensors, or numpy arrays (all of them)."""
    xp = np if isinstance(dq, np.ndarray) else torch
    eye = xp.eye(jac.shape[-1], dtype=jac.dtype, device=jac.device)
    H = (jac.mT @ jac)[:, None] + damping_sq[..., None, None] * eye  # (B, L, n, n)
    normal, bound = damper_constraints(distance, gradient, xi, safe, influence)
    normal = normal[:, None]  # (B, 1, K, n): the same constraints for every damping
    return hildreth(dq, normal, xp.linalg.solve(H, normal.mT).mT, bound[:, None], sweeps)


class Avoidance(NamedTuple):
    """The velocity damper's gains (:func:`damper_constraints`): ``xi`` in ``(0, 1]`` (dimensionless),
    ``safe >= 0`` and ``influence > safe`` (m)."""

    xi: float
    safe: float
    influence: float


def _number(value, name: str, low: float = 0.0) -> float:
    """``value`` as a float if it is a finite number >= ``low`` (not a bool), else ValueError naming it."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not low <= value < math.inf:
        raise ValueError(f"{name} must be a finite number >= {low:g}, got {value!r}")
    return float(value)


@dataclass(frozen=True)
class JointSettings:
    """:class:`JointGoalExtractor`'s options beyond the robot, each checked once, on construction (a
    ``ValueError`` naming it); the extractor also takes them as keywords (a config's
    ``features_extractor_kwargs``).

    dampings: the ``lambda`` values, m, all > 0.
    orientation_weight: ``w``, m/rad (> 0), for pose goals only.
    clearance_rows: where the capsules' clearances and gradients start in ``observation`` and
        the number K of capsules (filled in from the env by ``train.train``); None: not observed.
    avoidance: the velocity damper's ``xi`` (in (0, 1]), ``safe`` and ``influence`` (m), or None.
    limit_rounds: how many times a DLS step is solved again without the joints it would push
        past their limits (:meth:`JointGoalExtractor.bounded_step`; 0: never).
    error_damping: ``c >= 0`` (dimensionless): each damping grows with the error, ``lambda + c |e|``
        (m), the Levenberg-Marquardt rule of damping in proportion to the error (Sugihara's damps by
        its square); 0: constant dampings.
    step_bound: how a DLS step larger than full speed is brought into ``[-1, 1]`` (in actions):
        ``"shrink"`` divides the whole step by its largest entry (the direction kept), ``"clip"``
        clips each joint (the joints that do not saturate keep their own speed: the wrist goes on
        turning while the shoulder moves at full speed).
    null_space_centering: ``k >= 0`` (dimensionless): each DLS step also moves the joints towards the
        middle of their ranges inside the Jacobian's null space (:meth:`JointGoalExtractor.centering_step`, at ``k``
        times full speed at a limit; :meth:`JointGoalExtractor.bounded_step`), so the redundant arm keeps away from the
        joint limits where the pose task has local minima; 0: off.
    centering_twist: with ``null_space_centering`` and pose goals, the last joint is centred on
        where the rotation error would take it, ``q_n + phi`` (:meth:`JointGoalExtractor.last_joint_twist`), instead of
        on ``q_n``: a goal that the arm's present branch reaches only past that joint's limit moves
        the other joints early, while they can still carry the turn.
    limit_hold: with ``limit_rounds``, where a held joint goes: ``"still"``, nowhere; ``"limit"``, onto
        the limit it would have passed (the other joints' step solved for the rest of the error). A
        joint held still short of its limit leaves the step a fixed point wherever the other joints
        alone cannot lower the error: the arm stalls there, within a step of the limit.
    clip_guard: ``c`` in ``[0, 1]`` or None (off), with ``step_bound = "clip"``: a clipped step whose
        first-order progress ``e . J dq`` is below ``c`` times the shrunk step's is shrunk instead
        (:meth:`JointGoalExtractor.bounded_by_progress`). Clipping some joints of a large step turns its direction and
        can leave it no descent at all (the arm then stalls, above all where the velocity damper
        takes away the rest); shrinking keeps the DLS direction, a descent direction.

    """

    dampings: tuple[float, ...] = (0.1, 0.01)
    orientation_weight: float = 0.5
    clearance_rows: tuple[int, int] | None = None
    avoidance: Avoidance | None = None
    limit_rounds: int = 0
    error_damping: float = 0.0
    step_bound: str = "shrink"
    null_space_centering: float = 0.0
    centering_twist: bool = False
    limit_hold: str = "still"
    clip_guard: float | None = None

    def __post_init__(self) -> None:
        if len(self.dampings) == 0 or any(float(d) <= 0 for d in self.dampings):
            raise ValueError(f"dampings must be a non-empty list of positive numbers (m), got {list(self.dampings)}")
        if not float(self.orientation_weight) > 0:
            raise ValueError(f"orientation_weight must be a positive number (m/rad), got {self.orientation_weight!r}")
        rows = None if self.clearance_rows is None else tuple(int(c) for c in self.clearance_rows)
        if self.avoidance is not None:
            if rows is None:
                raise ValueError("avoidance needs the env's clearances: make the env with observe_clearance=True")
            gains = dict(self.avoidance._asdict() if isinstance(self.avoidance, Avoidance) else self.avoidance)
            if set(gains) != {"xi", "safe", "influence"} or not 0 < float(gains["xi"]) <= 1 \
                    or not 0 <= float(gains["safe"]) < float(gains["influence"]):
                raise ValueError("avoidance must be {xi: in (0, 1], safe: >= 0, influence: > safe} (m), "
                                 f"got {gains!r}")
            object.__setattr__(self, "avoidance", Avoidance(**{key: float(v) for key, v in gains.items()}))
        if isinstance(self.limit_rounds, bool) or not isinstance(self.limit_rounds, int) or self.limit_rounds < 0:
            raise ValueError(f"limit_rounds must be an int >= 0, got {self.limit_rounds!r}")
        numbers = {"dampings": tuple(float(d) for d in self.dampings), "clearance_rows": rows,
                   "orientation_weight": float(self.orientation_weight),
                   "error_damping": _number(self.error_damping, "error_damping"),
                   "null_space_centering": _number(self.null_space_centering, "null_space_centering")}
        for name, value in numbers.items():
            object.__setattr__(self, name, value)
        self._check_bounds()

    def _check_bounds(self) -> None:
        """The options of how a step is bounded and held at the limits."""
        if self.step_bound not in STEP_BOUNDS:
            raise ValueError(f"step_bound must be one of {STEP_BOUNDS}, got {self.step_bound!r}")
        check_bool(self.centering_twist, "centering_twist")
        if self.centering_twist and not self.null_space_centering:
            raise ValueError("centering_twist needs pose goals (9 numbers) and null_space_centering > 0")
        if self.limit_hold not in LIMIT_HOLDS:
            raise ValueError(f"limit_hold must be one of {LIMIT_HOLDS}, got {self.limit_hold!r}")
        if self.clip_guard is not None:
            guard = self.clip_guard
            if isinstance(guard, bool) or not isinstance(guard, (int, float)) or not 0 <= guard <= 1:
                raise ValueError(f"clip_guard must be a number in [0, 1] or None, got {guard!r}")
            if self.step_bound != "clip":
                raise ValueError("clip_guard needs step_bound: clip")
            object.__setattr__(self, "clip_guard", float(guard))

    def check_space(self, nj: int, obs_dim: int, goal_dim: int) -> None:
        """ValueError unless these options fit an arm of ``nj`` joints, observations of ``obs_dim`` numbers and
        goals of ``goal_dim``."""
        if self.centering_twist and goal_dim != 9:
            raise ValueError("centering_twist needs pose goals (9 numbers) and null_space_centering > 0")
        if self.avoidance is not None:
            start, k = self.clearance_rows
            if start < 3 * nj or start + k * (1 + nj) > obs_dim:
                raise ValueError(f"clearance_rows {list(self.clearance_rows)} lie outside the observation ({obs_dim})")


def _named_chain(robot: str):
    """The chain of an env's robot by name (a preset or a URDF arm of :mod:`envs.robot`)."""
    from envs.robot import URDF_ARMS, resolve_robot
    from iiwa_torch.robots import PRESETS

    names = sorted(PRESETS) + sorted(URDF_ARMS)
    if robot not in names:
        raise ValueError(f"robot must be one of {names}, got {robot!r}")
    return resolve_robot(robot, checked=False)[0]


class JointGoalExtractor(GoalDeltaExtractor):
    """:class:`GoalDeltaExtractor` plus joint-space features of the position error, from the robot's Jacobian.

    The network sees the goal error in metres, but acts in joint space, through a Jacobian that
    changes over the workspace and loses rank near the stretched arm. This extractor computes,
    for each damping ``lambda`` (m), the damped-least-squares joint step that would remove the
    position error ``e = desired[:3] - achieved[:3]`` (m):

        dq = J_p^T (J_p J_p^T + lambda^2 I)^-1 e        (rad; J_p: the Jacobian's position rows, m/rad)

    expressed in actions, ``u = dq / max_step`` (``max_step``: rad per step at ``|a| = 1``), and
    brought into ``[-1, 1]``: shrunk as a whole to ``u / max(1, max_i |u_i|)``, its direction kept,
    or clipped joint by joint (``step_bound``). It also appends ``J_p^T e / |e|`` (m; the
    steepest-descent direction, defined at any rank), each joint's place within its limits,
    ``2 (q - lower) / (upper - lower) - 1``, and the distance ``|e|`` (m).

    Pose goals (9 numbers: position, then the first two columns of the rotation matrix) use
    the whole Jacobian, its rotation rows weighted by ``w = orientation_weight`` (m/rad), and
    the error ``e = [e_p; w e_r]`` with ``e_r = log(R_desired R_achieved^T)`` (rotation vector
    in the world frame, rad): the same formulas with 6 rows, and ``|e|`` combines both.

    Everything is computed inside the network from the observation, so it stays correct when
    HER relabels ``desired_goal``. It needs the raw observation: its first ``2 nj`` entries are
    ``cos q``, ``sin q`` (read by :func:`envs.transport.joint_angles`), so train without ``VecNormalize`` (the
    observation entries are all O(1): cosines, sines, velocities in ``[-1, 1]``, metres).

    With ``avoidance`` (``{"xi", "safe", "influence"}``, see :func:`damper_constraints`) and an env
    that observes its clearances (``observe_clearance=True``; ``clearance_rows = (first column, K)``
    of them in ``observation``), every DLS step is first changed by :func:`velocity_damper` to keep
    each capsule clear, then bounded; and the damper's constraints in actions (``normal * max_step``,
    m, then ``bound``, m) are appended, ``K (nj + 1)`` columns from ``damper_columns[0]``, for a
    policy head that keeps its whole action clear (:class:`train.residual.ResidualDLSPolicy`).

    Args:
        observation_space: a ``Dict`` with ``observation`` (starting with ``cos q, sin q``),
            ``achieved_goal`` and ``desired_goal`` (3 numbers, a position in m, or 9, a pose).
        robot: the env's robot by name: one of ``iiwa_torch.robots.PRESETS`` or of ``envs.robot.URDF_ARMS``
            (``"panda"``).
        max_step: ``(nj,)`` joint motion per step at full action, rad (the env task's ``max_step``).
        scales: goal-delta scales, m (see :class:`GoalDeltaExtractor`).
        settings: a :class:`JointSettings`; ``options``, its fields as keywords (a config's
            ``features_extractor_kwargs``), override it.

    Output: ``(batch, GoalDeltaExtractor's features + (len(dampings) + 2) * nj + 1)`` features.
    """

    def __init__(self, observation_space: spaces.Dict, robot: str = "iiwa14",
                 max_step: Sequence[float] | None = None, scales: Sequence[float] = (0.3, 0.03, 0.003),
                 settings: JointSettings | None = None, **options):
        super().__init__(observation_space, scales)
        settings = JointSettings(**options) if settings is None else replace(settings, **options)
        self.chain = chain = _named_chain(robot)  # float64 buffers; the joint features are computed in float64
        self.nj = nj = chain.n_joints
        if max_step is None or len(max_step) != nj or any(float(s) <= 0 for s in max_step):
            raise ValueError(f"max_step must be {nj} positive numbers (rad per step), got {max_step!r}")
        obs_dim = int(observation_space["observation"].shape[0])
        goal_dim = int(observation_space["desired_goal"].shape[0])
        if obs_dim < 2 * nj or goal_dim not in (3, 9):
            raise ValueError(f"robot {robot!r} has {nj} joints: the observation needs >= {2 * nj} entries "
                             f"(cos q, sin q) and the goal 3 (a position) or 9 (a pose) numbers; got {obs_dim} "
                             f"and {goal_dim}")
        settings.check_space(nj, obs_dim, goal_dim)
        #: the options, checked
        self.settings = settings
        self.pose = goal_dim == 9
        self._add_columns(nj, len(settings.dampings))
        self.register_buffer("max_step", torch.tensor([float(s) for s in max_step], dtype=torch.float64))
        self.register_buffer("damping_sq", torch.tensor([float(d) ** 2 for d in settings.dampings],
                                                        dtype=torch.float64))

    def _add_columns(self, nj: int, dampings: int) -> None:
        """Name the joint features' columns, after the goal features, and count them in ``features_dim``."""
        #: columns of the output holding the DLS step (in actions) at the first damping
        self.step_columns = (self._features_dim, self._features_dim + nj)
        #: columns of ``J^T e / |e|`` (m), after the steps of every damping
        self.gradient_columns = (self._features_dim + dampings * nj, self._features_dim + (dampings + 1) * nj)
        self._features_dim += (dampings + 2) * nj + 1
        #: the column of the distance |e| (m)
        self.distance_column = self._features_dim - 1
        #: ``(first column, K)`` of the damper's constraints in actions, or None without avoidance
        self.damper_columns = None
        if self.settings.avoidance is not None:
            self.damper_columns = (self._features_dim, self.settings.clearance_rows[1])
            self._features_dim += self.settings.clearance_rows[1] * (nj + 1)

    def _constants(self, xp) -> tuple:
        """``max_step``, ``damping_sq`` and the chain's lower and upper limits, float64, in ``xp``'s arrays."""
        # _buffers, not attributes: nn.Module's attribute lookup costs more than the rest (several calls a step)
        buffers = self._buffers
        max_step, damping_sq, limits = buffers["max_step"], buffers["damping_sq"], self.chain._buffers["limits"]
        if xp is not torch:  # the chain's buffers are float64
            max_step, damping_sq, limits = max_step.numpy(), damping_sq.numpy(), limits.numpy()
        return max_step, damping_sq, limits[0], limits[1]

    def squared_dampings(self, error):
        """``error (B, k)`` (tensor or numpy array) -> the squared dampings ``(B, L)`` (m^2),
        ``(lambda + c |e|)^2`` with ``c = error_damping``."""
        xp = np if isinstance(error, np.ndarray) else torch
        damping_sq = self._constants(xp)[1]  # (L,)
        if not self.settings.error_damping:  # numpy: a copy (np.broadcast_to costs more than copying a few rows)
            return damping_sq[None].repeat(error.shape[0], 0) if xp is np else \
                damping_sq.expand(error.shape[0], damping_sq.shape[0])
        size = xp.sqrt((error * error).sum(-1))[:, None]  # (B, 1)
        return (xp.sqrt(damping_sq) + self.settings.error_damping * size) ** 2

    def _dls_solver(self, jac, damping):
        """``(free, rhs)`` -> the DLS steps ``(B, L, nj)`` (rad) per squared damping ``damping (B, L)`` for
        ``jac (B, k, nj)`` and the right-hand side ``rhs`` (``(B, k)``, or ``(B, L, k)``: one per damping),
        the held joints' columns of ``J`` counted as zero (``free (B, L, nj)``, 0 or 1, or None)."""
        b, m, n = jac.shape
        size = damping.shape[1]
        if isinstance(jac, np.ndarray):
            def solve_numpy(free, rhs):
                return dls_step_numpy(jac[:, None], rhs[:, None] if rhs.ndim == 2 else rhs, damping, free)
            return solve_numpy  # (B, L, nj)
        # dls_step's layout and kernel, unchecked: the inputs are this network's own
        J = jac.unsqueeze(1).expand(b, size, m, n).reshape(-1, m, n).permute(1, 2, 0)  # (m, nj, B L)
        damping, tiny = damping.reshape(-1), torch.finfo(jac.dtype).tiny

        def solve(free, rhs):
            rhs = (rhs.unsqueeze(1) if rhs.ndim == 2 else rhs).expand(b, size, m).reshape(-1, m).T[:, None]
            free = None if free is None else free.reshape(-1, n).T
            return dls_step_batch_last(J, rhs, damping, tiny, free)[:, 0].T.reshape(b, size, n)
        return solve

    def _bounded(self, u, xp):
        """Steps in actions ``u (..., nj)`` brought into ``[-1, 1]`` as ``step_bound`` says."""
        return u.clip(-1.0, 1.0) if self.settings.step_bound == "clip" else shrink(u, xp)

    def bounded_by_progress(self, u, jac, error):
        """Steps in actions ``u (B, L, nj)`` brought into ``[-1, 1]`` as ``step_bound`` says, but with
        ``clip_guard = c``, each clipped step whose first-order progress ``e . J dq`` (``dq = u max_step``;
        ``jac (B, k, nj)``, ``error (B, k)``) is below ``c`` times the shrunk step's is shrunk instead."""
        xp = np if isinstance(u, np.ndarray) else torch
        if self.settings.clip_guard is None:
            return self._bounded(u, xp)
        clipped, shrunk = u.clip(-1.0, 1.0), shrink(u, xp)
        gain = (jac * error[..., None]).sum(-2) * self._constants(xp)[0]  # (B, nj): J^T e max_step
        guard = self.settings.clip_guard
        behind = (clipped * gain[:, None]).sum(-1) < guard * (shrunk * gain[:, None]).sum(-1)  # (B, L)
        return xp.where(behind[..., None], shrunk, clipped)

    def bounded_step(self, q, jac, error, damping_sq=None):
        """The DLS step per damping in actions, bounded into ``[-1, 1]`` (``step_bound``): ``q (B, nj)``
        rad, ``jac (B, k, nj)``, ``error (B, k)`` (float64 tensors, or numpy arrays), ``damping_sq (B, L)``
        (:meth:`squared_dampings` of ``error`` if None) -> ``(B, L, nj)``.
        With ``limit_rounds``, a joint that the step would push past its limit is held still and the step
        solved again without it, up to that many times (the arm's other joints then carry the motion,
        instead of the step being clamped at the limit); with ``limit_hold = "limit"`` the held joint goes
        onto its limit, the others solving for the rest of the error.
        The steps are bounded by :meth:`bounded_by_progress` (``clip_guard``).
        With ``null_space_centering``, each solve is the damped least-squares step towards the preferred
        step ``dq0 =`` :meth:`centering_step` (``dq0`` of the held joints: 0), the minimiser of
        ``|J dq - e|^2 + lambda^2 |dq - dq0|^2``:

            dq = dq0 + J^T (J J^T + lambda^2 I)^-1 (e - J dq0) = J^+ e + (I - J^+ J) dq0

        (``J^+`` the damped pseudo-inverse): ``dq0`` projected onto the Jacobian's null space, with
        the share ``lambda^2 / (sigma^2 + lambda^2)`` of each singular direction ``sigma`` let through
        (the exact projection, a tiny damping in ``J^+`` of this term alone, did worse on the pose env:
        far from the goal the damped one also steers the arm's motion towards mid-range).
        With ``centering_twist`` (pose goals, ``k = 6``) the centering step is that of
        ``q_n + phi`` for the last joint (:meth:`last_joint_twist`)."""
        xp = np if isinstance(q, np.ndarray) else torch
        max_step, _, lower, upper = self._constants(xp)
        solver = self._dls_solver(jac, self.squared_dampings(error) if damping_sq is None else damping_sq)
        prior = None  # (B, nj) rad
        if self.settings.null_space_centering:
            twist = self.last_joint_twist(jac, error) if self.settings.centering_twist else None
            prior = self.centering_step(q, twist)

        def solve(free, hold=None):  # hold (B, L, nj) rad: the held joints' steps (limit_hold "limit")
            held = None if prior is None else prior[:, None] if free is None else prior[:, None] * free
            if hold is not None:
                held = hold if held is None else held + hold
            if held is None:
                return solver(free, error)
            return held + solver(free, error[:, None] - (held[..., None, :] * jac[:, None]).sum(-1))

        dq = solve(None)  # (B, L, nj) rad
        if self.settings.limit_rounds:
            free = xp.ones_like(dq)
            hold = xp.zeros_like(dq) if self.settings.limit_hold == "limit" else None
            for _ in range(self.settings.limit_rounds):
                step = self.bounded_by_progress(dq / max_step, jac, error) * max_step
                end = q[:, None] + step
                blocked = ((end > upper) & (step > 0)) | ((end < lower) & (step < 0))
                if not bool((blocked & (free > 0)).any()):
                    break
                if hold is not None:  # onto the limit it would pass
                    room = xp.where(step > 0, upper - q[:, None], lower - q[:, None])
                    hold = xp.where(blocked & (free > 0), room, hold)
                free = free * ~blocked
                dq = solve(free, hold)
        return self.bounded_by_progress(dq / max_step, jac, error)

    def centering_step(self, q, twist=None):
        """The secondary task of ``null_space_centering = k``: ``q (B, nj)`` rad (tensor or numpy array) and
        ``twist (B,)`` rad or None (added to the last joint's angle before its place is taken) ->
        ``dq0 = -k p |p| max_step`` ``(B, nj)`` rad, ``p = 2 (q - lower) / (upper - lower) - 1`` each joint's
        place within its limits: no push at mid-range, ``k`` times full speed towards the middle at a
        limit. It is ``-S grad H`` for ``H(q) = sum_i |p_i|^3 / 3`` and ``S = diag(k max_step_i (upper_i -
        lower_i) / 2)``: a joint-limit criterion for the gradient projection method of A. Liegeois,
        "Automatic supervisory control of the configuration and behavior of multibody mechanisms"
        (IEEE Trans. Systems, Man, and Cybernetics 7(12), 1977), flatter near mid-range than his
        quadratic one (which did no better on the pose env)."""
        xp = np if isinstance(q, np.ndarray) else torch
        if twist is not None:
            q = xp.concatenate([q[:, :-1], (q[:, -1] + twist)[:, None]], -1)
        place = self.joint_place(q)
        return -self.settings.null_space_centering * self._constants(xp)[0] * place * abs(place)

    def joint_place(self, q):
        """``q (B, nj)`` rad (tensor or numpy array) -> each joint's place within its limits,
        ``2 (q - lower) / (upper - lower) - 1``: -1 at the lower limit, 1 at the upper."""
        _, _, lower, upper = self._constants(np if isinstance(q, np.ndarray) else torch)
        return 2.0 * (q - lower) / (upper - lower) - 1.0

    def last_joint_twist(self, jac, error):
        """How far the last joint would turn to remove the rotation error alone: ``jac (B, 6, nj)`` (rows
        ``[J_p; w J_r]``), ``error (B, 6)`` (``[e_p; w e_r]``, ``e_r = theta u`` the rotation vector) ->
        the twist ``phi (B,)`` (rad, in ``(-pi, pi]``) of the swing-twist decomposition of the rotation
        ``exp(e_r)`` about the last joint's axis ``z`` (the last column of ``J_r``, a unit vector):
        ``phi = 2 atan2(sin(theta / 2) u.z, cos(theta / 2))``, the angle of the part of the rotation
        about ``z``. Tensors or numpy arrays."""
        xp = np if isinstance(jac, np.ndarray) else torch
        rotation, axis = error[:, 3:], jac[:, 3:, -1]  # w e_r, w z
        size = xp.sqrt((rotation * rotation).sum(-1))  # w theta
        along = (rotation * axis).sum(-1) / (size * xp.sqrt((axis * axis).sum(-1))).clip(min=1e-300)  # u.z
        half = size / (2.0 * self.settings.orientation_weight)
        return 2.0 * xp.arctan2(xp.sin(half) * along, xp.cos(half))

    def joint_features(self, q, error, clearance: tuple | None = None):
        """``q (B, nj)`` rad and ``error (B, k)`` -> ``(B, (len(dampings) + 2) * nj + 1)`` float64: the shrunk
        DLS steps in actions per damping, ``J^T e / |e|`` (m), the place within the limits, ``|e|`` (m).
        Tensors, or numpy arrays (all of them).

        ``k = 3``: a position error (m), ``J = J_p``; ``k = 6``: ``[e_p; w e_r]`` (m), ``J = [J_p; w J_r]``.
        ``clearance``: the capsules' distances ``(B, K)`` (m) and gradients ``(B, K, nj)`` (m/rad), for
        ``avoidance``."""
        xp = np if isinstance(q, np.ndarray) else torch
        if xp is torch:
            q, e = q.double(), error.double()
            jac = self.chain.jacobian(q)  # (B, 6, nj): m/rad, then rad/rad
        else:
            q, e = q.astype(np.float64), error.astype(np.float64)
            jac = kin.jacobian(self.chain.geometry(), torch.from_numpy(q)).numpy()
        max_step = self._constants(xp)[0]
        k = e.shape[-1]
        w = self.settings.orientation_weight
        jp = jac[..., :3, :] if k == 3 else xp.concatenate([jac[..., :3, :], w * jac[..., 3:, :]], -2)
        damping_sq = self.squared_dampings(e)  # (B, L)
        u = self.bounded_step(q, jp, e, damping_sq)  # (B, L, nj) in actions
        if self.settings.avoidance is not None:
            gains = self.settings.avoidance._asdict()
            u = velocity_damper(u * max_step, jp, damping_sq, *clearance, **gains) / max_step
            u = self._bounded(u, xp)
        distance = xp.sqrt((e * e).sum(-1))[:, None]  # (B, 1)
        grad = (jp.mT @ e[..., None])[..., 0] / distance.clip(min=1e-6)
        return xp.concatenate([u.reshape(u.shape[0], -1), grad, self.joint_place(q), distance], -1)

    def forward(self, observations: dict[str, torch.Tensor]) -> torch.Tensor:
        """The features ``(B, features_dim)``; up to ``NUMPY_ROWS`` rows on the CPU with nothing to
        differentiate (:func:`numpy_ok`: one env's policy step) the same formulas run in numpy, which
        costs a fraction of torch's per-op overhead (the DLS solves, by ``dls_step_numpy``, and the
        Jacobian are computed another way there: the same values to rounding)."""
        _, _, lower, upper = self._constants(np)
        # torch's float32 atan2 on both paths: numpy's may differ in the last bit
        q = joint_angles(observations["observation"], lower, upper)
        if numpy_ok(*observations.values()):
            return torch.from_numpy(self._features(q.numpy(), {key: v.numpy() for key, v in observations.items()}))
        return self._features(q, observations)

    def _features(self, q, observations: dict):
        """:meth:`forward` from ``q (B, nj)``, on tensors or numpy arrays (with numba, numpy arrays by
        one compiled kernel: :func:`train.policy_kernels.features`, the same formulas)."""
        xp = np if isinstance(q, np.ndarray) else torch
        obs, nj = observations["observation"], self.nj
        desired, achieved = observations["desired_goal"], observations["achieved_goal"]
        error = desired[:, :3] - achieved[:, :3]
        with torch.no_grad():  # no parameters upstream: features only
            if self.pose:
                rotation = _rotation_error(*(torch.from_numpy(g) for g in (desired, achieved))).numpy() \
                    if xp is np else _rotation_error(desired, achieved)
                error = xp.concatenate([error.astype(np.float64) if xp is np else error.double(),
                                        self.settings.orientation_weight * rotation], -1)
            if xp is np and compiled.ENABLED:
                return self._compiled_features(q, observations, error)
            base = self.goal_features(observations, xp)
            clearance, damper = None, []
            if self.settings.avoidance is not None:
                start, k = self.settings.clearance_rows
                rows = obs[:, start : start + k * (1 + nj)]
                rows = rows.astype(np.float64) if xp is np else rows.double()
                clearance = rows[:, :k], rows[:, k:].reshape(-1, k, nj)
                normal, bound = damper_constraints(*clearance, **self.settings.avoidance._asdict())
                damper = [(normal * self._constants(xp)[0]).reshape(normal.shape[0], -1), bound]
            joint = self.joint_features(q, error, clearance)
        parts = [joint, *damper]
        parts = [p.astype(base.dtype) for p in parts] if xp is np else [p.to(base.dtype) for p in parts]
        return xp.concatenate([base, *parts], -1)

    def _compiled_features(self, q: np.ndarray, observations: dict[str, np.ndarray], error: np.ndarray) -> np.ndarray:
        """:meth:`_features` on numpy arrays, by :func:`train.policy_kernels.features` (imported, numba
        with it, on the first call)."""
        from train.policy_kernels import features

        max_step, damping_sq, lower, upper = self._constants(np)
        arrays = (np.ascontiguousarray(observations[key]) for key in ("observation", "achieved_goal", "desired_goal"))
        return features(*arrays, np.ascontiguousarray(error, dtype=np.float64), q.astype(np.float64),
                        self._buffers["inv_scales"].numpy()[:, 0], damping_sq, np.stack([max_step, lower, upper]),
                        self._kernel_scalars(), *self.chain.geometry().float_arrays)

    def _kernel_scalars(self) -> np.ndarray:
        """The settings as :func:`train.policy_kernels.features` reads them (made once: the settings are frozen)."""
        scalars = self.__dict__.get("_scalars")
        if scalars is None:
            from train.policy_kernels import pack_scalars

            s = self.settings
            avoidance, (start, k) = s.avoidance or Avoidance(0.0, 0.0, 0.0), s.clearance_rows or (0, 0)
            scalars = self._scalars = pack_scalars({
                "error_damping": s.error_damping, "clip": s.step_bound == "clip", "limit_rounds": s.limit_rounds,
                "orientation_weight": s.orientation_weight, "centering": s.null_space_centering,
                "twist": s.centering_twist, "guarded": s.clip_guard is not None, "guard": s.clip_guard or 0.0,
                "hold_at_limit": s.limit_hold == "limit", **avoidance._asdict(), "clearance_start": start,
                "K": k if s.avoidance is not None else 0})
        return scalars


def _rotation_error(desired: torch.Tensor, achieved: torch.Tensor) -> torch.Tensor:
    """Pose goals ``(B, 9)`` -> ``log(R_desired R_achieved^T) (B, 3)`` (rad), in the goals' dtype (the
    numpy path hands its arrays over as tensors: a dozen torch ops, one formula)."""
    return so3.log(decode_pose_goal(desired)[:, :3, :3] @ decode_pose_goal(achieved)[:, :3, :3].mT)
