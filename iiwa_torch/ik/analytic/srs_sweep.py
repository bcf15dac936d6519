"""The iiwa's closed form (:mod:`.srs`) as a solver: one solution per pose, found by sweeping
the arm angle over a grid and refining around the best candidate (nearest a reference ``q0``,
or with the largest joint-limit margin), optionally clear of a world's obstacles.

Small batches: up to ``SOLVE_NUMPY_BATCH`` CPU poses with nothing to differentiate and no world,
:func:`iiwa_solve` runs its sweep in numpy (the closed form is written once over ``_common``'s
array libraries), or up to ``SOLVE_COMPILED_BATCH`` in one compiled call,
:func:`iiwa_torch.compiled.numba_kernels.iiwa_sweep`, when numba is enabled. That kernel restates
the closed form, the wrap into the limits, the ranking and the retry as scalar loops (numba cannot
run the array code); ``tests/test_iiwa_solve_numpy.py`` and ``tests/test_backends.py`` hold it to
the numpy and the batched sweep.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import operator
import weakref
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from ... import compiled
from ...checks import check_positive
from ...collision import Capsules, World, check_world, clearance
from ...dh import DHChain
from ...kinematics import all_poses
from ..lm_setup import broadcast_q
from ..result import IKResult, ik_result, ik_result_compiled
from ._common import (
    NUMPY,
    TORCH,
    check_target,
    last_frame_numpy,
    numpy_applies,
    numpy_strips,
    reach_tol,
    reduce_grouped,
    wrap_joints,
)
from .srs import Geometry, arm_angle_of_points, closed_form, iiwa_arm_angle, wrist_frame

__all__ = ["SOLVE_COMPILED_BATCH", "SOLVE_NUMPY_BATCH", "Obstacles", "iiwa_solve"]

Tensor = torch.Tensor

SOLVE_NUMPY_BATCH = 256  # up to this many poses per call (CPU, no world, no gradient), iiwa_solve runs in numpy
# with the compiled kernel, up to this many poses: at 1,000 it is still ahead of the torch sweep
# (the analytic.iiwa_solve rows of benchmarks/results/small.md; the torch sweep's: IIWA_TORCH_NUMBA=0)
SOLVE_COMPILED_BATCH = 1024

_CANDIDATES = 1 << 20  # candidate solutions per chunk in iiwa_solve (~60 MB in float64)
_LOCAL = 9  # arm angles of each of iiwa_solve's refining passes, centred on the best so far
_REFINE = 3  # refining passes when a reference q0 is given
_CLEARANCE_ROUNDS = ((0, 1), (1, 4), (4, 16), (16, 1 << 30))  # candidate ranks whose clearance is checked, by round


def iiwa_solve(
    chain: DHChain,
    target: Tensor,
    q0: Tensor | None = None,
    *,
    num_psi: int = 16,
    pos_tol: float = 1e-4,
    rot_tol: float = 1e-3,
    world: World | None = None,
    margin: float = 0.0,
    capsules: Capsules | None = None,
) -> IKResult:
    """One IK solution per pose by sweeping the arm angle: interchangeable with the
    gradient solver :func:`iiwa_torch.ik.solve`.

    Args:
        chain: as for :func:`iiwa`.
        target: ``(..., 4, 4)`` end-effector poses in the world frame (m).
        q0: optional ``(..., 7)`` reference configuration (e.g. the current one when
            tracking): the valid solution nearest to it (Euclidean joint-space distance, not
            wrapped: a joint cannot turn through its limits) is returned. Without it, the one
            with the largest joint-limit margin (radians, the smallest over the joints).
        num_psi: arm angles sampled evenly over ``[-pi, pi)`` (plus the arm angle of ``q0``),
            ``8 * num_psi`` candidates per pose; then 9 angles spanning one step either side of
            the best are tried (3 times, each a 4x finer window, when ``q0`` is given). Poses
            with no valid candidate are swept once more with ``16 * num_psi`` angles
            (narrow feasible intervals).
        pos_tol, rot_tol: success tolerances (m, rad), as in the gradient solver.
        world: optional :class:`~iiwa_torch.collision.World` (batch shape broadcasting to
            ``(...)``: one set of obstacles per pose). A candidate is then valid only if its
            clearance (self pairs and obstacles) is at least ``margin`` metres; among the valid
            ones the rule above picks. ``None``: no collision check (and no cost).
        margin: clearance required with a world (m, >= 0).
        capsules: the robot's capsule model (default :func:`~iiwa_torch.collision.robot_capsules`).

    Returns:
        :class:`~iiwa_torch.ik.IKResult` with ``q (..., 7)`` within the joint limits,
        ``success`` where the FK of ``q`` reproduces the target within ``pos_tol`` and
        ``rot_tol`` (whatever the branch geometry says: a target a rounding error beyond
        reach succeeds with that error) and, with a world, ``clearance >= margin``;
        ``iterations`` 0. Where no candidate is within the limits, ``q`` is the candidate nearest
        ``q0`` (or violating the limits least), reachable ones first, clamped into them. Where
        every in-limit candidate collides, ``q`` is the one with the largest clearance.
    """
    check_positive(num_psi, "num_psi", integer=True)
    for value, name in ((pos_tol, "pos_tol"), (rot_tol, "rot_tol")):
        check_positive(value, name)
    check_world(world, margin, capsules)
    check_target(chain, target)
    batch = target.shape[:-2]
    flat = target.reshape(-1, 4, 4)
    flat_q0 = None if q0 is None else broadcast_q(q0, chain, batch, "q0", target.dtype)
    if _numpy_applies(chain, flat, q0, world, num_psi):
        return _solve_numpy(chain, flat, flat_q0, num_psi, pos_tol, rot_tol, batch)
    return _solve_torch(chain, flat, flat_q0, num_psi, pos_tol, rot_tol, batch, world, margin, capsules)


def _solve_torch(chain: DHChain, flat: Tensor, q0: Tensor | None, num_psi: int, pos_tol: float, rot_tol: float,
                 batch: torch.Size, world: World | None, margin: float, capsules: Capsules | None) -> IKResult:
    """:func:`iiwa_solve` in torch (any device, autograd, a world) for ``flat (B, 4, 4)`` and ``q0
    (B, 7)`` (or None), checked and flattened."""
    obstacles = None if world is None else Obstacles.for_batch(world, margin, capsules, batch)
    if flat.shape[0] == 0:  # no poses
        q_best = flat.new_zeros(0, 7)
    else:
        setup = _Setup.build(chain, TORCH, chain.clamp, with_chain=chain)
        rot, sw = wrist_frame(chain, flat)
        psi0 = None if q0 is None else iiwa_arm_angle(chain, q0)
        q_best, _ = _solve_all(setup, rot, sw, q0, psi0, num_psi, flat.dtype, obstacles)
    result = ik_result(chain, q_best.reshape(*batch, 7), flat.reshape(*batch, 4, 4), "pose", pos_tol, rot_tol,
                       torch.zeros(batch, dtype=torch.int64, device=flat.device))
    if obstacles is None:
        return result
    clear = obstacles.clearance(chain, q_best).reshape(batch)
    return dataclasses.replace(result, success=result.success & (clear >= margin), clearance=clear)


def _numpy_applies(chain: DHChain, flat: Tensor, q0: Tensor | None, world: World | None, num_psi: int) -> bool:
    """Whether :func:`iiwa_solve` runs in numpy (:func:`_solve_numpy`): no world, the target, ``q0``,
    the chain's base and tool on the CPU with nothing to differentiate
    (:func:`~._common.numpy_applies`), and ``1..SOLVE_COMPILED_BATCH`` poses ``flat (B, 4, 4)`` with the
    compiled kernel (:data:`iiwa_torch.compiled.ENABLED`), else ``1..SOLVE_NUMPY_BATCH`` that fit in
    one chunk (the numpy sweep takes them all at once)."""
    size = flat.shape[0]
    if compiled.ENABLED:
        limit = SOLVE_COMPILED_BATCH
    else:
        limit = SOLVE_NUMPY_BATCH if size * 8 * (16 * num_psi + 1) <= _CANDIDATES else 0
    return world is None and numpy_applies(chain, size, limit, flat, *(() if q0 is None else (q0,)))


@dataclass(frozen=True)
class _Setup:
    """What a sweep takes from the chain, for the arrays of ``ops`` (``_common``): the closed
    form's constants ``geo``, the joint offsets and limits (floats, rad) and their mid-points and
    half-widths, and ``clamp``, ``q (B, 7)`` -> ``q`` clamped into the limits. For torch also the
    chain (for a world), for numpy the float64 arrays ``base`` and ``limits (2, 7)``, the chain's
    ``strips`` (:func:`~._common.numpy_strips`) and the cache of :func:`_kernel_args`."""

    geo: Geometry
    ops: object
    offsets: list
    lows: list
    highs: list
    mids: list
    halves: list
    clamp: Callable
    chain: DHChain | None = None
    base: np.ndarray | None = None
    limits: np.ndarray | None = None
    strips: tuple | None = None
    kernel_args: dict = dataclasses.field(default_factory=dict)

    def bounds(self, dtype: torch.dtype) -> tuple[list, list]:
        """The limits (rad) against which candidates for targets of ``dtype`` are checked: in numpy,
        those of float32 targets rounded to float32, as torch compares a float32 tensor with a number."""
        if self.ops is TORCH or dtype == torch.float64:
            return self.lows, self.highs
        return tuple(np.array(b, dtype=np.float32).tolist() for b in (self.lows, self.highs))

    @classmethod
    def build(cls, chain: DHChain, ops, clamp: Callable, with_chain: DHChain | None = None, **extra) -> _Setup:
        lows, highs = chain.limits.tolist()
        mids = chain.limits.mean(0).tolist()
        halves = ((chain.limits[1] - chain.limits[0]) / 2).tolist()
        offsets = chain.dh[:, 3].tolist()
        return cls(Geometry(chain), ops, offsets, lows, highs, mids, halves, clamp, with_chain, **extra)


_NUMPY_SETUPS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # chain.geometry(float64) -> _Setup


def _numpy_setup(chain: DHChain) -> _Setup:
    """The numpy :class:`_Setup` of ``chain``, cached on its float64 geometry (which the chain
    rebuilds when its buffers change; the entry holds no reference to the chain or geometry)."""
    key = chain.geometry(torch.float64)
    setup = _NUMPY_SETUPS.get(key)
    if setup is None:
        limits = chain.limits.double().numpy()
        setup = _Setup.build(
            chain, NUMPY, functools.partial(NUMPY.clamp, lo=limits[0], hi=limits[1]),
            base=chain.base.double().numpy(), limits=limits, strips=numpy_strips(chain),
        )
        _NUMPY_SETUPS[key] = setup
    return setup


def _solve_numpy(chain: DHChain, flat: Tensor, q0: Tensor | None, num_psi: int, pos_tol: float, rot_tol: float,
                 batch: torch.Size) -> IKResult:
    """:func:`iiwa_solve` in numpy float64 for ``flat (B, 4, 4)`` and ``q0 (B, 7)`` (or None), checked
    and flattened: the same sweep (:func:`_solve_all`, with the reach tolerance of ``flat``'s
    dtype; compiled, :func:`iiwa_torch.compiled.numba_kernels.iiwa_sweep`, when enabled), then ``q``
    in that dtype and its errors from the chain's FK, as the batched path."""
    dtype = flat.dtype
    setup = _numpy_setup(chain)
    target = (flat.detach() if flat.requires_grad else flat).numpy().astype(np.float64, copy=False)
    frame6 = last_frame_numpy(chain, target, setup.strips)
    rot, sw = np.ascontiguousarray(frame6[:, :3, :3]), frame6[:, :3, 3] - np.array([0.0, 0.0, setup.geo.d1])
    psi0 = None
    if q0 is not None:
        q0 = q0.detach().double().numpy()
        frames = all_poses(chain.geometry(torch.float64), torch.from_numpy(q0)).numpy().transpose(1, 0, 2, 3)
        # world frame; S, E, W back into frame 0
        base = setup.base
        psi0 = arm_angle_of_points(*((frames[[1, 3, 5], :, :3, 3] - base[:3, 3]) @ base[:3, :3]), ops=NUMPY)
    if compiled.ENABLED:
        q = _solve_compiled(setup, rot, sw, q0, psi0, num_psi, dtype)
        goal_pos, goal_rot = (np.ascontiguousarray(target[:, :3, c]) for c in (3, slice(3)))
        return ik_result_compiled(chain.geometry(dtype), q, goal_pos, goal_rot, torch.finfo(dtype).eps, pos_tol,
                                  rot_tol, batch, np.zeros(q.shape[0], dtype=np.int64))  # fmt: skip
    q, _ = _solve_all(setup, rot, sw, q0, psi0, num_psi, dtype, None)
    return ik_result(chain, torch.from_numpy(q).to(dtype).reshape(*batch, 7), flat.reshape(*batch, 4, 4), "pose",
                     pos_tol, rot_tol, torch.zeros(batch, dtype=torch.int64))


