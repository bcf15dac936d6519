"""VecEnv wrappers used by the training (the env itself stays as registered).

``LogDistanceBonus`` adds a precision term to the dense reward. With ``-d`` alone, the
return barely changes between a 5 mm and a 2 mm final error, so the policy has little
reason to settle closer than the centimetre. The added ``-weight * log1p(d / eps)`` has a
slope ``weight / (eps + d)``: negligible far away, several times ``-d``'s slope below a
centimetre, and it is scale-free in between (halving the error is worth the same at any
distance much larger than ``eps``).

Only for on-policy training: HER relabels goals through the env's ``compute_reward``,
which this wrapper does not change.
"""

from __future__ import annotations

import numpy as np
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper


class LogDistanceBonus(VecEnvWrapper):
    """``reward - weight * log1p(distance / eps)`` with ``distance`` (m) from ``infos[i]["distance"]``.

    Args:
        venv: a VecEnv whose infos carry ``distance`` (``envs.sb3.IiwaReachVecEnv`` does).
        weight: metres of reward per unit of log-distance (> 0).
        eps: the distance (m) below which the term flattens (> 0).
    """

    def __init__(self, venv: VecEnv, weight: float = 0.01, eps: float = 0.001):
        for name, value in (("weight", weight), ("eps", eps)):
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not value > 0:
                raise ValueError(f"{name} must be a positive number, got {value!r}")
        super().__init__(venv)
        self.weight, self.eps = float(weight), float(eps)

    def reset(self):
        return self.venv.reset()

    def step_wait(self):
        obs, reward, done, infos = self.venv.step_wait()
        distance = np.array([info["distance"] for info in infos], dtype=np.float64)
        bonus = -self.weight * np.log1p(distance / self.eps)
        return obs, (reward + bonus).astype(np.float32), done, infos
