"""Drag-to-solve: the target gizmo's pose solved by the gradient IK or, where the joint axes admit one,
the closed form. :class:`TargetSolver` holds the choice and solves; :class:`IKPanel` shows it."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from .. import collision, ik, so3
from ..chain import Chain
from ..dh import DHChain
from ..ik import analytic

_F64 = torch.float64
OUTCOMES = ("reached", "unreachable", "outside the joint limits", "colliding")
_ARM_ANGLES = 72  # analytic IK with a free arm angle: candidates every 5 degrees, plus the current one
_BRANCH_LABELS = tuple(f"{k} {'+-'[k >> 2 & 1]}{'+-'[k >> 1 & 1]}{'+-'[k & 1]}" for k in range(8))


@dataclass(frozen=True)
class TargetResult:
    """A target solve: ``outcome`` (of :data:`OUTCOMES`; only ``"reached"`` moves the arm), ``q (n,)`` rad
    shown afterwards, the best candidate's ``pos_err`` m, ``rot_err`` rad and ``clearance`` m (or None)."""

    outcome: str
    q: torch.Tensor
    pos_err: float
    rot_err: float
    clearance: float | None

    def text(self) -> str:
        """The panel's status line."""
        text = f"{self.outcome} (error {1000 * self.pos_err:.2f} mm, {math.degrees(self.rot_err):.2f} deg"
        if self.clearance is not None:
            text += f", clearance {1000 * self.clearance:+.1f} mm"
        return text + ")"


def _closed_form(chain: Chain, q: torch.Tensor) -> tuple[str | None, DHChain | None, torch.Tensor | None]:
    """``(kind, dh, signs (n,))``: ``"iiwa"`` (S-R-S) or ``"pieper"``, the DH chain it runs on and
    ``q_dh = signs * q``; a DH preset's own table if it fits (tried at ``q``). All None if none."""
    n = chain.n_joints
    if n not in (6, 7):
        return None, None, None
    kind = "iiwa" if n == 7 else "pieper"
    if isinstance(chain, DHChain):
        pose = chain.fk(q)
        try:
            if n == 7:
                analytic.iiwa(chain, pose, 0.0)
            else:
                analytic.pieper(chain, pose)
            return kind, chain, torch.ones(n, dtype=_F64)
        except ValueError:  # its table has other rows than the closed form needs: try its axes
            pass
    try:
        found = analytic.structure(chain)
    except ValueError:  # its axes admit no closed form
        return None, None, None
    return kind, found.dh, found.signs


