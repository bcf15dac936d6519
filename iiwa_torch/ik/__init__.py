"""Inverse kinematics: gradient-based solvers (``solve``, ``minimize``), the damped-least-squares
step they use (``dls_step``) and closed forms (``analytic``)."""

from .dls import dls_step
from .gradient import minimize, solve
from .result import IKResult

__all__ = ["IKResult", "dls_step", "minimize", "solve"]
