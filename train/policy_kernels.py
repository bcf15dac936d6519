"""The numba kernels of the residual policy's inference on a few rows (importing this module imports
numba; :class:`train.features.JointGoalExtractor` and :class:`train.residual.ResidualDLSPolicy` import it
on their first small-batch call when :data:`iiwa_torch.compiled.ENABLED`).

One policy step in one env computes the goal deltas, a Jacobian, a few DLS solves, the velocity
damper's Hildreth sweeps and the damper's constraints, then the action head's gated sum, Hildreth
again and a shrink: some sixty numpy calls of about a microsecond each, where the arithmetic itself
takes a fraction of one. :func:`features` restates the extractor's numpy path
(``JointGoalExtractor._features``) row by row in one compiled call, and :func:`residual_mean` the
head's (``_ResidualHead``); ``tests/test_train_features.py`` and ``tests/test_train_residual.py`` hold
them to those paths. Linear solves are by Cholesky (the matrices are symmetric positive definite;
:func:`iiwa_torch.compiled.numba_kernels.cholesky_solve`, the LM rounds' solve) where numpy's are by LU:
the same values to rounding.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from iiwa_torch.compiled.numba_kernels import cholesky_solve, jacobians

__all__ = ["SCALARS", "pack_scalars", "FeatureOptions", "features", "residual_mean"]

_jit = numba.njit(cache=True, error_model="numpy")
_PIVOT_FLOOR = float(np.finfo(np.float64).tiny)  # the torch path's pivot floor (never reached: damping > 0)


@_jit
def _dls(jp, e, damping_sq, free, prior, hold, dq, A, y):
    """``dq (nj,) = held + J^T (J_free J^T + damping_sq I)^-1 (e - J held)``, ``held = prior * free + hold``,
    zero at held joints (``free`` 0) but for their ``held``, for ``jp (k, nj)``, ``e (k,)``, ``prior (nj,)``
    (the preferred step, zeros without centering), ``hold (nj,)`` (the held joints' steps, zeros but with
    ``limit_hold = "limit"``): ``iiwa_torch.ik.dls.dls_step_numpy`` as ``JointGoalExtractor.bounded_step``
    calls it; ``A (k, k)``, ``y (k, 1)`` scratch."""
    k, nj = jp.shape
    for r in range(k):
        total = 0.0
        for j in range(nj):
            total += (prior[j] * free[j] + hold[j]) * jp[r, j]
        y[r, 0] = e[r] - total
    for r in range(k):
        for c in range(r + 1):
            total = 0.0
            for j in range(nj):
                total += jp[r, j] * free[j] * jp[c, j]
            A[r, c] = total
        A[r, r] += damping_sq
    cholesky_solve(A, y, 1, _PIVOT_FLOOR)
    for j in range(nj):
        total = 0.0
        for r in range(k):
            total += jp[r, j] * y[r, 0]
        dq[j] = prior[j] * free[j] + hold[j] + total * free[j]


@_jit
def _bound(u, clip):
    """Steps in actions ``u (nj,)`` into ``[-1, 1]`` in place: clipped joint by joint, or shrunk
    (``train.features.shrink``)."""
    if clip:
        for j in range(u.shape[0]):
            u[j] = min(max(u[j], -1.0), 1.0)
        return
    largest = 1.0
    for j in range(u.shape[0]):
        largest = max(largest, abs(u[j]))
    for j in range(u.shape[0]):
        u[j] = u[j] / largest


@_jit
def _bound_guarded(u, clip, guarded, guard, gain, shrunk):
    """``train.features.JointGoalExtractor.bounded_by_progress`` on one step ``u (nj,)``, in place: clipped
    (or shrunk) by :func:`_bound`, but with ``guarded``, a clipped step whose progress ``gain . u`` (``gain =
    J^T e max_step``) is below ``guard`` times the shrunk step's is shrunk instead; ``shrunk (nj,)`` scratch."""
    if not guarded:
        _bound(u, clip)
        return
    for j in range(u.shape[0]):
        shrunk[j] = u[j]
    _bound(shrunk, False)
    _bound(u, True)
    ahead, behind = 0.0, 0.0
    for j in range(u.shape[0]):
        ahead += u[j] * gain[j]
        behind += shrunk[j] * gain[j]
    if ahead < guard * behind:
        for j in range(u.shape[0]):
            u[j] = shrunk[j]


