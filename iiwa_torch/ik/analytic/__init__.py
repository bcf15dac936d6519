"""Closed-form inverse kinematics, batched and differentiable, returning every branch.

- :func:`planar3r`: planar 3R arm, 2 branches;
- :func:`pieper`: 6R arms with a spherical wrist (PUMA 560, LR Mate 200iC), 8 branches;

Each returns :class:`AnalyticSolutions` ``(q, valid, reachable, within_limits)``.
"""

from ._common import AnalyticSolutions
from .pieper import pieper
from .planar import planar3r

__all__ = ["AnalyticSolutions", "pieper", "planar3r"]
