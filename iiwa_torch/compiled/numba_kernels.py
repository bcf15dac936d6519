"""The numba kernels of :mod:`iiwa_torch.compiled` (importing this module imports numba).

Each kernel restates a formula of the torch code, and its docstring names the function it
restates (``tests/test_backends.py`` holds them together). Everything is float64
and unchecked: the callers check. A chain enters as the four
:attr:`~iiwa_torch.kinematics.Geometry.float_arrays` ``transforms, params, base, tool``.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .. import segments

__all__ = ["capsule_clearance", "cholesky_solve", "end_poses", "frames_axes", "into_limits", "jacobians", "lm_round",
           "lm_rounds", "own_clearance", "pose_errors"]

_jit = numba.njit(cache=True, error_model="numpy")
_inline = numba.njit(cache=True, error_model="numpy", inline="always")  # no call overhead in the LM loop


# ---------------------------------------------------------------------- kinematics
@_inline
def _turn(u0, u1, u2, v0, v1, v2, c, s):
    """A frame's axis pair ``(u, v)`` turned by the angle of cosine ``c`` and sine ``s`` about the
    third axis: ``(c u + s v, c v - s u)``, 3 + 3 components (a joint's Rz, or a link's Rx)."""
    return c * u0 + s * v0, c * u1 + s * v1, c * u2 + s * v2, c * v0 - s * u0, c * v1 - s * u1, c * v2 - s * u2


@_inline
def _store_frame(f, x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2):
    """A frame's axes and origin into the rows of ``f (4, 3)``."""
    f[0, 0], f[0, 1], f[0, 2], f[1, 0], f[1, 1], f[1, 2] = x0, x1, x2, y0, y1, y2
    f[2, 0], f[2, 1], f[2, 2], f[3, 0], f[3, 1], f[3, 2] = z0, z1, z2, p0, p1, p2


@_inline
def _apply(T, x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2):
    """A frame (axes x, y, z and origin p) times the constant transform ``T (4, 4)``."""
    c00, c10, c20, c01, c11, c21 = T[0, 0], T[1, 0], T[2, 0], T[0, 1], T[1, 1], T[2, 1]
    c02, c12, c22, t0, t1, t2 = T[0, 2], T[1, 2], T[2, 2], T[0, 3], T[1, 3], T[2, 3]
    return (c00 * x0 + c10 * y0 + c20 * z0, c00 * x1 + c10 * y1 + c20 * z1, c00 * x2 + c10 * y2 + c20 * z2,
            c01 * x0 + c11 * y0 + c21 * z0, c01 * x1 + c11 * y1 + c21 * z1, c01 * x2 + c11 * y2 + c21 * z2,
            c02 * x0 + c12 * y0 + c22 * z0, c02 * x1 + c12 * y1 + c22 * z1, c02 * x2 + c12 * y2 + c22 * z2,
            p0 + (t0 * x0 + t1 * y0 + t2 * z0), p1 + (t0 * x1 + t1 * y1 + t2 * z1),
            p2 + (t0 * x2 + t1 * y2 + t2 * z2))  # grouped as the float path groups them: the same bits


@_inline
def _joint(transforms, params, i, theta, x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2, axis):
    """Link frame ``i - 1`` -> link frame ``i`` through joint i at ``theta = q_i + offset_i``:
    ``before_i M(theta) after_i`` (identities skipped); joint i's axis and a point on it into
    ``axis (6,)`` if it has 6 entries."""
    if params[i, 2]:
        x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2 = _apply(transforms[i, 0], x0, x1, x2, y0, y1, y2, z0, z1,
                                                                z2, p0, p1, p2)
    if axis.shape[0] == 6:
        axis[0], axis[1], axis[2], axis[3], axis[4], axis[5] = z0, z1, z2, p0, p1, p2
    if params[i, 1]:  # prismatic: along z
        p0, p1, p2 = p0 + theta * z0, p1 + theta * z1, p2 + theta * z2
    else:
        x0, x1, x2, y0, y1, y2 = _turn(x0, x1, x2, y0, y1, y2, math.cos(theta), math.sin(theta))
    if params[i, 3]:
        x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2 = _apply(transforms[i, 1], x0, x1, x2, y0, y1, y2, z0, z1,
                                                                z2, p0, p1, p2)
    return x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2


@_jit
def _frames(transforms, params, base, tool, q, pose, Z, P, F):
    """``q (n,)`` -> the end pose (tool included) into ``pose (4, 4)``; if ``Z`` has ``n`` rows,
    joint i's axis into ``Z[i]`` and a point on it into ``P[i]`` (both ``(n, 3)``); if ``F`` has
    ``n + 1`` rows, the base and every link frame (no tool) into ``F (n + 1, 4, 3)``, each as its
    x, y, z axes and origin. The frame recursion of :func:`iiwa_torch.kinematics.frames_batch_last`
    (the torch elementwise kernel), one configuration at a time in scalars."""
    x0, x1, x2, y0, y1, y2 = base[0, 0], base[1, 0], base[2, 0], base[0, 1], base[1, 1], base[2, 1]
    z0, z1, z2, p0, p1, p2 = base[0, 2], base[1, 2], base[2, 2], base[0, 3], base[1, 3], base[2, 3]
    keep, every = Z.shape[0] > 0, F.shape[0] > 0
    axis = np.empty(6 if keep else 0)
    if every:
        _store_frame(F[0], x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2)
    for i in range(params.shape[0]):
        x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2 = _joint(transforms, params, i, q[i] + params[i, 0], x0, x1,
                                                                x2, y0, y1, y2, z0, z1, z2, p0, p1, p2, axis)
        if keep:
            Z[i, 0], Z[i, 1], Z[i, 2], P[i, 0], P[i, 1], P[i, 2] = axis[0], axis[1], axis[2], axis[3], axis[4], axis[5]
        if every:
            _store_frame(F[i + 1], x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2)
    for k in range(4):  # column k of the tool, (u, v, w), in the world: u x + v y + w z
        u, v, w = tool[0, k], tool[1, k], tool[2, k]
        pose[0, k], pose[1, k] = u * x0 + v * y0 + w * z0, u * x1 + v * y1 + w * z1
        pose[2, k] = u * x2 + v * y2 + w * z2
        pose[3, k] = 0.0
    pose[0, 3] += p0
    pose[1, 3] += p1
    pose[2, 3] += p2
    pose[3, 3] = 1.0