def _solve_compiled(setup: _Setup, rot, sw, q0, psi0, num_psi: int, dtype: torch.dtype) -> np.ndarray:
    """:func:`_solve_all` by :func:`iiwa_torch.compiled.numba_kernels.iiwa_sweep` (numpy arrays, no
    world) -> ``q (B, 7)``."""
    none = np.empty((0, 7))
    return compiled.kernels().iiwa_sweep(
        np.ascontiguousarray(rot), np.ascontiguousarray(sw), none if q0 is None else q0,
        none[:, 0] if psi0 is None else psi0, *_kernel_args(setup, num_psi, q0 is not None, dtype),
    )  # fmt: skip


def _kernel_args(setup: _Setup, num_psi: int, with_q0: bool, dtype: torch.dtype) -> tuple:
    """The constant arguments of :func:`iiwa_torch.compiled.numba_kernels.iiwa_sweep` for ``setup``'s
    chain (numpy), cached in it: the arm angles of the sweep and of its retry (:func:`_angles`), the
    closed form's constants and the joint offsets and limits."""
    key = (num_psi, with_q0, dtype)
    if key not in setup.kernel_args:
        grid, local = _angles(NUMPY, None, num_psi, with_q0)
        fine_grid, fine_local = _angles(NUMPY, None, 16 * num_psi, with_q0)
        geo = setup.geo
        consts = np.array([geo.d3, geo.d5, *geo.sig, reach_tol(dtype)])
        limits = np.array([setup.offsets, *setup.bounds(dtype), setup.mids, setup.halves, *setup.limits])
        setup.kernel_args[key] = (grid, np.stack(local), fine_grid, np.stack(fine_local), consts, limits,
                                  dtype == torch.float32)  # fmt: skip
    return setup.kernel_args[key]


