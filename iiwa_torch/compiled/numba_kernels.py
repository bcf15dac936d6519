"""The numba kernels of :mod:`iiwa_torch.compiled`, gathered (importing this imports numba). Each restates a torch
formula and names it (``tests/test_backends.py`` holds them together); all float64 and unchecked (the callers
check). A chain enters as its :attr:`~iiwa_torch.kinematics.Geometry.float_arrays` ``transforms, params, base, tool``.
"""

from __future__ import annotations

from .analytic_kernels import iiwa_sweep, pieper_branches
from .clearance_kernels import capsule_clearance, own_clearance, sin_cos
from .kinematics_kernels import answer_errors, end_pose, end_poses, frames_axes, jacobian, jacobians
from .lm_kernels import cholesky_solve, into_limits, lm_rounds

__all__ = ["answer_errors", "capsule_clearance", "cholesky_solve", "end_pose", "end_poses", "frames_axes",
           "iiwa_sweep", "into_limits", "jacobian", "jacobians", "lm_rounds", "own_clearance", "pieper_branches",
           "sin_cos"]
