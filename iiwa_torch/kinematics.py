"""Forward-kinematics kernels of any serial chain: pure functions over a frozen :class:`Geometry`,
which :class:`~iiwa_torch.chain.Chain` derives from its buffers.

Up to ``SMALL_BATCH`` configurations: the compiled recursion (CPU, no autograd, numba) or 4x4
link products; above, the elementwise batch-last kernel :func:`frames_batch_last` in blocks of
``BLOCK``. Which kernel runs, and why: docs/kinematics.md.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import reduce
from itertools import accumulate

import numpy as np
import torch
from torch.compiler import is_dynamo_compiling

from . import compiled

__all__ = ["BLOCK", "POSITION_BLOCK", "SMALL_BATCH", "EndPoseFunction", "Frame", "Geometry", "all_poses", "blockwise",
           "dh_transforms", "elementary_transform", "end_pose", "end_pose_matmul", "frame_lists", "float64_rows",
           "frames_batch_last", "jacobian", "like", "NUMPY_DTYPES", "pose_vjp", "position_batch_last",
           "position_horner", "tool_frame_batch_last", "untracked_cpu"]

Tensor = torch.Tensor
Frame = tuple[Tensor, Tensor, Tensor, Tensor]  # x, y, z axis columns and origin, each (3, batch)
BLOCK = 8192  # configurations per block: the elementwise kernel's working set stays in cache
POSITION_BLOCK = 65536  # the same for the position kernel, whose working set is a third (benchmarks/results/fk.md)
SMALL_BATCH = 128  # up to this many: the compiled or 4x4-product kernel (benchmarks/results/fk.md)


def _exact(v: float) -> float:
    """Snap cos/sin of a multiple of pi/2 to exactly 0 or +-1 (6e-17 is rounding noise)."""
    return float(round(v)) if abs(v - round(v)) < 1e-12 else v


def _snap_angle(angle: float, tol: float) -> float:
    """``angle`` (rad), or the multiple of pi/2 within ``tol`` of it."""
    k = round(angle / (math.pi / 2))
    return k * (math.pi / 2) if abs(angle - k * (math.pi / 2)) < tol else angle


def _snap_matrix(m: Tensor, tol: float) -> Tensor:
    """``m`` with entries within ``tol`` of 0 or +-1 set to it (rounding noise of exact rotations)."""
    near = torch.round(m)
    return torch.where(((m - near).abs() < tol) & (near.abs() <= 1), near, m)


def elementary_transform(rot_axis: str, angle: float = 0.0, shift: tuple[float, float, float] = (0.0, 0.0, 0.0)):
    """``(4, 4)`` float64: a rotation by ``angle`` (rad) about ``rot_axis`` (``"x"`` or ``"z"``),
    then the translation ``shift`` (m); cos/sin of multiples of pi/2 are exact."""
    if rot_axis not in ("x", "z"):
        raise ValueError(f"rot_axis must be 'x' or 'z', got {rot_axis!r}")
    c, s = _exact(math.cos(angle)), _exact(math.sin(angle))
    m = torch.eye(4, dtype=torch.float64)
    i, j = (1, 2) if rot_axis == "x" else (0, 1)
    m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
    m[:3, 3] = torch.tensor(shift, dtype=torch.float64)
    return m


def dh_transforms(dh: Tensor, modified: bool) -> tuple[Tensor, Tensor]:
    """DH rows ``(a, alpha, d, offset)`` ``(n, 4)`` -> ``before, after (n, 4, 4)`` (:class:`Geometry`):
    ``I, Tz(d) Tx(a) Rx(alpha)`` (standard) or ``Rx(alpha) Tx(a), Tz(d)`` (modified). Twists within a
    few ulps of a multiple of pi/2 are snapped to it (a float32 table's pi/2 is pi/2)."""
    snap = 32 * torch.finfo(dh.dtype).eps
    before, after = [], []
    for a, alpha, d, _ in dh.tolist():
        alpha = _snap_angle(alpha, snap)
        twist, lift = elementary_transform("x", alpha, (a, 0.0, 0.0)), elementary_transform("z", 0.0, (0.0, 0.0, d))
        before.append(twist if modified else torch.eye(4, dtype=torch.float64))
        after.append(lift if modified else lift @ twist)
    return torch.stack(before), torch.stack(after)


def _link_coefficients(before: Tensor, after: Tensor, prismatic: Sequence[bool]) -> Tensor:
    """``(n, 3, 16)``: each link ``before_i M(theta_i) after_i`` as ``f0 C0 + f1 C1 + C2``, with
    ``(f0, f1) = (cos theta, sin theta)`` (revolute) or ``(theta, anything)`` (prismatic, ``C1 = 0``)."""
    eye = torch.eye(4, dtype=torch.float64)
    rz_cos, rz_one = torch.diag(eye.new_tensor([1.0, 1.0, 0.0, 0.0])), torch.diag(eye.new_tensor([0.0, 0.0, 1.0, 1.0]))
    rz_sin, tz_unit, zero = torch.zeros(3, 4, 4, dtype=torch.float64)
    rz_sin[0, 1], rz_sin[1, 0], tz_unit[2, 3] = -1.0, 1.0, 1.0
    coeffs = []
    for b, a, slides in zip(before, after, prismatic):
        terms = (tz_unit, zero, eye) if slides else (rz_cos, rz_sin, rz_one)
        coeffs.append(torch.stack([(b @ m @ a).reshape(16) for m in terms]))
    return torch.stack(coeffs)


def _columns(m: Tensor) -> tuple[tuple[float, float, float], ...]:
    """A ``(4, 4)`` transform's rotation columns then translation, as 3-tuples of Python floats."""
    return tuple(map(tuple, m[:3].T.tolist()))


@dataclass(frozen=True, eq=False)
class Geometry:
    """A chain's geometry in one dtype and device (build with :meth:`build`).

    The chain is ``base . prod_i [before_i M_i(q_i + offset_i) after_i] . tool``, ``M_i`` a rotation
    about z (revolute) or a translation along z (prismatic); link frame i is the product up to
    ``after_i``. ``joints``: per joint ``(prismatic, before, after)`` as :func:`_columns` (None for
    the identity). Tensors: ``limits (2, n)``; ``draw_limits`` the same with infinite sides at +-pi;
    ``link_*``/``end_*`` the small-batch kernel's coefficients (``end_*`` with base and tool folded
    in); ``trig_phase (n, 1, 2) = (offset + pi/2, offset)``. ``float_arrays``: float64 arrays
    ``transforms (n, 2, 4, 4)``, ``params (n, 4)`` (offset, prismatic, before and after not the
    identity), base and tool, as :mod:`iiwa_torch.compiled.numba_kernels` takes them.
    """

    joints: tuple[tuple[bool, tuple | None, tuple | None], ...]
    has_base: bool
    has_tool: bool
    has_offsets: bool
    has_prismatic: bool
    tool_columns: tuple[tuple[float, float, float], ...]
    base: Tensor
    before: Tensor
    limits: Tensor
    draw_limits: Tensor
    link_trig: Tensor
    link_const: Tensor
    end_trig: Tensor
    end_const: Tensor
    trig_phase: Tensor
    offsets: Tensor
    offset_trig: Tensor
    prismatic: Tensor
    float_arrays: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]

    @property
    def n_joints(self) -> int:
        return len(self.joints)

    @classmethod
    def build(cls, before: Tensor, after: Tensor, prismatic: Sequence[bool], offsets: Tensor, base: Tensor,
              tool: Tensor, limits: Tensor, dtype: torch.dtype) -> Geometry:
        """From ``before, after (n, 4, 4)``, joint kinds, ``offsets (n,)``, ``base, tool (4, 4)`` and
        ``limits (2, n)`` on one device; tensors in ``dtype``. Entries within a few ulps of 0, +-1 or a
        multiple of pi/2 are snapped to it, so a float32 table's pi/2 twists give exact zeros."""
        device = limits.device
        snap = 32 * torch.finfo(before.dtype).eps
        before, after, base, tool = (_snap_matrix(t.detach().cpu().to(torch.float64), snap)
                                     for t in (before, after, base, tool))
        offsets = torch.tensor([_snap_angle(o, snap) for o in offsets.tolist()], dtype=torch.float64)
        prismatic = tuple(bool(p) for p in prismatic)
        eye = torch.eye(4, dtype=torch.float64)
        n = before.shape[0]
        links = _link_coefficients(before, after, prismatic).view(n, 3, 4, 4)
        end = links.clone()
        end[0] = base @ end[0]
        end[-1] = end[-1] @ tool
        links, end = links.reshape(n, 3, 16), end.reshape(n, 3, 16)
        phase = offsets[:, None] + torch.tensor([math.pi / 2, 0.0], dtype=torch.float64)
        lim = limits.detach().cpu().to(torch.float64)
        draw = torch.stack([lim[0].clamp(min=-math.pi), lim[1].clamp(max=math.pi)])
        draw = torch.where(torch.isinf(lim), draw, lim)

        def put(t: Tensor) -> Tensor:
            return t.contiguous().to(device=device, dtype=dtype)

        tensors = {
            "base": put(base),
            "before": put(before),
            "limits": put(lim),
            "draw_limits": put(draw),
            "link_trig": put(links[:, :2]),
            "link_const": put(links[:, 2:]),
            "end_trig": put(end[:, :2]),
            "end_const": put(end[:, 2:]),
            "trig_phase": put(phase[:, None]),
            "offsets": put(offsets[:, None]),
            "offset_trig": put(torch.stack([offsets.cos(), offsets.sin()])[..., None]),
            "prismatic": torch.tensor(prismatic, device=device)[:, None],
        }
        offset_list = tuple(offsets.tolist())
        kept = [(not torch.equal(b, eye), not torch.equal(a, eye)) for b, a in zip(before, after)]  # not the identity
        joints = tuple((p, _columns(b) if keep_b else None, _columns(a) if keep_a else None)
                       for p, b, a, (keep_b, keep_a) in zip(prismatic, before, after, kept))
        params = np.array([(o, p, kb, ka) for o, p, (kb, ka) in zip(offset_list, prismatic, kept)], dtype=np.float64)
        arrays = (torch.stack([before, after], 1).numpy().copy(), params.reshape(n, 4), base.numpy().copy(),
                  tool.numpy().copy())
        return cls(joints=joints, has_base=not torch.equal(base, eye), has_tool=not torch.equal(tool, eye),
                   has_offsets=any(offset_list), has_prismatic=any(prismatic), tool_columns=_columns(tool),
                   float_arrays=arrays, **tensors)


