"""Segment-segment, segment-point and segment-box distances in torch (differentiable) and numpy.

Each is ``|x - y|`` (or a box's signed distance) at closest points found without autograd: by the
envelope theorem the gradient of a minimum is its gradient at the minimiser, so gradients stay
finite for parallel, zero-length or touching segments.
"""

from __future__ import annotations

from functools import reduce

import numpy as np
import torch
from torch import Tensor

from ..checks import broadcast_shapes, check_tensor
from ..segments import EPS, closest_parameters
from ..so3 import check_rigid

__all__ = ["culled_box_distance", "norm_numpy", "point_gap_numpy", "safe_norm", "segment_box_distance",
           "segment_distance", "segment_gap", "unchecked_segment_box_distance", "unchecked_segment_distance"]


def _root(sq: Tensor) -> Tensor:
    """``sqrt(sq)`` with a zero (not NaN) gradient at ``sq = 0``."""
    positive = sq > 0
    return torch.where(positive, torch.where(positive, sq, 1.0).sqrt(), 0.0)


def safe_norm(v: Tensor) -> Tensor:
    """``|v|`` over the last axis, with a zero gradient at ``v = 0``."""
    return _root((v * v).sum(-1))


def segment_gap(p1: Tensor, d1: Tensor, p2: Tensor, d2: Tensor) -> Tensor:
    """Distance between segments ``p1 + s d1`` and ``p2 + t d2``, component first, ``(3, ...)`` each
    (broadcast) -> ``(...)``. The parameters follow Ericson, Real-Time Collision Detection, 5.1.9,
    in float64 whatever the input: in float32 the cancellation in ``b f - c e`` cost up to 1.5 mm
    on nearly parallel segments."""
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


