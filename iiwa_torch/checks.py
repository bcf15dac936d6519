"""Input checks shared by the library and the envs: clear errors that name what was expected
and what came."""

from __future__ import annotations

import importlib
import math
from itertools import chain
from types import ModuleType

import numpy as np
import torch


def all_finite(x: torch.Tensor | np.ndarray) -> bool:
    """True if no element of a tensor or numpy array is NaN or inf. A few numbers are read in
    Python (no torch op: one call's latency); more take one reduction, and for a tensor the
    elementwise test runs only when the sum is not finite (a NaN/inf, or an overflow of huge
    finite values)."""
    if (x.size if isinstance(x, np.ndarray) else x.numel()) <= 64:
        values = x.tolist()
        if not x.ndim:
            return math.isfinite(values)
        for _ in range(x.ndim - 1):  # nested lists, flattened: cheaper than the tolist of a reshape
            values = chain.from_iterable(values)
        return all(map(math.isfinite, values))
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


def check_tensor(x, name: str, shape: tuple[int, ...]) -> None:
    """Raise ``TypeError``/``ValueError`` unless ``x`` is a finite float32/float64 tensor of shape
    ``(..., *shape)``, e.g. ``shape=(3, 3)`` for rotations."""
    text = "(..., " + ", ".join(map(str, shape)) + ")"
    check_float_tensor(x, name, text)
    if x.ndim < len(shape) or tuple(x.shape[x.ndim - len(shape) :]) != tuple(shape):
        raise ValueError(f"{name} must have shape {text}, got {tuple(x.shape)}")
    check_finite(x, name)


def check_finite(x: torch.Tensor, name: str) -> None:
    """Raise ``ValueError`` naming the first NaN/inf element of ``x``, if any, or if ``x`` is a
    ``meta`` tensor (no values); ``TypeError`` inside ``torch.func.vmap`` (values cannot be read)."""
    if isinstance(x, torch.Tensor) and x.is_meta:
        raise ValueError(f"{name} is a meta tensor, without values; the kinematics needs real ones (cpu)")
    try:
        finite = all_finite(x)
    except RuntimeError:  # no storage to read: a torch.func.vmap BatchedTensor
        if isinstance(x, torch.Tensor) and torch._C._functorch.is_functorch_wrapped_tensor(x):
            raise TypeError(
                f"{name} is batched by torch.func.vmap, which iiwa_torch does not support (its checks read "
                "values in Python); pass the batch as leading dimensions instead, e.g. q (..., n)"
            ) from None
        raise
    if not finite:
        bad = tuple((~torch.isfinite(x)).nonzero()[0].tolist())
        raise ValueError(f"{name} contains NaN or inf (first at index {bad})")


def check_instance(value, kind: type, name: str) -> None:
    """Raise ``TypeError`` unless ``value`` is a ``kind`` (e.g. ``chain`` a ``DHChain``)."""
    if not isinstance(value, kind):
        raise TypeError(f"{name} must be a {kind.__name__}, got {type(value).__name__}")


def check_choice(value, choices: tuple, name: str) -> None:
    """Raise ``ValueError`` unless ``value`` is one of ``choices`` (e.g. ``get_args`` of a ``Literal``)."""
    if value not in choices:
        raise ValueError(f"{name} must be one of {list(choices)}, got {value!r}")


def check_positive(value, name: str, integer: bool = False) -> None:
    """Raise ``ValueError`` unless ``value`` is a finite number ``> 0`` (an int if ``integer``; never a bool)."""
    kind = int if integer else (int, float)
    if isinstance(value, bool) or not isinstance(value, kind) or not value > 0 or not math.isfinite(value):
        raise ValueError(f"{name} must be a positive {'integer' if integer else 'number'}, got {value!r}")


def check_nonnegative(value, name: str, integer: bool = False) -> None:
    """Raise ``ValueError`` unless ``value`` is a finite number ``>= 0`` (an int if ``integer``; never a bool)."""
    kind = int if integer else (int, float)
    if isinstance(value, bool) or not isinstance(value, kind) or not value >= 0 or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite {'integer' if integer else 'number'} >= 0, got {value!r}")


def as_point(point, name: str = "point") -> torch.Tensor:
    """``point``, 3 finite coordinates (m) or ``None`` (the origin), as a ``(3,)`` float64 tensor."""
    try:
        p = torch.zeros(3, dtype=torch.float64) if point is None else torch.as_tensor(point, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        p = None
    if p is None or p.shape != (3,) or not torch.isfinite(p).all():
        raise ValueError(f"{name} must be None or 3 finite coordinates (m) in the end-effector frame, got {point!r}")
    return p


class MissingExtra(ModuleNotFoundError):
    """An optional dependency is not installed; the message names the extra that installs it."""


def require(module: str, extra: str) -> ModuleType:
    """``module`` (e.g. ``"viser"``, ``"matplotlib.figure"``) imported, or :class:`MissingExtra`
    naming the extra that installs it (``pip install 'iiwa-torch[viewer]'``) if its top-level
    package is not installed. Every optional import of iiwa_torch, envs and train goes through here."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as err:
        top = module.partition(".")[0]
        if err.name is None or err.name.partition(".")[0] != top:
            raise  # a dependency of an installed package is missing: its own message says which
        raise MissingExtra(
            f"{top} is not installed; it comes with the {extra} extra: pip install 'iiwa-torch[{extra}]'", name=top
        ) from None
