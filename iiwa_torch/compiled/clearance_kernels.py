"""Compiled capsule clearance: the self and floor clearance of large batches (:func:`own_clearance`) and
each capsule's clearance with its gradient for one configuration (:func:`capsule_clearance`)."""

from __future__ import annotations

import math

import numpy as np

from .. import segments
from .decorators import inline, jit, jit_fused, jit_nogil
from .kinematics_kernels import apply_transform, frames_of, turn

__all__ = ["LANES", "SIN_COS_RANGE", "block_capsules", "block_minimum", "capsule_clearance", "capsule_ends",
           "half_lengths", "next_frame", "own_clearance", "sin_cos"]

# numba calls libm's sin and cos one element at a time (no SVML here), which stops LLVM from
# vectorising a loop and costs more than the rest of the clearance kernel: sin_cos is a
# branch-free restatement of fdlibm's (FreeBSD msun e_rem_pio2.c, k_sin.c, k_cos.c): the angle
# less the nearest multiple n of pi/2 (pi/2 in three 33-bit parts, so each product with n is
# exact for |n| < 2^20), then the two minimax polynomials on [-pi/4, pi/4] and n's quadrant.
SIN_COS_RANGE = 1e5  # rad: |angle| up to which sin_cos is within an ulp or two of libm; beyond, libm
_INV_PIO2 = 6.36619772367581382433e-01
_PIO2 = (1.57079632673412561417e00, 6.07710050630396597660e-11, 2.02226624871116645580e-21)
_SIN = (-1.66666666666666324348e-01, 8.33333333332248946124e-03, -1.98412698298579493134e-04,
        2.75573137070700676789e-06, -2.50507602534068634195e-08, 1.58969099521155010221e-10)  # fmt: skip
_COS = (4.16666666666666019037e-02, -1.38888888888741095749e-03, 2.48015872894767294178e-05,
        -2.75573143513906633035e-07, 2.08757232129817482790e-09, -1.13596475577881948265e-11)  # fmt: skip


@inline
def sin_cos(x):
    """``(sin x, cos x)`` for ``|x| <= SIN_COS_RANGE``, without a branch or a call (see above)."""
    n = math.floor(x * _INV_PIO2 + 0.5)
    r = ((x - n * _PIO2[0]) - n * _PIO2[1]) - n * _PIO2[2]
    z = r * r
    s1, s2, s3, s4, s5, s6 = _SIN
    c1, c2, c3, c4, c5, c6 = _COS
    s = r + r * z * (s1 + z * (s2 + z * (s3 + z * (s4 + z * (s5 + z * s6)))))
    half = 0.5 * z
    w = 1.0 - half
    c = w + (((1.0 - w) - half) + z * z * (c1 + z * (c2 + z * (c3 + z * (c4 + z * (c5 + z * c6))))))
    odd = n * 0.5 != math.floor(n * 0.5)  # quadrants 1 and 3: sine and cosine swap
    quadrant = n - 4.0 * math.floor(n * 0.25)
    sin, cos = (c, s) if odd else (s, c)
    return (-sin if quadrant >= 2.0 else sin), (-cos if (quadrant == 1.0) | (quadrant == 2.0) else cos)


# the one closest-point formula of the torch, numpy and float paths, with the float path's helpers
_closest = inline(segments.closest_parameters)
_choose, _unit, _quotient = inline(segments.choose), inline(segments.unit_float), inline(segments.quotient)
LANES = 256  # configurations per block: the block's frames and capsules stay in the L1 cache
_DENSE = 2  # a pair needed in more than 1 / _DENSE of a block's lanes is computed in all of them
_SLACK = 1e-9  # m: a pair is skipped if its lower bound beats the best by more (rounding of the bounds)


@inline
def _block_angles(q, params, row, m, angle, cs):
    """Joint angles ``q[row : row + m] + offset`` into ``angle (last, LANES)`` and their cosines and
    sines into ``cs (2, last, LANES)``: by :func:`sin_cos`, or libm's beyond ``SIN_COS_RANGE``."""
    wide = False
    for i in range(angle.shape[0]):
        turns = not params[i, 1]
        for j in range(m):
            angle[i, j] = q[row + j, i] + params[i, 0]
            wide |= turns & (abs(angle[i, j]) > SIN_COS_RANGE)
    for i in range(angle.shape[0]):
        if wide:
            for j in range(m):
                cs[0, i, j], cs[1, i, j] = math.cos(angle[i, j]), math.sin(angle[i, j])
        else:
            for j in range(m):
                cs[1, i, j], cs[0, i, j] = sin_cos(angle[i, j])