@dataclass(frozen=True)
class Obstacles:
    """A world for a flat batch of ``B`` poses: one shared set of obstacles (``shared``), or
    one row per pose, with the margin (m) and capsule model. Build it with :meth:`for_batch`."""

    world: World
    margin: float
    capsules: Capsules | None
    shared: bool

    @classmethod
    def for_batch(cls, world: World, margin: float, capsules: Capsules | None, batch: torch.Size) -> Obstacles:
        """``world``, whose batch shape must broadcast to the poses' ``batch``, flattened to one
        row per pose (kept as it is when it has no batch shape)."""
        if not world.batch_shape:
            return cls(world, margin, capsules, shared=True)
        world.check_batch(batch)

        def flatten(t: Tensor, k: int) -> Tensor:
            own = t.shape[t.ndim - k :]
            return t.expand(*batch, *own).reshape(-1, *own)

        return cls(world.map_batch(flatten), margin, capsules, shared=False)

    def take(self, index) -> Obstacles:
        """The obstacles of the poses ``index`` (a slice or an index tensor)."""
        if self.shared:
            return self
        return dataclasses.replace(self, world=self.world.map_batch(lambda t, k: t[index]))

    def clearance(self, chain: DHChain, q: Tensor, rows: Tensor | None = None) -> Tensor:
        """Clearance ``(V,)`` of ``q (V, 7)``, row ``v`` against pose ``rows[v]``'s obstacles
        (``rows=None``: ``q`` has one row per pose)."""
        world = self.world if rows is None else self.take(rows).world
        return clearance(chain, q, world, self.capsules)


