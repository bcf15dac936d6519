"""The reaching task's pure, batched step: one ``step`` drives every env.

:class:`ReachTask` assembles three parts, kept apart:

- the robot, :class:`envs.robot.JointVelocityArm` (``task.arm``): a DH chain, its limits and
  speeds, the integration of an action into joint angles;
- the goals, :class:`envs.goals.ReachGoals` (``task.goals``): goal kind, errors, success,
  reward;
- the transport, :class:`envs.transport.Transport` (``task.transport``): actions in, numpy
  observations and results out.

The task itself is immutable configuration with pure batched methods over a
:class:`ReachState` (a tuple of tensors with one column per environment):
``initial_state(keys)``, ``reset_all(state, seeds, rng)``, ``step(state, action)`` (the one
step) and ``step_autoreset(state, action)`` (the step, same-step auto-reset of the finished
environments and one transfer to numpy, for the vector envs). The envs (``envs.reach``,
``envs.sb3``) only keep the current state. Randomness is counter-based (``envs.seeding``).
"""

from __future__ import annotations

import math
from enum import Enum
from typing import NamedTuple

import numpy as np
import torch

from iiwa_torch.dh import DHChain
from iiwa_torch.robots import iiwa14

from .goals import GoalKind, ReachGoals, RewardKind, enum_option
from .robot import JointVelocityArm
from .seeding import keys_from_seeds, uniform
from .transport import Transition, Transport

__all__ = ["StartKind", "ReachState", "StepResult", "ReachTask"]

Tensor = torch.Tensor

_GOAL_CANDIDATES = 8  # goals drawn per reset when a minimum goal distance is asked for


class StartKind(str, Enum):
    """Where episodes start: the fixed ``home`` posture or a ``random`` one within the limits."""

    HOME = "home"
    RANDOM = "random"


# ---------------------------------------------------------------------------- state
class ReachState(NamedTuple):
    """State of ``n`` environments, components first ("structure of arrays": every per-env
    quantity is a contiguous row of ``n`` numbers, so per-joint constants broadcast along
    rows and elementwise ops run over long contiguous rows; measured 2x faster than
    ``(n, nj)`` rows at ``n = 65,536``). All tensors share the task's device.

    q: ``(nj, n)`` joint angles, rad. cos_q, sin_q: ``(nj, n)`` their cosines and sines (the
    observation's first rows, which the position kernel reuses). velocity: ``(nj, n)`` last
    joint velocity over the joint speed limits (in ``[-1, 1]``). goal: ``(g, n)`` desired
    goal. achieved: ``(g, n)`` achieved goal at ``q``. t: ``(n,)`` int64 steps taken this
    episode. key: ``(n,)`` int64 random key (from the seed). episode: ``(n,)`` int64 episode
    counter since seeding.
    """

    q: Tensor
    cos_q: Tensor
    sin_q: Tensor
    velocity: Tensor
    goal: Tensor
    achieved: Tensor
    t: Tensor
    key: Tensor
    episode: Tensor


class StepResult(NamedTuple):
    """Per-environment outcome of one step, ``(n,)`` each: reward (obs dtype), the
    ``terminated``/``truncated``/``success`` bools, the position distance (m) and the
    orientation error (rad; ``None`` for position goals)."""

    reward: Tensor
    terminated: Tensor
    truncated: Tensor
    success: Tensor
    distance: Tensor
    angle: Tensor | None


