"""The clearance queries: every checked distance with its pair's names, the smallest one, and each
capsule's smallest with its gradient; checked, any batch, differentiable."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .. import compiled
from ..chain import Chain
from .capsules import Capsules
from .cpu_paths import capsule_clearance_compiled, plain_path
from .distances import distances, resolve
from .world import World

__all__ = ["Clearances", "capsule_clearance", "capsule_clearance_of_one", "clearance", "pairwise_clearance"]


@dataclass(frozen=True)
class Clearances:
    """Every distance of one query.

    Attributes:
        distance: ``(..., P)`` signed distances, metres (negative: overlap).
        pairs: P ``(a, b)`` names: two capsule names for a self pair, else a capsule name
            and ``floor``, ``wall<i>``, ``sphere<i>``, ``box<i>`` or ``capsule<i>``.
    """

    distance: Tensor
    pairs: tuple[tuple[str, str], ...]


def pairwise_clearance(
    chain: Chain, q: Tensor, world: World | None = None, capsules: Capsules | None = None
) -> Clearances:
    """Every checked distance for ``q (..., n)``: the self pairs, then capsule-floor,
    -wall, -sphere, -box, -capsule (see :class:`Clearances`). ``world=None`` is the
    model's default floor; ``capsules=None`` is :func:`robot_capsules` of the chain."""
    own, others, labels = distances(chain, q, *resolve(chain, q, world, capsules))
    parts = ([] if own is None else [own.T.reshape(*q.shape[:-1], own.shape[0])]) + others
    shape = torch.broadcast_shapes(*(p.shape[:-1] for p in parts))
    distance = torch.cat([p.expand(*shape, p.shape[-1]) for p in parts], -1)
    return Clearances(distance=distance, pairs=tuple(labels))


def clearance(chain: Chain, q: Tensor, world: World | None = None, capsules: Capsules | None = None) -> Tensor:
    """Smallest signed distance, metres: ``q (..., n) -> (...)``, over the checked self pairs and
    capsule-obstacle pairs (arguments as :func:`pairwise_clearance`). Differentiable in ``q``
    and the obstacles' tensors. On the CPU with nothing to differentiate, the robot's own
    distances run compiled when numba is enabled, and up to ``CLEARANCE_NUMPY_BATCH``
    configurations the spheres and boxes in numpy float64 (no walls or obstacle capsules; above
    it, the floor must be the only obstacle) (:func:`iiwa_torch.collision.cpu_paths.plain_path`)."""
    world, capsules = resolve(chain, q, world, capsules)
    plain = plain_path(chain, q, world, capsules)
    if plain is not None:
        return plain(chain, q, world, capsules)
    own, others, _ = distances(chain, q, world, capsules, cull=True)
    # a kind given with no obstacle (M = 0) adds no distance
    mins = ([] if own is None else [own.amin(0).reshape(q.shape[:-1])]) + [o.amin(-1) for o in others if o.shape[-1]]
    if not mins:
        raise ValueError("nothing to check: the capsules have no self pairs and the world no obstacle they face")
    shape = torch.broadcast_shapes(*(m.shape for m in mins))
    return torch.stack([m.expand(shape) for m in mins]).amin(0)


def capsule_clearance(
    chain: Chain, q: Tensor, world: World | None = None, capsules: Capsules | None = None
) -> tuple[Tensor, Tensor]:
    """Each capsule's smallest signed distance and its gradient: ``q (..., n)`` ->
    ``distance (..., K)`` (m) and ``gradient (..., K, n)`` (m/rad), for the K capsules in
    ``capsules.names`` order (arguments as :func:`pairwise_clearance`). A capsule's distance is
    the minimum over every checked pair it is in (a self pair counts for both of its capsules);
    one in no pair gets ``inf`` and a zero gradient. For controllers that keep each link clear
    (e.g. a velocity damper: ``gradient[k] . dq >= -xi (distance[k] - d_safe)``). Neither output
    is differentiable further. The gradient is autograd's, but for one CPU configuration with no
    obstacle but the floor the compiled closed form
    (:func:`iiwa_torch.compiled.numba_kernels.capsule_clearance`) when enabled."""
    world, capsules = resolve(chain, q, world, capsules)
    if compiled.ENABLED and q.numel() == chain.n_joints and q.is_cpu and not world.tensors():
        distance, gradient = capsule_clearance_compiled(chain, q, world.floor, capsules)
        dtype = np.float32 if q.dtype == torch.float32 else np.float64
        return (torch.from_numpy(distance.astype(dtype, copy=False).reshape(*q.shape[:-1], -1)),
                torch.from_numpy(gradient.astype(dtype, copy=False).reshape(*q.shape[:-1], -1, chain.n_joints)))
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


def capsule_clearance_of_one(
    chain: Chain, q: Tensor, floor: float | None, capsules: Capsules
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`capsule_clearance` of one CPU configuration ``q`` (n numbers, nothing to differentiate)
    against itself and the floor at ``floor`` (m; ``None``: none), unchecked: for callers that built
    every argument themselves (the envs' single env) -> distances ``(K,)`` (m) and gradients ``(K, n)``
    (m/rad), float64 numpy arrays."""
    if compiled.ENABLED:
        return capsule_clearance_compiled(chain, q, floor, capsules)
    with torch.inference_mode(False):  # a caller's inference tensors cannot be differentiated: a copy can
        distance, gradient = capsule_clearance(chain, q.reshape(-1).double().clone(), World(floor=floor), capsules)
    return distance.numpy(), gradient.numpy()