def _solve_all(setup: _Setup, rot, sw, q0, psi0, num_psi: int, dtype: torch.dtype, obstacles: Obstacles | None):
    """Every pose's answer, ``rot (B, 3, 3)``, ``sw (B, 3)`` (:func:`wrist_frame`), ``q0 (B, 7)`` and its
    arm angle ``psi0 (B,)`` (or None), for targets of ``dtype``, -> ``q (B, 7)`` and ``found (B,)``:
    :func:`_sweep`, then poses with no valid candidate once more with 16 times as many arm angles
    (narrow feasible intervals)."""
    ops = setup.ops
    q_best, found = _sweep(setup, rot, sw, q0, psi0, num_psi, dtype, obstacles)
    missed = ops.nonzero(~found)
    if len(missed):
        q_fine, found_fine = _sweep(
            setup,
            rot[missed],
            sw[missed],
            None if q0 is None else q0[missed],
            None,
            16 * num_psi,
            dtype,
            None if obstacles is None else obstacles.take(missed),
        )
        q_best, found = ops.put(q_best, missed, q_fine), ops.put(found, missed, found_fine)
    return q_best, found


def _sweep(setup: _Setup, rot, sw, q0, psi0, num_psi: int, dtype: torch.dtype, obstacles: Obstacles | None):
    """Best candidate of each pose over ``num_psi`` evenly spaced arm angles (plus ``psi0``, the arm
    angle of ``q0``, when given), then over finer grids of ``_LOCAL`` angles spanning one step
    either side of the best so far (their centre; :func:`_angles`). Arguments as for :func:`_solve_all`."""
    ops = setup.ops
    pick = _pick_chunked if ops is TORCH else _pick
    grid, local = _angles(ops, rot, num_psi, q0 is not None)
    psi = ops.expand(grid, (rot.shape[0], num_psi))
    if psi0 is not None:
        psi = ops.cat([psi0[:, None], psi], -1)  # (B, K + 1)
    q, found, psi_best = pick(setup, rot, sw, psi, q0, dtype, obstacles)
    for offsets in local:
        q, found, psi_best = pick(setup, rot, sw, psi_best[:, None] + offsets, q0, dtype, obstacles)
    return q, found


