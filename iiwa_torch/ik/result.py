"""The result type every IK solver returns, gradient-based or analytic, and how the gradient-based
ones score an answer (:func:`ik_result`)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .. import so3

__all__ = ["IKResult", "ik_result"]


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
