"""The clearance queries: every distance with its pair's names, the smallest, and each capsule's
smallest with its gradient."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .. import compiled
from .. import kinematics as kin
from ..chain import Chain
from .capsules import Capsules
from .cpu_paths import capsule_clearance_compiled, plain_path
from .distances import distances, minima, resolve
from .world import World

__all__ = ["Clearances", "capsule_clearance", "capsule_clearance_of_one", "clearance", "pairwise_clearance"]


@dataclass(frozen=True)
class Clearances:
    """Every distance of one query: ``distance (..., P)`` (m, negative on overlap) and P ``pairs`` of
    names: two capsules, or a capsule and ``floor``, ``wall<i>``, ``sphere<i>``, ``box<i>`` or ``capsule<i>``."""

    distance: Tensor
    pairs: tuple[tuple[str, str], ...]


def pairwise_clearance(chain: Chain, q: Tensor, world: World | None = None,
                       capsules: Capsules | None = None) -> Clearances:
    """Every checked distance for ``q (..., n)``: self pairs, then floor, walls, spheres, boxes, capsules.
    ``world=None``: the model's floor; ``capsules=None``: :func:`robot_capsules`."""
    own, others, labels = distances(chain, q, *resolve(chain, q, world, capsules))
    parts = ([] if own is None else [own.T.reshape(*q.shape[:-1], own.shape[0])]) + others
    shape = torch.broadcast_shapes(*(p.shape[:-1] for p in parts))
    distance = torch.cat([p.expand(*shape, p.shape[-1]) for p in parts], -1)
    return Clearances(distance=distance, pairs=tuple(labels))


def clearance(chain: Chain, q: Tensor, world: World | None = None, capsules: Capsules | None = None) -> Tensor:
    """Smallest signed distance (m) over the checked pairs: ``q (..., n) -> (...)`` (arguments as
    :func:`pairwise_clearance`); differentiable in ``q`` and the obstacles. CPU calls without
    autograd may take :func:`~iiwa_torch.collision.cpu_paths.plain_path`."""
    world, capsules = resolve(chain, q, world, capsules)
    plain = plain_path(chain, q, world, capsules)
    if plain is not None:
        return plain(chain, q, world, capsules)
    own, others, _ = distances(chain, q, world, capsules, cull=True)
    mins = minima(own, others, q.shape[:-1])
    if not mins:
        raise ValueError("nothing to check: the capsules have no self pairs and the world no obstacle they face")
    shape = torch.broadcast_shapes(*(m.shape for m in mins))
    return torch.stack([m.expand(shape) for m in mins]).amin(0)


def capsule_clearance(chain: Chain, q: Tensor, world: World | None = None,
                      capsules: Capsules | None = None) -> tuple[Tensor, Tensor]:
    """Each capsule's smallest signed distance over the pairs it is in and its gradient: ``q (..., n)`` ->
    ``distance (..., K)`` (m; ``inf`` in no pair) and ``gradient (..., K, n)`` (m/rad), not
    differentiable further (arguments as :func:`pairwise_clearance`)."""
    world, capsules = resolve(chain, q, world, capsules)
    if compiled.ENABLED and q.numel() == chain.n_joints and q.is_cpu and not world.tensors():
        distance, gradient = capsule_clearance_compiled(chain, q, world.floor, capsules)
        lead = q.shape[:-1]
        return kin.like(distance.reshape(*lead, -1), q), kin.like(gradient.reshape(*lead, -1, chain.n_joints), q)
    with torch.enable_grad():
        x = q.detach().requires_grad_(True)
        d = pairwise_clearance(chain, x, world, capsules)
        inf = d.distance.new_tensor(math.inf)
        columns = []
        for name in capsules.names:
            member = torch.tensor([name in pair for pair in d.pairs], device=q.device)
            columns.append(torch.where(member, d.distance, inf).amin(-1) if d.pairs else inf.expand(q.shape[:-1]))
        distance = torch.stack(columns, -1)  # (..., K)
        k = len(capsules.names)
        one_hot = torch.eye(k, dtype=q.dtype, device=q.device).reshape(k, *(1,) * (q.ndim - 1), k)
        (gradient,) = torch.autograd.grad(distance, x, one_hot.expand(k, *distance.shape), is_grads_batched=True,
                                          allow_unused=True, materialize_grads=True)
    return distance.detach(), gradient.movedim(0, -2)


def capsule_clearance_of_one(chain: Chain, q: Tensor, floor: float | None,
                             capsules: Capsules) -> tuple[np.ndarray, np.ndarray]:
    """:func:`capsule_clearance` of one CPU configuration against itself and the floor at ``floor`` (m or
    None), unchecked -> float64 arrays ``(K,)`` (m) and ``(K, n)`` (m/rad)."""
    if compiled.ENABLED:
        return capsule_clearance_compiled(chain, q, floor, capsules)
    with torch.inference_mode(False):  # a caller's inference tensors cannot be differentiated: a copy can
        distance, gradient = capsule_clearance(chain, q.reshape(-1).double().clone(), World(floor=floor), capsules)
    return distance.numpy(), gradient.numpy()
