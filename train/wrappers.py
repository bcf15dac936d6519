"""VecEnv wrappers used by the training (the env itself stays as registered).

``LogDistanceBonus`` adds a precision term to the dense reward. With ``-d`` alone, the
return barely changes between a 5 mm and a 2 mm final error, so the policy has little
reason to settle closer than the centimetre. The added ``-weight * log1p(d / eps)`` has a
slope ``weight / (eps + d)``: negligible far away, several times ``-d``'s slope below a
centimetre, and it is scale-free in between (halving the error is worth the same at any
distance much larger than ``eps``).

``ClearancePenalty`` gives the rare collisions a signal on many more steps than the
collisions themselves: ``-weight * (1 - clearance / margin)`` on every step whose clearance
(floor, the arm itself, the episode's obstacles) is below ``margin``, rising to ``-weight`` at
contact; the env's own collision penalty still applies below zero.

Only for on-policy training: HER relabels goals through the env's ``compute_reward``,
which these wrappers do not change.
"""

from __future__ import annotations

import numpy as np
import torch
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper

from envs.transport import joint_angles


def _positive(**values) -> None:
    for name, value in values.items():
        if not isinstance(value, (int, float)) or isinstance(value, bool) or not value > 0:
            raise ValueError(f"{name} must be a positive number, got {value!r}")


class LogDistanceBonus(VecEnvWrapper):
    """``reward - weight * log1p(distance / eps)`` with ``distance`` (m) from ``infos[i]["distance"]``.

    Args:
        venv: a VecEnv whose infos carry ``distance`` (``envs.sb3.IiwaReachVecEnv`` does).
        weight: metres of reward per unit of log-distance (> 0).
        eps: the distance (m) below which the term flattens (> 0).
    """

    def __init__(self, venv: VecEnv, weight: float = 0.01, eps: float = 0.001):
        _positive(weight=weight, eps=eps)
        super().__init__(venv)
        self.weight, self.eps = float(weight), float(eps)

    def reset(self):
        return self.venv.reset()

    def step_wait(self):
        obs, reward, done, infos = self.venv.step_wait()
        distance = np.array([info["distance"] for info in infos], dtype=np.float64)
        bonus = -self.weight * np.log1p(distance / self.eps)
        return obs, (reward + bonus).astype(np.float32), done, infos


class ClearancePenalty(VecEnvWrapper):
    """``reward - weight * clip(1 - clearance / margin, 0, 1)``, the clearance (m) of the
    configuration each step ended in (for a finished episode, its last one), recomputed from
    the observation (``cos q``, ``sin q`` and the obstacle block) in one batched call.

    Args:
        venv: an ``envs.sb3.IiwaReachVecEnv`` (possibly wrapped) with collision checks on.
        margin: the clearance (m) below which the penalty starts (> 0).
        weight: the penalty at contact, in reward units (> 0).
    """

    def __init__(self, venv: VecEnv, margin: float = 0.02, weight: float = 0.1):
        _positive(margin=margin, weight=weight)
        super().__init__(venv)
        self.task = venv.unwrapped.task
        if self.task.world is None:
            raise ValueError("ClearancePenalty needs an env with collision checks (collision='off' has no world)")
        self.margin, self.weight = float(margin), float(weight)
        #: the arm's joint limits ``(nj,)`` each, rad, as numpy arrays
        self.limits = tuple(x.double().cpu().numpy() for x in (self.task.arm.lower, self.task.arm.upper))

    def reset(self):
        return self.venv.reset()

    def clearance(self, observation: np.ndarray) -> np.ndarray:
        """Observations ``(n, D)`` -> clearance ``(n,)``, m."""
        arm, world = self.task.arm, self.task.world
        nj = arm.n_joints
        obs = torch.as_tensor(observation, dtype=self.task.dtype)
        q = joint_angles(obs, *self.limits)
        block = obs[:, 3 * nj : 3 * nj + world.block_size].T if world.slots else None
        with torch.no_grad():
            return world.clearance(q, block).double().numpy()

    def step_wait(self):
        obs, reward, done, infos = self.venv.step_wait()
        last = obs["observation"].copy()
        for i in np.flatnonzero(done):
            last[i] = infos[i]["terminal_observation"]["observation"]
        shortfall = np.clip(1.0 - self.clearance(last) / self.margin, 0.0, 1.0)
        return obs, (reward - self.weight * shortfall).astype(np.float32), done, infos
