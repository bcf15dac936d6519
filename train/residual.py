"""A PPO policy whose action is a learned correction to a damped-least-squares step.

A damped-least-squares (DLS) controller, ``a = dq / max_step`` with
``dq = J_p^T (J_p J_p^T + lambda^2 I)^-1 e`` (see :class:`train.features.JointGoalExtractor`),
reaches most goals with sub-millimetre error, but it moves slowly to far goals and
stalls against the joint limits or near the stretched-arm singularity. The policy here
outputs ``mean = DLS step + g(d) Linear(latent)``, with ``g(d) = d / (d + s)`` of the
distance ``d`` to the goal: the network only learns the correction, and at initialisation
(the last layer is scaled by 0.01, as SB3 does) it is the DLS controller. The gate
matters: an ungated correction is never exactly zero at the goal, and a bias ``b`` in the
action holds the arm where the DLS step cancels it (runs R1 and R2 in
train/policies/ppo_iiwa_reach/RECORD.md). With the gate the correction fades below ``s``
and the DLS step settles the arm. With the extractor's ``avoidance`` (an env that observes its
clearances) the DLS step is kept clear of obstacles by a velocity damper, and so is the whole
mean: ``step + g(d) Linear(latent)`` is moved, as little as possible, back within the damper's
constraints (:func:`train.features.hildreth`, in actions) and shrunk into ``[-1, 1]``: a safety
layer that the correction cannot push through. The Gaussian exploration noise, the value network and PPO itself are
unchanged; the DLS step is computed from the observation inside the network, so
``model.predict`` on the env's raw observation is the whole controller.
"""

from __future__ import annotations

import numpy as np
import torch
from stable_baselines3.common.policies import MultiInputActorCriticPolicy
from torch import nn

from iiwa_torch import compiled
from iiwa_torch.checks import check_bool
from train.features import JointGoalExtractor, hildreth, numpy_ok, shrink


def run_layers(layers: nn.Sequential, x: torch.Tensor) -> torch.Tensor:
    """``layers(x)`` by each layer's ``forward``, without ``nn.Module.__call__``'s hook handling (no hooks
    are used here): the same ops, a few microseconds less per layer on a few rows at inference."""
    for layer in layers:
        x = layer.forward(x)
    return x