@_jit
def _jacobian_columns(params, pose, Z, P, J):
    """Column i of ``J (6, n)``: ``[z_i x (p_e - p_i); z_i]`` (revolute) or ``[z_i; 0]`` (prismatic),
    from :func:`_frames`' axes, as :func:`iiwa_torch.kinematics.jacobian` computes them."""
    e0, e1, e2 = pose[0, 3], pose[1, 3], pose[2, 3]
    for i in range(Z.shape[0]):
        z0, z1, z2 = Z[i, 0], Z[i, 1], Z[i, 2]
        if params[i, 1]:
            J[0, i], J[1, i], J[2, i], J[3, i], J[4, i], J[5, i] = z0, z1, z2, 0.0, 0.0, 0.0
            continue
        l0, l1, l2 = e0 - P[i, 0], e1 - P[i, 1], e2 - P[i, 2]
        J[0, i], J[1, i], J[2, i] = z1 * l2 - z2 * l1, z2 * l0 - z0 * l2, z0 * l1 - z1 * l0
        J[3, i], J[4, i], J[5, i] = z0, z1, z2


@_jit
def end_poses(transforms, params, base, tool, q):
    """Configurations ``q (b, n)`` -> their end poses ``(b, 4, 4)``, as :func:`_frames`."""
    out, none = np.empty((q.shape[0], 4, 4)), np.empty((0, 3))
    for k in range(q.shape[0]):
        _frames(transforms, params, base, tool, q[k], out[k], none, none, np.empty((0, 4, 3)))
    return out


@_jit
def frames_axes(transforms, params, base, tool, q):
    """Configurations ``q (b, n)`` -> the base and every link frame ``(b, n + 1, 4, 3)`` (rows: the
    x, y, z axes and the origin; no tool), each joint's axis and a point on it ``(b, n, 3)``
    each, and the end poses ``(b, 4, 4)`` (tool included), as :func:`_frames`."""
    b, n = q.shape
    frames, z, p, poses = np.empty((b, n + 1, 4, 3)), np.empty((b, n, 3)), np.empty((b, n, 3)), np.empty((b, 4, 4))
    for k in range(b):
        _frames(transforms, params, base, tool, q[k], poses[k], z[k], p[k], frames[k])
    return frames, z, p, poses


@_jit
def jacobians(transforms, params, base, tool, q):
    """Configurations ``q (b, n)`` -> their Jacobians ``(b, 6, n)`` (linear rows first, world frame)."""
    b, n = q.shape
    out, pose, Z, P = np.empty((b, 6, n)), np.empty((4, 4)), np.empty((n, 3)), np.empty((n, 3))
    for k in range(b):
        _frames(transforms, params, base, tool, q[k], pose, Z, P, np.empty((0, 4, 3)))
        _jacobian_columns(params, pose, Z, P, out[k])
    return out


@_jit
def _pose_error(pose, pos, rot, has_rot, eps, e):
    """End pose ``(4, 4)`` against a target position ``pos (3,)`` and rotation ``rot (3, 3)``
    -> the position error into ``e[:3]`` (target - pose, m), the rotation vector
    ``log(rot R^T)`` into ``e[3:6]`` (if ``has_rot``), and their norms ``(pos_err, rot_err)``.
    As :func:`iiwa_torch.so3.pose_error` (and the torch loop's ``_pose_terms``) define them."""
    e[0], e[1], e[2] = pos[0] - pose[0, 3], pos[1] - pose[1, 3], pos[2] - pose[2, 3]
    pos_err = math.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
    if not has_rot:
        return pos_err, 0.0

    def w(i, j):  # (R rot^T)[i, j]
        return pose[i, 0] * rot[j, 0] + pose[i, 1] * rot[j, 1] + pose[i, 2] * rot[j, 2]

    v0, v1, v2 = 0.5 * (w(1, 2) - w(2, 1)), 0.5 * (w(2, 0) - w(0, 2)), 0.5 * (w(0, 1) - w(1, 0))
    trace = w(0, 0) + w(1, 1) + w(2, 2)
    sin = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    angle = math.atan2(sin, (trace - 1) * 0.5)
    scale = angle / max(sin, eps)
    e[3], e[4], e[5] = v0 * scale, v1 * scale, v2 * scale
    return pos_err, angle


@_jit
def pose_errors(pose, pos, rot, eps):
    """:func:`_pose_error` of each ``pose (b, 4, 4)`` against ``pos (b, 3)``, ``rot (b, 3, 3)``
    (0 rows: position only) -> position and rotation errors ``(b,)`` each (m, rad)."""
    b, has_rot = pose.shape[0], rot.shape[0] > 0
    pos_err, rot_err, e = np.empty(b), np.empty(b), np.empty(6)
    for k in range(b):
        target_rot = rot[k] if has_rot else pose[k, :3, :3]  # a placeholder without rotations
        pos_err[k], rot_err[k] = _pose_error(pose[k], pos[k], target_rot, has_rot, eps, e)
    return pos_err, rot_err


