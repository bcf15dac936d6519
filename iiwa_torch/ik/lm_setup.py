"""What the two Levenberg-Marquardt solvers of :func:`~iiwa_torch.ik.solve` share: the batched
torch one (:mod:`iiwa_torch.ik.lm`) and the small-batch CPU one (:mod:`iiwa_torch.ik.lm_compiled`):
the seed pool and its ranking, the joint limits and the working dtype (the damping schedule and
the other settings: :class:`~iiwa_torch.ik.options.SolveOptions`)."""

from __future__ import annotations

import math

import numpy as np
import torch

from ..chain import Chain
from .limits import shift_into_limits
from .options import SolveOptions

__all__ = [
    "MIN_BATCH",
    "POOL",
    "broadcast_q",
    "inner_limits",
    "into_limits",
    "pool_distance",
    "pool_features",
    "round_width",
    "seed_ranks",
    "work_dtype",
]

Tensor = torch.Tensor

POOL = 64  # random configurations ranked by pose distance to pick each target's seeds
MIN_BATCH = 1024  # below this many problems, run several seeds of each side by side


def inner_limits(chain: Chain, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """``(lo, hi)``, each ``(n,)``, the joint limits in ``dtype`` rounded inward, so an angle
    within them is within the chain's float64 limits too (float32 rounding could cross them)."""
    exact = chain.limits
    lo, hi = exact.to(dtype)
    lo = torch.where(lo.double() < exact[0], torch.nextafter(lo, torch.full_like(lo, math.inf)), lo)
    hi = torch.where(hi.double() > exact[1], torch.nextafter(hi, torch.full_like(hi, -math.inf)), hi)
    return lo, hi


def into_limits(q: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    """Joint angles into ``[lo, hi]``: an angle outside is first shifted by a multiple of 2 pi
    (the same pose for a revolute joint), then clamped to the nearer limit (around the circle)
    if still outside. Numpy arrays in give a numpy array, by the same formula."""
    xp = np if isinstance(q, np.ndarray) else torch
    shifted, fits = shift_into_limits(q, lo, hi)
    with np.errstate(invalid="ignore"):  # as in shift_into_limits
        turned = lo + xp.remainder(q - lo, 2 * math.pi)  # in (hi, lo + 2 pi) where nothing fits
    nearer = xp.where(turned - hi <= lo + 2 * math.pi - turned, hi, lo)
    return xp.where(fits, shifted, nearer)


def broadcast_q(value: Tensor, chain: Chain, batch: torch.Size, name: str, dtype: torch.dtype) -> Tensor:
    """Check ``value (..., n)`` and broadcast it to ``(prod(batch), n)``."""
    chain.check_q(value, name)
    try:
        return torch.broadcast_to(value.to(dtype), (*batch, chain.n_joints)).reshape(-1, chain.n_joints)
    except RuntimeError:
        raise ValueError(
            f"{name} must broadcast to {(*batch, chain.n_joints)} (the targets' batch shape {tuple(batch)}, then "
            f"{chain.n_joints} joints), got {tuple(value.shape)}"
        ) from None


def rest_rows(rest: Tensor | None, rest_gain: float, chain: Chain, batch: torch.Size, dtype: torch.dtype
              ) -> Tensor | None:
    """The rest posture ``(..., n)`` checked and broadcast as :func:`broadcast_q`, or None; an error
    if given without a gain to pull toward it."""
    if rest is not None and rest_gain == 0:
        raise ValueError("rest has no effect with rest_gain=0: pass rest_gain > 0 (e.g. 0.1) to pull toward it")
    return None if rest is None else broadcast_q(rest, chain, batch, "rest", dtype)


def pool_distance(chain: Chain, pool: Tensor, target: Tensor, mode: str, features=None) -> Tensor:
    """``(pool, b)``: how far each pool configuration's end pose is from each target (poses
    ``(b, 4, 4)`` or positions ``(b, 3)``), as the squared position distance plus ``0.3^2``
    times the squared Frobenius rotation distance, less terms that are the same for every pool
    entry. ``features``: the pool's :func:`pool_features`, if computed already. Numpy
    ``target`` and ``features`` in give a numpy array, by the same formula."""
    sq, weights = pool_features(chain, pool, mode) if features is None else features
    return sq - weights @ target.reshape(target.shape[0], weights.shape[1]).T  # (b, 16) or (b, 3): also for b = 0


def pool_features(chain: Chain, pool: Tensor, mode: str) -> tuple[Tensor, Tensor]:
    """The pool's part of :func:`pool_distance`: squared end positions ``(pool, 1)`` and the
    weights of a target's entries, ``(pool, 16)`` on its flattened pose (twice the position
    in the last column, ``2 * 0.3^2`` times the rotation, zero on the bottom row) or
    ``(pool, 3)`` on its position (twice the position): one product ranks the pool."""
    pose = chain.fk(pool)
    position = pose[:, :3, 3]
    if mode == "pose":
        weights = torch.cat([2 * 0.09 * pose[:, :3, :3], 2 * position[:, :, None]], 2)  # (pool, 3, 4)
        weights = torch.cat([weights.flatten(1), torch.zeros_like(weights[:, 0])], 1)  # the bottom row: 0
    else:
        weights = 2 * position
    return position.square().sum(1, keepdim=True), weights


def seed_ranks(distance: Tensor, count: int) -> Tensor:
    """``(count, b)``: the indices of the ``count`` pool entries nearest each target, nearest
    first, from :func:`pool_distance` ``(pool, b)`` (a numpy array in: a numpy array out)."""
    if isinstance(distance, np.ndarray):
        return distance.argmin(0)[None] if count == 1 else distance.argsort(0, kind="stable")[:count]
    return distance.argmin(0, keepdim=True) if count == 1 else distance.topk(count, 0, largest=False).indices


def round_width(seeds: int, next_seed: int, remaining: int) -> int:
    """How many seeds (from ``next_seed`` on) each of ``remaining`` problems tries side by side
    in the next round: enough to fill ``MIN_BATCH`` slots."""
    return min(seeds - next_seed, max(1, -(-MIN_BATCH // remaining)))


def work_dtype(target: Tensor, options: SolveOptions) -> torch.dtype:
    """The dtype :func:`~iiwa_torch.ik.solve` iterates in for ``target`` (poses ``(..., 4, 4)`` or points
    ``(..., 3)``; see ``precision``): float32 for float64 targets when both tolerances are >= 1e-5 and
    float32's spacing at the farthest target coordinate is 8x below ``pos_tol`` (an arm 300 m from the
    world origin is not resolved to 1e-5 m in float32)."""
    if options.precision != "auto" or target.dtype != torch.float64 or min(options.pos_tol, options.rot_tol) < 1e-5:
        return target.dtype
    points = target[..., :3, 3] if options.mode == "pose" else target
    farthest = float(points.detach().abs().max()) if points.numel() else 0.0
    return torch.float32 if 8 * farthest * torch.finfo(torch.float32).eps <= options.pos_tol else torch.float64
