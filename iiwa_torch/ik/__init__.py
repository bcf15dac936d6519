"""Inverse kinematics: gradient-based solvers (``solve``, ``minimize``) and closed forms (``analytic``)."""

from .gradient import minimize, solve
from .result import IKResult

__all__ = ["IKResult", "minimize", "solve"]
