"""IK as gradient descent (``torch.optim``) on any differentiable loss of the joint angles and
the end-effector pose: :func:`minimize`."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from ..chain import Chain
from ..checks import check_instance
from ..collision import Capsules, World, robot_capsules
from .clearance import clearance_shortfall, with_clearance
from .inputs import check_target, check_world_for
from .lm_setup import inner_limits
from .options import MinimizeOptions, resolve
from .result import IKResult, ik_result

__all__ = ["minimize"]

Tensor = torch.Tensor


def minimize(
    chain: Chain,
    loss: Callable[[Tensor, Tensor], Tensor],
    q0: Tensor,
    *,
    target: Tensor,
    success_fn: Callable[[Tensor, Tensor], Tensor] | None = None,
    world: World | None = None,
    margin: float = 0.0,
    capsules: Capsules | None = None,
    options: MinimizeOptions | None = None,
    **settings,
) -> IKResult:
    """IK by gradient descent on any differentiable loss, for a batch of problems.

    Args:
        chain: the robot.
        loss: ``loss(q, pose) -> (...)``, one value per problem, from ``q (..., n)`` and
            ``pose = chain.fk(q) (..., 4, 4)`` (it may call ``chain.fk_all(q)`` for other links).
        q0: ``(..., n)`` starting joint angles (clamped into the limits); sets dtype and batch.
        target: ``(..., 4, 4)`` poses (``mode="pose"``) or ``(..., 3)`` positions
            (``mode="position"``) for ``pos_err``, ``rot_err`` and ``success`` (not added to the loss).
        success_fn: optional ``(q, pose) -> (...)`` bool, a further criterion success needs.
        world, margin: optional :class:`~iiwa_torch.collision.World` (``q0``'s dtype and
            device, batch broadcasting to ``q0``'s) and a clearance in metres (>= 0): the loss
            gets the term ``clearance_weight *`` :func:`~iiwa_torch.ik.clearance.clearance_shortfall`,
            success needs a clearance >= ``margin``, and the result carries ``clearance``.
        capsules: the capsule model with a world (default: the chain's preset model).
        options: a :class:`~iiwa_torch.ik.MinimizeOptions` (mode, optimizer, steps, lr,
            tolerances, clearance weight; its defaults if None).
        **settings: any of its fields by name (``steps=50``), replacing those of ``options``.

    Joint limits are kept by projection (the loss sees the parameters clamped, and they are
    clamped after every step). Each problem returns the lowest-loss ``q`` seen; ``iterations``
    is ``steps``.
    """
    opts = resolve(MinimizeOptions, options, settings, "minimize")
    check_instance(chain, Chain, "chain")
    if not callable(loss) or (success_fn is not None and not callable(success_fn)):
        raise TypeError("loss and success_fn must be callables (q, pose) -> tensor of shape q.shape[:-1]")
    chain.check_q(q0, "q0")
    check_target(target, opts.mode, q0.dtype, q0.shape[:-1])
    check_world_for(world, margin, target, q0.shape[:-1], capsules)
    if world is not None and capsules is None:
        capsules = robot_capsules(chain)
    objective = _objective(chain, loss, q0.shape[:-1], world, margin, capsules, opts.clearance_weight)
    lo, hi = inner_limits(chain, q0.dtype)
    best_q = _descend(objective, q0, lo, hi, opts)
    with torch.no_grad():
        result = _minimize_result(chain, best_q, target, opts, success_fn)
        return result if world is None else with_clearance(chain, result, world, margin, capsules)


def _objective(chain: Chain, loss, batch: torch.Size, world, margin: float, capsules, weight: float):
    """The caller's ``loss(q, fk(q))``, checked for one value per problem and a gradient, plus
    ``weight`` times the clearance shortfall with a world: ``q (..., n) -> (...)``."""

    def objective(q: Tensor) -> Tensor:
        value = loss(q, chain.fk(q))
        if not isinstance(value, torch.Tensor) or value.shape != batch:
            raise ValueError(
                f"loss must return one value per problem, shape {tuple(batch)}, got {getattr(value, 'shape', value)}"
            )
        if torch.is_grad_enabled() and not value.requires_grad:
            raise ValueError("loss must depend on q (or pose) through torch operations: its value has no gradient "
                             "(a constant, or computed through .detach(), .item() or numpy)")
        if world is None:
            return value
        return value + weight * clearance_shortfall(chain, q, world, margin, capsules)

    return objective


def _descend(objective, q0: Tensor, lo: Tensor, hi: Tensor, opts: MinimizeOptions) -> Tensor:
    """The optimiser's steps from ``q0 (..., n)`` within ``[lo, hi]`` -> the lowest-``objective``
    ``q`` evaluated (every evaluated ``q`` is within the limits, so any may be the answer)."""

    def clamp(q: Tensor) -> Tensor:
        return torch.minimum(torch.maximum(q, lo), hi)

    u = clamp(q0.detach()).requires_grad_(True)
    opt, decay = _optimizer(u, opts)
    best_q = u.detach().clone()
    best_loss = torch.full(q0.shape[:-1], math.inf, dtype=q0.dtype, device=q0.device)

    def closure() -> Tensor:
        nonlocal best_loss
        opt.zero_grad()
        q = clamp(u)
        value = objective(q)
        with torch.no_grad():
            better = value < best_loss
            best_q.copy_(torch.where(better[..., None], q, best_q))
            best_loss = torch.where(better, value.detach(), best_loss)
        value.sum().backward()
        return value.sum()

    for _ in range(opts.steps if decay is not None else 1):
        opt.step(closure)
        with torch.no_grad():  # projection; a non-finite update (from the caller's loss) restarts from the best
            u.copy_(clamp(torch.where(torch.isfinite(u), u, best_q)))
        if decay is not None:
            decay.step()
    with torch.no_grad():
        q = clamp(u)
        return torch.where((objective(q) < best_loss)[..., None], q, best_q)


def _optimizer(u: Tensor, opts: MinimizeOptions):
    """``(torch optimizer, learning-rate schedule or None)`` for :func:`minimize`."""
    if opts.optimizer == "adam":
        opt = torch.optim.Adam([u], lr=0.1 if opts.lr is None else opts.lr)
        return opt, torch.optim.lr_scheduler.ExponentialLR(opt, gamma=0.01 ** (1 / opts.steps))
    # One call runs every iteration: torch's L-BFGS keeps its history within a call.
    lr = 1.0 if opts.lr is None else opts.lr
    return torch.optim.LBFGS([u], lr=lr, max_iter=opts.steps, max_eval=2 * opts.steps, line_search_fn="strong_wolfe",
                             tolerance_grad=0.0, tolerance_change=0.0, history_size=20), None


def _minimize_result(chain, q, target, opts: MinimizeOptions, success_fn) -> IKResult:
    """:func:`minimize`'s answer ``q (..., n)`` -> :class:`IKResult`, with the caller's extra criterion."""
    batch = q.shape[:-1]
    iterations = torch.full(batch, opts.steps, dtype=torch.long, device=q.device)
    result = ik_result(chain, q, target, opts.mode, opts.pos_tol, opts.rot_tol, iterations)
    if success_fn is None:
        return result
    extra = success_fn(q, chain.fk(q))
    if not isinstance(extra, torch.Tensor) or extra.shape != batch:
        raise ValueError(f"success_fn must return one bool per problem, shape {tuple(batch)}")
    return IKResult(q, result.success & extra.bool(), result.pos_err, result.rot_err, iterations)
