"""The compiled path of :func:`~iiwa_torch.ik.solve` for up to ``COMPILED_BATCH`` targets on the CPU.

With the compiled kernels (:data:`iiwa_torch.compiled.ENABLED`), a batch of ``COMPILED_BATCH``
targets or fewer, on the CPU, with no world and nothing to differentiate (:func:`applies`), runs
its Levenberg-Marquardt iteration in one call of :func:`iiwa_torch.compiled.numba_kernels.lm_rounds`
instead of the torch loop: the same seeds (the same pool, drawn from the same generator, in the
same order), damping schedule, free steps and projection into the limits, convergence checks and
choice of answer. A torch op has a fixed cost however small its tensors, and an iteration takes
a few dozen ops; the kernel's whole iteration costs about one (benchmarks/results/small.md). Without numba every
batch takes the torch loop. :func:`track_small` runs the gradient method of
:func:`~iiwa_torch.trajectory.track` (one such solve per pose) in one call.
"""

from __future__ import annotations

from functools import lru_cache
from weakref import WeakKeyDictionary

import numpy as np
import torch

from .. import compiled
from ..chain import Chain
from ..kinematics import end_pose, untracked_cpu
from .lm_setup import POOL, broadcast_q, inner_limits, into_limits, pool_distance, pool_features, seed_ranks, work_dtype
from .options import SolveOptions
from .result import IKResult

__all__ = ["COMPILED_BATCH", "applies", "solve_small", "track_small"]

# up to this many targets per call: at 1,000 the compiled rounds are still ahead of the torch loop
# (the ik.solve rows of benchmarks/results/small.md; the torch loop's: IIWA_TORCH_NUMBA=0)
COMPILED_BATCH = 1024


def applies(target: torch.Tensor, q0, rest, world, size: int) -> bool:
    """Whether :func:`~iiwa_torch.ik.solve` takes this path for ``size`` targets: the compiled
    kernels enabled, at most ``COMPILED_BATCH``, no world, and ``target``, ``q0`` and ``rest`` on
    the CPU with nothing to differentiate (:func:`~iiwa_torch.kinematics.untracked_cpu`)."""
    given = [t for t in (target, q0, rest) if t is not None]
    # anything but a tensor goes the batched way, to the same error message as before
    return (compiled.ENABLED and world is None and size <= COMPILED_BATCH
            and all(isinstance(t, torch.Tensor) and untracked_cpu(t) for t in given))


class _Problems:
    """What every round shares, as :func:`iiwa_torch.compiled.numba_kernels.lm_rounds` takes it:
    targets ``pos (b, 3)`` and ``rot (b, 3, 3)`` (or None) in float64, the rest posture
    ``rest (b, n)`` or None, inner limits ``lo, hi (n,)``, the options of :func:`~iiwa_torch.ik.solve`
    as the kernel takes them (:func:`_kernel_arrays`), and the answers so far: ``q (b, n)``, key
    ``E (b,)`` (below 0: converged, the seed number minus ``seeds``) and iterations ``used (b,)``.
    ``work``: the dtype the batched loop would iterate in, which sets the smallest damping and the
    rounding ``eps``."""

    def __init__(self, chain: Chain, pos, rot, rest, lo, hi, options: SolveOptions, work: torch.dtype):
        self.g = chain.geometry(torch.float64)
        self.rest, self.lo, self.hi = rest, lo, hi
        self.eps = torch.finfo(work).eps
        self.q = np.empty((pos.shape[0], chain.n_joints))
        self.aim(pos, rot)
        self.kernel_options, self.kernel_counts = _kernel_arrays(options, work)

    def aim(self, pos, rot) -> None:
        """New targets ``pos (b, 3)``, ``rot (b, 3, 3)`` (or None) for the same problems: no answer yet."""
        self.pos, self.rot = pos, rot
        self.E, self.used = np.full(pos.shape[0], np.inf), np.zeros(pos.shape[0], dtype=np.int64)

    def run(self, pool, order, first) -> None:
        """Every round of seeds in one kernel call: each problem tries its next seed (``first (b, n)``,
        q0, if given, then the pool ``(P, n)`` entries of ranks ``order (ranks, b)``) until it
        converges or runs out of seeds. The kernel's rounds take one seed per problem (a compiled
        slot costs the same alone as beside others, so a later seed runs only if the earlier ones
        failed), where the torch loop runs seeds side by side: the work differs, not the answers."""
        b, n = self.q.shape
        none = np.empty((0, n))  # an absent input: no rows
        rot = np.empty((0, 3, 3)) if self.rot is None else self.rot
        rest = none if self.rest is None else np.ascontiguousarray(self.rest)
        order = np.empty((0, b), dtype=np.int64) if order is None else order
        pool, first = (none if x is None else x for x in (pool, first))
        compiled.kernels().lm_rounds(*self.g.float_arrays, pool, order, first, self.pos, rot, rest, self.lo, self.hi,
                                     self.kernel_options, self.kernel_counts, self.q, self.E, self.used)