# ---------------------------------------------------------------------- the LM iteration of ik.solve
@_inline
def _evaluate(arrays, q, pos, rot, has_rot, weight, eps, scratch, J, e):
    """``q (n,)`` -> weighted Jacobian into ``J (m, n)`` and weighted error into ``e (m,)`` (m = 6,
    or 3 without ``has_rot``); returns the squared weighted error, position and rotation error.
    The torch loop's ``_evaluate`` (:mod:`iiwa_torch.ik.gradient`) for one slot."""
    transforms, params, base, tool = arrays
    pose, Z, P, J6 = scratch
    _frames(transforms, params, base, tool, q, pose, Z, P, np.empty((0, 4, 3)))
    _jacobian_columns(params, pose, Z, P, J6)
    pos_err, rot_err = _pose_error(pose, pos, rot, has_rot, eps, e)
    m, n = J.shape
    for r in range(m):
        for i in range(n):
            J[r, i] = J6[r, i] * weight if r >= 3 else J6[r, i]
    if not has_rot:
        return pos_err * pos_err, pos_err, rot_err
    for r in range(3, 6):
        e[r] *= weight
    return pos_err * pos_err + (weight * rot_err) ** 2, pos_err, rot_err


@_jit
def into_limits(x, lo, hi):
    """One angle into ``[lo, hi]``: shifted by a multiple of 2 pi if that fits, else the nearer
    limit around the circle. Mirrors :func:`iiwa_torch.ik.lm_setup.into_limits`."""
    turn = 2 * math.pi
    turned = lo + (x - lo) % turn  # Python's float remainder: fmod, then the divisor's sign, as torch's
    if lo <= x <= hi:
        return x
    if turned <= hi:
        return turned
    return hi if turned - hi <= lo + turn - turned else lo


@_inline
def cholesky_solve(A, y, k, floor):
    """Solve ``A x = y`` in place for the first ``k`` columns of ``y (m, >= k)``, ``A (m, m)`` symmetric
    positive definite (its lower triangle read, then overwritten by the Cholesky factor), pivots
    floored at ``floor`` (as :func:`~iiwa_torch.ik.dls.cholesky_solve_batch_last`)."""
    m = A.shape[0]
    for j in range(m):  # Cholesky A = L L^T in the lower triangle, then L L^T x = y
        for c in range(j):
            A[j, j] -= A[j, c] * A[j, c]
        A[j, j] = math.sqrt(max(A[j, j], floor))
        for r in range(j + 1, m):
            for c in range(j):
                A[r, j] -= A[r, c] * A[j, c]
            A[r, j] /= A[j, j]
    for t in range(k):
        for r in range(m):
            for c in range(r):
                y[r, t] -= A[r, c] * y[c, t]
            y[r, t] /= A[r, r]
        for r in range(m - 1, -1, -1):
            for c in range(r + 1, m):
                y[r, t] -= A[c, r] * y[c, t]
            y[r, t] /= A[r, r]


@_inline
def _lm_step(arrays, q, J, e, E, pos_err, rot_err, lam, pos, rot, has_rot, rest, opts, limits, lo, hi, work):
    """One LM step of one slot, in place on its ``q (n,)``, ``J (m, n)``, ``e (m,)``; returns the
    new ``E``, position and rotation errors and damping (the old ones but the damping if the
    step is rejected). ``opts``: weight, rest gain, eps, lam_min, LAMBDA0, DAMP_DOWN, DAMP_UP.
    The torch loop's ``_lm_step`` (:mod:`iiwa_torch.ik.gradient`) for one slot: ``J diag(free) J^T + lam I`` solved by
    Cholesky (pivots floored at lam_min, as :func:`~iiwa_torch.ik.dls.cholesky_solve_batch_last`)."""
    weight, rest_gain, eps, lam_min, lambda0, damp_down, damp_up = opts
    m, n = J.shape
    free, pull, q_new, A, y, J_new, e_new, scratch = work
    for i in range(n):
        free[i] = 1.0
        if limits:  # joints at a limit that E pushes outward stay put
            descent = 0.0
            for r in range(m):
                descent += J[r, i] * e[r]
            sign = 1.0 if descent > 0 else (-1.0 if descent < 0 else 0.0)
            free[i] = 1.0 if min(max(q[i] + sign, lo[i]), hi[i]) != q[i] else 0.0
    k = 1 if rest.shape[0] == 0 else 2
    pulling = lam <= lambda0
    for i in range(n):
        pull[i] = rest_gain * (rest[i] - q[i]) * free[i] if k == 2 and pulling else 0.0
    for r in range(m):
        for c in range(r + 1):
            s = 0.0
            for i in range(n):
                s += J[r, i] * free[i] * J[c, i]
            A[r, c] = s + lam if r == c else s
        y[r, 0] = e[r]
        if k == 2:
            s = 0.0
            for i in range(n):
                s += J[r, i] * pull[i]
            y[r, 1] = s
    cholesky_solve(A, y, k, lam_min)
    for i in range(n):
        dq0 = dq1 = 0.0
        for r in range(m):
            dq0 += J[r, i] * y[r, 0]
            if k == 2:
                dq1 += J[r, i] * y[r, 1]
        dq = dq0 * free[i] + pull[i] - dq1 * free[i] if k == 2 else dq0 * free[i]
        q_new[i] = min(max(q[i] + dq, lo[i]), hi[i]) if limits else q[i] + dq
    E_new, pos_new, rot_new = _evaluate(arrays, q_new, pos, rot, has_rot, weight, eps, scratch, J_new, e_new)
    if E_new < E:
        q[:] = q_new
        J[:] = J_new
        e[:] = e_new
        return E_new, pos_new, rot_new, min(max(lam * damp_down, lam_min), 1e4)
    return E, pos_err, rot_err, min(max(lam * damp_up, lam_min), 1e4)


