"""Obstacles in the gradient-based IK solvers: the clearance penalty both use
(:func:`clearance_shortfall`), the world in the LM loop's layout (:class:`Obstacles`) with its
residual row (:func:`clearance_row`), and the clearance of an answer (:func:`with_clearance`)."""

from __future__ import annotations

from dataclasses import replace
from typing import NamedTuple

import torch

from ..chain import Chain
from ..collision import Capsules, World, clearance, pairwise_clearance, robot_capsules
from .result import IKResult

__all__ = ["CLEAR_BUFFER", "COLLIDING_RANK", "Obstacles", "clearance_row", "clearance_shortfall", "with_clearance"]

Tensor = torch.Tensor

# With a world, the clearance residual acts below margin + CLEAR_BUFFER and a seed counts as
# clear at margin + CLEAR_BUFFER / 2 (m): far above float32 rounding of the distances, so the
# float64 check of the answer agrees.
CLEAR_BUFFER = 2e-3
COLLIDING_RANK = 100.0  # added to a colliding pool entry's pose distance: clear entries are tried first


def clearance_shortfall(
    chain: Chain, q: Tensor, world: World, margin: float, capsules: Capsules | None = None
) -> Tensor:
    """``sum_p max(0, margin + 2 mm - d_p)^2`` over every checked pair's signed distance ``d_p``
    (:func:`~iiwa_torch.collision.pairwise_clearance`): ``q (..., n) -> (...)``, m^2, zero once
    every pair clears ``margin`` by 2 mm. Differentiable; the penalty both solvers use."""
    d = pairwise_clearance(chain, q, world, capsules).distance
    return (margin + CLEAR_BUFFER - d).clamp_min(0).square().sum(-1)


class Obstacles(NamedTuple):
    """A world in the LM loop's dtype: ``world`` unbatched, or with one leading dimension over the
    problems (``batched``), the robot's ``capsules`` and the clearance ``margin`` (m). With
    ``residual``, the LM objective has the clearance residual; else the clearance is only
    checked when a slot's pose has converged."""

    chain: Chain
    world: World
    batched: bool
    capsules: Capsules
    margin: float
    residual: bool = False

    @staticmethod
    def build(chain: Chain, world: World, margin: float, batch: torch.Size, work: torch.dtype,
              capsules: Capsules | None) -> Obstacles:
        """``world`` in the loop's dtype ``work``, a batch shape (if any) expanded and flattened
        to the problems' ``batch``."""
        batched = len(world.batch_shape) > 0

        def cast(t: Tensor, event: int) -> Tensor:
            if batched:
                event_shape = t.shape[t.ndim - event :]
                t = t.expand(*batch, *event_shape).reshape(-1, *event_shape)
            return t.to(work)

        capsules = robot_capsules(chain) if capsules is None else capsules
        return Obstacles(chain, world.map_batch(cast), batched, capsules, float(margin))

    def take(self, index: Tensor) -> Obstacles:
        if not self.batched:
            return self
        return self._replace(world=self.world.map_batch(lambda t, _: t.index_select(0, index)))

    def clearance(self, q: Tensor) -> Tensor:
        """``q (n, b)`` -> minimum signed clearance ``(b,)``, m."""
        return clearance(self.chain, q.T, self.world, self.capsules)

    def clear(self, q: Tensor) -> Tensor:
        """``q (n, b)`` -> ``(b,)`` bool: clear of the world by ``margin + CLEAR_BUFFER / 2``."""
        return self.clearance(q) >= self.margin + CLEAR_BUFFER / 2

    def colliding(self, pool: Tensor) -> Tensor:
        """``pool (p, n)`` -> ``(p,)`` float, 1 where a configuration is not clear of the part of
        the world every problem shares (all of it, or the robot itself and the floor if batched)."""
        shared = World(floor=self.world.floor) if self.batched else self.world
        return (clearance(self.chain, pool, shared, self.capsules) < self.margin + CLEAR_BUFFER).to(pool.dtype)


def clearance_row(q: Tensor, obstacles: Obstacles) -> tuple[Tensor, Tensor]:
    """``q (n, b)`` -> the clearance residual ``r = |max(0, margin + buffer - d)| (b,)`` (m) over
    every checked pair's distance ``d``, and its gradient ``(n, b)`` (m/rad).

    A residual beside the six pose rows (not a clearance step projected into the Jacobian's null
    space) lets LM weigh the two: with redundancy to spare the step moves in the pose rows' null
    space, else it is the least-squares compromise. The norm over all pairs (not the minimum)
    keeps every too-near pair in the step, so it does not alternate between two obstacles."""
    with torch.enable_grad():
        x = q.T.detach().requires_grad_(True)
        sq = clearance_shortfall(obstacles.chain, x, obstacles.world, obstacles.margin, obstacles.capsules)
        (grad,) = torch.autograd.grad(sq.sum(), x)
    r = sq.detach().sqrt()
    return r, grad.T / (2 * r).clamp_min(torch.finfo(q.dtype).tiny)


def with_clearance(chain: Chain, result: IKResult, world: World, margin: float,
                   capsules: Capsules | None) -> IKResult:
    """``result`` with the clearance of its ``q`` (in the target's dtype); success needs ``>= margin``."""
    d = clearance(chain, result.q, world, capsules)
    return replace(result, success=result.success & (d >= margin), clearance=d)
