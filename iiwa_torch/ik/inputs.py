"""Input checks both gradient-based solvers make: the target (:func:`check_target`) and the
world against it (:func:`check_world_for`)."""

from __future__ import annotations

import torch

from .. import so3
from ..checks import check_finite, check_float_tensor
from ..collision import check_world

__all__ = ["check_target", "check_world_for"]

Tensor = torch.Tensor


def check_target(target: Tensor, mode: str, dtype: torch.dtype | None, batch: torch.Size | None) -> torch.Size:
    """Validate a pose ``(..., 4, 4)`` or position ``(..., 3)`` target (of ``dtype`` and batch
    shape ``batch`` when they are given); return its batch shape."""
    if mode == "pose":
        if isinstance(target, torch.Tensor) and target.ndim and target.shape[-1] == 3:
            raise ValueError(
                f"target must have shape (..., 4, 4) (poses), got {tuple(target.shape)}; "
                'for positions (..., 3) pass mode="position"'
            )
        so3.check_rigid(target, "target")
        found = target.shape[:-2]
    else:
        check_float_tensor(target, "target", "(..., 3) in position mode")
        if target.ndim == 0 or target.shape[-1] != 3:
            raise ValueError(f"target must have shape (..., 3) in position mode, got {tuple(target.shape)}")
        check_finite(target, "target")
        found = target.shape[:-1]
    if dtype is not None and target.dtype != dtype:
        raise ValueError(f"target must have the dtype of q0 ({dtype}), got {target.dtype}")
    if batch is not None and found != batch:
        raise ValueError(f"target's batch shape {tuple(found)} must match q0's {tuple(batch)}")
    return found


def check_world_for(world, margin, target: Tensor, batch: torch.Size, capsules) -> None:
    """Validate a solver's ``world``, ``margin`` and ``capsules`` for ``target``:
    :func:`~iiwa_torch.collision.check_world`, then the target's dtype and device and a batch
    shape that broadcasts to the targets'."""
    check_world(world, margin, capsules)
    if world is None:
        return
    for t in world.tensors():
        if t.dtype != target.dtype or t.device != target.device:
            raise TypeError(
                f"world obstacles are {t.dtype} on {t.device} but the target is {target.dtype} on {target.device}; "
                "build the world in the target's dtype and device"
            )
    world.check_batch(batch)
