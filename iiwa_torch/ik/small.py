"""The low-overhead path of :func:`~iiwa_torch.ik.solve` for a few targets on the CPU.

For a batch of ``SMALL_BATCH`` targets or fewer, on the CPU, with no world and nothing to
differentiate (:func:`applies`), :func:`~iiwa_torch.ik.solve` runs its Levenberg-Marquardt
iteration here in numpy (float64) instead of torch, or up to ``COMPILED_BATCH`` targets in
compiled code (:func:`iiwa_torch.compiled.numba_kernels.lm_rounds`, when enabled): the same
seeds (the same pool, drawn from the same generator, in the same order), damping schedule,
free steps and projection into the limits, convergence checks and choice of answer, with the
end pose and Jacobian of :func:`~iiwa_torch.kinematics.pose_jacobian_numpy`. A torch op costs
several microseconds however small its tensors, a numpy op about one, and an iteration takes a
few dozen ops. The numpy rounds run seeds side by side as the batched loop does; the compiled
ones one seed per problem (see :meth:`_Problems.run`), which changes the work, not the answers.
The layout is batch first: ``(slots, ...)``, a slot being one seed of one problem.
:func:`track_small` runs the gradient method of :func:`~iiwa_torch.trajectory.track` (one
such solve per pose) in one call.
"""

from __future__ import annotations

from weakref import WeakKeyDictionary

import numpy as np
import torch

from .. import compiled
from ..chain import Chain
from ..kinematics import end_pose_matmul, floats_ok, pose_jacobian_numpy
from .lm_setup import (
    DAMP_DOWN,
    DAMP_UP,
    FREE_STEPS,
    LAMBDA0,
    POOL,
    broadcast_q,
    check_solve_options,
    inner_limits,
    into_limits,
    pool_distance,
    pool_features,
    round_width,
    seed_ranks,
    work_dtype,
)
from .result import IKResult

__all__ = ["COMPILED_BATCH", "SMALL_BATCH", "applies", "batch_limit", "pose_errors", "solve_small", "track_small"]

SMALL_BATCH = 64  # up to this many targets per call, solve iterates in numpy
COMPILED_BATCH = 1024  # with the compiled kernels, up to this many (measured: 1.5x the torch loop at 1,000)


def batch_limit() -> int:
    """The most targets per call this path takes: ``COMPILED_BATCH`` with the compiled kernels
    (:data:`iiwa_torch.compiled.ENABLED`), else ``SMALL_BATCH``."""
    return COMPILED_BATCH if compiled.ENABLED else SMALL_BATCH


def applies(target: torch.Tensor, q0, rest, world, size: int) -> bool:
    """Whether :func:`~iiwa_torch.ik.solve` takes this path for ``size`` targets: at most
    :func:`batch_limit`, no world, and ``target``, ``q0`` and ``rest`` on the CPU with nothing to
    differentiate (:func:`~iiwa_torch.kinematics.floats_ok`)."""
    given = [t for t in (target, q0, rest) if t is not None]
    # anything but a tensor goes the batched way, to the same error message as before
    return world is None and size <= batch_limit() and all(isinstance(t, torch.Tensor) and floats_ok(t) for t in given)


_SKEW = np.array([5, 6, 1]), np.array([7, 2, 3])  # (1, 2), (2, 0), (0, 1) and their mirrors in a flat 3x3


def pose_errors(pose: np.ndarray, pos: np.ndarray, rot: np.ndarray | None, eps: float):
    """End poses ``pose (s, 4, 4)`` against target positions ``pos (s, 3)`` and rotations
    ``rot (s, 3, 3)`` (None: position only) -> position error ``(s, 3)`` (target - pose, m)
    and its norm ``(s,)``, the rotation vector ``log(rot R^T) (s, 3)`` (rad; zeros without
    ``rot``) and its angle ``(s,)``. Below ``eps`` of sine the vector only shrinks (finite
    also at a half turn, as the batched loop's)."""
    e_pos = pos - pose[:, :3, 3]
    pos_err = np.sqrt((e_pos * e_pos).sum(1))
    if rot is None:
        return e_pos, pos_err, np.zeros_like(e_pos), np.zeros_like(pos_err)
    # log(R_t R^T): its skew part is sum_k r_k x t_k / 2 over the axes (columns) r_k, t_k, the
    # antisymmetric part of W = R R_t^T, and its trace is sum_k r_k . t_k
    W = (pose[:, :3, :3] @ rot.transpose(0, 2, 1)).reshape(-1, 9)
    v = 0.5 * (W[:, _SKEW[0]] - W[:, _SKEW[1]])  # sin(angle) * axis
    sin = np.sqrt((v * v).sum(1))
    angle = np.arctan2(sin, (W[:, 0] + W[:, 4] + W[:, 8] - 1) * 0.5)
    return e_pos, pos_err, v * (angle / np.maximum(sin, eps))[:, None], angle