@lru_cache(maxsize=64)
def _kernel_arrays(options: SolveOptions, work: torch.dtype) -> tuple[np.ndarray, np.ndarray]:
    """``options`` as :func:`~iiwa_torch.compiled.numba_kernels.lm_rounds` takes them, computed once
    per options and ``work`` dtype (the kernel only reads them): float64 ``(rot_weight,
    rest_gain, eps, lam_min, damping, damping_down, damping_up, pos_tol, rot_tol)`` and int64
    ``(iterations, check_every, unconstrained steps, seeds)``."""
    lam_min = 1e-12 if work == torch.float64 else 1e-6
    o = options
    values = np.array([o.rot_weight, o.rest_gain, torch.finfo(work).eps, lam_min, o.damping, o.damping_down,
                       o.damping_up, o.pos_tol, o.rot_tol], dtype=np.float64)
    counts = np.array([o.iterations, o.check_every, o.unconstrained_steps, o.seeds], dtype=np.int64)
    return values, counts


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


def solve_small(chain: Chain, target: torch.Tensor, q0, rest, options: SolveOptions, work: torch.dtype, generator
                ) -> IKResult:
    """:func:`~iiwa_torch.ik.solve` for checked inputs that :func:`applies` to: ``target`` as
    given, ``q0`` as given or None, ``rest (b, n)`` in ``work`` (or None), ``work`` the dtype
    the batched loop would iterate in (the seed pool is drawn and ranked in it)."""
    dtype, n, seeds, mode = target.dtype, chain.n_joints, options.seeds, options.mode
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
    # errors and success from the answer's end pose by chain.fk's kernel (the batched path calls
    # chain.fk; its input checks are moot on the kernels' own answers)
    pose = end_pose(chain.geometry(dtype), q_flat).numpy().astype(np.float64, copy=False)
    rot_in = np.empty((0, 3, 3)) if rot is None else rot
    pos_err, rot_err = compiled.kernels().pose_errors(pose, pos, rot_in, problems.eps)
    success = (pos_err <= options.pos_tol) & (rot_err <= options.rot_tol)
    pos_err, rot_err = (x.astype(out_dtype, copy=False) for x in (pos_err, rot_err))
    success, pos_err, rot_err, used = (torch.from_numpy(x.reshape(batch)) for x in (success, pos_err, rot_err,
                                                                                    problems.used))  # fmt: skip
    return IKResult(q_flat.reshape(*batch, n), success, pos_err, rot_err, used)


def track_small(chain: Chain, poses: torch.Tensor, q0: torch.Tensor, options: SolveOptions) -> torch.Tensor:
    """The gradient method of :func:`~iiwa_torch.trajectory.track` for checked ``poses (..., T, 4, 4)``
    and ``q0 (..., n)`` of the poses' batch shape that :func:`applies` to: each pose solved as
    :func:`~iiwa_torch.ik.solve` (here :func:`solve_small`) solves it with ``options`` (one seed)
    from the previous answer (``q0`` first) and ``rest=q0``, so the same iterations and answers,
    without each call's checks, set-up and error report -> ``q (..., T, n)`` in the poses' dtype."""
    dtype, n = poses.dtype, chain.n_joints
    batch, steps = poses.shape[:-3], poses.shape[-3]
    work = work_dtype(dtype, options)
    flat = poses.reshape(-1, steps, 4, 4).transpose(0, 1).double().numpy()  # (T, b, 4, 4)
    pos, rot = np.ascontiguousarray(flat[..., :3, 3]), np.ascontiguousarray(flat[..., :3, :3])
    start = q0.to(dtype)
    rest = None if options.rest_gain == 0 else broadcast_q(start, chain, batch, "rest", work).double().numpy()
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
