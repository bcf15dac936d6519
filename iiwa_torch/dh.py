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
from collections.abc import Sequence
from enum import Enum
from functools import reduce
from itertools import accumulate

import numpy as np
import torch
from torch import nn

from ._checks import check_finite, check_float_tensor

__all__ = ["Convention", "DHChain"]

Tensor = torch.Tensor
Frame = tuple[Tensor, Tensor, Tensor, Tensor]  # x, y, z axis columns and origin, each (3, batch)
_BLOCK = 8192  # configurations per block: the elementwise kernel's working set stays in cache
_POSITION_BLOCK = 65536  # the same for the position kernel, whose working set is a third (measured)
_SMALL_BATCH = 128  # up to this many configurations the 4x4-product kernel is faster (measured)
_NUMPY_DTYPES = {torch.float32: np.float32, torch.float64: np.float64}


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


def _rotate_x(y, z, ca: float, sa: float):
    """Rotate the frame axes y, z about its own x by a constant angle (cosine ca, sine sa).
    With ``-sa``, it rotates the y, z coordinates of points instead. Tensors or floats."""
    if ca == 0.0:  # alpha = +-pi/2: a swap and a sign flip
        return (z, -y) if sa > 0 else (-z, y)
    if sa == 0.0:  # alpha = 0 or pi
        return (y, z) if ca > 0 else (-y, -z)
    return ca * y + sa * z, ca * z - sa * y


def _rotate_point_z(x, y, c, s) -> tuple:
    """The x, y coordinates of points rotated about z by the angle with cosine c and sine s:
    ``(c x - s y, s x + c y)``. ``x`` and ``y`` are tensors or floats (a point on the z axis
    stays there); ``c`` and ``s`` are tensors, or floats when everything is."""
    if not isinstance(x, Tensor) and not isinstance(y, Tensor) and x == y == 0.0:
        return x, y
    if not isinstance(c, Tensor):  # one configuration, in Python floats
        return c * x - s * y, s * x + c * y
    return _multiply_add(c * x, s, y, -1.0), _multiply_add(s * x, c, y, 1.0)


def _multiply_add(u: Tensor, v: Tensor, w, sign: float) -> Tensor:
    """``u + sign * v * w`` in one op, ``w`` a tensor or a float."""
    return torch.addcmul(u, v, w, value=sign) if isinstance(w, Tensor) else torch.add(u, v, alpha=sign * w)


def _combine(vectors: Sequence[Tensor], coefficients: Sequence[float], start: Tensor | None = None) -> Tensor:
    """``start + sum_k c_k v_k`` for ``(3, b)`` vectors and Python-float coefficients, with no op
    for a zero coefficient (nor for a lone unit one): a flange offset along z is one multiply-add."""
    out = start
    for v, c in zip(vectors, coefficients):
        if c != 0.0:
            out = (v if c == 1.0 else v * c) if out is None else torch.add(out, v, alpha=c)
    return out


def _cross(u, v) -> tuple[Tensor, Tensor, Tensor]:
    """Cross product of vectors given by their components ``u[0..2]``, ``v[0..2]`` (tensors that
    broadcast): six elementwise ops on contiguous rows, several times faster here than
    ``torch.linalg.cross`` along a middle dimension."""
    return (
        torch.addcmul(u[1] * v[2], u[2], v[1], value=-1),
        torch.addcmul(u[2] * v[0], u[0], v[2], value=-1),
        torch.addcmul(u[0] * v[1], u[1], v[0], value=-1),
    )


def _off_torch_ok(q: Tensor) -> bool:
    """On the CPU with nothing to differentiate: one configuration may be computed outside torch
    (numpy, Python floats), whose per-call overhead is a fraction of torch's."""
    return q.device.type == "cpu" and not (q.requires_grad and torch.is_grad_enabled())


def _exact(v: float) -> float:
    """Snap cos/sin of a multiple of pi/2 to exactly 0 or +-1 (6e-17 is rounding noise)."""
    return float(round(v)) if abs(v - round(v)) < 1e-12 else v