# ---------------------------------------------------------------------- elementwise helpers
def _rotate_z(x: Tensor, y: Tensor, c: Tensor, s: Tensor) -> tuple[Tensor, Tensor]:
    """Rotate the frame axes x, y about its own z by the angle with cosine c and sine s."""
    return torch.addcmul(c * x, s, y), torch.addcmul(c * y, s, x, value=-1)


def _rotate_point_z(x, y, c, s) -> tuple:
    """``(c x - s y, s x + c y)``: x, y rotated about z; tensors or Python floats (kept floats while they can)."""
    if not isinstance(x, Tensor) and not isinstance(y, Tensor) and x == y == 0.0:
        return x, y
    if not isinstance(c, Tensor):  # one configuration, in Python floats
        return c * x - s * y, s * x + c * y
    return _multiply_add(c * x, s, y, -1.0), _multiply_add(s * x, c, y, 1.0)


def _multiply_add(u: Tensor, v: Tensor, w, sign: float) -> Tensor:
    """``u + sign * v * w`` in one op, ``w`` a tensor or a float."""
    return torch.addcmul(u, v, w, value=sign) if isinstance(w, Tensor) else torch.add(u, v, alpha=sign * w)


def _combine(vectors: Sequence[Tensor], coefficients: Sequence[float], start: Tensor | None = None) -> Tensor:
    """``start + sum_k c_k v_k`` for ``(3, b)`` vectors and float coefficients, skipping zero terms."""
    out = start
    for v, c in zip(vectors, coefficients):
        if c != 0.0:
            if out is not None:
                out = torch.add(out, v, alpha=c)
            else:
                out = v if c == 1.0 else -v if c == -1.0 else v * c
    return out