@_jit
def lm_round(transforms, params, base, tool, q, problem, number, pos, rot, rest, lo, hi, opts, counts,
             best_q, best_E, used):  # fmt: skip
    """The LM iterations of one round of seeds ``q (s, n)`` (in place), slot ``k`` a seed of
    problem ``problem[k]`` with seed number ``number[k]``; targets ``pos (b, 3)``, ``rot (b, 3, 3)``
    (0 rows: position only), ``rest (b, n)`` (0 rows: none), inner limits ``lo, hi (n,)``;
    ``opts`` as :func:`_lm_step` then pos_tol, rot_tol; ``counts`` iterations, check_every,
    free_steps, seeds. Records each problem's best slot in ``best_q (b, n)``, its key
    ``best_E (b,)`` and iterations ``used (b,)``, in place.
    The torch loop's ``_run_round`` and ``_check_slots`` (:mod:`iiwa_torch.ik.gradient`)."""
    arrays = (transforms, params, base, tool)
    iterations, check_every, free_steps, seeds = counts[0], counts[1], counts[2], counts[3]
    weight, eps, lam_min, lambda0, pos_tol, rot_tol = opts[0], opts[2], opts[3], opts[4], opts[7], opts[8]
    step_opts = (opts[0], opts[1], opts[2], opts[3], opts[4], opts[5], opts[6])
    s, n = q.shape
    b = best_E.shape[0]
    has_rot = rot.shape[0] > 0
    m = 6 if has_rot else 3
    J, e = np.empty((s, m, n)), np.empty((s, m))
    E, pos_err, rot_err, lam = np.empty(s), np.empty(s), np.empty(s), np.empty(s)
    scratch = (np.empty((4, 4)), np.empty((n, 3)), np.empty((n, 3)), np.empty((6, n)))
    work = (np.empty(n), np.empty(n), np.empty(n), np.empty((m, m)), np.empty((m, 2)), np.empty((m, n)),
            np.empty(m), scratch)  # fmt: skip
    no_rest, no_rot = np.empty(0), np.empty((3, 3))
    active = np.ones(s, dtype=np.bool_)
    key, done, lowest, winner = np.empty(s), np.empty(s, dtype=np.bool_), np.empty(b), np.empty(b, dtype=np.int64)

    def target(k):
        p = problem[k]
        return pos[p], rot[p] if has_rot else no_rot, rest[p] if rest.shape[0] else no_rest

    for k in range(s):
        tp, tr, _ = target(k)
        E[k], pos_err[k], rot_err[k] = _evaluate(arrays, q[k], tp, tr, has_rot, weight, eps, scratch, J[k], e[k])
        lam[k] = min(max(0.01 * E[k], lam_min), lambda0)
    checked, left = 0, s
    for step in range(iterations):
        limits = step >= free_steps
        for k in range(s):
            if not active[k]:
                continue
            tp, tr, tq = target(k)
            if step == free_steps and step:  # the unconstrained start ends: into the limits
                for i in range(n):
                    q[k, i] = into_limits(q[k, i], lo[i], hi[i])
                E[k], pos_err[k], rot_err[k] = _evaluate(arrays, q[k], tp, tr, has_rot, weight, eps, scratch, J[k],
                                                         e[k])  # fmt: skip
            E[k], pos_err[k], rot_err[k], lam[k] = _lm_step(arrays, q[k], J[k], e[k], E[k], pos_err[k], rot_err[k],
                                                             lam[k], tp, tr, has_rot, tq, step_opts, limits, lo, hi,
                                                             work)  # fmt: skip
        if (step + 1) % check_every and step + 1 < iterations:
            continue
        # the check: each problem's best slot; converged slots rank below every error, the
        # lowest seed number first
        lowest[:] = best_E
        for k in range(s):
            if not active[k]:
                continue
            used[problem[k]] += step + 1 - checked
            done[k] = pos_err[k] <= 0.5 * pos_tol and rot_err[k] <= 0.5 * rot_tol
            Ek = E[k]
            if step < free_steps:  # only the unconstrained start can leave the limits
                inside = True
                for i in range(n):
                    inside = inside and lo[i] <= q[k, i] <= hi[i]
                done[k] = done[k] and inside
                Ek = Ek if inside else np.inf
            key[k] = number[k] - seeds if done[k] else Ek
            lowest[problem[k]] = min(lowest[problem[k]], key[k])
        checked = step + 1
        winner[:] = -1
        for k in range(s):
            p = problem[k]
            if active[k] and key[k] <= lowest[p] and key[k] < best_E[p]:
                winner[p] = k
        for p in range(b):
            if winner[p] >= 0:
                best_q[p] = q[winner[p]]
        best_E[:] = lowest
        for k in range(s):
            if active[k]:
                first_done = lowest[problem[k]] + seeds if lowest[problem[k]] < 0 else seeds
                active[k] = not done[k] and number[k] < first_done
                left -= not active[k]
        if not left:
            break


@_jit
def lm_rounds(transforms, params, base, tool, pool, order, first, pos, rot, rest, lo, hi, opts, counts, best_q, best_E,
              used):  # fmt: skip
    """Every round of seeds of ``b = best_q.shape[0]`` problems, one seed per problem a round:
    ``first (b, n)`` (q0; 0 rows: none), then the pool ``(P, n)`` entries of ranks ``order (ranks, b)``,
    until a problem converges or runs out of its ``counts[3]`` seeds; the rest as :func:`lm_round`.
    The torch loop's ``_run_rounds`` (:mod:`iiwa_torch.ik.gradient`) with rounds one seed wide."""
    b, n = best_q.shape
    shift = 1 if first.shape[0] else 0
    remaining = np.arange(b)
    for k in range(counts[3]):
        s = remaining.shape[0]
        if not s:
            break
        q = np.empty((s, n))
        for j in range(s):
            p = remaining[j]
            q[j] = first[p] if k < shift else pool[order[k - shift, p]]
            if k == 0:  # until a better one is found, a problem's answer is its first seed
                best_q[p] = q[j]
        lm_round(transforms, params, base, tool, q, remaining, np.full(s, k), pos, rot, rest, lo, hi, opts, counts,
                 best_q, best_E, used)  # fmt: skip
        remaining = remaining[best_E[remaining] >= 0]


