"""Input checks shared by the library and the envs: clear errors that name what was expected
and what came."""

from __future__ import annotations

import importlib
import math
import numbers
import os
from itertools import chain
from types import ModuleType

import numpy as np
import torch


def all_finite(x: torch.Tensor | np.ndarray) -> bool:
    """True if no element of a tensor or numpy array is NaN or inf. Up to 64 numbers are read in Python
    (a torch op costs more); a tensor's elementwise test runs only when its sum is not finite."""
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


def check_tensor(x, name: str, shape: tuple[int, ...], finite: bool = True) -> None:
    """Raise ``TypeError``/``ValueError`` unless ``x`` is a float32/float64 tensor of shape
    ``(..., *shape)``, e.g. ``shape=(3, 3)`` for rotations, and finite (if ``finite``)."""
    text = "(..., " + ", ".join(map(str, shape)) + ")"
    check_float_tensor(x, name, text)
    if x.ndim < len(shape) or tuple(x.shape[x.ndim - len(shape) :]) != tuple(shape):
        raise ValueError(f"{name} must have shape {text}, got {tuple(x.shape)}")
    if finite:
        check_finite(x, name)


def check_finite(x: torch.Tensor, name: str) -> None:
    """Raise ``ValueError`` naming the first NaN/inf of ``x`` or for a ``meta`` tensor; ``TypeError`` under
    ``torch.func.vmap`` (values cannot be read)."""
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


def broadcast_shapes(shapes: dict[str, tuple[int, ...]]) -> torch.Size:
    """``torch.broadcast_shapes`` of the named ``shapes``, or a ``ValueError`` that names each."""
    try:
        return torch.broadcast_shapes(*shapes.values())
    except RuntimeError:
        got = ", ".join(f"{name} {tuple(shape)}" for name, shape in shapes.items())
        raise ValueError(f"{', '.join(shapes)} must broadcast together, got {got}") from None


def check_bool(value, name: str) -> None:
    """Raise ``TypeError`` unless ``value`` is a ``bool`` or numpy ``bool_`` (not merely truthy)."""
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be True or False, got {value!r} ({type(value).__name__})")


def check_choice(value, choices: tuple, name: str) -> None:
    """Raise ``ValueError`` unless ``value`` is one of ``choices`` (e.g. ``get_args`` of a ``Literal``)."""
    if value not in choices:
        raise ValueError(f"{name} must be one of {list(choices)}, got {value!r}")


def is_integer(value) -> bool:
    """True for an integer of any numeric type (``int``, ``np.int64``, ...), never a bool."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def is_number(value) -> bool:
    """True for a real number of any numeric type (``int``, ``float``, ``np.float32``, ...), never a bool."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def check_positive(value, name: str, integer: bool = False) -> None:
    """Raise ``ValueError`` unless ``value`` is a finite number ``> 0`` (an integer if ``integer``; not a bool)."""
    kind = is_integer if integer else is_number
    if not kind(value) or not value > 0 or not math.isfinite(value):
        raise ValueError(f"{name} must be a positive {'integer' if integer else 'number'}, got {value!r}")


def check_nonnegative(value, name: str, integer: bool = False) -> None:
    """Raise ``ValueError`` unless ``value`` is a finite number ``>= 0`` (an integer if ``integer``; not a bool)."""
    kind = is_integer if integer else is_number
    if not kind(value) or not value >= 0 or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite {'integer' if integer else 'number'} >= 0, got {value!r}")


def check_generator(generator, name: str = "generator") -> None:
    """Raise ``TypeError`` unless ``generator`` is a ``torch.Generator`` or ``None``."""
    if generator is not None and not isinstance(generator, torch.Generator):
        raise TypeError(f"{name} must be a torch.Generator or None (e.g. torch.Generator().manual_seed(0)), "
                        f"got {type(generator).__name__}")


def as_device(device, name: str = "device") -> torch.device:
    """``device`` (``torch.device``, a string, or ``None`` for the CPU) as a ``torch.device`` usable in this
    torch build; ``ValueError`` otherwise (``"meta"``, ``"cuda"`` on a CPU-only build)."""
    try:
        found = torch.device("cpu" if device is None else device)
    except (RuntimeError, TypeError):
        raise ValueError(f"{name} must be a torch device such as 'cpu', got {device!r}") from None
    if found.type == "meta":
        raise ValueError(f"{name} 'meta' holds no values; use a real device such as 'cpu'")
    try:
        torch.empty(0, device=found)
    except (RuntimeError, AssertionError) as err:  # torch asserts that CUDA was compiled in
        raise ValueError(f"{name} {device!r} is not usable in this torch build ({err}); use 'cpu'") from None
    return found


MEMORY_SHARE = 0.8  # of the available memory a single call may plan to allocate


def available_memory() -> int:
    """Bytes available to a new allocation: /proc/meminfo's ``MemAvailable``, else the free physical pages."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def check_memory(nbytes: int, what: str) -> None:
    """Raise ``ValueError`` if ``what`` would allocate ``nbytes``, more than ``MEMORY_SHARE`` of what is available."""
    free = available_memory()
    if nbytes > MEMORY_SHARE * free:
        raise ValueError(f"{what} needs about {nbytes / 1e9:.3g} GB of memory, more than the "
                         f"{free / 1e9:.3g} GB available: make it smaller (or split it into parts)")


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
    """``module`` imported, or :class:`MissingExtra` naming the ``extra`` that installs it if its top-level
    package is missing. Every optional import goes through here."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as err:
        top = module.partition(".")[0]
        if err.name is None or err.name.partition(".")[0] != top:
            raise  # a dependency of an installed package is missing: its own message says which
        raise MissingExtra(
            f"{top} is not installed; it comes with the {extra} extra: pip install 'iiwa-torch[{extra}]'", name=top
        ) from None
