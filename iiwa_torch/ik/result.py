"""The result type every IK solver returns, gradient-based or analytic, and how the gradient-based
ones score an answer (:func:`ik_result`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .. import compiled, so3
from ..kinematics import Geometry

__all__ = ["IKResult", "ik_result", "ik_result_compiled"]


@dataclass(frozen=True)
class IKResult:
    """Solutions of a batch of IK problems with leading shape ``(...)``.

    Attributes:
        q: ``(..., n)`` joint angles (radians), always within the chain's joint limits.
        success: ``(...)`` bool, both errors below the tolerances the caller set.
        pos_err: ``(...)`` position error norm of ``fk(q)`` against the target (metres).
        rot_err: ``(...)`` rotation error angle (radians); 0 for position-only problems.
        iterations: ``(...)`` int64, iterations spent on each problem (0 for closed forms).
        clearance: ``(...)`` minimum signed clearance of ``q`` (metres) when a world was given, else None.
    """

    q: torch.Tensor
    success: torch.Tensor
    pos_err: torch.Tensor
    rot_err: torch.Tensor
    iterations: torch.Tensor
    clearance: torch.Tensor | None = None


def ik_result(chain, q: torch.Tensor, target: torch.Tensor, mode: str, pos_tol: float, rot_tol: float,
              iterations: torch.Tensor) -> IKResult:
    """Errors and success from the public ``chain.fk`` of the answer ``q (..., n)`` against
    ``target`` (poses or positions, per ``mode``), tolerances in metres and radians."""
    pose = chain.fk(q)
    if mode == "pose":
        pos_vec, rot_vec = so3.pose_error(pose, target)
        rot_err = rot_vec.norm(dim=-1)
    else:
        pos_vec = target - pose[..., :3, 3]
        rot_err = torch.zeros_like(pos_vec[..., 0])
    pos_err = pos_vec.norm(dim=-1)
    success = (pos_err <= pos_tol) & (rot_err <= rot_tol)
    return IKResult(q=q, success=success, pos_err=pos_err, rot_err=rot_err, iterations=iterations)


def ik_result_compiled(g: Geometry, q: np.ndarray, pos: np.ndarray, rot: np.ndarray | None, eps: float, pos_tol: float,
                       rot_tol: float, batch: torch.Size, iterations: np.ndarray) -> IKResult:
    """:func:`ik_result` in one compiled call, for answers ``q (b, n)`` float64 on the CPU: ``g`` the
    chain's geometry in the targets' dtype (float32: ``q`` and the errors rounded to it, the pose
    as ``chain.fk`` returns it), targets ``pos (b, 3)``, ``rot (b, 3, 3)`` (None: positions) float64,
    ``eps`` the rotation log's floor, ``iterations (b,)`` int64; the fields shaped ``batch``."""
    single = g.base.dtype == torch.float32
    if single:
        q = q.astype(np.float32).astype(np.float64)  # the float32 answer, scored as chain.fk scores it
    no_rot = np.empty((0, 3, 3))
    pos_err, rot_err, success = compiled.kernels().answer_errors(*g.float_arrays, q, pos, no_rot if rot is None
                                                                  else rot, eps, single, pos_tol, rot_tol)  # fmt: skip
    out = np.float32 if single else np.float64
    fields = (q.astype(out, copy=False).reshape(*batch, q.shape[1]), success.reshape(batch),
              pos_err.astype(out, copy=False).reshape(batch), rot_err.astype(out, copy=False).reshape(batch),
              iterations.reshape(batch))  # fmt: skip
    return IKResult(*map(torch.from_numpy, fields))
