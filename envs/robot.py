"""The robot side of the reaching task: a DH chain moved by joint-velocity actions, within its limits."""

from __future__ import annotations

import copy

import torch

from iiwa_torch.dh import DHChain
from iiwa_torch.robots import IIWA_HOME

from .arrays import NUMPY, TORCH, ArrayOps

__all__ = ["JointVelocityArm"]

Tensor = torch.Tensor


class JointVelocityArm:
    """A chain driven by joint-velocity actions, batch last (joint angles ``(nj, n)``).

    Args:
        chain: a :class:`~iiwa_torch.dh.DHChain` with ``velocity_limits``.
        dt: control period, s: an action ``a`` in ``[-1, 1]^nj`` moves joint ``i`` by
            ``a_i * velocity_limits_i * dt``.
        home: start posture ``(nj,)`` rad, within the limits (default
            :data:`iiwa_torch.robots.IIWA_HOME` for 7 joints, else zeros).
        dtype, device: of the state; the arm keeps a private copy of the chain in them (so FK
            converts no buffer at each call, and the caller's chain is left alone).
    """

    def __init__(self, chain: DHChain, dt: float, home, dtype: torch.dtype, device: torch.device) -> None:
        if not isinstance(chain, DHChain):
            raise TypeError(f"robot must be a DHChain, got {type(chain).__name__}")
        if chain.velocity_limits is None:
            raise ValueError(f"robot {chain.name!r} has no velocity_limits; the action scale needs them")
        same = chain.dh.device == device and chain.dh.dtype == dtype
        self.chain = chain if same else copy.deepcopy(chain).to(device=device, dtype=dtype)
        self.n_joints = n = self.chain.n_joints
        if home is None:
            home = IIWA_HOME if n == 7 else [0.0] * n
        home = torch.as_tensor(home, dtype=dtype, device=device)
        if home.shape != (n,) or not torch.isfinite(home).all() or not bool(self.chain.within_limits(home)):
            raise ValueError(f"home must be {n} finite joint angles within the limits, got {home.tolist()}")
        self.home = home
        self.lower, self.upper = self.chain.limits.to(dtype)
        self.max_step = (self.chain.velocity_limits * dt).to(dtype)  # (nj,) rad per step at |a| = 1
        # the same as columns (nj, 1), to broadcast along the state's rows
        columns = (self.lower[:, None], self.upper[:, None], self.max_step[:, None])
        self._columns = {TORCH.name: columns}
        if self.lower.device.type == "cpu":  # the same as numpy arrays, for NUMPY
            self._columns[NUMPY.name] = tuple(c.numpy() for c in columns)
        #: bound on any end-effector coordinate, m
        self.position_bound = self.chain.reach_bound()

    def configurations(self, u: Tensor) -> Tensor:
        """Uniform numbers ``(..., nj)`` in ``[0, 1)`` -> joint angles ``(..., nj)`` within the limits."""
        return self.lower + u * (self.upper - self.lower)

    def integrate(self, q, action, xp: ArrayOps = TORCH):
        """Joint angles and finite actions ``(nj, n)`` -> the new angles (the actions clipped to
        ``[-1, 1]``, the result clamped to the limits) and the motion made over the speed limits.
        Tensors, or numpy arrays with ``xp=NUMPY`` (:mod:`envs.arrays`)."""
        lower, upper, max_step = self._columns[xp.name]
        a = xp.clip(action, -1.0, 1.0)  # not in place: the action may share the caller's memory
        # in place on the new arrays: a third faster at n = 65,536 than new ones per op
        new = xp.clip_(xp.multiply_add(q, a, max_step), lower, upper)
        # this clip only removes float rounding (1e-6)
        return new, xp.clip_(xp.divide_(new - q, max_step), -1.0, 1.0)

    def steps_to_reach_bound(self) -> int:
        """Steps a full-speed straight joint move needs, in the worst case, from ``home`` to any
        configuration within the limits: ``ceil(max_i max(|lo_i - h_i|, |hi_i - h_i|) / (v_i dt))``."""
        span = torch.maximum((self.lower - self.home).abs(), (self.upper - self.home).abs())
        return int(torch.ceil((span / self.max_step).max() - 1e-4))  # 1e-4: float32 rounding of exact ratios
