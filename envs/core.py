"""The reaching task as pure, batched torch functions: one ``step`` drives every env.

Robot, task and env are kept apart:

- the robot is a :class:`~iiwa_torch.dh.DHChain` (kinematics, joint limits, joint speeds);
- the task, :class:`ReachTask`, is immutable configuration (time step, goal kind, reward,
  thresholds) with pure batched methods over a :class:`ReachState` (a tuple of tensors
  with one column per environment): ``initial_state(keys)``, ``reset_all(state, seeds,
  rng)``, ``step(state, action)`` (the one step) and ``step_autoreset(state, action)`` (the
  step, same-step auto-reset of the finished environments and one transfer to numpy, for
  the vector envs);
- the envs (``envs.reach``, ``envs.sb3``) only convert to and from numpy and keep the
  current state.

Randomness is counter-based: every random number of environment ``i`` is a hash of
``(key_i, episode_i, index)``, where ``key_i`` comes from that environment's seed. So a
batch of N environments seeded ``s, s+1, ..., s+N-1`` draws exactly the numbers of N
single environments with those seeds, without a Python loop and without a generator
per environment.
"""

from __future__ import annotations

import copy
import math
from enum import Enum
from typing import NamedTuple

import numpy as np
import torch

from iiwa_torch._checks import all_finite
from iiwa_torch.dh import DHChain
from iiwa_torch.robots import iiwa14

__all__ = [
    "GoalKind",
    "RewardKind",
    "StartKind",
    "ReachState",
    "StepResult",
    "Transition",
    "ReachTask",
    "keys_from_seeds",
    "uniform",
    "IIWA_HOME",
]

Tensor = torch.Tensor

#: Default start posture of the iiwa (radians): elbow and wrist bent, away from the
#: stretched-out singularity at q = 0.
IIWA_HOME = tuple(math.radians(v) for v in (0.0, 30.0, 0.0, -60.0, 0.0, 30.0, 0.0))

_GOAL_CANDIDATES = 8  # goals drawn per reset when a minimum goal distance is asked for


class GoalKind(str, Enum):
    """What the end effector must reach: a position, or a position and an orientation."""

    POSITION = "position"
    POSE = "pose"


class RewardKind(str, Enum):
    """``dense``: minus the distance (plus weighted angle for poses); ``sparse``: 0 on success, else -1."""

    DENSE = "dense"
    SPARSE = "sparse"


class StartKind(str, Enum):
    """Where episodes start: the fixed ``home`` posture or a ``random`` one within the limits."""

    HOME = "home"
    RANDOM = "random"


def _enum(kind: type[Enum], value, name: str):
    try:
        return kind(value)
    except ValueError:
        raise ValueError(f"{name} must be one of {[k.value for k in kind]}, got {value!r}") from None


# ---------------------------------------------------------------------------- counter-based RNG
_M32 = 0xFFFFFFFF


def _mul32_(x: Tensor, c: int) -> Tensor:
    """``x = (x * c) mod 2**32``, in place, for int64 ``x`` in ``[0, 2**32)`` and a constant
    ``c`` in ``[0, 2**32)``.

    ``c`` is used as its signed 32-bit equal (``c - 2**32`` from ``2**31`` up), which is the
    same modulo ``2**32`` and keeps ``|x * c| < 2**63``: no int64 overflow, two ops.
    """
    return x.mul_(c - 2**32 if c >= 2**31 else c).bitwise_and_(_M32)


def _mix32(x: Tensor) -> Tensor:
    """MurmurHash3's 32-bit finaliser: a bijection of ``[0, 2**32)`` that mixes all bits.
    ``x`` is left alone; the rounds work in place on the new tensor (half the memory
    traffic of a new tensor per op, for the all-environment resets of large batches)."""
    x = x ^ (x >> 16)
    _mul32_(x, 0x85EBCA6B).bitwise_xor_(x >> 13)
    return _mul32_(x, 0xC2B2AE35).bitwise_xor_(x >> 16)


