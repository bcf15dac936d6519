"""Obstacle worlds: a floor, walls (half-spaces), spheres, boxes and capsules, each kind with an
optional leading batch shape (one set per environment)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import Tensor

from ..checks import check_finite, check_float_tensor, check_nonnegative, is_number
from ..so3 import check_rigid
from .capsules import Capsules

__all__ = ["MAX_EXTENT", "World", "check_world"]

#: Largest coordinate, size or offset (m) a World takes: far enough for any arm, near enough that
#: squared distances stay finite in float32 (beyond ~1e19 m they overflow to inf).
MAX_EXTENT = 1e6
# each kind's per-obstacle dims after M: (first tensor, second tensor)
_OBSTACLE_DIMS = {"walls": ((3,), ()), "spheres": ((3,), ()), "boxes": ((4, 4), (3,)), "capsules": ((2, 3), ())}


@dataclass(frozen=True)
class World:
    """Obstacles, each kind with an optional leading batch shape (one set per environment).

    Args:
        floor: height (m) of the floor half-space ``z <= floor``, or ``None``.
        walls: ``(normals (..., W, 3) unit, offsets (..., W))``: free space is ``n . x >= offset``.
        spheres: ``(centres (..., S, 3), radii (..., S))``.
        boxes: ``(poses (..., B, 4, 4) rigid, half_extents (..., B, 3))``.
        capsules: ``(points (..., C, 2, 3), radii (..., C))``.

    Tensors share one float dtype and device, their batch shapes broadcast with the queried
    configurations', and every value is within :data:`MAX_EXTENT`.
    """

    floor: float | None = 0.0
    walls: tuple[Tensor, Tensor] | None = None
    spheres: tuple[Tensor, Tensor] | None = None
    boxes: tuple[Tensor, Tensor] | None = None
    capsules: tuple[Tensor, Tensor] | None = None

    def __post_init__(self) -> None:
        if self.floor is not None:
            if not (is_number(self.floor) and abs(self.floor) <= MAX_EXTENT):
                raise ValueError(f"floor must be a height in metres within {MAX_EXTENT:g} or None, got {self.floor!r}")
            object.__setattr__(self, "floor", float(self.floor))  # a numpy scalar, in Python's float
        first = None
        for kind, pair in self._kinds():
            shape_a, shape_b = _OBSTACLE_DIMS[kind]
            if not isinstance(pair, tuple) or len(pair) != 2:
                raise TypeError(f"{kind} must be a tuple of two tensors, got {type(pair).__name__}")
            a, b = pair
            label_a, label_b = f"{kind}[0]", f"{kind}[1]"
            check_float_tensor(a, label_a, f"(..., M, {', '.join(map(str, shape_a))})")
            check_float_tensor(b, label_b, f"(..., M{''.join(', ' + str(s) for s in shape_b)})")
            lead = a.ndim - len(shape_a)
            if lead < 1 or tuple(a.shape[lead:]) != shape_a:
                raise ValueError(f"{label_a} must have shape (..., M, {shape_a}), got {tuple(a.shape)}")
            want_b = tuple(a.shape[:lead]) + shape_b
            if tuple(b.shape) != want_b:
                raise ValueError(f"{label_b} must have shape {want_b} to match {label_a}, got {tuple(b.shape)}")
            for t, label in ((a, label_a), (b, label_b)):
                if first is None:
                    first = t
                if t.dtype != first.dtype or t.device != first.device:
                    raise TypeError(f"{label} is {t.dtype} on {t.device} but other obstacles are "
                                    f"{first.dtype} on {first.device}")
                check_finite(t, label)
                if t.numel() and float(t.detach().abs().amax()) > MAX_EXTENT:
                    raise ValueError(f"{label} must be within {MAX_EXTENT:g} m, got {float(t.abs().amax()):g}")
        self._check_values()

    def _check_values(self) -> None:
        if self.walls is not None:
            norm = self.walls[0].norm(dim=-1)
            if not torch.allclose(norm, torch.ones_like(norm), atol=1e-5):
                raise ValueError(f"walls[0] normals must be unit vectors, got norms {norm.flatten()[:8].tolist()}")
        for kind, sizes in (("spheres", "radii"), ("capsules", "radii"), ("boxes", "half extents")):
            pair = getattr(self, kind)
            if pair is not None and not (pair[1] > 0).all():
                raise ValueError(f"{kind}[1] {sizes} must be positive, got min {pair[1].min().item()}")
        if self.boxes is not None:
            check_rigid(self.boxes[0], "boxes[0]", exact_bottom_row=True)

    def tensors(self) -> list[Tensor]:
        """Every obstacle tensor (for dtype/device checks and moving)."""
        return [t for _, pair in self._kinds() for t in pair]

    @property
    def batch_shape(self) -> torch.Size:
        """The broadcast leading batch shape of the obstacles (``()`` for one shared set)."""
        shapes = [a.shape[: a.ndim - len(_OBSTACLE_DIMS[kind][0]) - 1] for kind, (a, _) in self._kinds()]
        return torch.broadcast_shapes(*shapes) if shapes else torch.Size()

    def check_batch(self, batch: torch.Size, what: str = "targets") -> None:
        """Raise ``ValueError`` unless :attr:`batch_shape` broadcasts to ``batch`` without enlarging it."""
        try:
            fits = torch.broadcast_shapes(self.batch_shape, batch) == batch
        except RuntimeError:
            fits = False
        if not fits:
            raise ValueError(f"the world's batch shape {tuple(self.batch_shape)} must broadcast to the {what}' "
                             f"{tuple(batch)}")

    def map_batch(self, fn) -> World:
        """A world with ``fn(t, k)`` applied to every obstacle tensor ``t``, whose dims before the last
        ``k`` (``M`` and each obstacle's own) are the batch ``fn`` may reshape, expand or index."""
        changed = {
            kind: tuple(fn(t, 1 + len(dims)) for t, dims in zip(pair, _OBSTACLE_DIMS[kind]))
            for kind, pair in self._kinds()
        }
        return dataclasses.replace(self, **changed)

    def _kinds(self) -> list[tuple[str, tuple[Tensor, Tensor]]]:
        return [(kind, getattr(self, kind)) for kind in _OBSTACLE_DIMS if getattr(self, kind) is not None]


def check_world(world: World | None, margin: float, capsules: Capsules | None = None) -> None:
    """Check a solver's ``world`` (a :class:`World` or None), ``margin`` (m, >= 0) and ``capsules``,
    the last two only with a world."""
    if world is not None and not isinstance(world, World):
        raise TypeError(f"world must be an iiwa_torch.collision.World or None, got {type(world).__name__}")
    if capsules is not None and not isinstance(capsules, Capsules):
        raise TypeError(f"capsules must be an iiwa_torch.collision.Capsules or None, got {type(capsules).__name__}")
    check_nonnegative(margin, "margin")
    if world is None and (margin != 0 or capsules is not None):
        raise ValueError("margin and capsules apply to a world: pass world=World(...) (World() is the floor at z = 0)")
