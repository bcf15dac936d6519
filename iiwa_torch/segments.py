"""The closest points of two segments, one formula for every backend: :func:`closest_parameters` takes
a library's ``where``, clamp and division (torch, numpy, Python floats, numba), so the torch and
compiled collision kernels run the same operations in the same order.
"""

from __future__ import annotations

import operator

import numpy as np

__all__ = ["EPS", "choose", "closest_parameters", "quotient", "unit_float"]

EPS = float(np.finfo(np.float64).eps)  # a Python float: a numpy scalar would make the float kernel's products numpy's


def closest_parameters(a, e, b, c, f, where, unit, div=operator.truediv):
    """Closest-point parameters ``s, t`` of segments ``p1 + s d1``, ``p2 + t d2`` from ``a = d1.d1``,
    ``e = d2.d2``, ``b = d1.d2``, ``c = d1.r``, ``f = d2.r`` (``r = p1 - p2``); ``where``, ``unit``
    (clamp into [0, 1]) and ``div`` are the library's."""
    eps = EPS
    ae = a * e
    denom = ae - b * b
    s = unit(where(denom > eps * ae, div(b * f - c * e, denom), 0.0))
    t = unit(where(e <= eps * eps, 0.0, div(f + b * s, e)))
    s = unit(where(a <= eps * eps, 0.0, div(b * t - c, a)))
    return s, t


def choose(condition: bool, x: float, y: float) -> float:
    """``where`` for Python floats."""
    return x if condition else y


def unit_float(x: float) -> float:
    """``x`` clamped into [0, 1], for Python floats."""
    return min(max(x, 0.0), 1.0)


def quotient(x: float, y: float) -> float:
    """``x / y``, and 0 for ``y = 0`` (a quotient :func:`closest_parameters` then discards)."""
    return x / y if y else 0.0
