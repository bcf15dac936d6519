"""Clearance on the CPU without autograd: the robot's own distances compiled (numba; else torch), and
up to ``CLEARANCE_NUMPY_BATCH`` configurations the spheres and boxes in numpy float64, where torch's
per-op cost would dominate (benchmarks/results/collision_twins.md); and the envs' unchecked calls."""

from __future__ import annotations

import math
from functools import reduce

import numpy as np
import torch
from torch import Tensor

from .. import compiled
from .. import kinematics as kin
from ..chain import Chain
from ..runtime import in_parts
from .capsules import Capsules
from .distances import own_distances
from .primitives import norm_numpy, point_gap_numpy, unchecked_segment_box_distance
from .world import World

__all__ = ["CLEARANCE_NUMPY_BATCH", "NumpyPair", "capsule_clearance_compiled", "clearance_of_one",
           "obstacle_clearance_of_one", "own_clearance_of_one", "plain_path", "solids_numpy"]

CLEARANCE_NUMPY_BATCH = 32  # clearance: spheres and boxes in numpy up to this many CPU configurations without autograd
# from this many configurations the compiled self + floor clearance splits the batch over torch's threads
# (benchmarks/results/clearance_threads.md)
CLEARANCE_THREADS_BATCH = 16384

NumpyPair = tuple[np.ndarray, np.ndarray]


def _present(kind: tuple[Tensor, Tensor] | None, axis: int) -> bool:
    """Whether a world's spheres or boxes (``axis``: where their count M is) hold any obstacle."""
    return kind is not None and kind[1].shape[axis] > 0


def plain_path(chain: Chain, q: Tensor, world: World, capsules: Capsules):
    """The CPU function :func:`~iiwa_torch.collision.clearance` hands its checked arguments to, or ``None``:
    :func:`_clearance_small` up to ``CLEARANCE_NUMPY_BATCH`` configurations (no walls or obstacle
    capsules), :func:`_clearance_compiled` above (numba, no obstacle but the floor)."""
    if world.walls or world.capsules:
        return None
    if not all(kin.untracked_cpu(t) for t in (q, *world.tensors(), chain.limits)):
        return None
    tables = capsules.numpy_tables()
    floor = world.floor is not None and tables["floor"].size > 0
    if q.numel() > CLEARANCE_NUMPY_BATCH * chain.n_joints:
        return _clearance_compiled if compiled.ENABLED and not world.tensors() and (capsules.pairs or floor) else None
    solids = (_present(world.spheres, -1) or _present(world.boxes, -2)) and tables["world"].size > 0
    return _clearance_small if capsules.pairs or floor or solids else None


def _clearance_compiled(chain: Chain, q: Tensor, world: World, capsules: Capsules) -> Tensor:
    """Clearance of a CPU batch against itself and the floor, compiled."""
    own = _own_clearance(chain, kin.float64_rows(q, chain.n_joints), world.floor, capsules)
    return kin.like(own.reshape(q.shape[:-1]), q)


def _clearance_small(chain: Chain, q: Tensor, world: World, capsules: Capsules) -> Tensor:
    """Clearance of a small CPU batch: :func:`_own_clearance` and :func:`_solid_clearance`."""
    x = kin.float64_rows(q, chain.n_joints).reshape(*q.shape[:-1], chain.n_joints)
    own = _own_clearance(chain, x.reshape(-1, chain.n_joints), world.floor, capsules).reshape(q.shape[:-1])
    solid = _solid_clearance(chain, x, capsules, *solids_numpy(world), own)
    return kin.like(own if solid is None else np.minimum(own, solid), q)


def _own_clearance(chain: Chain, x: np.ndarray, floor: float | None, capsules: Capsules) -> np.ndarray:
    """Self and floor clearance of ``x (b, n)`` float64 -> ``(b,)`` (m, ``inf`` if nothing is checked),
    compiled when enabled."""
    if not compiled.ENABLED:
        own, _ = own_distances(chain, torch.from_numpy(x), floor, capsules)
        return np.full(x.shape[0], math.inf) if own is None else own.amin(0).numpy()
    out = np.empty(x.shape[0])
    kernel = compiled.kernels().own_clearance
    args = (*chain.geometry().float_arrays[:3], *_own_tables(capsules, floor))  # no tool
    in_parts(x.shape[0], lambda start, stop: kernel(x[start:stop], *args, out[start:stop]), CLEARANCE_THREADS_BATCH)
    return out


def _own_tables(capsules: Capsules, floor: float | None) -> tuple:
    """The capsule arguments of the compiled self + floor kernels (no capsule faces an absent floor)."""
    t = capsules.numpy_tables()
    floors = t["floor"] if floor is not None else t["floor"][:0]
    return (t["frames"], t["local"], t["first"], t["second"], t["pair_radius"], floors, t["floor_radius"],
            0.0 if floor is None else float(floor))


def solids_numpy(world: World) -> tuple[NumpyPair | None, NumpyPair | None]:
    """A CPU world's spheres and boxes as float64 arrays for :func:`clearance_of_one` (``None`` where
    absent or empty); walls and obstacle capsules are left out."""

    def arrays(pair, axis):
        return tuple(t.detach().numpy().astype(np.float64) for t in pair) if _present(pair, axis) else None

    return arrays(world.spheres, -1), arrays(world.boxes, -2)


