"""Capsule models of the presets, obstacle worlds and differentiable clearance (signed distance).

A robot is a set of K capsules (a segment and a radius), each fixed in one of the frames
``Chain.fk_all`` returns. :func:`clearance` is the smallest signed distance in metres
(negative when two shapes overlap) over the self-collision pairs and the capsule-obstacle
pairs; :func:`pairwise_clearance` returns every distance with the names of its pair.
Sizes and sources of the capsules, the formulas and the references they are tested
against: docs/collision.md.

Every distance is written as ``|x - y| - radii`` (or ``n . x - offset - r`` for a half-space)
at closest points ``x, y`` found without autograd; by the envelope theorem the gradient of a
minimum is the gradient at its minimiser, so gradients need no derivative of the search
and stay finite when segments are parallel, of zero length or touching.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from . import compiled
from . import kinematics as kin
from .chain import Chain
from .checks import (
    check_finite,
    check_float_tensor,
    check_instance,
    check_nonnegative,
    check_positive,
    check_tensor,
    is_number,
)
from .dh import DHChain
from .segments import EPS, choose, closest_parameters, quotient, unit_float
from .so3 import check_rigid

__all__ = [
    "CLEARANCE_NUMPY_BATCH",
    "Capsules",
    "Clearances",
    "World",
    "capsule_clearance",
    "capsule_clearance_of_one",
    "check_world",
    "clearance",
    "clearance_of_frames",
    "own_clearance_of_one",
    "obstacle_clearance_of_frames",
    "pairwise_clearance",
    "robot_capsules",
    "self_collision_pairs",
    "solids_numpy",
    "segment_distance",
    "segment_box_distance",
]

_BLOCK = 4096  # configurations per block of the robot's own distances
CLEARANCE_NUMPY_BATCH = 32  # clearance: numpy float64 up to this many CPU configurations without autograd


# ---------------------------------------------------------------------------- distance kernels
def _root(sq: Tensor) -> Tensor:
    """``sqrt(sq)`` with a zero (not NaN) gradient at ``sq = 0``."""
    positive = sq > 0
    return torch.where(positive, torch.where(positive, sq, 1.0).sqrt(), 0.0)


def _safe_norm(v: Tensor) -> Tensor:
    """``|v|`` over the last axis, with a zero gradient at ``v = 0``."""
    return _root((v * v).sum(-1))


def _dot(u, v) -> float:
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def _segment_closest_floats(p1, d1, p2, d2) -> tuple[float, float, tuple[float, float, float]]:
    """The closest points of one pair of segments ``p1 + s d1``, ``p2 + t d2`` (3-tuples of Python
    floats) as in :func:`_segment_gap`: ``s``, ``t`` and the vector ``w`` between them (first minus second)."""
    r = (p1[0] - p2[0], p1[1] - p2[1], p1[2] - p2[2])
    s, t = closest_parameters(_dot(d1, d1), _dot(d2, d2), _dot(d1, d2), _dot(d1, r), _dot(d2, r),
                               choose, unit_float, quotient)
    return s, t, (r[0] + s * d1[0] - t * d2[0], r[1] + s * d1[1] - t * d2[1], r[2] + s * d1[2] - t * d2[2])


def _segment_gap_floats(p1, d1, p2, d2) -> float:
    """:func:`_segment_gap` of one pair of segments, 3-tuples of Python floats."""
    w = _segment_closest_floats(p1, d1, p2, d2)[2]
    return math.sqrt(_dot(w, w))


def _segment_gap(p1: Tensor, d1: Tensor, p2: Tensor, d2: Tensor) -> Tensor:
    """Distance between segments ``p1 + s d1`` and ``p2 + t d2``, ``s, t`` in [0, 1]: vectors
    component first, ``(3, ...)`` each (broadcast) -> ``(...)``. The closest-point parameters
    are found without gradients; parallel segments take ``s0 = 0`` and a segment shorter than
    ~``eps`` metres is a point. The last step (``s`` from the clamped ``t``) makes the result
    exact in every case of the clamped quadratic (Ericson, Real-Time Collision Detection,
    5.1.9). They are computed in float64 whatever the input: in float32 the cancellation in
    ``b f - c e`` cost up to 1.5 mm on nearly parallel segments. A fixed number of tensor ops,
    whatever the number of pairs."""
    with torch.no_grad():
        u1, u2, r = (x.double() for x in (d1, d2, p1 - p2))
        if not u1.shape == u2.shape == r.shape:
            u1, u2, r = torch.broadcast_tensors(u1, u2, r)
        dots = ((x * y).sum(0) for x, y in ((u1, u1), (u2, u2), (u1, u2), (u1, r), (u2, r)))
        s, t = (x.to(p1.dtype) for x in closest_parameters(*dots, torch.where, lambda x: x.clamp_(0, 1)))
    w = p1 + s * d1 - p2 - t * d2
    # not linalg.vector_norm: over the first dim it is much slower (this kernel's time:
    # benchmarks/results/collision.md, torch rows)
    return _root((w * w).sum(0))


def _unit(x: np.ndarray) -> np.ndarray:
    """``x`` clamped to [0, 1] (two ufuncs: ``np.clip``'s Python wrapper costs more on tiny arrays)."""
    return np.minimum(np.maximum(x, 0.0), 1.0)


def _segment_gap_numpy(p1: np.ndarray, d1: np.ndarray, p2: np.ndarray, d2: np.ndarray) -> np.ndarray:
    """:func:`_segment_gap` in numpy float64, vectors component last: ``(..., 3)`` each
    (broadcast) -> ``(...)``."""
    r = p1 - p2
    dots = ((x * y).sum(-1) for x, y in ((d1, d1), (d2, d2), (d1, d2), (d1, r), (d2, r)))
    with np.errstate(divide="ignore", invalid="ignore"):  # the quotients np.where discards
        s, t = closest_parameters(*dots, np.where, _unit)
    w = r + s[..., None] * d1 - t[..., None] * d2
    return np.sqrt((w * w).sum(-1))


def _point_gap_numpy(p: np.ndarray, d: np.ndarray, c: np.ndarray) -> np.ndarray:
    """:func:`_segment_gap_numpy` from segments ``p + s d`` to points ``c`` (a second segment of
    zero length), ``(..., 3)`` each (broadcast) -> ``(...)``: the arithmetic
    :func:`_closest_parameters` does when ``d2 = 0`` (``s = -(d . r) / (d . d)`` clamped, ``t = 0``)
    without the ops that come to nothing, so the same distances bit for bit."""
    r = p - c
    a = (d * d).sum(-1)
    eps = EPS
    with np.errstate(divide="ignore", invalid="ignore"):  # the quotient np.where discards
        s = _unit(np.where(a <= eps * eps, 0.0, -(d * r).sum(-1) / a))
    w = r + s[..., None] * d
    return np.sqrt((w * w).sum(-1))


def segment_distance(p1: Tensor, q1: Tensor, p2: Tensor, q2: Tensor) -> Tensor:
    """Distance between segments ``p1 q1`` and ``p2 q2``: ``(..., 3)`` each (broadcast) -> ``(...)``
    metres. A zero-length segment is a point. Differentiable in all four end points."""
    _check_points(p1=p1, q1=q1, p2=p2, q2=q2)
    return _segment_distance(p1, q1, p2, q2)


def _check_points(**points: Tensor) -> None:
    for name, x in points.items():
        check_tensor(x, name, (3,))
    try:
        torch.broadcast_shapes(*(x.shape for x in points.values()))
    except RuntimeError:
        raise ValueError(
            f"{', '.join(points)} must broadcast together, got {[tuple(x.shape) for x in points.values()]}"
        ) from None


def _segment_distance(p1: Tensor, q1: Tensor, p2: Tensor, q2: Tensor) -> Tensor:
    vectors = torch.broadcast_tensors(p1, q1 - p1, p2, q2 - p2)  # before moving the components first
    return _segment_gap(*(v.movedim(-1, 0) for v in vectors))


def _norm_numpy(v: np.ndarray) -> np.ndarray:
    return np.sqrt((v * v).sum(-1))


def _box_sdf(local, half, xp=torch):
    """Signed distance of points ``local (..., 3)`` (box frame) to the box ``|x_i| <= half_i``;
    ``xp``: torch (tensors) or numpy (arrays)."""
    excess = xp.abs(local) - half
    norm = _safe_norm if xp is torch else _norm_numpy
    return norm(xp.clip(excess, 0, None)) + xp.clip(xp.amax(excess, -1), None, 0)


def segment_box_distance(p: Tensor, q: Tensor, pose: Tensor, half: Tensor) -> Tensor:
    """Signed distance from segment ``p q`` (``(..., 3)`` each) to the oriented box of pose
    ``(..., 4, 4)`` and half extents ``(..., 3)`` (all broadcast): ``min_t sdf(p + t (q - p))``,
    metres, negative inside.

    Exact (closed form, see :func:`_box_parameters`): outside the box this is the segment-box
    distance; when the segment enters the box it is minus the depth of the segment's deepest
    point (a lower bound on the penetration depth).
    """
    _check_points(p=p, q=q, half=half)
    check_rigid(pose, "pose")
    return _segment_box_distance(p, q, pose, half)


def _box_parameters(p, d, h, xp):
    """The two candidate minimisers ``(..., 2)`` in [0, 1] of the box's signed distance along
    ``p + t d`` (box frame, ``(..., 3)`` float64 each, of one shape): one of them is the exact
    minimiser. ``xp`` is torch or numpy (tensors or arrays): one formula for both.

    Outside: ``f(t) = |max(|x(t)| - h, 0)|^2`` is convex and C1, its derivative
    ``psi(t) = sum_i d_i (x_i - clamp(x_i, -h_i, h_i))`` is nondecreasing and linear between
    the breakpoints ``x_i(t) = +-h_i``; the zero of ``psi`` lies between the last of
    ``{0, 1, breakpoints}`` with ``psi <= 0`` and the first with ``psi > 0``, found by one
    Newton step from that bracket's midpoint. Inside: ``g(t) = max_i(|x_i| - h_i)`` is the
    larger of the increasing lines ``s_i x_i - h_i`` (``s_i = sign d_i``) and the decreasing
    ones ``-s_j x_j - h_j``; it is smallest where the two envelopes cross, at
    ``min_i max_j t_ij`` with ``t_ij`` the crossing of line ``i`` with line ``j``."""
    tiny = np.finfo(np.float64).tiny
    # outside: bracket the zero of psi among t = 0, 1 and the six breakpoints
    ends = [xp.zeros_like(p[..., :1]), xp.ones_like(p[..., :1])]
    bounds = xp.clip(xp.nan_to_num(xp.concatenate([*ends, (h - p) / d, (-h - p) / d], axis=-1), nan=0.0), 0, 1)
    x = p[..., None, :] + bounds[..., None] * d[..., None, :]  # (..., 8, 3)
    psi = (d[..., None, :] * (x - xp.maximum(xp.minimum(x, h[..., None, :]), -h[..., None, :]))).sum(-1)
    below = psi <= 0
    lo = xp.amax(xp.where(below, bounds, 0.0), -1)
    hi = xp.amin(xp.where(below, 1.0, bounds), -1)
    mid = (lo + hi) / 2
    xm = p + mid[..., None] * d
    excess = xm - xp.maximum(xp.minimum(xm, h), -h)
    slope = (d * d * (excess != 0)).sum(-1)
    outside = xp.minimum(xp.maximum(mid - (d * excess).sum(-1) / xp.clip(slope, tiny, None), lo), hi)
    # inside: the crossing of the increasing and decreasing envelopes of g's six lines
    u = xp.where(d < 0, -p, p)
    a = xp.abs(d)
    cross = ((h - u)[..., :, None] - (h + u)[..., None, :]) / (a[..., :, None] + a[..., None, :])
    inside = xp.clip(xp.amin(xp.amax(xp.nan_to_num(cross, nan=0.0), -1), -1), 0, 1)
    return xp.stack([outside, inside], -1)


def _box_minimisers(p, d, half, xp=torch):
    """:func:`_box_parameters` of ``p, d, half (..., 3)`` (broadcast), computed in float64
    without gradients, in ``half``'s dtype; ``xp``: torch or numpy (float64 arrays)."""
    if xp is torch:
        with torch.no_grad():
            wide = torch.broadcast_tensors(p.double(), d.double(), half.double())
            return _box_parameters(*wide, torch).to(half.dtype)
    with np.errstate(divide="ignore", invalid="ignore"):  # the quotients nan_to_num and clip discard
        return _box_parameters(*np.broadcast_arrays(p, d, half), np)


def _segment_box_distance(p, q, pose, half, xp=torch):
    rot, centre = pose[..., :3, :3], pose[..., :3, 3]
    lp, lq = (((x - centre)[..., None, :] @ rot)[..., 0, :] for x in (p, q))
    t = _box_minimisers(lp, lq - lp, half, xp)
    points = lp[..., None, :] + t[..., None] * (lq - lp)[..., None, :]  # (..., 2, 3)
    return xp.amin(_box_sdf(points, half[..., None, :], xp), -1)


def _culled_box_distance(a: Tensor, b: Tensor, pose: Tensor, half: Tensor, radius: Tensor,
                         found: list[Tensor]) -> Tensor:
    """Capsule-box distances ``(..., K, M)`` (segments ``a b`` ``(..., K, 1, 3)``, boxes
    ``(..., 1, M, ...)``, radii ``(K, 1)``) that are exact where they can be the minimum over
    them and ``found`` (earlier distances, each broadcasting to the batch ``(...)``), and
    lower bounds elsewhere: a query's minimum (value and gradient) is unchanged.

    With ``m`` the segment's midpoint, ``l`` its half length and ``c`` the box centre, the
    distance lies between ``|m - c| - l - |h| - r`` (every point of the box is within ``|h|``
    of ``c``) and ``|m - c| - r`` (``c`` is inside the box); the exact closed form runs only on
    pairs whose lower bound is below the smallest upper bound. Boxes far from the arm, such as
    the parked stand-ins of an env's absent obstacles, cost a few ops instead of the search."""
    centre = pose[..., :3, 3]
    mid, span = (a + b) / 2, _safe_norm(b - a) / 2  # (..., K, 1, 3), (..., K, 1)
    gap = _safe_norm(mid - centre)  # (..., K, M)
    shape = gap.shape
    lower = gap - span - _safe_norm(half) - radius
    upper = (gap - radius).flatten(-2).amin(-1)
    for f in found:
        upper = torch.minimum(upper, f)
    near = lower <= upper[..., None, None]
    if bool(near.all()):
        return _segment_box_distance(a, b, pose, half) - radius
    pick = [x.expand(*shape, *x.shape[x.ndim - k:])[near] for x, k in ((a, 1), (b, 1), (pose, 2), (half, 1))]
    exact = _segment_box_distance(*pick) - radius.expand(shape)[near]
    return lower.masked_scatter(near, exact)


# ---------------------------------------------------------------------------- robot model
@dataclass(frozen=True)
class Capsules:
    """K capsules fixed in a chain's frames, and which pairs are checked.

    Attributes:
        names: K names.
        frames: K indices into ``chain.fk_all(q)``'s frames (0 = base, i = link frame i).
        points: ``(K, 2, 3)`` float64 end points of each segment in its frame, metres.
        radii: ``(K,)`` float64 radii, metres, > 0.
        pairs: self-collision pairs ``(i, j)``, ``i < j``, that are checked.
        world: ``(K,)`` bool, capsules checked against walls, spheres, boxes and capsules.
        floor: ``(K,)`` bool, capsules checked against the floor.
        floor_height: the floor a query with ``world=None`` uses (``None``: no floor).

    Use :meth:`build` to make one; it validates everything.
    """

    names: tuple[str, ...]
    frames: tuple[int, ...]
    points: Tensor
    radii: Tensor
    pairs: tuple[tuple[int, int], ...]
    world: Tensor
    floor: Tensor
    floor_height: float | None = 0.0

    def __post_init__(self) -> None:
        k = len(self.names)
        if k == 0 or len(set(self.names)) != k:
            raise ValueError(f"names must be K >= 1 distinct names, got {self.names}")
        if len(self.frames) != k or not all(isinstance(f, int) and f >= 0 for f in self.frames):
            raise ValueError(f"frames must be {k} non-negative frame indices, got {self.frames}")
        for name, value, shape in (("points", self.points, (k, 2, 3)), ("radii", self.radii, (k,))):
            if not isinstance(value, Tensor) or value.dtype != torch.float64 or tuple(value.shape) != shape:
                raise ValueError(f"{name} must be a float64 tensor of shape {shape}, got {_describe(value)}")
            check_finite(value, name)
        if not (self.radii > 0).all():
            raise ValueError(f"radii must be positive, got {self.radii.tolist()}")
        for name, mask in (("world", self.world), ("floor", self.floor)):
            if not isinstance(mask, Tensor) or mask.dtype != torch.bool or tuple(mask.shape) != (k,):
                raise ValueError(f"{name} must be a bool tensor of shape ({k},), got {_describe(mask)}")
        for pair in self.pairs:
            if len(pair) != 2 or not (0 <= pair[0] < pair[1] < k):
                raise ValueError(f"pairs must be (i, j) with 0 <= i < j < {k}, got {pair}")
        if len(set(self.pairs)) != len(self.pairs):
            raise ValueError(f"pairs contains duplicates: {self.pairs}")
        if self.floor_height is not None and not (
            is_number(self.floor_height) and math.isfinite(self.floor_height)
        ):
            raise ValueError(f"floor_height must be a finite height in metres or None, got {self.floor_height!r}")
        if self.floor_height is not None:
            object.__setattr__(self, "floor_height", float(self.floor_height))
        object.__setattr__(self, "_cache", {})

    def _index_tables(self, dtype: torch.dtype, device: torch.device) -> dict[str, Tensor]:
        """Index and geometry tensors of the queries in ``dtype`` on ``device``, built once
        (the model is frozen): ``frames (K,)``, ``local (K, 4, 2)`` homogeneous end points,
        ``first``/``second (P,)`` and ``pair_radius (P, 1)`` of the self pairs,
        ``floor (F,)`` and ``floor_radius (F, 1)``, ``world (W,)`` and ``world_radius (W, 1)``."""
        key = (dtype, device)
        if key not in self._cache:
            with torch.inference_mode(False):  # the model is shared (robot_capsules): no inference tensors in it
                self._cache[key] = self._build_tables(dtype, device)
        return self._cache[key]

    def _build_tables(self, dtype: torch.dtype, device: torch.device) -> dict[str, Tensor]:
        """:meth:`_index_tables`, built."""
        options = {"device": device}
        index = {"dtype": torch.long, **options}
        radii = self.radii.to(dtype=dtype, **options)
        first, second = (
            (torch.tensor(c, **index) for c in zip(*self.pairs)) if self.pairs else (torch.zeros(0, **index),) * 2
        )
        floor, world = (m.to(device).nonzero().flatten() for m in (self.floor, self.world))
        ones = torch.ones(len(self.names), 2, 1, dtype=dtype, **options)
        return {
            "frames": torch.tensor(self.frames, **index),
            "local": torch.cat([self.points.to(dtype=dtype, **options), ones], -1).mT.contiguous(),
            "first": first,
            "second": second,
            "pair_radius": (radii[first] + radii[second])[:, None],
            "floor": floor,
            "floor_radius": radii[floor, None],
            "world": world,
            "world_radius": radii[world, None],
        }

    def _float_table(self) -> dict[str, list]:
        """The model as Python floats, built once: ``points`` K ``(frame, start, end)``, the end
        points 3-tuples in that frame, ``pair_radius`` P radius sums, ``floor`` ``(k, radius)``
        of the capsules checked against the floor."""
        if "floats" not in self._cache:
            radii = self.radii.tolist()
            self._cache["floats"] = {
                "points": [(f, *map(tuple, ends)) for f, ends in zip(self.frames, self.points.tolist())],
                "pair_radius": [radii[i] + radii[j] for i, j in self.pairs],
                "floor": [(k, radii[k]) for k in _where(self.floor)],
            }
        return self._cache["floats"]

    def _numpy_tables(self) -> dict[str, np.ndarray]:
        """:meth:`_index_tables` in float64 on the CPU as numpy arrays, built once."""
        if "numpy" not in self._cache:
            tables = self._index_tables(torch.float64, torch.device("cpu"))
            self._cache["numpy"] = {k: v.numpy() for k, v in tables.items()}
        return self._cache["numpy"]

    @classmethod
    def build(
        cls,
        chain: Chain,
        names,
        frames,
        points,
        radii,
        *,
        pairs=None,
        world=None,
        floor=None,
        floor_height: float | None = 0.0,
    ) -> Capsules:
        """Capsules for ``chain``, validated against it.

        ``points (K, 2, 3)`` and ``radii (K,)`` in metres; ``frames`` index ``chain.fk_all``'s
        ``n + 1`` frames. ``pairs=None`` takes :func:`self_collision_pairs`; ``world``/``floor``
        default to every capsule.
        """
        names = tuple(str(n) for n in names)
        k = len(names)
        frames = tuple(int(f) for f in frames)
        if any(f > chain.n_joints for f in frames):
            raise ValueError(f"frames must index the {chain.n_joints + 1} frames of fk_all, got {frames}")
        model = cls(
            names=names,
            frames=frames,
            points=torch.as_tensor(points, dtype=torch.float64),
            radii=torch.as_tensor(radii, dtype=torch.float64),
            pairs=(),
            world=torch.ones(k, dtype=torch.bool) if world is None else torch.as_tensor(world),
            floor=torch.ones(k, dtype=torch.bool) if floor is None else torch.as_tensor(floor),
            floor_height=floor_height,
        )
        chosen = self_collision_pairs(chain, model) if pairs is None else tuple(tuple(int(i) for i in p) for p in pairs)
        return dataclasses.replace(model, pairs=chosen)


def _describe(x) -> str:
    if isinstance(x, Tensor):
        return f"{x.dtype} tensor of shape {tuple(x.shape)}"
    return type(x).__name__


def self_collision_pairs(
    chain: Chain, capsules: Capsules, samples: int = 4096, seed: int = 0
) -> tuple[tuple[int, int], ...]:
    """Pairs worth checking: every ``(i, j)`` except neighbours in the list (``j = i + 1``, the
    links on either side of a joint) and pairs that overlap in every one of ``samples``
    uniform in-limit configurations (drawn with ``seed``): those touch by construction."""
    check_instance(chain, Chain, "chain")
    check_instance(capsules, Capsules, "capsules")
    check_positive(samples, "samples", integer=True)
    check_nonnegative(seed, "seed", integer=True)
    q = chain.random_q(samples, generator=torch.Generator().manual_seed(seed))
    start, direction = _capsule_segments(chain, capsules, q)  # components (K, samples)
    k = len(capsules.names)
    candidates = [(i, j) for i in range(k) for j in range(i + 2, k)]
    if not candidates:
        return ()
    first, second = (torch.tensor(c) for c in zip(*candidates))
    radii = capsules.radii.to(start)
    gap = _pair_gaps(start, direction, (radii[first] + radii[second])[:, None], first, second)
    keep = (gap > 0).any(1).tolist()
    return tuple(pair for pair, ok in zip(candidates, keep) if ok)


def _capsule_segments(chain: Chain, capsules: Capsules, q: Tensor) -> tuple[Tensor, Tensor]:
    """``q (..., n)`` -> each capsule's start point and start-to-end vector in the world frame,
    component first, ``(3, K, B)`` each over the ``B`` flattened configurations (this layout
    keeps every elementwise op of the distance kernels contiguous). A fixed number of tensor
    ops: the capsule frames are gathered and one batched product places both end points. Up
    to ``SMALL_BATCH`` configurations the frames come from ``fk_all``'s 4x4 kernel, above from
    the batch-last elementwise kernel, which computes only what the capsules use and is far faster
    than ``fk_all`` at large batches (benchmarks/results/fk.md)."""
    tables = capsules._index_tables(q.dtype, q.device)
    flat = q.reshape(-1, chain.n_joints)
    geometry = chain.geometry(q.dtype)
    if flat.shape[0] <= kin.SMALL_BATCH:
        frames = kin.all_poses(geometry, flat)[:, tables["frames"], :3]  # (B, K, 3, 4)
        ends = (frames @ tables["local"]).permute(3, 2, 1, 0)  # (2, 3, K, B)
    else:  # large batches: per capsule, multiply-adds of the nonzero local coordinates only (fewer bytes moved)
        frames, _ = kin.frames_batch_last(geometry, flat.T.contiguous())  # (x, y, z, p), (3, B) each
        ends = torch.stack(
            [
                torch.stack(
                    [
                        sum((c * axis for c, axis in zip(local, frames[frame][:3]) if c), frames[frame][3])
                        for frame, local in zip(capsules.frames, capsules.points[:, e].tolist())
                    ],
                    1,
                )
                for e in (0, 1)
            ]
        )  # (2, 3, K, B)
    return ends[0], ends[1] - ends[0]


def _pair_gaps(start: Tensor, direction: Tensor, radii: Tensor, first: Tensor, second: Tensor) -> Tensor:
    """Signed distances ``(P, B)`` of the capsule pairs ``(first, second)`` (indices ``(P,)``,
    radius sums ``radii (P, 1)``) from :func:`_capsule_segments`'s output."""
    return _segment_gap(start[:, first], direction[:, first], start[:, second], direction[:, second]) - radii


def _z_capsule(frame: int, z0: float, z1: float):
    return frame, ((0.0, 0.0, z0), (0.0, 0.0, z1))


def robot_capsules(chain: DHChain) -> Capsules:
    """The conservative capsule model of a preset (``chain.name`` in iiwa14, iiwa7, puma560,
    lrmate200ic, planar3r), sized from the chain's own DH lengths; radii and their sources
    are in docs/collision.md. The base capsule is not checked against the floor it stands on;
    the planar arm lies in the z = 0 plane, so its default world has no floor. Self pairs:
    every pair but neighbours in the list (no other pair overlaps in every posture). Built
    once per chain name and DH table, then shared (the model is frozen). Another arm (a URDF
    chain) has no preset model: fit one to its URDF (:func:`iiwa_torch.capsule_fit.urdf_capsules`)
    and pass it as ``capsules=`` to the functions that take one."""
    check_instance(chain, Chain, "chain")
    if not isinstance(chain, DHChain):
        raise ValueError(f"chain {chain.name!r} is not a DH preset, so it has no preset capsule model; fit one to its "
                         "URDF with capsule_fit.urdf_capsules(chain, source) and pass capsules=")
    dh = chain.dh.tolist()
    key = (chain.name, tuple(map(tuple, dh)))  # all the model depends on; it is frozen, so shared
    if key not in _MODELS:
        with torch.inference_mode(False):  # shared: no inference tensors in it, whoever asks first
            _MODELS[key] = _preset_capsules(chain, dh)
    return _MODELS[key]


_MODELS: dict[tuple, Capsules] = {}  # robot_capsules' models, by chain name and DH table


def _preset_capsules(chain: DHChain, dh: list[list[float]]) -> Capsules:
    """:func:`robot_capsules`, built (validated by :meth:`Capsules.build`)."""
    floor_height: float | None = 0.0
    if chain.name in ("iiwa14", "iiwa7"):
        l_bs, l_se, l_ew, l_wf = dh[0][2], dh[2][2], dh[4][2], dh[6][2]
        spec = [
            ("base", *_z_capsule(0, 0.0, l_bs), 0.11),
            ("upper_arm", *_z_capsule(2, 0.0, l_se), 0.09),
            ("forearm", *_z_capsule(4, 0.0, l_ew), 0.08),
            ("wrist", *_z_capsule(6, 0.0, l_wf), 0.075),
        ]
    elif chain.name == "puma560":
        d1, a2, d3, d4 = dh[0][2], dh[1][0], dh[2][2], dh[3][2]
        spec = [
            ("base", *_z_capsule(0, 0.0, d1), 0.13),
            ("upper_arm", 2, ((-a2, 0.0, d3), (0.0, 0.0, d3)), 0.10),
            ("forearm", *_z_capsule(3, -0.05, d4), 0.07),
            ("wrist", *_z_capsule(6, 0.0, 0.06), 0.06),
        ]
    elif chain.name == "lrmate200ic":
        d1, a2, a3, d4, d6 = dh[0][2], dh[1][0], dh[2][0], dh[3][2], dh[5][2]
        spec = [
            ("base", *_z_capsule(0, 0.0, d1), 0.10),
            ("upper_arm", 2, ((-a2, 0.0, 0.0), (0.0, 0.0, 0.0)), 0.07),
            ("forearm", 3, ((-a3, 0.0, 0.0), (0.0, 0.0, d4)), 0.06),
            ("wrist", *_z_capsule(6, -d6, 0.0), 0.05),
        ]
    elif chain.name == "planar3r":
        spec = [(f"link{i + 1}", i + 1, ((-row[0], 0.0, 0.0), (0.0, 0.0, 0.0)), 0.05) for i, row in enumerate(dh)]
        floor_height = None
    else:
        raise ValueError(
            f"no capsule model for a chain named {chain.name!r}; build one with Capsules.build(chain, ...)"
        )
    names, frames, points, radii = zip(*spec)
    floor = [name != "base" for name in names]
    # what self_collision_pairs finds for each preset (tested), fixed so a query samples nothing
    pairs = ((0, 2),) if chain.name == "planar3r" else ((0, 2), (0, 3), (1, 3))
    return Capsules.build(chain, names, frames, points, radii, pairs=pairs, floor=floor, floor_height=floor_height)


# ---------------------------------------------------------------------------- obstacles
# each kind's per-obstacle dims after M: (first tensor, second tensor)
#: Largest coordinate, size or offset (m) a World takes: far enough for any arm, near enough that
#: squared distances stay finite in float32 (beyond ~1e19 m they overflow to inf).
MAX_EXTENT = 1e6
_OBSTACLE_DIMS = {"walls": ((3,), ()), "spheres": ((3,), ()), "boxes": ((4, 4), (3,)), "capsules": ((2, 3), ())}


@dataclass(frozen=True)
class World:
    """Obstacles, each kind with an optional leading batch shape (one set per environment).

    Args:
        floor: height of the floor half-space ``z <= floor`` the robot must stay above
            (metres), or ``None`` for no floor.
        walls: ``(normals (..., W, 3) unit, offsets (..., W))``: free space is ``n . x >= offset``.
        spheres: ``(centres (..., S, 3), radii (..., S))``.
        boxes: ``(poses (..., B, 4, 4) rigid, half_extents (..., B, 3))``.
        capsules: ``(points (..., C, 2, 3), radii (..., C))``.

    All tensors share one float dtype and device; the batch shapes must broadcast with the
    batch shape of the joint angles queried. Every value is within :data:`MAX_EXTENT` (1e6 m).
    """

    floor: float | None = 0.0
    walls: tuple[Tensor, Tensor] | None = None
    spheres: tuple[Tensor, Tensor] | None = None
    boxes: tuple[Tensor, Tensor] | None = None
    capsules: tuple[Tensor, Tensor] | None = None

    def __post_init__(self) -> None:
        if self.floor is not None and not (is_number(self.floor) and abs(self.floor) <= MAX_EXTENT):
            raise ValueError(f"floor must be a height in metres within {MAX_EXTENT:g} or None, got {self.floor!r}")
        if self.floor is not None:
            object.__setattr__(self, "floor", float(self.floor))  # a numpy scalar, in Python's float
        first = None
        for kind, (shape_a, shape_b) in _OBSTACLE_DIMS.items():
            pair = getattr(self, kind)
            if pair is None:
                continue
            if not isinstance(pair, tuple) or len(pair) != 2:
                raise TypeError(f"{kind} must be a tuple of two tensors, got {type(pair).__name__}")
            a, b = pair
            label_a, label_b = f"{kind}[0]", f"{kind}[1]"
            check_float_tensor(a, label_a, f"(..., M, {', '.join(map(str, shape_a))})")
            check_float_tensor(b, label_b, f"(..., M{''.join(', ' + str(s) for s in shape_b)})")
            lead = a.ndim - len(shape_a)
            if lead < 1 or tuple(a.shape[lead:]) != shape_a:
                raise ValueError(f"{label_a} must have shape (..., M, {shape_a}), got {tuple(a.shape)}")
            want_b = tuple(a.shape[:lead]) + shape_b
            if tuple(b.shape) != want_b:
                raise ValueError(f"{label_b} must have shape {want_b} to match {label_a}, got {tuple(b.shape)}")
            for t, label in ((a, label_a), (b, label_b)):
                if first is None:
                    first = t
                if t.dtype != first.dtype or t.device != first.device:
                    raise TypeError(
                        f"{label} is {t.dtype} on {t.device} but other obstacles are {first.dtype} on {first.device}"
                    )
                check_finite(t, label)
                if t.numel() and float(t.detach().abs().amax()) > MAX_EXTENT:
                    raise ValueError(f"{label} must be within {MAX_EXTENT:g} m, got {float(t.abs().amax()):g}")
        self._check_values()

    def _check_values(self) -> None:
        if self.walls is not None:
            norm = self.walls[0].norm(dim=-1)
            if not torch.allclose(norm, torch.ones_like(norm), atol=1e-5):
                raise ValueError(f"walls[0] normals must be unit vectors, got norms {norm.flatten()[:8].tolist()}")
        for kind in ("spheres", "capsules"):
            pair = getattr(self, kind)
            if pair is not None and not (pair[1] > 0).all():
                raise ValueError(f"{kind}[1] radii must be positive, got min {pair[1].min().item()}")
        if self.boxes is not None:
            pose, half = self.boxes
            if not (half > 0).all():
                raise ValueError(f"boxes[1] half extents must be positive, got min {half.min().item()}")
            check_rigid(pose, "boxes[0]", exact_bottom_row=True)

    def tensors(self) -> list[Tensor]:
        """Every obstacle tensor (for dtype/device checks and moving)."""
        return [
            t for kind in ("walls", "spheres", "boxes", "capsules") if getattr(self, kind) for t in getattr(self, kind)
        ]

    @property
    def batch_shape(self) -> torch.Size:
        """The broadcast leading batch shape of the obstacles (``()`` for one shared set)."""
        shapes = [a.shape[: a.ndim - len(_OBSTACLE_DIMS[kind][0]) - 1] for kind, (a, _) in self._kinds()]
        return torch.broadcast_shapes(*shapes) if shapes else torch.Size()

    def check_batch(self, batch: torch.Size, what: str = "targets") -> None:
        """Raise ``ValueError`` unless :attr:`batch_shape` broadcasts to ``batch`` (the batch
        shape of the ``what`` it is used with) without enlarging it."""
        try:
            fits = torch.broadcast_shapes(self.batch_shape, batch) == batch
        except RuntimeError:
            fits = False
        if not fits:
            raise ValueError(
                f"the world's batch shape {tuple(self.batch_shape)} must broadcast to the {what}' {tuple(batch)}"
            )

    def map_batch(self, fn) -> World:
        """A world with ``fn(t, k)`` applied to every obstacle tensor ``t`` whose last ``k``
        dims are the obstacle dims (``M`` and each obstacle's own): the dims before them are
        the batch, which ``fn`` may reshape, expand or index (e.g. to one world per pose)."""
        changed = {
            kind: tuple(fn(t, 1 + len(dims)) for t, dims in zip(pair, _OBSTACLE_DIMS[kind]))
            for kind, pair in self._kinds()
        }
        return dataclasses.replace(self, **changed)

    def _kinds(self) -> list[tuple[str, tuple[Tensor, Tensor]]]:
        return [(kind, getattr(self, kind)) for kind in _OBSTACLE_DIMS if getattr(self, kind) is not None]


def check_world(world: World | None, margin: float, capsules: Capsules | None = None) -> None:
    """Check the ``world=``, ``margin=``, ``capsules=`` arguments of a solver: ``world`` a
    :class:`World` or ``None``, ``margin`` a finite number >= 0 (metres), and neither
    ``margin`` nor ``capsules`` given without a world."""
    if world is not None and not isinstance(world, World):
        raise TypeError(f"world must be an iiwa_torch.collision.World or None, got {type(world).__name__}")
    if capsules is not None and not isinstance(capsules, Capsules):
        raise TypeError(f"capsules must be an iiwa_torch.collision.Capsules or None, got {type(capsules).__name__}")
    check_nonnegative(margin, "margin")
    if world is None and (margin != 0 or capsules is not None):
        raise ValueError("margin and capsules apply to a world: pass world=World(...) (World() is the floor at z = 0)")


# ---------------------------------------------------------------------------- queries
@dataclass(frozen=True)
class Clearances:
    """Every distance of one query.

    Attributes:
        distance: ``(..., P)`` signed distances, metres (negative: overlap).
        pairs: P ``(a, b)`` names: two capsule names for a self pair, else a capsule name
            and ``floor``, ``wall<i>``, ``sphere<i>``, ``box<i>`` or ``capsule<i>``.
    """

    distance: Tensor
    pairs: tuple[tuple[str, str], ...]


def _check_query(chain: Chain, q: Tensor, world: World, capsules: Capsules) -> None:
    chain.check_q(q)
    if max(capsules.frames) > chain.n_joints:
        raise ValueError(f"capsules use frames {capsules.frames} but the chain has {chain.n_joints + 1} frames")
    for t in world.tensors():
        if t.dtype != q.dtype or t.device != q.device:
            raise TypeError(
                f"world obstacles are {t.dtype} on {t.device} but q is {q.dtype} on {q.device}; "
                "build the world in q's dtype and device"
            )
    try:
        torch.broadcast_shapes(world.batch_shape, q.shape[:-1])
    except RuntimeError:
        raise ValueError(f"the world's batch shape {tuple(world.batch_shape)} does not broadcast with q's "
                         f"{tuple(q.shape[:-1])}: give one world, or one per configuration") from None


def _resolve(chain: Chain, q: Tensor, world: World | None, capsules: Capsules | None) -> tuple[World, Capsules]:
    """The query's world and capsules (defaults filled in), all arguments checked."""
    check_instance(chain, Chain, "chain")
    capsules = robot_capsules(chain) if capsules is None else capsules
    world = World(floor=capsules.floor_height) if world is None else world
    check_instance(capsules, Capsules, "capsules")
    check_instance(world, World, "world")
    _check_query(chain, q, world, capsules)
    return world, capsules


def _distances(
    chain: Chain, q: Tensor, world: World, capsules: Capsules, cull: bool = False
) -> tuple[Tensor | None, list[Tensor], list[tuple[str, str]]]:
    """The robot's own distances (self pairs, then floor) ``(P, B)`` over the flattened batch,
    the other obstacles' ``(..., M)`` blocks, and every pair's names in that order, for
    arguments :func:`_resolve` returned. ``cull``: only the minimum matters (see
    :func:`_culled_box_distance`)."""
    tables = capsules._index_tables(q.dtype, q.device)
    names = capsules.names
    has_floor, has_obstacles = world.floor is not None, bool(world.tensors())
    floor_idx, idx = tables["floor"], tables["world"]
    labels = [(names[x], names[y]) for x, y in capsules.pairs]
    if has_floor:
        labels += [(names[x], "floor") for x in _where(capsules.floor)]
    flat = q.reshape(-1, chain.n_joints)
    own, segments = [], []
    with _one_thread(flat.shape[0] > _BLOCK and flat.device.type == "cpu"):
        for block in flat.split(_BLOCK):  # blocks small enough for the kernels' arrays to stay in the CPU cache
            start, direction = _capsule_segments(chain, capsules, block)
            parts = (
                [_pair_gaps(start, direction, tables["pair_radius"], tables["first"], tables["second"])]
                if capsules.pairs
                else []
            )
            if has_floor and floor_idx.numel():
                low = torch.minimum(start[2], start[2] + direction[2])[floor_idx]
                parts.append(low - (tables["floor_radius"] + world.floor))
            if parts:
                own.append(torch.cat(parts) if len(parts) > 1 else parts[0])
            if has_obstacles:
                segments.append((start, direction))
    others = []
    if has_obstacles and idx.numel():
        lead = q.shape[:-1]
        start, direction = (torch.cat(part, -1)[:, idx].permute(1, 2, 0) for part in zip(*segments))  # (K, B, 3)
        n_world = idx.shape[0]
        a, b = (x.transpose(0, 1).reshape(*lead, n_world, 1, 3) for x in (start, start + direction))
        r = tables["world_radius"]
        idx = _where(capsules.world)
        if world.walls is not None:
            normal, offset = world.walls
            n = normal[..., None, :, :]
            height = torch.minimum((a * n).sum(-1), (b * n).sum(-1))  # (..., K, W)
            others.append((height - offset[..., None, :] - r).flatten(-2))
            labels += [(names[x], f"wall{m}") for x in idx for m in range(normal.shape[-2])]
        if world.spheres is not None:
            centre, rad = world.spheres
            c = centre[..., None, :, :]
            others.append((_segment_distance(a, b, c, c) - r - rad[..., None, :]).flatten(-2))
            labels += [(names[x], f"sphere{m}") for x in idx for m in range(centre.shape[-2])]
        if world.boxes is not None:
            pose, half = world.boxes
            pose, half = pose[..., None, :, :, :], half[..., None, :, :]
            if cull and pose.shape[-3]:
                found = [] if own is None else [torch.cat(own, 1).amin(0).reshape(lead)]
                found += [o.amin(-1) for o in others if o.shape[-1]]
                dist = _culled_box_distance(a, b, pose, half, r, found)
            else:
                dist = _segment_box_distance(a, b, pose, half) - r
            others.append(dist.flatten(-2))
            labels += [(names[x], f"box{m}") for x in idx for m in range(pose.shape[-3])]
        if world.capsules is not None:
            pts, rad = world.capsules
            p = pts[..., None, :, :, :]
            dist = _segment_distance(a, b, p[..., 0, :], p[..., 1, :])
            others.append((dist - r - rad[..., None, :]).flatten(-2))
            labels += [(names[x], f"capsule{m}") for x in idx for m in range(pts.shape[-3])]
    if not own and not others:
        raise ValueError("nothing to check: the capsules have no self pairs and the world no obstacle they face")
    return (torch.cat(own, 1) if own else None), others, labels


@contextlib.contextmanager
def _one_thread(when: bool):
    """Run the block loop on one intra-op thread (``when``), then restore the count. Its ops are
    a block's size, too small for a second thread to pay: with OpenMP spinning
    (``OMP_WAIT_POLICY=ACTIVE``) a second thread gains nothing, and with ``PASSIVE`` every op's
    parallel region wakes a sleeping thread, which costs more than the op (the vector env's rows
    per wait policy: benchmarks/results/env.md; the measurement: benchmarks/results/log.md)."""
    threads = torch.get_num_threads()
    if not when or threads == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def _where(mask: Tensor) -> list[int]:
    return [i for i, m in enumerate(mask.tolist()) if m]


def pairwise_clearance(
    chain: Chain, q: Tensor, world: World | None = None, capsules: Capsules | None = None
) -> Clearances:
    """Every checked distance for ``q (..., n)``: the self pairs, then capsule-floor,
    -wall, -sphere, -box, -capsule (see :class:`Clearances`). ``world=None`` is the
    model's default floor; ``capsules=None`` is :func:`robot_capsules` of the chain."""
    own, others, labels = _distances(chain, q, *_resolve(chain, q, world, capsules))
    parts = ([] if own is None else [own.T.reshape(*q.shape[:-1], own.shape[0])]) + others
    shape = torch.broadcast_shapes(*(p.shape[:-1] for p in parts))
    distance = torch.cat([p.expand(*shape, p.shape[-1]) for p in parts], -1)
    return Clearances(distance=distance, pairs=tuple(labels))


def clearance(chain: Chain, q: Tensor, world: World | None = None, capsules: Capsules | None = None) -> Tensor:
    """Smallest signed distance, metres: ``q (..., n) -> (...)``, over the checked self pairs and
    capsule-obstacle pairs (arguments as :func:`pairwise_clearance`). Differentiable in ``q``
    and the obstacles' tensors. On the CPU with nothing to differentiate, the same formulas
    run in numpy float64 up to ``CLEARANCE_NUMPY_BATCH`` configurations (no walls or obstacle
    capsules), and compiled above when numba is enabled and the floor is the only obstacle
    (:func:`_plain_path`)."""
    world, capsules = _resolve(chain, q, world, capsules)
    plain = _plain_path(chain, q, world, capsules)
    if plain is not None:
        return plain(chain, q, world, capsules)
    own, others, _ = _distances(chain, q, world, capsules, cull=True)
    # a kind given with no obstacle (M = 0) adds no distance
    mins = ([] if own is None else [own.amin(0).reshape(q.shape[:-1])]) + [o.amin(-1) for o in others if o.shape[-1]]
    if not mins:
        raise ValueError("nothing to check: the capsules have no self pairs and the world no obstacle they face")
    shape = torch.broadcast_shapes(*(m.shape for m in mins))
    return torch.stack([m.expand(shape) for m in mins]).amin(0)


def capsule_clearance(
    chain: Chain, q: Tensor, world: World | None = None, capsules: Capsules | None = None
) -> tuple[Tensor, Tensor]:
    """Each capsule's smallest signed distance and its gradient: ``q (..., n)`` ->
    ``distance (..., K)`` (m) and ``gradient (..., K, n)`` (m/rad), for the K capsules in
    ``capsules.names`` order (arguments as :func:`pairwise_clearance`). A capsule's distance is
    the minimum over every checked pair it is in (a self pair counts for both of its capsules);
    one in no pair gets ``inf`` and a zero gradient. For controllers that keep each link clear
    (e.g. a velocity damper: ``gradient[k] . dq >= -xi (distance[k] - d_safe)``). Neither output
    is differentiable further. The gradient is autograd's, but for one CPU configuration with no
    obstacle but the floor the compiled closed form
    (:func:`iiwa_torch.compiled.numba_kernels.capsule_clearance`) when enabled."""
    world, capsules = _resolve(chain, q, world, capsules)
    if compiled.ENABLED and q.numel() == chain.n_joints and q.is_cpu and not world.tensors():
        distance, gradient = _capsule_clearance_compiled(chain, q, world.floor, capsules)
        dtype = np.float32 if q.dtype == torch.float32 else np.float64
        return (torch.from_numpy(distance.astype(dtype, copy=False).reshape(*q.shape[:-1], -1)),
                torch.from_numpy(gradient.astype(dtype, copy=False).reshape(*q.shape[:-1], -1, chain.n_joints)))
    with torch.enable_grad():
        x = q.detach().requires_grad_(True)
        d = pairwise_clearance(chain, x, world, capsules)
        inf = d.distance.new_tensor(math.inf)
        columns = []
        for name in capsules.names:
            member = torch.tensor([name in pair for pair in d.pairs], device=q.device)
            columns.append(torch.where(member, d.distance, inf).amin(-1) if d.pairs else inf.expand(q.shape[:-1]))
        distance = torch.stack(columns, -1)  # (..., K)
        k = len(capsules.names)
        one_hot = torch.eye(k, dtype=q.dtype, device=q.device).reshape(k, *(1,) * (q.ndim - 1), k)
        (gradient,) = torch.autograd.grad(distance, x, one_hot.expand(k, *distance.shape), is_grads_batched=True,
                                          allow_unused=True, materialize_grads=True)
    return distance.detach(), gradient.movedim(0, -2)


def capsule_clearance_of_one(
    chain: Chain, q: Tensor, floor: float | None, capsules: Capsules
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`capsule_clearance` of one CPU configuration ``q`` (n numbers, nothing to differentiate)
    against itself and the floor at ``floor`` (m; ``None``: none), unchecked: for callers that built
    every argument themselves (the envs' single env) -> distances ``(K,)`` (m) and gradients ``(K, n)``
    (m/rad), float64 numpy arrays."""
    if compiled.ENABLED:
        return _capsule_clearance_compiled(chain, q, floor, capsules)
    with torch.inference_mode(False):  # a caller's inference tensors cannot be differentiated: a copy can
        distance, gradient = capsule_clearance(chain, q.reshape(-1).double().clone(), World(floor=floor), capsules)
    return distance.numpy(), gradient.numpy()


def _capsule_clearance_compiled(
    chain: Chain, q: Tensor, floor: float | None, capsules: Capsules
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`capsule_clearance` of one configuration against the floor and itself by its compiled
    kernel: distances ``(K,)`` (m) and gradients ``(K, n)`` (m/rad), float64 arrays. A distance is
    ``|w| - r`` at the closest points ``x, y`` (``w = x - y``) or ``x_z - floor - r`` at the lower
    end point; by the envelope theorem its gradient is ``u . (dx/dq - dy/dq)`` (``u = w / |w|``, or
    ``e_z``), each point fixed in its capsule's frame: the value autograd gives."""
    tables, n = capsules._numpy_tables(), chain.n_joints
    k = len(capsules.names)
    distance, gradient = np.empty(k), np.empty((k, n))
    x = np.ascontiguousarray(q.detach().reshape(n).numpy(), dtype=np.float64)
    floors = tables["floor"] if floor is not None else tables["floor"][:0]
    compiled.kernels().capsule_clearance(*chain.geometry().float_arrays, x, tables["frames"], tables["local"],
                                         tables["first"], tables["second"], tables["pair_radius"], floors,
                                         tables["floor_radius"], 0.0 if floor is None else float(floor), distance,
                                         gradient)
    return distance, gradient


def _plain_path(chain: Chain, q: Tensor, world: World, capsules: Capsules):
    """The function :func:`clearance` hands checked arguments with nothing to differentiate on the
    CPU to, or ``None`` for its torch path: :func:`_clearance_numpy` up to ``CLEARANCE_NUMPY_BATCH``
    configurations (no walls or obstacle capsules), :func:`_clearance_compiled` above (numba
    enabled, no obstacle but the floor)."""
    if world.walls or world.capsules:
        return None
    if not all(kin.untracked_cpu(t) for t in (q, *world.tensors(), chain.limits)):
        return None
    tables = capsules._numpy_tables()
    floor = world.floor is not None and tables["floor"].size > 0
    if q.numel() > CLEARANCE_NUMPY_BATCH * chain.n_joints:
        return _clearance_compiled if compiled.ENABLED and not world.tensors() and (capsules.pairs or floor) else None
    solids = _present(world.spheres, -1) or _present(world.boxes, -2)
    solids = solids and tables["world"].size > 0
    return _clearance_numpy if capsules.pairs or floor or solids else None


def _clearance_compiled(chain: Chain, q: Tensor, world: World, capsules: Capsules) -> Tensor:
    """:func:`clearance` of a CPU batch against itself and the floor by the compiled kernel
    (:func:`iiwa_torch.compiled.numba_kernels.own_clearance`, float64 inside); not differentiable."""
    out = _own_clearance_kernel(chain, q.detach().reshape(-1, chain.n_joints).numpy(), world.floor, capsules)
    return torch.from_numpy(out.reshape(q.shape[:-1])).to(q.dtype)


def _own_clearance_kernel(chain: Chain, x: np.ndarray, floor: float | None, capsules: Capsules) -> np.ndarray:
    """:func:`iiwa_torch.compiled.numba_kernels.own_clearance` of ``x (b, n)`` against itself and the
    floor at ``floor`` (m; ``None``: none) -> ``(b,)`` float64 metres (``inf`` where nothing is checked)."""
    tables = capsules._numpy_tables()
    transforms, params, base, _ = chain.geometry().float_arrays
    out = np.empty(x.shape[0])
    compiled.kernels().own_clearance(x, transforms, params, base, tables["frames"], tables["local"], tables["first"],
                                     tables["second"], tables["pair_radius"],
                                     tables["floor"] if floor is not None else tables["floor"][:0],
                                     tables["floor_radius"], 0.0 if floor is None else float(floor), out)
    return out


def own_clearance_of_one(chain: Chain, q: Tensor, floor: float | None, capsules: Capsules) -> float:
    """:func:`clearance` of one CPU configuration ``q`` (n numbers, nothing to differentiate) against
    itself and the floor at ``floor`` (m; ``None``: none), unchecked, for callers that built every
    argument themselves (the envs' single env) -> metres (``inf`` if nothing is checked). Compiled
    when enabled, else in Python floats from its frames (:func:`iiwa_torch.kinematics.frame_lists`)."""
    if compiled.ENABLED:
        return float(_own_clearance_kernel(chain, q.reshape(1, -1).numpy(), floor, capsules)[0])
    own, _, _ = _own_clearance_floats(kin.frame_lists(chain.geometry(), q)[0], floor, capsules)
    return math.inf if own is None else own


def _capsule_ends_floats(frames: list[tuple], capsules: Capsules) -> tuple[list[tuple], list[tuple]]:
    """One configuration's capsules from its frames (:func:`iiwa_torch.kinematics.frame_lists`):
    their start points and start-to-end vectors, K 3-tuples of Python floats each."""
    start, direction = [], []
    for f, (u0, v0, w0), (u1, v1, w1) in capsules._float_table()["points"]:  # each end point: p + u x + v y + w z
        (x0, x1, x2), (y0, y1, y2), (z0, z1, z2), (p0, p1, p2) = frames[f]
        a = (p0 + u0 * x0 + v0 * y0 + w0 * z0, p1 + u0 * x1 + v0 * y1 + w0 * z1, p2 + u0 * x2 + v0 * y2 + w0 * z2)
        start.append(a)
        direction.append((p0 + u1 * x0 + v1 * y0 + w1 * z0 - a[0], p1 + u1 * x1 + v1 * y1 + w1 * z1 - a[1],
                          p2 + u1 * x2 + v1 * y2 + w1 * z2 - a[2]))
    return start, direction


def _own_clearance_floats(
    frames: list[tuple], floor: float | None, capsules: Capsules
) -> tuple[float | None, list[tuple], list[tuple]]:
    """One configuration's self and floor clearance in Python floats (``None``: neither is
    checked) from its frames, and :func:`_capsule_ends_floats`, as :func:`_clearance_numpy`
    computes them for a batch, the segments by :func:`_closest_parameters`."""
    table = capsules._float_table()
    start, direction = _capsule_ends_floats(frames, capsules)
    gaps = [_segment_gap_floats(start[i], direction[i], start[j], direction[j]) - r
            for (i, j), r in zip(capsules.pairs, table["pair_radius"])]
    if floor is not None:
        gaps += [min(start[k][2], start[k][2] + direction[k][2]) - (r + floor) for k, r in table["floor"]]
    return (min(gaps) if gaps else None), start, direction


def _present(kind: tuple[Tensor, Tensor] | None, axis: int) -> bool:
    """Whether a world's spheres or boxes (``axis``: where their count M is) hold any obstacle."""
    return kind is not None and kind[1].shape[axis] > 0


NumpyPair = tuple[np.ndarray, np.ndarray]


def solids_numpy(world: World) -> tuple[NumpyPair | None, NumpyPair | None]:
    """A CPU world's spheres and boxes as float64 numpy arrays, as :func:`clearance_of_frames`
    takes them: ``(centres (..., S, 3), radii (..., S))`` and ``(poses (..., B, 4, 4), half
    extents (..., B, 3))``, ``None`` for a kind that is absent or holds no obstacle (walls and
    obstacle capsules are left out: no numpy path has them)."""

    def arrays(pair, axis):
        return tuple(t.detach().numpy().astype(np.float64) for t in pair) if _present(pair, axis) else None

    return arrays(world.spheres, -1), arrays(world.boxes, -2)


def _least(values: list):
    """The elementwise minimum of arrays (or floats) that broadcast; ``None`` for none."""
    out = values[0] if values else None
    for v in values[1:]:
        out = np.minimum(out, v)
    return out


def _solid_gaps(a: np.ndarray, b: np.ndarray, radius: np.ndarray, spheres: NumpyPair | None,
                boxes: NumpyPair | None, found) -> list[np.ndarray]:
    """The smallest signed distances ``(...)`` of capsule segments ``a b`` (``(..., W, 1, 3)``, radii
    ``radius (W, 1)``) to the spheres and to the boxes (:func:`solids_numpy`'s arrays, their batch
    broadcasting with ``...``), one array per kind given. ``found``: the batch's smallest distance
    so far (an array or a float; ``None``: none). As in :func:`_culled_box_distance`, the exact
    capsule-box closed form runs only on pairs whose lower bound ``|s - c| - |h| - r`` (``s`` the
    segment's point nearest the box centre ``c``) is at most the smallest upper bound
    ``|s - c| - r`` and ``found``: the others cannot be the minimum, and keep the lower bound."""
    mins, d = [], b - a
    if spheres is not None:
        centre, rad = spheres
        c = centre[..., None, :, :]
        gap = _point_gap_numpy(a, d, c) - radius - rad[..., None, :]
        mins.append(gap.min((-2, -1)))
    if boxes is not None:
        pose, half = boxes[0][..., None, :, :, :], boxes[1][..., None, :, :]
        c = pose[..., :3, 3]
        upper = _point_gap_numpy(a, d, c) - radius  # (..., W, B): c is inside its box
        lower = upper - _norm_numpy(half)  # every point of a box is within |h| of its centre
        limit = _least([upper.min((-2, -1))] + ([] if found is None else [found]) + mins)
        near = lower <= limit[..., None, None]
        if near.all():
            lower = _segment_box_distance(a, b, pose, half, np) - radius
        elif near.any():
            pick = [np.broadcast_to(x, near.shape + x.shape[x.ndim - k:])[near]
                    for x, k in ((a, 1), (b, 1), (pose, 2), (half, 1))]
            lower[near] = _segment_box_distance(*pick, np) - np.broadcast_to(radius, near.shape)[near]
        mins.append(lower.min((-2, -1)))
    return mins


def _obstacle_gaps(capsules: Capsules, start: list[tuple], direction: list[tuple], spheres: NumpyPair | None,
                   boxes: NumpyPair | None, found: float) -> np.ndarray | None:
    """One configuration's capsules (:func:`_own_clearance_floats`' start points and vectors)
    against the spheres and boxes: the smallest distance per world of their batch (boxes exact
    where it can be below ``found``, see :func:`_solid_gaps`), ``None`` if nothing faces them."""
    tables = capsules._numpy_tables()
    idx = tables["world"]
    if (spheres is None and boxes is None) or not idx.size:
        return None
    start, direction = np.array([start, direction])[:, idx, None]  # (W, 1, 3) each
    return _least(_solid_gaps(start, start + direction, tables["world_radius"], spheres, boxes, found))


def clearance_of_frames(capsules: Capsules, frames: list[tuple], floor: float | None,
                        spheres: NumpyPair | None = None, boxes: NumpyPair | None = None,
                        exact_below: float = math.inf) -> float:
    """:func:`clearance` of one configuration from its frames, unchecked: for callers that built
    every argument themselves and query one configuration at a time (the envs' single env).
    ``frames``: the first of :func:`iiwa_torch.kinematics.frame_lists` of the configuration (the
    capsules' chain); ``floor``: its height (m, ``None``: none); ``spheres``, ``boxes``: one set of
    obstacles (:func:`solids_numpy`, every batch dim of size 1) -> metres, a Python float.
    ``exact_below``: a clearance at or above it may come back as any value at or above it (boxes
    farther than it are not searched): with ``exact_below=0`` the sign is still exact, and 0
    comes back only for a clearance of 0. :func:`clearance` runs the same functions on one CPU
    configuration after its checks."""
    own, start, direction = _own_clearance_floats(frames, floor, capsules)
    mins = [] if own is None else [own]
    # a box pair whose lower bound exceeds the smallest of these cannot matter
    solid = _obstacle_gaps(capsules, start, direction, spheres, boxes, min(mins + [exact_below]))
    if solid is not None:
        mins.append(float(solid.min()))
    if not mins:
        raise ValueError("nothing to check: the capsules have no self pairs and the world no obstacle they face")
    return min(mins)


def obstacle_clearance_of_frames(capsules: Capsules, frames: list[tuple], spheres: NumpyPair | None = None,
                                 boxes: NumpyPair | None = None, exact_below: float = math.inf) -> np.ndarray:
    """:func:`clearance_of_frames` against the obstacles alone (no self pairs, no floor), for each
    world of the obstacles' batch: ``(...)`` float64 metres (e.g. one candidate obstacle per
    world, each against the same configuration). Unchecked, as :func:`clearance_of_frames`."""
    start, direction = _capsule_ends_floats(frames, capsules)
    solid = _obstacle_gaps(capsules, start, direction, spheres, boxes, exact_below)
    if solid is None:
        raise ValueError("nothing to check: no obstacle, or no capsule checked against obstacles")
    return solid


def _clearance_numpy(chain: Chain, q: Tensor, world: World, capsules: Capsules) -> Tensor:
    """:func:`clearance` of a small CPU batch in numpy float64: a few dozen numpy ops, each a
    fraction of a torch op's overhead. Self pairs, floor, spheres and boxes; not differentiable."""
    tables = capsules._numpy_tables()
    lead = q.shape[:-1]
    floor = tables["floor"]
    spheres, boxes = solids_numpy(world)
    if q.numel() == chain.n_joints:  # one configuration: its own distances in Python floats
        frames = kin.frame_lists(chain.geometry(), q)[0]
        own, start, direction = _own_clearance_floats(frames, world.floor, capsules)
        mins = [] if own is None else [np.array(own).reshape(lead)]
    else:
        flat = q.detach().reshape(-1, chain.n_joints).numpy().astype(np.float64)
        frames = kin.all_poses(chain.geometry(), torch.from_numpy(flat)).numpy()
        frames = frames.transpose(1, 0, 2, 3)[tables["frames"], :, :3]  # (K, B, 3, 4)
        ends = frames @ tables["local"][:, None]  # (K, B, 3, 2)
        start, direction = ends[..., 0], ends[..., 1] - ends[..., 0]  # (K, B, 3)
        mins = []
        if capsules.pairs:
            first, second = tables["first"], tables["second"]
            gap = _segment_gap_numpy(start[first], direction[first], start[second], direction[second])
            mins.append((gap - tables["pair_radius"]).min(0))
        if world.floor is not None and floor.size:
            low = np.minimum(start[floor, :, 2], start[floor, :, 2] + direction[floor, :, 2])
            mins.append((low - (tables["floor_radius"] + world.floor)).min(0))
        mins = [m.reshape(lead) for m in mins]
    idx = tables["world"]
    if (spheres is not None or boxes is not None) and idx.size:  # a kind with M = 0 adds nothing
        if isinstance(start, list):  # one configuration's, from the float path: (K, 1, 3) arrays
            start, direction = np.array([start, direction])[:, :, None]
        a, b = (x.transpose(1, 0, 2).reshape(*lead, idx.size, 1, 3) for x in (start[idx], start[idx] + direction[idx]))
        mins += _solid_gaps(a, b, tables["world_radius"], spheres, boxes, _least(mins))
    return torch.from_numpy(np.array(_least(mins), dtype=np.float32 if q.dtype == torch.float32 else np.float64))
