"""Capsule models: K capsules fixed in a chain's frames, the self pairs worth checking, the presets'
models (docs/collision.md), and the capsules placed in the world for a batch of configurations."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .. import kinematics as kin
from ..chain import Chain
from ..checks import check_finite, check_instance, check_nonnegative, check_positive, is_number
from ..dh import DHChain
from .primitives import segment_gap

__all__ = ["Capsules", "capsule_segments", "pair_gaps", "robot_capsules", "self_collision_pairs"]


@dataclass(frozen=True)
class Capsules:
    """K capsules fixed in a chain's frames, and which pairs are checked (make one with :meth:`build`).

    Attributes:
        names: K names.
        frames: K indices into ``chain.fk_all(q)``'s frames (0 = base).
        points: ``(K, 2, 3)`` float64 segment ends in their frames (m).
        radii: ``(K,)`` float64 radii (m), > 0.
        pairs: checked self pairs ``(i, j)``, ``i < j``.
        world, floor: ``(K,)`` bool, capsules checked against obstacles, against the floor.
        floor_height: the floor of a query with ``world=None`` (m; ``None``: no floor).
    """

    names: tuple[str, ...]
    frames: tuple[int, ...]
    points: Tensor
    radii: Tensor
    pairs: tuple[tuple[int, int], ...]
    world: Tensor
    floor: Tensor
    floor_height: float | None = 0.0

    def __post_init__(self) -> None:
        k = len(self.names)
        if k == 0 or len(set(self.names)) != k:
            raise ValueError(f"names must be K >= 1 distinct names, got {self.names}")
        if len(self.frames) != k or not all(isinstance(f, int) and f >= 0 for f in self.frames):
            raise ValueError(f"frames must be {k} non-negative frame indices, got {self.frames}")
        for name, value, shape in (("points", self.points, (k, 2, 3)), ("radii", self.radii, (k,))):
            if not isinstance(value, Tensor) or value.dtype != torch.float64 or tuple(value.shape) != shape:
                raise ValueError(f"{name} must be a float64 tensor of shape {shape}, got {_describe(value)}")
            check_finite(value, name)
        if not (self.radii > 0).all():
            raise ValueError(f"radii must be positive, got {self.radii.tolist()}")
        for name, mask in (("world", self.world), ("floor", self.floor)):
            if not isinstance(mask, Tensor) or mask.dtype != torch.bool or tuple(mask.shape) != (k,):
                raise ValueError(f"{name} must be a bool tensor of shape ({k},), got {_describe(mask)}")
        for pair in self.pairs:
            if len(pair) != 2 or not (0 <= pair[0] < pair[1] < k):
                raise ValueError(f"pairs must be (i, j) with 0 <= i < j < {k}, got {pair}")
        if len(set(self.pairs)) != len(self.pairs):
            raise ValueError(f"pairs contains duplicates: {self.pairs}")
        if self.floor_height is not None:
            if not (is_number(self.floor_height) and math.isfinite(self.floor_height)):
                raise ValueError(f"floor_height must be a finite height in metres or None, got {self.floor_height!r}")
            object.__setattr__(self, "floor_height", float(self.floor_height))
        object.__setattr__(self, "_cache", {})

    def tables(self, dtype: torch.dtype, device: torch.device) -> dict[str, Tensor]:
        """The queries' tensors in ``dtype`` on ``device``, built once: ``frames (K,)``, ``local (K, 4, 2)``
        homogeneous ends, self pairs ``first, second (P,)``, ``pair_radius (P, 1)``, and the indices
        and radii of the capsules facing the floor (``floor``, ``floor_radius``) and obstacles (``world``)."""
        key = (dtype, device)
        if key not in self._cache:
            with torch.inference_mode(False):  # the model is shared (robot_capsules): no inference tensors in it
                self._cache[key] = self._build_tables(dtype, device)
        return self._cache[key]

    def _build_tables(self, dtype: torch.dtype, device: torch.device) -> dict[str, Tensor]:
        float_type, index = {"dtype": dtype, "device": device}, {"dtype": torch.long, "device": device}
        radii = self.radii.to(**float_type)
        first, second = torch.tensor(self.pairs, **index).reshape(-1, 2).T.contiguous()  # each (P,), also for P = 0
        floor, world = (m.to(device).nonzero().flatten() for m in (self.floor, self.world))
        ones = torch.ones(len(self.names), 2, 1, **float_type)
        return {
            "frames": torch.tensor(self.frames, **index),
            "local": torch.cat([self.points.to(**float_type), ones], -1).mT.contiguous(),
            "first": first,
            "second": second,
            "pair_radius": (radii[first] + radii[second])[:, None],
            "floor": floor,
            "floor_radius": radii[floor, None],
            "world": world,
            "world_radius": radii[world, None],
        }

    def numpy_tables(self) -> dict[str, np.ndarray]:
        """:meth:`tables` in float64 on the CPU as numpy arrays, built once."""
        if "numpy" not in self._cache:
            tables = self.tables(torch.float64, torch.device("cpu"))
            self._cache["numpy"] = {k: v.numpy() for k, v in tables.items()}
        return self._cache["numpy"]

    @classmethod
    def build(cls, chain: Chain, names, frames, points, radii, *, pairs=None, world=None, floor=None,
              floor_height: float | None = 0.0) -> Capsules:
        """Capsules for ``chain``, validated: ``points (K, 2, 3)``, ``radii (K,)`` (m), ``frames`` into
        ``fk_all``; ``pairs=None`` takes :func:`self_collision_pairs`, ``world``/``floor`` default to all."""
        names = tuple(str(n) for n in names)
        k = len(names)
        frames = tuple(int(f) for f in frames)
        if any(f > chain.n_joints for f in frames):
            raise ValueError(f"frames must index the {chain.n_joints + 1} frames of fk_all, got {frames}")
        model = cls(names=names, frames=frames, points=torch.as_tensor(points, dtype=torch.float64),
                    radii=torch.as_tensor(radii, dtype=torch.float64), pairs=(),
                    world=torch.ones(k, dtype=torch.bool) if world is None else torch.as_tensor(world),
                    floor=torch.ones(k, dtype=torch.bool) if floor is None else torch.as_tensor(floor),
                    floor_height=floor_height)
        chosen = self_collision_pairs(chain, model) if pairs is None else tuple(tuple(int(i) for i in p) for p in pairs)
        return dataclasses.replace(model, pairs=chosen)


def _describe(x) -> str:
    return f"{x.dtype} tensor of shape {tuple(x.shape)}" if isinstance(x, Tensor) else type(x).__name__


def self_collision_pairs(chain: Chain, capsules: Capsules, samples: int = 4096,
                         seed: int = 0) -> tuple[tuple[int, int], ...]:
    """Every pair ``(i, j)`` but neighbours (``j = i + 1``) and pairs overlapping in all of ``samples``
    random in-limit configurations (``seed``)."""
    check_instance(chain, Chain, "chain")
    check_instance(capsules, Capsules, "capsules")
    check_positive(samples, "samples", integer=True)
    check_nonnegative(seed, "seed", integer=True)
    q = chain.random_q(samples, generator=torch.Generator().manual_seed(seed))
    start, direction = capsule_segments(chain, capsules, q)  # components (K, samples)
    k = len(capsules.names)
    candidates = tuple((i, j) for i in range(k) for j in range(i + 2, k))
    if not candidates:
        return ()
    gap = pair_gaps(start, direction, dataclasses.replace(capsules, pairs=candidates).tables(start.dtype, start.device))
    keep = (gap > 0).any(1).tolist()
    return tuple(pair for pair, ok in zip(candidates, keep) if ok)


def capsule_segments(chain: Chain, capsules: Capsules, q: Tensor) -> tuple[Tensor, Tensor]:
    """``q (..., n)`` -> each capsule's start point and start-to-end vector in the world, ``(3, K, B)``
    each over the flattened batch (component first: the distance kernels' ops stay contiguous).
    Above ``SMALL_BATCH`` the batch-last kernel, far faster there (benchmarks/results/fk.md)."""
    tables = capsules.tables(q.dtype, q.device)
    flat = q.reshape(-1, chain.n_joints)
    geometry = chain.geometry(q.dtype)
    if flat.shape[0] <= kin.SMALL_BATCH:
        frames = kin.all_poses(geometry, flat)[:, tables["frames"], :3]  # (B, K, 3, 4)
        ends = (frames @ tables["local"]).permute(3, 2, 1, 0)  # (2, 3, K, B)
    else:  # large batches: per capsule, multiply-adds of the nonzero local coordinates only (fewer bytes moved)
        frames, _ = kin.frames_batch_last(geometry, flat.T.contiguous())  # (x, y, z, p), (3, B) each
        points = capsules.points.tolist()
        ends = torch.stack([torch.stack([_place(frames[f], local[e]) for f, local in zip(capsules.frames, points)], 1)
                            for e in (0, 1)])  # (2, 3, K, B)
    return ends[0], ends[1] - ends[0]


def _place(frame: tuple[Tensor, ...], local: list[float]) -> Tensor:
    """The point of local coordinates ``local`` in ``frame`` ``(x, y, z, p)``, skipping zero coordinates."""
    return sum((c * axis for c, axis in zip(local, frame[:3]) if c), frame[3])


def pair_gaps(start: Tensor, direction: Tensor, tables: dict[str, Tensor]) -> Tensor:
    """Signed distances ``(P, B)`` of the self pairs of :meth:`Capsules.tables`' ``tables``."""
    first, second, radii = tables["first"], tables["second"], tables["pair_radius"]
    return segment_gap(start[:, first], direction[:, first], start[:, second], direction[:, second]) - radii


def _z_capsule(frame: int, z0: float, z1: float):
    return frame, ((0.0, 0.0, z0), (0.0, 0.0, z1))


def robot_capsules(chain: DHChain) -> Capsules:
    """The conservative capsule model of a preset (sized from its DH lengths; radii: docs/collision.md),
    built once per name and table and shared. The base does not face the floor; the planar arm has
    no floor. For a URDF chain fit one with :func:`iiwa_torch.capsule_fit.urdf_capsules`."""
    check_instance(chain, Chain, "chain")
    if not isinstance(chain, DHChain):
        raise ValueError(f"chain {chain.name!r} is not a DH preset, so it has no preset capsule model; fit one to its "
                         "URDF with capsule_fit.urdf_capsules(chain, source) and pass capsules=")
    dh = chain.dh.tolist()
    key = (chain.name, tuple(map(tuple, dh)))  # all the model depends on; it is frozen, so shared
    if key not in _MODELS:
        with torch.inference_mode(False):  # shared: no inference tensors in it, whoever asks first
            _MODELS[key] = _preset_capsules(chain, dh)
    return _MODELS[key]


_MODELS: dict[tuple, Capsules] = {}  # robot_capsules' models, by chain name and DH table


def _preset_capsules(chain: DHChain, dh: list[list[float]]) -> Capsules:
    floor_height: float | None = 0.0
    if chain.name in ("iiwa14", "iiwa7"):
        l_bs, l_se, l_ew, l_wf = dh[0][2], dh[2][2], dh[4][2], dh[6][2]
        spec = [
            ("base", *_z_capsule(0, 0.0, l_bs), 0.11),
            ("upper_arm", *_z_capsule(2, 0.0, l_se), 0.09),
            ("forearm", *_z_capsule(4, 0.0, l_ew), 0.08),
            ("wrist", *_z_capsule(6, 0.0, l_wf), 0.075),
        ]
    elif chain.name == "puma560":
        d1, a2, d3, d4 = dh[0][2], dh[1][0], dh[2][2], dh[3][2]
        spec = [
            ("base", *_z_capsule(0, 0.0, d1), 0.13),
            ("upper_arm", 2, ((-a2, 0.0, d3), (0.0, 0.0, d3)), 0.10),
            ("forearm", *_z_capsule(3, -0.05, d4), 0.07),
            ("wrist", *_z_capsule(6, 0.0, 0.06), 0.06),
        ]
    elif chain.name == "lrmate200ic":
        d1, a2, a3, d4, d6 = dh[0][2], dh[1][0], dh[2][0], dh[3][2], dh[5][2]
        spec = [
            ("base", *_z_capsule(0, 0.0, d1), 0.10),
            ("upper_arm", 2, ((-a2, 0.0, 0.0), (0.0, 0.0, 0.0)), 0.07),
            ("forearm", 3, ((-a3, 0.0, 0.0), (0.0, 0.0, d4)), 0.06),
            ("wrist", *_z_capsule(6, -d6, 0.0), 0.05),
        ]
    elif chain.name == "planar3r":
        spec = [(f"link{i + 1}", i + 1, ((-row[0], 0.0, 0.0), (0.0, 0.0, 0.0)), 0.05) for i, row in enumerate(dh)]
        floor_height = None
    else:
        raise ValueError(f"no capsule model for a chain named {chain.name!r}; build one with "
                         "Capsules.build(chain, ...)")
    names, frames, points, radii = zip(*spec)
    floor = [name != "base" for name in names]
    # what self_collision_pairs finds for each preset (tested), fixed so a query samples nothing
    pairs = ((0, 2),) if chain.name == "planar3r" else ((0, 2), (0, 3), (1, 3))
    return Capsules.build(chain, names, frames, points, radii, pairs=pairs, floor=floor, floor_height=floor_height)
