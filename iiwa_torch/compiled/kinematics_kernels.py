"""Compiled forward kinematics, one configuration at a time: frames, Jacobian columns, pose error."""

from __future__ import annotations

import math

import numpy as np

from .decorators import inline, jit

__all__ = ["answer_errors", "apply_transform", "end_pose", "end_poses", "frames_axes", "frames_of", "jacobian",
           "jacobian_columns", "jacobians", "pose_error", "turn"]

@inline
def turn(u0, u1, u2, v0, v1, v2, c, s):
    """A frame's axis pair ``(u, v)`` turned by the angle of cosine ``c`` and sine ``s`` about the
    third axis: ``(c u + s v, c v - s u)``, 3 + 3 components (a joint's Rz, or a link's Rx)."""
    return c * u0 + s * v0, c * u1 + s * v1, c * u2 + s * v2, c * v0 - s * u0, c * v1 - s * u1, c * v2 - s * u2


@inline
def _store_frame(f, x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2):  # axes and origin into the rows of f (4, 3)
    f[0, 0], f[0, 1], f[0, 2], f[1, 0], f[1, 1], f[1, 2] = x0, x1, x2, y0, y1, y2
    f[2, 0], f[2, 1], f[2, 2], f[3, 0], f[3, 1], f[3, 2] = z0, z1, z2, p0, p1, p2


@inline
def apply_transform(T, x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2):
    """A frame (axes x, y, z and origin p) times the constant transform ``T (4, 4)``."""
    c00, c10, c20, c01, c11, c21 = T[0, 0], T[1, 0], T[2, 0], T[0, 1], T[1, 1], T[2, 1]
    c02, c12, c22, t0, t1, t2 = T[0, 2], T[1, 2], T[2, 2], T[0, 3], T[1, 3], T[2, 3]
    return (c00 * x0 + c10 * y0 + c20 * z0, c00 * x1 + c10 * y1 + c20 * z1, c00 * x2 + c10 * y2 + c20 * z2,
            c01 * x0 + c11 * y0 + c21 * z0, c01 * x1 + c11 * y1 + c21 * z1, c01 * x2 + c11 * y2 + c21 * z2,
            c02 * x0 + c12 * y0 + c22 * z0, c02 * x1 + c12 * y1 + c22 * z1, c02 * x2 + c12 * y2 + c22 * z2,
            p0 + (t0 * x0 + t1 * y0 + t2 * z0), p1 + (t0 * x1 + t1 * y1 + t2 * z1),
            p2 + (t0 * x2 + t1 * y2 + t2 * z2))  # grouped as the float path groups them: the same bits


@inline
def _joint(transforms, params, i, theta, x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2, Z, P):
    """Link frame ``i - 1`` -> link frame ``i`` through joint i at ``theta = q_i + offset_i``:
    ``before_i M(theta) after_i`` (identities skipped); joint i's axis into ``Z[i]`` and a point on
    it into ``P[i]`` if ``Z`` has rows."""
    if params[i, 2]:
        x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2 = apply_transform(transforms[i, 0], x0, x1, x2, y0, y1, y2,
                                                                         z0, z1, z2, p0, p1, p2)
    if Z.shape[0] > 0:
        Z[i, 0], Z[i, 1], Z[i, 2], P[i, 0], P[i, 1], P[i, 2] = z0, z1, z2, p0, p1, p2
    if params[i, 1]:  # prismatic: along z
        p0, p1, p2 = p0 + theta * z0, p1 + theta * z1, p2 + theta * z2
    else:
        x0, x1, x2, y0, y1, y2 = turn(x0, x1, x2, y0, y1, y2, math.cos(theta), math.sin(theta))
    if params[i, 3]:
        x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2 = apply_transform(transforms[i, 1], x0, x1, x2, y0, y1, y2,
                                                                         z0, z1, z2, p0, p1, p2)
    return x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2


@jit
def frames_of(transforms, params, base, tool, q, pose, Z, P, F):
    """:func:`iiwa_torch.kinematics.frames_batch_last`'s recursion in scalars: ``q (n,)`` -> the end pose (with tool)
    into ``pose (4, 4)``; if ``Z`` has ``n`` rows, joint i's axis into ``Z[i]`` and a point on it into ``P[i]``; if
    ``F`` has ``n + 1`` rows, the base and link frames (no tool) into ``F (n + 1, 4, 3)``: x, y, z axes and origin."""
    x0, x1, x2, y0, y1, y2 = base[0, 0], base[1, 0], base[2, 0], base[0, 1], base[1, 1], base[2, 1]
    z0, z1, z2, p0, p1, p2 = base[0, 2], base[1, 2], base[2, 2], base[0, 3], base[1, 3], base[2, 3]
    every = F.shape[0] > 0
    if every:
        _store_frame(F[0], x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2)
    for i in range(params.shape[0]):
        x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2 = _joint(transforms, params, i, q[i] + params[i, 0], x0, x1,
                                                                x2, y0, y1, y2, z0, z1, z2, p0, p1, p2, Z, P)
        if every:
            _store_frame(F[i + 1], x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2)
    for k in range(4):  # column k of the tool, (u, v, w), in the world: u x + v y + w z
        u, v, w = tool[0, k], tool[1, k], tool[2, k]
        pose[0, k], pose[1, k] = u * x0 + v * y0 + w * z0, u * x1 + v * y1 + w * z1
        pose[2, k], pose[3, k] = u * x2 + v * y2 + w * z2, 0.0
    pose[0, 3], pose[1, 3], pose[2, 3], pose[3, 3] = pose[0, 3] + p0, pose[1, 3] + p1, pose[2, 3] + p2, 1.0


