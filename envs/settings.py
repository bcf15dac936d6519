"""The reaching task's options as one checked, immutable object: :class:`ReachSettings`.

``ReachTask(**options)`` and ``gymnasium.make(id, **options)`` build it from their keywords; the
arm itself (``robot``, ``end_link``, ``capsules``, ``home``) and where the state lives (``dtype``,
``device``) stay :class:`envs.core.ReachTask`'s own arguments.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from enum import Enum

from iiwa_torch.checks import check_bool, is_integer, is_number

from .goals import GoalKind, GoalRegion, RewardKind, enum_option

__all__ = ["StartKind", "CollisionKind", "ReachSettings", "MAX_OBSTACLES"]

MAX_OBSTACLES = 8  # obstacle slots an episode may have


class StartKind(str, Enum):
    """Where episodes start: the fixed ``home`` posture or a ``random`` one within the limits."""

    HOME = "home"
    RANDOM = "random"


class CollisionKind(str, Enum):
    """What a step into the floor, an obstacle or the arm itself does (``info["collision"]``):
    ``terminate`` the episode (default) or only ``penalize`` it (both subtract
    ``collision_penalty`` from that step's reward); ``off``: nothing is checked (the kinematic
    task of the first versions: goals anywhere in the joint limits, no ``info["collision"]``)."""

    TERMINATE = "terminate"
    PENALIZE = "penalize"
    OFF = "off"


@dataclass(frozen=True)
class ReachSettings:
    """The reaching task's options, checked once on construction (a ``ValueError`` or ``TypeError``
    naming the option); option strings become their enums.

    Attributes:
        goal: ``"position"`` (3 numbers) or ``"pose"`` (position and the first two columns
            of the rotation matrix: 9 numbers).
        goal_region: ``"joint_limits"`` (the FK of configurations within the limits) or
            ``"panda_gym"`` (positions in panda-gym's box, :data:`envs.goals.PANDA_GYM_BOX`;
            :class:`envs.goals.GoalRegion`; position goals, no ``goal_min_distance``).
        reward: ``"dense"`` or ``"sparse"`` (see :class:`envs.goals.RewardKind`).
        start: ``"home"`` (the task's ``home``) or ``"random"`` (uniform within the joint limits).
        dt: control period, s (> 0): an action ``a`` in ``[-1, 1]^n`` moves joint ``i`` by
            ``a_i * velocity_limits_i * dt``.
        distance_threshold: success radius, m (> 0).
        orientation_threshold: success angle for pose goals, rad (> 0).
        orientation_weight: metres per radian of orientation error in the dense pose reward (>= 0).
        goal_min_distance: goals closer than this to the start position (m, >= 0) are redrawn
            (the farthest of 8 candidates is kept if none is far enough).
        max_episode_steps: truncate after this many steps (``None``: never).
        terminate_on_success: end the episode when the goal is reached (as panda-gym).
        floor: height of the floor (m, base frame; ``None``: no floor).
        collision: ``"terminate"``, ``"penalize"`` or ``"off"`` (:class:`CollisionKind`): a step
            whose clearance (:func:`iiwa_torch.collision.clearance`: the arm's capsules against
            themselves, the floor and the obstacles) is negative. Unless ``"off"``, starts and
            goals are drawn collision-free.
        collision_penalty: subtracted from the reward of a colliding step (>= 0).
        obstacles: at most this many random spheres or boxes per episode (0 to :data:`MAX_OBSTACLES`;
            1 to ``obstacles`` drawn, 0: none), in the observation's obstacle block (:mod:`envs.world`);
            they need collision checks.
        observe_clearance: append each capsule's clearance and its joint gradient to the observation
            (after the obstacle block: K distances, m, then K x nj gradients, m/rad; see
            :meth:`envs.core.ReachTask.clearance_rows`), computed once per step, for controllers that
            keep every link clear; it needs collision checks.
    """

    goal: GoalKind = GoalKind.POSITION
    goal_region: GoalRegion = GoalRegion.JOINT_LIMITS
    reward: RewardKind = RewardKind.DENSE
    start: StartKind = StartKind.HOME
    dt: float = 0.05
    distance_threshold: float = 0.01
    orientation_threshold: float = 0.1
    orientation_weight: float = 0.1
    goal_min_distance: float = 0.0
    max_episode_steps: int | None = None
    terminate_on_success: bool = True
    floor: float | None = 0.0
    collision: CollisionKind = CollisionKind.TERMINATE
    collision_penalty: float = 1.0
    obstacles: int = 0
    observe_clearance: bool = False

    def __post_init__(self) -> None:
        for name, kind in (("goal", GoalKind), ("goal_region", GoalRegion), ("reward", RewardKind),
                           ("start", StartKind), ("collision", CollisionKind)):
            object.__setattr__(self, name, enum_option(kind, getattr(self, name), name))
        self._check_numbers()
        check_bool(self.observe_clearance, "observe_clearance")
        check_bool(self.terminate_on_success, "terminate_on_success")
        if self.goal_region is GoalRegion.PANDA_GYM and (self.goal is not GoalKind.POSITION or self.goal_min_distance):
            raise ValueError("goal_region='panda_gym' draws positions: it takes goal='position' and no "
                             "goal_min_distance")
        if self.obstacles and self.collision is CollisionKind.OFF:
            raise ValueError("obstacles need collision checks: use collision='terminate' or 'penalize', not 'off'")
        if self.observe_clearance and self.collision is CollisionKind.OFF:
            raise ValueError("observe_clearance needs collision checks: use collision='terminate' or 'penalize'")
        numbers = {"dt": float(self.dt), "distance_threshold": float(self.distance_threshold),
                   "orientation_threshold": float(self.orientation_threshold),
                   "orientation_weight": float(self.orientation_weight),
                   "goal_min_distance": float(self.goal_min_distance),
                   "max_episode_steps": None if self.max_episode_steps is None else int(self.max_episode_steps),
                   "floor": None if self.floor is None else float(self.floor),
                   "collision_penalty": float(self.collision_penalty), "obstacles": int(self.obstacles)}
        for name, value in numbers.items():
            object.__setattr__(self, name, value)

    def _check_numbers(self) -> None:
        """Each numeric option in its range (else a ``ValueError`` naming it)."""
        for name in ("dt", "distance_threshold", "orientation_threshold"):
            value = getattr(self, name)
            if not (is_number(value) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive finite number, got {value!r}")
        weight, far = self.orientation_weight, self.goal_min_distance
        if not (is_number(weight) and math.isfinite(weight) and weight >= 0):
            raise ValueError(f"orientation_weight must be >= 0, got {weight!r}")
        if not (is_number(far) and 0 <= far < math.inf):
            raise ValueError(f"goal_min_distance must be >= 0 (metres), got {far!r}")
        steps = self.max_episode_steps
        if steps is not None and (not is_integer(steps) or steps < 1):
            raise ValueError(f"max_episode_steps must be a positive int or None, got {steps!r}")
        if self.floor is not None and (not is_number(self.floor) or not math.isfinite(self.floor)):
            raise ValueError(f"floor must be a finite height in metres or None, got {self.floor!r}")
        penalty = self.collision_penalty
        if not (is_number(penalty) and math.isfinite(penalty) and penalty >= 0):
            raise ValueError(f"collision_penalty must be a finite number >= 0, got {penalty!r}")
        if not is_integer(self.obstacles) or not 0 <= self.obstacles <= MAX_OBSTACLES:
            raise ValueError(f"obstacles must be an int in [0, {MAX_OBSTACLES}], got {self.obstacles!r}")

    @classmethod
    def names(cls) -> tuple[str, ...]:
        """The options' names (the keywords ``ReachTask`` maps onto these settings)."""
        return tuple(f.name for f in fields(cls))
