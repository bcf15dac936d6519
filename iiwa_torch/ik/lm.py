"""Batched inverse kinematics by damped least squares / Levenberg-Marquardt on the geometric
Jacobian: :func:`solve`, for thousands of targets at once, with joint limits, several seeds per
target and an optional null-space pull toward a rest posture.

How :func:`solve` is fast on a CPU: the inner loop keeps every quantity batch last, as
``(rows, batch)`` tensors, so each operation is one elementwise kernel over the whole batch
(no batched ``4x4`` products; for large batches no per-problem LAPACK call either: the
damped ``6x6`` normal equations are solved by a Cholesky factorisation written out over the
batch). Problems that converge leave the batch every ``check_every`` iterations, and the ones
that stall restart from their next seed, so the batch shrinks as the solve goes on. Up to
``lm_compiled.COMPILED_BATCH`` CPU targets take the compiled rounds of :mod:`iiwa_torch.ik.lm_compiled`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch

from ..chain import Chain
from ..checks import check_generator, check_instance
from ..collision import Capsules, World
from . import lm_compiled
from .clearance import COLLIDING_RANK, Obstacles, clearance_row, with_clearance
from .dls import dls_step_batch_last
from .inputs import check_target, check_world_for
from .lm_setup import (
    POOL,
    broadcast_q,
    inner_limits,
    into_limits,
    pool_distance,
    rest_rows,
    round_width,
    seed_ranks,
    work_dtype,
)
from .options import SolveOptions, resolve
from .result import IKResult, ik_result

__all__ = ["solve"]

Tensor = torch.Tensor

_LAM_MAX = 1e4  # the damping's ceiling (m^2), as the compiled rounds'


# ---------------------------------------------------------------------- batch-last kinematics
def _kinematics(chain: Chain, q: Tensor, Z: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``q (n, b)`` -> end axes ``R (3, 3, b)`` (axis x/y/z, component), end position ``p (3, b)``
    and points on the joint axes ``P (3, n, b)``; the joint axes are written into ``Z (3, n, b)``.
    Uses the chain's own batch-last kernel, so no layout change happens inside the loop."""
    frames, axes = chain.frames_batch_last(q)
    torch.stack([z for z, _ in axes], 1, out=Z)
    P = torch.stack([p for _, p in axes], 1)
    x, y, z, p = chain.tool_frame_batch_last(frames[-1])
    return torch.stack([x, y, z]), p, P  # (3, 3, b), (3, b), (3, n, b)


def _roll(vectors: Tensor, dim: int) -> Tensor:
    """Vector components ``(x, y, z)`` along ``dim`` rotated to ``(y, z, x)``."""
    return torch.roll(vectors, -1, dim)


def _take(values: Tensor, index: Tensor) -> Tensor:
    """``values (..., b)`` at the batch positions ``index (k,)`` -> ``(..., k)``. Gathering rows
    of a 2-D view is several times faster than ``index_select`` on the last of 3 dimensions."""
    return values.reshape(-1, values.shape[-1]).index_select(1, index).reshape(*values.shape[:-1], -1)


class _Target:
    """Targets in the loop's layout: rotation axes ``(3, 3, b)`` (axis, component) and the same
    with rolled components (for cross products), position ``(3, b)``; or position only. With
    ``obstacles``, the objective also has the clearance residual (:func:`clearance_row`)."""

    def __init__(
        self, rot: Tensor | None, pos: Tensor, rolled: Tensor | None = None, obstacles: Obstacles | None = None
    ) -> None:
        self.pos, self.rot, self.obstacles = pos, rot, obstacles
        self.rolled = None if rot is None else _roll(rot, 1) if rolled is None else rolled

    def take(self, index: Tensor) -> _Target:
        obstacles = None if self.obstacles is None else self.obstacles.take(index)
        if self.rot is None:
            return _Target(None, _take(self.pos, index), obstacles=obstacles)
        return _Target(_take(self.rot, index), _take(self.pos, index), _take(self.rolled, index), obstacles)

    def with_obstacles(self, obstacles: Obstacles) -> _Target:
        return _Target(self.rot, self.pos, self.rolled, obstacles)


