"""A PPO policy whose action is a learned correction to a damped-least-squares step.

A damped-least-squares (DLS) controller, ``a = dq / max_step`` with
``dq = J_p^T (J_p J_p^T + lambda^2 I)^-1 e`` (see :class:`train.features.JointGoalExtractor`),
reaches most goals with sub-millimetre error, but it moves slowly to far goals and
stalls against the joint limits or near the stretched-arm singularity. The policy here
outputs ``mean = DLS step + Linear(latent)``: the network only learns the correction, and
at initialisation (the last layer is scaled by 0.01, as SB3 does) it is the DLS
controller. The Gaussian exploration noise, the value network and PPO itself are
unchanged; the DLS step is computed from the observation inside the network, so
``model.predict`` on the env's raw observation is the whole controller.
"""

from __future__ import annotations

import torch
from stable_baselines3.common.policies import MultiInputActorCriticPolicy
from torch import nn

from train.features import JointGoalExtractor


class _LatentWithBase(nn.Module):
    """``features -> (cat(latent_pi, features[:, columns]), latent_vf)``: SB3's MLP extractor that also
    carries the DLS step (``(B, nj)``, in actions) to the action head."""

    def __init__(self, inner: nn.Module, columns: tuple[int, int]):
        super().__init__()
        self.inner, self.columns = inner, columns
        self.latent_dim_pi = inner.latent_dim_pi + columns[1] - columns[0]
        self.latent_dim_vf = inner.latent_dim_vf

    def _base(self, features: torch.Tensor) -> torch.Tensor:
        return features[:, self.columns[0] : self.columns[1]]

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        latent_pi, latent_vf = self.inner(features)
        return torch.cat([latent_pi, self._base(features)], dim=-1), latent_vf

    def forward_actor(self, features: torch.Tensor) -> torch.Tensor:
        return torch.cat([self.inner.forward_actor(features), self._base(features)], dim=-1)

    def forward_critic(self, features: torch.Tensor) -> torch.Tensor:
        return self.inner.forward_critic(features)


class _ResidualHead(nn.Module):
    """``cat(latent (B, L), base (B, nj)) -> linear(latent) + base``: the action mean."""

    def __init__(self, linear: nn.Linear):
        super().__init__()
        self.linear = linear

    def forward(self, latent: torch.Tensor) -> torch.Tensor:
        return self.linear(latent[:, : self.linear.in_features]) + latent[:, self.linear.in_features :]


class ResidualDLSPolicy(MultiInputActorCriticPolicy):
    """``MultiInputPolicy`` with ``mean = DLS step + Linear(latent_pi)``.

    Needs ``features_extractor_class=JointGoalExtractor`` (its first damping gives the
    DLS step) and a shared features extractor (SB3's default for PPO); keyword arguments
    are those of ``MultiInputActorCriticPolicy``.
    """

    def _build(self, lr_schedule) -> None:
        super()._build(lr_schedule)  # builds mlp_extractor, action_net, value_net and the optimizer
        if not isinstance(self.features_extractor, JointGoalExtractor) or not self.share_features_extractor:
            raise ValueError("ResidualDLSPolicy needs a shared JointGoalExtractor (features_extractor: joint), "
                             f"got {type(self.features_extractor).__name__}, "
                             f"share_features_extractor={self.share_features_extractor}")
        # wrap the modules already built (same parameters, so the optimizer built above still holds them)
        self.mlp_extractor = _LatentWithBase(self.mlp_extractor, self.features_extractor.step_columns)
        self.action_net = _ResidualHead(self.action_net)