def _angles(ops, like, num_psi: int, with_q0: bool) -> tuple:
    """The arm angles of :func:`_sweep` (arrays of ``ops`` like ``like``): the grid ``(num_psi,)``
    over ``[-pi, pi)`` and the offsets ``(_LOCAL,)`` of each refining pass (``_REFINE`` passes
    ``with_q0``, else one)."""
    step = 2 * math.pi / num_psi
    grid = ops.arange(num_psi, like) * step - math.pi
    local = []
    for _ in range(_REFINE if with_q0 else 1):  # a margin is flat near its best: one pass
        local.append(ops.linspace(-step, step, _LOCAL, like))
        step = 2 * step / (_LOCAL - 1)  # the next window spans the neighbours of the best
    return grid, local


def _pick_chunked(setup: _Setup, rot: Tensor, sw: Tensor, psi: Tensor, q0: Tensor | None, dtype: torch.dtype,
                  obstacles: Obstacles | None) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`_pick` over chunks of poses, so that memory stays bounded."""
    chunk = max(1, _CANDIDATES // (8 * psi.shape[-1]))
    picks = [
        _pick(
            setup,
            rot[i : i + chunk],
            sw[i : i + chunk],
            psi[i : i + chunk],
            None if q0 is None else q0[i : i + chunk],
            dtype,
            None if obstacles is None else obstacles.take(slice(i, i + chunk)),
        )
        for i in range(0, rot.shape[0], chunk)
    ]
    return tuple(torch.cat(parts) for parts in zip(*picks))


def _pick(setup: _Setup, rot, sw, psi, q0, dtype: torch.dtype, obstacles: Obstacles | None):
    """Best of the ``K * 8`` candidates of each pose: ``rot (B, 3, 3)``, ``sw (B, 3)``, ``psi (B, K)``,
    ``q0 (B, 7)`` or None -> ``q (B, 7)`` clamped into the limits, ``found (B,)`` bool (the
    candidate is valid) and its arm angle ``(B,)``; arrays of ``setup.ops``, for targets of
    ``dtype`` (its reach tolerance and precision of the ranking)."""
    ops = setup.ops
    thetas, reachable = closed_form(setup.geo, rot[:, None], sw[:, None], psi, reach_tol(dtype), ops)
    lows, highs = setup.bounds(dtype)
    qs, within = wrap_joints(thetas, setup.offsets, lows, highs, ops)  # each as large as its branches need
    batch = rot.shape[0]
    if q0 is None:  # minus the margin to the nearest limit (negative outside)
        margins = [abs(qj - mid) - half for qj, mid, half in zip(qs, setup.mids, setup.halves)]
        cost = reduce_grouped(ops.maximum, margins)
    else:  # squared distance to q0; no wrapping: a joint cannot turn through its limits
        diffs = [qj - q0[:, j].reshape(batch, 1, 1, 1, 1) for j, qj in enumerate(qs)]
        cost = reduce_grouped(operator.add, [d * d for d in diffs])
    shape = cost.shape  # (B, K, 2, 2, 2)
    valid = ops.expand(reachable & within, shape)
    # Valid candidates first, then those outside the limits, then the geometrically unreachable
    # ones (their cosines clamped: a target a rounding error out of reach is met to that error).
    big = 1e6
    key = cost + big * ops.as_float(~within, cost) + 2 * big * ops.as_float(~reachable, cost)
    key = ops.rounded(key, dtype)  # the target's precision, in which the batched path ranks
    if obstacles is None:
        best = key.reshape(batch, -1).argmin(-1)  # (B,)
        found = ops.take(valid.reshape(batch, -1), best)
    else:
        best, found = _free_pick(setup.chain, key.reshape(batch, -1), valid.reshape(batch, -1), qs, obstacles)
    index = ops.unravel(best, shape[1:])  # arm angle, shoulder, elbow, wrist
    rows = ops.rows(batch, best)
    zero = index[0] * 0
    q_best = ops.stack(
        [qj[(rows,) + tuple(ix if n > 1 else zero for ix, n in zip(index, qj.shape[1:]))] for qj in qs], -1
    )
    return setup.clamp(q_best), found, ops.take(psi, index[0])


def _free_pick(
    chain: DHChain, key: Tensor, valid: Tensor, qs: list[Tensor], obstacles: Obstacles
) -> tuple[Tensor, Tensor]:
    """Per pose, the lowest-``key`` valid candidate whose clearance is at least the margin:
    ``key, valid (B, N)`` over the candidates, ``qs`` their joints (broadcasting to
    ``(B, ...)`` with ``N`` entries after the first dim) -> its index ``(B,)`` and whether one
    was found. Clearance is computed in key order, in rounds of growing size, only for the
    poses still without one; where no valid candidate clears the margin, the valid one with
    the largest clearance is returned, and where none is valid, the lowest key."""
    batch, n = key.shape
    order = key.argsort(-1)  # valid candidates first: the others carry a key >= 1e6
    n_valid = valid.sum(-1)
    shape = torch.broadcast_shapes(*(q.shape for q in qs))
    joints = [q.expand(shape).reshape(batch, n) for q in qs]
    clear = key.new_full((batch, n), -math.inf)
    best, found = order[:, 0].clone(), torch.zeros(batch, dtype=torch.bool, device=key.device)
    undecided = n_valid > 0
    for lo, hi in _CLEARANCE_ROUNDS:
        ranks = torch.arange(lo, min(hi, n), device=key.device)
        todo = undecided[:, None] & (ranks < n_valid[:, None])  # (B, R)
        if not todo.any():
            break
        rows, cols = todo.nonzero().unbind(-1)
        picked = order[rows, ranks[cols]]
        values = obstacles.clearance(chain, torch.stack([q[rows, picked] for q in joints], -1), rows)
        clear[rows, picked] = values
        free = torch.zeros_like(todo).index_put((rows, cols), values >= obstacles.margin)
        hit = free.any(-1)
        first = ranks[free.to(torch.int8).argmax(-1)]  # the first free rank of each pose
        best = torch.where(hit, order.gather(-1, first[:, None]).squeeze(-1), best)
        found, undecided = found | hit, undecided & ~hit
    return torch.where(undecided, clear.argmax(-1), best), found