@_jit
def _hildreth(x, normal, scaled, bound, sweeps):
    """``train.features.hildreth`` on one row, in place on ``x (nj,)``: ``normal``, ``scaled (K, nj)``,
    ``bound (K,)``."""
    K, nj = normal.shape
    curvature, multiplier = np.empty(K), np.zeros(K)
    acting = np.zeros(K, dtype=np.bool_)
    for k in range(K):
        total = 0.0
        for j in range(nj):
            total += normal[k, j] * scaled[k, j]
            acting[k] = acting[k] or scaled[k, j] != 0.0
        curvature[k] = max(total, 1e-12)
    for _ in range(sweeps):
        moved = False
        for k in range(K):
            if not acting[k]:
                continue
            total = 0.0
            for j in range(nj):
                total += normal[k, j] * x[j]
            change = max((bound[k] - total) / curvature[k], -multiplier[k])
            multiplier[k] += change
            for j in range(nj):
                x[j] += scaled[k, j] * change
            moved = moved or change != 0.0
        if not moved:
            break


#: The extractor's scalar options in :func:`features`' ``scalars`` array, in this order (flags as 0 or 1):
#: ``error_damping``, ``clip`` (``step_bound == "clip"``, else shrink), ``limit_rounds``, ``orientation_weight``
#: (m/rad), ``centering`` (``null_space_centering``, 0: none), ``twist`` (``centering_twist``), ``guarded``
#: (``clip_guard`` set), ``guard`` (its value), ``hold_at_limit`` (``limit_hold == "limit"``), the damper's
#: ``xi``, ``safe``, ``influence`` (m), ``clearance_start`` (the first clearance column of the observation)
#: and ``K`` (capsules; 0: no avoidance).
SCALARS = ("error_damping", "clip", "limit_rounds", "orientation_weight", "centering", "twist", "guarded", "guard",
           "hold_at_limit", "xi", "safe", "influence", "clearance_start", "K")


def pack_scalars(values: dict) -> np.ndarray:
    """The options ``values`` (by the names of :data:`SCALARS`) -> :func:`features`' ``scalars (14,)`` float64."""
    return np.array([float(values[name]) for name in SCALARS])


class FeatureOptions(NamedTuple):
    """The options as :func:`features`' parts read them (built inside the kernel: a tuple argument would
    cost the call more than its arithmetic, typed in Python field by field).

    ``inv_scales (S,)`` in the goals' dtype; ``max_step`` (rad per step), ``lower``, ``upper`` (rad) ``(nj,)``
    and ``damping_sq (L,)`` (m^2), float64; the :data:`SCALARS`, ``damper = (xi, safe, influence)``."""

    inv_scales: np.ndarray
    max_step: np.ndarray
    damping_sq: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    error_damping: float
    clip: bool
    limit_rounds: int
    orientation_weight: float
    centering: float
    twist: bool
    guarded: bool
    guard: float
    hold_at_limit: bool
    damper: np.ndarray
    clearance_start: int
    K: int


@_jit
def features(observation, achieved, desired, e, q, inv_scales, damping_sq, joints, scalars, transforms, params, base,
             tool):
    """The extractor's features ``(B, F)`` in ``observation``'s dtype.

    ``observation (B, O)``, ``achieved``, ``desired (B, G)`` as observed; ``e (B, k)`` float64, the
    error (position, then the weighted rotation error for pose goals, k = 6); ``q (B, nj)`` rad;
    ``inv_scales (S,)`` in the goals' dtype; ``damping_sq (L,)`` (m^2); ``joints (3, nj)``: ``max_step``
    (rad per step), ``lower``, ``upper`` (rad); ``scalars`` (:func:`pack_scalars`); the chain's
    ``float_arrays``."""
    o = FeatureOptions(inv_scales, joints[0], damping_sq, joints[1], joints[2], scalars[0], scalars[1] != 0.0,
                       int(scalars[2]), scalars[3], scalars[4], scalars[5] != 0.0, scalars[6] != 0.0, scalars[7],
                       scalars[8] != 0.0, scalars[9:12], int(scalars[12]), int(scalars[13]))
    B, width_obs = observation.shape
    G, S, k = desired.shape[1], inv_scales.shape[0], e.shape[1]
    nj, L, K = q.shape[1], damping_sq.shape[0], o.K
    out = np.empty((B, width_obs + (2 + S) * G + (L + 2) * nj + 1 + K * (nj + 1)), dtype=observation.dtype)
    jac = np.empty((B, 6, nj))
    jacobians(transforms, params, base, tool, q, jac)
    jp, row, prior, gain = np.empty((k, nj)), np.empty(k), np.zeros(nj), np.empty(nj)
    normal, bound = np.zeros((K, nj)), np.empty(K)
    scratch = (np.empty((k, k)), np.empty((k, 1)), np.empty(nj), np.empty(nj), np.empty(nj), np.zeros(nj),
               np.empty(nj), np.empty((nj, nj)), np.empty((nj, K)), np.empty((K, nj)))
    for b in range(B):
        col = _goal_features(out[b], observation[b], achieved[b], desired[b], o.inv_scales)
        size = _task_rows(jac[b], e[b], o, jp, row, gain)
        if o.centering:
            _centering(q[b], jp, row, o, prior)
        if K:
            _damper_rows(observation[b], o, K, normal, bound)
        for lam in range(L):
            d = o.damping_sq[lam] if o.error_damping == 0.0 else \
                (math.sqrt(o.damping_sq[lam]) + o.error_damping * size) ** 2
            step = _bounded_step(q[b], jp, row, d, prior, gain, o, scratch)
            if K:
                _damped(step, jp, d, normal, bound, o, scratch)
            for j in range(nj):
                out[b, col] = step[j]
                col += 1
        _joint_tail(out[b], col, jp, e[b], size, q[b], o, normal, bound)
    return out


