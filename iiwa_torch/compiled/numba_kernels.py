"""The numba kernels of :mod:`iiwa_torch.compiled` (importing this module imports numba).

Each kernel restates a formula of the numpy / Python-float paths, and its docstring names the
function it mirrors (``tests/test_compiled.py`` holds them together). Everything is float64
and unchecked: the callers check. A chain enters as the four
:attr:`~iiwa_torch.kinematics.Geometry.float_arrays` ``table, base, tool, modified``.
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["end_pose", "into_limits", "jacobian", "lm_round", "pose_errors"]

_jit = numba.njit(cache=True, error_model="numpy")
_inline = numba.njit(cache=True, error_model="numpy", inline="always")  # no call overhead in the LM loop


# ---------------------------------------------------------------------- kinematics
@_jit
def _frames(table, base, tool, modified, q, pose, Z, P):
    """``q (n,)`` -> the end pose (tool included) into ``pose (4, 4)`` and, if ``Z`` has ``n``
    rows, joint i's axis into ``Z[i]`` and a point on it into ``P[i]`` (both ``(n, 3)``).
    Mirrors :func:`iiwa_torch.kinematics._frames_floats` (the frame recursion in Python floats),
    which skips zero lengths and an identity tool: adding those zero terms changes no value."""
    x0, x1, x2, y0, y1, y2 = base[0, 0], base[1, 0], base[2, 0], base[0, 1], base[1, 1], base[2, 1]
    z0, z1, z2, p0, p1, p2 = base[0, 2], base[1, 2], base[2, 2], base[0, 3], base[1, 3], base[2, 3]
    keep = Z.shape[0] > 0
    for i in range(table.shape[0]):
        a, ca, sa, d, offset = table[i, 0], table[i, 1], table[i, 2], table[i, 3], table[i, 4]
        if modified:  # A_i = Rx(alpha) Tx(a) Rz(theta) Tz(d)
            y0, y1, y2, z0, z1, z2 = (ca * y0 + sa * z0, ca * y1 + sa * z1, ca * y2 + sa * z2,
                                      ca * z0 - sa * y0, ca * z1 - sa * y1, ca * z2 - sa * y2)  # fmt: skip
            p0, p1, p2 = p0 + a * x0, p1 + a * x1, p2 + a * x2
        if keep:
            Z[i, 0], Z[i, 1], Z[i, 2], P[i, 0], P[i, 1], P[i, 2] = z0, z1, z2, p0, p1, p2
        c, s = math.cos(q[i] + offset), math.sin(q[i] + offset)
        x0, x1, x2, y0, y1, y2 = (c * x0 + s * y0, c * x1 + s * y1, c * x2 + s * y2,
                                  c * y0 - s * x0, c * y1 - s * x1, c * y2 - s * x2)  # fmt: skip
        p0, p1, p2 = p0 + d * z0, p1 + d * z1, p2 + d * z2
        if not modified:  # A_i = Rz(theta) Tz(d) Tx(a) Rx(alpha)
            p0, p1, p2 = p0 + a * x0, p1 + a * x1, p2 + a * x2
            y0, y1, y2, z0, z1, z2 = (ca * y0 + sa * z0, ca * y1 + sa * z1, ca * y2 + sa * z2,
                                      ca * z0 - sa * y0, ca * z1 - sa * y1, ca * z2 - sa * y2)  # fmt: skip
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
def _jacobian_columns(pose, Z, P, J):
    """Column i of ``J (6, n)``: ``[z_i x (p_e - p_i); z_i]``, from :func:`_frames`' axes.
    Mirrors :func:`iiwa_torch.kinematics.jacobian_floats`."""
    e0, e1, e2 = pose[0, 3], pose[1, 3], pose[2, 3]
    for i in range(Z.shape[0]):
        z0, z1, z2 = Z[i, 0], Z[i, 1], Z[i, 2]
        l0, l1, l2 = e0 - P[i, 0], e1 - P[i, 1], e2 - P[i, 2]
        J[0, i], J[1, i], J[2, i] = z1 * l2 - z2 * l1, z2 * l0 - z0 * l2, z0 * l1 - z1 * l0
        J[3, i], J[4, i], J[5, i] = z0, z1, z2


@_jit
def end_pose(table, base, tool, modified, q):
    """One configuration ``q (n,)`` -> its end pose ``(4, 4)``, as :func:`_frames`."""
    pose = np.empty((4, 4))
    _frames(table, base, tool, modified, q, pose, np.empty((0, 3)), np.empty((0, 3)))
    return pose


@_jit
def jacobian(table, base, tool, modified, q):
    """One configuration ``q (n,)`` -> its Jacobian ``(6, n)`` (linear rows first, world frame)."""
    n = table.shape[0]
    pose, Z, P, J = np.empty((4, 4)), np.empty((n, 3)), np.empty((n, 3)), np.empty((6, n))
    _frames(table, base, tool, modified, q, pose, Z, P)
    _jacobian_columns(pose, Z, P, J)
    return J


@_jit
def _pose_error(pose, pos, rot, has_rot, eps, e):
    """End pose ``(4, 4)`` against a target position ``pos (3,)`` and rotation ``rot (3, 3)``
    -> the position error into ``e[:3]`` (target - pose, m), the rotation vector
    ``log(rot R^T)`` into ``e[3:6]`` (if ``has_rot``), and their norms ``(pos_err, rot_err)``.
    Mirrors :func:`iiwa_torch.ik.small.pose_errors`."""
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
    Mirrors :meth:`iiwa_torch.ik.small._Problems.evaluate`."""
    table, base, tool, modified = arrays
    pose, Z, P, J6 = scratch
    _frames(table, base, tool, modified, q, pose, Z, P)
    _jacobian_columns(pose, Z, P, J6)
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
    limit around the circle. Mirrors :func:`iiwa_torch.ik.gradient.into_limits`."""
    turn = 2 * math.pi
    turned = lo + (x - lo) % turn  # Python's float remainder: fmod, then the divisor's sign, as torch's
    if lo <= x <= hi:
        return x
    if turned <= hi:
        return turned
    return hi if turned - hi <= lo + turn - turned else lo


@_inline
def _lm_step(arrays, q, J, e, E, pos_err, rot_err, lam, pos, rot, has_rot, rest, opts, limits, lo, hi, work):
    """One LM step of one slot, in place on its ``q (n,)``, ``J (m, n)``, ``e (m,)``; returns the
    new ``E``, position and rotation errors and damping (the old ones but the damping if the
    step is rejected). ``opts``: weight, rest gain, eps, lam_min, LAMBDA0, DAMP_DOWN, DAMP_UP.
    Mirrors :meth:`iiwa_torch.ik.small._Problems.step`: ``J diag(free) J^T + lam I`` solved by
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
    for j in range(m):  # Cholesky A = L L^T in the lower triangle, then L L^T y = rhs
        for c in range(j):
            A[j, j] -= A[j, c] * A[j, c]
        A[j, j] = math.sqrt(max(A[j, j], lam_min))
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
def lm_round(table, base, tool, modified, q, problem, number, pos, rot, rest, lo, hi, opts, counts,
             best_q, best_E, used):  # fmt: skip
    """The LM iterations of one round of seeds ``q (s, n)`` (in place), slot ``k`` a seed of
    problem ``problem[k]`` with seed number ``number[k]``; targets ``pos (b, 3)``, ``rot (b, 3, 3)``
    (0 rows: position only), ``rest (b, n)`` (0 rows: none), inner limits ``lo, hi (n,)``;
    ``opts`` as :func:`_lm_step` then pos_tol, rot_tol; ``counts`` iterations, check_every,
    free_steps, seeds. Records each problem's best slot in ``best_q (b, n)``, its key
    ``best_E (b,)`` and iterations ``used (b,)``, in place.
    Mirrors :meth:`iiwa_torch.ik.small._Problems.run_round` and its ``check``."""
    arrays = (table, base, tool, modified)
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