def _transform(frame: Frame, columns) -> Frame:
    """A frame ``(x, y, z, p)``, each ``(3, b)``, times a constant transform given by its :func:`_columns`."""
    axes = frame[:3]
    return (*(_combine(axes, column) for column in columns[:3]), _combine(axes, columns[3], start=frame[3]))


def _map_point(columns, v) -> tuple:
    """The point ``v`` (3 tensors or floats) mapped by a transform given by its :func:`_columns`."""
    out = []
    for j in range(3):
        acc = columns[3][j]
        for k in range(3):
            c = columns[k][j]
            if c == 0.0:
                continue
            if isinstance(acc, Tensor) and isinstance(v[k], Tensor):
                acc = torch.add(acc, v[k], alpha=c)
            elif isinstance(acc, float) and acc == 0.0:
                acc = v[k] if c == 1.0 else v[k] * c
            else:
                acc = acc + (v[k] if c == 1.0 else v[k] * c)
        out.append(acc)
    return tuple(out)


def _cross(u, v) -> tuple[Tensor, Tensor, Tensor]:
    """Cross product of vectors given by components ``u[0..2]``, ``v[0..2]``: several times faster
    than ``torch.linalg.cross`` along a middle dimension."""
    return (
        torch.addcmul(u[1] * v[2], u[2], v[1], value=-1),
        torch.addcmul(u[2] * v[0], u[0], v[2], value=-1),
        torch.addcmul(u[0] * v[1], u[1], v[0], value=-1),
    )