# ---------------------------------------------------------------------------- task
class ReachTask:
    """Immutable configuration of the reaching task plus its pure batched functions.

    Args:
        robot: the chain (default ``iiwa14()``); it must have ``velocity_limits``.
        goal: ``"position"`` (3 numbers) or ``"pose"`` (position and the first two columns
            of the rotation matrix: 9 numbers).
        reward: ``"dense"`` or ``"sparse"`` (see :class:`envs.goals.RewardKind`).
        start: ``"home"`` (``home``) or ``"random"`` (uniform within the joint limits).
        dt: control period, s: an action ``a`` in ``[-1, 1]^n`` moves joint ``i`` by
            ``a_i * velocity_limits_i * dt``.
        distance_threshold: success radius, m.
        orientation_threshold: success angle for pose goals, rad.
        orientation_weight: metres per radian of orientation error in the dense pose reward.
        goal_min_distance: goals closer than this to the start position (m) are redrawn
            (the farthest of 8 candidates is kept if none is far enough).
        max_episode_steps: truncate after this many steps (``None``: never).
        terminate_on_success: end the episode when the goal is reached (as panda-gym).
        home: start posture for ``start="home"`` (default :data:`iiwa_torch.robots.IIWA_HOME` for 7 joints,
            else zeros; it must lie within the limits).
        dtype: float dtype of the state (observations are always float32).
        device: torch device of the state.
    """

    def __init__(
        self,
        robot: DHChain | None = None,
        *,
        goal: GoalKind | str = GoalKind.POSITION,
        reward: RewardKind | str = RewardKind.DENSE,
        start: StartKind | str = StartKind.HOME,
        dt: float = 0.05,
        distance_threshold: float = 0.01,
        orientation_threshold: float = 0.1,
        orientation_weight: float = 0.1,
        goal_min_distance: float = 0.0,
        max_episode_steps: int | None = None,
        terminate_on_success: bool = True,
        home=None,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
    ) -> None:
        goal, reward = enum_option(GoalKind, goal, "goal"), enum_option(RewardKind, reward, "reward")
        self.start_kind = enum_option(StartKind, start, "start")
        for name, value in [("dt", dt), ("distance_threshold", distance_threshold),
                            ("orientation_threshold", orientation_threshold)]:
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive finite number, got {value!r}")
        if not (isinstance(orientation_weight, (int, float)) and math.isfinite(orientation_weight)
                and orientation_weight >= 0):
            raise ValueError(f"orientation_weight must be >= 0, got {orientation_weight!r}")
        if not (isinstance(goal_min_distance, (int, float)) and 0 <= goal_min_distance < math.inf):
            raise ValueError(f"goal_min_distance must be >= 0 (metres), got {goal_min_distance!r}")
        if max_episode_steps is not None and (isinstance(max_episode_steps, bool) or
                                              not isinstance(max_episode_steps, int) or max_episode_steps < 1):
            raise ValueError(f"max_episode_steps must be a positive int or None, got {max_episode_steps!r}")
        if dtype not in (torch.float32, torch.float64):
            raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        self.dt = float(dt)
        self.goal_min_distance = float(goal_min_distance)
        self.max_episode_steps = max_episode_steps
        self.terminate_on_success = bool(terminate_on_success)
        self.dtype = dtype
        self.device = torch.device("cpu") if device is None else torch.device(device)
        self.arm = JointVelocityArm(iiwa14() if robot is None else robot, self.dt, home, dtype, self.device)
        self.goals = ReachGoals(goal, reward, float(distance_threshold), float(orientation_threshold),
                                float(orientation_weight))
        self.transport = Transport(self.arm.n_joints, self.goals.size, dtype, self.device)
        #: the chain (the task's own copy, in its dtype and device)
        self.robot = self.arm.chain
        #: ``(nj,)`` rad per step at ``|a| = 1``
        self.max_step = self.arm.max_step
        self._home_goal = self.goal_of(self.arm.home[:, None])  # (g, 1): every episode from home starts there

    # ------------------------------------------------------------------ what the callers read
    @property
    def goal_kind(self) -> GoalKind:
        return self.goals.kind

    @property
    def distance_threshold(self) -> float:
        """Success radius, m."""
        return self.goals.distance_threshold

    @property
    def orientation_threshold(self) -> float:
        """Success angle of pose goals, rad."""
        return self.goals.orientation_threshold

    def steps_to_reach_bound(self) -> int:
        """Steps a full-speed straight joint move needs, in the worst case, from ``home`` to any
        configuration within the limits. Every sampled goal is the FK of such a configuration,
        so it can be reached in this many steps."""
        return self.arm.steps_to_reach_bound()

    def goal_of(self, q: Tensor, trig: tuple[Tensor, Tensor] | None = None) -> Tensor:
        """Joint angles ``(nj, b)``, batch last -> goal vectors ``(g, b)`` (:meth:`ReachGoals.goal_of`)."""
        return self.goals.goal_of(self.robot, q, trig)

    # ------------------------------------------------------------------ pure functions
    def initial_state(self, key: Tensor) -> ReachState:
        """Fresh episode 0 for the ``(n,)`` keys."""
        return self._new_episodes(key, torch.zeros_like(key))

    def reset_all(self, state: ReachState | None, seeds: list, rng: np.random.Generator) -> ReachState:
        """Reset every environment, as the envs' ``reset`` does: without seeds (all ``None``)
        an existing state goes on to the next episode of each environment; otherwise
        episode 0 starts from the keys of ``seeds`` (a ``None`` entry draws a seed from ``rng``;
        others must be ints in ``[0, 2**64)``, see :func:`envs.seeding.keys_from_seeds`)."""
        if state is not None and all(s is None for s in seeds):
            return self._new_episodes(state.key, state.episode + 1)  # every environment's next episode
        fresh = rng.integers(2**63, size=len(seeds)).tolist()
        return self.initial_state(keys_from_seeds([f if s is None else s for f, s in zip(fresh, seeds)], self.device))

    def _new_episodes(self, key: Tensor, episode: Tensor) -> ReachState:
        """Start episode ``episode`` for each key: draw the start and the goal, compute FK once."""
        arm = self.arm
        n, nj = key.shape[0], arm.n_joints
        k = _GOAL_CANDIDATES if self.goal_min_distance > 0 else 1
        # draws 0..nj-1 are the start, then k goal candidates; starts from home skip the start's
        # draws (counter-based: the goals' draws stay the same, at half the hashing)
        home = self.start_kind is StartKind.HOME
        first = nj if home else 0
        configs = arm.configurations(uniform(key, episode, first, nj * (k + 1) - first, self.dtype).view(n, -1, nj))
        goals = self.goal_of(configs.reshape(-1, nj).T).view(-1, n, configs.shape[1])  # (g, n, k or k + 1)
        if home:
            start, start_goal, candidates = arm.home.expand(n, nj), self._home_goal.expand(-1, n), goals
        else:
            start, start_goal, candidates = configs[:, 0], goals[:, :, 0], goals[:, :, 1:]
        if k > 1:
            d = torch.linalg.vector_norm(candidates[:3] - start_goal[:3, :, None], dim=0)  # (n, k)
            # the first candidate far enough, else the farthest: no loop, no sync
            score = torch.where(d >= self.goal_min_distance, -torch.arange(k, device=d.device, dtype=d.dtype), d - 1e9)
            goal = candidates[:, torch.arange(n, device=d.device), score.argmax(-1)]
        else:
            goal = candidates[:, :, 0]
        q = start.T.clone(memory_format=torch.contiguous_format)  # never a view of home
        return ReachState(
            q=q,
            cos_q=torch.cos(q),
            sin_q=torch.sin(q),
            velocity=torch.zeros(nj, n, dtype=self.dtype, device=self.device),
            goal=goal.contiguous(),
            achieved=start_goal.clone(memory_format=torch.contiguous_format),
            t=torch.zeros(n, dtype=torch.int64, device=self.device),
            key=key,
            episode=episode,
        )

    def step(self, state: ReachState, action: Tensor) -> tuple[ReachState, StepResult]:
        """Apply actions ``(nj, n)`` (clipped to ``[-1, 1]``): integrate, clamp to the limits, FK.

        The actions must be finite, in the state's layout, dtype and device:
        ``task.transport.check_action`` makes them so from the envs' ``(n, nj)`` batches.
        """
        q, velocity = self.arm.integrate(state.q, action)
        cos_q, sin_q = torch.cos(q), torch.sin(q)
        achieved = self.goal_of(q, (cos_q, sin_q))
        observed = (achieved, state.goal) if self.dtype == torch.float32 else (achieved.float(), state.goal.float())
        dist, angle, success = self.goals.errors(*observed)  # the reward of the goals as observed, in float32
        reward = self.goals.reward_of(dist, angle, success)
        t = state.t + 1
        terminated = success if self.terminate_on_success else torch.zeros_like(success)
        truncated = torch.zeros_like(success) if self.max_episode_steps is None else t >= self.max_episode_steps
        new = ReachState(q, cos_q, sin_q, velocity, state.goal, achieved, t, state.key, state.episode)
        return new, StepResult(reward, terminated, truncated, success, dist, angle)

    def reset_transition(self, state: ReachState) -> Transition:
        """The observation and status of a state just reset, as numpy (one transfer)."""
        dist, angle, success = self.goals.errors(state.achieved.float(), state.goal.float())
        no = torch.zeros_like(success)
        status = StepResult(self.goals.reward_of(dist, angle, success), no, no, success, dist, angle)
        io = self.transport
        return io.unpack(*(part.numpy(force=True) for part in io.pack(state, status)))

    def step_autoreset(self, state: ReachState, action: Tensor) -> tuple[ReachState, Transition]:
        """``step``, then same-step auto-reset of the environments that terminated or truncated.

        One transfer to numpy for the whole batch (plus one for the finished columns). The
        returned observation of a finished environment is the first of its next episode;
        its last observation is in ``final_obs`` (environments ``final_index``).
        """
        io = self.transport
        state, res = self.step(state, action)
        out, flags = io.pack(state, res)  # new tensors of our own, updated in place below
        idx = (res.terminated | res.truncated).nonzero().squeeze(-1)  # which environments restart: one sync
        d = io.packed_size
        # (D, m) copy: the finished episodes' last observations (index_select: 2x faster than out[:d, idx])
        final = out[:d].index_select(1, idx)
        if idx.numel():
            fresh = self._new_episodes(state.key[idx], state.episode[idx] + 1)
            # q and what follows from it, velocity and t were created by this step: update them in
            # place; goal and episode are the caller's tensors: copy them.
            for name in ("q", "cos_q", "sin_q", "velocity", "achieved", "t"):
                mine = getattr(state, name)
                mine.index_copy_(mine.ndim - 1, idx, getattr(fresh, name))
            state = state._replace(
                goal=state.goal.index_copy(1, idx, fresh.goal), episode=state.episode.index_copy(0, idx, fresh.episode)
            )
            out[:d].index_copy_(1, idx, io.observe(fresh))
        tr = io.unpack(out.numpy(force=True), flags.numpy(force=True))
        return state, tr._replace(final_index=idx.numpy(force=True), final_obs=io.split(final.numpy(force=True).T))
