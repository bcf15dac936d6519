"""The reaching task's world: the floor, the arm's own capsules and random obstacles, batched.

Obstacles live in a fixed-size block of the observation, ``SLOT_SIZE`` numbers per slot and
``slots`` slots (``(SLOT_SIZE * slots, n)`` in the state, components first)::

    active, is_box, cx, cy, cz, sx, sy, sz, cos_yaw, sin_yaw

``active`` and ``is_box`` are 0 or 1; the centre ``c`` is in metres in the base frame; ``s``
holds a box's half extents, or a sphere's radius three times; a box is turned by ``yaw``
about the vertical (a sphere has yaw 0). An inactive slot is all zeros. The distances are
those of :func:`iiwa_torch.collision.clearance`: a slot that is not a sphere (or not a box)
is handed to it as a small one parked ``PARK`` metres above the base, where it touches nothing.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from iiwa_torch import kinematics as kin
from iiwa_torch.chain import Chain
from iiwa_torch.collision import (
    Capsules,
    World,
    clearance,
    clearance_of_one,
    obstacle_clearance_of_one,
    own_clearance_of_one,
    pairwise_clearance,
)

from .arrays import NUMPY, TORCH, ArrayOps
from .seeding import uniform

__all__ = ["SLOT_SIZE", "PARK", "ObstacleWorld", "obstacle_world", "active_obstacles"]

Tensor = torch.Tensor

SLOT_SIZE = 10
PARK = 100.0  # m: height of the stand-in of an absent sphere or box
START_MARGIN = 0.05  # m: an obstacle clears the start configuration by at least this much
# Where obstacles are drawn: around the arm, where it reaches (m, m, m, rad)
RADIUS_RANGE = (0.3, 0.8)  # from the base axis
HEIGHT_RANGE = (0.05, 1.0)
SPHERE_RADIUS_RANGE = (0.05, 0.15)
HALF_EXTENT_RANGE = (0.03, 0.15)
_DRAWS_PER_SLOT = 8


def _scale(u: Tensor, bounds: tuple[float, float]) -> Tensor:
    return bounds[0] + u * (bounds[1] - bounds[0])


def _slot_solids(block, xp: ArrayOps = TORCH) -> tuple:
    """Obstacle blocks ``(SLOT_SIZE * M, m)`` (tensors, or numpy arrays with ``xp=NUMPY``) -> sphere
    centres ``(m, M, 3)`` and radii ``(m, M)``, box poses ``(m, M, 4, 4)`` and half extents
    ``(m, M, 3)``: every slot as a sphere and as a box, the one it is not a stand-in."""
    b = xp.moveaxis(block.reshape(block.shape[0] // SLOT_SIZE, SLOT_SIZE, -1), -1, 0)  # (m, M, SLOT_SIZE)
    active, is_box = b[..., 0] > 0.5, b[..., 1] > 0.5
    centre, size, cos, sin = b[..., 2:5], b[..., 5:8], b[..., 8], b[..., 9]
    sphere, box = active & ~is_box, active & is_box
    sphere_centre = xp.stack([xp.where(sphere, centre[..., 0], 0.0), xp.where(sphere, centre[..., 1], 0.0),
                              xp.where(sphere, centre[..., 2], PARK)], -1)
    sphere_radius = xp.where(sphere, size[..., 0], 0.01)
    zero, one = xp.zeros_like(cos), xp.ones_like(cos)
    c, s = xp.where(box, cos, one), xp.where(box, sin, zero)
    rows = [[c, -s, zero, xp.where(box, centre[..., 0], 0.0)],
            [s, c, zero, xp.where(box, centre[..., 1], 0.0)],
            [zero, zero, one, xp.where(box, centre[..., 2], PARK)],
            [zero, zero, zero, one]]
    pose = xp.stack([xp.stack(r, -1) for r in rows], -2)  # (m, M, 4, 4)
    half = xp.where(box[..., None], size, 0.01)
    return sphere_centre, sphere_radius, pose, half


def obstacle_world(block: Tensor | None, floor: float | None, extra: int = 0) -> World:
    """Obstacle blocks ``(SLOT_SIZE * M, m)`` (``None`` or no rows: no obstacle) -> a :class:`World`
    with the floor at ``floor`` and obstacles of batch shape ``(m,)`` plus ``extra`` dims of
    size 1 (to broadcast with several configurations per env)."""
    if block is None or not block.shape[0]:
        return World(floor=floor)
    lead = (block.shape[1],) + (1,) * extra
    sphere_centre, sphere_radius, pose, half = (t.reshape(*lead, *t.shape[1:]) for t in _slot_solids(block))
    return World(floor=floor, spheres=(sphere_centre, sphere_radius), boxes=(pose, half))


def _numpy_solids(block: Tensor) -> tuple:
    """:func:`_slot_solids` of blocks ``(SLOT_SIZE * M, m)`` (CPU) in float64 numpy, as
    :func:`iiwa_torch.collision.solids_numpy` gives a world's: without building the world."""
    centre, radius, pose, half = _slot_solids(NUMPY.of(block).astype(np.float64), NUMPY)
    return (centre, radius), (pose, half)


