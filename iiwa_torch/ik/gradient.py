"""Batched gradient-based inverse kinematics.

- :func:`solve`: damped least squares / Levenberg-Marquardt on the geometric Jacobian, for
  thousands of targets at once, with joint limits, several seeds per target and an optional
  null-space pull toward a rest posture.
- :func:`minimize`: IK as gradient descent (``torch.optim``) on any differentiable loss of
  the joint angles and the end-effector pose.

How :func:`solve` is fast on a CPU: the inner loop keeps every quantity batch last, as
``(rows, batch)`` tensors, so each operation is one elementwise kernel over the whole batch
(no batched ``4x4`` products; for large batches no per-problem LAPACK call either: the
damped ``6x6`` normal equations are solved by a Cholesky factorisation written out over the
batch). Problems that converge leave the batch every ``check_every`` iterations, and the ones
that stall restart from their next seed, so the batch shrinks as the solve goes on.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Literal, NamedTuple, get_args

import torch

from .. import so3
from ..chain import Chain
from ..checks import check_choice, check_finite, check_float_tensor, check_generator, check_instance, check_positive
from ..collision import Capsules, World, check_world, clearance, pairwise_clearance, robot_capsules
from . import small
from .dls import dls_step_batch_last
from .lm_setup import (
    DAMP_DOWN,
    DAMP_UP,
    FREE_STEPS,
    LAMBDA0,
    POOL,
    Mode,
    Precision,
    broadcast_q,
    check_solve_options,
    inner_limits,
    into_limits,
    pool_distance,
    round_width,
    seed_ranks,
    work_dtype,
)
from .result import IKResult

__all__ = [
    "Optimizer",
    "clearance_shortfall",
    "ik_result",
    "minimize",
    "solve",
]

Tensor = torch.Tensor
Optimizer = Literal["adam", "lbfgs"]

# With a world, the clearance residual acts below margin + _CLEAR_BUFFER and a seed counts as
# clear at margin + _CLEAR_BUFFER / 2 (m): far above float32 rounding of the distances, so the
# float64 check of the answer agrees.
_CLEAR_BUFFER = 2e-3
_COLLIDING_RANK = 100.0  # added to a colliding pool entry's pose distance: clear entries are tried first


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


class _Obstacles(NamedTuple):
    """A world in the loop's dtype: ``world`` unbatched, or with one leading dimension over the
    problems (``batched``), the robot's ``capsules`` and the clearance ``margin`` (m). With
    ``residual``, the LM objective has the clearance residual; else the clearance is only
    checked when a slot's pose has converged."""

    chain: Chain
    world: World
    batched: bool
    capsules: Capsules
    margin: float
    residual: bool = False

    def take(self, index: Tensor) -> _Obstacles:
        if not self.batched:
            return self
        return self._replace(world=self.world.map_batch(lambda t, _: t.index_select(0, index)))

    def clearance(self, q: Tensor) -> Tensor:
        """``q (n, b)`` -> minimum signed clearance ``(b,)``, m."""
        return clearance(self.chain, q.T, self.world, self.capsules)

    def colliding(self, pool: Tensor) -> Tensor:
        """``pool (p, n)`` -> ``(p,)`` float, 1 where a configuration is not clear of the part of
        the world every problem shares (all of it, or the robot itself and the floor if batched)."""
        shared = World(floor=self.world.floor) if self.batched else self.world
        return (clearance(self.chain, pool, shared, self.capsules) < self.margin + _CLEAR_BUFFER).to(pool.dtype)


class _Target:
    """Targets in the loop's layout: rotation axes ``(3, 3, b)`` (axis, component) and the same
    with rolled components (for cross products), position ``(3, b)``; or position only. With
    ``obstacles``, the objective also has the clearance residual (:func:`_clearance_row`)."""

    def __init__(
        self, rot: Tensor | None, pos: Tensor, rolled: Tensor | None = None, obstacles: _Obstacles | None = None
    ) -> None:
        self.pos, self.rot, self.obstacles = pos, rot, obstacles
        self.rolled = None if rot is None else _roll(rot, 1) if rolled is None else rolled

    def take(self, index: Tensor) -> _Target:
        obstacles = None if self.obstacles is None else self.obstacles.take(index)
        if self.rot is None:
            return _Target(None, _take(self.pos, index), obstacles=obstacles)
        return _Target(_take(self.rot, index), _take(self.pos, index), _take(self.rolled, index), obstacles)

    def with_obstacles(self, obstacles: _Obstacles) -> _Target:
        return _Target(self.rot, self.pos, self.rolled, obstacles)


