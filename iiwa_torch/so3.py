"""Batched, differentiable rotation maths: quaternions, SO(3) log/exp, roll-pitch-yaw, pose error.

Rotations ``(..., 3, 3)``, quaternions ``(..., 4)`` as ``(w, x, y, z)`` with ``w >= 0``, rotation
vectors ``(..., 3)`` (axis times angle, rad), poses ``(..., 4, 4)``.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .checks import all_finite, broadcast_shapes, check_finite, check_tensor

__all__ = [
    "skew",
    "exp",
    "log",
    "matrix_to_quaternion",
    "quaternion_to_matrix",
    "matrix_to_rpy",
    "rpy_to_matrix",
    "pose_error",
    "check_pose",
    "check_rigid",
    "check_rotation",
    "RIGID_TOL",
]


def skew(v: torch.Tensor) -> torch.Tensor:
    """``(..., 3) -> (..., 3, 3)`` cross-product matrix, ``skew(a) @ b == a x b``."""
    check_tensor(v, "v", (3,))
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).unflatten(-1, (3, 3))


def exp(rotvec: torch.Tensor) -> torch.Tensor:
    """Rotation vector ``(..., 3)`` (rad) -> rotation ``(..., 3, 3)`` (Rodrigues; Taylor series near zero
    keep values and gradients finite). ValueError if the squared norm overflows."""
    check_tensor(rotvec, "rotvec", (3,))
    theta2 = (rotvec * rotvec).sum(-1, keepdim=True)[..., None]  # (..., 1, 1)
    if not all_finite(theta2):
        raise ValueError(f"rotvec's squared norm overflows {rotvec.dtype}: its angle has no meaning, got "
                         f"max |rotvec| {float(rotvec.detach().abs().amax()):g} rad")  # fmt: skip
    small = theta2 < 1e-8
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    safe = safe2.sqrt()
    a = torch.where(small, 1 - theta2 / 6, torch.sin(safe) / safe)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(safe)) / safe2)
    k = skew(rotvec)
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device)
    return eye + a * k + b * (k @ k)


def matrix_to_quaternion(rot: torch.Tensor) -> torch.Tensor:
    """Rotation ``(..., 3, 3)`` -> unit quaternion ``(..., 4)``, ``w >= 0``; Shepperd's method (the
    largest component from the diagonal), accurate near a half turn too."""
    check_tensor(rot, "rot", (3, 3))
    return _quaternion_of(rot)


def _quaternion_of(rot: torch.Tensor) -> torch.Tensor:
    m = rot.unbind(-1)  # columns
    m00, m10, m20 = m[0].unbind(-1)
    m01, m11, m21 = m[1].unbind(-1)
    m02, m12, m22 = m[2].unbind(-1)
    # 4 * component^2 for w, x, y, z from the diagonal
    four_sq = torch.stack(
        [
            1 + m00 + m11 + m22,
            1 + m00 - m11 - m22,
            1 - m00 + m11 - m22,
            1 - m00 - m11 + m22,
        ],
        -1,
    )  # (..., 4)
    # Row k: 4 * component_k * (w, x, y, z), built from the off-diagonal terms.
    rows = torch.stack(
        [
            torch.stack([four_sq[..., 0], m21 - m12, m02 - m20, m10 - m01], -1),
            torch.stack([m21 - m12, four_sq[..., 1], m10 + m01, m02 + m20], -1),
            torch.stack([m02 - m20, m10 + m01, four_sq[..., 2], m21 + m12], -1),
            torch.stack([m10 - m01, m02 + m20, m21 + m12, four_sq[..., 3]], -1),
        ],
        -2,
    )  # (..., 4, 4)
    best = four_sq.argmax(-1, keepdim=True)  # (..., 1)
    row = rows.gather(-2, best[..., None].expand(*best.shape[:-1], 1, 4)).squeeze(-2)
    scale = 2 * four_sq.gather(-1, best).clamp_min(1e-30).sqrt()  # 4 * |component|
    quat = row / scale
    return torch.where(quat[..., :1] < 0, -quat, quat)


def quaternion_to_matrix(quat: torch.Tensor) -> torch.Tensor:
    """Quaternion ``(..., 4)``, ``(w, x, y, z)``, not zero, normalised here -> rotation ``(..., 3, 3)``."""
    check_tensor(quat, "quat", (4,))
    norm = quat.norm(dim=-1, keepdim=True)
    if quat.numel() and not bool((norm > 0).all()):
        raise ValueError("quat must not be zero (it is normalised)")
    w, x, y, z = (quat / norm).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        -1,
    ).unflatten(-1, (3, 3))


def log(rot: torch.Tensor) -> torch.Tensor:
    """Rotation ``(..., 3, 3)`` (:func:`check_rotation`) -> rotation vector ``(..., 3)``, angle in ``[0, pi]``;
    through the quaternion, so stable near the identity and near a half turn."""
    check_rotation(rot, "rot")
    return _log(rot)


def _log(rot: torch.Tensor) -> torch.Tensor:
    quat = _quaternion_of(rot)
    w, v = quat[..., :1], quat[..., 1:]
    vn2 = (v * v).sum(-1, keepdim=True)
    small = vn2 < 1e-12
    vn = torch.where(small, torch.ones_like(vn2), vn2).sqrt()
    # angle / |v| = 2 atan2(|v|, w) / |v|; for |v| -> 0 (w -> 1) it tends to 2 / w.
    factor = torch.where(small, 2 / w.clamp_min(1e-6), 2 * torch.atan2(vn, w) / vn)
    return factor * v


def matrix_to_rpy(rot: torch.Tensor) -> torch.Tensor:
    """Rotation ``(..., 3, 3)`` -> URDF's roll, pitch, yaw ``(..., 3)``, ``R = Rz(yaw) Ry(pitch) Rx(roll)``;
    roll 0 at gimbal lock (``cos(pitch) = 0`` exactly; near it the general formulas stay exact)."""
    check_tensor(rot, "rot", (3, 3))
    cos_pitch = torch.hypot(rot[..., 0, 0], rot[..., 1, 0])
    pitch = torch.atan2(-rot[..., 2, 0], cos_pitch)  # asin(-r20) loses digits near +-pi/2
    locked = cos_pitch == 0
    roll = torch.where(locked, torch.zeros_like(pitch), torch.atan2(rot[..., 2, 1], rot[..., 2, 2]))
    yaw = torch.where(
        locked,
        torch.atan2(-rot[..., 0, 1], rot[..., 1, 1]),
        torch.atan2(rot[..., 1, 0], rot[..., 0, 0]),
    )
    return torch.stack([roll, pitch, yaw], -1)


def rpy_to_matrix(rpy: torch.Tensor) -> torch.Tensor:
    """Roll, pitch, yaw ``(..., 3)`` (radians) -> ``Rz(yaw) Ry(pitch) Rx(roll)`` ``(..., 3, 3)``."""
    check_tensor(rpy, "rpy", (3,))
    cr, cp, cy = torch.cos(rpy).unbind(-1)
    sr, sp, sy = torch.sin(rpy).unbind(-1)
    return torch.stack(
        [
            cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr,
            sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr,
            -sp, cp * sr, cp * cr,
        ],
        -1,
    ).unflatten(-1, (3, 3))


def check_pose(pose: torch.Tensor, name: str = "pose") -> None:
    """Raise ``TypeError``/``ValueError`` unless ``pose`` is a finite float ``(..., 4, 4)`` tensor."""
    check_tensor(pose, name, (4, 4))


def check_rotation(rot: torch.Tensor, name: str = "rot") -> None:
    """Raise ``TypeError``/``ValueError`` unless ``rot`` is a finite float ``(..., 3, 3)`` batch of
    rotations, within :func:`check_rigid`'s tolerance."""
    check_tensor(rot, name, (3, 3))
    pose = torch.nn.functional.pad(rot.detach(), (0, 1, 0, 1))  # (..., 4, 4), bottom row 0 0 0 0
    pose[..., 3, 3] = 1.0
    check_rigid(pose, name, rotation_only=True)


