"""Inverse kinematics: gradient-based solvers (``solve``, ``minimize``) and closed forms (``analytic``)."""

from .result import IKResult

__all__ = ["IKResult"]