class TargetSolver:
    """How targets are solved: ``method``, ``branch`` (0..7 or None: nearest), ``arm_angle`` (rad or None),
    checked against ``capsules`` in ``world`` if given; ``kind``: the closed form or None."""

    def __init__(self, chain: Chain, q: torch.Tensor, capsules: collision.Capsules | None,
                 world: collision.World | None):  # fmt: skip
        self.chain, self.capsules, self.world = chain, capsules, world
        self.kind, self._dh, self._signs = _closed_form(chain, q)
        self.method, self.branch, self.arm_angle = "gradient", None, None

    @property
    def methods(self) -> tuple[str, ...]:
        """``"gradient"``, and ``"analytic"`` where a closed form exists."""
        return ("gradient", "analytic") if self.kind else ("gradient",)

    def choose(self, method: str, branch: int | None = None, arm_angle: float | None = None) -> None:
        """Check and take the choice (as ``Viewer.set_ik``)."""
        if method not in self.methods:
            raise ValueError(f"method must be one of {list(self.methods)} for {self.chain.name}, got {method!r}")
        if branch is not None and (isinstance(branch, bool) or branch not in range(8)):
            raise ValueError(f"branch must be None or an int 0..7, got {branch!r}")
        if arm_angle is not None:
            if self.kind != "iiwa":
                raise ValueError(f"an arm angle applies to S-R-S arms like the iiwa only, not to {self.chain.name}")
            if isinstance(arm_angle, bool) or not isinstance(arm_angle, (int, float)) or not math.isfinite(arm_angle):
                raise ValueError(f"arm_angle must be a finite number of radians or None, got {arm_angle!r}")
        self.method, self.branch = method, branch
        self.arm_angle = None if arm_angle is None else math.remainder(float(arm_angle), 2 * math.pi)

    def arm_angle_at(self, q: torch.Tensor) -> torch.Tensor:
        """The S-R-S arm angle of ``q (n,)`` (rad, 0-dim tensor)."""
        return analytic.iiwa_arm_angle(self._dh, q * self._signs)

    def arm_text(self, q: torch.Tensor, psi: float) -> str:
        """The readout's line of the arm angle ``psi`` (degrees) and the branch signs at ``q (n,)``."""
        theta = (q * self._signs + self._dh.dh[:, 3].to(_F64))[[1, 3, 5]]
        signs = "".join("+" if math.sin(t) >= 0 else "-" for t in theta.tolist())
        return f"  \narm angle (deg): {psi:+.1f}, branch {signs}"

    def solve(self, pose: torch.Tensor, q: torch.Tensor) -> TargetResult:
        """Solve ``pose (4, 4)`` (float64, m) from ``q (n,)``."""
        candidates, outcome = self._candidates(pose, q)
        return self._best(pose, q, candidates, outcome)

    def _candidates(self, pose: torch.Tensor, q_now: torch.Tensor) -> tuple[torch.Tensor, str | None]:
        """In-limit candidates ``(m, n)`` for ``pose`` and None, or the best attempt ``(1, n)`` and why it fails."""
        if self.method == "gradient":
            result = ik.solve(self.chain, pose, q_now)
            q = result.q.to(_F64)[None]
            ok = bool(result.success) and bool(self.chain.within_limits(q[0], tol=1e-9))
            return self.chain.clamp(q), None if ok else "unreachable"
        if self.kind == "iiwa":
            if self.arm_angle is None:
                grid = torch.linspace(-math.pi, math.pi, _ARM_ANGLES + 1, dtype=_F64)[:-1]
                psi = torch.cat([self.arm_angle_at(q_now)[None], grid])
            else:
                psi = torch.tensor([self.arm_angle], dtype=_F64)
            sol = analytic.iiwa(self._dh, pose, psi)  # q (K, 8, 7), of the DH chain
        else:
            sol = analytic.pieper(self._dh, pose)  # q (8, 6)
        n = self.chain.n_joints
        q = (sol.q * self._signs).reshape(-1, 8, n)
        reachable, within = sol.reachable.reshape(-1, 8), sol.within_limits.reshape(-1, 8)
        if self.branch is not None:
            q, reachable, within = q[:, self.branch], reachable[:, self.branch], within[:, self.branch]
        q, reachable, within = q.reshape(-1, n), reachable.reshape(-1), within.reshape(-1)
        valid = reachable & within
        if bool(valid.any()):
            return q[valid], None
        if bool(reachable.any()):
            return self.chain.clamp(q[reachable][:1]), "outside the joint limits"
        return self.chain.clamp(q[:1]), "unreachable"

    def _best(self, pose: torch.Tensor, q_now: torch.Tensor, q: torch.Tensor, outcome: str | None) -> TargetResult:
        """The collision-free candidate of ``q (m, n)`` nearest ``q_now``, as a :class:`TargetResult`."""
        cost = (q - q_now).square().sum(-1)
        gaps = None
        if self.capsules is not None:
            with torch.no_grad():
                gaps = collision.clearance(self.chain, q, self.world, self.capsules)
            if outcome is None and not bool((gaps >= 0).any()):
                outcome = "colliding"
            cost = torch.where(gaps >= 0, cost, torch.inf) if outcome is None else -gaps  # else the least colliding
        k = int(cost.argmin())
        pos_vec, rot_vec = so3.pose_error(self.chain.fk(q[k]), pose)
        pos_err, rot_err = float(pos_vec.norm()), float(rot_vec.norm())
        if outcome is None and (pos_err > 1e-4 or rot_err > 1e-3):
            outcome = "unreachable"
        outcome = outcome or "reached"
        shown = q[k].clone() if outcome == "reached" else q_now.clone()
        return TargetResult(outcome, shown, pos_err, rot_err, None if gaps is None else float(gaps[k]))


class IKPanel:
    """The "IK target" folder: ``method``, ``branch``, ``hold_psi``, ``psi_slider`` (degrees, S-R-S arms)
    and ``status``, showing ``solver``'s choice; ``on_change()``: a user changed a widget."""

    def __init__(self, gui, guard, solver: TargetSolver, on_change: Callable[[], None]):
        self._guard, self._solver = guard, solver
        with gui.add_folder("IK target"):
            self.method = gui.add_dropdown("method", solver.methods, initial_value="gradient")
            self.branch = gui.add_dropdown("branch", ("nearest", *_BRANCH_LABELS), initial_value="nearest")
            srs = solver.kind == "iiwa"
            self.hold_psi = gui.add_checkbox("hold arm angle", False, visible=srs)
            self.psi_slider = gui.add_slider("arm angle (deg)", min=-180, max=180, step=0.5, initial_value=0.0,
                                             visible=srs)  # fmt: skip
            self.status = gui.add_markdown("")
        for widget in (self.method, self.branch, self.hold_psi, self.psi_slider):
            widget.on_update(guard.callback(on_change))

    def chosen(self) -> tuple[str, int | None, float | None]:
        """``(method, branch, arm angle rad)`` as the widgets show them (None: nearest, or not held)."""
        branch = None if self.branch.value == "nearest" else _BRANCH_LABELS.index(self.branch.value)
        psi = math.radians(self.psi_slider.value) if self.hold_psi.value else None
        return self.method.value, branch, psi if self._solver.kind == "iiwa" else None

    def sync(self) -> None:
        """Show the solver's choice (branch and arm angle apply to the closed form only)."""
        solver = self._solver
        with self._guard.quiet():
            self.method.value = solver.method
            self.branch.value = "nearest" if solver.branch is None else _BRANCH_LABELS[solver.branch]
            self.hold_psi.value = solver.arm_angle is not None
            if solver.arm_angle is not None:
                self.psi_slider.value = math.degrees(solver.arm_angle)
            analytic_on = solver.method == "analytic"
            self.branch.disabled = not analytic_on
            self.hold_psi.disabled = self.psi_slider.disabled = not analytic_on

    def follow(self, psi: float) -> None:
        """Move the arm-angle slider to ``psi`` (degrees) unless one is held, so holding starts there."""
        if self._solver.arm_angle is None:
            with self._guard.quiet():
                self.psi_slider.value = psi
