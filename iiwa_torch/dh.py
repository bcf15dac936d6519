"""Denavit-Hartenberg chains: :class:`~iiwa_torch.chain.Chain` read from a table of rows
``(a, alpha, d, theta_offset)`` (m, rad), one per revolute joint:

- ``standard``: ``A_i = Rz(q_i + offset_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``;
- ``modified`` (Craig): ``A_i = Rx(alpha_{i-1}) Tx(a_{i-1}) Rz(q_i + offset_i) Tz(d_i)``.

The end pose is ``base @ A_1 @ ... @ A_n @ tool``; ``fk_all`` gives the DH frames. The table is
the buffer ``dh``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from enum import Enum

import torch
from torch import nn

from . import kinematics as kin
from .chain import Chain
from .checks import check_finite

__all__ = ["Convention", "DHChain"]

Tensor = torch.Tensor


class Convention(str, Enum):
    """Which Denavit-Hartenberg convention a table is written in."""

    STANDARD = "standard"
    MODIFIED = "modified"


def _check_table(dh: Tensor) -> None:
    if dh.ndim != 2 or dh.shape[1] != 4 or dh.shape[0] < 1:
        raise ValueError(f"table must have shape (n, 4) with rows (a, alpha, d, theta_offset), got {tuple(dh.shape)}")
    check_finite(dh, "table")


class DHChain(Chain):
    """A serial chain of revolute joints from a DH ``table (n, 4)`` in ``convention`` (module doc);
    the other arguments are :class:`~iiwa_torch.chain.Chain`'s (limits default to +-pi)."""

    def __init__(
        self,
        table,
        *,
        convention: Convention | str = Convention.STANDARD,
        limits=None,
        joint_names: Sequence[str] | None = None,
        base=None,
        tool=None,
        velocity_limits=None,
        name: str = "chain",
    ) -> None:
        nn.Module.__init__(self)  # not Chain's: the joints come from the table, not from origins and axes
        dh = torch.as_tensor(table, dtype=torch.float64)
        _check_table(dh)
        try:
            self.convention = Convention(convention)
        except ValueError:
            raise ValueError(f"convention must be one of {[c.value for c in Convention]}, got {convention!r}") from None
        self._setup(dh.shape[0], None, limits, joint_names, base, tool, velocity_limits, name)
        self.link_names = tuple(f"link{i + 1}" for i in range(self.n_joints))
        self.register_buffer("dh", dh)

    def _geometry_buffers(self) -> tuple[Tensor, ...]:
        b = self._buffers
        return b["dh"], b["base"], b["tool"], b["limits"]

    def _joint_transforms(self) -> tuple[Tensor, Tensor, Tensor]:
        dh = self.dh.detach().cpu()
        before, after = kin.dh_transforms(dh, self.convention is Convention.MODIFIED)
        return before, after, dh[:, 3].to(torch.float64)

    def _check_buffers(self) -> None:
        _check_table(self.dh)
        if self.dh.shape[0] != self.n_joints:
            raise ValueError(f"table must have {self.n_joints} rows (one per joint), got {tuple(self.dh.shape)}")
        self._check_common()

    def extra_repr(self) -> str:
        head = f"name={self.name!r}, convention={self.convention.value!r}, n_joints={self.n_joints}"
        width = max(map(len, ("joint", *self.joint_names))) + 2
        rows = [f"  {'joint':<{width}}{'a':>9}{'alpha':>9}{'d':>9}{'offset':>9}{'min':>9}{'max':>9}   (m, deg)"]
        for name, (a, al, d, off), lo, hi in zip(self.joint_names, self.dh.tolist(), *self.limits.tolist()):
            # rounded, then + 0.0: a -1e-17 shows as 0.0000, not -0.0000
            a, d, al, off, lo, hi = (round(v, 4) + 0.0 for v in (a, d, *map(math.degrees, (al, off, lo, hi))))
            rows.append(f"  {name:<{width}}{a:9.4f}{al:9.1f}{d:9.4f}{off:9.1f}{lo:9.1f}{hi:9.1f}")
        return head + "\n" + "\n".join(rows)
