"""Fixed, seeded goal sets and batched closed-loop rollouts on the pure reaching task.

The training's periodic evaluation and ``train.evaluate`` both use these: a goal set is
the FK of configurations drawn uniformly within the joint limits from a seeded
``torch.Generator`` (the env's own goal distribution, from a separate random stream, so
the goals are held out from training), every arm starting at the task's ``home``
posture. A rollout runs the task's pure ``step`` for a fixed number of steps without
early termination or auto-reset, so the final distance says whether the controller
reaches the goal *and stays there*.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from envs.core import ReachState, ReachTask, StartKind, keys_from_seeds

__all__ = ["GoalSet", "Rollout", "make_goal_set", "rollout", "policy_actor"]


@dataclass(frozen=True)
class GoalSet:
    """``n`` goals: ``pose (n, 4, 4)`` float64 (the FK of ``q_goal``), ``q_goal (n, nj)``, and the
    task's start ``state`` whose ``goal`` rows are these goals."""

    pose: torch.Tensor
    q_goal: torch.Tensor
    state: ReachState

    @property
    def n(self) -> int:
        return self.pose.shape[0]


@dataclass(frozen=True)
class Rollout:
    """A batched rollout of ``T`` steps over ``n`` goals (numpy, float64).

    distance: ``(T + 1, n)`` position error (m) before each step and after the last one.
    angle: ``(T + 1, n)`` orientation error (rad; zero for position goals).
    q: ``(T + 1, n, nj)`` joint angles (rad) along the way.
    seconds: wall time of the whole rollout (policy and task), s.
    """

    distance: np.ndarray
    angle: np.ndarray
    q: np.ndarray
    seconds: float


def make_goal_set(task: ReachTask, n: int, seed: int) -> GoalSet:
    """``n`` seeded goals for ``task`` (reachable by construction), all starting at ``task.home``."""
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be a positive int, got {n!r}")
    gen = torch.Generator().manual_seed(int(seed))
    robot = task.robot
    q_goal = robot.random_q(n, generator=gen, dtype=torch.float64).to(task.device)  # (n, nj)
    pose = robot.fk(q_goal)  # (n, 4, 4) float64
    if task.start_kind is not StartKind.HOME:
        raise ValueError("goal sets start at the task's home posture: build the task with start='home'")
    start = task.initial_state(keys_from_seeds(range(n), task.device))
    return GoalSet(pose=pose, q_goal=q_goal, state=start._replace(goal=task.goal_of(pose).to(task.dtype)))


Actor = Callable[[dict[str, np.ndarray]], np.ndarray]


def rollout(task: ReachTask, goals: GoalSet, act: Actor, steps: int) -> Rollout:
    """Run ``act`` (observation dict of ``(n, ...)`` float32 arrays -> ``(n, nj)`` actions) for ``steps`` steps."""
    state = goals.state
    dists, angles, qs = [], [], []

    def record(s: ReachState) -> None:
        dist, angle, _ = task.errors(s.achieved.float(), s.goal.float())
        dists.append(dist)
        angles.append(torch.zeros_like(dist) if angle is None else angle)  # None for position goals
        qs.append(s.q)

    start = time.perf_counter()
    record(state)
    for _ in range(steps):
        obs = task.split(task.observe(state).cpu().numpy())
        action = task.check_action(act(obs), goals.n)
        state, _ = task.step(state, action)
        record(state)
    seconds = time.perf_counter() - start
    as_np = lambda xs: torch.stack(xs).double().cpu().numpy()
    return Rollout(distance=as_np(dists), angle=as_np(angles), q=as_np(qs), seconds=seconds)


def policy_actor(model, vec_normalize=None) -> Actor:
    """A deterministic SB3 policy as an actor; ``vec_normalize``: the training's ``VecNormalize`` (or None)."""

    def act(obs: dict[str, np.ndarray]) -> np.ndarray:
        if vec_normalize is not None:
            obs = vec_normalize.normalize_obs(obs)
        action, _ = model.predict(obs, deterministic=True)
        return action

    return act
