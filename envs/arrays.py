"""The few array operations the task's formulas use, for torch tensors and for numpy arrays.

The step's formulas (:meth:`envs.robot.JointVelocityArm.integrate`,
:meth:`envs.goals.ReachGoals.errors`, ...) are written once and take one of these namespaces:
:data:`TORCH` for batches (the state's own tensors, in place where the formula owns them) and
:data:`NUMPY` for one environment on the CPU, whose per-op cost is a fraction of torch's
(about 1 us against 3-5 us here). Operators (``+ - * / < |``) are the arrays' own. The
functions whose names differ between the libraries are the only ones here; the ``_`` ones
write into their first argument, which must be a temporary of the formula. The multiply-add
(fused), arcsine and cross product of :data:`NUMPY` are torch's (as are the step's cosine and
sine of q), run on views of the arrays: torch's float32 results differ from numpy's in the last
bit for 1 in 5 inputs or more (measured), and one env's observations must equal a batch's, and
its rewards ``compute_reward``'s (torch), bit for bit. The square root is correctly rounded on
both (torch's own float32 one is not, for 1 in 5 inputs: :data:`TORCH` takes it in float64), as
the compiled step (:mod:`envs.compiled_step`) computes it.
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["ArrayOps", "TORCH", "NUMPY"]


class ArrayOps:
    """The torch versions; :class:`_NumpyOps` overrides them."""

    name = "torch"

    @staticmethod
    def of(t: torch.Tensor):
        """A state tensor as this library's array (numpy: a view of its memory, no copy)."""
        return t

    @staticmethod
    def tensor(x) -> torch.Tensor:
        """This library's array as a tensor (numpy: sharing its memory, no copy)."""
        return x

    @staticmethod
    def clip(x, low: float, high: float):
        """A new array: ``x`` clipped into ``[low, high]`` (floats)."""
        return torch.clamp(x, low, high)

    @staticmethod
    def clip_(x, low, high):
        """``x`` clipped in place into ``[low, high]`` (floats or arrays that broadcast; for
        tensor bounds clamp_max_/clamp_min_: clamp with tensor bounds was measured 2-3x slower)."""
        if isinstance(low, float) and isinstance(high, float):
            return x.clamp_(low, high)
        return x.clamp_max_(high).clamp_min_(low)

    @staticmethod
    def multiply_add(x, a, b):
        """A new array ``x + a * b``."""
        return torch.addcmul(x, a, b)

    @staticmethod
    def divide_(x, y):
        return x.div_(y)

    @staticmethod
    def square_(x):
        return x.mul_(x)

    @staticmethod
    def sqrt_(x):
        """The square root, correctly rounded: a float32 one through float64 (exact once rounded back)."""
        return x.sqrt_() if x.dtype == torch.float64 else x.copy_(x.double().sqrt_())

    @staticmethod
    def at_most(x, high: float):
        return torch.clamp(x, max=high)

    where, asin, zeros_like = staticmethod(torch.where), staticmethod(torch.asin), staticmethod(torch.zeros_like)
    ones_like, stack, moveaxis = staticmethod(torch.ones_like), staticmethod(torch.stack), staticmethod(torch.moveaxis)
    concatenate = staticmethod(torch.cat)

    @staticmethod
    def cross(u, v):
        """Cross product of vectors along the first axis."""
        return torch.linalg.cross(u, v, dim=0)

    @staticmethod
    def like(x, other):
        """``x`` in ``other``'s dtype."""
        return x.to(other.dtype)


class _NumpyOps(ArrayOps):
    name = "numpy"

    @staticmethod
    def of(t: torch.Tensor) -> np.ndarray:
        return t.numpy()

    @staticmethod
    def tensor(x) -> torch.Tensor:
        return torch.from_numpy(np.asarray(x))

    @staticmethod
    def clip(x, low: float, high: float):
        return np.minimum(np.maximum(x, low), high)  # two ufuncs: np.clip's wrapper costs more on tiny arrays

    @staticmethod
    def clip_(x, low, high):
        return np.maximum(np.minimum(x, high, out=x), low, out=x)

    @staticmethod
    def multiply_add(x, a, b):  # torch's: addcmul is fused (one rounding)
        return torch.addcmul(torch.from_numpy(x), torch.from_numpy(a), torch.from_numpy(b)).numpy()

    @staticmethod
    def divide_(x, y):
        return np.divide(x, y, out=x)

    @staticmethod
    def square_(x):
        return np.multiply(x, x, out=x)

    @staticmethod
    def sqrt_(x):
        return np.sqrt(x, out=x)

    @staticmethod
    def at_most(x, high: float):
        return np.minimum(x, high)

    where, zeros_like = staticmethod(np.where), staticmethod(np.zeros_like)
    ones_like, stack, moveaxis = staticmethod(np.ones_like), staticmethod(np.stack), staticmethod(np.moveaxis)
    concatenate = staticmethod(np.concatenate)


    @staticmethod
    def asin(x):
        return torch.asin(torch.from_numpy(x)).numpy()  # torch's, as for multiply_add

    @staticmethod
    def cross(u, v):  # torch's, as for multiply_add (np.cross differs in the last bit in 4 of 5 cases)
        return torch.linalg.cross(torch.from_numpy(u), torch.from_numpy(v), dim=0).numpy()

    @staticmethod
    def like(x, other):
        return x.astype(other.dtype)


#: the torch operations (any batch, any device)
TORCH = ArrayOps()
#: the numpy operations (CPU state)
NUMPY = _NumpyOps()