def keys_from_seeds(seeds, device=None) -> Tensor:
    """Integer seeds (any non-negative ints, a sequence or array) -> ``(n,)`` int64 keys in ``[0, 2**32)``."""
    s = np.asarray(seeds, dtype=object).reshape(-1)
    if any(not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < 0 for v in s.tolist()):
        raise ValueError(f"seeds must be non-negative integers, got {list(s)[:5]}")
    s = np.array([int(v) % 2**64 for v in s.tolist()], dtype=np.uint64)
    lo = torch.from_numpy((s & np.uint64(_M32)).astype(np.int64)).to(device)
    hi = torch.from_numpy((s >> np.uint64(32)).astype(np.int64)).to(device)
    return _mix32(lo ^ _mix32(hi ^ 0x9E3779B9))


def uniform(key: Tensor, episode: Tensor, start: int, count: int, dtype: torch.dtype) -> Tensor:
    """Counter-based uniform numbers in ``[0, 1)``: ``(n,)`` keys and episodes -> ``(n, count)``.

    Column ``j`` is the draw number ``start + j`` of that (key, episode): a pure function,
    so any subset of environments can be (re)drawn in any order with the same result.
    24 random bits each (resolution 6e-8). The stream of one (key, episode) is SplitMix's:
    the finaliser applied to a start point plus ``j`` times the golden-ratio increment.
    """
    base = _mix32(key ^ _mix32((episode & _M32) ^ 0x7F4A7C15))  # (n,) start point
    steps = torch.tensor([(j * 0x9E3779B9) & _M32 for j in range(start, start + count)], device=key.device)
    h = _mix32((base[:, None] + steps).bitwise_and_(_M32))  # (n, count)
    return h.bitwise_right_shift_(8).to(dtype).mul_(2.0**-24)


def _distance_sq(u: Tensor, w: Tensor) -> Tensor:
    """``(3, ...)`` twice -> ``(...)``: the squared distance, summed over the 3 components in the
    order 0, 1, 2 whatever the layout (3 terms are fewer than a SIMD vector, so torch's
    reduction is a plain sequential loop both for one environment and for a batch:
    bit-identical results). The difference is squared in place: one pass less."""
    d = u - w
    return d.mul_(d).sum(0)


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


class Transition(NamedTuple):
    """A batched step as numpy, for the envs: ``obs`` dict of ``(n, ...)`` float32 arrays
    (after auto-reset), ``reward`` ``(n,)`` float32, ``terminated``/``truncated``/``success``
    ``(n,)`` bool, ``distance`` (m) and ``angle`` (rad; ``None`` for position goals) ``(n,)``
    float32, ``final_index`` the ``(m,)`` rows that finished and ``final_obs`` their last
    observations ``(m, ...)``."""

    obs: dict
    reward: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    success: np.ndarray
    distance: np.ndarray
    angle: np.ndarray | None
    final_index: np.ndarray
    final_obs: dict