def point_gap_numpy(p: np.ndarray, d: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Distance from segments ``p + s d`` to points ``c``, numpy float64 ``(..., 3)`` each -> ``(...)``:
    :func:`~iiwa_torch.segments.closest_parameters` with a point for the second segment."""
    r = p - c
    a = (d * d).sum(-1)
    with np.errstate(divide="ignore", invalid="ignore"):  # the quotient np.where discards
        s = np.where(a <= EPS * EPS, 0.0, -(d * r).sum(-1) / a)
    s = np.minimum(np.maximum(s, 0.0), 1.0)  # not np.clip: its Python wrapper costs more on tiny arrays
    return norm_numpy(r + s[..., None] * d)


def segment_distance(p1: Tensor, q1: Tensor, p2: Tensor, q2: Tensor) -> Tensor:
    """Distance (m) between segments ``p1 q1`` and ``p2 q2``, ``(..., 3)`` each (broadcast) -> ``(...)``;
    differentiable."""
    _check_points(p1=p1, q1=q1, p2=p2, q2=q2)
    return unchecked_segment_distance(p1, q1, p2, q2)


def _check_points(**points: Tensor) -> None:
    for name, x in points.items():
        check_tensor(x, name, (3,))
    broadcast_shapes({name: x.shape for name, x in points.items()})


def unchecked_segment_distance(p1: Tensor, q1: Tensor, p2: Tensor, q2: Tensor) -> Tensor:
    """:func:`segment_distance` without its checks."""
    vectors = torch.broadcast_tensors(p1, q1 - p1, p2, q2 - p2)  # before moving the components first
    return segment_gap(*(v.movedim(-1, 0) for v in vectors))


def norm_numpy(v: np.ndarray) -> np.ndarray:
    """``|v|`` over the last axis of a numpy array."""
    return np.sqrt((v * v).sum(-1))


def _box_sdf(local, half, xp=torch):
    """Signed distance of points ``local (..., 3)`` (box frame) to the box ``|x_i| <= half_i``;
    ``xp``: torch (tensors) or numpy (arrays)."""
    excess = xp.abs(local) - half
    norm = safe_norm if xp is torch else norm_numpy
    return norm(xp.clip(excess, 0, None)) + xp.clip(xp.amax(excess, -1), None, 0)


def segment_box_distance(p: Tensor, q: Tensor, pose: Tensor, half: Tensor) -> Tensor:
    """Signed distance (m) ``min_t sdf(p + t (q - p))`` from segment ``p q`` ``(..., 3)`` to the box of
    ``pose (..., 4, 4)`` and ``half`` extents ``(..., 3)`` (broadcast); inside, minus the deepest
    point's depth. Exact (:func:`_box_parameters`)."""
    _check_points(p=p, q=q, half=half)
    check_rigid(pose, "pose")
    return unchecked_segment_box_distance(p, q, pose, half)


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
            t = _box_parameters(*wide, torch).to(half.dtype)
        if torch.is_grad_enabled() and (p.requires_grad or d.requires_grad or half.requires_grad):
            t = torch.stack([t[..., 0], _moving_crossing(p, d, half, t[..., 1])], -1)
        return t
    with np.errstate(divide="ignore", invalid="ignore"):  # the quotients nan_to_num and clip discard
        return _box_parameters(*np.broadcast_arrays(p, d, half), np)


def _moving_crossing(p: Tensor, d: Tensor, h: Tensor, t: Tensor) -> Tensor:
    """The inside candidate ``t (...)`` of :func:`_box_parameters`, same value, with the derivative in
    ``p, d, h`` of the crossing it sits on. The envelope theorem that lets the outside candidate's
    gradient ignore ``t`` does not hold at a kink: there the minimum moves with the two lines."""
    p, d, h = torch.broadcast_tensors(p, d, h)
    u = torch.where(d < 0, -p, p)
    den = d.abs()[..., :, None] + d.abs()[..., None, :]
    cross = ((h - u)[..., :, None] - (h + u)[..., None, :]) / torch.where(den > 0, den, 1.0)  # (..., 3, 3)
    with torch.no_grad():  # the crossing t is (two constant lines have none)
        gap = torch.where(den > 0, (cross - t[..., None, None]).abs(), torch.inf).flatten(-2)
    moving = cross.flatten(-2).gather(-1, gap.argmin(-1, keepdim=True))[..., 0]
    return torch.where((t > 0) & (t < 1), t + (moving - moving.detach()), t)  # at an end t stays put


def unchecked_segment_box_distance(p, q, pose, half, xp=torch):
    """:func:`segment_box_distance` without its checks; ``xp``: torch (tensors) or numpy (float64
    arrays)."""
    rot, centre = pose[..., :3, :3], pose[..., :3, 3]
    lp, lq = (((x - centre)[..., None, :] @ rot)[..., 0, :] for x in (p, q))
    t = _box_minimisers(lp, lq - lp, half, xp)
    points = lp[..., None, :] + t[..., None] * (lq - lp)[..., None, :]  # (..., 2, 3)
    sdf = _box_sdf(points, half[..., None, :], xp)
    # the inside candidate minimises max_i(|x_i| - h_i) <= sdf: where that reaches 0 or below, it is the
    # minimum (picked, not tied with the outside one: only its gradient follows the moving crossing)
    return xp.where(sdf[..., 1] <= 0, sdf[..., 1], sdf[..., 0])


def culled_box_distance(a: Tensor, b: Tensor, pose: Tensor, half: Tensor, radius: Tensor,
                        found: list[Tensor]) -> Tensor:
    """Capsule-box distances ``(..., K, M)`` (segments ``a b (..., K, 1, 3)``, radii ``(K, 1)``), exact
    where they can be the minimum over them and ``found`` (earlier distances), lower bounds elsewhere.

    The distance lies between ``|m - c| - l - |h| - r`` and ``|m - c| - r`` (``m`` the midpoint,
    ``l`` the half length, ``c`` the box centre); the closed form runs only where the lower bound
    is below the smallest upper one, so far boxes cost a few ops."""
    centre = pose[..., :3, 3]
    mid, span = (a + b) / 2, safe_norm(b - a) / 2  # (..., K, 1, 3), (..., K, 1)
    gap = safe_norm(mid - centre)  # (..., K, M)
    shape = gap.shape
    lower = gap - span - safe_norm(half) - radius
    upper = reduce(torch.minimum, found, (gap - radius).flatten(-2).amin(-1))
    near = lower <= upper[..., None, None]
    if bool(near.all()):
        return unchecked_segment_box_distance(a, b, pose, half) - radius
    pick = [x.expand(*shape, *x.shape[x.ndim - k:])[near] for x, k in ((a, 1), (b, 1), (pose, 2), (half, 1))]
    exact = unchecked_segment_box_distance(*pick) - radius.expand(shape)[near]
    return lower.masked_scatter(near, exact)
