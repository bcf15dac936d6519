"""The result type every IK solver returns, gradient-based or analytic."""

from __future__ import annotations

from dataclasses import dataclass

import torch


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