# ---------------------------------------------------------------------- the arm-angle sweep of iiwa_solve
_TINY = 1e-30  # iiwa_torch.ik.analytic._common.TINY


@_inline
def _safe_atan2(y, x):
    """Mirrors :func:`iiwa_torch.ik.analytic._common.safe_atan2`."""
    return math.atan2(y, 1.0 if x * x + y * y < _TINY else x)


@_inline
def _safe_norm2(x, y):
    """Mirrors :func:`iiwa_torch.ik.analytic._common.safe_norm2`."""
    return math.sqrt(max(x * x + y * y, _TINY))


@_inline
def _zxzxz_ab(m02, m12, m22, sig_a, sig_b):
    """The first two angles ``(a, b)`` of branch 0 of a spherical triple, from column 2 of ``M``, and
    ``(cos a, sin a, cos b, sin b)`` (the flip is ``(a + pi, -b)``). Mirrors
    :func:`iiwa_torch.ik.analytic._common.decompose_zxzxz`."""
    sb = _safe_norm2(m02, m12)
    cb = -sig_a * sig_b * m22
    a = _safe_atan2(sig_b * m12, sig_b * m02)
    return a, math.atan2(sb, cb), math.cos(a), math.sin(a), cb, sb


@_inline
def _zxzxz_c(ab, m00, m10, m20, sig_a, sig_b):
    """The third angle ``c`` of branch 0 (the flip: ``c + pi``) from ``ab`` (:func:`_zxzxz_ab`) and
    column 0 of ``M``. Mirrors :func:`iiwa_torch.ik.analytic._common.decompose_zxzxz`."""
    _, _, ca, sa, cb, sb = ab
    cos_c = cb * (ca * m00 + sa * m10) + sig_a * sb * m20
    sin_c = sig_a * sig_b * (sa * m00 - ca * m10)
    return _safe_atan2(sin_c, cos_c)


@_inline
def _iiwa_pose(rot, sw, d3, d5, sig, tol):
    """What the closed form takes from one pose: ``rot (3, 3)`` and ``W - S`` ``sw (3,)`` ->
    ``(dist, c4, s4_abs, theta4 of both elbow branches, reachable, u, v_ref, w_ref)`` (``w_ref``'s
    third entry is 0). Mirrors the psi-independent part of :func:`iiwa_torch.ik.analytic.srs._closed_form`
    (``_elbow``, ``_reference``)."""
    sx, sy, sz = sw[0], sw[1], sw[2]
    dist = _safe_norm2(_safe_norm2(sx, sy), sz)
    # _common.triangle(dist, d3, d5, tol)
    c = (dist * dist - (d3 * d3 + d5 * d5)) / (2 * d3 * d5)
    reachable = abs(c) <= 1 + tol
    outer, inner = d3 + d5, abs(d3 - d5)
    s2 = (outer - dist) * (outer + dist) * (dist - inner) * (dist + inner)
    c4 = -sig[2] * sig[3] * min(max(c, -1.0), 1.0)
    s4_abs = math.sqrt(max(s2, _TINY)) / (2 * d3 * d5)
    ux, uy, uz = sx / dist, sy / dist, sz / dist
    b = _safe_atan2(uy, ux)
    cb, sb = math.cos(b), math.sin(b)
    theta4 = (math.atan2(s4_abs, c4), math.atan2(-s4_abs, c4))
    return dist, c4, s4_abs, theta4, reachable, (ux, uy, uz), (-uz * cb, -uz * sb, _safe_norm2(ux, uy)), (sb, -cb)


@_inline
def _dot_col(r, rot, col):
    """``r . rot[:, col]``, summed left to right as :func:`iiwa_torch.ik.analytic.srs._dot`."""
    return r[0] * rot[0, col] + r[1] * rot[1, col] + r[2] * rot[2, col]