def _active_kinds(block: Tensor) -> tuple[Tensor, Tensor]:
    """One env's obstacle block ``(SLOT_SIZE * M,)`` -> which slots hold an active sphere and which
    an active box, ``(M,)`` bools each."""
    b = block.reshape(-1, SLOT_SIZE)
    active, is_box = b[:, 0] > 0.5, b[:, 1] > 0.5
    return active & ~is_box, active & is_box


def active_obstacles(block: Tensor, floor: float | None) -> World:
    """One env's obstacle block ``(SLOT_SIZE * M,)`` -> an unbatched :class:`World` with the floor at
    ``floor`` and only the active slots (no stand-ins), e.g. to draw it."""
    full = obstacle_world(block[:, None], floor)
    if full.spheres is None:
        return full
    sphere, box = _active_kinds(block)
    (centre, radius), (pose, half) = full.spheres, full.boxes
    return World(floor=floor, spheres=(centre[0, sphere], radius[0, sphere]), boxes=(pose[0, box], half[0, box]))


class ObstacleWorld:
    """The floor at ``floor`` metres (``None``: none), the ``capsules`` of ``chain`` (a model fitted to
    it: :func:`envs.robot.resolve_robot`) and up to ``slots`` obstacles per env."""

    def __init__(self, chain: Chain, capsules: Capsules, floor: float | None, slots: int) -> None:
        self.chain, self.capsules, self.floor, self.slots = chain, capsules, floor, slots
        self.block_size = SLOT_SIZE * slots
        self._floor_world = World(floor=floor)
        self._last: tuple = (None, None, None)  # (block, extra, its World): the last one built
        self._last_solids: tuple = (None, (None, None))  # (one env's block, its spheres and boxes as numpy)

    def world_of(self, block: Tensor | None, extra: int = 0) -> World:
        """:func:`obstacle_world` of ``block``, kept for the next call with the same block
        tensor (an episode's obstacles are fixed: every step of it passes the same block, which
        the task never writes in place; the one world is rebuilt only when the block changes)."""
        if block is None or not block.shape[0]:
            return self._floor_world
        last, last_extra, world = self._last
        if last is not block or last_extra != extra:
            world = obstacle_world(block, self.floor, extra)
            self._last = (block, extra, world)
        return world

    def clearance(self, q: Tensor, block: Tensor | None = None, extra: int = 0) -> Tensor:
        """Smallest signed distance (m) of ``q (m, *extra, nj)`` to itself, the floor and the
        obstacles of ``block`` (one batched :func:`~iiwa_torch.collision.clearance` call)."""
        return clearance(self.chain, q, self.world_of(block, extra), self.capsules)

    def clearance_of_one(self, q: Tensor, block: Tensor | None = None) -> float:
        """:meth:`clearance` of one CPU configuration ``q`` (nj numbers, nothing to differentiate)
        and one env's ``block`` ``(SLOT_SIZE * M, 1)``, unchecked, exact where negative: a value >= 0
        only has the clearance's sign (0 for 0), which is all the envs ask of it. Without active
        obstacles, :func:`~iiwa_torch.collision.own_clearance_of_one`; with them,
        :func:`~iiwa_torch.collision.clearance_of_one`, the block's active obstacles made float64
        arrays once per block (the stand-ins of absent ones are left out: they are never the minimum)."""
        spheres = boxes = None
        if block is not None and block.shape[0]:
            last, (spheres, boxes) = self._last_solids
            if last is not block:
                spheres, boxes = self._active_solids(block)
                self._last_solids = (block, (spheres, boxes))
        if spheres is None and boxes is None:
            return own_clearance_of_one(self.chain, q, self.floor, self.capsules)
        return clearance_of_one(self.chain, q, self.floor, self.capsules, spheres, boxes, exact_below=0.0)

    def _active_solids(self, block: Tensor) -> tuple:
        """One env's block ``(SLOT_SIZE * M, 1)`` -> its active spheres and boxes as
        :func:`~iiwa_torch.collision.solids_numpy` gives them (``None`` for a kind it has none of)."""
        spheres, boxes = _numpy_solids(block)  # (1, M, ...) each, stand-ins included
        kinds = [mask.numpy() for mask in _active_kinds(block[:, 0])]
        return tuple(tuple(t[:, mask] for t in solids) if mask.any() else None
                     for solids, mask in zip((spheres, boxes), kinds))

    def is_free(self, q: Tensor, block: Tensor | None = None, extra: int = 0) -> Tensor:
        """``clearance(q, block, extra) > 0``, bools ``(m, *extra)``; for one env on the CPU
        (``m = 1``, nothing to differentiate) one configuration at a time
        (:meth:`clearance_of_one`), with the obstacles built once for the episode's steps."""
        if q.shape[0] != 1 or not kin.untracked_cpu(q):
            return self.clearance(q, block, extra) > 0
        free = [self.clearance_of_one(c, block) > 0 for c in q.reshape(-1, q.shape[-1])]
        return torch.tensor(free, device=q.device).reshape(q.shape[:-1])

    def draw(self, key: Tensor, episode: Tensor, start: Tensor, offset: int, rounds: int) -> Tensor:
        """Obstacle blocks ``(SLOT_SIZE * slots, n)`` for ``n`` envs starting at ``start (n, nj)``:
        1 to ``slots`` obstacles, each a sphere or a box with equal odds, each clear of the start
        configuration by ``START_MARGIN`` (redrawn, up to ``rounds`` times, else left out).
        Draws ``offset`` (the count) and on from the counter stream of each (key, episode)."""
        n, m = key.shape[0], self.slots
        count = 1 + (uniform(key, episode, offset, 1, start.dtype)[:, 0] * m).long().clamp_(max=m - 1)
        slot = torch.arange(m, device=key.device)
        block = start.new_zeros(n, m, SLOT_SIZE)
        env = torch.arange(n, device=key.device).repeat_interleave(m)  # one item per (env, slot)
        item_slot = slot.repeat(n)
        pending = (item_slot < count[env]).nonzero().squeeze(-1)
        one = n == 1 and kin.untracked_cpu(start)  # one env on the CPU: each item in numpy
        for r in range(rounds):
            if not pending.numel():
                break
            e, s = env[pending], item_slot[pending]
            u = uniform(key[e], episode[e], offset + 1 + r * m * _DRAWS_PER_SLOT, m * _DRAWS_PER_SLOT, start.dtype)
            u = u.view(-1, m, _DRAWS_PER_SLOT)[torch.arange(e.shape[0], device=e.device), s]  # (p, 8)
            rows = self._slot_rows(u)
            # each item alone against its env's start (rows.T: one slot per column)
            if one:
                d = obstacle_clearance_of_one(self.chain, start, self.capsules, *_numpy_solids(rows.T),
                                              exact_below=START_MARGIN)
                ok = torch.from_numpy(d > START_MARGIN)
            else:
                d = pairwise_clearance(self.chain, start[e], obstacle_world(rows.T, None), self.capsules)
                facing = torch.tensor([b in ("sphere0", "box0") for _, b in d.pairs], device=key.device)
                ok = d.distance[:, facing].amin(-1) > START_MARGIN
            block[e[ok], s[ok]] = rows[ok]
            pending = pending[~ok]
        return block.reshape(n, -1).T.contiguous()

    @staticmethod
    def _slot_rows(u: Tensor) -> Tensor:
        """Uniform numbers ``(p, 8)`` -> ``(p, SLOT_SIZE)`` active slots (the layout above)."""
        is_box = (u[:, 0] < 0.5).to(u.dtype)
        radius, angle = _scale(u[:, 1], RADIUS_RANGE), _scale(u[:, 2], (-math.pi, math.pi))
        centre = torch.stack([radius * torch.cos(angle), radius * torch.sin(angle), _scale(u[:, 3], HEIGHT_RANGE)], -1)
        sphere_size = _scale(u[:, 4], SPHERE_RADIUS_RANGE)[:, None].expand(-1, 3)
        box_size = _scale(u[:, 4:7], HALF_EXTENT_RANGE)
        size = torch.where(is_box[:, None] > 0, box_size, sphere_size)
        yaw = torch.where(is_box > 0, _scale(u[:, 7], (-math.pi, math.pi)), 0.0)
        return torch.cat([torch.ones_like(is_box)[:, None], is_box[:, None], centre, size,
                          torch.cos(yaw)[:, None], torch.sin(yaw)[:, None]], -1)
