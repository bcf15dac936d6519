"""Compiled Levenberg-Marquardt rounds of :func:`iiwa_torch.ik.solve` (the small-batch path of
:mod:`iiwa_torch.ik.lm_compiled`), one slot at a time."""

from __future__ import annotations

import math

import numpy as np

from .decorators import inline, jit
from .kinematics_kernels import frames_of, jacobian_columns, pose_error

__all__ = ["cholesky_solve", "into_limits", "lm_rounds"]

@inline
def _evaluate(arrays, q, pos, rot, has_rot, weight, eps, scratch, J, e):
    """``q (n,)`` -> weighted Jacobian into ``J (m, n)``, weighted error into ``e (m,)`` (m = 6, or 3 without
    ``has_rot``); returns (squared weighted error, pos_err, rot_err). :mod:`iiwa_torch.ik.lm`'s ``_evaluate``."""
    transforms, params, base, tool = arrays
    pose, Z, P, J6 = scratch
    frames_of(transforms, params, base, tool, q, pose, Z, P, np.empty((0, 4, 3)))
    jacobian_columns(params, pose, Z, P, J6)
    pos_err, rot_err = pose_error(pose, pos, rot, has_rot, eps, e)
    m, n = J.shape
    for r in range(m):
        for i in range(n):
            J[r, i] = J6[r, i] * weight if r >= 3 else J6[r, i]
    if not has_rot:
        return pos_err * pos_err, pos_err, rot_err
    for r in range(3, 6):
        e[r] *= weight
    return pos_err * pos_err + (weight * rot_err) ** 2, pos_err, rot_err


@jit
def into_limits(x, lo, hi):
    """One angle into ``[lo, hi]``, as :func:`iiwa_torch.ik.lm_setup.into_limits`."""
    turn = 2 * math.pi
    turned = lo + (x - lo) % turn  # Python's float remainder: fmod, then the divisor's sign, as torch's
    if lo <= x <= hi:
        return x
    if turned <= hi:
        return turned
    return hi if turned - hi <= lo + turn - turned else lo


@inline
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


@inline
def _lm_step(arrays, q, J, e, E, pos_err, rot_err, lam, pos, rot, has_rot, rest, opts, limits, lo, hi, work):
    """One LM step of one slot (:mod:`iiwa_torch.ik.lm`'s ``_lm_step``), in place on ``q (n,)``, ``J (m, n)``,
    ``e (m,)``; returns the new ``E``, pos_err, rot_err and damping (the old ones if rejected). ``opts``: weight,
    rest gain, eps, lam_min, then :class:`~iiwa_torch.ik.options.SolveOptions`' damping, damping_down, damping_up."""
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


@inline
def _rank_slots(q, problem, number, status, key, done, lowest, used, lo, hi, step, checked, bounds):
    """The check after ``step`` (:mod:`iiwa_torch.ik.lm`'s ``_check_slots``): each active slot's key (converged
    slots below every error, lowest seed number first) into ``key``, converged into ``done``, each problem's lowest
    key into ``lowest``, iterations since the last check into ``used``. ``status``: E, pos_err, rot_err, active
    ``(s,)``; ``bounds``: free_steps, seeds, pos_tol, rot_tol."""
    E, pos_err, rot_err, active = status
    free_steps, seeds, pos_tol, rot_tol = bounds
    for k in range(q.shape[0]):
        if not active[k]:
            continue
        used[problem[k]] += step + 1 - checked
        done[k] = pos_err[k] <= 0.5 * pos_tol and rot_err[k] <= 0.5 * rot_tol
        Ek = E[k]
        if step < free_steps:  # only the unconstrained start can leave the limits
            inside = True
            for i in range(q.shape[1]):
                inside = inside and lo[i] <= q[k, i] <= hi[i]
            done[k] = done[k] and inside
            Ek = Ek if inside else np.inf
        key[k] = number[k] - seeds if done[k] else Ek
        lowest[problem[k]] = min(lowest[problem[k]], key[k])


@inline
def _record_slots(q, problem, number, active, key, done, lowest, winner, best_q, best_E, seeds):
    """After :func:`_rank_slots`: each problem's best slot into ``best_q``, ``lowest`` into ``best_E``,
    and the slots that stop (converged, or a lower seed number of their problem did) marked
    inactive; returns how many stopped."""
    winner[:] = -1
    for k in range(q.shape[0]):
        p = problem[k]
        if active[k] and key[k] <= lowest[p] and key[k] < best_E[p]:
            winner[p] = k
    for p in range(best_E.shape[0]):
        if winner[p] >= 0:
            best_q[p] = q[winner[p]]
    best_E[:] = lowest
    stopped = 0
    for k in range(q.shape[0]):
        if active[k]:
            first_done = lowest[problem[k]] + seeds if lowest[problem[k]] < 0 else seeds
            active[k] = not done[k] and number[k] < first_done
            stopped += not active[k]
    return stopped


@jit
def _lm_round(transforms, params, base, tool, q, problem, number, pos, rot, rest, lo, hi, opts, counts,
             best_q, best_E, used):  # fmt: skip
    """The LM iterations of one round of seeds ``q (s, n)`` (in place), slot ``k`` a seed of
    problem ``problem[k]`` with seed number ``number[k]``; targets ``pos (b, 3)``, ``rot (b, 3, 3)``
    (0 rows: position only), ``rest (b, n)`` (0 rows: none), inner limits ``lo, hi (n,)``;
    ``opts`` as :func:`_lm_step` then pos_tol, rot_tol; ``counts`` iterations, check_every,
    free_steps, seeds. Records each problem's best slot in ``best_q (b, n)``, its key
    ``best_E (b,)`` and iterations ``used (b,)``, in place.
    The torch loop's ``_run_round`` (:mod:`iiwa_torch.ik.lm`)."""
    arrays = (transforms, params, base, tool)
    iterations, check_every, free_steps, seeds = counts[0], counts[1], counts[2], counts[3]
    weight, eps, lam_min, lambda0 = opts[0], opts[2], opts[3], opts[4]
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
                                                             lam[k], tp, tr, has_rot, tq, step_opts,
                                                             step >= free_steps, lo, hi, work)  # fmt: skip
        if (step + 1) % check_every and step + 1 < iterations:
            continue
        lowest[:] = best_E
        _rank_slots(q, problem, number, (E, pos_err, rot_err, active), key, done, lowest, used, lo, hi, step, checked,
                    (free_steps, seeds, opts[7], opts[8]))  # fmt: skip
        checked = step + 1
        left -= _record_slots(q, problem, number, active, key, done, lowest, winner, best_q, best_E, seeds)
        if not left:
            break


@jit
def lm_rounds(transforms, params, base, tool, pool, order, first, pos, rot, rest, lo, hi, opts, counts, best_q, best_E,
              used):  # fmt: skip
    """Every round of seeds of ``b = best_q.shape[0]`` problems, one seed per problem a round:
    ``first (b, n)`` (q0; 0 rows: none), then the pool ``(P, n)`` entries of ranks ``order (ranks, b)``,
    until a problem converges or runs out of its ``counts[3]`` seeds; the rest as :func:`_lm_round`.
    The torch loop's ``_run_rounds`` (:mod:`iiwa_torch.ik.lm`) with rounds one seed wide."""
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
        _lm_round(transforms, params, base, tool, q, remaining, np.full(s, k), pos, rot, rest, lo, hi, opts, counts,
                 best_q, best_E, used)  # fmt: skip
        remaining = remaining[best_E[remaining] >= 0]

