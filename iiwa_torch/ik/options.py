"""The settings of the gradient-based IK solvers, as frozen dataclasses checked once when built:
:class:`SolveOptions` for :func:`~iiwa_torch.ik.solve` (Levenberg-Marquardt) and
:class:`MinimizeOptions` for :func:`~iiwa_torch.ik.minimize` (``torch.optim``).

Build one and reuse it (``opts = SolveOptions(pos_tol=1e-6)``, ``solve(chain, T, options=opts)``),
or pass the same names as keyword arguments (``solve(chain, T, pos_tol=1e-6)``); keywords given
beside ``options`` replace its fields. Tensors and objects (``q0``, ``rest``, ``generator``,
``world``, ``capsules``, the loss) stay arguments of the solvers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Literal, TypeVar, get_args

from ..checks import check_choice, check_nonnegative, check_positive, is_number

__all__ = ["MinimizeOptions", "Mode", "Optimizer", "Precision", "SolveOptions", "resolve"]

Mode = Literal["pose", "position"]
Precision = Literal["auto", "input"]
Optimizer = Literal["adam", "lbfgs"]


def _check_tolerances(options) -> None:
    """The fields both classes share: ``mode``, ``pos_tol``, ``rot_tol``."""
    check_choice(options.mode, get_args(Mode), "mode")
    check_positive(options.pos_tol, "pos_tol")
    check_positive(options.rot_tol, "rot_tol")


@dataclass(frozen=True)
class SolveOptions:
    """Settings of :func:`~iiwa_torch.ik.solve`. Hashable, so a solver may cache what it derives.

    Attributes:
        mode: ``"pose"`` (position and orientation, targets ``(..., 4, 4)``) or ``"position"``
            (orientation free, targets ``(..., 3)``).
        rot_weight: metres per radian of rotation error in the least-squares objective (> 0).
        pos_tol, rot_tol: success tolerances, metres and radians (defaults 0.1 mm, 1 mrad).
        seeds: starting configurations per target (>= 1): ``q0`` if given, then configurations
            drawn within the limits, nearest in pose to the target first. A seed runs only if
            the ones before it failed.
        iterations: LM iterations per seed before a problem that has not converged restarts.
        rest_gain: null-space pull toward ``rest``, a fraction of ``rest - q`` per iteration (0 to 1).
        check_every: iterations between convergence checks (each one syncs and shrinks the batch).
        precision: ``"auto"``: float64 targets are iterated in float32 when both tolerances are
            at least 1e-5 (the answer is checked in float64); ``"input"``: the target's dtype.
        damping: the largest initial LM damping, m^2 (a seed starts at ``0.01 E``, at most this;
            the entries of ``J J^T`` are of order 1 m^2 for an arm).
        damping_down, damping_up: factors of the damping after a kept step (in (0, 1)) and a
            rejected one (> 1).
        free_steps: LM steps of each seed without joint limits before projecting into them
            (>= 0; at most half of ``iterations`` are taken).
    """

    mode: Mode = "pose"
    rot_weight: float = 1.0
    pos_tol: float = 1e-4
    rot_tol: float = 1e-3
    seeds: int = 32
    iterations: int = 16
    rest_gain: float = 0.0
    check_every: int = 2
    precision: Precision = "auto"
    damping: float = 1e-2
    damping_down: float = 0.25
    damping_up: float = 3.0
    free_steps: int = 4

    def __post_init__(self) -> None:
        _check_tolerances(self)
        check_positive(self.rot_weight, "rot_weight")
        for name in ("seeds", "iterations", "check_every"):
            check_positive(getattr(self, name), name, integer=True)
        if not is_number(self.rest_gain) or not 0 <= self.rest_gain <= 1:
            raise ValueError(f"rest_gain must be a number in [0, 1], got {self.rest_gain!r}")
        check_choice(self.precision, get_args(Precision), "precision")
        check_positive(self.damping, "damping")
        if not is_number(self.damping_down) or not 0 < self.damping_down < 1:
            raise ValueError(f"damping_down must be a number in (0, 1), got {self.damping_down!r}")
        if not is_number(self.damping_up) or not 1 < self.damping_up < math.inf:
            raise ValueError(f"damping_up must be a finite number > 1, got {self.damping_up!r}")
        check_nonnegative(self.free_steps, "free_steps", integer=True)

    @property
    def unconstrained_steps(self) -> int:
        """The steps each seed takes without limits: ``free_steps``, at most half the iterations."""
        return min(self.free_steps, self.iterations // 2)


@dataclass(frozen=True)
class MinimizeOptions:
    """Settings of :func:`~iiwa_torch.ik.minimize`.

    Attributes:
        mode: ``"pose"`` or ``"position"``: which errors ``pos_err``, ``rot_err`` and ``success``
            measure against the target.
        optimizer: ``"adam"`` (each problem optimised independently, the step size decaying
            from ``lr`` to ``lr / 100``) or ``"lbfgs"`` (strong Wolfe line search on the summed
            loss: one step length for the batch, best for small batches).
        steps: optimiser steps (L-BFGS: iterations, with at most ``2 * steps`` evaluations).
        lr: learning rate (> 0), or None: 0.1 rad for Adam, 1 for L-BFGS.
        pos_tol, rot_tol: success tolerances, metres and radians.
        clearance_weight: with a world, the weight of the clearance term in the loss (1/m^2 of
            loss per m^2 of :func:`~iiwa_torch.ik.clearance.clearance_shortfall`, > 0).
    """

    mode: Mode = "pose"
    optimizer: Optimizer = "adam"
    steps: int = 500
    lr: float | None = None
    pos_tol: float = 1e-4
    rot_tol: float = 1e-3
    clearance_weight: float = 1.0

    def __post_init__(self) -> None:
        _check_tolerances(self)
        check_choice(self.optimizer, get_args(Optimizer), "optimizer")
        check_positive(self.steps, "steps", integer=True)
        if self.lr is not None:
            check_positive(self.lr, "lr")
        check_positive(self.clearance_weight, "clearance_weight")


Options = TypeVar("Options", SolveOptions, MinimizeOptions)
_DEFAULTS = {SolveOptions: SolveOptions(), MinimizeOptions: MinimizeOptions()}


def resolve(kind: type[Options], options: Options | None, settings: dict, caller: str) -> Options:
    """The options a solver runs with: ``options`` (default ``kind()``) with the keyword
    ``settings`` of the same names replacing its fields (checked again then). An unknown
    keyword is a ``TypeError`` that lists the known ones."""
    if options is not None and not isinstance(options, kind):
        raise TypeError(f"options must be an iiwa_torch.ik.{kind.__name__} or None, got {type(options).__name__}")
    base = _DEFAULTS[kind] if options is None else options
    if not settings:
        return base
    unknown = settings.keys() - {f.name for f in fields(kind)}
    if unknown:
        raise TypeError(f"{caller}() got unexpected keyword argument(s) {sorted(unknown)}; "
                        f"its options ({kind.__name__}) are {[f.name for f in fields(kind)]}")
    return replace(base, **settings)