def _transform(rot_axis: str, angle: float = 0.0, shift: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Tensor:
    c, s = _exact(math.cos(angle)), _exact(math.sin(angle))
    m = torch.eye(4, dtype=torch.float64)
    i, j = (1, 2) if rot_axis == "x" else (0, 1)
    m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
    m[:3, 3] = torch.tensor(shift, dtype=torch.float64)
    return m


def _link_coefficients(dh: Tensor, convention: Convention) -> Tensor:
    """``(n, 3, 16)``: ``A_i = cos(theta_i) C0 + sin(theta_i) C1 + C2`` with constant ``C_k``."""
    rz_cos = torch.diag(torch.tensor([1.0, 1.0, 0.0, 0.0], dtype=torch.float64))
    rz_sin = torch.zeros(4, 4, dtype=torch.float64)
    rz_sin[0, 1], rz_sin[1, 0] = -1.0, 1.0
    rz_one = torch.diag(torch.tensor([0.0, 0.0, 1.0, 1.0], dtype=torch.float64))
    coeffs = []
    for a, alpha, d, _ in dh.tolist():
        if convention is Convention.STANDARD:  # Rz(theta) . [Tz(d) Tx(a) Rx(alpha)]
            after = _transform("z", 0.0, (0.0, 0.0, d)) @ _transform("x", alpha, (a, 0.0, 0.0))
            terms = [m @ after for m in (rz_cos, rz_sin, rz_one)]
        else:  # [Rx(alpha) Tx(a)] . Rz(theta) . [Tz(d)]
            before, after = _transform("x", alpha, (a, 0.0, 0.0)), _transform("z", 0.0, (0.0, 0.0, d))
            terms = [before @ m @ after for m in (rz_cos, rz_sin, rz_one)]
        coeffs.append(torch.stack([t.reshape(16) for t in terms]))
    return torch.stack(coeffs)


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
            raise ValueError(
                f"table must have shape (n, 4) with rows (a, alpha, d, theta_offset), got {tuple(dh.shape)}"
            )
        if not torch.isfinite(dh).all():
            raise ValueError("table contains NaN or inf")
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
        self._has_base = not torch.equal(self.base, torch.eye(4, dtype=torch.float64))
        self._has_tool = not torch.equal(self.tool, torch.eye(4, dtype=torch.float64))
        self._tool_columns = self.tool[:3].T.tolist()  # its rotation's columns, then its translation
        self._base_rows = self.base[:3].tolist()
        self._offset_list = dh[:, 3].tolist()
        # The small-batch kernel's constants: A_i = cos C0 + sin C1 + C2, per link; the "end"
        # set has the base folded into the first link and the tool into the last.
        links = _link_coefficients(dh, self.convention).view(n, 3, 4, 4)
        end = links.clone()
        end[0] = self.base @ end[0]
        end[-1] = end[-1] @ self.tool
        for name, coeffs in (("_link", links), ("_end", end)):
            coeffs = coeffs.reshape(n, 3, 16)
            self.register_buffer(f"{name}_trig", coeffs[:, :2].contiguous(), persistent=False)
            self.register_buffer(f"{name}_const", coeffs[:, 2:].contiguous(), persistent=False)
        # sin(theta + phase) is (cos theta, sin theta) in one op: phase (n, 1, 2) = (offset + pi/2, offset)
        phase = dh[:, 3, None] + torch.tensor([math.pi / 2, 0.0], dtype=torch.float64)
        self.register_buffer("_trig_phase", phase[:, None], persistent=False)
        self.register_buffer("_offsets", dh[:, 3, None].clone(), persistent=False)  # (n, 1)
        # cos and sin of the offsets (n, 1), to turn a caller's cos/sin of q into those of q + offset
        self.register_buffer("_offset_trig", torch.stack([dh[:, 3].cos(), dh[:, 3].sin()])[..., None], persistent=False)
        self._has_offsets = any(self._offset_list)
        self._converted: dict[tuple[torch.dtype, str], Tensor | tuple[np.ndarray, ...]] = {}

    def _in(self, dtype: torch.dtype, name: str) -> Tensor:
        """Buffer ``name`` in ``dtype``, converted once and cached (``.to()`` and friends clear the
        cache): a float64 chain fed float32 angles converts nothing per call."""
        key = (dtype, name)
        if key not in self._converted:
            self._converted[key] = getattr(self, name).to(dtype)
        return self._converted[key]

    def _apply(self, fn, recurse=True):
        self._converted = {}
        return super()._apply(fn, recurse)

    # ------------------------------------------------------------------ properties
    @property
    def n_joints(self) -> int:
        return len(self._steps)

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
        check_float_tensor(q, name, f"(..., {n})")
        if q.ndim == 0 or q.shape[-1] != n:
            raise ValueError(f"{name} must have shape (..., {n}), got {tuple(q.shape)}")
        if q.device != self.dh.device:
            raise ValueError(
                f"{name} is on {q.device} but the chain is on {self.dh.device}; use chain.to({str(q.device)!r})"
            )
        check_finite(q, name)

    def within_limits(self, q: Tensor, tol: float = 0.0) -> Tensor:
        """``(..., n) -> (...)`` bool: every joint within ``[lower - tol, upper + tol]``."""
        lim = self._in(q.dtype, "limits")
        return ((q >= lim[0] - tol) & (q <= lim[1] + tol)).all(-1)

    def clamp(self, q: Tensor) -> Tensor:
        """``(..., n) -> (..., n)``: ``q`` clamped into the joint limits (a new tensor)."""
        lim = self._in(q.dtype, "limits")
        return torch.maximum(torch.minimum(q, lim[1]), lim[0])

    def random_q(
        self, *shape: int, generator: torch.Generator | None = None, dtype: torch.dtype = torch.float64
    ) -> Tensor:
        """``(*shape, n)`` joint angles drawn uniformly within the limits."""
        u = torch.rand(*shape, self.n_joints, generator=generator, dtype=dtype, device=self.dh.device)
        lim = self._in(dtype, "limits")
        return lim[0] + u * (lim[1] - lim[0])

    # ------------------------------------------------------------------ kinematics
    # Inside, frames are "batch last": a (F, 3, 4, b) tensor of frame, row, column (x, y, z
    # axes, origin) and configuration, with F = n + 1 (base and links) if ``keep``, else 1
    # (the last link). Batch last keeps every elementwise op contiguous.

    def _cos_sin(self, q: Tensor, trig: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
        """``q (n, b)`` -> cosine and sine of the joint angles plus offsets, each ``(n, b)`` contiguous.

        ``trig``: the caller's cosine and sine of ``q`` itself, reused (rotated by the offsets
        if the chain has any) instead of computed again."""
        if trig is None:
            theta = (q + self._in(q.dtype, "_offsets")).contiguous()
            return torch.cos(theta), torch.sin(theta)
        c, s = trig
        if not self._has_offsets:
            return c, s
        co, so = self._in(q.dtype, "_offset_trig")  # cos(q + o) = c co - s so, sin(q + o) = s co + c so
        return torch.addcmul(c * co, s, so, value=-1), torch.addcmul(s * co, c, so)

    def frames_batch_last(self, q: Tensor, keep: bool = True) -> tuple[list[Frame], list[tuple[Tensor, Tensor]]]:
        """The elementwise kernel itself, for hot loops that keep a batch-last layout (IK).

        ``q (n, b)``: joint angles, batch last, not checked. Returns ``(frames, axes)``:
        ``frames`` holds ``(x, y, z, p)``, the axis columns and the origin of a frame, each
        ``(3, b)``, for the base and every link if ``keep`` (else only the last link);
        ``axes`` holds ``(z_i, p_i)``, joint i's axis and a point on it (if ``keep``). The
        tool is not applied. The moving frame's axes are rotated with elementwise
        multiply-adds over the whole batch; the constant twists (``alpha`` of 0 or +-pi/2)
        are swaps and sign flips; no 4x4 products.
        """
        c, s = self._cos_sin(q)
        x, y, z, p = self._in(q.dtype, "base")[:3, :, None].expand(3, 4, q.shape[1]).unbind(1)  # each (3, b)
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
        return (frames if keep else [(x, y, z, p)]), axes

    def position_batch_last(self, q: Tensor, trig: tuple[Tensor, Tensor] | None = None) -> Tensor:
        """The end-effector position alone: ``q (n, b)`` -> ``(3, b)``, batch last, not checked
        (for hot loops that keep a batch-last layout: the envs). One configuration is computed
        in Python floats, small batches take the 4x4 product kernel, large ones
        :meth:`_position_horner` in blocks.

        ``trig``: ``(cos q, sin q)``, each ``(n, b)``, if the caller has them (the envs'
        observations do): large batches then skip their own trigonometry."""
        b = q.shape[1]
        if b == 1 and _off_torch_ok(q):
            return self._position_floats(q)
        if b <= _SMALL_BATCH:
            return self._end_pose_matmul(q.T)[:, :3, 3].T
        return self._position_horner(q, trig)

    def _carry_tool_point(self, c, s) -> tuple:
        """Horner's scheme: the tool point carried through ``A_n, ..., A_1`` from the end of the
        chain. ``c``, ``s``: per joint, the cosine and sine of its angle (rows of ``b``, or Python
        floats for one configuration) -> the point's three coordinates before the base transform.

        Per joint, a rotation of the point's coordinates instead of a rotation of three frame
        axes: about a third of the elementwise work of :meth:`frames_batch_last`. Coordinates
        stay Python floats while they are constant (the tool point on the last axes), so those
        joints cost nothing."""
        v0, v1, v2 = self._tool_columns[3]
        standard = self.convention is Convention.STANDARD
        for i, (a, ca, sa, d) in reversed(list(enumerate(self._steps))):
            if standard:  # A_i = Rz(theta) Tz(d) Tx(a) Rx(alpha)
                v1, v2 = _rotate_x(v1, v2, ca, -sa)
                v0 = v0 + a if a else v0
            v2 = v2 + d if d else v2
            v0, v1 = _rotate_point_z(v0, v1, c[i], s[i])
            if not standard:  # A_i = Rx(alpha) Tx(a) Rz(theta) Tz(d)
                v0 = v0 + a if a else v0
                v1, v2 = _rotate_x(v1, v2, ca, -sa)
        return v0, v1, v2

    def _position_horner(self, q: Tensor, trig: tuple[Tensor, Tensor] | None = None) -> Tensor:
        """``q (n, b)`` -> ``(3, b)`` end-effector positions, elementwise (:meth:`_carry_tool_point`),
        in blocks of configurations that keep the working set in cache."""
        c, s = self._cos_sin(q, trig)
        blocks = []
        for i in range(0, q.shape[1], _POSITION_BLOCK):
            cb, sb = c[:, i : i + _POSITION_BLOCK], s[:, i : i + _POSITION_BLOCK]
            blocks.append(torch.stack([v if isinstance(v, Tensor) else cb[0].new_full(cb[0].shape, v)
                                       for v in self._carry_tool_point(cb, sb)]))
        point = blocks[0] if len(blocks) == 1 else torch.cat(blocks, 1)
        if not self._has_base:
            return point
        base = self._in(q.dtype, "base")
        return torch.addmm(base[:3, 3, None], base[:3, :3], point)

    def _position_floats(self, q: Tensor) -> Tensor:
        """One configuration ``(n, 1)`` -> its ``(3, 1)`` position, computed in Python floats
        (double precision): fewer instructions than even one chain of small numpy products."""
        theta = [t + offset for (t,), offset in zip(q.tolist(), self._offset_list)]
        point = self._carry_tool_point([math.cos(t) for t in theta], [math.sin(t) for t in theta])
        if self._has_base:
            point = [row[3] + row[0] * point[0] + row[1] * point[1] + row[2] * point[2] for row in self._base_rows]
        return torch.from_numpy(np.array(point, dtype=_NUMPY_DTYPES[q.dtype]).reshape(3, 1))

    def _frames_elementwise(self, q: Tensor) -> Tensor:
        """Large batches: ``(b, n) -> (n + 1, 3, 4, b)`` through :meth:`frames_batch_last`."""
        frames, _ = self.frames_batch_last(q.T)
        return torch.stack([torch.stack(f, 1) for f in frames], 0)

    def _link_matrices(self, q: Tensor, end: bool) -> tuple[Tensor, ...]:
        """``(b, n)`` -> the n link transforms ``A_i``, each ``(b, 4, 4)``, or ``(4, 4)`` if b is 1
        (``mm`` on matrices costs half of ``bmm`` on a batch of one). With ``end``, the base is
        folded into the first and the tool into the last. Each ``A_i`` is linear in the cosine
        and sine of its angle, so one batched product with constant coefficients builds them all."""
        n, b, dtype = self.n_joints, q.shape[0], q.dtype
        trig = torch.sin(q.T.unsqueeze(-1) + self._in(dtype, "_trig_phase"))  # (n, b, 2): cos, sin
        prefix = "_end" if end else "_link"
        links = torch.baddbmm(self._in(dtype, prefix + "_const"), trig, self._in(dtype, prefix + "_trig"))  # (n, b, 16)
        return links.view(n, 4, 4).unbind(0) if b == 1 else links.view(n, b, 4, 4).unbind(0)

    def _end_pose_matmul(self, q: Tensor) -> Tensor:
        """Small batches, few ops: ``(b, n) -> (b, 4, 4)`` end pose (tool included), a chain of 4x4 products."""
        if q.shape[0] == 1 and _off_torch_ok(q):
            return torch.from_numpy(self._end_pose_numpy(q)[None])
        product = torch.mm if q.shape[0] == 1 else torch.bmm
        return reduce(product, self._link_matrices(q, end=True)).view(q.shape[0], 4, 4)

    def _end_pose_numpy(self, q: Tensor) -> np.ndarray:
        """One configuration, ``(1, n)`` or ``(n, 1)`` -> its ``(4, 4)`` end pose: the
        same products as :meth:`_link_matrices` and :meth:`_end_pose_matmul`, in numpy. Its
        latency is all per-call overhead, and numpy's is about a third of torch's (measured:
        one call about half as long)."""
        key = (q.dtype, "numpy")  # the constants as numpy arrays, cached (.numpy() costs 4 dispatches)
        if key not in self._converted:
            names = ("_trig_phase", "_end_trig", "_end_const")
            self._converted[key] = tuple(self._in(q.dtype, name).numpy() for name in names)
        phase, coeffs, const = self._converted[key]
        trig = np.sin(q.numpy().reshape(-1, 1, 1) + phase)  # (n, 1, 2): cos, sin
        return reduce(np.matmul, (const + trig @ coeffs).reshape(-1, 4, 4))

    def _frames_matmul(self, q: Tensor) -> Tensor:
        """Small batches: ``(b, n) -> (n + 1, b, 4, 4)``: the base and every link frame."""
        b = q.shape[0]
        base = self._in(q.dtype, "base")
        product, base = (torch.mm, base) if b == 1 else (torch.bmm, base.expand(b, 4, 4))
        links = self._link_matrices(q, end=False)
        if self._has_base:
            frames = list(accumulate(links, product, initial=base))
        else:
            frames = [base, *accumulate(links, product)]
        return torch.stack(frames).view(self.n_joints + 1, b, 4, 4)

    def _tool_frame(self, frame: Frame) -> Frame:
        """The last link frame ``(x, y, z, p)``, each ``(3, b)``, -> the end-effector (tool) frame."""
        if not self._has_tool:
            return frame
        axes, columns = frame[:3], self._tool_columns
        return (*(_combine(axes, column) for column in columns[:3]), _combine(axes, columns[3], start=frame[3]))

    def _axes(self, q: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(b, n)`` -> joint axes ``z (n, 3, b)``, a point on each ``(n, 3, b)`` and the end
        position ``(3, b)``: what the Jacobian needs, without stacking whole frames."""
        if q.shape[0] <= _SMALL_BATCH:
            frames = self._frames_matmul(q)[:, :, :3].permute(0, 2, 3, 1)  # (n + 1, 3, 4, b), a view
            axes = frames[:-1] if self.convention is Convention.STANDARD else frames[1:]
            return axes[:, :, 2], axes[:, :, 3], self._tool_frame(frames[-1].unbind(1))[3]
        frames, axes = self.frames_batch_last(q.T)
        z, origin = (torch.stack(column) for column in zip(*axes))
        return z, origin, self._tool_frame(frames[-1])[3]

    @staticmethod
    def _poses(frames: Tensor) -> Tensor:
        """``(F, 3, 4, b)`` -> ``(b, F, 4, 4)`` homogeneous matrices."""
        top = frames.permute(3, 0, 1, 2)
        bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=top.dtype, device=top.device)
        return torch.cat([top, bottom.expand(*top.shape[:2], 1, 4)], -2)

    def _blockwise(self, q: Tensor, shape: tuple[int, ...], fn, *others: Tensor) -> Tensor:
        """Apply ``fn: (b, n), *others' blocks -> (b, *shape)`` to blocks of at most ``_BLOCK``
        configurations of ``q (..., n)`` (so each block's intermediates stay in the CPU cache)
        and return ``(..., *shape)``. ``others`` share ``q``'s leading batch shape."""
        flat = q.reshape(-1, self.n_joints)
        rest = [o.reshape(flat.shape[0], *o.shape[q.ndim - 1 :]) for o in others]
        if flat.shape[0] <= _BLOCK:
            out = fn(flat, *rest)
        else:
            out = q.new_empty(flat.shape[0], *shape)
            for start in range(0, flat.shape[0], _BLOCK):
                block = slice(start, start + _BLOCK)
                out[block] = fn(flat[block], *(o[block] for o in rest))
        return out.reshape(*q.shape[:-1], *shape)

    def _end_pose(self, qb: Tensor) -> Tensor:
        if qb.shape[0] <= _SMALL_BATCH:
            return self._end_pose_matmul(qb)
        frames, _ = self.frames_batch_last(qb.T, keep=False)
        return self._poses(torch.stack(self._tool_frame(frames[0]), 1)[None])[:, 0]

    def _all_poses(self, qb: Tensor) -> Tensor:
        if qb.shape[0] <= _SMALL_BATCH:
            return self._frames_matmul(qb).transpose(0, 1)
        return self._poses(self._frames_elementwise(qb))

    def _pose_vjp(self, q: Tensor, pose: Tensor, grad: Tensor) -> Tensor:
        """The backward pass of :meth:`fk`: angles ``(b, n)``, their end poses ``(b, 4, 4)`` and
        the gradient of a loss with respect to those poses -> its gradient ``(b, n)`` with
        respect to the angles, computed batch last:
        ``dL/dq_i = z_i . ((p_e - p_i) x g + w)``, with ``g = dL/dp`` and ``w = sum_k R[:, k] x G[:, k]``
        (``G = dL/dR``) the axial vector of ``R G^T``."""
        z, origin, end = self._axes(q)  # (n, 3, b), (n, 3, b), (3, b)
        g = grad[:, :3].permute(1, 2, 0).contiguous()  # (3, 4, b): rows of dL/dT, batch last
        w = [c.sum(0) for c in _cross(pose[:, :3, :3].permute(1, 2, 0), g[:, :3])]  # sum over columns k
        moment = [m + wc for m, wc in zip(_cross(end, g[:, 3]), w)]  # (p_e x g + w), each (b,)
        z, lever_x_g = z.unbind(1), _cross(origin.unbind(1), g[:, 3])  # each (n, b)
        return sum(zc * (mc - pc) for zc, mc, pc in zip(z, moment, lever_x_g)).T

    def _jacobian(self, qb: Tensor) -> Tensor:
        z, origin, end = self._axes(qb)  # (n, 3, b), (n, 3, b), (3, b)
        z = z.unbind(1)
        rows = (*_cross(z, (end - origin).unbind(1)), *z)  # 6 x (n, b)
        return torch.stack([row.T for row in rows], 1)  # (b, 6, n): the transpose happens in this one copy

    def fk(self, q: Tensor) -> Tensor:
        """End-effector pose: ``q (..., n)`` radians -> ``(..., 4, 4)``, metres, in the world frame.

        Differentiable. Above 128 configurations the backward pass is ``J(q)^T`` times the
        pose gradient's twist, not a replay of the forward kernel; up to 128, autograd
        through the few ops of the small-batch kernel costs less (at batch 1, half the
        instructions of the closed form).
        """
        self.check_q(q)
        if q.requires_grad and torch.is_grad_enabled() and q.numel() > _SMALL_BATCH * self.n_joints:
            return _EndPose.apply(q, self)
        return self._blockwise(q, (4, 4), self._end_pose)

    def fk_all(self, q: Tensor) -> Tensor:
        """Every frame: ``q (..., n) -> (..., n + 1, 4, 4)``: the base, then link frames 1..n.

        The tool transform is not applied: ``fk(q) == fk_all(q)[..., -1, :, :] @ chain.tool``.
        """
        self.check_q(q)
        return self._blockwise(q, (self.n_joints + 1, 4, 4), self._all_poses)

    def position(self, q: Tensor) -> Tensor:
        """End-effector position: ``q (..., n)`` radians -> ``(..., 3)`` metres, in the world frame.

        Equal to ``fk(q)[..., :3, 3]``; for large batches it computes no rotation matrices
        (:meth:`position_batch_last`), which makes it 2-3x faster. Differentiable (autograd).
        """
        self.check_q(q)
        return self.position_batch_last(q.reshape(-1, self.n_joints).T).T.reshape(*q.shape[:-1], 3)

    def jacobian(self, q: Tensor) -> Tensor:
        """Geometric Jacobian in the world frame: ``q (..., n) -> (..., 6, n)``.

        Rows 0-2 map joint rates (rad/s) to the end-effector's linear velocity (m/s), rows
        3-5 to its angular velocity (rad/s). Column i is ``[z_i x (p_e - p_i); z_i]`` for
        joint i's axis ``z_i`` through the point ``p_i``, computed from the frames, not by
        autograd. The axis of joint i is the z axis of frame i - 1 (standard DH) or of
        frame i (modified DH), and that frame's origin lies on it.
        """
        self.check_q(q)
        return self._blockwise(q, (6, self.n_joints), self._jacobian)

    def forward(self, q: Tensor) -> Tensor:
        """Same as :meth:`fk`."""
        return self.fk(q)


class _EndPose(torch.autograd.Function):
    """``fk`` with a closed-form backward: the pose moves as ``dT/dq_i = [z_i]x T`` about
    joint i's axis, so ``dL/dq = J^T [g_p; w]``, with ``g_p = dL/dp`` and ``w`` the axial
    vector of ``R (dL/dR)^T`` (:meth:`DHChain._pose_vjp`). The joint axes instead of
    replaying every op of the forward."""

    @staticmethod
    def forward(q: Tensor, chain: DHChain) -> Tensor:
        return chain._blockwise(q, (4, 4), chain._end_pose)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        ctx.chain = inputs[1]
        ctx.save_for_backward(inputs[0], output)

    @staticmethod
    def backward(ctx, grad: Tensor):
        q, pose = ctx.saved_tensors
        return ctx.chain._blockwise(q, (ctx.chain.n_joints,), ctx.chain._pose_vjp, pose, grad), None
