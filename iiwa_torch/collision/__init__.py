"""Capsule models of the presets, obstacle worlds and differentiable clearance (signed distance).

A robot is a set of K capsules (a segment and a radius), each fixed in one of the frames
``Chain.fk_all`` returns. :func:`clearance` is the smallest signed distance in metres
(negative when two shapes overlap) over the self-collision pairs and the capsule-obstacle
pairs; :func:`pairwise_clearance` returns every distance with the names of its pair.
Sizes and sources of the capsules, the formulas and the references they are tested
against: docs/collision.md.

Every distance is written as ``|x - y| - radii`` (or ``n . x - offset - r`` for a half-space)
at closest points ``x, y`` found without autograd; by the envelope theorem the gradient of a
minimum is the gradient at its minimiser, so gradients need no derivative of the search
and stay finite when segments are parallel, of zero length or touching.

Modules: :mod:`.capsules` (the capsule model, presets), :mod:`.world` (obstacles),
:mod:`.primitives` (segment-segment, -point, -box distances), :mod:`.distances` (every pair's
distance in torch), :mod:`.cpu_paths` (CPU calls without autograd: compiled, numpy obstacles),
:mod:`.queries` (the public queries). Every public name is here.
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