@inline
def _transform_lanes(T, m, state):
    """The frames ``state (12, LANES)`` (x, y, z axes and origin, 3 rows each) times ``T (4, 4)``, in place."""
    for j in range(m):
        x0, x1, x2, y0, y1, y2 = state[0, j], state[1, j], state[2, j], state[3, j], state[4, j], state[5, j]
        z0, z1, z2, p0, p1, p2 = state[6, j], state[7, j], state[8, j], state[9, j], state[10, j], state[11, j]
        x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2 = apply_transform(T, x0, x1, x2, y0, y1, y2, z0, z1, z2, p0,
                                                                         p1, p2)
        state[0, j], state[1, j], state[2, j], state[3, j], state[4, j], state[5, j] = x0, x1, x2, y0, y1, y2
        state[6, j], state[7, j], state[8, j], state[9, j], state[10, j], state[11, j] = z0, z1, z2, p0, p1, p2


@inline
def next_frame(transforms, params, i, m, angle, cs, state):
    """The frames ``state (12, LANES)`` of link ``i`` -> link ``i + 1``, as :func:`~.kinematics_kernels.frames_of`;
    each branch once for the block, outside the loops (a branch inside would stop LLVM vectorising them)."""
    if params[i, 2]:
        _transform_lanes(transforms[i, 0], m, state)
    if params[i, 1]:  # prismatic: along z
        for r in range(3):
            for j in range(m):
                state[9 + r, j] += angle[i, j] * state[6 + r, j]
    else:
        for j in range(m):
            c, s = cs[0, i, j], cs[1, i, j]
            x0, x1, x2, y0, y1, y2 = turn(state[0, j], state[1, j], state[2, j], state[3, j], state[4, j],
                                          state[5, j], c, s)  # fmt: skip
            state[0, j], state[1, j], state[2, j], state[3, j], state[4, j], state[5, j] = x0, x1, x2, y0, y1, y2
    if params[i, 3]:
        _transform_lanes(transforms[i, 1], m, state)