@_jit
def _goal_features(out, observation, achieved, desired, inv_scales):
    """One row's goal features into ``out``: observation, both goals, ``clip(delta / s, -1, 1)`` per scale
    (goals' dtype); -> the next column."""
    G, col = desired.shape[0], 0
    for j in range(observation.shape[0]):
        out[col] = observation[j]
        col += 1
    for j in range(G):
        out[col], out[col + G] = achieved[j], desired[j]
        col += 1
    col += G
    for s in range(inv_scales.shape[0]):
        for j in range(G):
            out[col] = min(max((desired[j] - achieved[j]) * inv_scales[s], -1.0), 1.0)
            col += 1
    return col


@_jit
def _task_rows(jac, e, o, jp, row, gain):
    """One row's task Jacobian into ``jp (k, nj)`` (position rows, then the weighted rotation rows for pose
    goals), its error into ``row (k,)`` and ``J^T e max_step`` into ``gain (nj,)`` (the first-order progress
    of a step in actions, for ``clip_guard``); -> ``|e|``."""
    k, nj = jp.shape
    for r in range(k):
        weight = 1.0 if r < 3 else o.orientation_weight
        for j in range(nj):
            jp[r, j] = weight * jac[r, j]
    size = 0.0
    for r in range(k):
        size += e[r] * e[r]
        row[r] = e[r]
    size = math.sqrt(size)
    for j in range(nj):
        total = 0.0
        for r in range(k):
            total += jp[r, j] * e[r]
        gain[j] = total * o.max_step[j]
    return size


@_jit
def _centering(q, jp, row, o, prior):
    """One row's preferred step into ``prior (nj,)`` (``JointGoalExtractor.centering_step``, with
    ``last_joint_twist``)."""
    nj = q.shape[0]
    phi = 0.0
    if o.twist:
        spin, size_axis = 0.0, 0.0
        for r in range(3):
            spin += row[3 + r] * jp[3 + r, nj - 1]
            size_axis += jp[3 + r, nj - 1] * jp[3 + r, nj - 1]
        size_rot = math.sqrt(row[3] ** 2 + row[4] ** 2 + row[5] ** 2)
        along = spin / max(size_rot * math.sqrt(size_axis), 1e-300)
        half = size_rot / (2.0 * o.orientation_weight)
        phi = 2.0 * math.atan2(math.sin(half) * along, math.cos(half))
    for j in range(nj):
        angle = q[j] + phi if j == nj - 1 else q[j]
        place = 2.0 * (angle - o.lower[j]) / (o.upper[j] - o.lower[j]) - 1.0
        prior[j] = -o.centering * o.max_step[j] * place * abs(place)


@_jit
def _damper_rows(observation, o, K, normal, bound):
    """One row's damper constraints into ``normal (K, nj)`` and ``bound (K,)``
    (``train.features.damper_constraints``)."""
    xi, safe, influence = o.damper[0], o.damper[1], o.damper[2]
    nj, start = normal.shape[1], o.clearance_start
    for c in range(K):
        distance = float(observation[start + c])
        near = distance < influence
        bound[c] = -xi * (distance - safe) if near else -1.0
        for j in range(nj):
            normal[c, j] = float(observation[start + K + c * nj + j]) if near else 0.0


