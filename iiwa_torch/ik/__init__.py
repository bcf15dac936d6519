"""Inverse kinematics: gradient-based solvers (``solve``: Levenberg-Marquardt, :mod:`.lm`;
``minimize``: ``torch.optim`` on any loss, :mod:`.descent`), their settings
(``SolveOptions``, ``MinimizeOptions``), the damped-least-squares step they use
(``dls_step``) and closed forms (``analytic``)."""

from .descent import minimize
from .dls import dls_step
from .lm import solve
from .options import MinimizeOptions, SolveOptions
from .result import IKResult

__all__ = ["IKResult", "MinimizeOptions", "SolveOptions", "dls_step", "minimize", "solve"]
