"""Denavit-Hartenberg chains: batched, differentiable forward kinematics and Jacobians.

A chain is a table of rows ``(a, alpha, d, theta_offset)`` (metres, radians), one per
revolute joint, in one of two conventions:

- ``standard`` (classical DH): ``A_i = Rz(q_i + offset_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``;
- ``modified`` (Craig): ``A_i = Rx(alpha_{i-1}) Tx(a_{i-1}) Rz(q_i + offset_i) Tz(d_i)``,
  the row holding ``a_{i-1}, alpha_{i-1}, d_i, offset_i``.

The end-effector pose is ``base @ A_1 @ ... @ A_n @ tool``.

:class:`DHChain` holds the table, limits, base and tool as buffers (the truth: ``state_dict``,
``.to()``) and checks inputs; the kernels are pure functions in :mod:`iiwa_torch.kinematics`
over a frozen :class:`~iiwa_torch.kinematics.Geometry` derived from those buffers.
:meth:`DHChain.geometry` rebuilds it whenever a buffer changed (``.to()`` and friends,
``load_state_dict``, an in-place edit), so cached constants never disagree with ``chain.dh``.
How the kernels work and which runs when: :mod:`iiwa_torch.kinematics`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from enum import Enum

import numpy as np
import torch
from torch import nn

from . import compiled, so3
from . import kinematics as kin
from .checks import as_point, check_finite, check_float_tensor, check_nonnegative
from .kinematics import Frame, Geometry

__all__ = ["Convention", "DHChain"]

Tensor = torch.Tensor


class Convention(str, Enum):
    """Which Denavit-Hartenberg convention a table is written in."""

    STANDARD = "standard"
    MODIFIED = "modified"


def _as_matrix(value, name: str) -> Tensor:
    matrix = torch.eye(4, dtype=torch.float64) if value is None else torch.as_tensor(value, dtype=torch.float64)
    _check_transform(matrix, name)
    return matrix


def _check_transform(matrix: Tensor, name: str) -> None:
    if matrix.shape != (4, 4):
        raise ValueError(f"{name} must be a 4x4 homogeneous transform, got shape {tuple(matrix.shape)}")
    so3.check_rigid(matrix, name, exact_bottom_row=True)


def _check_limits(lim: Tensor, n: int) -> None:
    if lim.shape != (2, n):
        raise ValueError(f"limits must have shape (2, {n}) with lower <= upper, got {tuple(lim.shape)}")
    if not torch.isfinite(lim).all():
        raise ValueError(f"limits must be finite (radians), got {lim.tolist()}")
    if not (lim[0] <= lim[1]).all():
        raise ValueError(f"limits must have shape (2, {n}) with lower <= upper, got lower {lim[0].tolist()}, "
                         f"upper {lim[1].tolist()}")


def _check_table(dh: Tensor) -> None:
    if dh.ndim != 2 or dh.shape[1] != 4 or dh.shape[0] < 1:
        raise ValueError(f"table must have shape (n, 4) with rows (a, alpha, d, theta_offset), got {tuple(dh.shape)}")
    check_finite(dh, "table")


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

    The table, limits and transforms are buffers, so ``.to(device)`` moves them and
    ``state_dict``/``load_state_dict`` carry them; results always follow the dtype and device
    of the joint angles ``q``. The buffers are the geometry: after any change to them (loaded,
    moved, edited in place) the next call uses the new values, checked again.
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
        _check_table(dh)
        try:
            self.convention = Convention(convention)
        except ValueError:
            raise ValueError(f"convention must be one of {[c.value for c in Convention]}, got {convention!r}") from None
        n = dh.shape[0]
        lim = (
            torch.tensor([[-math.pi] * n, [math.pi] * n], dtype=torch.float64)
            if limits is None
            else torch.as_tensor(limits, dtype=torch.float64)
        )
        _check_limits(lim, n)
        names = [f"joint{i + 1}" for i in range(n)] if joint_names is None else list(joint_names)
        if len(names) != n:
            raise ValueError(f"joint_names must have {n} names, got {len(names)}")
        if not isinstance(name, str):
            raise TypeError(f"name must be a string, got {name!r}")
        self.name = name
        self.joint_names = tuple(names)
        self._q_shape = f"(..., {n})"  # the shape check_q names
        self._one_shapes = ((n,), (1, n))  # one configuration's shapes, for _plain_one
        self.register_buffer("dh", dh)
        self.register_buffer("limits", lim)
        self.register_buffer("base", _as_matrix(base, "base"))
        self.register_buffer("tool", _as_matrix(tool, "tool"))
        vel = None if velocity_limits is None else torch.as_tensor(velocity_limits, dtype=torch.float64)
        if vel is not None and (vel.shape != (n,) or not (vel > 0).all()):
            raise ValueError(f"velocity_limits must be {n} positive speeds in rad/s, got {vel.tolist()}")
        self.register_buffer("velocity_limits", vel)
        self._geometry: dict[torch.dtype, Geometry] = {}
        self._stamp: tuple = ()
        self.register_load_state_dict_post_hook(_after_load)

    def _buffer_stamp(self) -> tuple:
        """What identifies the geometry buffers' current contents: each one's version counter
        (bumped by every in-place write, ``load_state_dict``'s copies too) and storage address
        (``.data =`` and a new buffer change it). Unrolled: it runs on every call (about 0.5 us;
        ``fk`` of one configuration takes about 20 us)."""
        b = self._buffers
        dh, base, tool, lim = b["dh"], b["base"], b["tool"], b["limits"]
        return (dh._version, base._version, tool._version, lim._version,
                dh.data_ptr(), base.data_ptr(), tool.data_ptr(), lim.data_ptr())

    def geometry(self, dtype: torch.dtype = torch.float64) -> Geometry:
        """The chain's :class:`~iiwa_torch.kinematics.Geometry` in ``dtype`` (float32 or float64), on
        the chain's device: what the kernels of :mod:`iiwa_torch.kinematics` take. Cached, and
        rebuilt (and the buffers checked again) whenever ``dh``, ``base``, ``tool`` or ``limits``
        changed since, however they changed."""
        stamp = self._buffer_stamp()
        if stamp != self._stamp:
            self._check_buffers()
            self._geometry, self._stamp = {}, stamp
        g = self._geometry.get(dtype)
        if g is None:
            if dtype not in (torch.float32, torch.float64):
                raise TypeError(f"the chain computes in float32 or float64, got {dtype}")
            g = Geometry.build(self.dh, self.base, self.tool, self.limits, self.convention is Convention.MODIFIED,
                               dtype)
            self._geometry[dtype] = g
        return g

    def _check_buffers(self) -> None:
        """The constructor's checks, on the buffers as they are now."""
        _check_table(self.dh)
        if self.dh.shape[0] != self.n_joints:
            raise ValueError(f"table must have {self.n_joints} rows (one per joint), got {tuple(self.dh.shape)}")
        _check_limits(self.limits, self.n_joints)
        _check_transform(self.base, "base")
        _check_transform(self.tool, "tool")

    def _apply(self, fn, recurse=True):
        self._geometry, self._stamp = {}, ()
        return super()._apply(fn, recurse)

    # ------------------------------------------------------------------ properties
    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

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
        """Raise a clear ``TypeError``/``ValueError`` unless ``q`` is a finite ``(..., n)`` float32 or
        float64 tensor on this chain's device, with data (not ``meta``), outside ``torch.func.vmap``
        (batch with leading dimensions instead: every method takes ``(..., n)``)."""
        n = self.n_joints
        check_float_tensor(q, name, self._q_shape)
        if q.ndim == 0 or q.shape[-1] != n:
            raise ValueError(f"{name} must have shape {self._q_shape}, got {tuple(q.shape)}")
        dh = self._buffers["dh"]  # not self.dh: nn.Module's attribute lookup of a buffer costs a third of this check
        if not (q.is_cpu and dh.is_cpu) and q.device != dh.device:  # is_cpu: no device object built
            raise ValueError(
                f"{name} is on {q.device} but the chain is on {dh.device}; use chain.to({str(q.device)!r})"
            )
        check_finite(q, name)

    def _plain_one(self, q) -> np.ndarray | None:
        """The common case of ``fk``/``jacobian`` checked at a fraction of :meth:`check_q`'s cost:
        ``q``'s values as a ``(1, n)`` float64 array (a view) if the compiled kernels are on and
        ``q`` is one finite configuration, ``(n,)`` or ``(1, n)``, a plain contiguous float64
        CPU tensor without ``requires_grad``, on a CPU chain; else ``None``, and the caller runs
        :meth:`check_q` and its ordinary path, which raises for every bad input. Finite: the
        Python sum of the n values is (a NaN or inf makes it NaN or inf; an overflow of huge
        finite values only sends ``q`` to the ordinary path)."""
        if not (compiled.ENABLED and type(q) is Tensor and q.dtype is torch.float64 and q.is_cpu
                and not q.requires_grad and q.is_contiguous() and q.shape in self._one_shapes
                and self._buffers["dh"].is_cpu):  # fmt: skip
            return None
        try:
            x = q.numpy()
        except (RuntimeError, TypeError):  # no storage to read (torch.func.vmap): check_q says so
            return None
        if not math.isfinite(sum(x.tolist() if x.ndim == 1 else x[0].tolist())):
            return None
        return x[None] if x.ndim == 1 else x

    def within_limits(self, q: Tensor, tol: float = 0.0) -> Tensor:
        """``(..., n) -> (...)`` bool: every joint within ``[lower - tol, upper + tol]``."""
        self.check_q(q)
        check_nonnegative(tol, "tol")
        lim = self.geometry(q.dtype).limits
        return ((q >= lim[0] - tol) & (q <= lim[1] + tol)).all(-1)

    def clamp(self, q: Tensor) -> Tensor:
        """``(..., n) -> (..., n)``: ``q`` clamped into the joint limits (a new tensor)."""
        self.check_q(q)
        lim = self.geometry(q.dtype).limits
        return torch.maximum(torch.minimum(q, lim[1]), lim[0])

    def reach_bound(self, point=None) -> float:
        """An upper bound (m) on the distance from the world origin to ``point``, a ``(3,)`` point
        fixed in the end-effector frame (default: the end effector's origin): the base offset,
        plus the configuration-independent distances between consecutive frame origins, plus
        the point's distance from the last link frame's origin."""
        zero = torch.zeros(self.n_joints, dtype=torch.float64, device=self.dh.device)
        frames = self.fk_all(zero)  # (n + 1, 4, 4)
        tip = torch.zeros(4, dtype=torch.float64, device=self.dh.device)
        tip[3] = 1.0
        tip[:3] = as_point(point).to(self.dh.device)
        tip = (self.fk(zero) @ tip)[:3]
        links = (frames[1:, :3, 3] - frames[:-1, :3, 3]).norm(dim=-1).sum()
        return float(frames[0, :3, 3].norm() + links + (tip - frames[-1, :3, 3]).norm())

    def random_q(
        self, *shape: int, generator: torch.Generator | None = None, dtype: torch.dtype = torch.float64
    ) -> Tensor:
        """``(*shape, n)`` joint angles drawn uniformly within the limits; ``shape``: non-negative
        ints, ``dtype``: float32 or float64."""
        for size in shape:
            if isinstance(size, bool) or not isinstance(size, int) or size < 0:
                raise ValueError(f"random_q's shape must be non-negative integers, got {shape}")
        if dtype not in (torch.float32, torch.float64):
            raise TypeError(f"random_q's dtype must be float32 or float64, got {dtype!r}")
        lim = self.geometry(dtype).limits
        u = torch.rand(*shape, self.n_joints, generator=generator, dtype=dtype, device=self.dh.device)
        return lim[0] + u * (lim[1] - lim[0])

    # ------------------------------------------------------------------ batch-last API (unchecked)
    def frames_batch_last(self, q: Tensor, keep: bool = True) -> tuple[list[Frame], list[tuple[Tensor, Tensor]]]:
        """For hot loops that keep a batch-last layout (IK): ``q (n, b)``, not checked ->
        ``(frames, axes)``, the base and link frames as ``(x, y, z, p)`` columns ``(3, b)`` and
        the joint axes ``(z_i, p_i)``; see :func:`iiwa_torch.kinematics.frames_batch_last`."""
        return kin.frames_batch_last(self.geometry(q.dtype), q, keep)

    def tool_frame_batch_last(self, frame: Frame) -> Frame:
        """The last link frame ``(x, y, z, p)`` of :meth:`frames_batch_last`, each ``(3, b)``, ->
        the end-effector frame (the tool applied), in the same layout."""
        return kin.tool_frame_batch_last(self.geometry(frame[0].dtype), frame)

    def position_batch_last(self, q: Tensor, trig: tuple[Tensor, Tensor] | None = None) -> Tensor:
        """The end-effector position alone, for hot loops that keep a batch-last layout (envs):
        ``q (n, b)``, not checked -> ``(3, b)``. ``trig``: ``(cos q, sin q)``, each ``(n, b)``, if
        the caller has them; see :func:`iiwa_torch.kinematics.position_batch_last`."""
        return kin.position_batch_last(self.geometry(q.dtype), q, trig)

    # ------------------------------------------------------------------ kinematics (checked, batch first)
    def fk(self, q: Tensor) -> Tensor:
        """End-effector pose: ``q (..., n)`` radians -> ``(..., 4, 4)``, metres, in the world frame.

        Differentiable. Above 128 configurations the backward pass is ``J(q)^T`` times the
        pose gradient's twist, not a replay of the forward kernel; up to 128, autograd
        through the few ops of the small-batch kernel costs less (at batch 1, half the
        instructions of the closed form).
        """
        x = self._plain_one(q)
        if x is not None:
            return kin.one_by_kernel(compiled.kernels().end_poses, self.geometry(torch.float64), x, q.ndim)
        self.check_q(q)
        g = self.geometry(q.dtype)
        if q.numel() == self.n_joints and kin.floats_ok(q):
            return kin.end_pose_floats(g, q)
        if q.requires_grad and torch.is_grad_enabled() and q.numel() > kin.SMALL_BATCH * self.n_joints:
            return kin.EndPoseFunction.apply(q, g)
        return kin.blockwise(q, self.n_joints, (4, 4), lambda qb: kin.end_pose(g, qb))

    def fk_all(self, q: Tensor) -> Tensor:
        """Every frame: ``q (..., n) -> (..., n + 1, 4, 4)``: the base, then link frames 1..n.

        The tool transform is not applied: ``fk(q) == fk_all(q)[..., -1, :, :] @ chain.tool``.
        """
        self.check_q(q)
        g = self.geometry(q.dtype)
        return kin.blockwise(q, self.n_joints, (self.n_joints + 1, 4, 4), lambda qb: kin.all_poses(g, qb))

    def position(self, q: Tensor) -> Tensor:
        """End-effector position: ``q (..., n)`` radians -> ``(..., 3)`` metres, in the world frame.

        Equal to ``fk(q)[..., :3, 3]``; for large batches it computes no rotation matrices
        (:meth:`position_batch_last`), which makes it 2-3x faster. Differentiable (autograd).
        """
        self.check_q(q)
        g = self.geometry(q.dtype)
        return kin.position_batch_last(g, q.reshape(-1, self.n_joints).T).T.reshape(*q.shape[:-1], 3)

    def jacobian(self, q: Tensor) -> Tensor:
        """Geometric Jacobian in the world frame: ``q (..., n) -> (..., 6, n)``.

        Rows 0-2 map joint rates (rad/s) to the end-effector's linear velocity (m/s), rows
        3-5 to its angular velocity (rad/s). Column i is ``[z_i x (p_e - p_i); z_i]`` for
        joint i's axis ``z_i`` through the point ``p_i``, computed from the frames, not by
        autograd. The axis of joint i is the z axis of frame i - 1 (standard DH) or of
        frame i (modified DH), and that frame's origin lies on it.
        """
        x = self._plain_one(q)
        if x is not None:
            return kin.one_by_kernel(compiled.kernels().jacobians, self.geometry(torch.float64), x, q.ndim)
        self.check_q(q)
        g = self.geometry(q.dtype)
        if q.numel() == self.n_joints and kin.floats_ok(q):
            return kin.jacobian_floats(g, q)
        return kin.blockwise(q, self.n_joints, (6, self.n_joints), lambda qb: kin.jacobian(g, qb))

    def forward(self, q: Tensor) -> Tensor:
        """Same as :meth:`fk`."""
        return self.fk(q)




def _after_load(chain: DHChain, incompatible_keys) -> None:
    """``load_state_dict`` post-hook: the loaded buffers are checked now and the geometry rebuilt
    on next use (their version counters would show the change too; this also fails early)."""
    chain._geometry, chain._stamp = {}, ()
    chain._check_buffers()