#: Largest deviation a pose may have from a rigid transform, per dtype (see :func:`check_rigid`).
RIGID_TOL = {torch.float64: 1e-6, torch.float32: 1e-5}


_RIGID_NUMPY_BATCH = 256  # up to this many CPU poses check_rigid computes in numpy (benchmarks/results/paths.md)


def _rigid_numpy(pose: np.ndarray, tol: float) -> bool:
    """Whether ``pose (b, 4, 4)`` is finite and passes :func:`check_rigid`'s test within ``tol``, in numpy
    (one pose in Python floats: a NaN or inf makes the sum of its entries NaN or inf)."""
    if pose.shape[0] == 1:
        values = pose.reshape(16).tolist()
        a, b, c, _, d, e, f, _, g, h, k, _, w0, w1, w2, w3 = values
        gram = (a * a + d * d + g * g - 1, b * b + e * e + h * h - 1, c * c + f * f + k * k - 1,
                a * b + d * e + g * h, a * c + d * f + g * k, b * c + e * f + h * k)  # fmt: skip
        det = a * (e * k - f * h) - b * (d * k - f * g) + c * (d * h - e * g)
        deviation = max(max(map(abs, gram)), abs(w0), abs(w1), abs(w2), abs(w3 - 1))
        return math.isfinite(sum(values)) and det > 0 and deviation <= tol
    R = pose[:, :3, :3]
    gram = np.abs(R.transpose(0, 2, 1) @ R - np.eye(3)).max()
    bottom = np.abs(pose[:, 3] - np.array([0.0, 0.0, 0.0, 1.0])).max()
    return bool(np.isfinite(pose).all() and (np.linalg.det(R) > 0).all() and max(gram, bottom) <= tol)