@_jit
def _bounded_step(q, jp, row, d, prior, gain, o, scratch):
    """One row's DLS step at squared damping ``d`` in actions, bounded (``JointGoalExtractor.bounded_step``,
    its limit rounds); -> ``step (nj,)``, a scratch array."""
    A, y, dq, free, step, hold, shrunk = scratch[:7]
    nj = q.shape[0]
    free[:] = 1.0
    hold[:] = 0.0
    _dls(jp, row, d, free, prior, hold, dq, A, y)
    for _ in range(o.limit_rounds):
        for j in range(nj):
            step[j] = dq[j] / o.max_step[j]
        _bound_guarded(step, o.clip, o.guarded, o.guard, gain, shrunk)
        blocked = False
        for j in range(nj):
            move = step[j] * o.max_step[j]
            end = q[j] + move
            if free[j] > 0 and ((end > o.upper[j] and move > 0) or (end < o.lower[j] and move < 0)):
                free[j], blocked = 0.0, True
                if o.hold_at_limit:  # onto the limit it would pass
                    hold[j] = (o.upper[j] if move > 0 else o.lower[j]) - q[j]
        if not blocked:
            break
        _dls(jp, row, d, free, prior, hold, dq, A, y)
    for j in range(nj):
        step[j] = dq[j] / o.max_step[j]
    _bound_guarded(step, o.clip, o.guarded, o.guard, gain, shrunk)
    return step


@_jit
def _damped(step, jp, d, normal, bound, o, scratch):
    """One row's bounded step ``step (nj,)`` (actions) through the velocity damper in the metric
    ``J^T J + d I``, in place (``train.features.velocity_damper``), then bounded again."""
    H, columns, scaled = scratch[7], scratch[8], scratch[9]
    k, nj = jp.shape
    K = normal.shape[0]
    for r in range(nj):
        for c in range(r + 1):
            total = 0.0
            for i in range(k):
                total += jp[i, r] * jp[i, c]
            H[r, c] = total
        H[r, r] += d
    for c in range(K):
        for j in range(nj):
            columns[j, c] = normal[c, j]
    cholesky_solve(H, columns, K, _PIVOT_FLOOR)
    for c in range(K):
        for j in range(nj):
            scaled[c, j] = columns[j, c]
    for j in range(nj):
        step[j] *= o.max_step[j]
    _hildreth(step, normal, scaled, bound, 5)
    for j in range(nj):
        step[j] /= o.max_step[j]
    _bound(step, o.clip)


@_jit
def _joint_tail(out, col, jp, e, size, q, o, normal, bound):
    """One row's last features into ``out`` from ``col``: ``J^T e / |e|``, the place within the limits, ``|e|``,
    then the damper's constraints in actions and their bounds."""
    k, nj = jp.shape
    for j in range(nj):
        total = 0.0
        for r in range(k):
            total += jp[r, j] * e[r]
        out[col] = total / max(size, 1e-6)
        out[col + nj] = 2.0 * (q[j] - o.lower[j]) / (o.upper[j] - o.lower[j]) - 1.0
        col += 1
    col += nj
    out[col] = size
    col += 1
    for c in range(normal.shape[0]):
        for j in range(nj):
            out[col] = normal[c, j] * o.max_step[j]
            col += 1
    for c in range(normal.shape[0]):
        out[col] = bound[c]
        col += 1


@_jit
def residual_mean(step, distance, correction, damper, gradient, ahead_scale, gate):
    """``_ResidualHead``'s mean ``(B, nj)`` float32: ``step + d / (d + gate) * correction`` in float32
    (the numpy path's operations, so the same bits), then, with constraints (``K = damper.shape[1] /
    (nj + 1)`` of the damper, and the progress constraint ``a . x >= a . step``, ``a = gradient *
    ahead_scale``, when ``ahead_scale`` is not empty), Hildreth's sweeps and the shrink (in float64, rounded
    back: the same values to float32 rounding where a constraint acts).

    ``step``, ``correction``, ``gradient (B, nj)`` (``(B, 0)`` without progress constraint), ``distance
    (B, 1)`` (m), ``damper (B, K nj + K)`` (the normals in actions, then the bounds), ``ahead_scale (nj,)``
    or ``(0,)``, float32; ``gate`` (m) a float32."""
    B, nj = step.shape
    K = damper.shape[1] // (nj + 1)
    P = 1 if ahead_scale.shape[0] else 0
    out = np.empty((B, nj), dtype=np.float32)
    x, normal, bound = np.empty(nj), np.empty((P + K, nj)), np.empty(P + K)
    for b in range(B):
        weight = distance[b, 0] / (distance[b, 0] + gate)
        for j in range(nj):
            x[j] = step[b, j] + weight * correction[b, j]
        if P + K:
            if P:
                total = 0.0
                for j in range(nj):
                    normal[0, j] = float(gradient[b, j]) * float(ahead_scale[j])
                    total += normal[0, j] * float(step[b, j])
                bound[0] = total
            for c in range(K):
                for j in range(nj):
                    normal[P + c, j] = damper[b, c * nj + j]
                bound[P + c] = damper[b, K * nj + c]
            _hildreth(x, normal, normal, bound, 5)
            _bound(x, False)
        for j in range(nj):
            out[b, j] = x[j]
    return out