@_inline
def _iiwa_branches(pose, rot, psi, d3, d5, sig, theta):
    """The DH angles of the 8 branches at arm angle ``psi`` into ``theta (7, 4)``: each joint's
    distinct values (as the array code holds each joint at the size its branches need), branch
    ``(s, e, w)`` taking joints 1-2 from column ``s``, joint 3 from ``2 s + e``, joint 4 from ``e``
    and joints 5-7 from ``2 e + w``; ``pose`` from :func:`_iiwa_pose`. Mirrors
    :func:`iiwa_torch.ik.analytic.srs._closed_form`."""
    dist, c4, s4_abs, theta4s, _, u, v_ref, w_ref = pose
    cp, sp = math.cos(psi), math.sin(psi)
    v0, v1, v2 = cp * v_ref[0] + sp * w_ref[0], cp * v_ref[1] + sp * w_ref[1], cp * v_ref[2] + sp * 0.0
    n0, n1, n2 = cp * w_ref[0] - sp * v_ref[0], cp * w_ref[1] - sp * v_ref[1], cp * 0.0 - sp * v_ref[2]
    cos_a = (d3 - sig[2] * sig[3] * d5 * c4) / dist
    sin_a = d5 * abs(s4_abs) / dist
    e0, e1, e2 = cos_a * u[0] + sin_a * v0, cos_a * u[1] + sin_a * v1, cos_a * u[2] + sin_a * v2
    x0, x1, x2 = sin_a * u[0] - cos_a * v0, sin_a * u[1] - cos_a * v1, sin_a * u[2] - cos_a * v2
    y0, y1, y2 = sig[2] * e0, sig[2] * e1, sig[2] * e2  # y3
    shoulder = _zxzxz_ab(sig[2] * y0, sig[2] * y1, sig[2] * y2, sig[0], sig[1])  # the same for both elbows
    t1, t2 = shoulder[0], shoulder[1]
    for el in range(2):
        sign = 1.0 if el == 0 else -1.0
        kappa = sig[2] * sig[3] * sign
        theta4 = theta4s[el]
        s4 = s4_abs * sign
        k3 = sig[2] * kappa
        a0, a1, a2 = k3 * x0, k3 * x1, k3 * x2  # x3
        z0, z1, z2 = kappa * n0, kappa * n1, kappa * n2  # z3
        t3 = _zxzxz_c(shoulder, a0, a1, a2, sig[0], sig[1])
        # R_04 = R_03 Rz(theta4) Rx(alpha4), then columns 0, 2 of R_04^T R
        r0 = (c4 * a0 + s4 * y0, c4 * a1 + s4 * y1, c4 * a2 + s4 * y2)
        r1 = (sig[3] * z0, sig[3] * z1, sig[3] * z2)
        r2 = (sig[3] * (s4 * a0 - c4 * y0), sig[3] * (s4 * a1 - c4 * y1), sig[3] * (s4 * a2 - c4 * y2))
        wrist = _zxzxz_ab(_dot_col(r0, rot, 2), _dot_col(r1, rot, 2), _dot_col(r2, rot, 2), sig[4], sig[5])
        t5, t6 = wrist[0], wrist[1]
        t7 = _zxzxz_c(wrist, _dot_col(r0, rot, 0), _dot_col(r1, rot, 0), _dot_col(r2, rot, 0), sig[4], sig[5])
        theta[2, el], theta[2, 2 + el] = t3, t3 + math.pi  # shoulder branch 0, 1
        theta[3, el] = theta4
        theta[4, 2 * el], theta[4, 2 * el + 1] = t5, t5 + math.pi  # wrist branch 0, 1
        theta[5, 2 * el], theta[5, 2 * el + 1] = t6, -t6
        theta[6, 2 * el], theta[6, 2 * el + 1] = t7, t7 + math.pi
    theta[0, 0], theta[0, 1] = t1, t1 + math.pi
    theta[1, 0], theta[1, 1] = t2, -t2


_DISTINCT = (2, 2, 4, 2, 4, 4, 4)  # distinct values of each joint over the 8 branches


@_inline
def _wrap_joint(theta, offset, lo, hi):
    """One DH angle -> ``(q, within)``. Mirrors :func:`iiwa_torch.ik.analytic._common.wrap_joints`
    (and :func:`iiwa_torch.ik.limits.shift_into_limits`)."""
    turn = 2 * math.pi
    q = theta - offset if offset else theta
    q = q - turn * np.rint(q * (1 / turn))
    inside = lo <= q <= hi
    if not (hi > math.pi or lo < -math.pi):
        return q, inside
    turned = lo + (q - lo) % turn  # Python's float remainder, as np.remainder
    fits = turned <= hi
    return (q if inside or not fits else turned), inside or fits


@_inline
def _iiwa_pick(rot, sw, psis, count, q0, has_q0, d3, d5, sig, tol, limits, single, work, best_q):
    """Best of the ``count * 8`` candidates of one pose at the arm angles ``psis[:count]`` into
    ``best_q (7,)``, clamped into the limits; returns ``(found, psi_best)``. ``limits (7, 7)``: the
    joints' offsets, lows and highs to check against, mid-points, half-widths, and the limits to
    clamp into; ``single``: rank in float32; ``work``: scratch ``(7, 4)`` arrays for the angles, the
    wrapped joints, their limit checks and scores. Mirrors :func:`iiwa_torch.ik.analytic.srs._pick`,
    whose sum of squares it adds in the same order (``_common.reduce_grouped``: joint 4, then 1 + 2,
    3, then 5 + 6 + 7)."""
    theta, q, inside, score = work
    pose = _iiwa_pose(rot, sw, d3, d5, sig, tol)
    reachable = pose[4]
    best_key, best_found, psi_best = np.inf, False, psis[0]
    for k in range(count):
        _iiwa_branches(pose, rot, psis[k], d3, d5, sig, theta)
        for j in range(7):  # each distinct joint value wrapped, checked and scored once
            for i in range(_DISTINCT[j]):
                q[j, i], inside[j, i] = _wrap_joint(theta[j, i], limits[0, j], limits[1, j], limits[2, j])
                if has_q0:
                    score[j, i] = (q[j, i] - q0[j]) * (q[j, i] - q0[j])
                else:  # minus the margin to the nearer limit
                    score[j, i] = abs(q[j, i] - limits[3, j]) - limits[4, j]
        for c in range(8):  # branch c = 4 s + 2 e + w, in the array code's order
            a, e = c // 4, (c // 2) % 2  # columns of joints 1-2 and 4 (_iiwa_branches)
            b, w = 2 * a + e, 2 * e + c % 2  # of joint 3, of joints 5-7
            within = (inside[0, a] and inside[1, a] and inside[2, b] and inside[3, e] and inside[4, w]
                      and inside[5, w] and inside[6, w])  # fmt: skip
            if has_q0:
                cost = ((score[3, e] + (score[0, a] + score[1, a])) + score[2, b]) + (
                    (score[4, w] + score[5, w]) + score[6, w])  # fmt: skip
            else:
                cost = max(score[0, a], score[1, a], score[2, b], score[3, e], score[4, w], score[5, w], score[6, w])
            key = (cost + (0.0 if within else 1e6)) + (0.0 if reachable else 2e6)
            if single:
                key = float(np.float32(key))
            if key < best_key:
                best_key, best_found, psi_best = key, reachable and within, psis[k]
                best_q[0], best_q[1], best_q[2], best_q[3] = q[0, a], q[1, a], q[2, b], q[3, e]
                best_q[4], best_q[5], best_q[6] = q[4, w], q[5, w], q[6, w]
    for j in range(7):
        best_q[j] = min(max(best_q[j], limits[5, j]), limits[6, j])
    return best_found, psi_best


