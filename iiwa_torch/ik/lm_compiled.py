"""The compiled path of :func:`~iiwa_torch.ik.solve` for up to ``COMPILED_BATCH`` targets on the CPU.

With the compiled kernels (:data:`iiwa_torch.compiled.ENABLED`), a batch of ``COMPILED_BATCH``
targets or fewer, on the CPU, with no world and nothing to differentiate (:func:`handles`), runs
its Levenberg-Marquardt iteration in one call of :func:`iiwa_torch.compiled.numba_kernels.lm_rounds`
instead of the torch loop: the same seeds (the same pool, drawn from the same generator, in the
same order), damping schedule, free steps and projection into the limits, convergence checks and
choice of answer. A torch op has a fixed cost however small its tensors, and an iteration takes
a few dozen ops; the kernel's whole iteration costs about one (benchmarks/results/small.md). Without numba every
batch takes the torch loop. :func:`track_compiled` runs the gradient method of
:func:`~iiwa_torch.trajectory.track` (one such solve per pose) in one call.
"""

from __future__ import annotations

from functools import lru_cache
from weakref import WeakKeyDictionary

import numpy as np
import torch

from .. import compiled
from ..chain import Chain
from ..kinematics import Geometry, untracked_cpu
from .lm_setup import POOL, broadcast_q, inner_limits, into_limits, pool_distance, pool_features, seed_ranks, work_dtype
from .options import SolveOptions
from .result import IKResult, ik_result_compiled

__all__ = ["COMPILED_BATCH", "handles", "solve_compiled", "track_compiled"]

# up to this many targets per call: at 1,000 the compiled rounds are still ahead of the torch loop
# (the ik.solve rows of benchmarks/results/small.md; the torch loop's: IIWA_TORCH_NUMBA=0)
COMPILED_BATCH = 1024


def handles(target: torch.Tensor, q0, rest, world, size: int) -> bool:
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

    def __init__(self, g: Geometry, pos, rot, rest, lo, hi, options: SolveOptions, work: torch.dtype):
        self.g = g  # the chain's float64 geometry
        self.rest, self.lo, self.hi = rest, lo, hi
        self.eps = torch.finfo(work).eps
        b = pos.shape[0]
        self.q, self.E, self.used = np.empty((b, g.n_joints)), np.empty(b), np.empty(b, dtype=np.int64)
        self.aim(pos, rot)
        self.kernel_options, self.kernel_counts = _kernel_arrays(options, work)

    def aim(self, pos, rot) -> None:
        """New targets ``pos (b, 3)``, ``rot (b, 3, 3)`` (or None) for the same problems: no answer
        yet (the answer arrays are reset in place: a caller keeps what it needs before)."""
        self.pos, self.rot = pos, rot
        self.E.fill(np.inf)
        self.used.fill(0)

    def run(self, pool, order, first) -> None:
        """Every round of seeds in one kernel call: each problem tries its next seed (``first (b, n)``,
        q0, if given, then the pool ``(P, n)`` entries of ranks ``order (ranks, b)``) until it
        converges or runs out of seeds. The kernel's rounds take one seed per problem (a compiled
        slot costs the same alone as beside others, so a later seed runs only if the earlier ones
        failed), where the torch loop runs seeds side by side: the work differs, not the answers."""
        b, n = self.q.shape
        none = _no_rows((0, n), np.float64)  # an absent input: no rows
        rot = _no_rows((0, 3, 3), np.float64) if self.rot is None else self.rot
        rest = none if self.rest is None else np.ascontiguousarray(self.rest)
        order = _no_rows((0, b), np.int64) if order is None else order
        pool = none if pool is None else pool
        first = none if first is None else first
        compiled.kernels().lm_rounds(*self.g.float_arrays, pool, order, first, self.pos, rot, rest, self.lo, self.hi,
                                     self.kernel_options, self.kernel_counts, self.q, self.E, self.used)


@lru_cache(maxsize=64)
def _no_rows(shape: tuple[int, ...], dtype) -> np.ndarray:
    """An empty array of ``shape`` (its first dimension 0): an absent input of the kernels, which
    never write to it, so one per shape serves every call."""
    return np.empty(shape, dtype=dtype)


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
_CACHE: WeakKeyDictionary = WeakKeyDictionary()  # float64 Geometry -> {key: value}


def _cached(g: Geometry, key, make):
    """``make()``, computed once per ``key`` and chain geometry ``g`` (float64): the chain
    rebuilds its geometries (every dtype's) whenever its buffers change, so the value is
    computed again then."""
    entries = _CACHE.setdefault(g, {})
    if key not in entries:
        entries[key] = make()
    return entries[key]


def _limits(chain: Chain, g: Geometry, dtype: torch.dtype) -> tuple[np.ndarray, np.ndarray]:
    """:func:`~iiwa_torch.ik.lm_setup.inner_limits` for ``dtype``, as float64 numpy ``(n,)`` each."""
    return _cached(g, ("limits", dtype), lambda: tuple(x.double().numpy() for x in inner_limits(chain, dtype)))


def _pool(chain: Chain, size: int, generator, work: torch.dtype, mode: str):
    """The seed pool as :func:`~iiwa_torch.ik.solve` draws it (``generator`` None: a fresh one
    seeded with 0) -> the pool ``(size, n)`` in float64 and its :func:`pool_features` in
    ``work``, numpy arrays."""
    generator = torch.Generator().manual_seed(0) if generator is None else generator
    pool = chain.random_q(size, generator=generator, dtype=work)
    return pool.double().numpy(), tuple(x.numpy() for x in pool_features(chain, pool, mode))