def check_rigid(pose: torch.Tensor, name: str = "pose", exact_bottom_row: bool = False, *,
                rotation_only: bool = False) -> None:
    """Raise ``TypeError``/``ValueError`` unless ``pose`` is a finite float ``(..., 4, 4)`` batch of rigid
    transforms: ``|R^T R - I| <= tol`` entrywise, ``det R > 0``, bottom row ``[0, 0, 0, 1]`` within
    ``tol`` (exactly if ``exact_bottom_row``), ``tol = RIGID_TOL[dtype]``. ``rotation_only``: the message
    speaks of the rotations alone (:func:`check_rotation`'s padded input)."""
    check_tensor(pose, name, (4, 4), finite=False)
    if pose.numel() == 0:
        return
    tol = RIGID_TOL.get(pose.dtype, RIGID_TOL[torch.float32])
    if pose.device.type == "cpu" and pose.numel() <= 16 * _RIGID_NUMPY_BATCH and not exact_bottom_row:
        try:
            if _rigid_numpy(pose.detach().numpy().reshape(-1, 4, 4), tol):
                return  # else the checks below find the culprit for the message
        except RuntimeError:  # no storage to read (torch.func.vmap): check_finite says so
            pass
    check_finite(pose, name)
    last = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=pose.dtype, device=pose.device)
    if exact_bottom_row and not bool((pose[..., 3, :] == last).all()):
        bad = (pose[..., 3, :] != last).any(-1).nonzero()[0].tolist()
        raise ValueError(f"{name}'s bottom row must be exactly [0, 0, 0, 1], got {pose[(*bad, 3)].tolist()}")
    R = pose[..., :3, :3]
    eye = torch.eye(3, dtype=pose.dtype, device=pose.device)
    gram = R.mT @ R - eye
    c0, c1, c2 = R.unbind(-1)
    det = (torch.linalg.cross(c0, c1) * c2).sum(-1)
    worst = torch.maximum(gram.abs().amax((-2, -1)), (pose[..., 3, :] - last).abs().amax(-1))
    worst = torch.where(det > 0, worst, torch.inf).detach()
    if float(worst.max()) <= tol:
        return
    index = tuple((worst > tol).nonzero()[0].tolist())
    what = ("a rotation", "rotations") if rotation_only else ("a rigid transform", "rigid transforms")
    what, where = (what[0], name) if pose.dim() == 2 else (what[1], f"{name}[{index}]")
    rule, bottom = ("", "") if rotation_only else (
        ", bottom row [0, 0, 0, 1]", f", bottom row {pose[index][3].tolist()}"
    )
    raise ValueError(
        f"{name} must be {what} (orthonormal with det +1{rule}, within {tol:g}); {where} has max "
        f"|R^T R - I| = {float(gram[index].abs().max()):.3g}, det R = {float(det[index]):.6g}{bottom}"
    )


def pose_error(pose: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The error taking rigid ``pose`` to ``target`` ``(..., 4, 4)``, in the base frame: ``target_p - pose_p``
    (m) and ``log(target_R pose_R^T)`` (rad), each ``(..., 3)``, so that ``J dq ~ (pos_err, rot_err)``."""
    check_rigid(pose, "pose")
    check_rigid(target, "target")
    broadcast_shapes({"pose": pose.shape, "target": target.shape})
    if pose.dtype != target.dtype or pose.device != target.device:
        raise ValueError(
            f"pose and target must share dtype and device, got {pose.dtype}/{pose.device} "
            f"and {target.dtype}/{target.device}"
        )
    pos_err = target[..., :3, 3] - pose[..., :3, 3]
    rot = target[..., :3, :3] @ pose[..., :3, :3].transpose(-1, -2)
    rot_err = _log(rot)
    return pos_err, rot_err
