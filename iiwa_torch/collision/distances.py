"""Every checked distance of a query in torch (differentiable): the robot's own (self pairs, floor),
then each kind of obstacle, with each pair's names; and the checks of a query's arguments."""

from __future__ import annotations

import contextlib

import torch
from torch import Tensor

from ..chain import Chain
from ..checks import check_instance
from .capsules import Capsules, capsule_segments, pair_gaps, robot_capsules
from .primitives import culled_box_distance, unchecked_segment_box_distance, unchecked_segment_distance
from .world import World

__all__ = ["distances", "minima", "own_distances", "resolve"]

_BLOCK = 4096  # configurations per block of the robot's own distances


def resolve(chain: Chain, q: Tensor, world: World | None, capsules: Capsules | None) -> tuple[World, Capsules]:
    """A query's world and capsules, defaults filled in, every argument checked."""
    check_instance(chain, Chain, "chain")
    capsules = robot_capsules(chain) if capsules is None else capsules
    world = World(floor=capsules.floor_height) if world is None else world
    check_instance(capsules, Capsules, "capsules")
    check_instance(world, World, "world")
    chain.check_q(q)
    if max(capsules.frames) > chain.n_joints:
        raise ValueError(f"capsules use frames {capsules.frames} but the chain has {chain.n_joints + 1} frames")
    for t in world.tensors():
        if t.dtype != q.dtype or t.device != q.device:
            raise TypeError(f"world obstacles are {t.dtype} on {t.device} but q is {q.dtype} on {q.device}; "
                            "build the world in q's dtype and device")
    try:
        torch.broadcast_shapes(world.batch_shape, q.shape[:-1])
    except RuntimeError:
        raise ValueError(f"the world's batch shape {tuple(world.batch_shape)} does not broadcast with q's "
                         f"{tuple(q.shape[:-1])}: give one world, or one per configuration") from None
    return world, capsules


def own_distances(chain: Chain, q: Tensor, floor: float | None, capsules: Capsules,
                  keep_segments: bool = False) -> tuple[Tensor | None, tuple[Tensor, Tensor] | None]:
    """The robot's own distances ``(P, B)`` over the flattened batch (self pairs, then the floor at
    ``floor``; ``None`` if none), and with ``keep_segments`` :func:`capsule_segments`' output."""
    tables = capsules.tables(q.dtype, q.device)
    floor_idx = tables["floor"]
    flat = q.reshape(-1, chain.n_joints)
    own, segments = [], []
    with _one_thread(flat.shape[0] > _BLOCK and flat.device.type == "cpu"):
        for block in flat.split(_BLOCK):  # blocks small enough for the kernels' arrays to stay in the CPU cache
            start, direction = capsule_segments(chain, capsules, block)
            parts = []
            if capsules.pairs:
                parts.append(pair_gaps(start, direction, tables))
            if floor is not None and floor_idx.numel():
                low = torch.minimum(start[2], start[2] + direction[2])[floor_idx]
                parts.append(low - (tables["floor_radius"] + floor))
            if parts:
                own.append(torch.cat(parts) if len(parts) > 1 else parts[0])
            if keep_segments:
                segments.append((start, direction))
    ends = tuple(torch.cat(part, -1) for part in zip(*segments)) if keep_segments else None
    return (torch.cat(own, 1) if own else None), ends


def _walls(a: Tensor, b: Tensor, r: Tensor, walls: tuple[Tensor, Tensor]) -> Tensor:
    normal, offset = walls
    n = normal[..., None, :, :]
    height = torch.minimum((a * n).sum(-1), (b * n).sum(-1))  # (..., K, W)
    return height - offset[..., None, :] - r


def _spheres(a: Tensor, b: Tensor, r: Tensor, spheres: tuple[Tensor, Tensor]) -> Tensor:
    centre, rad = spheres
    c = centre[..., None, :, :]
    return unchecked_segment_distance(a, b, c, c) - r - rad[..., None, :]


