"""The reaching task's pure, batched step: one ``step`` drives every env.

:class:`ReachTask` assembles three parts, kept apart:

- the robot, :class:`envs.robot.JointVelocityArm` (``task.arm``): any chain, its limits and
  speeds, the integration of an action into joint angles (which arm: :func:`envs.robot.resolve_robot`);
- the goals, :class:`envs.goals.ReachGoals` (``task.goals``): goal kind, errors, success,
  reward;
- the transport, :class:`envs.transport.Transport` (``task.transport``): actions in, numpy
  observations and results out.

The task itself is immutable configuration with pure batched methods over a
:class:`ReachState` (a tuple of tensors with one column per environment):
``initial_state(keys)``, ``reset_all(state, seeds, rng)``, ``step(state, action)`` (the one
step) and ``step_autoreset(state, action)`` (the step, same-step auto-reset of the finished
environments and one transfer to numpy, for the vector envs); ``step_one`` and ``reset_one`` for
the single env. Where the task allows (position goals without obstacles, float32, CPU, numba) the
step and the resets' goal draws run compiled (``step_compiled``, :mod:`envs.compiled_step`), the
same results but for last bits (docs/envs.md). The envs (``envs.reach``, ``envs.sb3``) only keep
the current state. Randomness is counter-based (``envs.seeding``).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import NamedTuple

import numpy as np
import torch

from iiwa_torch import compiled
from iiwa_torch import kinematics as kin
from iiwa_torch.chain import Chain
from iiwa_torch.checks import as_device, check_instance
from iiwa_torch.collision import Capsules, capsule_clearance, capsule_clearance_of_one
from iiwa_torch.collision.cpu_paths import CLEARANCE_THREADS_BATCH
from iiwa_torch.runtime import in_parts

from .arrays import NUMPY, TORCH, ArrayOps
from .goals import PANDA_GYM_BOX, GoalKind, GoalRegion, ReachGoals, RewardKind
from .robot import JointVelocityArm, default_home, resolve_robot
from .seeding import keys_from_seeds, uniform
from .settings import CollisionKind, ReachSettings, StartKind
from .transport import Transition, Transport
from .world import ObstacleWorld, obstacle_world

__all__ = ["StartKind", "CollisionKind", "ReachState", "StepResult", "ReachTask"]

Tensor = torch.Tensor

_GOAL_CANDIDATES = 8  # goals drawn per reset when a minimum goal distance is asked for
_FREE_CANDIDATES = 2  # goals drawn per round when they must be collision-free (the floor rules out ~11%)
CLEARANCE_RANGE = 1.0  # m: the observed clearance of a capsule saturates here (its gradient reads 0)
_DRAW_ROUNDS = 32  # rounds of draws for a collision-free start, goal or obstacle before the fallback
# from this many envs the compiled goal draws of a reset split over torch's threads: a goal costs about a
# microsecond, a thread pool's call tens (the Panda's vector env, ~3,200 resets a step: 4.3 -> 2.8 ms)
GOAL_THREADS_BATCH = 1024
# Where in each (key, episode) counter stream the redraws of later rounds and the obstacles start
_START_REDRAWS, _GOAL_REDRAWS, _OBSTACLE_DRAWS = 1 << 24, 2 << 24, 3 << 24


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
    counter since seeding. obstacles: ``(10 M, n)`` the obstacle block of the observation
    (:mod:`envs.world`; ``(0, n)`` without obstacles). clearance: ``(K (1 + nj), n)`` the
    observation's clearance rows at ``q`` (:meth:`ReachTask.clearance_rows`; ``(0, n)`` unless
    ``observe_clearance``).
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
    obstacles: Tensor
    clearance: Tensor


class StepResult(NamedTuple):
    """Per-environment outcome of one step, ``(n,)`` each: reward (obs dtype), the
    ``terminated``/``truncated``/``success`` bools, the position distance (m) and the
    orientation error (rad; ``None`` for position goals) and the collision flag (``None``
    when collisions are off)."""

    reward: Tensor
    terminated: Tensor
    truncated: Tensor
    success: Tensor
    distance: Tensor
    angle: Tensor | None
    collision: Tensor | None = None


# ---------------------------------------------------------------------------- task
class ReachTask:
    """Immutable configuration of the reaching task plus its pure batched functions.

    Args:
        robot: the arm (default ``iiwa14()``): a preset name (``"iiwa14"``, ...), ``"panda"`` (the
            Franka Panda of pybullet_data), a URDF file path or a :class:`~iiwa_torch.chain.Chain`;
            it must have ``velocity_limits`` (:func:`envs.robot.resolve_robot`).
        settings: the task's options, a :class:`envs.settings.ReachSettings` (goal, reward, start, dt,
            thresholds, floor, collisions, obstacles, ...: documented there, with their units);
            ``options``, its fields as keywords (``ReachTask(goal="pose", dt=0.02)``), override it.
        end_link: a URDF robot's end link (needed where the file branches; the Panda's default:
            ``panda_grasptarget``, between the fingertips).
        capsules: the arm's :class:`~iiwa_torch.collision.Capsules` (default: a preset's model, or
            one fitted to the URDF's collision meshes; a plain ``Chain`` that checks collisions needs it).
        home: start posture for ``start="home"`` (default :func:`envs.robot.default_home`:
            :data:`iiwa_torch.robots.IIWA_HOME` for the iiwa presets, else zeros if free, else the middle of
            the limits; it must lie within the limits).
        dtype: float dtype of the state (observations are always float32).
        device: torch device of the state.
    """

    def __init__(
        self,
        robot: Chain | str | None = None,
        *,
        settings: ReachSettings | None = None,
        end_link: str | None = None,
        capsules: Capsules | None = None,
        home=None,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
        **options,
    ) -> None:
        unknown = sorted(set(options) - set(ReachSettings.names()))
        if unknown:
            raise TypeError(f"ReachTask got unknown options {unknown}; the options are {list(ReachSettings.names())}")
        if dtype not in (torch.float32, torch.float64):
            raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        if settings is not None:
            check_instance(settings, ReachSettings, "settings")
        s = ReachSettings(**options) if settings is None else replace(settings, **options)
        #: the options, checked
        self.settings = s
        # the options the step reads, as attributes
        self.start_kind, self.goal_region, self.collision = s.start, s.goal_region, s.collision
        self.observe_clearance, self.collision_penalty, self.dt = s.observe_clearance, s.collision_penalty, s.dt
        self.goal_min_distance, self.max_episode_steps = s.goal_min_distance, s.max_episode_steps
        self.terminate_on_success = s.terminate_on_success
        self.dtype, self.device = dtype, as_device(device)
        chain, capsules = resolve_robot(robot, end_link, capsules, checked=s.collision is not CollisionKind.OFF)
        self.arm = JointVelocityArm(chain, s.dt, default_home(chain, capsules, s.floor) if home is None else home,
                                    dtype, self.device)
        self.goals = ReachGoals(s.goal, s.reward, s.distance_threshold, s.orientation_threshold, s.orientation_weight)
        #: the chain (the task's own copy, in its dtype and device)
        self.robot = self.arm.chain
        #: the floor, the capsules and the obstacles (``None`` when collisions are off)
        self.world = None
        if s.collision is not CollisionKind.OFF:
            self.world = ObstacleWorld(self.robot, capsules, s.floor, s.obstacles)
            if not bool(self.world.clearance(self.arm.home[None]) > 0):
                raise ValueError(f"home {self.arm.home.tolist()} collides with the floor or the arm itself")
        block = 0 if self.world is None else self.world.block_size
        sensed = len(self.world.capsules.names) * (1 + self.arm.n_joints) if s.observe_clearance else 0
        self.transport = Transport(self.arm.n_joints, self.goals.size, dtype, self.device, block, sensed)
        #: ``(nj,)`` rad per step at ``|a| = 1``
        self.max_step = self.arm.max_step
        self._home_goal = self.goal_of(self.arm.home[:, None])  # (g, 1): every episode from home starts there
        self._step_constants = self._compiled_step_constants()
        self._reset_constants = self._compiled_reset_constants()

    def _compiled_step_constants(self) -> tuple | None:
        """The constant arguments of :func:`envs.compiled_step.reach_step` for this task, or ``None`` where
        the envs step by :meth:`step` and ``pack`` instead: without numba, off the CPU, in float64, for
        pose goals, with obstacles or with observed clearances."""
        world = self.world
        if not (compiled.ENABLED and self.device.type == "cpu" and self.dtype == torch.float32
                and self.goal_kind is GoalKind.POSITION and not self.observe_clearance
                and (world is None or not world.slots)):
            return None
        from .compiled_step import reach_step

        arm = torch.stack([self.arm.lower, self.arm.upper, self.arm.max_step]).numpy()
        if world is None:  # nothing checked: no capsules (the kernel's argument types all the same)
            index, radius = np.zeros(0, dtype=np.int64), np.zeros((0, 1))
            clearance = (index, np.zeros((0, 4, 2)), index, index, radius, index, radius)
        else:
            tables = world.capsules.numpy_tables()
            floors = tables["floor"] if world.floor is not None else tables["floor"][:0]
            clearance = (*(tables[k] for k in ("frames", "local", "first", "second", "pair_radius")), floors,
                         tables["floor_radius"])
        s = self.settings
        settings = np.array([self.goals.distance_threshold, s.collision_penalty,
                             -1 if s.max_episode_steps is None else s.max_episode_steps, world is not None,
                             0.0 if world is None or world.floor is None else world.floor, s.terminate_on_success,
                             s.collision is CollisionKind.TERMINATE, self.goals.reward_kind is RewardKind.SPARSE])
        return reach_step, arm, clearance, settings

    def _compiled_reset_constants(self) -> tuple | None:
        """The constant arguments of :func:`envs.compiled_step.reach_reset_one` (after the key and the
        episode), or ``None`` where one env's reset is :meth:`reset_all`'s: where the step is not
        compiled, for random starts or a minimum goal distance."""
        if self._step_constants is None or self.start_kind is not StartKind.HOME or self.goal_min_distance > 0:
            return None
        from .compiled_step import draw_goals, reach_reset_one

        _, _, clearance, settings = self._step_constants
        arm = self.arm
        box = np.array(PANDA_GYM_BOX if self.goal_region is GoalRegion.PANDA_GYM else np.zeros((0, 3)), np.float32)
        constants = (torch.stack([arm.draw_lower, arm.draw_upper]).numpy(), arm.home[:, None].numpy(),
                     self._home_goal.numpy())
        return (reach_reset_one, draw_goals), constants, clearance, settings, box

    def clearance_rows(self, q: Tensor, obstacles: Tensor) -> tuple[Tensor, Tensor]:
        """Joint angles ``(nj, n)`` and the obstacle block ``(10 M, n)`` -> the observation's clearance rows
        ``(K (1 + nj), n)`` in ``q``'s dtype: each capsule's clearance (m,
        :func:`iiwa_torch.collision.capsule_clearance`), then its gradient ``(K, nj)`` (m/rad), both read
        as ``CLEARANCE_RANGE`` and zeros where the capsule is farther than that; and whether each
        configuration collides ``(n,)`` (its least capsule clearance below 0: the world's clearance)."""
        world = self.world
        xp = NUMPY if q.shape[1] == 1 and self.device.type == "cpu" else TORCH  # as step's
        if xp is NUMPY and not world.slots:  # one env, the floor and itself: a closed form (float64 inside)
            dtype = q.numpy().dtype
            distance, gradient = (x[None].astype(dtype, copy=False) for x in capsule_clearance_of_one(
                self.robot, q, world.floor, world.capsules))
        else:  # the envs step in inference mode, whose tensors autograd cannot record: copies made outside it
            with torch.inference_mode(False):
                block = obstacles.clone() if world.slots else None
                distance, gradient = (xp.of(x) for x in capsule_clearance(
                    self.robot, q.T.clone(), obstacle_world(block, world.floor), world.capsules))
        near = distance < CLEARANCE_RANGE
        gradient = xp.where(near[..., None], gradient, 0.0)
        rows = [xp.where(near, distance, CLEARANCE_RANGE).T, gradient.reshape(distance.shape[0], -1).T]
        return xp.tensor(xp.concatenate(rows, 0)), xp.tensor((distance < 0).any(-1))

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
        return self._new_episodes(*self._episodes(state, seeds, rng))

    def _episodes(self, state: ReachState | None, seeds: list, rng: np.random.Generator) -> tuple[Tensor, Tensor]:
        """The keys and episode numbers ``(n,)`` each of the episodes :meth:`reset_all` starts."""
        if state is not None and all(s is None for s in seeds):
            return state.key, state.episode + 1  # every environment's next episode
        fresh = rng.integers(2**63, size=len(seeds)).tolist()
        key = keys_from_seeds([f if s is None else s for f, s in zip(fresh, seeds)], self.device)
        return key, torch.zeros_like(key)

    def reset_one(self, state: ReachState | None, seed: int | None, rng: np.random.Generator
                  ) -> tuple[ReachState, np.ndarray, np.ndarray]:
        """One CPU environment's reset as the single env takes it (:meth:`reset_all` of ``[seed]``) -> the new
        state and the rows of ``transport.pack`` as numpy, as :meth:`step_one`. From home (position goals, no
        obstacles, float32, numba installed, no minimum goal distance) one compiled call
        (:func:`envs.compiled_step.reach_reset_one`: :meth:`reset_all`'s goal bit for bit, tested)."""
        if self._reset_constants is None:
            with torch.inference_mode():
                state = self.reset_all(state, [seed], rng)
                floats, flags = (part.numpy(force=True)[:, 0] for part in self._reset_rows(state))
            return state, floats, flags
        key, episode = self._episodes(state, [seed], rng)
        (kernel, _), (draw, home, home_goal), clearance, settings, box = self._reset_constants
        nj = self.arm.n_joints
        out, flags = np.empty((3 * nj + 8, 1), dtype=np.float32), np.empty(4, dtype=np.bool_)
        kernel(key.numpy(), episode.numpy(), draw, home, home_goal, *self.robot.geometry(self.dtype).float_arrays,
               *clearance, settings, box, _DRAW_ROUNDS, _GOAL_REDRAWS, out, flags)
        blank = torch.zeros(0, 1)
        goal = torch.from_numpy(out[3 * nj + 3 : 3 * nj + 6].copy())  # the episode's own: not the observation's
        state = _state_of_rows(home.copy(), out, goal, np.zeros(1, dtype=np.int64), key, episode, blank, blank)
        return state, out[:, 0], flags if self.world is not None else flags[:3]

    def _random_starts(self, key: Tensor, episode: Tensor) -> Tensor:
        """Uniform starts within the limits ``(n, nj)`` (draws 0..nj-1 of each key's stream), those
        that collide redrawn from later parts of the stream (home where 32 rounds fail)."""
        arm, world, n, nj = self.arm, self.world, key.shape[0], self.arm.n_joints

        def draw_start(idx: Tensor, r: int) -> tuple[Tensor, Tensor]:
            u = uniform(key[idx], episode[idx], 0 if r == 0 else _START_REDRAWS + r * nj, nj, self.dtype)
            q = arm.configurations(u)  # (m, nj)
            if world is None:
                return torch.ones(len(idx), dtype=torch.bool, device=q.device), q.T
            return world.is_free(q), q.T

        return _first_found(n, draw_start, lambda: arm.home[:, None].expand(nj, n), self.device).T

    def _new_episodes(self, key: Tensor, episode: Tensor) -> ReachState:
        """Start episode ``episode`` for each key: draw the start, the obstacles and the goal.

        Draws 0..nj-1 are the start, then the goal candidates; episodes from home skip the
        start's draws (counter-based: the goals' draws stay the same). With collision checks,
        candidates that collide are redrawn in later rounds from other parts of the stream,
        for the environments that need it only (so each environment's draws stay its own)."""
        arm, world = self.arm, self.world
        n, nj = key.shape[0], arm.n_joints
        home = self.start_kind is StartKind.HOME
        # the start's goal: from home, home's; else computed with the first goal candidates (in one
        # FK call whose batch, and so whose kernel and rounding, are those of the first versions)
        start_goal = {"all": self._home_goal.expand(-1, n)} if home else {}
        start = arm.home.expand(n, nj) if home else self._random_starts(key, episode)
        blank = start.new_zeros(0, n)
        obstacles = blank if world is None or not world.slots else world.draw(key, episode, start, _OBSTACLE_DRAWS,
                                                                              _DRAW_ROUNDS)
        goal = self._goals(key, episode, start, start_goal, obstacles) if self._reset_constants is None else \
            self._goals_compiled(key, episode)
        q = start.T.clone(memory_format=torch.contiguous_format)  # never a view of home
        clearance = self.clearance_rows(q, obstacles)[0] if self.observe_clearance else blank
        return ReachState(
            q=q,
            # in float64, then rounded: as one env's compiled reset (torch's float32 ones miss the last bit of some)
            cos_q=torch.cos(q.double()).to(q.dtype),
            sin_q=torch.sin(q.double()).to(q.dtype),
            velocity=torch.zeros(nj, n, dtype=self.dtype, device=self.device),
            goal=goal.contiguous(),
            achieved=start_goal["all"].clone(memory_format=torch.contiguous_format),
            t=torch.zeros(n, dtype=torch.int64, device=self.device),
            key=key,
            episode=episode,
            obstacles=obstacles,
            clearance=clearance,
        )

    def _goals_compiled(self, key: Tensor, episode: Tensor) -> Tensor:
        """:meth:`_goals` of episodes from home, position goals without obstacles, in one compiled call
        (:func:`envs.compiled_step.draw_goals`, split over torch's threads from :data:`GOAL_THREADS_BATCH`
        environments) -> ``(3, n)``: the same candidates and choices; each goal is the end point in float64
        rounded once, as one env's (tested), where :meth:`_goals` rounds a batch's above ``SMALL_BATCH``
        through its float32 FK."""
        (_, kernel), (draw, _, home_goal), clearance, settings, box = self._reset_constants
        keys, episodes, goal = key.numpy(), episode.numpy(), np.empty((3, key.shape[0]), dtype=np.float32)
        args = (keys, episodes, draw, home_goal, *self.robot.geometry(self.dtype).float_arrays, *clearance, settings,
                box, _DRAW_ROUNDS, _GOAL_REDRAWS)
        in_parts(key.shape[0], lambda start, stop: kernel(*args, start, stop, goal), GOAL_THREADS_BATCH)
        return torch.from_numpy(goal)

    def _goals(self, key: Tensor, episode: Tensor, start: Tensor, start_goal: dict, obstacles: Tensor) -> Tensor:
        """The goals ``(g, n)`` of new episodes from ``start (n, nj)`` among ``obstacles`` (their block); fills
        ``start_goal["all"]``, the start's goal ``(g, n)``, if it is not there (with the first candidates)."""
        arm, world = self.arm, self.world
        n, nj = key.shape[0], arm.n_joints
        far = self.goal_min_distance > 0
        k = _GOAL_CANDIDATES if far else (1 if world is None else _FREE_CANDIDATES)

        def draw_goal(idx: Tensor, r: int) -> tuple[Tensor, Tensor]:
            m = len(idx)
            first = nj if r == 0 else _GOAL_REDRAWS + r * k * nj
            configs = arm.configurations(uniform(key[idx], episode[idx], first, k * nj, self.dtype).view(m, k, nj))
            if "all" in start_goal:
                goals = self.goal_of(configs.reshape(-1, nj).T).view(-1, m, k)
            else:  # the first round, over every environment
                both = torch.cat([start[:, None], configs], 1)
                goals = self.goal_of(both.reshape(-1, nj).T).view(-1, m, k + 1)
                start_goal["all"], goals = goals[:, :, 0], goals[:, :, 1:]
            # the whole block when every env draws (round 0): the block the episode's steps then use
            block = None if world is None or not world.slots else obstacles if m == n else obstacles[:, idx]
            ok = torch.ones(m, k, dtype=torch.bool, device=goals.device) if world is None else \
                world.is_free(configs, block, extra=1)
            rank = -torch.arange(k, dtype=goals.dtype, device=goals.device)
            if far:  # the first valid candidate far enough, else the farthest valid: no loop, no sync
                d = torch.linalg.vector_norm(goals[:3] - start_goal["all"][:3, idx, None], dim=0)  # (m, k)
                rank = torch.where(d >= self.goal_min_distance, rank, d - 1e9)
            score = torch.where(ok, rank, -math.inf)
            return ok.any(-1), goals[:, torch.arange(m, device=goals.device), score.argmax(-1)]

        if self.goal_region is GoalRegion.PANDA_GYM:  # draws nj.. as the candidates would; nothing to check
            low, high = (start.new_tensor(corner)[:, None] for corner in PANDA_GYM_BOX)
            start_goal.setdefault("all", self.goal_of(start.T))
            return low + uniform(key, episode, nj, 3, self.dtype).T * (high - low)  # (3, n)
        if world is not None:  # the last resort (never seen: 32 rounds of collisions): the start's own goal
            return _first_found(n, draw_goal, lambda: start_goal["all"], self.device)
        return draw_goal(torch.arange(n, device=self.device), 0)[1]

    def step(self, state: ReachState, action: Tensor) -> tuple[ReachState, StepResult]:
        """Apply actions ``(nj, n)`` (clipped to ``[-1, 1]``): integrate, clamp to the limits, FK.

        The actions must be finite, in the state's layout, dtype and device:
        ``task.transport.check_action`` makes them so from the envs' ``(n, nj)`` batches.
        One environment on the CPU runs the same formulas on numpy views of its tensors
        (:data:`envs.arrays.NUMPY`: each op a fraction of a torch op's cost); more, on torch.
        """
        xp = NUMPY if state.q.shape[1] == 1 and self.device.type == "cpu" else TORCH
        q, velocity = self.arm.integrate(xp.of(state.q), xp.of(action), xp)
        q_t = xp.tensor(q)
        cos_t, sin_t = torch.cos(q_t), torch.sin(q_t)  # torch's on both paths: one env's equal a batch's
        world = self.world
        block = state.obstacles if world is not None and world.slots else None
        collision, clearance = None, state.clearance
        if self.observe_clearance:  # the rows' capsule clearances say whether it collides
            clearance, collision = self.clearance_rows(q_t, state.obstacles)
            collision = xp.of(collision)
        if xp is NUMPY:  # one env: its end frame in Python floats for the goal
            achieved = self.goals.goal_of_frame(kin.frame_lists(self.robot.geometry(self.dtype), q_t)[1], self.dtype)
            if world is not None and collision is None:
                collision = np.array([world.clearance_of_one(q_t, block) < 0])
        else:
            achieved = self.goal_of(q_t, (cos_t, sin_t))
            if world is not None and collision is None:  # one clearance call for the batch
                collision = world.clearance(q_t.T, block) < 0
        observed = (achieved, state.goal) if self.dtype == torch.float32 else (achieved.float(), state.goal.float())
        # the reward of the goals as observed, in float32
        dist, angle, success = self.goals.errors(*map(xp.of, observed), xp)
        reward = self.penalised(self.goals.reward_of(dist, angle, success, xp), collision, xp)
        t = xp.of(state.t) + 1
        terminated = success if self.terminate_on_success else xp.zeros_like(success)
        if self.collision is CollisionKind.TERMINATE:
            terminated = terminated | collision
        truncated = xp.zeros_like(success) if self.max_episode_steps is None else t >= self.max_episode_steps
        new = ReachState(q_t, cos_t, sin_t, xp.tensor(velocity), state.goal, achieved, xp.tensor(t), state.key,
                         state.episode, state.obstacles, clearance)
        result = (reward, terminated, truncated, success, dist, angle, collision)
        return new, StepResult(*(None if x is None else xp.tensor(x) for x in result))

    def step_one(self, state: ReachState, action) -> tuple[ReachState, np.ndarray, np.ndarray]:
        """One CPU environment's step as the single env takes it: ``action`` ``(nj,)`` as the user gave it
        (checked as :meth:`envs.transport.Transport.check_action` does) -> the new state and the rows of
        ``transport.pack`` as numpy, floats ``(D + k,)`` and flags ``(3,)`` or ``(4,)``: one compiled call
        where it applies (:meth:`step_compiled`), else :meth:`step` and ``pack``."""
        io = self.transport
        if self._step_constants is None:
            with torch.inference_mode():
                state, res = self.step(state, io.check_action(action, 1))
                floats, flags = (part.numpy(force=True)[:, 0] for part in io.pack(state, res))
            return state, floats, flags
        state, floats, flags = self.step_compiled(state, io.check_action_one(action).reshape(-1, 1))
        return state, floats[:, 0], flags[:, 0]

    def step_compiled(self, state: ReachState, action: np.ndarray) -> tuple[ReachState, np.ndarray, np.ndarray]:
        """:meth:`step` and ``transport.pack`` of ``n`` CPU environments in one compiled pass
        (:func:`envs.compiled_step.reach_step`, split over torch's threads from
        :data:`~iiwa_torch.collision.cpu_paths.CLEARANCE_THREADS_BATCH` environments), for tasks of position
        goals without obstacles or observed clearances, float32, with numba (``None`` constants otherwise):
        finite actions ``(nj, n)`` float32 -> the new state, floats ``(D + k, n)`` float32 and flags
        ``(3 or 4, n)`` as numpy. The new state's rows are views of the floats; its results are
        :meth:`step`'s, but for the last bit of the cosines and sines of q and of the end point (tested)."""
        kernel, arm, clearance, settings = self._step_constants
        nj, n = action.shape
        new_q, out, flags = np.empty((nj, n), dtype=np.float32), np.empty((3 * nj + 8, n), dtype=np.float32), \
            np.empty((4, n), dtype=np.bool_)
        t = state.t.numpy() + 1
        args = (state.q.numpy(), action, arm, *self.robot.geometry(self.dtype).float_arrays, *clearance, settings,
                state.goal.numpy(), t)
        in_parts(n, lambda start, stop: kernel(*args, start, stop, new_q, out, flags), CLEARANCE_THREADS_BATCH)
        flags = flags if self.world is not None else flags[:3]
        return _state_of_rows(new_q, out, state.goal, t, *state[7:]), out, flags

    def penalised(self, reward, collision, xp: ArrayOps = TORCH):
        """``reward - collision_penalty`` where ``collision`` (``None``: no collision checked)."""
        return reward if collision is None else xp.where(collision, reward - self.collision_penalty, reward)

    def compute_reward(self, achieved_goal, desired_goal, info=None) -> np.ndarray:
        """The envs' ``compute_reward``: goals ``(..., g)``, numpy or torch -> ``(...)`` float32 numpy,
        the step's reward bit for bit. The collision penalty is read from ``info``: a dict whose
        ``collision`` is a bool or an array (vector envs), or a sequence of per-env dicts (SB3,
        HER); no ``info`` (or no ``collision`` in it): no penalty."""
        reward = self.goals.compute_reward(achieved_goal, desired_goal)
        collision = _collision_of(info)
        if collision is None or self.world is None:
            return reward
        try:
            flags = torch.as_tensor(np.broadcast_to(collision, reward.shape).copy())
        except ValueError:
            raise ValueError(f"info's collision flags {collision.shape} do not fit the rewards {reward.shape}"
                             ) from None
        return self.penalised(torch.from_numpy(np.asarray(reward)), flags).numpy()

    def reset_transition(self, state: ReachState) -> Transition:
        """The observation and status of a state just reset, as numpy (one transfer)."""
        return self.transport.unpack(*(part.numpy(force=True) for part in self._reset_rows(state)))

    def _reset_rows(self, state: ReachState) -> tuple[Tensor, Tensor]:
        """``transport.pack`` of a state just reset: its observation, reward and errors, and its flags."""
        dist, angle, success = self.goals.errors(state.achieved.float(), state.goal.float())
        no = torch.zeros_like(success)
        collision = None if self.world is None else no  # starts are collision-free by construction
        status = StepResult(self.goals.reward_of(dist, angle, success), no, no, success, dist, angle, collision)
        return self.transport.pack(state, status)

    def step_autoreset(self, state: ReachState, action: Tensor) -> tuple[ReachState, Transition]:
        """``step``, then same-step auto-reset of the environments that terminated or truncated.

        One transfer to numpy for the whole batch (plus one for the finished columns). The
        returned observation of a finished environment is the first of its next episode;
        its last observation is in ``final_obs`` (environments ``final_index``).
        """
        io = self.transport
        if self._step_constants is None or action.device.type != "cpu":
            state, res = self.step(state, action)
            out, flags = io.pack(state, res)  # new tensors of our own, updated in place below
        else:
            state, out, flags = self.step_compiled(state, action.numpy())
            out, flags = torch.from_numpy(out), torch.from_numpy(flags)
        idx = (flags[0] | flags[1]).nonzero().squeeze(-1)  # which environments restart: one sync
        d = io.packed_size
        # (D, m) copy: the finished episodes' last observations (index_select: 2x faster than out[:d, idx])
        final = out[:d].index_select(1, idx)
        if idx.numel():
            fresh = self._new_episodes(state.key[idx], state.episode[idx] + 1)
            # q and what follows from it, velocity and t were created by this step: update them in
            # place; goal and episode are the caller's tensors: copy them.
            for name in ("q", "cos_q", "sin_q", "velocity", "achieved", "t", "clearance"):
                mine = getattr(state, name)
                mine.index_copy_(mine.ndim - 1, idx, getattr(fresh, name))
            state = state._replace(
                goal=state.goal.index_copy(1, idx, fresh.goal), episode=state.episode.index_copy(0, idx, fresh.episode),
                obstacles=state.obstacles.index_copy(1, idx, fresh.obstacles),
            )
            out[:d].index_copy_(1, idx, io.observe(fresh))
        tr = io.unpack(out.numpy(force=True), flags.numpy(force=True))
        return state, tr._replace(final_index=idx.numpy(force=True), final_obs=io.split(final.numpy(force=True).T))


def _state_of_rows(q: np.ndarray, rows: np.ndarray, goal: Tensor, t: np.ndarray, *rest: Tensor) -> ReachState:
    """The state whose angles are ``q (nj, n)`` and steps ``t (n,)``, its cos q, sin q, motion and achieved
    goal the views of the packed rows ``rows`` (``transport.pack``'s layout) -> no copy; ``rest``: key,
    episode, obstacles and clearance."""
    nj = q.shape[0]
    views = (torch.from_numpy(rows[i * nj : (i + 1) * nj]) for i in range(3))  # cos q, sin q, velocity
    return ReachState(torch.from_numpy(q), *views, goal, torch.from_numpy(rows[3 * nj : 3 * nj + 3]),
                      torch.from_numpy(t), *rest)


def _first_found(n: int, draw, fallback, device: torch.device) -> Tensor:
    """Rounds of ``draw(idx, r) -> (found (m,) bool, values (c, m))`` for the environments ``idx``
    still without a value (round 0: all ``n``), up to ``_DRAW_ROUNDS``; the rest take the columns of
    ``fallback() (c, n)``. -> ``(c, n)``."""
    pending = torch.arange(n, device=device)
    found, values = draw(pending, 0)
    out = values.new_empty(values.shape[0], n)
    for r in range(1, _DRAW_ROUNDS + 1):
        out[:, pending[found]] = values[:, found]
        pending = pending[~found]
        if not pending.numel():
            return out
        if r < _DRAW_ROUNDS:
            found, values = draw(pending, r)
    out[:, pending] = fallback()[:, pending]
    return out


def _collision_of(info):
    """The collision flags of an env's ``info`` (see :meth:`ReachTask.compute_reward`), or None;
    TypeError unless they are booleans."""
    if isinstance(info, dict):
        flags = info.get("collision")
    elif info is None or (isinstance(info, np.ndarray) and info.dtype != object):
        return None
    elif not isinstance(info, (list, tuple, np.ndarray)) or not all(isinstance(i, dict) for i in info):
        raise TypeError(f"info must be a dict, a sequence of per-env dicts or None, got {info!r:.200}")
    else:
        flags = [i.get("collision") for i in info]
        if any(f is None for f in flags):
            return None
    if flags is None:
        return None
    array = np.asarray(flags)
    if array.dtype != np.bool_:
        raise TypeError(f"info['collision'] must be a bool or booleans, got {flags!r}")
    return array
