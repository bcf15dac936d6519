"""Which closed form solves a chain, found from its joint axes, and solving with it.

:func:`structure` reads the joint axes (lines at ``q = 0``) from the chain's Jacobian and builds
the standard-DH table of them (frame ``k`` on axis ``k + 1``, x along the common normal; for
parallel axes the normal through the previous origin, ``d = 0``), with the base, tool and joint
signs that make the :class:`~iiwa_torch.dh.DHChain` move as the chain (``q_dh = sign * q``); it
then checks the rows a solver needs, within ``tol``: planar 3R (3 parallel distinct axes), Pieper
(6R, axes 4-6 meet, 2 and 3 parallel, the others perpendicular) or S-R-S (7R like the iiwa).

:func:`solve` runs that solver and maps the joints back. A file with rounded numbers
(``1.57079632679`` for pi/2) leaves axes meeting only within about ``1e-11``: the closed form
solves the ideal arm and one Gauss-Newton step on the chain removes the rest.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from enum import Enum

import torch

from ...chain import Chain, JointKind
from ...checks import check_instance, check_positive
from ...collision import Capsules, World
from ...dh import DHChain
from ...so3 import pose_error
from ..dls import dls_step
from ._common import IDEAL_TOL, AnalyticSolutions, reach_tol, with_clearance
from .planar import PLANAR_ROWS, planar3r
from .spherical6r import PIEPER_ROWS, pieper
from .srs import SRS_ROWS, iiwa

__all__ = ["ClosedForm", "Structure", "solve", "structure"]

Tensor = torch.Tensor

DETECT_TOL = 1e-9  # default tolerance (m, rad) for axes to count as meeting, parallel or perpendicular
_DAMPING = 1e-12  # of the Gauss-Newton step (m^2): bounds it near a singularity
_NEWTON_STEPS = 3  # Gauss-Newton steps on a chain off the ideal structure (one takes 3e-7 rad to about 1e-8)
_EXACT = 1e-14  # departures from the ideal structure below this are rounding: no Gauss-Newton step


class ClosedForm(str, Enum):
    """The closed forms :func:`structure` recognises."""

    PLANAR3R = "planar3r"
    PIEPER = "pieper"
    SRS = "srs"


_FORMS = {  # joints -> (closed form, its rows, what it is)
    3: (ClosedForm.PLANAR3R, PLANAR_ROWS, "planar 3R arm (three parallel, distinct axes)"),
    6: (ClosedForm.PIEPER, PIEPER_ROWS,
        "6R arm with a spherical wrist (Pieper: axes 4-6 meet, axes 2 and 3 parallel, the others perpendicular)"),
    7: (ClosedForm.SRS, SRS_ROWS,
        "7R S-R-S arm (axes 1-3 meet, axes 5-7 meet, axis 4 meets axes 3 and 5, consecutive axes perpendicular)"),
}  # fmt: skip


@dataclass(frozen=True)
class Structure:
    """A chain's closed form, from :func:`structure`.

    Attributes:
        form: which closed form applies.
        dh: the equivalent standard-DH chain: ``dh.fk(to_dh(q)) == chain.fk(q)`` (to rounding
            and ``deviation``), with the chain's limits (mapped by the signs), names and name.
        signs: ``(n,)`` float64, +-1: the DH joint ``i`` turns ``signs[i]`` times joint ``i``.
        deviation: how far the chain is from the ideal structure (the largest of the lengths,
            m, and angles, rad, that the closed form takes as 0; 0 for an exact arm).
    """

    form: ClosedForm
    dh: DHChain
    signs: Tensor
    deviation: float

    def to_dh(self, q: Tensor) -> Tensor:
        """Joint values of the chain ``(..., n)`` -> those of :attr:`dh` ``(..., n)``."""
        return q * self.signs.to(q)

    def from_dh(self, q_dh: Tensor) -> Tensor:
        """Joint values of :attr:`dh` ``(..., n)`` -> those of the chain ``(..., n)``."""
        return q_dh * self.signs.to(q_dh)


def structure(chain: Chain, tol: float = DETECT_TOL) -> Structure:
    """The closed form that solves ``chain``, found from its joint axes (module doc).

    Args:
        chain: any :class:`~iiwa_torch.chain.Chain` (DH preset, URDF, hand-made) of revolute or
            continuous joints.
        tol: how far (m, rad) axes may miss meeting, being parallel or perpendicular.

    Raises:
        ValueError: naming every condition the chain fails (e.g. ``axes 6 and 7 do not meet
            (closest approach 0.088 m)``); :func:`iiwa_torch.ik.solve` solves any chain.
    """
    check_instance(chain, Chain, "chain")
    check_positive(tol, "tol")
    n = chain.n_joints
    fallback = "; iiwa_torch.ik.solve (the gradient IK) solves any chain"
    if n not in _FORMS:
        raise ValueError(f"chain {chain.name!r} has {n} joints: the closed forms solve 3 (planar 3R), "
                         f"6 (Pieper) and 7 (S-R-S){fallback}")
    form, rows, what = _FORMS[n]
    prismatic = [i + 1 for i, kind in enumerate(chain.kinds) if kind is JointKind.PRISMATIC]
    if prismatic:
        raise ValueError(f"chain {chain.name!r} is not a {what}: joints {prismatic} are prismatic{fallback}")
    points, dirs, end = _axis_lines(chain)
    first, _, _ = _table(points, dirs, end, tol)
    signs = _signs(first, rows, dirs, tol)
    table, base, snapped = _table(points, dirs * signs[:, None], end, tol)
    problems, deviation = _check_rows(table, rows, tol)
    if problems:
        raise ValueError(f"chain {chain.name!r} is not a {what}: " + "; ".join(problems) + fallback)
    lo, hi = chain.limits.detach().cpu().to(torch.float64).nan_to_num(posinf=math.pi, neginf=-math.pi)  # one turn
    lo, hi = torch.where(signs > 0, lo, -hi), torch.where(signs > 0, hi, -lo)
    kwargs = dict(limits=torch.stack([lo, hi]), joint_names=chain.joint_names, name=chain.name, base=base)
    bare = DHChain(table, **kwargs)
    zero = torch.zeros(n, dtype=torch.float64)
    tool = _inverse(bare.fk(zero)) @ chain.fk(zero.to(chain.limits.device)).detach().cpu().to(torch.float64)
    dh = DHChain(table, tool=tool, **kwargs)
    return Structure(form=form, dh=dh, signs=signs, deviation=max(deviation, snapped))


def solve(
    chain: Chain,
    target: Tensor,
    psi=None,
    *,
    tol: float = DETECT_TOL,
    world: World | None = None,
    margin: float = 0.0,
    capsules: Capsules | None = None,
) -> AnalyticSolutions:
    """Every closed-form IK branch of ``chain``, whichever closed form :func:`structure` finds.

    Args:
        chain: any chain :func:`structure` recognises.
        target: ``(..., 4, 4)`` end-effector poses in the world frame (m).
        psi: the arm angles (rad) of an S-R-S arm, as for :func:`~iiwa_torch.ik.analytic.iiwa`
            (measured in the equivalent chain's frame 0: the first axis and the world x axis);
            must be None for the other arms.
        tol: as for :func:`structure`.
        world, margin, capsules: optional obstacles, as for :func:`~iiwa_torch.ik.analytic.pieper`
            (clearances of the chain itself; a chain that is not a DH preset needs ``capsules``).

    Returns:
        :class:`AnalyticSolutions` of the chain's joint values: ``q (..., 2, 3)`` (planar 3R; a
        target off the arm's plane is unreachable), ``(..., 8, 6)`` (Pieper) or ``(..., [K,] 8, 7)``
        (S-R-S), branches as for :func:`~iiwa_torch.ik.analytic.planar3r`, ``pieper`` and ``iiwa``
        on :attr:`Structure.dh`. Where the chain departs from the ideal by more than rounding, each
        reachable branch gets three Gauss-Newton steps (each kept where it lowers the pose error) and
        counts as reachable only if it then closes to 1e-9 (float64; 100 ulp in float32).

    Raises:
        ValueError: a chain :func:`structure` rejects, or one more than 1e-6 (m, rad) from the ideal arm.
    """
    found = structure(chain, tol)
    if found.deviation > IDEAL_TOL:
        raise ValueError(f"chain {chain.name!r} is {found.deviation:.2g} (m or rad) from an ideal {found.form.value} "
                         f"arm, which structure(tol={tol:g}) accepts but the closed form takes only within "
                         f"{IDEAL_TOL:g}; iiwa_torch.ik.solve (the gradient IK) solves any chain")
    if (psi is None) == (found.form is ClosedForm.SRS):
        need = "needs the arm angles psi" if psi is None else "takes no psi (only an S-R-S arm has an arm angle)"
        raise ValueError(f"chain {chain.name!r} is a {found.form.value} arm: solve {need}")
    if found.form is ClosedForm.SRS:
        sol = iiwa(found.dh, target, psi)
    elif found.form is ClosedForm.PIEPER:
        sol = pieper(found.dh, target)
    else:
        sol = _planar(found.dh, target)
    q = found.from_dh(sol.q)
    if found.deviation > _EXACT:
        for _ in range(_NEWTON_STEPS):
            q = _newton_step(chain, q, target, sol.reachable)
        within, closes = chain.within_limits(q), _closure(chain, q, target) <= _closure_tol(q.dtype)
        reachable = sol.reachable & closes
        sol = dataclasses.replace(sol, reachable=reachable, valid=reachable & within, within_limits=within)
    sol = dataclasses.replace(sol, q=q)
    return with_clearance(chain, sol, target.ndim - 2, world, margin, capsules)


def _planar(dh: DHChain, target: Tensor) -> AnalyticSolutions:
    """:func:`planar3r` for ``target (..., 4, 4)`` in the world: the pose of the last DH frame in
    frame 0, read as position and heading in the plane; off the plane (height or tilt beyond the
    reach tolerance) it is unreachable."""
    local = _inverse(dh.base).to(target) @ target @ _inverse(dh.tool).to(target)
    height = float(dh.dh[:, 2].sum())
    plane_tol = max(DETECT_TOL, reach_tol(target.dtype))
    on_plane = ((local[..., 2, 3] - height).abs() <= plane_tol) & (local[..., 2, :2].norm(dim=-1) <= plane_tol)
    flat = DHChain(dh.dh, limits=dh.limits, joint_names=dh.joint_names, name=dh.name)
    sol = planar3r(flat, local[..., 0, 3], local[..., 1, 3], torch.atan2(local[..., 1, 0], local[..., 0, 0]))
    reachable = sol.reachable & on_plane[..., None]
    return dataclasses.replace(sol, reachable=reachable, valid=reachable & sol.within_limits)


def _goal(q: Tensor, target: Tensor) -> Tensor:
    """``target (..., 4, 4)`` expanded over the branches of ``q (..., [K,] B, n)``."""
    branch_dims = q.ndim - 1 - (target.ndim - 2)
    return target.reshape(*target.shape[:-2], *(1,) * branch_dims, 4, 4).expand(*q.shape[:-1], 4, 4)


def _closure(chain: Chain, q: Tensor, target: Tensor) -> Tensor:
    """``(..., [K,] B)``: the larger of the position (m) and rotation (rad) errors of each branch."""
    pos, rot = pose_error(chain.fk(q), _goal(q, target))
    return torch.maximum(pos.norm(dim=-1), rot.norm(dim=-1))


def _closure_tol(dtype: torch.dtype) -> float:
    """The pose error (m, rad) a branch of a chain off the ideal structure may keep and count as reachable."""
    return max(1e-9, 100 * torch.finfo(dtype).eps)


def _newton_step(chain: Chain, q: Tensor, target: Tensor, reachable: Tensor) -> Tensor:
    """``q (..., [K,] B, n)`` after one Gauss-Newton step towards ``target (..., 4, 4)`` on ``chain``
    where ``reachable (..., [K,] B)`` and the step lowers the pose error."""
    goal = _goal(q, target)
    errors = torch.cat(pose_error(chain.fk(q), goal), -1)  # (..., B, 6)
    moved = q + dls_step(chain.jacobian(q), errors, _DAMPING)
    better = torch.cat(pose_error(chain.fk(moved), goal), -1).norm(dim=-1) < errors.norm(dim=-1)
    return torch.where((better & reachable)[..., None], moved, q)


def _axis_lines(chain: Chain) -> tuple[Tensor, Tensor, Tensor]:
    """The joint axes at ``q = 0`` in the world: ``points (n, 3)`` (each the axis point nearest
    the world origin), unit ``dirs (n, 3)``, and the end-effector pose ``(4, 4)``, float64 on the
    CPU, from the Jacobian's columns ``[z x (p_e - p); z]``."""
    zero = torch.zeros(chain.n_joints, dtype=torch.float64, device=chain.limits.device)
    jac = chain.jacobian(zero).detach().cpu().T  # (n, 6)
    end = chain.fk(zero).detach().cpu()
    dirs = jac[:, 3:] / jac[:, 3:].norm(dim=-1, keepdim=True)
    moment = torch.linalg.cross(dirs, end[:3, 3].expand_as(dirs)) - jac[:, :3]  # z x p
    return -torch.linalg.cross(dirs, moment), dirs, end


def _table(points: Tensor, dirs: Tensor, end: Tensor, tol: float) -> tuple[list[list[float]], Tensor, float]:
    """The standard-DH table ``[[a, alpha, d, offset], ...]`` of the axis lines ``points, dirs
    (n, 3)`` (module doc), the base ``(4, 4)`` (frame 0: on axis 1 nearest the world origin, x
    along the world x axis where it can), and the largest angle between axes taken as parallel.

    The last frame sits on axis n level with the end effector ``end (4, 4)``, its x axis that of
    frame n - 1 at ``q = 0`` (row n ``(0, 0, d_n, 0)``); the tool takes the rest."""
    z_prev = dirs[0]
    world = torch.eye(3, dtype=torch.float64)
    x_prev = _perpendicular(world[0], z_prev)
    x_prev = _unit(x_prev if x_prev.norm() > 0.5 else _perpendicular(world[1], z_prev))  # else axis 1 is along x
    o_prev = points[0]
    base = torch.eye(4, dtype=torch.float64)
    base[:3, 0], base[:3, 1], base[:3, 2], base[:3, 3] = x_prev, torch.linalg.cross(z_prev, x_prev), z_prev, o_prev
    rows, snapped = [], 0.0
    for k in range(1, len(dirs) + 1):
        if k < len(dirs):
            z, p = dirs[k], points[k]
            normal = torch.linalg.cross(z_prev, z)
            if normal.norm() > tol:  # the common normal is unique
                x = _unit(normal)
                foot, origin = _closest_points(o_prev, z_prev, p, z)
                alpha = math.atan2(float(normal.norm()), float(z_prev @ z))
            else:  # parallel: the normal through the previous origin
                snapped = max(snapped, float(normal.norm()))
                foot, origin = o_prev, o_prev + _perpendicular(p - o_prev, z_prev)
                x = _unit(origin - foot) if (origin - foot).norm() > tol else x_prev
                z = z_prev if float(z_prev @ z) > 0 else -z_prev
                alpha = 0.0 if float(z_prev @ z) > 0 else math.pi
            a = float((origin - foot) @ x)
        else:  # the last frame: on axis n, level with the end effector
            foot = origin = o_prev + z_prev * float((end[:3, 3] - o_prev) @ z_prev)
            x, z, a, alpha = x_prev, z_prev, 0.0, 0.0
        d = float((foot - o_prev) @ z_prev)
        offset = math.atan2(float(torch.linalg.cross(x_prev, x) @ z_prev), float(x_prev @ x))
        rows.append([a, alpha, d, offset])
        z_prev, x_prev, o_prev = z, x, origin
    return rows, base, snapped


def _signs(rows: list[list[float]], rules: list[dict], dirs: Tensor, tol: float) -> Tensor:
    """``(n,)`` axis signs that meet the sign rules of ``rules``, the table ``rows`` built with the
    axes as given: a positive ``d`` (``"d+"``: turn the axis the row runs along) and parallel
    axes pointing the same way (``"twist0"``: turn the next axis, unless its own ``d+`` fixes it)."""
    pinned = [bool(rule.get("d+")) and abs(row[2]) > tol for row, rule in zip(rows, rules)]
    signs = [math.copysign(1.0, row[2]) if pin else 1.0 for row, pin in zip(rows, pinned)]
    for j, rule in enumerate(rules[: len(rows) - 1]):
        if rule.get("twist0"):
            same = math.copysign(1.0, float(dirs[j] @ dirs[j + 1]))
            if pinned[j + 1]:
                signs[j] = signs[j + 1] * same
            else:
                signs[j + 1] = signs[j] * same
    return torch.tensor(signs, dtype=torch.float64)


def _check_rows(rows: list[list[float]], rules: list[dict], tol: float) -> tuple[list[str], float]:
    """Each rule of ``rules`` the table ``rows`` breaks beyond ``tol``, said of the axes, and the
    largest value the kept zero rules allow (the chain's deviation from the ideal)."""
    problems, deviation = [], 0.0
    for j, ((a, alpha, d, _), rule) in enumerate(zip(rows, rules), start=1):
        pair = f"axes {j} and {j + 1}"
        cos = math.cos(alpha)
        zeros = {  # rule -> (the value it takes as 0, what a larger one means)
            "a0": (abs(a), f"{pair} do not meet (closest approach {abs(a):.3g} m)"),
            "d0": (abs(d), f"axes {j - 1}, {j} and {j + 1} do not meet in one point "
                           f"({abs(d):.3g} m apart along axis {j})"),
            "perp": (abs(cos), f"{pair} are not perpendicular ({abs(math.asin(cos)):.3g} rad off)"),
            "twist0": (abs(alpha), f"{pair} are not parallel ({abs(alpha):.3g} rad apart)"),
        }
        for value, text in [zeros[key] for key in zeros if rule.get(key)]:
            if value > tol:
                problems.append(text)
            else:
                deviation = max(deviation, value)
        if rule.get("a+") and a <= tol:
            problems.append(f"{pair} coincide (no link between them)")
        if rule.get("d+") and d <= tol:
            problems.append(f"axis {j} has no length between its meetings with axes {j - 1} and {j + 1}")
    return problems, deviation


def _closest_points(p: Tensor, u: Tensor, q: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """The points of the lines ``p + s u`` and ``q + t v`` (unit, not parallel) nearest each other."""
    w, b = p - q, float(u @ v)
    du, dv = float(u @ w), float(v @ w)
    denom = 1.0 - b * b
    return p + u * ((b * dv - du) / denom), q + v * ((dv - b * du) / denom)


def _perpendicular(vector: Tensor, axis: Tensor) -> Tensor:
    """The part of ``vector (3,)`` perpendicular to the unit ``axis (3,)``."""
    return vector - axis * float(vector @ axis)


def _unit(vector: Tensor) -> Tensor:
    return vector / vector.norm()


def _inverse(pose: Tensor) -> Tensor:
    """The inverse of a rigid ``(4, 4)`` transform (transpose and back-rotated translation)."""
    out = torch.eye(4, dtype=pose.dtype, device=pose.device)
    out[:3, :3] = pose[:3, :3].T
    out[:3, 3] = -(pose[:3, :3].T @ pose[:3, 3])
    return out
