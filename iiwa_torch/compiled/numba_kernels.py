"""The numba kernels of :mod:`iiwa_torch.compiled`, gathered from their modules (importing this
module imports numba): :mod:`~iiwa_torch.compiled.kinematics_kernels` (end poses, frames,
Jacobians, answers' errors), :mod:`~iiwa_torch.compiled.lm_kernels` (the LM rounds of ``ik.solve``),
:mod:`~iiwa_torch.compiled.analytic_kernels` (``iiwa_solve``'s sweep, ``pieper``) and
:mod:`~iiwa_torch.compiled.clearance_kernels` (self and floor clearance).

Each kernel restates a formula of the torch code, and its docstring names the function it
restates (``tests/test_backends.py`` holds them together). Everything is float64
and unchecked: the callers check. A chain enters as the four
:attr:`~iiwa_torch.kinematics.Geometry.float_arrays` ``transforms, params, base, tool``.
"""

from __future__ import annotations

from .analytic_kernels import iiwa_sweep, pieper_branches
from .clearance_kernels import capsule_clearance, own_clearance, sin_cos
from .kinematics_kernels import answer_errors, end_poses, frames_axes, jacobians
from .lm_kernels import cholesky_solve, into_limits, lm_round, lm_rounds

__all__ = ["answer_errors", "capsule_clearance", "cholesky_solve", "end_poses", "frames_axes", "iiwa_sweep",
           "into_limits", "jacobians", "lm_round", "lm_rounds", "own_clearance", "pieper_branches", "sin_cos"]