# ---------------------------------------------------------------------------- task
class ReachTask:
    """Immutable configuration of the reaching task plus its pure batched functions.

    Args:
        robot: the chain (default ``iiwa14()``); it must have ``velocity_limits``.
        goal: ``"position"`` (3 numbers) or ``"pose"`` (position and the first two columns
            of the rotation matrix: 9 numbers).
        reward: ``"dense"`` or ``"sparse"`` (see :class:`RewardKind`).
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
        home: start posture for ``start="home"`` (default :data:`IIWA_HOME` for 7 joints,
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
        robot = iiwa14() if robot is None else robot
        if not isinstance(robot, DHChain):
            raise TypeError(f"robot must be a DHChain, got {type(robot).__name__}")
        if robot.velocity_limits is None:
            raise ValueError(f"robot {robot.name!r} has no velocity_limits; the action scale needs them")
        self.goal_kind = _enum(GoalKind, goal, "goal")
        self.reward_kind = _enum(RewardKind, reward, "reward")
        self.start_kind = _enum(StartKind, start, "start")
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
        self.distance_threshold = float(distance_threshold)
        self.orientation_threshold = float(orientation_threshold)
        self.orientation_weight = float(orientation_weight)
        self.goal_min_distance = float(goal_min_distance)
        self.max_episode_steps = max_episode_steps
        self.terminate_on_success = bool(terminate_on_success)
        self.dtype = dtype
        self.device = torch.device("cpu") if device is None else torch.device(device)
        # A private copy in the state's dtype and device (Module.to() works in place and the
        # caller keeps theirs): FK then converts no buffer at each call.
        same = robot.dh.device == self.device and robot.dh.dtype == dtype
        self.robot = robot if same else copy.deepcopy(robot).to(device=self.device, dtype=dtype)
        n = self.robot.n_joints
        # Sizes, plain attributes (read several times in every step; the task never changes):
        self.n_joints = n
        #: length of ``achieved_goal`` / ``desired_goal``: 3 (position) or 9 (pose);
        self.goal_size = 3 if self.goal_kind is GoalKind.POSITION else 9
        #: length of ``observation``: cos q, sin q, joint velocity (normalised), the achieved goal;
        self.observation_size = 3 * n + self.goal_size
        #: rows of :meth:`observe`: the observation, then the desired goal.
        self.packed_size = self.observation_size + self.goal_size
        lim = self.robot.limits.to(dtype)
        if home is None:
            home = IIWA_HOME if n == 7 else [0.0] * n
        home = torch.as_tensor(home, dtype=dtype, device=self.device)
        if home.shape != (n,) or not torch.isfinite(home).all() or not bool(self.robot.within_limits(home)):
            raise ValueError(f"home must be {n} finite joint angles within the limits, got {home.tolist()}")
        self.home = home
        self._home_goal = self.goal_of(home[:, None])  # (g, 1): every episode from home starts there
        self.lower, self.upper = lim[0], lim[1]
        self.max_step = (self.robot.velocity_limits * self.dt).to(dtype)  # (nj,) rad per step at |a| = 1
        # the same as columns (nj, 1), to broadcast along the state's rows
        self._lower_c, self._upper_c = self.lower[:, None], self.upper[:, None]
        self._max_step_c = self.max_step[:, None]
        # The thresholds as 0-dim float32 tensors (the errors are float32): comparing with a
        # Python float wraps it in a new tensor at every call, more than doubling the op's cost.
        self._distance_threshold = torch.tensor(self.distance_threshold, dtype=torch.float32)
        # Chordal threshold: ||R1 - R2||_F = 2 sqrt(2) sin(angle / 2), monotone in the angle.
        self._chord_sq_threshold = torch.tensor(8.0 * math.sin(min(self.orientation_threshold, math.pi) / 2) ** 2,
                                                dtype=torch.float32)
        reach = float((self.robot.dh[:, 0].abs() + self.robot.dh[:, 2].abs()).sum() + self.robot.tool[:3, 3].norm())
        self.position_bound = float(self.robot.base[:3, 3].abs().max()) + reach  # |ee coordinate| <= this

    def steps_to_reach_bound(self) -> int:
        """Steps a full-speed straight joint move needs, in the worst case, from ``home`` to any
        configuration within the limits: ``ceil(max_i max(|lo_i - h_i|, |hi_i - h_i|) / (v_i dt))``.
        Every sampled goal is the FK of such a configuration, so it can be reached in this many steps."""
        span = torch.maximum((self.lower - self.home).abs(), (self.upper - self.home).abs())
        return int(torch.ceil((span / self.max_step).max() - 1e-4))  # 1e-4: float32 rounding of exact ratios

    # ------------------------------------------------------------------ pure functions
    def goal_of(self, q: Tensor, trig: tuple[Tensor, Tensor] | None = None) -> Tensor:
        """Joint angles ``(nj, b)``, batch last -> goal vectors ``(g, b)``: the end-effector
        position (the chain's position-only kernel, which reuses ``trig = (cos q, sin q)`` if
        given), then for pose goals the first two columns of its rotation matrix."""
        if self.goal_kind is GoalKind.POSITION:
            return self.robot.position_batch_last(q, trig)
        pose = self.robot.fk(q.T)
        return torch.cat([pose[:, :3, 3], pose[:, :3, 0], pose[:, :3, 1]], -1).T.contiguous()

    def errors(self, achieved: Tensor, desired: Tensor) -> tuple[Tensor, Tensor | None, Tensor]:
        """Goals ``(g, ...)``, components first -> position distance (m), orientation angle
        (rad; ``None`` for position goals) and success, each ``(...)``.

        Each environment's numbers are reduced on their own (over the few components), so
        batched and single calls agree bit for bit (tested): what SB3's checker and HER's
        relabelled rewards rely on.
        """
        position = self.goal_kind is GoalKind.POSITION
        dist = (_distance_sq(achieved, desired) if position else _distance_sq(achieved[:3], desired[:3])).sqrt_()
        ok = dist < self._distance_threshold
        if position:
            return dist, None, ok
        xa, ya, xd, yd = achieved[3:6], achieved[6:9], desired[3:6], desired[6:9]
        # ||Ra - Rd||_F^2 over the three columns (z = x cross y) = 8 sin^2(angle / 2)
        za, zd = torch.linalg.cross(xa, ya, dim=0), torch.linalg.cross(xd, yd, dim=0)
        chord_sq = _distance_sq(xa, xd) + _distance_sq(ya, yd) + _distance_sq(za, zd)
        angle = 2 * torch.asin(torch.clamp(torch.sqrt(chord_sq / 8), max=1.0))
        return dist, angle, ok & (chord_sq < self._chord_sq_threshold)

    def _reward(self, dist: Tensor, angle: Tensor | None, ok: Tensor) -> Tensor:
        if self.reward_kind is RewardKind.SPARSE:
            return ok.to(dist.dtype) - 1
        return -dist if angle is None else -(dist + self.orientation_weight * angle)

    def reward(self, achieved: Tensor, desired: Tensor) -> Tensor:
        """Batched reward of goals ``(g, ...)`` (components first) -> ``(...)`` in their dtype."""
        return self._reward(*self.errors(achieved, desired))

    def initial_state(self, key: Tensor) -> ReachState:
        """Fresh episode 0 for the ``(n,)`` keys."""
        return self._new_episodes(key, torch.zeros_like(key))

    def reset_all(self, state: ReachState | None, seeds: list, rng: np.random.Generator) -> ReachState:
        """Reset every environment, as the envs' ``reset`` does: without seeds (all ``None``)
        an existing state goes on to the next episode of each environment; otherwise
        episode 0 starts from the keys of ``seeds`` (a ``None`` entry draws a seed from ``rng``)."""
        if state is not None and all(s is None for s in seeds):
            return self._new_episodes(state.key, state.episode + 1)  # every environment's next episode
        fresh = rng.integers(2**63, size=len(seeds)).tolist()
        return self.initial_state(keys_from_seeds([f if s is None else s for f, s in zip(fresh, seeds)], self.device))

    def _new_episodes(self, key: Tensor, episode: Tensor) -> ReachState:
        """Start episode ``episode`` for each key: draw the start and the goal, compute FK once."""
        n, nj = key.shape[0], self.n_joints
        k = _GOAL_CANDIDATES if self.goal_min_distance > 0 else 1
        # draws 0..nj-1 are the start, then k goal candidates; starts from home skip the start's
        # draws (counter-based: the goals' draws stay the same, at half the hashing)
        home = self.start_kind is StartKind.HOME
        first = nj if home else 0
        u = uniform(key, episode, first, nj * (k + 1) - first, self.dtype).view(n, -1, nj)
        configs = self.lower + u * (self.upper - self.lower)  # (n, k or k + 1, nj)
        goals = self.goal_of(configs.reshape(-1, nj).T).view(-1, n, configs.shape[1])  # (g, n, k or k + 1)
        if home:
            start, start_goal, candidates = self.home.expand(n, nj), self._home_goal.expand(-1, n), goals
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

        The actions must be finite, in the state's layout, dtype and device: ``check_action``
        makes them so from the envs' ``(n, nj)`` batches.
        """
        a = torch.clamp(action, -1.0, 1.0)  # not in place: the action may share the caller's memory
        # in place on the new tensors: a third faster at n = 65,536 than new ones per op; and
        # clamp_max_/clamp_min_, as clamp with tensor bounds was measured 2-3x slower
        q = torch.addcmul(state.q, a, self._max_step_c).clamp_max_(self._upper_c).clamp_min_(self._lower_c)
        # the motion actually made, over the speed limit; this clamp only removes float rounding (1e-6)
        velocity = (q - state.q).div_(self._max_step_c).clamp_(-1.0, 1.0)
        cos_q, sin_q = torch.cos(q), torch.sin(q)
        achieved = self.goal_of(q, (cos_q, sin_q))
        observed = (achieved, state.goal) if self.dtype == torch.float32 else (achieved.float(), state.goal.float())
        dist, angle, success = self.errors(*observed)  # the reward of the goals as observed, in float32
        reward = self._reward(dist, angle, success)
        t = state.t + 1
        terminated = success if self.terminate_on_success else torch.zeros_like(success)
        truncated = torch.zeros_like(success) if self.max_episode_steps is None else t >= self.max_episode_steps
        new = ReachState(q, cos_q, sin_q, velocity, state.goal, achieved, t, state.key, state.episode)
        return new, StepResult(reward, terminated, truncated, success, dist, angle)

    def reset_transition(self, state: ReachState) -> Transition:
        """The observation and status of a state just reset, as numpy (one transfer)."""
        dist, angle, success = self.errors(state.achieved.float(), state.goal.float())
        no = torch.zeros_like(success)
        status = StepResult(self._reward(dist, angle, success), no, no, success, dist, angle)
        return self.unpack(*(part.numpy(force=True) for part in self.pack(state, status)))

    @staticmethod
    def _rows(state: ReachState) -> list[Tensor]:
        return [state.cos_q, state.sin_q, state.velocity, state.achieved, state.goal]

    def observe(self, state: ReachState) -> Tensor:
        """``(D, n)`` float32, ``D = packed_size``: the observation (which ends with the achieved
        goal), then the desired goal, one row per component; :meth:`split` makes the
        observation dict of its numpy transpose."""
        return torch.cat(self._rows(state), 0).float()

    def pack(self, state: ReachState, result: StepResult) -> tuple[Tensor, Tensor]:
        """Everything a step returns, for two transfers: ``(D + k, n)`` float32, the observation
        rows then reward, distance and, for pose goals, angle (``k`` = 2 or 3); and ``(3, n)``
        bool, terminated, truncated and success.

        Each is one ``cat``/``stack`` of rows of one dtype, written once, with no type promotion
        (a mixed bool and float ``stack`` costs 4x a plain one for one env). ``out=`` writes into
        the rows of a preallocated buffer would save ~0.5 ms of the cat's ~2 ms at ``n = 65,536``
        but cost more for one env (and into strided views, 3-10x more)."""
        status = [result.reward, result.distance] + ([] if result.angle is None else [result.angle])
        floats = torch.cat([*self._rows(state), torch.stack(status)], 0)
        floats = floats if floats.dtype == torch.float32 else floats.float()
        return floats, torch.stack([result.terminated, result.truncated, result.success])

    def unpack(self, floats: np.ndarray, flags: np.ndarray) -> Transition:
        """``pack``'s outputs as numpy -> a :class:`Transition` without finished episodes.

        The observation arrays are ``(n, ...)`` views of ``floats.T`` (Fortran-ordered: one
        memory row per component); rewards and flags are contiguous rows."""
        d = self.packed_size
        empty = np.zeros(0, dtype=np.int64)
        return Transition(
            obs=self.split(floats[:d].T),
            reward=floats[d],
            terminated=flags[0],
            truncated=flags[1],
            success=flags[2],
            distance=floats[d + 1],
            angle=floats[d + 2] if self.goal_kind is GoalKind.POSE else None,
            final_index=empty,
            final_obs=self.split(floats[:d, :0].T),
        )

    def step_autoreset(self, state: ReachState, action: Tensor) -> tuple[ReachState, Transition]:
        """``step``, then same-step auto-reset of the environments that terminated or truncated.

        One transfer to numpy for the whole batch (plus one for the finished columns). The
        returned observation of a finished environment is the first of its next episode;
        its last observation is in ``final_obs`` (environments ``final_index``).
        """
        state, res = self.step(state, action)
        out, flags = self.pack(state, res)  # new tensors of our own, updated in place below
        idx = (res.terminated | res.truncated).nonzero().squeeze(-1)  # which environments restart: one sync
        d = self.packed_size
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
            out[:d].index_copy_(1, idx, self.observe(fresh))
        tr = self.unpack(out.numpy(force=True), flags.numpy(force=True))
        return state, tr._replace(final_index=idx.numpy(force=True), final_obs=self.split(final.numpy(force=True).T))

    @staticmethod
    def obs_per_env(obs: dict[str, np.ndarray]) -> list[dict[str, np.ndarray]]:
        """An observation dict of ``(m, ...)`` arrays -> ``m`` per-environment dicts of row views
        (for the finished episodes' last observations; dict literals over zipped rows: 1.7x a
        dict of indexed arrays per environment)."""
        keys = ("observation", "achieved_goal", "desired_goal")
        return [{"observation": o, "achieved_goal": a, "desired_goal": d} for o, a, d in zip(*(obs[k] for k in keys))]

    def split(self, packed: np.ndarray) -> dict[str, np.ndarray]:
        """Split observations ``(..., D)`` (last axis) into the goal-env observation dict.

        The arrays are views of ``packed`` (no copy), and the achieved goal is stored once:
        the end of ``observation`` and ``achieved_goal`` are the same memory. Every step
        packs into a new array, so a returned observation is never overwritten later."""
        o, g = self.observation_size, self.goal_size
        return {
            "observation": packed[..., :o],
            "achieved_goal": packed[..., o - g : o],
            "desired_goal": packed[..., o : o + g],
        }

    def check_action(self, action, n: int) -> Tensor:
        """Actions ``(n, nj)`` (or ``(nj,)`` for one env), numpy or torch -> the ``(nj, n)``
        tensor ``step`` takes, in the state's dtype and device.

        Raises ``ValueError`` on a wrong shape or a NaN/inf entry (out-of-range values are
        fine: ``step`` clips them to ``[-1, 1]``).
        """
        nj = self.n_joints
        if isinstance(action, torch.Tensor):
            a = action.to(self.device, self.dtype)
        else:  # numpy all the way to the transposed copy: a fraction of torch's per-call cost
            try:
                a = np.asarray(action, dtype=np.float32 if self.dtype == torch.float32 else np.float64)
            except (TypeError, ValueError):
                raise ValueError(f"action must be numbers of shape ({n}, {nj}), got {action!r}") from None
        if tuple(a.shape) != (n, nj) and not (n == 1 and tuple(a.shape) == (nj,)):
            single = f" (or ({nj},))" if n == 1 else ""
            raise ValueError(f"action must have shape ({n}, {nj}){single}, got {tuple(a.shape)}")
        if not all_finite(a):
            raise ValueError("action contains NaN or inf; actions must be finite (values outside [-1, 1] are clipped)")
        if isinstance(a, torch.Tensor):
            return a.reshape(n, nj).T.contiguous()
        columns = torch.from_numpy(np.ascontiguousarray(a.reshape(n, nj).T))
        return columns if self.device.type == "cpu" else columns.to(self.device)