class _LatentWithBase(nn.Module):
    """``features -> (cat(latent_pi, base), latent_vf)``: SB3's MLP extractor that also carries the
    DLS step (``(B, nj)``, in actions), the distance (``(B, 1)``, m) and the damper's constraints
    (``(B, K (nj + 1))``; ``K = 0`` without avoidance) to the action head."""

    def __init__(self, inner: nn.Module, columns: list[tuple[int, int]]):
        super().__init__()
        self.inner, self.columns = inner, columns
        self.latent_dim_pi = inner.latent_dim_pi + sum(b - a for a, b in columns)
        self.latent_dim_vf = inner.latent_dim_vf

    def _with_base(self, latent: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        return torch.cat([latent, *(features[:, a:b] for a, b in self.columns)], -1)

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        latent_pi, latent_vf = self.inner(features)
        return self._with_base(latent_pi, features), latent_vf

    def forward_actor(self, features: torch.Tensor) -> torch.Tensor:
        if not torch.is_grad_enabled() and numpy_ok(features):  # a few rows at inference: numpy's concatenation
            x = features.numpy()
            latent = run_layers(self.inner.policy_net, features).numpy()
            return torch.from_numpy(np.concatenate([latent, *(x[:, a:b] for a, b in self.columns)], -1))
        return self._with_base(self.inner.forward_actor(features), features)

    def forward_critic(self, features: torch.Tensor) -> torch.Tensor:
        return self.inner.forward_critic(features)


class _ResidualHead(nn.Module):
    """``cat(latent (B, L), step (B, nj), d (B, 1), normal (B, K nj), bound (B, K), gradient (B, nj or 0))``
    -> the action mean ``step + d / (d + s) * linear(latent)``, kept within the K damper constraints and,
    with ``max_step`` (``(nj,)`` rad per action, for ``keep_progress``), the constraint
    ``g . mean >= g . step`` (``g = gradient * max_step``: ``J^T e`` in actions, so the first-order
    progress towards the goal is at least the DLS step's)."""

    def __init__(self, linear: nn.Linear, gate_distance: float, constraints: int = 0,
                 max_step: torch.Tensor | None = None):
        super().__init__()
        self.linear, self.gate_distance, self.constraints = linear, gate_distance, constraints
        self.register_buffer("ahead_scale", None if max_step is None else max_step.float(), persistent=False)

    def forward(self, latent: torch.Tensor) -> torch.Tensor:
        n, nj, k = self.linear.in_features, self.linear.out_features, self.constraints
        end = n + nj + 1 + k * (nj + 1)
        parts = (latent[:, n : n + nj], latent[:, n + nj : n + nj + 1], latent[:, n + nj + 1 : end], latent[:, end:])
        if not torch.is_grad_enabled() and numpy_ok(latent):  # a few rows at inference: the rest in numpy
            return self.mean_numpy(self.linear.forward(latent[:, :n]).numpy(), *(p.numpy() for p in parts))
        return self._mean(self.linear(latent[:, :n]), *parts, torch)

    def mean_numpy(self, correction, step, distance, damper, gradient) -> torch.Tensor:
        """The mean (a tensor) from float32 numpy arrays: ``correction = linear(latent)``, ``step (B, nj)``,
        ``distance (B, 1)``, ``damper (B, K (nj + 1))`` (``(B, 0)`` without constraints), ``gradient (B, nj)``
        (``(B, 0)`` without ``max_step``); by :func:`train.policy_kernels.residual_mean` (imported, numba with it, on
        the first call) when :data:`iiwa_torch.compiled.ENABLED`."""
        if compiled.ENABLED:
            from train.policy_kernels import residual_mean

            scale = np.empty(0, np.float32) if self.ahead_scale is None else self.ahead_scale.numpy()
            return torch.from_numpy(residual_mean(step, distance, correction, damper, gradient, scale,
                                                  np.float32(self.gate_distance)))
        return torch.from_numpy(self._mean(correction, step, distance, damper, gradient, np))

    def _mean(self, correction, step, distance, damper, gradient, xp):
        """The mean from ``correction`` and the parts of :meth:`mean_numpy`, tensors or numpy arrays (``xp``)."""
        mean = step + distance / (distance + self.gate_distance) * correction
        k, nj = self.constraints, step.shape[-1]
        normal, bound = damper[:, : k * nj].reshape(step.shape[0], k, nj), damper[:, k * nj :]
        if self.ahead_scale is not None:  # the progress constraint first, then the damper's
            ahead = gradient * (self.ahead_scale if xp is torch else self.ahead_scale.numpy())
            normal = xp.concatenate([ahead[:, None], normal], 1)
            bound = xp.concatenate([(ahead * step).sum(-1)[:, None], bound], 1)
        if not normal.shape[1]:
            return mean
        return shrink(hildreth(mean, normal, normal, bound), xp)


class ResidualDLSPolicy(MultiInputActorCriticPolicy):
    """``MultiInputPolicy`` with ``mean = DLS step + d / (d + gate_distance) * Linear(latent_pi)``.

    Needs ``features_extractor_class=JointGoalExtractor`` (its first damping gives the
    DLS step) and a shared features extractor (SB3's default for PPO).

    Args:
        gate_distance: ``s`` (m, > 0): the correction is halved at this distance to the goal.
        keep_progress: keep the mean's first-order progress towards the goal, ``e . J dq``, at least the
            DLS step's (one more constraint of the head's Hildreth projection): the correction may turn
            the step, never slow its approach.
        *args, **kwargs: those of ``MultiInputActorCriticPolicy``.
    """

    def __init__(self, *args, gate_distance: float = 0.01, keep_progress: bool = False, **kwargs):
        if isinstance(gate_distance, bool) or not isinstance(gate_distance, (int, float)) or not gate_distance > 0:
            raise ValueError(f"gate_distance must be a positive number (m), got {gate_distance!r}")
        check_bool(keep_progress, "keep_progress")
        self.gate_distance, self.keep_progress = float(gate_distance), keep_progress
        super().__init__(*args, **kwargs)

    def _predict(self, observation, deterministic: bool = False) -> torch.Tensor:
        """SB3's ``_predict``; deterministic: the action head's mean, without building the Gaussian
        whose mode it is (the same tensor)."""
        if not deterministic:
            return super()._predict(observation, deterministic)
        features = self.extract_features(observation)
        if not torch.is_grad_enabled() and numpy_ok(features):  # one env's step: the head's parts, not their concat
            correction = self.action_net.linear.forward(run_layers(self.mlp_extractor.inner.policy_net, features))
            x = features.numpy()
            return self.action_net.mean_numpy(correction.numpy(), *(x[:, a:b] for a, b in self.mlp_extractor.columns))
        return self.action_net(self.mlp_extractor.forward_actor(features))

    def set_training_mode(self, mode: bool) -> None:
        """SB3's, skipped when the policy is in that mode already (``predict`` calls it every step, and
        the walk over every module costs more than a features extractor call on one row)."""
        if mode != self.training:
            super().set_training_mode(mode)

    def _get_constructor_parameters(self) -> dict:
        return {**super()._get_constructor_parameters(), "gate_distance": self.gate_distance,
                "keep_progress": self.keep_progress}

    def _build(self, lr_schedule) -> None:
        super()._build(lr_schedule)  # builds mlp_extractor, action_net, value_net and the optimizer
        if not isinstance(self.features_extractor, JointGoalExtractor) or not self.share_features_extractor:
            raise ValueError("ResidualDLSPolicy needs a shared JointGoalExtractor (features_extractor: joint), "
                             f"got {type(self.features_extractor).__name__}, "
                             f"share_features_extractor={self.share_features_extractor}")
        # wrap the modules already built (same parameters, so the optimizer built above still holds them)
        ext = self.features_extractor
        columns = [ext.step_columns, (ext.distance_column, ext.distance_column + 1)]
        start, k = ext.damper_columns or (ext.distance_column + 1, 0)  # no constraints: an empty block
        columns.append((start, start + k * (ext.nj + 1)))
        gradient = ext.gradient_columns
        columns.append(gradient if self.keep_progress else (gradient[0], gradient[0]))  # unused: an empty block
        self.mlp_extractor = _LatentWithBase(self.mlp_extractor, columns)
        self.action_net = _ResidualHead(self.action_net, self.gate_distance, k,
                                        ext.max_step if self.keep_progress else None)
