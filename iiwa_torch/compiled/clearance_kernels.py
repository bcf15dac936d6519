"""Compiled capsule clearance: the self and floor clearance of large batches (:func:`own_clearance`) and
each capsule's clearance with its gradient for one configuration (:func:`capsule_clearance`)."""

from __future__ import annotations

import math

import numpy as np

from .. import segments
from .decorators import inline, jit
from .kinematics_kernels import apply_transform, frames_of, turn

__all__ = ["SIN_COS_RANGE", "capsule_clearance", "own_clearance", "sin_cos"]

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
_LANES = 256  # configurations per block: the block's frames and capsules stay in the L1 cache


@jit
def own_clearance(  # noqa: C901 (to split: tests/test_codebase.py LONG_FUNCTIONS)
    q, transforms, params, base, frames, local, first, second, pair_radius, floor, floor_radius, height, out
):
    """Self and floor clearance of ``q (N, n)`` (float32 or float64; computed in float64) into
    ``out (N,)``, metres: the smallest of ``|x - y| - r`` over the self pairs ``first, second
    (P,)`` (``pair_radius (P, 1)`` radius sums) and ``min(z_start, z_end) - (r + height)`` over the
    capsules ``floor (F,)`` (``floor_radius (F, 1)``). Capsule k joins the homogeneous points
    ``local[k] (4, 2)`` (columns) of frame ``frames[k]`` (0 the base, i link i; the tool is not
    used). The arguments are :meth:`iiwa_torch.collision.Capsules._numpy_tables`' and the chain's
    ``float_arrays``. Mirrors :func:`iiwa_torch.collision._distances` without obstacles: the
    frames of :func:`iiwa_torch.kinematics.frames_batch_last`, the segments of
    :func:`iiwa_torch.collision._segment_gap` (:func:`iiwa_torch.segments.closest_parameters`
    itself, compiled). Each block of configurations goes through every step as a loop over the
    block, straight-line and branch-free, which LLVM vectorises."""
    count, k_all, last = q.shape[0], frames.shape[0], 0
    for k in range(k_all):
        last = max(last, frames[k])
    angle, cs = np.empty((last, _LANES)), np.empty((2, last, _LANES))
    state = np.empty((12, _LANES))  # the moving frame: x, y, z axes and origin, 3 rows each
    ends = np.empty((k_all, 6, _LANES))  # per capsule: start point, start-to-end vector
    best = np.empty(_LANES)
    for row in range(0, count, _LANES):
        m = min(_LANES, count - row)
        wide = False
        for j in range(m):
            for i in range(last):
                angle[i, j] = q[row + j, i] + params[i, 0]
                wide = wide or (abs(angle[i, j]) > SIN_COS_RANGE and not params[i, 1])
        for i in range(last):
            if wide:
                for j in range(m):
                    cs[0, i, j], cs[1, i, j] = math.cos(angle[i, j]), math.sin(angle[i, j])
            else:
                for j in range(m):
                    cs[1, i, j], cs[0, i, j] = sin_cos(angle[i, j])
        for r in range(12):
            for j in range(m):
                state[r, j] = base[r % 3, r // 3]
        for f in range(last + 1):
            if f > 0:
                i = f - 1
                for j in range(m):
                    x0, x1, x2 = state[0, j], state[1, j], state[2, j]
                    y0, y1, y2 = state[3, j], state[4, j], state[5, j]
                    z0, z1, z2 = state[6, j], state[7, j], state[8, j]
                    p0, p1, p2 = state[9, j], state[10, j], state[11, j]
                    if params[i, 2]:
                        x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2 = apply_transform(transforms[i, 0], x0, x1, x2, y0, y1,
                                                                                y2, z0, z1, z2, p0, p1, p2)
                    if params[i, 1]:  # prismatic: along z
                        t = angle[i, j]
                        p0, p1, p2 = p0 + t * z0, p1 + t * z1, p2 + t * z2
                    else:
                        x0, x1, x2, y0, y1, y2 = turn(x0, x1, x2, y0, y1, y2, cs[0, i, j], cs[1, i, j])
                    if params[i, 3]:
                        x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2 = apply_transform(transforms[i, 1], x0, x1, x2, y0, y1,
                                                                                y2, z0, z1, z2, p0, p1, p2)
                    state[0, j], state[1, j], state[2, j] = x0, x1, x2
                    state[3, j], state[4, j], state[5, j] = y0, y1, y2
                    state[6, j], state[7, j], state[8, j] = z0, z1, z2
                    state[9, j], state[10, j], state[11, j] = p0, p1, p2
            for k in range(k_all):
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
        for j in range(m):
            best[j] = np.inf
        for pair in range(first.shape[0]):
            e1, e2, radius = ends[first[pair]], ends[second[pair]], pair_radius[pair, 0]
            for j in range(m):
                r0, r1, r2 = e1[0, j] - e2[0, j], e1[1, j] - e2[1, j], e1[2, j] - e2[2, j]
                a0, a1, a2, b0, b1, b2 = e1[3, j], e1[4, j], e1[5, j], e2[3, j], e2[4, j], e2[5, j]
                s, t = _closest(a0 * a0 + a1 * a1 + a2 * a2, b0 * b0 + b1 * b1 + b2 * b2, a0 * b0 + a1 * b1 + a2 * b2,
                                a0 * r0 + a1 * r1 + a2 * r2, b0 * r0 + b1 * r1 + b2 * r2, _choose, _unit, _quotient)
                w0, w1, w2 = r0 + s * a0 - t * b0, r1 + s * a1 - t * b1, r2 + s * a2 - t * b2
                best[j] = min(best[j], math.sqrt(w0 * w0 + w1 * w1 + w2 * w2) - radius)
        for i in range(floor.shape[0]):
            e, offset = ends[floor[i]], floor_radius[i, 0] + height
            for j in range(m):
                best[j] = min(best[j], min(e[2, j], e[2, j] + e[5, j]) - offset)
        for j in range(m):
            out[row + j] = best[j]


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
    zeros for a capsule in no pair); the capsules as in :func:`own_clearance`. Mirrors
    :func:`iiwa_torch.collision._capsule_clearance_floats`: the same closest points, the same
    envelope-theorem gradients, the same order of comparisons."""
    n, k_all = q.shape[0], frames.shape[0]
    F, pose, Z, P = np.empty((n + 1, 4, 3)), np.empty((4, 4)), np.empty((n, 3)), np.empty((n, 3))
    frames_of(transforms, params, base, tool, q, pose, Z, P, F)
    ends = np.empty((k_all, 6))  # per capsule: start point, start-to-end vector
    for k in range(k_all):
        f = frames[k]
        u0, v0, w0 = local[k, 0, 0], local[k, 1, 0], local[k, 2, 0]
        u1, v1, w1 = local[k, 0, 1], local[k, 1, 1], local[k, 2, 1]
        for r in range(3):  # each end point: p + u x + v y + w z
            x, y, z, p = F[f, 0, r], F[f, 1, r], F[f, 2, r], F[f, 3, r]
            start = p + u0 * x + v0 * y + w0 * z
            ends[k, r] = start
            ends[k, 3 + r] = p + u1 * x + v1 * y + w1 * z - start
    candidate = np.empty(n)
    for k in range(k_all):
        distance[k] = np.inf
        gradient[k, :] = 0.0
    for pair in range(first.shape[0]):
        i, j, radius = first[pair], second[pair], pair_radius[pair, 0]
        a, b = ends[i], ends[j]
        r0, r1, r2 = a[0] - b[0], a[1] - b[1], a[2] - b[2]
        a0, a1, a2, b0, b1, b2 = a[3], a[4], a[5], b[3], b[4], b[5]
        s, t = _closest(a0 * a0 + a1 * a1 + a2 * a2, b0 * b0 + b1 * b1 + b2 * b2, a0 * b0 + a1 * b1 + a2 * b2,
                        a0 * r0 + a1 * r1 + a2 * r2, b0 * r0 + b1 * r1 + b2 * r2, _choose, _unit, _quotient)
        w0, w1, w2 = r0 + s * a0 - t * b0, r1 + s * a1 - t * b1, r2 + s * a2 - t * b2
        norm = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
        u0, u1, u2 = (w0 / norm, w1 / norm, w2 / norm) if norm > 0 else (0.0, 0.0, 0.0)
        candidate[:] = 0.0
        _along(params, Z, P, frames[i], a[0] + s * a0, a[1] + s * a1, a[2] + s * a2, u0, u1, u2, candidate, 1.0)
        _along(params, Z, P, frames[j], b[0] + t * b0, b[1] + t * b1, b[2] + t * b2, u0, u1, u2, candidate, -1.0)
        for k in (i, j):
            if norm - radius < distance[k]:
                distance[k] = norm - radius
                gradient[k, :] = candidate
    for c in range(floor.shape[0]):
        k, e = floor[c], ends[floor[c]]
        low = 0 if e[2] <= e[2] + e[5] else 1  # the lower end point
        x0, x1, x2 = (e[0], e[1], e[2]) if low == 0 else (e[0] + e[3], e[1] + e[4], e[2] + e[5])
        value = x2 - (floor_radius[c, 0] + height)
        if value < distance[k]:
            distance[k] = value
            gradient[k, :] = 0.0
            _along(params, Z, P, frames[k], x0, x1, x2, 0.0, 0.0, 1.0, gradient[k], 1.0)