def _solid_gaps(a: np.ndarray, b: np.ndarray, radius: np.ndarray, spheres: NumpyPair | None,
                boxes: NumpyPair | None, found) -> list[np.ndarray]:
    """The smallest distances ``(...)`` of segments ``a b (..., W, 1, 3)``, radii ``(W, 1)``, to the spheres
    and to the boxes, one per kind given. Boxes are exact only where the lower bound can be below
    ``found`` and the upper bounds, as in :func:`~iiwa_torch.collision.primitives.culled_box_distance`."""
    mins, d = [], b - a
    if spheres is not None:
        centre, rad = spheres
        gap = point_gap_numpy(a, d, centre[..., None, :, :]) - radius - rad[..., None, :]
        mins.append(gap.min((-2, -1)))
    if boxes is not None:
        pose, half = boxes[0][..., None, :, :, :], boxes[1][..., None, :, :]
        upper = point_gap_numpy(a, d, pose[..., :3, 3]) - radius  # (..., W, B): c is inside its box
        lower = upper - norm_numpy(half)  # every point of a box is within |h| of its centre
        near = lower <= reduce(np.minimum, [upper.min((-2, -1)), found, *mins])[..., None, None]
        if near.all():
            lower = unchecked_segment_box_distance(a, b, pose, half, np) - radius
        elif near.any():
            pick = [np.broadcast_to(x, near.shape + x.shape[x.ndim - k:])[near]
                    for x, k in ((a, 1), (b, 1), (pose, 2), (half, 1))]
            lower[near] = unchecked_segment_box_distance(*pick, np) - np.broadcast_to(radius, near.shape)[near]
        mins.append(lower.min((-2, -1)))
    return mins


def _frames(chain: Chain, x: np.ndarray) -> np.ndarray:
    """The base and link frames of ``x (b, n)`` as rows (axes, origin): ``(b, n + 1, 4, 3)`` float64."""
    if compiled.ENABLED:
        return compiled.kernels().frames_axes(*chain.geometry().float_arrays, x)[0]
    return kin.all_poses(chain.geometry(torch.float64), torch.from_numpy(x)).numpy()[..., :3, :].swapaxes(-1, -2)


def _solid_clearance(chain: Chain, x: np.ndarray, capsules: Capsules, spheres: NumpyPair | None,
                     boxes: NumpyPair | None, found) -> np.ndarray | None:
    """The smallest distance ``(...)`` of configurations ``x (..., n)`` to the spheres and boxes, ``None``
    if nothing faces them (boxes exact below ``found``: :func:`_solid_gaps`)."""
    tables = capsules.numpy_tables()
    idx = tables["world"]
    if (spheres is None and boxes is None) or not idx.size:
        return None
    frames = _frames(chain, x.reshape(-1, x.shape[-1]))[:, tables["frames"][idx]]  # (B, W, 4, 3)
    ends = (tables["local"][idx].swapaxes(-1, -2) @ frames).reshape(*x.shape[:-1], idx.size, 2, 3)
    a, b = ends[..., None, 0, :], ends[..., None, 1, :]  # (..., W, 1, 3)
    return reduce(np.minimum, _solid_gaps(a, b, tables["world_radius"], spheres, boxes, found))


def own_clearance_of_one(chain: Chain, q: Tensor, floor: float | None, capsules: Capsules) -> float:
    """Clearance (m, ``inf`` if nothing is checked) of one CPU configuration against itself and the floor
    at ``floor`` (m or None), unchecked."""
    return float(_own_clearance(chain, kin.float64_rows(q, chain.n_joints), floor, capsules)[0])


def clearance_of_one(chain: Chain, q: Tensor, floor: float | None, capsules: Capsules,
                     spheres: NumpyPair | None = None, boxes: NumpyPair | None = None,
                     exact_below: float = math.inf) -> float:
    """:func:`own_clearance_of_one` and the spheres and boxes (:func:`solids_numpy`, batch dims 1), unchecked.
    A clearance at or above ``exact_below`` may come back as any value at or above it (with 0, the
    sign stays exact)."""
    x = kin.float64_rows(q, chain.n_joints)
    own = float(_own_clearance(chain, x, floor, capsules)[0])
    solid = _solid_clearance(chain, x[0], capsules, spheres, boxes, min(own, exact_below))
    return own if solid is None else min(own, float(np.min(solid)))


def obstacle_clearance_of_one(chain: Chain, q: Tensor, capsules: Capsules, spheres: NumpyPair | None = None,
                              boxes: NumpyPair | None = None, exact_below: float = math.inf) -> np.ndarray:
    """:func:`clearance_of_one` against the obstacles alone, per world of their batch: ``(...)`` (m)."""
    solid = _solid_clearance(chain, kin.float64_rows(q, chain.n_joints)[0], capsules, spheres, boxes, exact_below)
    if solid is None:
        raise ValueError("nothing to check: no obstacle, or no capsule checked against obstacles")
    return solid


def capsule_clearance_compiled(chain: Chain, q: Tensor, floor: float | None,
                               capsules: Capsules) -> tuple[np.ndarray, np.ndarray]:
    """:func:`~iiwa_torch.collision.capsule_clearance` of one configuration against itself and the floor,
    compiled: ``(K,)`` (m) and ``(K, n)`` (m/rad). By the envelope theorem each gradient is
    ``u . (dx/dq - dy/dq)`` at the closest points (``u`` the unit gap, or ``e_z``), as autograd gives."""
    k, n = len(capsules.names), chain.n_joints
    distance, gradient = np.empty(k), np.empty((k, n))
    compiled.kernels().capsule_clearance(*chain.geometry().float_arrays, kin.float64_rows(q, n)[0],
                                         *_own_tables(capsules, floor), distance, gradient)
    return distance, gradient