@jit_fused
def block_capsules(transforms, params, base, frames, local, m, angle, cs, state, ends):
    """Every capsule of a block into ``ends (K, 9, LANES)`` (start point, start-to-end vector, mid-point) from the
    block's angles (:func:`_block_angles`); the last frames stay in ``state``. Fused into FMAs: ~10% off the envs'
    compiled step, float64 results moving in their last bits, far below what the clearance and float32 resolve."""
    for r in range(12):
        for j in range(m):
            state[r, j] = base[r % 3, r // 3]
    for f in range(angle.shape[0] + 1):
        if f > 0:
            next_frame(transforms, params, f - 1, m, angle, cs, state)
        capsule_ends(frames, local, f, m, state, ends)


@inline
def capsule_ends(frames, local, f, m, state, ends):
    """The capsules of frame ``f`` (0 the base, i link i) into ``ends (K, 9, LANES)`` (start point,
    start-to-end vector, mid-point) from the block's frames ``state (12, LANES)`` (x, y, z axes and
    origin, 3 rows each)."""
    for k in range(frames.shape[0]):
        if frames[k] != f:
            continue
        u0, v0, w0 = local[k, 0, 0], local[k, 1, 0], local[k, 2, 0]
        u1, v1, w1 = local[k, 0, 1], local[k, 1, 1], local[k, 2, 1]
        for r in range(3):  # each end point: p + u x + v y + w z
            for j in range(m):
                x, y, z, p = state[r, j], state[3 + r, j], state[6 + r, j], state[9 + r, j]
                start = p + u0 * x + v0 * y + w0 * z
                ends[k, r, j] = start
                ends[k, 3 + r, j] = p + u1 * x + v1 * y + w1 * z - start
                ends[k, 6 + r, j] = start + 0.5 * ends[k, 3 + r, j]


@inline
def half_lengths(local):
    """Half the length of each capsule ``local (K, 4, 2)`` (its two end points as columns), ``(K,)`` m."""
    half = np.empty(local.shape[0])
    for k in range(local.shape[0]):
        d0, d1, d2 = local[k, 0, 1] - local[k, 0, 0], local[k, 1, 1] - local[k, 1, 0], local[k, 2, 1] - local[k, 2, 0]
        half[k] = 0.5 * math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    return half


@inline
def _closest_gap(e1, e2, j):
    """Lane ``j``'s capsules ``e1, e2 (9, LANES)`` (start ``x``, ``y``, vectors ``a``, ``b``) at their closest points
    ``x + s a``, ``y + t b`` (:func:`iiwa_torch.segments.closest_parameters`, compiled) -> ``s, t`` and the gap's 3."""
    r0, r1, r2 = e1[0, j] - e2[0, j], e1[1, j] - e2[1, j], e1[2, j] - e2[2, j]
    a0, a1, a2, b0, b1, b2 = e1[3, j], e1[4, j], e1[5, j], e2[3, j], e2[4, j], e2[5, j]
    s, t = _closest(a0 * a0 + a1 * a1 + a2 * a2, b0 * b0 + b1 * b1 + b2 * b2, a0 * b0 + a1 * b1 + a2 * b2,
                    a0 * r0 + a1 * r1 + a2 * r2, b0 * r0 + b1 * r1 + b2 * r2, _choose, _unit, _quotient)
    return s, t, r0 + s * a0 - t * b0, r1 + s * a1 - t * b1, r2 + s * a2 - t * b2


@inline
def _pair_clearance(e1, e2, j, radius):
    """The clearance ``|x - y| - radius`` (m) of lane ``j``'s capsules at their closest points."""
    _, _, w0, w1, w2 = _closest_gap(e1, e2, j)
    return math.sqrt(w0 * w0 + w1 * w1 + w2 * w2) - radius


@inline
def block_minimum(ends, m, first, second, pair_radius, half, floor, floor_radius, height, gap, lanes, best):
    """The block's clearance into ``best (LANES,)``: the floor's exact values and, per self pair, the
    mid-points' distance ``gap (P, LANES)``, an upper bound of the pair's distance (``- radius``,
    into ``best``), then each pair's exact distance only in the lanes ``lanes`` where its lower
    bound ``gap - half-lengths - radius`` (``half (K,)``) is under ``best`` (exact, as the others
    are not the minimum: see :func:`own_clearance`)."""
    best[:m] = np.inf
    for i in range(floor.shape[0]):
        e, offset = ends[floor[i]], floor_radius[i, 0] + height
        for j in range(m):
            best[j] = min(best[j], min(e[2, j], e[2, j] + e[5, j]) - offset)
    for pair in range(first.shape[0]):
        e1, e2, radius = ends[first[pair]], ends[second[pair]], pair_radius[pair, 0]
        for j in range(m):
            d0, d1, d2 = e1[6, j] - e2[6, j], e1[7, j] - e2[7, j], e1[8, j] - e2[8, j]
            gap[pair, j] = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            best[j] = min(best[j], gap[pair, j] - radius)
    for pair in range(first.shape[0]):
        e1, e2, radius = ends[first[pair]], ends[second[pair]], pair_radius[pair, 0]
        reach = half[first[pair]] + half[second[pair]] + radius + _SLACK
        count = 0
        for j in range(m):
            count += gap[pair, j] - reach < best[j]
        if count > m // _DENSE:  # many lanes: all of them, vectorised
            for j in range(m):
                best[j] = min(best[j], _pair_clearance(e1, e2, j, radius))
            continue
        count = 0
        for j in range(m):  # the few lanes to compute, gathered without a branch
            lanes[count] = j
            count += gap[pair, j] - reach < best[j]
        for c in range(count):
            j = lanes[c]
            best[j] = min(best[j], _pair_clearance(e1, e2, j, radius))


@jit_nogil
def own_clearance(q, transforms, params, base, frames, local, first, second, pair_radius, floor, floor_radius, height,
                  out):  # fmt: skip
    """Self and floor clearance (m) of ``q (N, n)`` (float32 or float64; computed in float64) into ``out (N,)``: the
    least ``|x - y| - r`` over the self pairs ``first, second (P,)`` (radius sums ``pair_radius (P, 1)``) and
    ``min(z_start, z_end) - (r + height)`` over the capsules ``floor (F,)`` (``floor_radius (F, 1)``). Capsule k joins
    the points ``local[k] (4, 2)`` (columns) of frame ``frames[k]`` (0 the base, i link i; no tool): the tables of
    :meth:`iiwa_torch.collision.Capsules.numpy_tables`. As :func:`iiwa_torch.collision.distances.own_distances`.
    Blocks of configurations go through each step as a branch-free loop, which LLVM vectorises. A pair's exact
    distance is computed only where it can be the minimum: each segment lies within half its length ``h`` of its
    mid-point ``c``, so a pair is between ``|c1 - c2| - h1 - h2`` and ``|c1 - c2|`` apart; the result is exact."""
    count, k_all, last = q.shape[0], frames.shape[0], 0
    half = half_lengths(local)  # each segment lies within half its length of its mid-point
    for k in range(k_all):
        last = max(last, frames[k])
    w = max(1, min(LANES, count))  # lanes: one configuration (the single env) allocates one, none still one
    angle, cs, state = np.empty((last, w)), np.empty((2, last, w)), np.empty((12, w))
    ends = np.empty((k_all, 9, w))  # per capsule: start point, start-to-end vector, mid-point
    gap, lanes, best = np.empty((first.shape[0], w)), np.empty(w, dtype=np.int64), np.empty(w)
    for row in range(0, count, w):
        m = min(w, count - row)
        _block_angles(q, params, row, m, angle, cs)
        block_capsules(transforms, params, base, frames, local, m, angle, cs, state, ends)
        block_minimum(ends, m, first, second, pair_radius, half, floor, floor_radius, height, gap, lanes, best)
        out[row : row + m] = best[:m]


@inline
def _along(params, Z, P, frame, x0, x1, x2, u0, u1, u2, out, sign):
    """``out += sign * u . d x / dq`` for the point ``x`` fixed in link frame ``frame``: joint j
    (axis ``Z[j]`` through ``P[j]``), j < ``frame``, moves it by ``z_j x (x - p_j)``, or by ``z_j``
    if prismatic."""
    for j in range(frame):
        z0, z1, z2, p0, p1, p2 = Z[j, 0], Z[j, 1], Z[j, 2], P[j, 0], P[j, 1], P[j, 2]
        if params[j, 1]:
            out[j] += sign * (u0 * z0 + u1 * z1 + u2 * z2)
            continue
        l0, l1, l2 = x0 - p0, x1 - p1, x2 - p2
        out[j] += sign * (u0 * (z1 * l2 - z2 * l1) + u1 * (z2 * l0 - z0 * l2) + u2 * (z0 * l1 - z1 * l0))


@jit
def capsule_clearance(transforms, params, base, tool, q, frames, local, first, second, pair_radius, floor, floor_radius,
                      height, distance, gradient):
    """One configuration ``q (n,)`` -> each capsule's smallest signed distance (m) to itself and the
    floor into ``distance (K,)`` and its gradient (m/rad) into ``gradient (K, n)`` (``inf`` and
    zeros for a capsule in no pair); the capsules as in :func:`own_clearance`. The torch
    path is :func:`iiwa_torch.collision.capsule_clearance` (the same closest points and
    envelope-theorem gradients; tests/test_backends.py holds them equal)."""
    n, k_all = q.shape[0], frames.shape[0]
    F, pose, Z, P = np.empty((n + 1, 4, 3)), np.empty((4, 4)), np.empty((n, 3)), np.empty((n, 3))
    frames_of(transforms, params, base, tool, q, pose, Z, P, F)
    lane = np.empty((k_all, 9, 1))  # per capsule: start point, start-to-end vector, mid-point
    for f in range(n + 1):
        capsule_ends(frames, local, f, 1, F[f].reshape(12, 1), lane)
    ends = lane[:, :, 0]
    candidate = np.empty(n)
    distance[:] = np.inf
    gradient[:] = 0.0
    for pair in range(first.shape[0]):
        i, j, radius = first[pair], second[pair], pair_radius[pair, 0]
        a, b = ends[i], ends[j]
        s, t, w0, w1, w2 = _closest_gap(lane[i], lane[j], 0)
        norm = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
        u0, u1, u2 = (w0 / norm, w1 / norm, w2 / norm) if norm > 0 else (0.0, 0.0, 0.0)
        candidate[:] = 0.0
        _along(params, Z, P, frames[i], a[0] + s * a[3], a[1] + s * a[4], a[2] + s * a[5], u0, u1, u2, candidate, 1.0)
        _along(params, Z, P, frames[j], b[0] + t * b[3], b[1] + t * b[4], b[2] + t * b[5], u0, u1, u2, candidate, -1.0)
        for k in (i, j):
            if norm - radius < distance[k]:
                distance[k] = norm - radius
                gradient[k, :] = candidate
    for c in range(floor.shape[0]):
        k, e = floor[c], ends[floor[c]]
        x0, x1, x2 = (e[0], e[1], e[2]) if e[2] <= e[2] + e[5] else (e[0] + e[3], e[1] + e[4], e[2] + e[5])  # lower end
        value = x2 - (floor_radius[c, 0] + height)
        if value < distance[k]:
            distance[k] = value
            gradient[k, :] = 0.0
            _along(params, Z, P, frames[k], x0, x1, x2, 0.0, 0.0, 1.0, gradient[k], 1.0)
