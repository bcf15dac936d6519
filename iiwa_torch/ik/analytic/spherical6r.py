"""Closed-form IK of 6R arms with a spherical wrist (Pieper's decoupling): PUMA 560,
FANUC LR Mate 200iC and any standard-DH arm of the same structure. All 8 branches.

Structure (standard DH rows ``(a, alpha, d, offset)``, read from the chain):

====  =======  ==========  =====  ===================================================
row   a        alpha       d      role
====  =======  ==========  =====  ===================================================
1     a1       +-pi/2      d1     waist: vertical axis, shoulder offset a1 (LR Mate)
2     a2 > 0   0           d2     shoulder: axis parallel to the elbow's
3     a3       +-pi/2      d3     elbow; d2 + d3 is the lateral offset (PUMA: 0.150)
4     0        +-pi/2      d4     wrist roll; the forearm is (a3, d4)
5     0        +-pi/2      0      wrist pitch
6     a6       alpha6      d6     wrist roll / flange (folded into the tool)
====  =======  ==========  =====  ===================================================

Method: the wrist centre ``w`` (frame 5's origin) is the target with tool and row 6 stripped.
Joint 1 puts ``w`` at the lateral offset ``D = d2 + d3``: ``theta_1 = atan2(w_y, w_x) -
atan2(-sig1 D, +-sqrt(r^2 - D^2))`` (shoulder branch 0 for ``+``: wrist in front of the waist).
Joints 2, 3 are a planar two-link arm ``a2``, ``L3 = |(a3, d4)|`` (elbow branch 0 for
``sin(theta_3 + gamma) >= 0``); joints 4-6 follow from ``R_03^T R_06`` (wrist branch 0 for
``sin(theta_5) >= 0``). Branch ``k = 4 shoulder + 2 elbow + wrist``.

Singularities (finite values, not errors): ``r = |D|`` (``D = 0``: ``w`` on the waist axis,
``theta_1 = 0``), arm stretched or folded, wrist aligned (``sin theta_5 = 0``: ``theta_4`` set
so the pose is still reproduced).

Up to ``PIEPER_NUMPY_BATCH`` CPU poses with nothing to differentiate and no world run in numpy,
in the target's dtype (a torch op's few microseconds are most of a small call); float64 ones go
through :func:`iiwa_torch.compiled.numba_kernels.pieper_branches` when numba is enabled (the same
closed form as scalar loops; ``tests/test_pieper_numpy.py`` runs every case both ways).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ... import compiled
from ...collision import Capsules, World
from ...dh import DHChain
from ._common import (
    NUMPY,
    TINY,
    TORCH,
    AnalyticSolutions,
    check_chain,
    check_target,
    decompose_zxzxz,
    entries,
    finish,
    last_frame_numpy,
    last_frame_target,
    numpy_applies,
    reach_tol,
    safe_atan2,
    safe_norm2,
    sigma,
    transpose_times,
    triangle,
    with_clearance,
    zxzx,
)

__all__ = ["PIEPER_NUMPY_BATCH", "pieper"]

Tensor = torch.Tensor

PIEPER_NUMPY_BATCH = 512  # up to this many poses per call (CPU, no world, no gradient), pieper runs in numpy

PIEPER_ROWS = [
    {"perp": True},
    {"twist0": True, "a+": True},
    {"perp": True},
    {"a0": True, "perp": True},
    {"a0": True, "d0": True, "perp": True},
    {},
]


def pieper(
    chain: DHChain, target: Tensor, *, world: World | None = None, margin: float = 0.0, capsules: Capsules | None = None
) -> AnalyticSolutions:
    """All 8 IK solutions of a 6R spherical-wrist arm (structure in the module doc).

    Args:
        chain: e.g. :func:`iiwa_torch.robots.puma560` or :func:`~iiwa_torch.robots.lrmate200ic`;
            its base and tool transforms are honoured.
        target: ``(..., 4, 4)`` end-effector poses in the world frame (m).
        world, margin, capsules: optional obstacles (batch shape broadcasting with ``(...)``),
            a clearance margin (m) and a capsule model (default ``robot_capsules(chain)``): each
            branch then carries its ``clearance`` and ``collision_free`` (``valid`` requires it).

    Returns:
        :class:`AnalyticSolutions` with ``q (..., 8, 6)``, branch ``k = 4 shoulder + 2 elbow +
        wrist`` (0 = first sign: wrist centre in front of the waist, ``sin(elbow) >= 0``,
        ``sin(q5 + offset5) >= 0``).
    """
    rows = check_chain(chain, 6, PIEPER_ROWS, "6R spherical-wrist (Pieper)")
    check_target(chain, target)
    tol = reach_tol(target.dtype)
    if world is None and numpy_applies(chain, target.numel() // 16, PIEPER_NUMPY_BATCH, target):
        ops, frame5 = NUMPY, last_frame_numpy(chain, target.detach().numpy())
    else:
        ops, frame5 = TORCH, last_frame_target(chain, target)
    if ops is NUMPY and compiled.ENABLED and target.dtype == torch.float64:
        sol = _solve_compiled(chain, rows, frame5, tol)
    else:
        thetas, reachable = _closed_form(rows, frame5, tol, ops)
        sol = finish(chain, thetas, reachable, branch_dims=3, ops=ops)
    return with_clearance(chain, sol, target.ndim - 2, world, margin, capsules)


def _solve_compiled(chain: DHChain, rows: list[tuple], frame5: np.ndarray, tol: float) -> AnalyticSolutions:
    """:func:`_closed_form` and :func:`~._common.finish` by
    :func:`iiwa_torch.compiled.numba_kernels.pieper_branches` for a float64 ``frame5 (..., 4, 4)``."""
    consts = np.array([*_geometry(rows), tol])
    limits = np.array([[row[3] for row in rows], *chain.limits.tolist()])
    batch = frame5.shape[:-2]
    q, reachable, within = compiled.kernels().pieper_branches(np.ascontiguousarray(frame5.reshape(-1, 4, 4)),
                                                              consts, limits)  # fmt: skip
    q = np.moveaxis(q.reshape(6, *batch, 8), 0, -1)  # joint-major, as finish lays it out
    reachable, within = reachable.reshape(*batch, 8), within.reshape(*batch, 8)
    return AnalyticSolutions(*(torch.from_numpy(x) for x in (q, reachable & within, reachable, within)))


def _geometry(rows: list[tuple]) -> tuple[float, ...]:
    """What the closed form takes from the rows ``(a, alpha, d, offset)``: ``a1, d1, a2``, the
    lateral offset ``d2 + d3``, the forearm ``(a3, d4)`` as length and angle, and ``sigma`` of
    ``alpha1, alpha3, alpha4, alpha5`` (the order :func:`~iiwa_torch.compiled.numba_kernels.pieper_branches` reads)."""
    (a1, al1, d1, _), (a2, _, d2, _), (a3, al3, d3, _), (_, al4, d4, _), (_, al5, *_), _ = rows
    return (a1, d1, a2, d2 + d3, math.hypot(a3, d4), math.atan2(-sigma(al3) * d4, a3),
            *(sigma(al) for al in (al1, al3, al4, al5)))  # fmt: skip


def _closed_form(rows: list[tuple], frame5, tol: float, ops=TORCH) -> tuple[list, Tensor]:
    """The DH angles of every branch from the chain's rows ``(a, alpha, d, offset)`` and
    ``frame5 = T_05 Rz(theta6) (..., 4, 4)`` (:func:`~._common.last_frame_target`), in the arrays of
    ``ops`` (``_common``): 6 arrays broadcasting to ``(..., 2 shoulder, 2 elbow, 2 wrist)`` and
    ``reachable``, broadcastable too."""
    a1, d1, a2, lateral, link3, gamma, s1, s3, s4, s5 = _geometry(rows)
    wx, wy, wz = frame5[..., 0, 3], frame5[..., 1, 3], frame5[..., 2, 3]

    # Waist (shoulder branch): Rz(-theta1) w = (X, -s1 D, wz) with X = +-sqrt(r^2 - D^2).
    r = safe_norm2(wx, wy, ops)
    shoulder_ok = r >= abs(lateral) * (1 - tol)
    along = ops.sqrt(ops.clamp_min((r - abs(lateral)) * (r + abs(lateral)), TINY))  # sqrt(r^2 - D^2)
    sign = ops.signs(wx)
    big_x = along[..., None] * sign  # (..., 2)
    theta1 = safe_atan2(wy, wx, ops)[..., None] - ops.atan2(ops.full_like(big_x, -s1 * lateral), big_x)

    # Shoulder and elbow: planar two-link arm in frame 1's xy plane, second link (a3, -s3 d4).
    px = big_x - a1  # (..., 2)
    py = ops.expand((s1 * (wz - d1))[..., None], px.shape)
    c_el, s_el_abs, elbow_ok = triangle(safe_norm2(px, py, ops), a2, link3, tol, ops)
    s_el = s_el_abs[..., None] * sign  # (..., 2 shoulder, 2 elbow)
    c_el = ops.expand(c_el[..., None], s_el.shape)
    theta3 = ops.atan2(s_el, c_el) - gamma
    theta2 = safe_atan2(py, px, ops)[..., None] - safe_atan2(link3 * s_el, a2 + link3 * c_el, ops)

    # Wrist: R_03^T (R_05 Rz(theta6)) = Rz(theta4) Rx(alpha4) Rz(theta5) Rx(alpha5) Rz(theta6).
    r03 = zxzx(theta1[..., None], theta2 + theta3, s1, s3, ops)  # entries (..., 2, 2); alpha2 = 0
    rot = entries(frame5[..., :3, 0:3:2], ops)  # columns 0, 2 of R (per pose)
    m = transpose_times(r03, [[v[..., None, None] for v in row] for row in rot])  # R_03^T R
    theta4, theta5, theta6 = decompose_zxzxz(m, s4, s5, ops)  # (..., 2, 2, 2)
    thetas = [theta1[..., None, None], theta2[..., None], theta3[..., None], theta4, theta5, theta6]
    return thetas, (shoulder_ok[..., None] & elbow_ok)[..., None, None]
