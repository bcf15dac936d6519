"""A trained policy's rollouts as joint paths, for the viewer's playback (``iiwa-torch view --policy``).

The ``iiwa-torch`` command finds :func:`policy_rollouts` through the ``iiwa_torch.playback`` entry
point (``pyproject.toml``), so the library itself never imports the training code.
"""

from __future__ import annotations

from pathlib import Path

import torch

__all__ = ["policy_rollouts"]


def policy_rollouts(policy: Path, n_goals: int, seed: int) -> tuple[str, torch.Tensor, float, torch.Tensor]:
    """A policy folder (a ``train.train`` run or a shipped policy) rolled out on ``n_goals`` held-out
    goals of its env (goal-set ``seed``, as ``train.evaluate`` draws them) -> the robot's name, joint
    paths ``q (n_goals, T + 1, n)`` (rad, float64), the control period ``dt`` (s) and the goal
    positions ``(n_goals, 3)`` (m). ``FileNotFoundError`` if the folder holds no policy."""
    from envs.sb3 import IiwaReachVecEnv
    from train.evaluate import load_policy
    from train.rollout import make_goal_set, policy_actor, rollout

    model, vec_normalize, config = load_policy(Path(policy))
    env_kwargs = config["hyperparams"].get("env_kwargs")
    task = IiwaReachVecEnv(1, config["env_id"], **(env_kwargs or {})).task
    goals = make_goal_set(config["env_id"], n_goals, seed, env_kwargs)
    result = rollout(goals, policy_actor(model, vec_normalize))
    q = torch.as_tensor(result.q, dtype=torch.float64).transpose(0, 1).contiguous()
    return task.robot.name, q, task.dt, goals.pose[:, :3, 3].to(torch.float64)
