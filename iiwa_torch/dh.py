"""Denavit-Hartenberg chains: batched, differentiable forward kinematics and Jacobians.

A chain is a table of rows ``(a, alpha, d, theta_offset)`` (metres, radians), one per
revolute joint, in one of two conventions:

- ``standard`` (classical DH): ``A_i = Rz(q_i + offset_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``;
- ``modified`` (Craig): ``A_i = Rx(alpha_{i-1}) Tx(a_{i-1}) Rz(q_i + offset_i) Tz(d_i)``,
  the row holding ``a_{i-1}, alpha_{i-1}, d_i, offset_i``.

The end-effector pose is ``base @ A_1 @ ... @ A_n @ tool``.

How it is computed: the rotation about each joint axis is applied to the frame's three
axis columns with elementwise multiply-adds, batch last and contiguous, and the constant
twists (``alpha`` of 0 or +-pi/2) become swaps and sign flips. That is a few dozen
memory-bound elementwise kernels for the whole batch, with no ``4x4`` matrix products;
the benchmark in ``benchmarks/bench_fk.py`` compares it with the peers and a matmul chain.
"""

from __future__ import annotations

import math
from enum import Enum
from typing import Sequence

import torch
from torch import nn

__all__ = ["Convention", "DHChain"]

Tensor = torch.Tensor
# One frame in "structure of arrays" form: the x, y, z axis columns and the origin, each (3, *batch).
_Frame = tuple[Tensor, Tensor, Tensor, Tensor]


class Convention(str, Enum):
    """Which Denavit-Hartenberg convention a table is written in."""

    STANDARD = "standard"
    MODIFIED = "modified"


def _as_matrix(value, name: str) -> Tensor:
    matrix = torch.eye(4, dtype=torch.float64) if value is None else torch.as_tensor(value, dtype=torch.float64)
    if matrix.shape != (4, 4) or not torch.isfinite(matrix).all():
        raise ValueError(f"{name} must be a finite 4x4 homogeneous transform, got shape {tuple(matrix.shape)}")
    if not torch.allclose(matrix[:3, :3] @ matrix[:3, :3].T, torch.eye(4, dtype=torch.float64)[:3, :3], atol=1e-9):
        raise ValueError(f"{name}'s rotation part is not orthonormal")
    return matrix


def _rotate_z(x: Tensor, y: Tensor, c: Tensor, s: Tensor) -> tuple[Tensor, Tensor]:
    """Rotate the frame axes x, y about its own z by the angle with cosine c and sine s."""
    return torch.addcmul(c * x, s, y), torch.addcmul(c * y, s, x, value=-1)


def _rotate_x(y: Tensor, z: Tensor, ca: float, sa: float) -> tuple[Tensor, Tensor]:
    """Rotate the frame axes y, z about its own x by a constant angle (cosine ca, sine sa)."""
    if ca == 0.0:  # alpha = +-pi/2: a swap and a sign flip
        return (z, -y) if sa > 0 else (-z, y)
    if sa == 0.0:  # alpha = 0 or pi
        return (y, z) if ca > 0 else (-y, -z)
    return torch.add(ca * y, z, alpha=sa), torch.add(ca * z, y, alpha=-sa)


def _exact(v: float) -> float:
    """Snap cos/sin of a multiple of pi/2 to exactly 0 or +-1 (6e-17 is rounding noise)."""
    return float(round(v)) if abs(v - round(v)) < 1e-12 else v


