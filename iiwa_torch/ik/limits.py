"""Revolute joint angles and joint limits: an angle and the same angle plus a multiple of 2 pi
are the same pose, so an angle outside its limits may have a turn that is inside."""

from __future__ import annotations

import math

import numpy as np
import torch

__all__ = ["shift_into_limits"]


def shift_into_limits(q: torch.Tensor, lo, hi) -> tuple[torch.Tensor, torch.Tensor]:
    """Shift joint angles ``q (..., n)`` (rad) by multiples of 2 pi into ``[lo, hi]`` where a turn
    gets them there. ``lo, hi``: numbers or tensors broadcasting with ``q`` (rad).

    Returns ``(shifted, fits)``: ``shifted`` is ``q`` where ``q`` is inside or no turn fits, else the
    turn inside; ``fits`` (bool) is True where ``shifted`` lies in ``[lo, hi]``. A numpy ``q``
    (with numbers or arrays ``lo, hi``) gives numpy arrays, by the same formula."""
    xp = np if isinstance(q, np.ndarray) else torch
    with np.errstate(invalid="ignore"):  # a continuous joint's infinite limits: NaN turns, unused (it is inside)
        turned = lo + xp.remainder(q - lo, 2 * math.pi)  # in [lo, lo + 2 pi)
    inside = (q >= lo) & (q <= hi)
    fits = turned <= hi
    return xp.where(inside, q, xp.where(fits, turned, q)), inside | fits