def solve_compiled(chain: Chain, target: torch.Tensor, q0, rest, options: SolveOptions, work: torch.dtype, generator
                ) -> IKResult:
    """:func:`~iiwa_torch.ik.solve` for checked inputs that :func:`handles`: ``target`` as
    given, ``q0`` as given or None, ``rest (b, n)`` in ``work`` (or None), ``work`` the dtype
    the batched loop would iterate in (the seed pool is drawn and ranked in it)."""
    dtype, mode = target.dtype, options.mode
    g = chain.geometry(torch.float64)  # once: each call checks the chain's buffers for changes
    batch = target.shape[:-2] if mode == "pose" else target.shape[:-1]
    flat = (target.detach() if target.requires_grad else target).numpy().reshape(-1, *target.shape[len(batch) :])
    lo, hi = _limits(chain, g, dtype)
    first = None if q0 is None else into_limits(broadcast_q(q0, chain, batch, "q0", torch.float64).numpy(), lo, hi)
    pool, order = _seed_order(chain, g, flat, options, work, generator, 0 if first is None else 1)
    flat = flat.astype(np.float64, copy=False)
    # contiguous copies: the compiled kernels are typed (and compiled) for C-ordered arrays
    pos, rot = (np.ascontiguousarray(flat), None) if mode == "position" else (flat[:, :3, 3].copy(),
                                                                            flat[:, :3, :3].copy())
    rest = None if rest is None else rest.double().numpy()
    problems = _Problems(g, pos, rot, rest, lo, hi, options, work)
    problems.run(pool, order, first)
    return ik_result_compiled(chain.geometry(dtype) if dtype != torch.float64 else g, problems.q, pos, rot,
                              problems.eps, options.pos_tol, options.rot_tol, batch, problems.used)


def _seed_order(chain: Chain, g: Geometry, flat: np.ndarray, options: SolveOptions, work: torch.dtype, generator,
                shift: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The seeds after the first ``shift`` (q0): the pool ``(P, n)`` drawn from ``generator`` (the
    default one's cached per geometry) and the ranks ``(seeds - shift, b)`` of its entries
    nearest each target ``flat``; ``(None, None)`` when q0 is the only seed."""
    seeds, mode = options.seeds, options.mode
    if seeds <= shift:
        return None, None
    size = max(POOL, seeds)
    if generator is None:  # a fresh generator seeded with 0 draws the same pool every time
        pool, features = _cached(g, (size, mode, work), lambda: _pool(chain, size, None, work, mode))
    else:
        pool, features = _pool(chain, size, generator, work, mode)
    # numpy's product runs on OpenBLAS's own threads above 2^18 multiply-adds (some 340 targets),
    # whose wake-up on a busy machine can cost milliseconds; torch's keeps to torch's threads
    xp = (lambda x: x) if flat.shape[0] <= 256 else torch.from_numpy
    distance = pool_distance(chain, pool, xp(flat.astype(_NUMPY[work])), mode, tuple(map(xp, features)))
    return pool, np.asarray(seed_ranks(distance, seeds - shift))  # (ranks, b)


def track_compiled(chain: Chain, poses: torch.Tensor, q0: torch.Tensor, options: SolveOptions) -> torch.Tensor:
    """The gradient method of :func:`~iiwa_torch.trajectory.track` for checked ``poses (..., T, 4, 4)``
    and ``q0 (..., n)`` of the poses' batch shape that :func:`handles`: each pose solved as
    :func:`~iiwa_torch.ik.solve` (here :func:`solve_compiled`) solves it with ``options`` (one seed)
    from the previous answer (``q0`` first) and ``rest=q0``, so the same iterations and answers,
    without each call's checks, set-up and error report -> ``q (..., T, n)`` in the poses' dtype."""
    dtype, n = poses.dtype, chain.n_joints
    batch, steps = poses.shape[:-3], poses.shape[-3]
    work = work_dtype(poses, options)
    flat = poses.reshape(-1, steps, 4, 4).transpose(0, 1).double().numpy()  # (T, b, 4, 4)
    pos, rot = np.ascontiguousarray(flat[..., :3, 3]), np.ascontiguousarray(flat[..., :3, :3])
    start = q0.to(dtype)
    rest = None if options.rest_gain == 0 else broadcast_q(start, chain, batch, "rest", work).double().numpy()
    g = chain.geometry(torch.float64)
    lo, hi = _limits(chain, g, dtype)
    problems = _Problems(g, pos[0], rot[0], rest, lo, hi, options, work)
    q = np.empty((steps, pos.shape[1], n), dtype=_NUMPY[dtype])
    # q0 into the limits; every later start is an answer, within them already (also rounded
    # to float32: the float32 limits lo, hi are representable, and rounding keeps the order)
    previous = into_limits(broadcast_q(start, chain, batch, "q0", torch.float64).numpy(), lo, hi)
    for k in range(steps):  # sequential by nature: each step starts from the last
        problems.aim(pos[k], rot[k])
        problems.run(None, None, previous)
        q[k] = problems.q
        previous = q[k].astype(np.float64)
    return torch.from_numpy(q).transpose(0, 1).reshape(*batch, steps, n)