def _boxes(a: Tensor, b: Tensor, r: Tensor, boxes: tuple[Tensor, Tensor], found: list[Tensor] | None = None):
    pose, half = boxes[0][..., None, :, :, :], boxes[1][..., None, :, :]
    if found is not None and pose.shape[-3]:
        return culled_box_distance(a, b, pose, half, r, found)
    return unchecked_segment_box_distance(a, b, pose, half) - r


def _capsules(a: Tensor, b: Tensor, r: Tensor, capsules: tuple[Tensor, Tensor]) -> Tensor:
    pts, rad = capsules
    p = pts[..., None, :, :, :]
    return unchecked_segment_distance(a, b, p[..., 0, :], p[..., 1, :]) - r - rad[..., None, :]


# each kind of obstacle: the World field, its pairs' label, its capsule-obstacle distances (..., K, M)
_KINDS = (("walls", "wall", _walls), ("spheres", "sphere", _spheres), ("boxes", "box", _boxes),
          ("capsules", "capsule", _capsules))


def _obstacle_distances(world: World, capsules: Capsules, ends: tuple[Tensor, Tensor], lead: torch.Size,
                        own: Tensor | None, cull: bool) -> tuple[list[Tensor], list[tuple[str, str]]]:
    """The capsules' distances to each kind of obstacle, ``(..., K * M)`` blocks, and their pairs' names.
    ``cull``: only the minimum matters (:func:`~iiwa_torch.collision.primitives.culled_box_distance`)."""
    tables = capsules.tables(ends[0].dtype, ends[0].device)
    idx = tables["world"]
    names = [capsules.names[x] for x in idx.tolist()]
    start, direction = (x[:, idx].permute(1, 2, 0) for x in ends)  # (K, B, 3)
    a, b = (x.transpose(0, 1).reshape(*lead, len(names), 1, 3) for x in (start, start + direction))
    r = tables["world_radius"]
    others, labels = [], []
    for field, label, kind in _KINDS:
        pair = getattr(world, field)
        if pair is None:
            continue
        found = (minima(own, others, lead),) if cull and kind is _boxes else ()
        dist = kind(a, b, r, pair, *found)
        others.append(dist.flatten(-2))
        labels += [(name, f"{label}{m}") for name in names for m in range(dist.shape[-1])]
    return others, labels


def minima(own: Tensor | None, others: list[Tensor], lead: torch.Size) -> list[Tensor]:
    """The smallest distance ``lead`` of the robot's own and of each kind given an obstacle (M > 0)."""
    return ([] if own is None else [own.amin(0).reshape(lead)]) + [o.amin(-1) for o in others if o.shape[-1]]


def distances(chain: Chain, q: Tensor, world: World, capsules: Capsules,
              cull: bool = False) -> tuple[Tensor | None, list[Tensor], list[tuple[str, str]]]:
    """The robot's own distances ``(P, B)``, the obstacles' ``(..., M)`` blocks and every pair's names,
    for arguments :func:`resolve` returned; ``cull`` as :func:`_obstacle_distances`."""
    obstacles = bool(world.tensors()) and bool(capsules.world.any())
    own, ends = own_distances(chain, q, world.floor, capsules, keep_segments=obstacles)
    tables = capsules.tables(q.dtype, q.device)
    names = capsules.names
    labels = [(names[x], names[y]) for x, y in capsules.pairs]
    if world.floor is not None:
        labels += [(names[x], "floor") for x in tables["floor"].tolist()]
    others = []
    if obstacles:
        others, more = _obstacle_distances(world, capsules, ends, q.shape[:-1], own, cull)
        labels += more
    if own is None and not others:
        raise ValueError("nothing to check: the capsules have no self pairs and the world no obstacle they face")
    return own, others, labels


@contextlib.contextmanager
def _one_thread(when: bool):
    """Run the block loop on one intra-op thread (``when``). A block's ops are too small for a second
    thread to pay: with ``OMP_WAIT_POLICY=PASSIVE`` waking it costs more than the op
    (benchmarks/results/env.md, log.md)."""
    threads = torch.get_num_threads()
    if not when or threads == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