class _Problems:
    """What every round shares: targets ``pos (b, 3)`` and ``rot (b, 3, 3)`` (or None) in
    float64, the rest posture ``rest (b, n)`` or None, limits ``lo, hi (n,)``, the options of
    :func:`~iiwa_torch.ik.solve`, and the answers so far: ``q (b, n)``, key ``E (b,)``
    (below 0: converged, the seed number minus ``seeds``) and iterations ``used (b,)``; the
    options again as :func:`iiwa_torch.compiled.numba_kernels.lm_rounds` takes them
    (``kernel_options``, ``kernel_counts``). ``work``: the dtype the batched loop would iterate
    in, which sets the smallest damping and the rounding ``eps``."""

    def __init__(self, chain: Chain, pos, rot, rest, lo, hi, options: dict, work: torch.dtype):
        self.g = chain.geometry(torch.float64)
        self.rest, self.lo, self.hi = rest, lo, hi
        lam_min, eps = 1e-12 if work == torch.float64 else 1e-6, torch.finfo(work).eps
        self.weight = float(options["rot_weight"])
        self.rest_gain = options["rest_gain"]
        self.iterations, self.check_every = options["iterations"], options["check_every"]
        self.free_steps = min(FREE_STEPS, self.iterations // 2)
        self.seeds, self.pos_tol, self.rot_tol = options["seeds"], options["pos_tol"], options["rot_tol"]
        self.lam_min, self.eps = lam_min, eps
        self.q = np.empty((pos.shape[0], chain.n_joints))
        self.aim(pos, rot)
        self.kernel_options = np.array([self.weight, self.rest_gain, eps, lam_min, LAMBDA0, DAMP_DOWN, DAMP_UP,
                                 self.pos_tol, self.rot_tol])  # fmt: skip
        self.kernel_counts = np.array([self.iterations, self.check_every, self.free_steps, self.seeds])

    def aim(self, pos, rot) -> None:
        """New targets ``pos (b, 3)``, ``rot (b, 3, 3)`` (or None) for the same problems: no answer yet."""
        self.pos, self.rot = pos, rot
        self.E, self.used = np.full(pos.shape[0], np.inf), np.zeros(pos.shape[0], dtype=np.int64)

    def evaluate(self, q, pos, rot):
        """``q (s, n)`` and the slots' targets -> weighted Jacobian ``J (s, m, n)``, weighted error
        ``e (s, m)``, squared weighted error ``E (s,)``, position and rotation errors ``(s,)``."""
        pose, J = pose_jacobian_numpy(self.g, q)
        e_pos, pos_err, e_rot, rot_err = pose_errors(pose, pos, rot, self.eps)
        if rot is None:
            return J[:, :3], e_pos, pos_err * pos_err, pos_err, rot_err
        if self.weight != 1:
            J[:, 3:] *= self.weight
            e_rot *= self.weight
        return J, np.concatenate([e_pos, e_rot], 1), pos_err * pos_err + (self.weight * rot_err) ** 2, pos_err, rot_err

    def step(self, state, pos, rot, rest, limits: bool):
        """One LM step of every slot, as :func:`~iiwa_torch.ik.gradient` takes it: kept where it
        lowers ``E``; with ``limits``, joints at a limit that ``E`` pushes outward stay put."""
        q, J, e, E, pos_err, rot_err, lam = state
        lo, hi = self.lo, self.hi
        free = None
        Jt = J.transpose(0, 2, 1)
        if limits:
            descent = (Jt @ e[:, :, None])[:, :, 0]  # J^T e, where E wants each joint to go
            free = (np.minimum(np.maximum(q + np.sign(descent), lo), hi) != q).astype(q.dtype)
        A = (J if free is None else J * free[:, None]) @ Jt
        A.reshape(A.shape[0], -1)[:, :: A.shape[1] + 1] += lam[:, None]  # the diagonal
        if rest is None:
            rhs = e[:, :, None]
        else:
            pull = self.rest_gain * (rest - q) * (lam <= LAMBDA0)[:, None]
            pull = pull if free is None else pull * free
            rhs = np.stack([e, (J @ pull[:, :, None])[:, :, 0]], 2)
        # J diag(free) J^T + lam I has every eigenvalue >= lam >= lam_min, far above rounding
        dq = Jt @ np.linalg.solve(A, rhs)  # (s, n, k)
        if free is not None:
            dq *= free[:, :, None]
        dq = dq[:, :, 0] if rest is None else dq[:, :, 0] + pull - dq[:, :, 1]
        q_new = q + dq if not limits else np.minimum(np.maximum(q + dq, lo), hi)
        new = self.evaluate(q_new, pos, rot)
        kept = new[2] < E
        out = [np.where(kept.reshape(-1, *(1,) * (old.ndim - 1)), x, old) for x, old in zip((q_new, *new), state)]
        out.append(np.minimum(np.maximum(lam * np.where(kept, DAMP_DOWN, DAMP_UP), self.lam_min), 1e4))
        return out

    def check(self, state, step: int, problem, number):
        """Record each problem's best slot; return the indices of the slots that run on."""
        q, E, pos_err, rot_err = state[0], state[3], state[4], state[5]
        done = (pos_err <= 0.5 * self.pos_tol) & (rot_err <= 0.5 * self.rot_tol)
        if step < self.free_steps:  # only the unconstrained start can leave the limits
            inside = ((q >= self.lo) & (q <= self.hi)).all(1)
            done, E = done & inside, np.where(inside, E, np.inf)
        # converged slots rank below every error, the lowest seed number first
        key = np.where(done, (number - self.seeds).astype(E.dtype), E)
        lowest = self.E.copy()
        np.minimum.at(lowest, problem, key)
        better = ((key <= lowest[problem]) & (key < self.E[problem])).nonzero()[0]
        winner = np.full(self.E.shape[0], -1)
        np.maximum.at(winner, problem[better], better)
        improved = winner >= 0
        self.q[improved] = q[winner[improved]]
        self.E = lowest
        first_done = np.where(lowest < 0, lowest + self.seeds, self.seeds)  # lowest converged seed
        return (~done & (number < first_done[problem])).nonzero()[0]

    def run(self, pool, order, first) -> None:
        """Every round of seeds: each remaining problem tries its next seeds (``first (b, n)``, q0,
        if given, then the pool ``(P, n)`` entries of ranks ``order (ranks, b)``), side by side to
        fill ``MIN_BATCH`` slots as the batched loop does, until it converges or runs out of seeds.
        Compiled: one call of :func:`iiwa_torch.compiled.numba_kernels.lm_rounds`, whose rounds take
        one seed per problem (a compiled slot costs the same alone as beside others, so a later seed
        runs only if the earlier ones failed; the answers do not depend on the width)."""
        b, n = self.q.shape
        if compiled.ENABLED:
            none = np.empty((0, n))  # an absent input: no rows
            rot = np.empty((0, 3, 3)) if self.rot is None else self.rot
            rest = none if self.rest is None else np.ascontiguousarray(self.rest)
            order = np.empty((0, b), dtype=np.int64) if order is None else order
            pool, first = (none if x is None else x for x in (pool, first))
            compiled.kernels().lm_rounds(*self.g.float_arrays, pool, order, first, self.pos, rot, rest, self.lo,
                                         self.hi, self.kernel_options, self.kernel_counts, self.q, self.E, self.used)
            return
        shift = 0 if first is None else 1
        remaining, next_seed = np.arange(b), 0
        while remaining.size and next_seed < self.seeds:
            width = round_width(self.seeds, next_seed, remaining.size)
            problem = np.concatenate([remaining] * width)  # slot -> problem (np.tile: the same, slower)
            number = np.repeat(np.arange(next_seed, next_seed + width), remaining.size)
            ranks = None if order is None else order[max(next_seed, shift) - shift : next_seed + width - shift]
            q = pool[ranks[:, remaining].reshape(-1)] if ranks is not None else None  # pool seeds, seed-major
            if next_seed < shift:  # q0 first
                q = first[remaining] if q is None else np.concatenate([first[remaining], q])
            if next_seed == 0:  # until a better one is found, a problem's answer is its first seed
                self.q[:] = q[:b]
            self.run_round(q, problem, number)
            next_seed += width
            remaining = remaining[self.E[remaining] >= 0]

    def run_round(self, q, problem, number) -> None:
        """The LM iterations of one round of seeds ``q (s, n)``, slot ``k`` a seed of problem
        ``problem[k]`` with seed number ``number[k]``."""
        pos, rot = self.pos[problem], None if self.rot is None else self.rot[problem]
        rest = None if self.rest is None else self.rest[problem]
        J, e, E, pos_err, rot_err = self.evaluate(q, pos, rot)
        state = [q, J, e, E, pos_err, rot_err, np.clip(0.01 * E, self.lam_min, LAMBDA0)]
        checked = 0
        for step in range(self.iterations):
            if step == self.free_steps and step:  # the unconstrained start ends: into the limits
                q = into_limits(state[0], self.lo, self.hi)
                state = [q, *self.evaluate(q, pos, rot), state[6]]
            state = self.step(state, pos, rot, rest, step >= self.free_steps)
            if (step + 1) % self.check_every and step + 1 < self.iterations:
                continue
            np.add.at(self.used, problem, step + 1 - checked)
            checked = step + 1
            keep = self.check(state, step, problem, number)
            if keep.size < problem.size:
                problem, number, pos = problem[keep], number[keep], pos[keep]
                rot = None if rot is None else rot[keep]
                rest = None if rest is None else rest[keep]
                state = [x[keep] for x in state]
            if not problem.size:
                break


_NUMPY = {torch.float32: np.float32, torch.float64: np.float64}
_CACHE: WeakKeyDictionary = WeakKeyDictionary()  # Geometry -> {key: value}


def _cached(chain: Chain, dtype: torch.dtype, key, make):
    """``make()``, computed once per ``key`` and chain geometry in ``dtype``: the geometry is
    rebuilt whenever the chain's buffers change, so the value is computed again then."""
    entries = _CACHE.setdefault(chain.geometry(dtype), {})
    if key not in entries:
        entries[key] = make()
    return entries[key]


def _limits(chain: Chain, dtype: torch.dtype) -> tuple[np.ndarray, np.ndarray]:
    """:func:`~iiwa_torch.ik.lm_setup.inner_limits` for ``dtype``, as float64 numpy ``(n,)`` each."""
    return _cached(chain, dtype, "limits", lambda: tuple(x.double().numpy() for x in inner_limits(chain, dtype)))


def _pool(chain: Chain, size: int, generator, work: torch.dtype, mode: str):
    """The seed pool as :func:`~iiwa_torch.ik.solve` draws it (``generator`` None: a fresh one
    seeded with 0) -> the pool ``(size, n)`` in float64 and its :func:`pool_features` in
    ``work``, numpy arrays."""
    generator = torch.Generator().manual_seed(0) if generator is None else generator
    pool = chain.random_q(size, generator=generator, dtype=work)
    return pool.double().numpy(), tuple(x.numpy() for x in pool_features(chain, pool, mode))


def solve_small(
    chain: Chain, target: torch.Tensor, q0, rest, *, mode: str, work: torch.dtype, generator, **options
) -> IKResult:
    """:func:`~iiwa_torch.ik.solve` for checked inputs that :func:`applies` to: ``target`` as
    given, ``q0`` as given or None, ``rest (b, n)`` in ``work`` (or None), ``work`` the dtype
    the batched loop would iterate in (the seed pool is drawn and ranked in it), ``options``
    the remaining options of :func:`~iiwa_torch.ik.solve` (``seeds`` resolved)."""
    dtype, n, seeds = target.dtype, chain.n_joints, options["seeds"]
    batch = target.shape[:-2] if mode == "pose" else target.shape[:-1]
    flat = target.detach().numpy().reshape(-1, *target.shape[len(batch) :])
    b = flat.shape[0]
    lo, hi = _limits(chain, dtype)
    first = None if q0 is None else into_limits(broadcast_q(q0, chain, batch, "q0", torch.float64).numpy(), lo, hi)
    shift = 0 if first is None else 1
    pool = order = None
    if seeds > shift:
        size = max(POOL, seeds)
        if generator is None:  # a fresh generator seeded with 0 draws the same pool every time
            pool, features = _cached(chain, work, (size, mode), lambda: _pool(chain, size, None, work, mode))
        else:
            pool, features = _pool(chain, size, generator, work, mode)
        # numpy's product runs on OpenBLAS's own threads above 2^18 multiply-adds (some 340 targets),
        # whose wake-up on a busy machine can cost milliseconds; torch's keeps to torch's threads
        xp = (lambda x: x) if b <= 256 else torch.from_numpy
        distance = pool_distance(chain, pool, xp(flat.astype(_NUMPY[work])), mode, tuple(map(xp, features)))
        order = np.asarray(seed_ranks(distance, seeds - shift))  # (ranks, b)
    flat = flat.astype(np.float64, copy=False)
    # contiguous copies: the compiled kernels are typed (and compiled) for C-ordered arrays
    pos, rot = (np.ascontiguousarray(flat), None) if mode == "position" else (flat[:, :3, 3].copy(),
                                                                            flat[:, :3, :3].copy())
    rest = None if rest is None else rest.double().numpy()
    problems = _Problems(chain, pos, rot, rest, lo, hi, options, work)
    problems.run(pool, order, first)
    out_dtype = _NUMPY[dtype]
    q_flat = torch.from_numpy(problems.q.astype(out_dtype, copy=False))
    # errors and success from the answer's end pose by chain.fk's kernel for these (the batched path
    # calls chain.fk; its input checks are moot on the kernels' own answers)
    pose = end_pose_matmul(chain.geometry(dtype), q_flat).numpy().astype(np.float64, copy=False)
    if compiled.ENABLED:
        rot_in = np.empty((0, 3, 3)) if rot is None else rot
        pos_err, rot_err = compiled.kernels().pose_errors(pose, pos, rot_in, problems.eps)
    else:
        _, pos_err, _, rot_err = pose_errors(pose, pos, rot, problems.eps)
    success = (pos_err <= options["pos_tol"]) & (rot_err <= options["rot_tol"])
    pos_err, rot_err = (x.astype(out_dtype, copy=False) for x in (pos_err, rot_err))
    success, pos_err, rot_err, used = (torch.from_numpy(x.reshape(batch)) for x in (success, pos_err, rot_err,
                                                                                    problems.used))  # fmt: skip
    return IKResult(q_flat.reshape(*batch, n), success, pos_err, rot_err, used)


def track_small(chain: Chain, poses: torch.Tensor, q0: torch.Tensor, *, pos_tol: float, rot_tol: float,
                rest_gain: float, iterations: int) -> torch.Tensor:
    """The gradient method of :func:`~iiwa_torch.trajectory.track` for checked ``poses (..., T, 4, 4)``
    and ``q0 (..., n)`` of the poses' batch shape that :func:`applies` to: each pose solved as
    :func:`~iiwa_torch.ik.solve` (here :func:`solve_small`) solves it with the one seed of the
    previous answer (``q0`` first) and ``rest=q0``, so the same iterations and answers, without
    each call's checks, set-up and error report -> ``q (..., T, n)`` in the poses' dtype."""
    check_solve_options("pose", 1.0, pos_tol, rot_tol, iterations, 2, rest_gain, "auto")
    dtype, n = poses.dtype, chain.n_joints
    batch, steps = poses.shape[:-3], poses.shape[-3]
    work = work_dtype(dtype, "auto", pos_tol, rot_tol)
    flat = poses.reshape(-1, steps, 4, 4).transpose(0, 1).double().numpy()  # (T, b, 4, 4)
    pos, rot = np.ascontiguousarray(flat[..., :3, 3]), np.ascontiguousarray(flat[..., :3, :3])
    start = q0.to(dtype)
    rest = None if rest_gain == 0 else broadcast_q(start, chain, batch, "rest", work).double().numpy()
    options = {"rot_weight": 1.0, "rest_gain": rest_gain, "iterations": iterations, "check_every": 2, "seeds": 1,
               "pos_tol": pos_tol, "rot_tol": rot_tol}  # fmt: skip
    lo, hi = _limits(chain, dtype)
    problems = _Problems(chain, pos[0], rot[0], rest, lo, hi, options, work)
    q = np.empty((steps, pos.shape[1], n), dtype=_NUMPY[dtype])
    previous = broadcast_q(start, chain, batch, "q0", torch.float64).numpy()
    for k in range(steps):  # sequential by nature: each step starts from the last
        problems.aim(pos[k], rot[k])
        problems.run(None, None, into_limits(previous, lo, hi))
        q[k] = problems.q
        previous = q[k].astype(np.float64)
    return torch.from_numpy(q).transpose(0, 1).reshape(*batch, steps, n)