# ---------------------------------------------------------------------- batch last (every elementwise op contiguous)


def _joint_trig(g: Geometry, q: Tensor, trig: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """``q (n, b)`` -> ``theta = q + offset``, its cosine and sine, each ``(n, b)``; ``trig``: the
    caller's ``(cos q, sin q)``, reused."""
    theta = (q + g.offsets if g.has_offsets else q).contiguous()  # rows of a batch-last view of q are strided
    if trig is None:
        return theta, torch.cos(theta), torch.sin(theta)
    c, s = trig
    if not g.has_offsets:
        return theta, c, s
    co, so = g.offset_trig  # cos(q + o) = c co - s so, sin(q + o) = s co + c so
    return theta, torch.addcmul(c * co, s, so, value=-1), torch.addcmul(s * co, c, so)


def frames_batch_last(g: Geometry, q: Tensor, keep: bool = True) -> tuple[list[Frame], list[tuple[Tensor, Tensor]]]:
    """The elementwise kernel: ``q (n, b)`` (not checked) -> ``(frames, axes)``: ``(x, y, z, p)``
    axis columns and origin, each ``(3, b)``, of the base and every link (``keep``) or the last
    link alone; ``axes``: ``(z_i, p_i)``, joint i's axis and a point on it (``keep``). No tool."""
    if q.shape[1] <= SMALL_BATCH and compilable(q):
        return _frames_batch_last_compiled(g, q, keep)
    theta, c, s = _joint_trig(g, q)
    frame = tuple(g.base[:3, :, None].expand(3, 4, q.shape[1]).unbind(1))  # (x, y, z, p), each (3, b)
    frames, axes = [frame], []
    for i, (prismatic, before, after) in enumerate(g.joints):
        if before is not None:
            frame = _transform(frame, before)
        x, y, z, p = frame
        if keep:
            axes.append((z, p))
        if prismatic:
            p = torch.addcmul(p, z, theta[i])
        else:
            x, y = _rotate_z(x, y, c[i], s[i])
        frame = (x, y, z, p)
        if after is not None:
            frame = _transform(frame, after)
        if keep:
            frames.append(frame)
    return (frames if keep else [frame]), axes


def tool_frame_batch_last(g: Geometry, frame: Frame) -> Frame:
    """The last link frame ``(x, y, z, p)``, each ``(3, b)``, -> the end-effector (tool) frame."""
    return _transform(frame, g.tool_columns) if g.has_tool else frame


def position_batch_last(g: Geometry, q: Tensor, trig: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """End-effector positions: ``q (n, b)`` (not checked) -> ``(3, b)``; ``trig``: ``(cos q, sin q)``
    if the caller has them."""
    if q.shape[1] <= SMALL_BATCH:
        return end_pose(g, q.T)[:, :3, 3].T
    return position_horner(g, q, trig)


def _carry_tool_point(g: Geometry, theta, c, s) -> tuple:
    """Horner's scheme: the tool point carried back through links ``n, ..., 1`` -> its three coordinates
    before the base transform (a third of :func:`frames_batch_last`'s work)."""
    v = g.tool_columns[3]
    for i, (prismatic, before, after) in reversed(list(enumerate(g.joints))):
        if after is not None:
            v = _map_point(after, v)
        if prismatic:
            v = (v[0], v[1], v[2] + theta[i])
        else:
            v = (*_rotate_point_z(v[0], v[1], c[i], s[i]), v[2])
        if before is not None:
            v = _map_point(before, v)
    return v


def position_horner(g: Geometry, q: Tensor, trig: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """``q (n, b)`` -> ``(3, b)`` end-effector positions by Horner's scheme, in blocks of ``POSITION_BLOCK``."""
    theta, c, s = _joint_trig(g, q, trig)
    blocks = []
    for tb, cb, sb in zip(*(x.split(POSITION_BLOCK, 1) for x in (theta, c, s))):
        blocks.append(torch.stack([v if isinstance(v, Tensor) else cb[0].new_full(cb[0].shape, v)
                                   for v in _carry_tool_point(g, tb, cb, sb)]))
    point = blocks[0] if len(blocks) == 1 else torch.cat(blocks, 1)
    if not g.has_base:
        return point
    return torch.addmm(g.base[:3, 3, None], g.base[:3, :3], point)


def untracked_cpu(q: Tensor) -> bool:
    """Whether ``q`` is on the CPU with nothing to differentiate, outside ``torch.compile``'s tracing: what
    compiled or numpy code may take."""
    return q.is_cpu and not (q.requires_grad and torch.is_grad_enabled()) and not is_dynamo_compiling()


def compilable(q: Tensor) -> bool:
    """Whether ``q`` may take the compiled kernels: they are enabled and :func:`untracked_cpu`."""
    return compiled.ENABLED and untracked_cpu(q)


def float64_rows(q: Tensor, n: int) -> np.ndarray:
    """CPU ``q (..., n)`` -> its ``(b, n)`` float64 C-ordered rows, as the compiled kernels take them."""
    x = (q.detach() if q.requires_grad else q).numpy().reshape(-1, n)
    if x.dtype != np.float64 or not x.flags.c_contiguous:
        x = np.ascontiguousarray(x, dtype=np.float64)
    return x


#: the numpy dtype of each float dtype the compiled paths return
NUMPY_DTYPES = {torch.float32: np.dtype(np.float32), torch.float64: np.dtype(np.float64)}


def like(out, q: Tensor) -> Tensor:
    """A float64 array (or scalar) as a tensor in ``q``'s dtype, outside autograd."""
    return torch.from_numpy(np.asarray(out, dtype=NUMPY_DTYPES.get(q.dtype, np.float64)))


def by_kernel(kernel, g: Geometry, q: Tensor, shape: tuple[int, ...]) -> Tensor:
    """A compiled ``kernel(*g.float_arrays, q (b, n), out (b, *shape))`` on ``q (..., n)`` -> ``(..., *shape)``,
    written straight into ``q``'s dtype."""
    rows = float64_rows(q, g.n_joints)
    out = np.empty((rows.shape[0], *shape), NUMPY_DTYPES[q.dtype])
    kernel(*g.float_arrays, rows, out)
    return torch.from_numpy(out).reshape(*q.shape[:-1], *shape)


def _frames_batch_last_compiled(g: Geometry, q: Tensor, keep: bool) -> tuple[list[Frame], list[tuple[Tensor, Tensor]]]:
    """:func:`frames_batch_last` of ``q (n, b)`` (:func:`compilable`) by the compiled recursion."""
    frames, z, p, _ = compiled.kernels().frames_axes(*g.float_arrays, float64_rows(q.T, g.n_joints))
    if not keep:
        frames = frames[:, -1:]
    columns = like(np.ascontiguousarray(frames.transpose(1, 2, 3, 0)), q)  # (F, 4, 3, b)
    out = [tuple(f.unbind(0)) for f in columns.unbind(0)]
    if not keep:
        return out, []
    axes = like(np.ascontiguousarray(np.stack([z, p], 2).transpose(1, 2, 3, 0)), q)  # (n, 2, 3, b)
    return out, [tuple(a.unbind(0)) for a in axes.unbind(0)]


def frame_lists(g: Geometry, q: Tensor) -> tuple[list, list]:
    """One configuration ``q`` (:func:`untracked_cpu`, not checked) -> its base and link frames, ``n + 1``
    lists ``[x, y, z, p]`` of three floats (axis columns and origin), and the end-effector frame
    in the same form; float64."""
    if compiled.ENABLED:
        frames, _, _, pose = compiled.kernels().frames_axes(*g.float_arrays, float64_rows(q, g.n_joints))
        return frames[0].tolist(), pose[0, :3].T.tolist()
    one = q.reshape(1, -1)
    return ([f[:3].T.tolist() for f in all_poses(g, one)[0].double()],
            end_pose(g, one)[0, :3].double().T.tolist())


# ---------------------------------------------------------------------- batch first, small batches
def _link_features(g: Geometry, q: Tensor) -> Tensor:
    """``q (b, n)`` -> ``(n, b, 2)``: each link's ``(f0, f1)`` of :func:`_link_coefficients`."""
    trig = torch.sin(q.T.unsqueeze(-1) + g.trig_phase)  # (n, b, 2): cos, sin
    return torch.where(g.prismatic[..., None], (q.T + g.offsets).unsqueeze(-1), trig) if g.has_prismatic else trig


def _link_matrices(g: Geometry, q: Tensor, end: bool) -> tuple[Tensor, ...]:
    """``(b, n)`` -> the n link transforms, each ``(b, 4, 4)``, or ``(4, 4)`` if b is 1 (``mm`` costs less
    than ``bmm`` of one); with ``end``, base and tool folded in. One batched product builds them all."""
    n, b = g.n_joints, q.shape[0]
    coeffs, const = (g.end_trig, g.end_const) if end else (g.link_trig, g.link_const)
    links = torch.baddbmm(const, _link_features(g, q), coeffs)  # (n, b, 16)
    return links.view(n, 4, 4).unbind(0) if b == 1 else links.view(n, b, 4, 4).unbind(0)


def end_pose_matmul(g: Geometry, q: Tensor) -> Tensor:
    """``q (b, n) -> (b, 4, 4)`` end poses as a chain of 4x4 products."""
    product = torch.mm if q.shape[0] == 1 else torch.bmm
    return reduce(product, _link_matrices(g, q, end=True)).view(q.shape[0], 4, 4)


def _frames_matmul(g: Geometry, q: Tensor) -> Tensor:
    """Small batches: ``(b, n) -> (n + 1, b, 4, 4)``: the base and every link frame."""
    b = q.shape[0]
    product, base = (torch.mm, g.base) if b == 1 else (torch.bmm, g.base.expand(b, 4, 4))
    links = _link_matrices(g, q, end=False)
    if g.has_base:
        frames = list(accumulate(links, product, initial=base))
    else:
        frames = [base, *accumulate(links, product)]
    return torch.stack(frames).view(g.n_joints + 1, b, 4, 4)


# ---------------------------------------------------------------------- batch first, any size
def _axes(g: Geometry, q: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``(b, n)`` -> joint axes ``z (n, 3, b)``, a point on each ``(n, 3, b)`` and the end position ``(3, b)``."""
    if q.shape[0] <= SMALL_BATCH:
        frames = _frames_matmul(g, q)
        axes = frames[:-1]
        if any(before is not None for _, before, _ in g.joints):
            axes = axes @ g.before[:, None]
        axes = axes[:, :, :3].permute(0, 2, 3, 1)  # (n, 3, 4, b)
        last = frames[-1, :, :3].permute(1, 2, 0).unbind(1)
        return axes[:, :, 2], axes[:, :, 3], tool_frame_batch_last(g, last)[3]
    frames, axes = frames_batch_last(g, q.T)
    z, origin = (torch.stack(column) for column in zip(*axes))
    return z, origin, tool_frame_batch_last(g, frames[-1])[3]


def _poses(frames: Tensor) -> Tensor:
    """``(F, 3, 4, b)`` -> ``(b, F, 4, 4)`` homogeneous matrices."""
    top = frames.permute(3, 0, 1, 2)
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=top.dtype, device=top.device)
    return torch.cat([top, bottom.expand(*top.shape[:2], 1, 4)], -2)


def blockwise(q: Tensor, n: int, shape: tuple[int, ...], fn, *others: Tensor) -> Tensor:
    """``fn: (b, n), *others -> (b, *shape)`` over blocks of ``BLOCK`` rows of ``q (..., n)`` (and of
    ``others``, sharing its batch shape) -> ``(..., *shape)``; blocks keep the work in the CPU cache."""
    flat = q.reshape(-1, n)
    rest = [o.reshape(flat.shape[0], *o.shape[q.ndim - 1 :]) for o in others]
    if flat.shape[0] <= BLOCK:
        out = fn(flat, *rest)
    else:
        out = q.new_empty(flat.shape[0], *shape)
        for start in range(0, flat.shape[0], BLOCK):
            block = slice(start, start + BLOCK)
            out[block] = fn(flat[block], *(o[block] for o in rest))
    return out.reshape(*q.shape[:-1], *shape)


def end_pose(g: Geometry, q: Tensor) -> Tensor:
    """``q (b, n) -> (b, 4, 4)`` end poses."""
    if q.shape[0] <= SMALL_BATCH:
        return by_kernel(compiled.kernels().end_poses, g, q, (4, 4)) if compilable(q) else end_pose_matmul(g, q)
    frames, _ = frames_batch_last(g, q.T, keep=False)
    return _poses(torch.stack(tool_frame_batch_last(g, frames[0]), 1)[None])[:, 0]


def all_poses(g: Geometry, q: Tensor) -> Tensor:
    """``q (b, n) -> (b, n + 1, 4, 4)``: the base and every link frame (no tool)."""
    if q.shape[0] <= SMALL_BATCH and compilable(q):
        frames = compiled.kernels().frames_axes(*g.float_arrays, float64_rows(q, g.n_joints))[0]  # (b, n + 1, 4, 3)
        out = np.zeros((*frames.shape[:2], 4, 4))
        out[..., :3, :], out[..., 3, 3] = frames.transpose(0, 1, 3, 2), 1.0
        return like(out, q)
    if q.shape[0] <= SMALL_BATCH:
        return _frames_matmul(g, q).transpose(0, 1)
    frames, _ = frames_batch_last(g, q.T)
    return _poses(torch.stack([torch.stack(f, 1) for f in frames], 0))


def _prismatic_rows(g: Geometry, revolute: Tensor, sliding: Tensor) -> Tensor:
    """Rows ``(n, ...)`` of a per-joint quantity: ``sliding``'s for prismatic joints, else ``revolute``'s."""
    if not g.has_prismatic:
        return revolute
    return torch.where(g.prismatic.reshape(-1, *([1] * (revolute.ndim - 1))), sliding, revolute)


def pose_vjp(g: Geometry, q: Tensor, pose: Tensor, grad: Tensor) -> Tensor:
    """Backward of :func:`end_pose`: ``q (b, n)``, poses ``(b, 4, 4)``, ``dL/dpose`` -> ``dL/dq (b, n)``:
    ``z_i . ((p_e - p_i) x g + w)``, ``g = dL/dp``, ``w = sum_k R[:, k] x G[:, k]`` (``G = dL/dR``);
    ``z_i . g`` for a prismatic joint."""
    z, origin, end = _axes(g, q)  # (n, 3, b), (n, 3, b), (3, b)
    gt = grad[:, :3].permute(1, 2, 0).contiguous()  # (3, 4, b): rows of dL/dT, batch last
    w = [c.sum(0) for c in _cross(pose[:, :3, :3].permute(1, 2, 0), gt[:, :3])]  # sum over columns k
    moment = [m + wc for m, wc in zip(_cross(end, gt[:, 3]), w)]  # (p_e x g + w), each (b,)
    z, lever_x_g = z.unbind(1), _cross(origin.unbind(1), gt[:, 3])  # each (n, b)
    turning = sum(zc * (mc - pc) for zc, mc, pc in zip(z, moment, lever_x_g))
    return _prismatic_rows(g, turning, sum(zc * gc for zc, gc in zip(z, gt[:, 3]))).T


def jacobian(g: Geometry, q: Tensor) -> Tensor:
    """``q (b, n) -> (b, 6, n)``: the geometric Jacobian in the world frame (linear rows first)."""
    if q.shape[0] <= SMALL_BATCH and compilable(q):
        return by_kernel(compiled.kernels().jacobians, g, q, (6, g.n_joints))
    z, origin, end = _axes(g, q)  # (n, 3, b), (n, 3, b), (3, b)
    z = z.unbind(1)
    linear, angular = _cross(z, (end - origin).unbind(1)), z  # 3 x (n, b) each
    if g.has_prismatic:  # a sliding joint: [z; 0]
        linear = [_prismatic_rows(g, row, zc) for row, zc in zip(linear, z)]
        angular = [_prismatic_rows(g, zc, torch.zeros_like(zc)) for zc in z]
    return torch.stack([row.T for row in (*linear, *angular)], 1)  # (b, 6, n): the transpose happens in this one copy


class EndPoseFunction(torch.autograd.Function):
    """``EndPoseFunction.apply(q, g)``: ``q (..., n) -> (..., 4, 4)`` end poses whose backward is
    ``J^T`` times the pose gradient's twist (:func:`pose_vjp`), not a replay of the forward."""

    @staticmethod
    def forward(q: Tensor, g: Geometry) -> Tensor:
        return blockwise(q, g.n_joints, (4, 4), lambda qb: end_pose(g, qb))

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        ctx.geometry = inputs[1]
        ctx.save_for_backward(inputs[0], output)

    @staticmethod
    def backward(ctx, grad: Tensor):
        q, pose = ctx.saved_tensors
        g = ctx.geometry
        return blockwise(q, g.n_joints, (g.n_joints,), lambda *a: pose_vjp(g, *a), pose, grad), None