class DHChain(nn.Module):
    """A serial chain of revolute joints described by a Denavit-Hartenberg table.

    Args:
        table: ``(n, 4)`` rows ``(a, alpha, d, theta_offset)``, metres and radians.
        convention: ``"standard"`` (classical) or ``"modified"`` (Craig); see the module doc.
        limits: ``(2, n)`` lower and upper joint limits in radians (default: +-pi).
        joint_names: n names (default ``joint1 ... jointn``).
        base: ``(4, 4)`` transform from the world to the chain's first frame.
        tool: ``(4, 4)`` transform from the last link frame to the end effector.
        velocity_limits: ``(n,)`` maximum joint speeds in rad/s, if known.
        name: the robot's name (used in ``repr`` and URDF export).

    The table, limits and transforms are buffers, so ``.to(device)`` moves them; results
    always follow the dtype and device of the joint angles ``q``. A chain is immutable:
    build a new one to change its geometry.
    """

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
        super().__init__()
        dh = torch.as_tensor(table, dtype=torch.float64)
        if dh.ndim != 2 or dh.shape[1] != 4 or dh.shape[0] < 1:
            raise ValueError(f"table must have shape (n, 4) with rows (a, alpha, d, theta_offset), got {tuple(dh.shape)}")
        if not torch.isfinite(dh).all():
            raise ValueError("table contains NaN or inf")
        try:
            self.convention = Convention(convention)
        except ValueError:
            raise ValueError(f"convention must be one of {[c.value for c in Convention]}, got {convention!r}") from None
        n = dh.shape[0]
        lim = torch.tensor([[-math.pi] * n, [math.pi] * n], dtype=torch.float64) if limits is None else torch.as_tensor(limits, dtype=torch.float64)
        if lim.shape != (2, n) or not (lim[0] <= lim[1]).all():
            raise ValueError(f"limits must have shape (2, {n}) with lower <= upper, got {tuple(lim.shape)}")
        names = [f"joint{i + 1}" for i in range(n)] if joint_names is None else list(joint_names)
        if len(names) != n:
            raise ValueError(f"joint_names must have {n} names, got {len(names)}")
        self.name = name
        self.joint_names = tuple(names)
        self.register_buffer("dh", dh)
        self.register_buffer("limits", lim)
        self.register_buffer("base", _as_matrix(base, "base"))
        self.register_buffer("tool", _as_matrix(tool, "tool"))
        vel = None if velocity_limits is None else torch.as_tensor(velocity_limits, dtype=torch.float64)
        if vel is not None and (vel.shape != (n,) or not (vel > 0).all()):
            raise ValueError(f"velocity_limits must be {n} positive speeds in rad/s, got {vel.tolist()}")
        self.register_buffer("velocity_limits", vel)
        # Python-float copies of the geometry for the kernel: the constants of each joint.
        self._steps = [(a, _exact(math.cos(al)), _exact(math.sin(al)), d) for a, al, d, _ in dh.tolist()]
        self._base = self.base.tolist()
        self._tool = None if torch.equal(self.tool, torch.eye(4, dtype=torch.float64)) else self.tool.tolist()

    # ------------------------------------------------------------------ properties
    @property
    def n_joints(self) -> int:
        return self.dh.shape[0]

    def extra_repr(self) -> str:
        head = f"name={self.name!r}, convention={self.convention.value!r}, n_joints={self.n_joints}"
        rows = [f"  {'joint':<10}{'a':>9}{'alpha':>9}{'d':>9}{'offset':>9}{'min':>9}{'max':>9}   (m, deg)"]
        for name, (a, al, d, off), lo, hi in zip(self.joint_names, self.dh.tolist(), *self.limits.tolist()):
            rows.append(
                f"  {name:<10}{a:9.4f}{math.degrees(al):9.1f}{d:9.4f}{math.degrees(off):9.1f}"
                f"{math.degrees(lo):9.1f}{math.degrees(hi):9.1f}"
            )
        return head + "\n" + "\n".join(rows)

    # ------------------------------------------------------------------ input checks
    def check_q(self, q: Tensor, name: str = "q") -> None:
        """Raise a clear ``TypeError``/``ValueError`` unless ``q`` is a finite ``(..., n)`` float tensor
        on this chain's device."""
        n = self.n_joints
        if not isinstance(q, torch.Tensor):
            raise TypeError(f"{name} must be a torch.Tensor of shape (..., {n}), got {type(q).__name__}")
        if not q.is_floating_point():
            raise TypeError(f"{name} must be a float32 or float64 tensor, got {q.dtype}")
        if q.ndim == 0 or q.shape[-1] != n:
            raise ValueError(f"{name} must have shape (..., {n}), got {tuple(q.shape)}")
        if q.device != self.dh.device:
            raise ValueError(f"{name} is on {q.device} but the chain is on {self.dh.device}; use chain.to({str(q.device)!r})")
        if not torch.isfinite(q).all():
            bad = (~torch.isfinite(q)).nonzero()[0].tolist()
            raise ValueError(f"{name} contains NaN or inf (first at index {tuple(bad)}); joint angles must be finite")

    def within_limits(self, q: Tensor, tol: float = 0.0) -> Tensor:
        """``(..., n) -> (...)`` bool: every joint within ``[lower - tol, upper + tol]``."""
        lim = self.limits.to(q.dtype)
        return ((q >= lim[0] - tol) & (q <= lim[1] + tol)).all(-1)

    def clamp(self, q: Tensor) -> Tensor:
        """``(..., n) -> (..., n)``: ``q`` clamped into the joint limits (a new tensor)."""
        lim = self.limits.to(q.dtype)
        return torch.maximum(torch.minimum(q, lim[1]), lim[0])

    def random_q(self, *shape: int, generator: torch.Generator | None = None, dtype: torch.dtype = torch.float64) -> Tensor:
        """``(*shape, n)`` joint angles drawn uniformly within the limits."""
        u = torch.rand(*shape, self.n_joints, generator=generator, dtype=dtype, device=self.dh.device)
        lim = self.limits.to(dtype)
        return lim[0] + u * (lim[1] - lim[0])

    # ------------------------------------------------------------------ kinematics
    def _propagate(self, q: Tensor, keep: bool) -> tuple[list[_Frame], list[tuple[Tensor, Tensor]]]:
        """Walk the chain. Returns the link frames (all if ``keep``, else the last) and, if
        ``keep``, each joint's axis and a point on it, all as ``(3, *batch)`` tensors."""
        batch = q.shape[:-1]
        theta = q + self.dh[:, 3].to(q.dtype)
        c = torch.cos(theta).movedim(-1, 0).contiguous()  # (n, *batch)
        s = torch.sin(theta).movedim(-1, 0).contiguous()
        cols = torch.tensor(self._base, dtype=q.dtype, device=q.device)[:3].reshape(3, 4, *([1] * len(batch)))
        x, y, z, p = (cols[:, k].expand(3, *batch) for k in range(4))
        frames, axes = [(x, y, z, p)], []
        modified = self.convention is Convention.MODIFIED
        for i, (a, ca, sa, d) in enumerate(self._steps):
            if modified:
                y, z = _rotate_x(y, z, ca, sa)
                p = torch.add(p, x, alpha=a) if a else p
            if keep:
                axes.append((z, p))
            x, y = _rotate_z(x, y, c[i], s[i])
            p = torch.add(p, z, alpha=d) if d else p
            if not modified:
                p = torch.add(p, x, alpha=a) if a else p
                y, z = _rotate_x(y, z, ca, sa)
            if keep:
                frames.append((x, y, z, p))
        if not keep:
            frames = [(x, y, z, p)]
        return frames, axes

    def _apply_tool(self, frame: _Frame) -> _Frame:
        if self._tool is None:
            return frame
        x, y, z, p = frame
        t = self._tool

        def combine(k: int) -> Tensor:  # x * t[0][k] + y * t[1][k] + z * t[2][k]
            return torch.add(torch.add(x * t[0][k], y, alpha=t[1][k]), z, alpha=t[2][k])

        return combine(0), combine(1), combine(2), combine(3) + p

    @staticmethod
    def _to_matrix(frames: list[_Frame]) -> Tensor:
        """Frames in SoA form -> ``(*batch, len(frames), 4, 4)`` homogeneous matrices."""
        top = torch.stack([torch.stack(f, -1) for f in frames], 0)  # (F, 3, *batch, 4)
        nb = top.ndim - 3
        top = top.permute(*range(2, 2 + nb), 0, 1, -1)  # (*batch, F, 3, 4)
        bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=top.dtype, device=top.device)
        return torch.cat([top, bottom.expand(*top.shape[:-2], 1, 4)], -2)

    def fk(self, q: Tensor) -> Tensor:
        """End-effector pose: ``q (..., n)`` radians -> ``(..., 4, 4)``, metres, in the base's world frame."""
        self.check_q(q)
        frames, _ = self._propagate(q, keep=False)
        return self._to_matrix([self._apply_tool(frames[0])])[..., 0, :, :]

    def fk_all(self, q: Tensor) -> Tensor:
        """Every frame: ``q (..., n) -> (..., n + 1, 4, 4)``: the base, then link frames 1..n.

        The tool transform is not applied: ``fk(q) == fk_all(q)[..., -1, :, :] @ chain.tool``.
        """
        self.check_q(q)
        frames, _ = self._propagate(q, keep=True)
        return self._to_matrix(frames)

    def jacobian(self, q: Tensor) -> Tensor:
        """Geometric Jacobian in the world frame: ``q (..., n) -> (..., 6, n)``.

        Rows 0-2 map joint rates (rad/s) to the end-effector's linear velocity (m/s), rows
        3-5 to its angular velocity (rad/s). Column i is ``[z_i x (p_e - p_i); z_i]`` for
        joint i's axis ``z_i`` through the point ``p_i``, computed from the frames, not by autograd.
        """
        self.check_q(q)
        frames, axes = self._propagate(q, keep=True)
        p_end = self._apply_tool(frames[-1])[3]
        z = torch.stack([zi for zi, _ in axes], 0)  # (n, 3, *batch)
        lever = p_end - torch.stack([pi for _, pi in axes], 0)
        jac = torch.cat([torch.linalg.cross(z, lever, dim=1), z], 1)  # (n, 6, *batch)
        return jac.permute(*range(2, jac.ndim), 1, 0)

    def forward(self, q: Tensor) -> Tensor:
        """Same as :meth:`fk`."""
        return self.fk(q)