@jit
def jacobian_columns(params, pose, Z, P, J):
    """Column i of ``J (6, n)``: ``[z_i x (p_e - p_i); z_i]`` (revolute) or ``[z_i; 0]`` (prismatic),
    from :func:`frames_of`' axes, as :func:`iiwa_torch.kinematics.jacobian` computes them."""
    e0, e1, e2 = pose[0, 3], pose[1, 3], pose[2, 3]
    for i in range(Z.shape[0]):
        z0, z1, z2 = Z[i, 0], Z[i, 1], Z[i, 2]
        if params[i, 1]:
            J[0, i], J[1, i], J[2, i], J[3, i], J[4, i], J[5, i] = z0, z1, z2, 0.0, 0.0, 0.0
            continue
        l0, l1, l2 = e0 - P[i, 0], e1 - P[i, 1], e2 - P[i, 2]
        J[0, i], J[1, i], J[2, i] = z1 * l2 - z2 * l1, z2 * l0 - z0 * l2, z0 * l1 - z1 * l0
        J[3, i], J[4, i], J[5, i] = z0, z1, z2


@jit
def end_pose(transforms, params, base, tool, q, out):
    """One configuration ``q`` (n floats: a tuple, or a row of an array) -> its end pose into ``out (4, 4)`` (float32
    or float64), as :func:`frames_of`; ``False``, ``out`` all NaN, if ``q`` is not finite."""
    for v in q:
        if not math.isfinite(v):
            out[:] = np.nan
            return False
    pose, none = np.empty((4, 4)), np.empty((0, 3))
    frames_of(transforms, params, base, tool, q, pose, none, none, np.empty((0, 4, 3)))
    out[:] = pose
    return True


@jit
def end_poses(transforms, params, base, tool, q, out):
    """Configurations ``q (b, n)`` -> their end poses into ``out (b, 4, 4)``, as :func:`end_pose`."""
    for k in range(q.shape[0]):
        end_pose(transforms, params, base, tool, q[k], out[k])


@jit
def frames_axes(transforms, params, base, tool, q):
    """Configurations ``q (b, n)`` -> frames ``(b, n + 1, 4, 3)``, joint axes and points on them ``(b, n, 3)`` each,
    end poses ``(b, 4, 4)``, as :func:`frames_of` writes them."""
    b, n = q.shape
    frames, z, p, poses = np.empty((b, n + 1, 4, 3)), np.empty((b, n, 3)), np.empty((b, n, 3)), np.empty((b, 4, 4))
    for k in range(b):
        frames_of(transforms, params, base, tool, q[k], poses[k], z[k], p[k], frames[k])
    return frames, z, p, poses


@jit
def jacobian(transforms, params, base, tool, q, out):
    """One configuration ``q`` (n floats: a tuple, or a row of an array) -> its Jacobian into ``out (6, n)`` (float32
    or float64; linear rows first, world frame); ``False``, ``out`` all NaN, if ``q`` is not finite."""
    for v in q:
        if not math.isfinite(v):
            out[:] = np.nan
            return False
    n = len(q)
    pose, Z, P = np.empty((4, 4)), np.empty((n, 3)), np.empty((n, 3))
    frames_of(transforms, params, base, tool, q, pose, Z, P, np.empty((0, 4, 3)))
    jacobian_columns(params, pose, Z, P, out)
    return True


@jit
def jacobians(transforms, params, base, tool, q, out):
    """Configurations ``q (b, n)`` -> their Jacobians into ``out (b, 6, n)``, as :func:`jacobian` (with one scratch
    for all: a fifth faster at 10,000)."""
    n = q.shape[1]
    pose, Z, P = np.empty((4, 4)), np.empty((n, 3)), np.empty((n, 3))
    for k in range(q.shape[0]):
        frames_of(transforms, params, base, tool, q[k], pose, Z, P, np.empty((0, 4, 3)))
        jacobian_columns(params, pose, Z, P, out[k])


@jit
def pose_error(pose, pos, rot, has_rot, eps, e):
    """:func:`iiwa_torch.so3.pose_error`: ``pose (4, 4)`` against ``pos (3,)``, ``rot (3, 3)`` -> target - pose (m) into
    ``e[:3]``, ``log(rot R^T)`` into ``e[3:6]`` (if ``has_rot``); returns their norms ``(pos_err, rot_err)``."""
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


@jit
def answer_errors(transforms, params, base, tool, q, pos, rot, eps, single, pos_tol, rot_tol):
    """Answers ``q (b, n)`` against ``pos (b, 3)``, ``rot (b, 3, 3)`` (0 rows: position only), as
    :func:`iiwa_torch.ik.result.ik_result` scores them (pose rounded to float32 if ``single``, as ``chain.fk``)
    -> position and rotation errors ``(b,)`` (m, rad) and success (within ``pos_tol``, ``rot_tol``)."""
    b, has_rot = q.shape[0], rot.shape[0] > 0
    pos_err, rot_err, success = np.empty(b), np.empty(b), np.empty(b, dtype=np.bool_)
    pose, e, none = np.empty((4, 4)), np.empty(6), np.empty((0, 3))
    for k in range(b):
        frames_of(transforms, params, base, tool, q[k], pose, none, none, np.empty((0, 4, 3)))
        if single:
            pose[:3] = pose[:3].astype(np.float32)
        target_rot = rot[k] if has_rot else pose[:3, :3]  # a placeholder without rotations
        pos_err[k], rot_err[k] = pose_error(pose, pos[k], target_rot, has_rot, eps, e)
        success[k] = pos_err[k] <= pos_tol and rot_err[k] <= rot_tol
    return pos_err, rot_err, success
