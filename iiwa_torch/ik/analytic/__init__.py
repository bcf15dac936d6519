"""Closed-form inverse kinematics, batched and differentiable, returning every branch.

- :func:`iiwa`: KUKA LBR iiwa (7R) for given arm angles, 8 branches per angle;
  :func:`iiwa_arm_angle` the arm angle of a configuration; :func:`iiwa_solve` sweeps the
  arm angle and returns one solution per pose as an :class:`~iiwa_torch.ik.IKResult`;
- :func:`iiwa_q3_locked`: the iiwa with joint 3 held fixed, 8 branches;
- :func:`pieper`: 6R arms with a spherical wrist (PUMA 560, LR Mate 200iC), 8 branches;
- :func:`planar3r`: planar 3R arm, 2 branches;
- :func:`structure`: which of these solves a chain (any :class:`~iiwa_torch.chain.Chain`: URDF,
  hand-made), found from its joint axes; :func:`solve` solves with it.

Each multi-branch solver returns :class:`AnalyticSolutions` ``(q, valid, reachable,
within_limits)``. See docs/analytic_ik.md.
"""

from ._common import AnalyticSolutions
from .detect import ClosedForm, Structure, solve, structure
from .planar import planar3r
from .spherical6r import pieper
from .srs import iiwa, iiwa_arm_angle, iiwa_q3_locked
from .srs_sweep import iiwa_solve

__all__ = [
    "AnalyticSolutions",
    "ClosedForm",
    "Structure",
    "iiwa",
    "iiwa_arm_angle",
    "iiwa_q3_locked",
    "iiwa_solve",
    "pieper",
    "planar3r",
    "solve",
    "structure",
]
