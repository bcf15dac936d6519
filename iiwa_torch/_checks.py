"""Input checks shared by the library: clear errors that name what was expected and what came."""

from __future__ import annotations

import math

import numpy as np
import torch


def all_finite(x: torch.Tensor | np.ndarray) -> bool:
    """True if no element of a tensor or numpy array is NaN or inf. A few numbers are read in
    Python (no torch op: one call's latency); more take one reduction, and for a tensor the
    elementwise test runs only when the sum is not finite (a NaN/inf, or an overflow of huge
    finite values)."""
    if (x.size if isinstance(x, np.ndarray) else x.numel()) <= 64:
        return all(map(math.isfinite, x.reshape(-1).tolist()))
    if isinstance(x, np.ndarray):
        return bool(np.isfinite(x).all())
    return math.isfinite(x.detach().sum()) or bool(torch.isfinite(x).all())


def check_float_tensor(x, name: str, shape: str) -> None:
    """Raise ``TypeError`` unless ``x`` is a float32/float64 tensor; ``shape`` (e.g.
    ``"(..., 4, 4)"``) goes into the message."""
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape {shape}, got {type(x).__name__}")
    if x.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"{name} must be a float32 or float64 tensor, got {x.dtype}")


def check_finite(x: torch.Tensor, name: str) -> None:
    """Raise ``ValueError`` naming the first NaN/inf element of ``x``, if any."""
    if not all_finite(x):
        bad = tuple((~torch.isfinite(x)).nonzero()[0].tolist())
        raise ValueError(f"{name} contains NaN or inf (first at index {bad})")


def check_choice(value, choices: tuple, name: str) -> None:
    """Raise ``ValueError`` unless ``value`` is one of ``choices`` (e.g. ``get_args`` of a ``Literal``)."""
    if value not in choices:
        raise ValueError(f"{name} must be one of {list(choices)}, got {value!r}")


def check_positive(value, name: str, integer: bool = False) -> None:
    """Raise ``ValueError`` unless ``value`` is a finite number ``> 0`` (an int if ``integer``; never a bool)."""
    kind = int if integer else (int, float)
    if isinstance(value, bool) or not isinstance(value, kind) or not value > 0 or not math.isfinite(value):
        raise ValueError(f"{name} must be a positive {'integer' if integer else 'number'}, got {value!r}")


def check_nonnegative(value, name: str) -> None:
    """Raise ``ValueError`` unless ``value`` is a finite number ``>= 0`` (never a bool)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value >= 0 or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