@_jit
def iiwa_sweep(rot, sw, q0, psi0, grid, local, fine_grid, fine_local, consts, limits, single):
    """:func:`iiwa_torch.ik.analytic.srs._solve_all` for ``rot (B, 3, 3)``, ``sw (B, 3)``, ``q0 (B, 7)``
    and its arm angles ``psi0 (B,)`` (both 0 rows: none) -> ``q (B, 7)``: per pose the sweep over
    ``grid (K,)`` (after ``psi0``) and the refining passes ``local (P, 9)`` from the best so far, then,
    where nothing valid was found, over ``fine_grid`` and ``fine_local`` (``srs._angles``).
    ``consts``: ``d3, d5``, the six ``sin(alpha)`` and the reach tolerance; ``limits`` as
    :func:`_iiwa_pick`. Mirrors :func:`iiwa_torch.ik.analytic.srs._sweep`."""
    b = rot.shape[0]
    d3, d5, sig, tol = consts[0], consts[1], consts[2:8], consts[8]
    has_q0 = q0.shape[0] > 0
    out = np.empty((b, 7))
    work = (np.empty((7, 4)), np.empty((7, 4)), np.empty((7, 4), dtype=np.bool_), np.empty((7, 4)))
    psis = np.empty(max(grid.shape[0], fine_grid.shape[0]) + 1)
    no_q0 = np.empty(7)
    for p in range(b):
        q0p = q0[p] if has_q0 else no_q0
        for attempt in range(2):
            angles, passes = (grid, local) if attempt == 0 else (fine_grid, fine_local)
            first = 1 if has_q0 and attempt == 0 else 0  # the retry sweeps without psi0
            if first:
                psis[0] = psi0[p]
            psis[first : first + angles.shape[0]] = angles
            found, psi_best = _iiwa_pick(rot[p], sw[p], psis, first + angles.shape[0], q0p, has_q0, d3, d5, sig,
                                         tol, limits, single, work, out[p])  # fmt: skip
            for r in range(passes.shape[0]):
                for i in range(passes.shape[1]):
                    psis[i] = psi_best + passes[r, i]
                found, psi_best = _iiwa_pick(rot[p], sw[p], psis, passes.shape[1], q0p, has_q0, d3, d5, sig, tol,
                                             limits, single, work, out[p])  # fmt: skip
            if found:
                break
    return out


# ---------------------------------------------------------------------- the closed form of pieper
@_jit
def pieper_branches(frame5, consts, limits):
    """All 8 branches of :func:`iiwa_torch.ik.analytic.pieper` for ``frame5 = T_05 Rz(theta6)
    (B, 4, 4)``: ``consts`` ``a1, d1, a2, d2 + d3, L3 = |(a3, d4)|, gamma``, the four ``sin(alpha)``
    of rows 1, 3, 4, 5 and the reach tolerance, ``limits (3, 6)`` the joints' offsets, lows and
    highs -> joint angles ``(6, B, 8)`` (joint-major, as the array code lays them out), reachable and
    within the limits ``(B, 8)``, branch ``4 shoulder + 2 elbow + wrist``. Mirrors
    :func:`iiwa_torch.ik.analytic.spherical6r._closed_form` (with ``_common.zxzx`` and
    ``transpose_times``) and :func:`iiwa_torch.ik.analytic._common.finish`."""
    a1, d1, a2, lateral, link3, gamma = consts[0], consts[1], consts[2], consts[3], consts[4], consts[5]
    s1, s3, s4, s5, tol = consts[6], consts[7], consts[8], consts[9], consts[10]
    b = frame5.shape[0]
    q, reachable, within = np.empty((6, b, 8)), np.empty((b, 8), dtype=np.bool_), np.empty((b, 8), dtype=np.bool_)
    theta = np.empty(6)
    for p in range(b):
        f = frame5[p]
        wx, wy, wz = f[0, 3], f[1, 3], f[2, 3]
        r = _safe_norm2(wx, wy)
        shoulder_ok = r >= abs(lateral) * (1 - tol)
        along = math.sqrt(max((r - abs(lateral)) * (r + abs(lateral)), _TINY))
        for sh in range(2):
            big_x = along * (1.0 if sh == 0 else -1.0)
            theta[0] = _safe_atan2(wy, wx) - math.atan2(-s1 * lateral, big_x)
            px, py = big_x - a1, s1 * (wz - d1)
            # _common.triangle(|(px, py)|, a2, L3, tol)
            dist = _safe_norm2(px, py)
            c = (dist * dist - (a2 * a2 + link3 * link3)) / (2 * a2 * link3)
            elbow_ok = abs(c) <= 1 + tol
            outer, inner = a2 + link3, abs(a2 - link3)
            s2 = (outer - dist) * (outer + dist) * (dist - inner) * (dist + inner)
            c_el = min(max(c, -1.0), 1.0)
            s_el_abs = math.sqrt(max(s2, _TINY)) / (2 * a2 * link3)
            ca, sa = math.cos(theta[0]), math.sin(theta[0])
            for el in range(2):
                s_el = s_el_abs * (1.0 if el == 0 else -1.0)
                theta[2] = math.atan2(s_el, c_el) - gamma
                theta[1] = _safe_atan2(py, px) - _safe_atan2(link3 * s_el, a2 + link3 * c_el)
                # R_03 = zxzx(theta1, theta2 + theta3, s1, s3); m = columns 0, 2 of R_03^T R
                t23 = theta[1] + theta[2]
                cb, sb = math.cos(t23), math.sin(t23)
                k = s1 * s3
                r00, r01, r02 = ca * cb, k * sa, s3 * ca * sb
                r10, r11, r12 = sa * cb, -k * ca, s3 * sa * sb
                r20, r22 = s1 * sb, -k * cb  # r21 = 0: transpose_times skips it
                x0, x1, x2, z0, z1, z2 = f[0, 0], f[1, 0], f[2, 0], f[0, 2], f[1, 2], f[2, 2]
                ab = _zxzxz_ab(r00 * z0 + r10 * z1 + r20 * z2, r01 * z0 + r11 * z1, r02 * z0 + r12 * z1 + r22 * z2,
                               s4, s5)  # fmt: skip
                t6 = _zxzxz_c(ab, r00 * x0 + r10 * x1 + r20 * x2, r01 * x0 + r11 * x1, r02 * x0 + r12 * x1 + r22 * x2,
                              s4, s5)  # fmt: skip
                for wr in range(2):
                    branch = 4 * sh + 2 * el + wr
                    theta[3] = ab[0] + math.pi if wr else ab[0]
                    theta[4] = -ab[1] if wr else ab[1]
                    theta[5] = t6 + math.pi if wr else t6
                    inside = True
                    for j in range(6):
                        q[j, p, branch], fits = _wrap_joint(theta[j], limits[0, j], limits[1, j], limits[2, j])
                        inside = inside and fits
                    reachable[p, branch] = shoulder_ok and elbow_ok
                    within[p, branch] = inside
    return q, reachable, within


