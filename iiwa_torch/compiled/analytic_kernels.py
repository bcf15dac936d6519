"""Compiled closed-form IK: the arm-angle sweep of :func:`iiwa_torch.ik.analytic.iiwa_solve` and the
8 branches of :func:`iiwa_torch.ik.analytic.pieper`."""

from __future__ import annotations

import math

import numpy as np

from .decorators import inline, jit

__all__ = ["iiwa_sweep", "pieper_branches"]

_TINY = 1e-30  # iiwa_torch.ik.analytic._common.TINY


@inline
def _safe_atan2(y, x):  # _common.safe_atan2
    return math.atan2(y, 1.0 if x * x + y * y < _TINY else x)


@inline
def _safe_norm2(x, y):  # _common.safe_norm2
    return math.sqrt(max(x * x + y * y, _TINY))


@inline
def _triangle(dist, a, b, tol):
    """:func:`iiwa_torch.ik.analytic._common.triangle`: the angle between sides ``a, b`` opposite ``dist`` ->
    ``(cos clamped to [-1, 1], |sin|, reachable)``."""
    c = (dist * dist - (a * a + b * b)) / (2 * a * b)
    outer, inner = a + b, abs(a - b)
    s2 = (outer - dist) * (outer + dist) * (dist - inner) * (dist + inner)
    return min(max(c, -1.0), 1.0), math.sqrt(max(s2, _TINY)) / (2 * a * b), abs(c) <= 1 + tol


@inline
def _zxzxz_ab(m02, m12, m22, sig_a, sig_b):
    """Branch 0's ``(a, b, cos a, sin a, cos b, sin b)`` of a spherical triple from column 2 of ``M`` (the flip:
    ``(a + pi, -b)``), as :func:`iiwa_torch.ik.analytic._common.decompose_zxzxz`."""
    sb = _safe_norm2(m02, m12)
    cb = -sig_a * sig_b * m22
    a = _safe_atan2(sig_b * m12, sig_b * m02)
    return a, math.atan2(sb, cb), math.cos(a), math.sin(a), cb, sb


@inline
def _zxzxz_c(ab, m00, m10, m20, sig_a, sig_b):
    """Branch 0's third angle ``c`` (the flip: ``c + pi``) from ``ab`` (:func:`_zxzxz_ab`) and column 0 of ``M``."""
    _, _, ca, sa, cb, sb = ab
    cos_c = cb * (ca * m00 + sa * m10) + sig_a * sb * m20
    sin_c = sig_a * sig_b * (sa * m00 - ca * m10)
    return _safe_atan2(sin_c, cos_c)


@inline
def _iiwa_pose(sw, d3, d5, sig, tol):
    """The psi-independent part of :func:`iiwa_torch.ik.analytic.srs.closed_form` (``_elbow``, ``_reference``) for
    ``W - S`` ``sw (3,)`` -> ``(dist, c4, s4_abs, both elbows' theta4, reachable, u, v_ref, w_ref[:2])``."""
    sx, sy, sz = sw[0], sw[1], sw[2]
    dist = _safe_norm2(_safe_norm2(sx, sy), sz)
    c, s4_abs, reachable = _triangle(dist, d3, d5, tol)
    c4 = -sig[2] * sig[3] * c
    ux, uy, uz = sx / dist, sy / dist, sz / dist
    b = _safe_atan2(uy, ux)
    cb, sb = math.cos(b), math.sin(b)
    theta4 = (math.atan2(s4_abs, c4), math.atan2(-s4_abs, c4))
    return dist, c4, s4_abs, theta4, reachable, (ux, uy, uz), (-uz * cb, -uz * sb, _safe_norm2(ux, uy)), (sb, -cb)


@inline
def _dot_col(r, rot, col):  # r . rot[:, col], summed left to right as srs.closed_form sums it
    return r[0] * rot[0, col] + r[1] * rot[1, col] + r[2] * rot[2, col]


@inline
def _iiwa_branches(pose, rot, psi, d3, d5, sig, theta):
    """:func:`iiwa_torch.ik.analytic.srs.closed_form`'s 8 branches at arm angle ``psi`` into ``theta (7, 4)``, each
    joint's distinct values only: branch ``(s, e, w)`` takes joints 1-2 from column ``s``, joint 3 from ``2 s + e``,
    joint 4 from ``e``, joints 5-7 from ``2 e + w``; ``pose`` from :func:`_iiwa_pose`."""
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


@inline
def _wrap_joint(theta, offset, lo, hi):
    """One DH angle -> ``(q, within)``, as :func:`iiwa_torch.ik.analytic._common.wrap_joints`."""
    turn = 2 * math.pi
    q = theta - offset if offset else theta
    q = q - turn * np.rint(q * (1 / turn))
    inside = lo <= q <= hi
    if not (hi > math.pi or lo < -math.pi):
        return q, inside
    turned = lo + (q - lo) % turn  # Python's float remainder, as np.remainder
    fits = turned <= hi
    return (q if inside or not fits else turned), inside or fits


@inline
def _iiwa_pick(rot, sw, psis, count, q0, has_q0, d3, d5, sig, tol, limits, single, work, best_q):
    """:func:`iiwa_torch.ik.analytic.srs_sweep._pick`: the best of one pose's ``count * 8`` candidates at arm angles
    ``psis[:count]`` into ``best_q (7,)``, clamped; returns ``(found, psi_best)``. ``limits (7, 7)``: offsets, lows,
    highs to check, mid-points, half-widths, limits to clamp into; ``single``: rank in float32; ``work``: ``(7, 4)``
    scratch. Sums of squares in ``_common.reduce_grouped``'s order (joint 4, then 1 + 2, 3, then 5 + 6 + 7)."""
    theta, q, inside, score = work
    pose = _iiwa_pose(sw, d3, d5, sig, tol)
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


@jit
def iiwa_sweep(rot, sw, q0, psi0, grid, local, fine_grid, fine_local, consts, limits, single):
    """:func:`iiwa_torch.ik.analytic.srs_sweep._solve_all` for ``rot (B, 3, 3)``, ``sw (B, 3)``, ``q0 (B, 7)`` and its
    arm angles ``psi0 (B,)`` (both 0 rows: none) -> ``q (B, 7)``: per pose the sweep over ``grid (K,)`` (after
    ``psi0``) and refining passes ``local (P, 9)``, then where nothing valid was found ``fine_grid``, ``fine_local``.
    ``consts``: ``d3, d5``, the six ``sin(alpha)``, the reach tolerance; ``limits`` as :func:`_iiwa_pick`."""
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
@jit
def pieper_branches(frame5, consts, limits):
    """The 8 branches of :func:`iiwa_torch.ik.analytic.pieper` (``spherical6r._closed_form``, ``_common.finish``) for
    ``frame5 = T_05 Rz(theta6) (B, 4, 4)``; ``consts``: ``a1, d1, a2, d2 + d3, L3 = |(a3, d4)|, gamma``, the
    ``sin(alpha)`` of rows 1, 3, 4, 5, the reach tolerance; ``limits (3, 6)``: offsets, lows, highs -> joint angles
    ``(6, B, 8)`` (joint-major), reachable and within limits ``(B, 8)``; branch ``4 shoulder + 2 elbow + wrist``."""
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
            c_el, s_el_abs, elbow_ok = _triangle(_safe_norm2(px, py), a2, link3, tol)
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