def _evaluate(
    chain: Chain, q: Tensor, target: _Target, weight: float
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """``q (n, b)`` -> weighted Jacobian ``J (m, n, b)``, weighted error ``e (m, b)`` (m = 6 or 3,
    one more with obstacles: the clearance residual of :func:`clearance_row`), squared weighted
    error ``E (b,)``, position error ``(b,)`` m, rotation error ``(b,)`` rad."""
    terms = _pose_terms(chain, q, target, weight)
    if target.obstacles is None or not target.obstacles.residual:
        return terms
    J, e, E, pos_err, rot_err = terms
    r, grad = clearance_row(q, target.obstacles)
    return torch.cat([J, grad[None]]), torch.cat([e, -r[None]]), E + r * r, pos_err, rot_err


def _pose_terms(
    chain: Chain, q: Tensor, target: _Target, weight: float
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """:func:`_evaluate` for the pose (or position) rows alone."""
    n, b = q.shape
    pose = target.rot is not None
    J = q.new_empty(6 if pose else 3, n, b)
    Z = J[3:] if pose else q.new_empty(3, n, b)  # the angular rows are the joint axes
    R, p, P = _kinematics(chain, q, Z)
    e_pos = target.pos - p
    pos_err = torch.addcmul(torch.addcmul(e_pos[0] * e_pos[0], e_pos[1], e_pos[1]), e_pos[2], e_pos[2]).sqrt()
    lever = p[:, None] - P  # (3, n, b)
    for r, (i, j) in enumerate(((1, 2), (2, 0), (0, 1))):  # z x lever, one component per row
        torch.mul(Z[i], lever[j], out=J[r])
        J[r].addcmul_(Z[j], lever[i], value=-1)
    g = chain.geometry(q.dtype)
    if g.has_prismatic:  # a sliding joint's column is [z; 0]
        J[:3] = torch.where(g.prismatic, Z, J[:3])
        if pose:
            J[3:].masked_fill_(g.prismatic, 0.0)
    if not pose:
        return J, e_pos, pos_err.square(), pos_err, torch.zeros_like(pos_err)
    if weight != 1:
        J[3:].mul_(weight)
    # log(R_t R^T): its skew part is sum_k r_k x t_k / 2 (r_k, t_k the axes), its trace sum_k r_k . t_k;
    # a x b = roll(a * roll(b) - roll(a) * b) with roll: (x, y, z) -> (y, z, x).
    v = _roll((R * target.rolled - _roll(R, 1) * target.rot).sum(0), 0).mul_(0.5)  # sin(angle) * axis
    cos = ((R * target.rot).sum((0, 1)) - 1) * 0.5
    sin = torch.addcmul(torch.addcmul(v[0] * v[0], v[1], v[1]), v[2], v[2]).sqrt()
    rot_err = torch.atan2(sin, cos)
    # angle / sin: |e_rot| <= angle and finite, also at a half turn (below eps the vector only
    # shrinks, for angles that small it does not matter)
    e_rot = v * (rot_err / sin.clamp_min(torch.finfo(q.dtype).eps))
    e = torch.cat([e_pos, e_rot * weight])
    return J, e, pos_err.square() + (weight * rot_err).square(), pos_err, rot_err


# ---------------------------------------------------------------------- solve
class _LMState(NamedTuple):
    """Every slot's iterate, batch last: joint angles ``q (n, s)``, weighted Jacobian ``J (m, n, s)``,
    weighted error ``e (m, s)``, squared weighted error ``E (s,)``, position and rotation errors
    ``(s,)`` (m, rad) and the damping ``lam (s,)`` (m^2)."""

    q: Tensor
    J: Tensor
    e: Tensor
    E: Tensor
    pos_err: Tensor
    rot_err: Tensor
    lam: Tensor

    def take(self, index: Tensor) -> _LMState:
        return _LMState(*(_take(value, index) for value in self))


def _lm_step(settings: _Settings, state: _LMState, target: _Target, limited: bool, rest: Tensor | None) -> _LMState:
    """One Levenberg-Marquardt step for every slot: a step is kept where it lowers ``E``, and
    the damping follows. ``limited``: a step within the limits ``settings.lo, hi``, else free."""
    opts, lo, hi = settings.options, settings.lo, settings.hi
    q, J, e, E, pos_err, rot_err, lam = state
    free = None
    if limited:  # box constraint: joints at a limit that E pushes outward are frozen
        descent = (J * e[:, None]).sum(0)  # J^T e (n, b), where E wants each joint to go
        # 1 where a unit move along the descent, projected into the limits, still moves the
        # joint, else 0; float arithmetic throughout (boolean ops are several times slower here).
        moved = torch.minimum(torch.maximum(q + torch.sign(descent), lo), hi) - q
        free = moved.abs_().sign_()
    if rest is None:
        dq = dls_step_batch_last(J, e[:, None], lam, settings.lam_min, free)[:, 0]
    else:  # pull toward the rest posture inside the (damped) null space of J, while the damping
        # is low: a large damping would turn the projected pull into the full pull.
        pull = opts.rest_gain * (rest - q) * (lam <= opts.damping)
        pull = pull if free is None else pull * free
        sol = dls_step_batch_last(J, torch.stack([e, (J * pull).sum(1)], 1), lam, settings.lam_min, free)
        dq = sol[:, 0] + pull - sol[:, 1]
    q_new = torch.minimum(torch.maximum(q + dq, lo), hi) if limited else q + dq
    J_new, e_new, E_new, pos_new, rot_new = _evaluate(settings.chain, q_new, target, opts.rot_weight)
    # lerp with weight 0 or 1 is exact, and cheaper than torch.where (the solve's time: benchmarks/results/ik.md)
    kept = (E_new < E).to(q.dtype)
    factor = torch.lerp(torch.full_like(lam, opts.damping_up), torch.full_like(lam, opts.damping_down), kept)
    return _LMState(
        torch.lerp(q, q_new, kept),
        torch.lerp(J, J_new, kept),
        torch.lerp(e, e_new, kept),
        torch.lerp(E, E_new, kept),
        torch.lerp(pos_err, pos_new, kept),
        torch.lerp(rot_err, rot_new, kept),
        (lam * factor).clamp_(settings.lam_min, _LAM_MAX),
    )


def _seed_q(
    pool: Tensor | None, distance: Tensor | None, first: Tensor | None, problems: Tensor, width: int, start: int
) -> Tensor:
    """Seeds ``start .. start + width - 1`` of each problem, as ``(n, width * len(problems))``
    (seed-major): ``first`` (q0) is seed 0 if given, then the pool entries nearest the target."""
    shift = 0 if first is None else 1
    count = start + width - shift  # pool ranks needed: 0 .. count - 1
    if count > 0:
        nearest = seed_ranks(distance[:, problems], count)
    seeds = []
    for number in range(start, start + width):
        seeds.append(first[problems] if number < shift else pool[nearest[number - shift]])
    return torch.cat(seeds).T.contiguous()


def _keep_best(best_q: Tensor, best_E: Tensor, q: Tensor, key: Tensor, problem: Tensor) -> Tensor:
    """Per problem, keep the slot with the lowest ``key`` (several slots may share a problem).

    ``best_q (n, b)`` is updated in place where a slot of ``q (n, s)`` improves on ``best_E (b,)``
    (one slot per problem is copied, never a mix); returns the new ``best_E``.
    """
    lowest = best_E.scatter_reduce(0, problem, key, "amin")
    better = ((key <= lowest[problem]) & (key < best_E[problem])).nonzero().squeeze(1)
    winner = torch.full_like(best_E, -1, dtype=torch.long).scatter_reduce_(0, problem[better], better, "amax")
    problems = (winner >= 0).nonzero().squeeze(1)
    best_q.index_copy_(1, problems, q.index_select(1, winner[problems]))
    return lowest


def solve(
    chain: Chain,
    target: Tensor,
    q0: Tensor | None = None,
    *,
    rest: Tensor | None = None,
    generator: torch.Generator | None = None,
    world: World | None = None,
    margin: float = 0.0,
    capsules: Capsules | None = None,
    options: SolveOptions | None = None,
    **settings,
) -> IKResult:
    """Inverse kinematics for a batch of targets by damped least squares (Levenberg-Marquardt).

    Args:
        chain: the robot.
        target: ``(..., 4, 4)`` end-effector poses (``mode="pose"``) or ``(..., 3)`` positions
            (``mode="position"``), metres, in the chain's world frame. The dtype (float32 or
            float64) and device of the solve and of the result follow it.
        q0: optional ``(..., n)`` first seed (broadcast to the targets), e.g. the previous
            solution when tracking; an angle outside its limits is shifted by 2 pi or clamped.
        rest: optional ``(..., n)`` posture that ``rest_gain`` pulls toward inside the
            Jacobian's null space, so a redundant arm (the iiwa) stays near it (e.g. ``rest=q0``
            when tracking); it needs ``rest_gain > 0`` (a ``ValueError`` otherwise).
        generator: source of the random seeds (default: a fresh generator seeded with 0, so
            results are reproducible).
        world, margin: optional :class:`~iiwa_torch.collision.World` (the target's dtype and
            device, a batch shape broadcasting to the targets') and clearance (m, >= 0): then
            ``success`` also needs :func:`~iiwa_torch.collision.clearance` of ``q`` (self pairs
            and world) >= ``margin``; answers that are not clear are solved again with a
            clearance residual in the LM system (docs/ik.md). ``None``: no collision check.
        capsules: the robot's capsule model with a world (default
            :func:`~iiwa_torch.collision.robot_capsules`; a custom ``Chain`` needs its own).
        options: a :class:`~iiwa_torch.ik.SolveOptions`: mode, tolerances, seeds, iterations,
            rest gain, damping schedule, ... (its defaults if None).
        **settings: any of its fields by name (``pos_tol=1e-6``, ``seeds=8``,
            ``mode="position"``), replacing the ones of ``options``.

    Returns:
        :class:`IKResult`: ``q (..., n)`` always within the joint limits, errors and ``success``
        from ``chain.fk(q)``, ``iterations`` over all seeds, ``clearance`` with a world. An
        unreachable target (or one reachable only through a collision) is not an error:
        ``success`` is False and ``q`` the best attempt (smallest weighted error).

    Not differentiable (it runs under ``torch.no_grad``): :func:`~iiwa_torch.ik.minimize` is.
    """
    opts = resolve(SolveOptions, options, settings, "solve")
    check_instance(chain, Chain, "chain")
    check_generator(generator)
    batch = check_target(target, opts.mode, None, None)
    if target.device != chain.limits.device:
        raise ValueError(f"target is on {target.device} but the chain is on {chain.limits.device}")
    check_world_for(world, margin, target, batch, capsules)
    work = work_dtype(target, opts)
    rest_flat = rest_rows(rest, opts.rest_gain, chain, batch, work)
    if lm_compiled.handles(target, q0, rest, world, batch.numel()):  # it caches the default generator's pool
        return lm_compiled.solve_compiled(chain, target, q0, rest_flat, opts, work, generator)
    with torch.no_grad():
        return _solve_batched(chain, target, batch, q0, rest_flat, generator, (world, margin, capsules), opts, work)


def _solve_batched(chain: Chain, target: Tensor, batch: torch.Size, q0, rest, generator, obstacle_args,
                   opts: SolveOptions, work: torch.dtype) -> IKResult:
    """:func:`solve`'s torch loop for checked inputs (``rest (b, n)`` in ``work`` or None,
    ``obstacle_args`` its ``(world, margin, capsules)``), iterating in ``work``."""
    world, margin, capsules = obstacle_args
    device, n = target.device, chain.n_joints
    if generator is None:
        generator = torch.Generator(device).manual_seed(0)
    flat = target.reshape(-1, *target.shape[len(batch) :]).to(work)
    lo, hi = (x[:, None] for x in inner_limits(chain, work))  # (n, 1) each
    first = None if q0 is None else into_limits(broadcast_q(q0, chain, batch, "q0", work).T, lo, hi).T
    obstacles = None if world is None else Obstacles.build(chain, world, margin, batch, work, capsules)
    pool, distance = _seed_pool(chain, flat, opts, first is not None, generator, obstacles)
    tgt = _Target(
        None if opts.mode == "position" else flat[:, :3, :3].permute(2, 1, 0).contiguous(),
        (flat if opts.mode == "position" else flat[:, :3, 3]).T.contiguous(),
        obstacles=obstacles,
    )
    settings = _Settings(chain, opts, lo, hi, 1e-12 if work == torch.float64 else 1e-6)
    answers = _Answers.empty(n, flat.shape[0], work, device)
    _run_rounds(settings, tgt, rest, pool, distance, first, answers)
    if obstacles is not None:
        _clear_answers(settings, tgt, rest, pool, distance, answers)
    q_out = answers.q.T.to(target.dtype).reshape(*batch, n)
    result = ik_result(chain, q_out, target, opts.mode, opts.pos_tol, opts.rot_tol, answers.used.reshape(batch))
    return result if world is None else with_clearance(chain, result, world, margin, capsules)


def _seed_pool(chain: Chain, flat: Tensor, opts: SolveOptions, has_first: bool, generator,
               obstacles: Obstacles | None) -> tuple[Tensor | None, Tensor | None]:
    """The seeds after ``q0``: ``max(POOL, seeds)`` configurations ``(P, n)`` drawn within the
    limits and their :func:`pool_distance` ``(P, b)`` to the targets ``flat`` (colliding ones
    ranked last); ``(None, None)`` when ``q0`` is the only seed (tracking)."""
    if opts.seeds <= has_first:
        return None, None
    pool = chain.random_q(max(POOL, opts.seeds), generator=generator, dtype=flat.dtype)
    distance = pool_distance(chain, pool, flat, opts.mode)  # (pool, b)
    if obstacles is not None:
        distance += COLLIDING_RANK * obstacles.colliding(pool)[:, None]
    return pool, distance


def _clear_answers(settings: _Settings, tgt: _Target, rest, pool, distance, answers: _Answers) -> None:
    """Solve again, with the clearance residual, every problem none of whose seeds converged
    clear of the obstacles, from its best answer and then from its pool seeds."""
    tgt = tgt.with_obstacles(tgt.obstacles._replace(residual=True))
    redo = (answers.E >= 0).nonzero().squeeze(1)
    if not redo.numel():
        return
    again = _Answers.empty(answers.q.shape[0], redo.numel(), answers.q.dtype, answers.q.device)
    sub_rest = None if rest is None else rest[redo]
    sub_distance = None if distance is None else distance[:, redo]
    _run_rounds(settings, tgt.take(redo), sub_rest, pool, sub_distance, answers.q[:, redo].T, again)
    answers.q[:, redo] = again.q
    answers.used[redo] += again.used


class _Settings(NamedTuple):
    """What every round of :func:`solve` shares: the ``options``, ``lo, hi (n, 1)`` the inner joint
    limits (rad) and ``lam_min`` the damping floor (m^2) in the loop's dtype."""

    chain: Chain
    options: SolveOptions
    lo: Tensor
    hi: Tensor
    lam_min: float


@dataclass
class _Answers:
    """Per problem: the best ``q (n, b)`` so far, its key ``E (b,)`` (below 0: converged, see
    :func:`_check_slots`) and the iterations ``used (b,)`` over all seeds."""

    q: Tensor
    E: Tensor
    used: Tensor

    @staticmethod
    def empty(n: int, b: int, dtype: torch.dtype, device: torch.device) -> _Answers:
        return _Answers(
            torch.empty(n, b, dtype=dtype, device=device),
            torch.full((b,), math.inf, dtype=dtype, device=device),
            torch.zeros(b, dtype=torch.long, device=device),
        )


def _run_rounds(settings: _Settings, tgt: _Target, rest, pool, distance, first, answers: _Answers) -> None:
    """Rounds: every remaining problem tries its next ``width`` seeds side by side; the width
    grows when few problems remain, so the small tail of hard targets fills the batch."""
    b, seeds = answers.E.shape[0], settings.options.seeds
    device = answers.E.device
    remaining, next_seed = torch.arange(b, device=device), 0
    while remaining.numel() and next_seed < seeds:
        width = round_width(seeds, next_seed, remaining.numel())
        problem = remaining.repeat(width)  # slot -> problem
        number = torch.arange(next_seed, next_seed + width, device=device).repeat_interleave(remaining.numel())
        q = _seed_q(pool, distance, first, remaining, width, next_seed)
        if next_seed == 0:  # until a better one is found, a problem's answer is its first seed
            answers.q.copy_(q[:, :b])
        slot_rest = None if rest is None else rest[problem].T.contiguous()
        _run_round(settings, q, tgt.take(problem), slot_rest, problem, number, answers)
        next_seed += width
        remaining = remaining[answers.E[remaining] >= 0]


def _run_round(settings: _Settings, q, slot_tgt: _Target, slot_rest, problem, number, answers: _Answers) -> None:
    """The LM iterations of one round of seeds ``q (n, s)``; slots leave as they converge or as a
    lower-numbered seed of their problem converges."""
    chain, opts = settings.chain, settings.options
    free_steps = opts.unconstrained_steps
    J, e, E, pos_err, rot_err = _evaluate(chain, q, slot_tgt, opts.rot_weight)
    # Initial damping: 1% of the squared error, at most opts.damping: a seed near its answer
    # (tracking) starts with nearly Gauss-Newton steps (measured: 2.7 instead of 4.1
    # iterations from 0.05 rad away; no change from random seeds).
    state = _LMState(q, J, e, E, pos_err, rot_err, (0.01 * E).clamp(settings.lam_min, opts.damping))
    checked = 0
    for step in range(opts.iterations):
        if step == free_steps and step:  # the unconstrained start ends: into the limits
            q = into_limits(state.q, settings.lo, settings.hi)
            state = _LMState(q, *_evaluate(chain, q, slot_tgt, opts.rot_weight), state.lam)
        state = _lm_step(settings, state, slot_tgt, step >= free_steps, slot_rest)
        if (step + 1) % opts.check_every and step + 1 < opts.iterations:
            continue
        answers.used.index_add_(0, problem, torch.full_like(problem, step + 1 - checked))
        checked = step + 1
        keep = _check_slots(settings, state, step, problem, number, answers, slot_tgt.obstacles)
        if keep.numel() < problem.numel():
            problem, number, slot_tgt, state = problem[keep], number[keep], slot_tgt.take(keep), state.take(keep)
            slot_rest = None if slot_rest is None else _take(slot_rest, keep)
        if not problem.numel():
            break


def _check_slots(
    settings: _Settings, state: _LMState, step: int, problem, number, answers: _Answers, obstacles
) -> Tensor:
    """Record each problem's best slot in ``answers``; return the indices of the slots that run on.
    With ``obstacles``, a slot is done when its pose has converged and it is clear; without the
    clearance residual, one whose pose converged in a collision stops (its next seed may be clear)."""
    opts = settings.options
    done = (state.pos_err <= 0.5 * opts.pos_tol) & (state.rot_err <= 0.5 * opts.rot_tol)
    E = state.E
    if step < opts.unconstrained_steps:  # only the unconstrained start can leave the limits
        inside = ((state.q >= settings.lo) & (state.q <= settings.hi)).all(0)
        done, E = done & inside, torch.where(inside, E, math.inf)
    stop = done
    at = None if obstacles is None else done.nonzero().squeeze(1)
    if at is not None and at.numel():  # a clearance query costs milliseconds even for a few slots
        clear = obstacles.take(at).clear(_take(state.q, at))
        done = done.index_put((at,), clear)
        stop = done if obstacles.residual else stop
    # Converged slots rank below every error, the lowest seed number first, so the
    # answer does not depend on how many seeds ran side by side.
    seeds = opts.seeds
    key = torch.where(done, (number - seeds).to(E.dtype), E)
    answers.E = _keep_best(answers.q, answers.E, state.q, key, problem)
    # A slot runs on while no lower-numbered seed of its problem has converged.
    winner = torch.where(answers.E < 0, answers.E + seeds, seeds)  # lowest converged seed number
    return (~stop & (number < winner[problem])).nonzero().squeeze(1)