# ---------------------------------------------------------------------- collision: clearance of large batches
# numba calls libm's sin and cos one element at a time (no SVML here), which stops LLVM from
# vectorising a loop and costs more than the rest of the clearance kernel: _sin_cos is a
# branch-free restatement of fdlibm's (FreeBSD msun e_rem_pio2.c, k_sin.c, k_cos.c): the angle
# less the nearest multiple n of pi/2 (pi/2 in three 33-bit parts, so each product with n is
# exact for |n| < 2^20), then the two minimax polynomials on [-pi/4, pi/4] and n's quadrant.
_SIN_COS_RANGE = 1e5  # rad: |angle| up to which _sin_cos is within an ulp or two of libm; beyond, libm
_INV_PIO2 = 6.36619772367581382433e-01
_PIO2 = (1.57079632673412561417e00, 6.07710050630396597660e-11, 2.02226624871116645580e-21)
_SIN = (-1.66666666666666324348e-01, 8.33333333332248946124e-03, -1.98412698298579493134e-04,
        2.75573137070700676789e-06, -2.50507602534068634195e-08, 1.58969099521155010221e-10)  # fmt: skip
_COS = (4.16666666666666019037e-02, -1.38888888888741095749e-03, 2.48015872894767294178e-05,
        -2.75573143513906633035e-07, 2.08757232129817482790e-09, -1.13596475577881948265e-11)  # fmt: skip


@_inline
def _sin_cos(x):
    """``(sin x, cos x)`` for ``|x| <= _SIN_COS_RANGE``, without a branch or a call (see above)."""
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
_closest = _inline(segments.closest_parameters)
_choose, _unit, _quotient = _inline(segments.choose), _inline(segments.unit_float), _inline(segments.quotient)
_LANES = 256  # configurations per block: the block's frames and capsules stay in the L1 cache


@_jit
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
                wide = wide or (abs(angle[i, j]) > _SIN_COS_RANGE and not params[i, 1])
        for i in range(last):
            if wide:
                for j in range(m):
                    cs[0, i, j], cs[1, i, j] = math.cos(angle[i, j]), math.sin(angle[i, j])
            else:
                for j in range(m):
                    cs[1, i, j], cs[0, i, j] = _sin_cos(angle[i, j])
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
                        x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2 = _apply(transforms[i, 0], x0, x1, x2, y0, y1,
                                                                                y2, z0, z1, z2, p0, p1, p2)
                    if params[i, 1]:  # prismatic: along z
                        t = angle[i, j]
                        p0, p1, p2 = p0 + t * z0, p1 + t * z1, p2 + t * z2
                    else:
                        x0, x1, x2, y0, y1, y2 = _turn(x0, x1, x2, y0, y1, y2, cs[0, i, j], cs[1, i, j])
                    if params[i, 3]:
                        x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2 = _apply(transforms[i, 1], x0, x1, x2, y0, y1,
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


@_inline
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


@_jit
def capsule_clearance(transforms, params, base, tool, q, frames, local, first, second, pair_radius, floor, floor_radius,
                      height, distance, gradient):
    """One configuration ``q (n,)`` -> each capsule's smallest signed distance (m) to itself and the
    floor into ``distance (K,)`` and its gradient (m/rad) into ``gradient (K, n)`` (``inf`` and
    zeros for a capsule in no pair); the capsules as in :func:`own_clearance`. Mirrors
    :func:`iiwa_torch.collision._capsule_clearance_floats`: the same closest points, the same
    envelope-theorem gradients, the same order of comparisons."""
    n, k_all = q.shape[0], frames.shape[0]
    F, pose, Z, P = np.empty((n + 1, 4, 3)), np.empty((4, 4)), np.empty((n, 3)), np.empty((n, 3))
    _frames(transforms, params, base, tool, q, pose, Z, P, F)
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
