"""Serial chains: one kinematic model for any arm, batched and differentiable.

A chain of ``n`` joints is ``base . prod_i [origin_i . M_i(q_i)] . tool``, joint i moving about
(revolute, continuous) or along (prismatic) its unit ``axis_i`` in its own frame, as in URDF.
:class:`Chain` holds these as buffers and derives the kernels' :class:`~iiwa_torch.kinematics.Geometry`
from them, rebuilt whenever a buffer changes (``.to()``, ``load_state_dict``, an in-place edit).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from enum import Enum
from operator import attrgetter

import numpy as np
import torch
from torch import nn
from torch.compiler import is_dynamo_compiling

from . import compiled, so3
from . import kinematics as kin
from .checks import (
    all_finite,
    as_point,
    check_finite,
    check_float_tensor,
    check_generator,
    check_nonnegative,
    is_integer,
)
from .kinematics import Frame, Geometry

__all__ = ["Chain", "JointKind"]

Tensor = torch.Tensor
_version = attrgetter("_version")


class JointKind(str, Enum):
    """How a joint moves: about its axis within limits, about it without limits, or along it."""

    REVOLUTE = "revolute"
    CONTINUOUS = "continuous"
    PRISMATIC = "prismatic"


def as_transform(value, name: str) -> Tensor:
    """``value`` (``None``: the identity) as a checked ``(4, 4)`` float64 rigid transform."""
    matrix = torch.eye(4, dtype=torch.float64) if value is None else torch.as_tensor(value, dtype=torch.float64)
    check_transform(matrix, name)
    return matrix


def check_transform(matrix: Tensor, name: str) -> None:
    """Raise ``ValueError`` unless ``matrix`` is one ``(4, 4)`` rigid transform."""
    if matrix.shape != (4, 4):
        raise ValueError(f"{name} must be a 4x4 homogeneous transform, got shape {tuple(matrix.shape)}")
    so3.check_rigid(matrix, name, exact_bottom_row=True)


def check_limits(lim: Tensor, kinds: Sequence[JointKind]) -> None:
    """Raise ``ValueError`` unless ``lim (2, n)`` holds finite lower <= upper, ``(-inf, inf)`` for continuous joints."""
    n = len(kinds)
    if lim.shape != (2, n):
        raise ValueError(f"limits must have shape (2, {n}) with lower <= upper, got {tuple(lim.shape)}")
    if torch.isnan(lim).any():
        raise ValueError(f"limits must be finite numbers (or infinite for a continuous joint), got {lim.tolist()}")
    for i, kind in enumerate(kinds):
        lo, hi = lim[:, i].tolist()
        if kind is JointKind.CONTINUOUS:
            if (lo, hi) != (-math.inf, math.inf):
                raise ValueError(f"joint {i + 1} is continuous: its limits are (-inf, inf), got ({lo}, {hi})")
        elif not (math.isfinite(lo) and math.isfinite(hi)):
            raise ValueError(f"limits must be finite (radians or metres) for a {kind.value} joint, "
                             f"got {lim.tolist()}")
        elif lo > hi:
            raise ValueError(f"limits must have shape (2, {n}) with lower <= upper, got lower {lim[0].tolist()}, "
                             f"upper {lim[1].tolist()}")


def z_onto(axis: Tensor) -> Tensor:
    """A ``(3, 3)`` float64 rotation taking z onto the unit ``axis (3,)`` (Rodrigues; exact for coordinate axes)."""
    x, y, c = map(float, axis)
    s2 = x * x + y * y  # sin^2 of the angle between z and the axis
    if s2 == 0.0 and c < 0:  # -z: a half turn about x
        return torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    # 1 + c cancels near -z (an axis 2e-6 rad off -z lost 5 digits): there 1 + c = s2 / (1 - c) exactly
    one_plus_c = 1.0 + c if c >= 0 else s2 / (1.0 - c)
    k = torch.tensor([[0.0, 0.0, x], [0.0, 0.0, y], [-x, -y, 0.0]], dtype=torch.float64)  # [z x axis]_x
    return torch.eye(3, dtype=torch.float64) + k + k @ k / one_plus_c


class Chain(nn.Module):
    """A serial chain of revolute, continuous and prismatic joints, as a URDF file describes it.

    Args:
        origins: ``(n, 4, 4)`` each joint's transform from the previous link frame at ``q = 0``.
        axes: ``(n, 3)`` each joint's axis in its own frame (normalised here).
        kinds: n :class:`JointKind` values or names (default: all revolute).
        limits: ``(2, n)`` lower and upper limits, rad or m (default +-pi; continuous ``(-inf, inf)``;
            prismatic joints need them).
        joint_names, link_names: n names each (link i is joint i's child).
        base, tool: ``(4, 4)`` world to first frame, last link frame to end effector.
        velocity_limits: ``(n,)`` joint speeds (rad/s or m/s), if known.
        name: the robot's name.

    Results follow the dtype and device of ``q``; buffer changes are seen (and checked) by the next call.
    """

    def __init__(
        self,
        origins,
        axes,
        *,
        kinds: Sequence[JointKind | str] | None = None,
        limits=None,
        joint_names: Sequence[str] | None = None,
        link_names: Sequence[str] | None = None,
        base=None,
        tool=None,
        velocity_limits=None,
        name: str = "chain",
    ) -> None:
        super().__init__()
        origins = torch.as_tensor(origins, dtype=torch.float64)
        if origins.ndim != 3 or origins.shape[1:] != (4, 4) or origins.shape[0] < 1:
            raise ValueError(f"origins must have shape (n, 4, 4) with n >= 1, got {tuple(origins.shape)}")
        n = origins.shape[0]
        axes = torch.as_tensor(axes, dtype=torch.float64)
        if axes.shape != (n, 3):
            raise ValueError(f"axes must have shape ({n}, 3), got {tuple(axes.shape)}")
        self._setup(n, kinds, limits, joint_names, base, tool, velocity_limits, name)
        self.link_names = _names(link_names, "link_names", "link", n)
        self.register_buffer("origins", origins)
        self.register_buffer("axes", axes)
        self._check_buffers()
        self.axes = axes / axes.norm(dim=-1, keepdim=True)

    def _setup(self, n, kinds, limits, joint_names, base, tool, velocity_limits, name) -> None:
        """What every chain has: kinds, names, limits, base, tool, speeds; checked."""
        try:
            self.kinds = tuple(JointKind(k) for k in (kinds if kinds is not None else ["revolute"] * n))
        except ValueError:
            raise ValueError(f"kinds must be among {[k.value for k in JointKind]}, got {list(kinds)}") from None
        if len(self.kinds) != n:
            raise ValueError(f"kinds must have {n} entries, got {len(self.kinds)}")
        if not isinstance(name, str):
            raise TypeError(f"name must be a string, got {name!r}")
        self.name = name
        self.joint_names = _names(joint_names, "joint_names", "joint", n)
        if limits is None:
            if JointKind.PRISMATIC in self.kinds:
                raise ValueError("limits are needed for prismatic joints (metres)")
            bound = [math.inf if k is JointKind.CONTINUOUS else math.pi for k in self.kinds]
            limits = [[-b for b in bound], bound]
        lim = torch.as_tensor(limits, dtype=torch.float64)
        check_limits(lim, self.kinds)
        self._q_shape = f"(..., {n})"  # the shape check_q names
        self._one_shapes = ((n,), (1, n))  # one configuration's shapes, for _one_by_kernel
        self.register_buffer("limits", lim)
        self.register_buffer("base", as_transform(base, "base"))
        self.register_buffer("tool", as_transform(tool, "tool"))
        vel = None if velocity_limits is None else torch.as_tensor(velocity_limits, dtype=torch.float64)
        self.register_buffer("velocity_limits", vel)
        self._forget_geometry()
        self.register_load_state_dict_post_hook(_after_load)

    # ------------------------------------------------------------------ geometry
    def _geometry_buffers(self) -> tuple[Tensor, ...]:
        """The buffers the geometry is derived from (their changes rebuild it)."""
        b = self._buffers
        return b["origins"], b["axes"], b["base"], b["tool"], b["limits"]

    def _joint_transforms(self) -> tuple[Tensor, Tensor, Tensor]:
        """Float64 ``before, after (n, 4, 4)`` and ``offsets (n,)`` of :class:`~iiwa_torch.kinematics.Geometry`."""
        origins, axes = (t.detach().cpu().to(torch.float64) for t in (self.origins, self.axes))
        n = origins.shape[0]
        turn = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
        turn[:, :3, :3] = torch.stack([z_onto(a) for a in axes])
        return origins @ turn, turn.transpose(1, 2), torch.zeros(n, dtype=torch.float64)

    def _buffer_stamp(self) -> list[int]:
        """The geometry buffers' version counters (bumped by in-place writes) and storage addresses
        (changed by ``.data =``); assigning a buffer anew forgets them (:meth:`register_buffer`)."""
        watched = self._watched
        if watched is None:
            watched = self._watched = self._geometry_buffers()
        return [*map(_version, watched), *map(Tensor.data_ptr, watched)]

    def _forget_geometry(self) -> None:
        """Drop the cached geometry: the next call rebuilds it from the buffers as they are then."""
        self._geometry: dict[torch.dtype, Geometry] = {}
        self._stamp: list[int] = []
        self._watched: tuple[Tensor, ...] | None = None
        self._one_arrays: tuple | None = None  # the float64 geometry's float_arrays, on a CPU chain

    def geometry(self, dtype: torch.dtype = torch.float64) -> Geometry:
        """The cached :class:`~iiwa_torch.kinematics.Geometry` in ``dtype`` (float32 or float64), rebuilt
        and checked again whenever a geometry buffer changed."""
        stamp = self._buffer_stamp()
        if stamp != self._stamp:
            self._check_buffers()
            self._forget_geometry()
            self._stamp = self._buffer_stamp()
        g = self._geometry.get(dtype)
        if g is None:
            if dtype not in (torch.float32, torch.float64):
                raise TypeError(f"the chain computes in float32 or float64, got {dtype}")
            before, after, offsets = self._joint_transforms()
            prismatic = [k is JointKind.PRISMATIC for k in self.kinds]
            g = Geometry.build(before, after, prismatic, offsets, self.base, self.tool, self.limits, dtype)
            self._geometry[dtype] = g
            if g.limits.is_cpu:  # float64 arrays of the buffers, the same in either dtype's geometry
                self._one_arrays = g.float_arrays
        return g

    def _check_buffers(self) -> None:
        """The constructor's checks, on the buffers as they are now."""
        origins, axes = self._buffers["origins"], self._buffers["axes"]
        n = self.n_joints
        if origins.shape != (n, 4, 4) or axes.shape != (n, 3):
            raise ValueError(f"origins and axes must have shapes ({n}, 4, 4) and ({n}, 3), got "
                             f"{tuple(origins.shape)} and {tuple(axes.shape)}")
        for i, origin in enumerate(origins):
            check_transform(origin, f"origins[{i}]")
        check_finite(axes, "axes")
        if not (axes.norm(dim=-1) > 1e-9).all():
            raise ValueError(f"axes must be nonzero vectors, got {axes.tolist()}")
        self._check_common()

    def _check_common(self) -> None:
        _check_speeds(self.velocity_limits, self.n_joints)
        check_limits(self.limits, self.kinds)
        check_transform(self.base, "base")
        check_transform(self.tool, "tool")

    def _apply(self, fn, recurse=True):
        self._forget_geometry()
        return super()._apply(fn, recurse)

    def __setattr__(self, name: str, value) -> None:
        # nn.Module would drop the buffer before registering the parameter: refuse first, losing nothing
        if isinstance(value, nn.Parameter) and name in self._buffers:
            raise TypeError(f"chain.{name} is a buffer: assign a plain tensor (the kinematics are not "
                            "differentiable in the chain's own numbers)")
        super().__setattr__(name, value)

    def register_buffer(self, name: str, tensor: Tensor | None, persistent: bool = True) -> None:
        """``nn.Module``'s (assigning ``chain.tool = t`` calls it too), then the geometry is forgotten;
        ``velocity_limits`` (read by the trajectories and envs, not by the geometry) is checked here."""
        if name == "velocity_limits":
            _check_speeds(tensor, len(self.joint_names))
        super().register_buffer(name, tensor, persistent)
        self._forget_geometry()

    # ------------------------------------------------------------------ properties
    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    def extra_repr(self) -> str:
        head = f"name={self.name!r}, n_joints={self.n_joints}"
        width = max(map(len, ("joint", *self.joint_names))) + 2
        rows = [f"  {'joint':<{width}}{'kind':<11}{'axis':<22}{'min':>9}{'max':>9}   (deg or m)"]
        for name, kind, axis, lo, hi in zip(self.joint_names, self.kinds, self.axes.tolist(), *self.limits.tolist()):
            scale = 1.0 if kind is JointKind.PRISMATIC else math.degrees(1.0)
            text = "(" + ", ".join(f"{v + 0.0:.3g}" for v in axis) + ")"  # + 0.0: no "-0"
            rows.append(f"  {name:<{width}}{kind.value:<11}{text:<22}{lo * scale:9.1f}{hi * scale:9.1f}")
        return head + "\n" + "\n".join(rows)

    # ------------------------------------------------------------------ input checks
    def check_q(self, q: Tensor, name: str = "q") -> None:
        """Raise ``TypeError``/``ValueError`` unless ``q`` is a finite float ``(..., n)`` tensor on the
        chain's device (not ``meta``, not under ``torch.func.vmap``)."""
        n = self.n_joints
        check_float_tensor(q, name, self._q_shape)
        if q.ndim == 0 or q.shape[-1] != n:
            raise ValueError(f"{name} must have shape {self._q_shape}, got {tuple(q.shape)}")
        # not self.limits: nn.Module's attribute lookup is a large share of this check, which one
        # configuration's fk pays on every call (benchmarks/results/small.md, fk at batch 1)
        check_finite(q, name)  # first: a meta q is told it has no values, not to move the chain to meta
        lim = self._buffers["limits"]
        if not (q.is_cpu and lim.is_cpu) and q.device != lim.device:  # is_cpu: no device object built
            raise ValueError(
                f"{name} is on {q.device} but the chain is on {lim.device}; use chain.to({str(q.device)!r})"
            )

    def _one_by_kernel(self, q, kernel: str, shape: tuple[int, int]) -> np.ndarray | None:
        """The compiled one-configuration ``kernel`` (``end_pose`` or ``jacobian`` of
        :mod:`iiwa_torch.compiled.numba_kernels`) of one plain finite CPU configuration ``(n,)`` or ``(1, n)``
        without ``requires_grad``, with a current CPU geometry, as an array ``(*shape)`` or ``(1, *shape)`` in
        ``q``'s dtype; else ``None``, and the caller takes the checked path.

        One configuration's call is mostly overhead, so each check is one attribute read, ``q`` enters the kernel
        as a tuple of floats (cheaper to build and pass than an array) and the kernel checks that it is finite:
        benchmarks/results/small.md, fk at batch 1."""
        arrays = self._one_arrays
        if arrays is None or type(q) is not Tensor or not q.is_cpu or q.requires_grad or is_dynamo_compiling():
            return None  # torch.compile traces the torch path (it cannot trace into numba)
        dtype, q_shape = kin.NUMPY_DTYPES.get(q.dtype), q.shape
        if dtype is None or q_shape not in self._one_shapes or not compiled.ENABLED:
            return None
        try:
            values = q.tolist()
        except RuntimeError:  # no storage to read (torch.func.vmap): check_q says so
            return None
        if self._buffer_stamp() != self._stamp:
            return None
        row = len(q_shape) == 2
        out = np.empty(shape, dtype)
        if not getattr(compiled.kernels(), kernel)(*arrays, tuple(values[0] if row else values), out):
            return None  # not finite
        return out[None] if row else out

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
        """An upper bound (m) on the distance from the world origin to ``point (3,)``, fixed in the
        end-effector frame (default its origin): the sum of the fixed distances between frame
        origins, plus each prismatic joint's largest travel."""
        device = self.limits.device
        zero = torch.zeros(self.n_joints, dtype=torch.float64, device=device)
        frames = self.fk_all(zero)  # (n + 1, 4, 4)
        tip = torch.zeros(4, dtype=torch.float64, device=device)
        tip[3] = 1.0
        tip[:3] = as_point(point).to(device)
        tip = (self.fk(zero) @ tip)[:3]
        links = (frames[1:, :3, 3] - frames[:-1, :3, 3]).norm(dim=-1).sum()
        travel = sum(float(self.limits[:, i].abs().max()) for i, k in enumerate(self.kinds) if k is JointKind.PRISMATIC)
        return float(frames[0, :3, 3].norm() + links + (tip - frames[-1, :3, 3]).norm()) + travel

    def random_q(
        self, *shape: int, generator: torch.Generator | None = None, dtype: torch.dtype = torch.float64
    ) -> Tensor:
        """``(*shape, n)`` joint values uniform within the limits (a continuous joint within ``[-pi, pi]``)."""
        if not all(is_integer(size) and size >= 0 for size in shape):
            raise ValueError(f"random_q's shape must be non-negative integers, got {shape}")
        shape = tuple(map(int, shape))  # numpy's integers too
        if dtype not in (torch.float32, torch.float64):
            raise TypeError(f"random_q's dtype must be float32 or float64, got {dtype!r}")
        check_generator(generator)
        lim = self.geometry(dtype).draw_limits
        u = torch.rand(*shape, self.n_joints, generator=generator, dtype=dtype, device=lim.device)
        return lim[0] + u * (lim[1] - lim[0])

    # ------------------------------------------------------------------ batch-last API (unchecked)
    def frames_batch_last(self, q: Tensor, keep: bool = True) -> tuple[list[Frame], list[tuple[Tensor, Tensor]]]:
        """:func:`iiwa_torch.kinematics.frames_batch_last`: ``q (n, b)``, not checked -> base and link
        frames ``(x, y, z, p)``, each ``(3, b)``, and joint axes ``(z_i, p_i)``."""
        return kin.frames_batch_last(self.geometry(q.dtype), q, keep)

    def tool_frame_batch_last(self, frame: Frame) -> Frame:
        """The last link frame of :meth:`frames_batch_last` -> the end-effector frame, same layout."""
        return kin.tool_frame_batch_last(self.geometry(frame[0].dtype), frame)

    def position_batch_last(self, q: Tensor, trig: tuple[Tensor, Tensor] | None = None) -> Tensor:
        """End-effector positions: ``q (n, b)``, not checked -> ``(3, b)``; ``trig``: ``(cos q, sin q)`` if known."""
        return kin.position_batch_last(self.geometry(q.dtype), q, trig)

    # ------------------------------------------------------------------ kinematics (checked, batch first)
    def fk(self, q: Tensor) -> Tensor:
        """End-effector pose: ``q (..., n)`` (rad, m for prismatic) -> ``(..., 4, 4)`` (m), world frame.

        Differentiable; above ``SMALL_BATCH`` configurations the backward is ``J^T`` times the pose
        gradient's twist (:class:`~iiwa_torch.kinematics.EndPoseFunction`).
        """
        out = self._one_by_kernel(q, "end_pose", (4, 4))
        if out is not None:
            return torch.from_numpy(out)
        self.check_q(q)
        g = self.geometry(q.dtype)
        if q.requires_grad and torch.is_grad_enabled() and q.numel() > kin.SMALL_BATCH * self.n_joints:
            return kin.EndPoseFunction.apply(q, g)
        return kin.blockwise(q, self.n_joints, (4, 4), lambda qb: kin.end_pose(g, qb))

    def fk_all(self, q: Tensor) -> Tensor:
        """``q (..., n) -> (..., n + 1, 4, 4)``: the base, then link frames 1..n (DH frames, or a URDF's
        child links); no tool: ``fk(q) == fk_all(q)[..., -1, :, :] @ chain.tool``."""
        self.check_q(q)
        g = self.geometry(q.dtype)
        return kin.blockwise(q, self.n_joints, (self.n_joints + 1, 4, 4), lambda qb: kin.all_poses(g, qb))

    def position(self, q: Tensor) -> Tensor:
        """``fk(q)[..., :3, 3]``: ``q (..., n)`` -> ``(..., 3)`` (m), without rotations (but for one configuration,
        whose :meth:`fk` costs less than the batched position kernel's set-up); differentiable."""
        out = self._one_by_kernel(q, "end_pose", (4, 4))
        if out is not None:
            return torch.from_numpy(out[..., :3, 3])
        self.check_q(q)
        g = self.geometry(q.dtype)
        return kin.position_batch_last(g, q.reshape(-1, self.n_joints).T).T.reshape(*q.shape[:-1], 3)

    def jacobian(self, q: Tensor) -> Tensor:
        """Geometric Jacobian in the world frame: ``q (..., n) -> (..., 6, n)``: linear (m/s) then angular
        (rad/s) rows; column i is ``[z_i x (p_e - p_i); z_i]``, or ``[z_i; 0]`` for a prismatic joint."""
        out = self._one_by_kernel(q, "jacobian", (6, self.n_joints))
        if out is not None:
            return torch.from_numpy(out)
        self.check_q(q)
        g = self.geometry(q.dtype)
        return kin.blockwise(q, self.n_joints, (6, self.n_joints), lambda qb: kin.jacobian(g, qb))

    def forward(self, q: Tensor) -> Tensor:
        """Same as :meth:`fk`."""
        return self.fk(q)


def _after_load(chain: Chain, incompatible_keys) -> None:
    """``load_state_dict`` post-hook: check the loaded buffers now (fail early)."""
    chain._forget_geometry()
    chain._check_buffers()


def _check_speeds(speeds, n: int) -> None:
    """``velocity_limits``: None, or ``n`` positive finite speeds (rad/s, m/s)."""
    if speeds is None:
        return
    if not (isinstance(speeds, Tensor) and speeds.shape == (n,) and bool((speeds > 0).all()) and all_finite(speeds)):
        shown = speeds.tolist() if isinstance(speeds, Tensor) else speeds
        raise ValueError(f"velocity_limits must be {n} positive finite speeds (rad/s, m/s), got {shown}")


def _names(names, what: str, stem: str, n: int) -> tuple[str, ...]:
    """``n`` names (default ``stem1 ... stemn``), checked."""
    out = [f"{stem}{i + 1}" for i in range(n)] if names is None else list(names)
    if len(out) != n or not all(isinstance(v, str) for v in out):
        raise ValueError(f"{what} must be {n} strings, got {out!r}")
    return tuple(out)
