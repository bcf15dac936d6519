"""Capsule models, obstacle worlds and differentiable clearance (signed distance, m, negative on overlap).

A robot is K capsules, each fixed in a frame of ``Chain.fk_all``. :func:`clearance` is the smallest
distance over the self pairs and capsule-obstacle pairs; :func:`pairwise_clearance` gives each with
its pair's names. Formulas, sizes and references: docs/collision.md.

Modules: :mod:`.capsules` (model, presets), :mod:`.world` (obstacles), :mod:`.primitives`
(segment distances), :mod:`.distances` (every pair in torch), :mod:`.cpu_paths` (CPU calls
without autograd), :mod:`.queries` (the public queries).
"""

from __future__ import annotations

from .capsules import Capsules, robot_capsules, self_collision_pairs
from .cpu_paths import (
    CLEARANCE_NUMPY_BATCH,
    clearance_of_one,
    obstacle_clearance_of_one,
    own_clearance_of_one,
    solids_numpy,
)
from .primitives import segment_box_distance, segment_distance
from .queries import Clearances, capsule_clearance, capsule_clearance_of_one, clearance, pairwise_clearance
from .world import MAX_EXTENT, World, check_world

__all__ = [
    "CLEARANCE_NUMPY_BATCH",
    "MAX_EXTENT",
    "Capsules",
    "Clearances",
    "World",
    "capsule_clearance",
    "capsule_clearance_of_one",
    "check_world",
    "clearance",
    "clearance_of_one",
    "obstacle_clearance_of_one",
    "own_clearance_of_one",
    "pairwise_clearance",
    "robot_capsules",
    "segment_box_distance",
    "segment_distance",
    "self_collision_pairs",
    "solids_numpy",
]