def _evaluate(
    chain: Chain, q: Tensor, target: _Target, weight: float
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """``q (n, b)`` -> weighted Jacobian ``J (m, n, b)``, weighted error ``e (m, b)`` (m = 6 or 3,
    one more with obstacles: the clearance residual), squared weighted error ``E (b,)``, position
    error ``(b,)`` m, rotation error ``(b,)`` rad."""
    terms = _pose_terms(chain, q, target, weight)
    if target.obstacles is None or not target.obstacles.residual:
        return terms
    J, e, E, pos_err, rot_err = terms
    r, grad = _clearance_row(q, target.obstacles)
    return torch.cat([J, grad[None]]), torch.cat([e, -r[None]]), E + r * r, pos_err, rot_err


def _clearance_row(q: Tensor, obstacles: _Obstacles) -> tuple[Tensor, Tensor]:
    """``q (n, b)`` -> the clearance residual ``r = |max(0, margin + buffer - d)| (b,)`` (m) over
    every checked pair's distance ``d``, and its gradient ``(n, b)`` (m/rad).

    A residual beside the six pose rows, rather than a clearance-gradient step projected into
    the Jacobian's null space, lets LM weigh the two: where the arm's redundancy can satisfy
    both, the 7-row system's solution moves along the null space of the pose rows; where it
    cannot, the step is the least-squares compromise and the answer stays finite. The norm
    over all pairs (not the minimum) keeps every pair that is too near in the step at once,
    so it does not alternate between two obstacles."""
    with torch.enable_grad():
        x = q.T.detach().requires_grad_(True)
        sq = clearance_shortfall(obstacles.chain, x, obstacles.world, obstacles.margin, obstacles.capsules)
        (grad,) = torch.autograd.grad(sq.sum(), x)
    r = sq.detach().sqrt()
    return r, grad.T / (2 * r).clamp_min(torch.finfo(q.dtype).tiny)


def clearance_shortfall(
    chain: Chain, q: Tensor, world: World, margin: float, capsules: Capsules | None = None
) -> Tensor:
    """``sum_p max(0, margin + 2 mm - d_p)^2`` over every checked pair's signed distance ``d_p``
    (:func:`~iiwa_torch.collision.pairwise_clearance`): ``q (..., n) -> (...)``, m^2, zero once
    every pair clears ``margin`` by 2 mm. Differentiable; the penalty both solvers use."""
    d = pairwise_clearance(chain, q, world, capsules).distance
    return (margin + _CLEAR_BUFFER - d).clamp_min(0).square().sum(-1)


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


def _lm_step(chain, state: _LMState, target, weight, limits, rest, rest_gain, lam_min, lam_max) -> _LMState:
    """One Levenberg-Marquardt step for every slot: a step is kept where it lowers ``E``, and
    the damping follows. ``limits`` is ``(lo, hi)``, each ``(n, 1)``, or None for an
    unconstrained step."""
    q, J, e, E, pos_err, rot_err, lam = state
    free = None
    if limits is not None:  # box constraint: joints at a limit that E pushes outward are frozen
        lo, hi = limits
        descent = (J * e[:, None]).sum(0)  # J^T e (n, b), where E wants each joint to go
        # 1 where a unit move along the descent, projected into the limits, still moves the
        # joint, else 0; float arithmetic throughout (boolean ops are several times slower here).
        moved = torch.minimum(torch.maximum(q + torch.sign(descent), lo), hi) - q
        free = moved.abs_().sign_()
    if rest is None:
        dq = dls_step_batch_last(J, e[:, None], lam, lam_min, free)[:, 0]
    else:  # pull toward the rest posture inside the (damped) null space of J, while the damping
        # is low: a large damping would turn the projected pull into the full pull.
        pull = rest_gain * (rest - q) * (lam <= LAMBDA0)
        pull = pull if free is None else pull * free
        sol = dls_step_batch_last(J, torch.stack([e, (J * pull).sum(1)], 1), lam, lam_min, free)
        dq = sol[:, 0] + pull - sol[:, 1]
    q_new = q + dq if limits is None else torch.minimum(torch.maximum(q + dq, lo), hi)
    J_new, e_new, E_new, pos_new, rot_new = _evaluate(chain, q_new, target, weight)
    # lerp with weight 0 or 1 is exact, and cheaper than torch.where (the solve's time: benchmarks/results/ik.md)
    kept = (E_new < E).to(q.dtype)
    return _LMState(
        torch.lerp(q, q_new, kept),
        torch.lerp(J, J_new, kept),
        torch.lerp(e, e_new, kept),
        torch.lerp(E, E_new, kept),
        torch.lerp(pos_err, pos_new, kept),
        torch.lerp(rot_err, rot_new, kept),
        (lam * torch.lerp(torch.full_like(lam, DAMP_UP), torch.full_like(lam, DAMP_DOWN), kept)).clamp_(
            lam_min, lam_max
        ),
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


def _check_target(target: Tensor, mode: str, dtype: torch.dtype | None, batch: torch.Size | None) -> torch.Size:
    """Validate a pose ``(..., 4, 4)`` or position ``(..., 3)`` target; return its batch shape."""
    if mode == "pose":
        if isinstance(target, torch.Tensor) and target.ndim and target.shape[-1] == 3:
            raise ValueError(
                f"target must have shape (..., 4, 4) (poses), got {tuple(target.shape)}; "
                'for positions (..., 3) pass mode="position"'
            )
        so3.check_rigid(target, "target")
        found = target.shape[:-2]
    else:
        check_float_tensor(target, "target", "(..., 3) in position mode")
        if target.ndim == 0 or target.shape[-1] != 3:
            raise ValueError(f"target must have shape (..., 3) in position mode, got {tuple(target.shape)}")
        check_finite(target, "target")
        found = target.shape[:-1]
    if dtype is not None and target.dtype != dtype:
        raise ValueError(f"target must have the dtype of q0 ({dtype}), got {target.dtype}")
    if batch is not None and found != batch:
        raise ValueError(f"target's batch shape {tuple(found)} must match q0's {tuple(batch)}")
    return found


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
    mode: Mode = "pose",
    rot_weight: float = 1.0,
    pos_tol: float = 1e-4,
    rot_tol: float = 1e-3,
    seeds: int = 32,
    iterations: int = 16,
    rest: Tensor | None = None,
    rest_gain: float = 0.0,
    check_every: int = 2,
    precision: Precision = "auto",
    generator: torch.Generator | None = None,
    world: World | None = None,
    margin: float = 0.0,
    capsules: Capsules | None = None,
) -> IKResult:
    """Inverse kinematics for a batch of targets by damped least squares (Levenberg-Marquardt).

    Args:
        chain: the robot.
        target: ``(..., 4, 4)`` end-effector poses (``mode="pose"``) or ``(..., 3)`` positions
            (``mode="position"``), metres, in the chain's world frame. The dtype (float32 or
            float64) and device of the solve and of the result follow it.
        q0: optional ``(..., n)`` first seed (broadcast to the targets), e.g. the previous
            solution when tracking; an angle outside its limits is shifted by 2 pi or clamped.
        mode: ``"pose"`` (position and orientation) or ``"position"`` (orientation free).
        rot_weight: metres per radian of rotation error in the least-squares objective.
        pos_tol, rot_tol: success tolerances, metres and radians (defaults 0.1 mm, 1 mrad).
        seeds: starting configurations per target: ``q0`` if given, then configurations drawn
            within the limits from ``generator``, nearest in pose to the target first. A seed
            costs only if the ones before it failed, so the default 32 costs nothing on reachable
            targets that converge early (at 1e-5, 8 seeds solve 99.3% of random Panda poses,
            32 seeds 99.96%; a 6-joint arm has up to 8 branches and its limits cut some).
        iterations: LM iterations per seed before a problem that has not converged restarts.
        rest, rest_gain: optional ``(..., n)`` posture and gain (per iteration, 0 to 1): each
            step also moves ``rest_gain * (rest - q)`` inside the Jacobian's null space, so a
            redundant arm (the iiwa) stays near ``rest`` (pass ``rest=q0`` when tracking).
        check_every: iterations between convergence checks (each check syncs and removes
            converged problems from the batch).
        precision: ``"auto"``: float64 targets are iterated in float32 (half the memory
            traffic) when both tolerances are at least 1e-5, and the answer is checked in
            float64; ``"input"``: iterate in the target's dtype.
        generator: source of the random seeds (default: a fresh generator seeded with 0, so
            results are reproducible).
        world: optional :class:`~iiwa_torch.collision.World` (the target's dtype and device;
            a batch shape, if any, broadcasting to the targets'). Then ``success`` also needs
            the clearance of ``q`` (self pairs and world, :func:`~iiwa_torch.collision.clearance`)
            to be at least ``margin``: collision-free pool seeds are tried first, and every
            answer that is not clear is solved again from itself and further seeds with a
            clearance residual in the LM system. ``None``: no collision check.
        margin: the clearance required with a world, metres (>= 0).
        capsules: the robot's capsule model with a world (default
            :func:`~iiwa_torch.collision.robot_capsules` of the chain; a custom ``Chain``
            needs its own).

    Returns:
        :class:`IKResult` with ``q (..., n)`` always within the joint limits; the errors and
        ``success`` come from ``chain.fk(q)``; ``iterations`` counts every iteration spent on a
        problem, over all its seeds; ``clearance`` is the clearance of ``q`` with a world, else
        None. A target that cannot be reached (or only through a collision) is not an error:
        its ``success`` is False and ``q`` is the best attempt (smallest weighted error, the
        clearance shortfall included).

    The solve is not differentiable (it runs under ``torch.no_grad``); use :func:`minimize`
    to optimise through IK.
    """
    check_instance(chain, Chain, "chain")
    check_solve_options(mode, rot_weight, pos_tol, rot_tol, iterations, check_every, rest_gain, precision)
    check_positive(seeds, "seeds", integer=True)
    check_generator(generator)
    batch = _check_target(target, mode, None, None)
    if target.device != chain.limits.device:
        raise ValueError(f"target is on {target.device} but the chain is on {chain.limits.device}")
    _check_world(world, margin, target, batch, capsules)
    dtype, device, n = target.dtype, target.device, chain.n_joints
    work = work_dtype(dtype, precision, pos_tol, rot_tol)
    flat = target.reshape(-1, *target.shape[len(batch) :])
    rest_flat = None if rest is None or rest_gain == 0 else broadcast_q(rest, chain, batch, "rest", work)
    if small.applies(target, q0, rest, world, flat.shape[0]):  # it caches the default generator's pool
        return small.solve_small(
            chain, target, q0, rest_flat, mode=mode, work=work, generator=generator, rot_weight=rot_weight,
            pos_tol=pos_tol, rot_tol=rot_tol, seeds=seeds, iterations=iterations, rest_gain=rest_gain,
            check_every=check_every,
        )  # fmt: skip

    if generator is None:
        generator = torch.Generator(device).manual_seed(0)
    with torch.no_grad():
        flat = flat.to(work)
        lo, hi = (x[:, None] for x in inner_limits(chain, work))  # (n, 1) each
        first = None if q0 is None else into_limits(broadcast_q(q0, chain, batch, "q0", work).T, lo, hi).T
        obstacles = None if world is None else _obstacles(chain, world, margin, batch, work, capsules)
        # Seeds: q0, then pool configurations ranked by pose distance to each target.
        pool = distance = None  # not needed when q0 is the only seed (tracking)
        if seeds > (first is not None):
            pool = chain.random_q(max(POOL, seeds), generator=generator, dtype=work)
            distance = pool_distance(chain, pool, flat, mode)  # (pool, b)
            if obstacles is not None:
                distance += _COLLIDING_RANK * obstacles.colliding(pool)[:, None]
        tgt = _Target(
            None if mode == "position" else flat[:, :3, :3].permute(2, 1, 0).contiguous(),
            (flat if mode == "position" else flat[:, :3, 3]).T.contiguous(),
            obstacles=obstacles,
        )
        settings = _Settings(
            chain, float(rot_weight), lo, hi, 1e-12 if work == torch.float64 else 1e-6, rest_gain,
            iterations, min(FREE_STEPS, iterations // 2), check_every, seeds, pos_tol, rot_tol,
        )  # fmt: skip
        answers = _Answers.empty(n, flat.shape[0], work, device)
        _run_rounds(settings, tgt, rest_flat, pool, distance, first, answers)
        if obstacles is not None:
            _clear_answers(settings, tgt, rest_flat, pool, distance, answers)
        q_out = answers.q.T.to(dtype).reshape(*batch, n)
        result = ik_result(chain, q_out, target, mode, pos_tol, rot_tol, answers.used.reshape(batch))
        return result if world is None else _with_clearance(chain, result, world, margin, capsules)


def _check_world(world, margin, target: Tensor, batch: torch.Size, capsules) -> None:
    """Validate :func:`solve`'s (or :func:`minimize`'s) ``world``, ``margin`` and ``capsules`` for
    ``target``: :func:`~iiwa_torch.collision.check_world`, then the target's dtype and device and
    a batch shape that broadcasts to the targets'."""
    check_world(world, margin, capsules)
    if world is None:
        return
    for t in world.tensors():
        if t.dtype != target.dtype or t.device != target.device:
            raise TypeError(
                f"world obstacles are {t.dtype} on {t.device} but the target is {target.dtype} on {target.device}; "
                "build the world in the target's dtype and device"
            )
    world.check_batch(batch)


def _obstacles(chain: Chain, world: World, margin: float, batch: torch.Size, work: torch.dtype,
               capsules: Capsules | None) -> _Obstacles:
    """``world`` in the loop's dtype, a batch shape (if any) expanded and flattened to the problems'."""
    batched = len(world.batch_shape) > 0

    def cast(t: Tensor, event: int) -> Tensor:
        if batched:
            event_shape = t.shape[t.ndim - event :]
            t = t.expand(*batch, *event_shape).reshape(-1, *event_shape)
        return t.to(work)

    capsules = robot_capsules(chain) if capsules is None else capsules
    return _Obstacles(chain, world.map_batch(cast), batched, capsules, float(margin))


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


def _with_clearance(chain: Chain, result: IKResult, world: World, margin: float,
                    capsules: Capsules | None) -> IKResult:
    """``result`` with the clearance of its ``q`` (in the target's dtype); success needs ``>= margin``."""
    d = clearance(chain, result.q, world, capsules)
    return replace(result, success=result.success & (d >= margin), clearance=d)


class _Settings(NamedTuple):
    """What every round of :func:`solve` shares; ``lo, hi (n, 1)`` the inner joint limits (rad),
    ``lam_min`` the damping floor (m^2), ``free_steps`` the unconstrained steps of each seed."""

    chain: Chain
    weight: float
    lo: Tensor
    hi: Tensor
    lam_min: float
    rest_gain: float
    iterations: int
    free_steps: int
    check_every: int
    seeds: int
    pos_tol: float
    rot_tol: float


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
    b, seeds = answers.E.shape[0], settings.seeds
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
    chain, weight, lo, hi = settings.chain, settings.weight, settings.lo, settings.hi
    J, e, E, pos_err, rot_err = _evaluate(chain, q, slot_tgt, weight)
    # Initial damping: 1% of the squared error, at most LAMBDA0: a seed near its answer
    # (tracking) starts with nearly Gauss-Newton steps (measured: 2.7 instead of 4.1
    # iterations from 0.05 rad away; no change from random seeds).
    state = _LMState(q, J, e, E, pos_err, rot_err, (0.01 * E).clamp(settings.lam_min, LAMBDA0))
    checked = 0
    for step in range(settings.iterations):
        if step == settings.free_steps and step:  # the unconstrained start ends: into the limits
            q = into_limits(state.q, lo, hi)
            state = _LMState(q, *_evaluate(chain, q, slot_tgt, weight), state.lam)
        limits = None if step < settings.free_steps else (lo, hi)
        state = _lm_step(chain, state, slot_tgt, weight, limits, slot_rest, settings.rest_gain, settings.lam_min, 1e4)
        if (step + 1) % settings.check_every and step + 1 < settings.iterations:
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
    done = (state.pos_err <= 0.5 * settings.pos_tol) & (state.rot_err <= 0.5 * settings.rot_tol)
    E = state.E
    if step < settings.free_steps:  # only the unconstrained start can leave the limits
        inside = ((state.q >= settings.lo) & (state.q <= settings.hi)).all(0)
        done, E = done & inside, torch.where(inside, E, math.inf)
    stop = done
    at = None if obstacles is None else done.nonzero().squeeze(1)
    if at is not None and at.numel():  # a clearance query costs milliseconds even for a few slots
        clear = obstacles.take(at).clearance(_take(state.q, at)) >= obstacles.margin + _CLEAR_BUFFER / 2
        done = done.index_put((at,), clear)
        stop = done if obstacles.residual else stop
    # Converged slots rank below every error, the lowest seed number first, so the
    # answer does not depend on how many seeds ran side by side.
    seeds = settings.seeds
    key = torch.where(done, (number - seeds).to(E.dtype), E)
    answers.E = _keep_best(answers.q, answers.E, state.q, key, problem)
    # A slot runs on while no lower-numbered seed of its problem has converged.
    winner = torch.where(answers.E < 0, answers.E + seeds, seeds)  # lowest converged seed number
    return (~stop & (number < winner[problem])).nonzero().squeeze(1)


def ik_result(
    chain: Chain, q: Tensor, target: Tensor, mode: str, pos_tol: float, rot_tol: float, iterations: Tensor
) -> IKResult:
    """Errors and success from the public ``chain.fk`` of the returned ``q``."""
    pose = chain.fk(q)
    if mode == "pose":
        pos_vec, rot_vec = so3.pose_error(pose, target)
        rot_err = rot_vec.norm(dim=-1)
    else:
        pos_vec = target - pose[..., :3, 3]
        rot_err = torch.zeros_like(pos_vec[..., 0])
    pos_err = pos_vec.norm(dim=-1)
    success = (pos_err <= pos_tol) & (rot_err <= rot_tol)
    return IKResult(q=q, success=success, pos_err=pos_err, rot_err=rot_err, iterations=iterations)


# ---------------------------------------------------------------------- minimize
def minimize(
    chain: Chain,
    loss: Callable[[Tensor, Tensor], Tensor],
    q0: Tensor,
    *,
    target: Tensor,
    mode: Mode = "pose",
    optimizer: Optimizer = "adam",
    steps: int = 500,
    lr: float | None = None,
    pos_tol: float = 1e-4,
    rot_tol: float = 1e-3,
    success_fn: Callable[[Tensor, Tensor], Tensor] | None = None,
    world: World | None = None,
    margin: float = 0.0,
    clearance_weight: float = 1.0,
    capsules: Capsules | None = None,
) -> IKResult:
    """IK by gradient descent on any differentiable loss, for a batch of problems.

    Args:
        chain: the robot.
        loss: ``loss(q, pose) -> (...)``, one value per problem, from the joint angles
            ``q (..., n)`` and the end-effector pose ``chain.fk(q) (..., 4, 4)``; it may call
            ``chain.fk_all(q)`` for other links (e.g. to keep the elbow high).
        q0: ``(..., n)`` starting joint angles (clamped into the limits); sets dtype and batch.
        target: ``(..., 4, 4)`` poses (``mode="pose"``) or ``(..., 3)`` positions
            (``mode="position"``) that define ``pos_err``, ``rot_err`` and ``success``; the
            loss itself should contain the reaching term (the target is not added to it).
        optimizer: ``"adam"`` (default; each problem is optimised independently, its step
            size decays from ``lr`` to ``lr / 100``) or ``"lbfgs"`` (strong Wolfe line search
            on the summed loss, so the batch shares one step length: best for small batches).
        steps: optimiser steps (L-BFGS: iterations, with at most ``2 * steps`` evaluations).
        lr: learning rate (default 0.1 rad for Adam, 1 for L-BFGS).
        pos_tol, rot_tol: success tolerances, metres and radians.
        success_fn: optional ``(q, pose) -> (...)`` bool, a further criterion of the caller's
            loss (e.g. "elbow above 0.5 m"); success needs it and the tolerances.
        world, margin, clearance_weight: optional :class:`~iiwa_torch.collision.World` (``q0``'s
            dtype and device, batch broadcasting to ``q0``'s), a clearance in metres (>= 0) and
            a weight (1/m^2 of loss per m^2): the loss gets the term ``clearance_weight *``
            :func:`clearance_shortfall`, success needs a clearance >= ``margin``, and the
            result carries ``clearance``.
        capsules: the capsule model with a world (default: the chain's preset model).

    Joint limits are kept by projection: the loss sees the parameters clamped into the limits,
    and the parameters are clamped after every step. Each problem returns the lowest-loss ``q``
    seen; ``iterations`` is ``steps`` for every problem.
    """
    check_instance(chain, Chain, "chain")
    check_choice(mode, get_args(Mode), "mode")
    check_choice(optimizer, get_args(Optimizer), "optimizer")
    check_positive(steps, "steps", integer=True)
    for value, name in ((pos_tol, "pos_tol"), (rot_tol, "rot_tol")) + (() if lr is None else ((lr, "lr"),)):
        check_positive(value, name)
    if not callable(loss) or (success_fn is not None and not callable(success_fn)):
        raise TypeError("loss and success_fn must be callables (q, pose) -> tensor of shape q.shape[:-1]")
    chain.check_q(q0, "q0")
    batch = q0.shape[:-1]
    _check_target(target, mode, q0.dtype, batch)
    _check_world(world, margin, target, batch, capsules)
    check_positive(clearance_weight, "clearance_weight")
    if world is not None and capsules is None:
        capsules = robot_capsules(chain)

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
        return value + clearance_weight * clearance_shortfall(chain, q, world, margin, capsules)

    lo, hi = inner_limits(chain, q0.dtype)

    def clamp(q: Tensor) -> Tensor:
        return torch.minimum(torch.maximum(q, lo), hi)

    u = clamp(q0.detach()).requires_grad_(True)
    opt, decay = _optimizer(u, optimizer, steps, lr)
    best_q = u.detach().clone()
    best_loss = torch.full(batch, math.inf, dtype=q0.dtype, device=q0.device)

    def closure() -> Tensor:
        nonlocal best_loss
        opt.zero_grad()
        q = clamp(u)
        value = objective(q)
        with torch.no_grad():  # every evaluated q is within limits, so any may be the answer
            better = value < best_loss
            best_q.copy_(torch.where(better[..., None], q, best_q))
            best_loss = torch.where(better, value.detach(), best_loss)
        value.sum().backward()
        return value.sum()

    for _ in range(steps if decay is not None else 1):
        opt.step(closure)
        with torch.no_grad():  # projection; a non-finite update (from the caller's loss) restarts from the best
            u.copy_(clamp(torch.where(torch.isfinite(u), u, best_q)))
        if decay is not None:
            decay.step()
    with torch.no_grad():
        q = clamp(u)
        best_q = torch.where((objective(q) < best_loss)[..., None], q, best_q)
        result = _minimize_result(chain, best_q, target, mode, pos_tol, rot_tol, steps, success_fn)
        return result if world is None else _with_clearance(chain, result, world, margin, capsules)


def _optimizer(u: Tensor, optimizer: str, steps: int, lr: float | None):
    """``(torch optimizer, learning-rate schedule or None)`` for :func:`minimize`."""
    if optimizer == "adam":
        opt = torch.optim.Adam([u], lr=0.1 if lr is None else lr)
        return opt, torch.optim.lr_scheduler.ExponentialLR(opt, gamma=0.01 ** (1 / steps))
    # One call runs every iteration: torch's L-BFGS keeps its history within a call.
    opt = torch.optim.LBFGS(
        [u],
        lr=1.0 if lr is None else lr,
        max_iter=steps,
        max_eval=2 * steps,
        line_search_fn="strong_wolfe",
        tolerance_grad=0.0,
        tolerance_change=0.0,
        history_size=20,
    )
    return opt, None


def _minimize_result(chain, q, target, mode, pos_tol, rot_tol, steps, success_fn) -> IKResult:
    """:func:`minimize`'s answer ``q (..., n)`` -> :class:`IKResult`, with the caller's extra criterion."""
    batch = q.shape[:-1]
    iterations = torch.full(batch, steps, dtype=torch.long, device=q.device)
    result = ik_result(chain, q, target, mode, pos_tol, rot_tol, iterations)
    if success_fn is None:
        return result
    extra = success_fn(q, chain.fk(q))
    if not isinstance(extra, torch.Tensor) or extra.shape != batch:
        raise ValueError(f"success_fn must return one bool per problem, shape {tuple(batch)}")
    return IKResult(q, result.success & extra.bool(), result.pos_err, result.rot_err, iterations)
