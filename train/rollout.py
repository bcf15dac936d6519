"""Fixed, seeded goal sets and closed-loop rollouts, through the public SB3 VecEnv only.

The training's periodic evaluation and ``train.evaluate`` both use these. A goal set is
the first episode of ``n`` environments of ``envs.sb3.IiwaReachVecEnv`` seeded
``base + i``, with ``base = 2**40 + seed * 2**20``: training seeds its environments with
small integers, so these goals are held out from training. Every arm starts at home.

A rollout runs the policy for the env's ``max_episode_steps`` with
``terminate_on_success=False``: no early stop, so the final distance says whether the
controller reached the goal *and stayed there*. A collision does not stop it either: an env
whose ``collision`` is ``"terminate"`` (the default) is rolled out with ``"penalize"``, the
same dynamics and goals, so the whole path is there to be checked for collisions. Joint angles
are read back from the observation's documented ``cos q``, ``sin q`` entries.

For the IK solvers a goal set also carries full goal poses: for position goals, the
orientation comes from ``IiwaReachPose-v0`` with the same seeds and the env's other options
(its obstacles: the same configuration is drawn for the goal; this is checked position by
position, and obstacle by obstacle). It carries the env's world too, so that every method is
checked in the same one: the floor, the arm's own capsules and, for ``IiwaReachObstacles-v0``,
each goal's obstacles as its env observed them at reset (``GoalSet.world``). A rollout also keeps
the env's own collision flag of every configuration.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

__all__ = ["GoalSet", "Rollout", "PolicyEvaluator", "make_goal_set", "rollout", "policy_actor", "held_out_seed",
           "reached", "summarise_finals"]



def held_out_seed(seed: int) -> int:
    """First environment seed of goal set ``seed`` (far from the small seeds training uses)."""
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**20:
        raise ValueError(f"seed must be an int in [0, 2**20), got {seed!r}")
    return 2**40 + seed * 2**20


def _env(env_id: str, n: int, seed: int, env_kwargs: dict[str, Any] | None):
    from envs.sb3 import IiwaReachVecEnv

    options = {**(env_kwargs or {}), "terminate_on_success": False, "start": "home"}
    if options.get("collision", "terminate") == "terminate":
        options["collision"] = "penalize"
    return IiwaReachVecEnv(n, env_id, seed=held_out_seed(seed), **options)


@dataclass(frozen=True)
class GoalSet:
    """``n`` goals of ``env_id``: ``desired_goal (n, g)`` float32 as the env observes them and
    ``pose (n, 4, 4)`` float64 goal poses (for the IK solvers).

    The world every method is checked in: ``robot`` (the env's chain), ``floor`` (m, or None),
    ``obstacles (n, SLOT_SIZE * M)`` float32, each goal's obstacle block as its env observes it
    at reset (:mod:`envs.world`; None for an env without obstacles) and ``collision_checked``
    (False for ``collision="off"``: then :meth:`world` is None).
    """

    env_id: str
    seed: int
    env_kwargs: dict[str, Any] = field(repr=False)
    desired_goal: np.ndarray = field(repr=False)
    pose: torch.Tensor = field(repr=False)
    robot: Any = field(repr=False)
    floor: float | None
    obstacles: np.ndarray | None = field(repr=False)
    collision_checked: bool
    #: the capsules the env checks (None when it checks none)
    capsules: Any = field(default=None, repr=False)

    @property
    def pose_goals(self) -> bool:
        """Whether the env's goals are poses (else positions)."""
        return self.desired_goal.shape[1] > 3

    @property
    def n(self) -> int:
        return self.desired_goal.shape[0]

    def world(self, dtype: torch.dtype = torch.float64):
        """The env's world of every goal: an :class:`iiwa_torch.collision.World` with the floor and,
        with obstacles, a leading batch dim ``(n,)`` (goal ``i``'s obstacles); None when the env
        checks no collisions."""
        from envs.world import obstacle_world

        if not self.collision_checked:
            return None
        block = None if self.obstacles is None else torch.as_tensor(self.obstacles.T, dtype=dtype)
        return obstacle_world(block, self.floor)

    def goal_world(self, i: int):
        """Goal ``i``'s world, unbatched, with its active obstacles only (to draw it); None as :meth:`world`."""
        from envs.world import active_obstacles
        from iiwa_torch.collision import World

        if not self.collision_checked:
            return None
        if self.obstacles is None:
            return World(floor=self.floor)
        return active_obstacles(torch.as_tensor(self.obstacles[i], dtype=torch.float64), self.floor)


@dataclass(frozen=True)
class Rollout:
    """A closed-loop rollout of ``T`` steps over ``n`` goals (numpy float64).

    distance: ``(T + 1, n)`` position error (m) at reset and after each step.
    angle: ``(T + 1, n)`` orientation error (rad; zeros for position goals and at reset).
    q: ``(T + 1, n, nj)`` joint angles (rad) along the way.
    seconds: wall time of the whole rollout (policy and env), s.
    act_seconds: the part of it spent in ``act`` (the policy alone), s.
    collision: ``(T + 1, n)`` bool, the env's own ``info["collision"]`` at each configuration (its
    clearance in float32 below 0; the reset configuration is collision-free by construction), or
    None for an env that checks no collisions.
    """

    distance: np.ndarray
    angle: np.ndarray
    q: np.ndarray
    seconds: float
    act_seconds: float
    collision: np.ndarray | None = None


def make_goal_set(env_id: str, n: int, seed: int, env_kwargs: dict[str, Any] | None = None) -> GoalSet:
    """``n`` held-out goals of ``env_id`` (one of ``envs.ENV_IDS``) for goal-set ``seed``."""
    from envs.goals import decode_pose_goal

    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be a positive int, got {n!r}")
    env_kwargs = dict(env_kwargs or {})
    env = _env(env_id, n, seed, env_kwargs)
    obs = env.reset()
    desired, task = obs["desired_goal"], env.task
    obstacles = task.transport.obstacles_of(obs["observation"]).copy() if task.transport.obstacle_size else None
    # the same env with pose goals (its obstacles, say, alike) draws the same goal configurations
    if desired.shape[1] > 3:
        pose_goal = desired
    else:
        pose_env = _env(env_id, n, seed, {**env_kwargs, "goal": "pose"})
        pose_obs = pose_env.reset()
        pose_goal = pose_obs["desired_goal"]
        same = obstacles is None or np.array_equal(pose_env.task.transport.obstacles_of(pose_obs["observation"]),
                                                   obstacles)
        if not same or not np.allclose(pose_goal[:, :3], desired[:, :3], atol=1e-6):
            raise RuntimeError(f"{env_id} with pose goals draws other goals for the same seeds: no goal poses")
    checked = task.world is not None
    return GoalSet(env_id, seed, env_kwargs, desired, decode_pose_goal(pose_goal), robot=task.robot,
                   floor=task.world.floor if checked else None, obstacles=obstacles, collision_checked=checked,
                   capsules=task.world.capsules if checked else None)


Actor = Callable[[dict[str, np.ndarray]], np.ndarray]


def rollout(goals: GoalSet, act: Actor) -> Rollout:
    """Run ``act`` (observation dict of ``(n, ...)`` arrays -> ``(n, nj)`` actions) on every goal."""
    from envs.transport import joint_angles

    env = _env(goals.env_id, goals.n, goals.seed, goals.env_kwargs)
    steps = env.task.max_episode_steps
    lower, upper = (x.double().cpu().numpy() for x in (env.task.arm.lower, env.task.arm.upper))

    def joints(observation: np.ndarray) -> np.ndarray:
        return joint_angles(observation, lower, upper)

    start = time.perf_counter()
    obs = env.reset()
    if not np.array_equal(obs["desired_goal"], goals.desired_goal):
        raise RuntimeError("the env no longer draws this goal set's goals for its seeds")
    dist = [np.linalg.norm(obs["achieved_goal"][:, :3] - obs["desired_goal"][:, :3], axis=-1)]
    angle = [np.zeros(goals.n)]
    q = [joints(obs["observation"])]
    checked = env.task.world is not None
    collision = [np.array([i["collision"] for i in env.reset_infos])] if checked else None
    act_seconds = 0.0
    for t in range(steps):
        tic = time.perf_counter()
        action = act(obs)
        act_seconds += time.perf_counter() - tic
        obs, _, done, infos = env.step(action)
        dist.append(np.array([i["distance"] for i in infos]))
        angle.append(np.array([i.get("orientation_error", 0.0) for i in infos]))
        if checked:
            collision.append(np.array([i["collision"] for i in infos]))
        last = np.stack([i["terminal_observation"]["observation"] for i in infos]) if t == steps - 1 \
            else obs["observation"]
        q.append(joints(last))
    seconds = time.perf_counter() - start
    if not all(i.get("TimeLimit.truncated", False) for i in infos):
        raise RuntimeError(f"expected every episode to end by time limit after {steps} steps")
    return Rollout(np.array(dist, dtype=np.float64), np.array(angle, dtype=np.float64),
                   np.array(q, dtype=np.float64), seconds, act_seconds,
                   None if collision is None else np.array(collision, dtype=bool))


def policy_actor(model, vec_normalize=None) -> Actor:
    """A deterministic SB3 policy as an actor: one network call per step for the whole batch.

    ``vec_normalize``: the training's ``VecNormalize`` (or None); its observation statistics
    are applied in torch exactly as ``VecNormalize.normalize_obs`` does. The actions are
    those of ``model.predict(obs, deterministic=True)`` before its clipping to the action
    box (the env clips them to ``[-1, 1]``).
    """
    policy = model.policy
    policy.set_training_mode(False)
    stats = {}
    if vec_normalize is not None and vec_normalize.norm_obs:
        for key in vec_normalize.norm_obs_keys:
            rms = vec_normalize.obs_rms[key]
            std = np.sqrt(rms.var + vec_normalize.epsilon)
            stats[key] = (torch.as_tensor(rms.mean, dtype=torch.float32), torch.as_tensor(std, dtype=torch.float32))
    clip = float(vec_normalize.clip_obs) if vec_normalize is not None else 0.0

    def act(obs: dict[str, np.ndarray]) -> np.ndarray:
        x = {key: torch.as_tensor(value, dtype=torch.float32) for key, value in obs.items()}
        for key, (mean, std) in stats.items():
            x[key] = ((x[key] - mean) / std).clamp(-clip, clip)
        with torch.no_grad():
            return policy._predict(x, deterministic=True).numpy()

    return act


def reached(final: np.ndarray, threshold: float, angle: np.ndarray | None = None,
            orientation_threshold: float | None = None) -> np.ndarray:
    """``(n,)`` bool: final distance (m) below ``threshold`` and, with final angles (rad), angle below
    ``orientation_threshold``."""
    ok = final < threshold
    return ok if angle is None else ok & (angle < orientation_threshold)


def summarise_finals(final: np.ndarray, threshold: float, angle: np.ndarray | None = None,
                     orientation_threshold: float | None = None) -> dict[str, float]:
    """Success rate, median and 95th percentile of final distances ``(n,)`` (m); with final angles
    ``(n,)`` (rad) ``success`` needs both thresholds and ``success_position``, ``median_angle`` are added."""
    out = {
        "success": float(np.mean(reached(final, threshold))),
        "median_distance": float(np.median(final)),
        "p95_distance": float(np.percentile(final, 95)),
    }
    if angle is not None:
        out["success_position"] = out["success"]
        out["success"] = float(np.mean(reached(final, threshold, angle, orientation_threshold)))
        out["median_angle"] = float(np.median(angle))
    return out


@dataclass(frozen=True)
class PolicyEvaluator:
    """A deterministic policy on a fixed goal set: one batched closed-loop rollout and its summary.

    The one evaluation of ``train.train`` (periodic) and ``train.evaluate`` (the policy's row).
    ``distance_threshold`` in m; ``orientation_threshold`` in rad, for pose goals only (else None).
    """

    goals: GoalSet
    distance_threshold: float
    orientation_threshold: float | None = None

    def rollout(self, model, vec_normalize=None) -> Rollout:
        return rollout(self.goals, policy_actor(model, vec_normalize))

    def summary(self, r: Rollout) -> dict[str, float]:
        """:func:`summarise_finals` of the final errors; for an env that checks collisions also
        ``collisions`` (share of rollouts with a colliding configuration, of the ``T + 1``: the env's
        own flags, :attr:`Rollout.collision`, computed by its step anyway) and
        ``success_collision_free`` (success and no collision)."""
        angle = r.angle[-1] if self.orientation_threshold is not None else None
        out = summarise_finals(r.distance[-1], self.distance_threshold, angle, self.orientation_threshold)
        if r.collision is not None:
            collided = r.collision.any(0)
            ok = reached(r.distance[-1], self.distance_threshold, angle, self.orientation_threshold)
            out["collisions"] = float(np.mean(collided))
            out["success_collision_free"] = float(np.mean(ok & ~collided))
        return out

    def __call__(self, model, vec_normalize=None) -> tuple[dict[str, float], float]:
        """``(summary, seconds of the rollout)``."""
        r = self.rollout(model, vec_normalize)
        return self.summary(r), r.seconds
