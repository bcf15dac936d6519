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

from collections.abc import Sequence

import torch
from gymnasium import spaces
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor


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
        achieved, desired = observations["achieved_goal"], observations["desired_goal"]  # (B, G)
        delta = desired - achieved  # (B, G)
        scaled = (delta.unsqueeze(-2) * self.inv_scales).clamp(-1.0, 1.0).flatten(-2)  # (B, S * G)
        return torch.cat([observations["observation"], achieved, desired, scaled], dim=-1)
