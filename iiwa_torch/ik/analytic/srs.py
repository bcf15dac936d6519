"""Closed-form IK of the KUKA LBR iiwa (7R, shoulder-elbow-wrist with spherical shoulder
and wrist): every branch for a given arm angle, the arm angle of a configuration and
the 6-DOF variant with joint 3 locked (seed 002).

Structure (standard DH rows ``(a, alpha, d, offset)``, read from the chain): all ``a = 0``;
twists ``+-pi/2`` on rows 1-6; ``d_2 = d_4 = d_6 = 0``; ``d_1`` the shoulder height,
``d_3 > 0`` upper arm, ``d_5 > 0`` forearm; row 7 (flange) and the tool are arbitrary.
The shoulder ``S = (0, 0, d_1)`` (frame 0), elbow ``E`` (origin of frame 3) and wrist
``W`` (origin of frame 5) are joint-axis intersections.

**Arm angle** ``psi``. Let ``u`` be the unit vector from ``S`` to ``W``. The *reference
plane* is the plane through ``S`` and ``W`` that contains the base z axis (the vertical
plane through the shoulder-wrist line): it is where the elbow lies whenever ``q3 = 0`` or
``q3 = pi``. Its in-plane unit normal to ``u`` pointing up is
``v_ref = (-u_z cos b, -u_z sin b, sqrt(u_x^2 + u_y^2))`` with ``b = atan2(u_y, u_x)``, and
``w_ref = u x v_ref = (sin b, -cos b, 0)``. The elbow lies on a circle about the line
``SW``; ``psi`` is the angle of ``E - S`` about ``u`` (right hand), measured from ``v_ref``:
``psi = atan2((E - S).w_ref, (E - S).v_ref)``. So ``psi = 0`` is "elbow up" in the vertical
plane, ``psi = pi`` "elbow down", and one ``psi`` is one elbow position, shared by all 8
branches. If ``SW`` is vertical, ``b = 0`` (the reference plane is the base xz plane).

**Branches** at a given ``psi``: ``k = 4 shoulder + 2 elbow + wrist``, 0 for the first
sign: ``sin(theta_2) >= 0``, ``sin(theta_4) >= 0``, ``sin(theta_6) >= 0`` (``theta = q +
offset``; the iiwa's offsets are 0, so these are the signs of q2, q4, q6).

Method: ``|SW|`` fixes ``theta_4`` (law of cosines); ``psi`` fixes the elbow and with it
``R_03``, built from the upper-arm direction and the normal of the ``S, E, W`` plane (no
division by ``sin theta_4``); ``R_03`` and ``R_04^T R_06`` are then split into the
shoulder and wrist angles as ``Rz Rx Rz Rx Rz`` products.

Singularities (finite values, not errors): arm stretched (``theta_4 = 0``; ``psi`` is then
undefined and :func:`iiwa_arm_angle` returns 0), ``SW`` along the base z axis (see above),
shoulder or wrist aligned (``sin theta_2 = 0`` or ``sin theta_6 = 0``: only the sum or
difference of the neighbouring angles is determined; the first is set to 0 there and the
pose is still reproduced exactly).

One solution per pose, sweeping the arm angle: :func:`~.srs_sweep.iiwa_solve`.
"""

from __future__ import annotations

import torch

from ...collision import Capsules, World
from ...dh import DHChain
from ._common import (
    TORCH,
    AnalyticSolutions,
    acos_pair,
    as_values,
    check_chain,
    check_target,
    decompose_zxzxz,
    entries,
    finish,
    last_frame_target,
    reach_tol,
    safe_atan2,
    safe_norm2,
    sigma,
    transpose_times,
    triangle,
    with_clearance,
    zxzx,
)

__all__ = ["iiwa", "iiwa_arm_angle", "iiwa_q3_locked"]

Tensor = torch.Tensor

SRS_ROWS = [
    {"a0": True, "perp": True},
    {"a0": True, "d0": True, "perp": True},
    {"a0": True, "d+": True, "perp": True},
    {"a0": True, "d0": True, "perp": True},
    {"a0": True, "d+": True, "perp": True},
    {"a0": True, "d0": True, "perp": True},
    {},
]


class Geometry:
    """The chain's constants for the closed form (checked on construction)."""

    def __init__(self, chain: DHChain) -> None:
        rows = check_chain(chain, 7, SRS_ROWS, "iiwa (S-R-S)")
        self.d1, self.d3, self.d5 = rows[0][2], rows[2][2], rows[4][2]
        self.sig = [sigma(row[1]) for row in rows[:6]]  # sin(alpha_1..6)


def wrist_frame(chain: DHChain, target: Tensor) -> tuple[Tensor, Tensor]:
    """``(R, sw)``: the rotation of ``T_06 Rz(theta7)`` ``(..., 3, 3)`` and ``W - S`` ``(..., 3)``."""
    check_target(chain, target)
    frame6 = last_frame_target(chain, target)
    sw = frame6[..., :3, 3] - torch.tensor([0.0, 0.0, float(chain.dh[0, 2])], dtype=target.dtype, device=target.device)
    return frame6[..., :3, :3], sw


def _elbow(geo: Geometry, sw: Tensor, tol: float, ops=TORCH, dist=None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Both elbow branches from ``W - S``: ``theta_4 (..., 2)``, ``cos theta_4 (...)``,
    ``sin theta_4 (..., 2)`` and whether ``W`` is in reach ``(...)`` (arrays of ``ops``, ``_common``;
    ``dist``: ``|W - S|`` if known)."""
    if dist is None:
        dist = safe_norm2(safe_norm2(sw[..., 0], sw[..., 1], ops), sw[..., 2], ops)
    c4, s4_abs, ok = triangle(dist, geo.d3, geo.d5, tol, ops)
    c4 = -geo.sig[2] * geo.sig[3] * c4  # the triangle's angle is between z2 and z4, up to sign
    s4 = s4_abs[..., None] * ops.signs(sw)
    return ops.atan2(s4, c4[..., None]), c4, s4, ok


def _reference(u: tuple, ops=TORCH) -> tuple[tuple, tuple]:
    """Unit ``u`` along ``SW`` (3 components) -> ``(v_ref, w_ref)``, 3 components each (module doc)."""
    ux, uy, uz = u
    b = safe_atan2(uy, ux, ops)
    cb, sb = ops.cos(b), ops.sin(b)
    return (-uz * cb, -uz * sb, safe_norm2(ux, uy, ops)), (sb, -cb, 0.0)


def _dot(a: tuple, b: tuple) -> Tensor:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def iiwa(
    chain: DHChain,
    target: Tensor,
    psi,
    *,
    world: World | None = None,
    margin: float = 0.0,
    capsules: Capsules | None = None,
) -> AnalyticSolutions:
    """All 8 IK branches of an iiwa-like 7R arm for given arm angles.

    Args:
        chain: e.g. :func:`iiwa_torch.robots.iiwa14` (any flange length, base and tool).
        target: ``(..., 4, 4)`` end-effector poses in the world frame (m).
        psi: arm angles (rad, module doc), a float or a tensor of shape ``(...)``
            (broadcastable: one angle per pose) or ``(..., K)`` (K angles per pose).
        world, margin, capsules: optional obstacles (batch shape broadcasting with ``(...)``),
            a clearance margin (m) and a capsule model (default ``robot_capsules(chain)``): each
            branch then carries its ``clearance`` and ``collision_free`` (``valid`` requires it).

    Returns:
        :class:`AnalyticSolutions` with ``q (..., [K,] 8, 7)``, branch ``k = 4 shoulder +
        2 elbow + wrist`` (module doc).
    """
    thetas, reachable = _iiwa_thetas(chain, target, psi)
    sol = finish(chain, thetas, reachable, branch_dims=3)
    return with_clearance(chain, sol, target.ndim - 2, world, margin, capsules)


def _iiwa_thetas(chain: DHChain, target: Tensor, psi) -> tuple[list[Tensor], Tensor]:
    """:func:`iiwa` before assembly: the 7 DH angles, each broadcastable to
    ``(..., [K,] 2 shoulder, 2 elbow, 2 wrist)``, and ``reachable`` (broadcastable too)."""
    geo = Geometry(chain)
    rot, sw = wrist_frame(chain, target)
    psi = as_values(psi, "psi", target.dtype, target.device)
    batch_dims = target.ndim - 2
    if psi.ndim == batch_dims + 1:  # K angles per pose
        rot, sw = rot[..., None, :, :], sw[..., None, :]
    elif psi.ndim > batch_dims:
        raise ValueError(
            f"psi must have shape (...) or (..., K) for targets of shape (..., 4, 4) = {tuple(target.shape)}, "
            f"got {tuple(psi.shape)}"
        )
    as_values(psi[..., 0] if psi.ndim == batch_dims + 1 else psi, "psi", target.dtype, target.device, target.shape[:-2])
    return closed_form(geo, rot, sw, psi, reach_tol(target.dtype))


def closed_form(geo: Geometry, rot, sw, psi, tol: float, ops=TORCH) -> tuple[list, Tensor]:
    """:func:`_iiwa_thetas` from the rotation ``R (..., 3, 3)`` and ``W - S (..., 3)`` of
    :func:`wrist_frame` and the arm angles ``psi``, broadcasting with ``(...)``, in the arrays of
    ``ops`` (``_common``: torch, or numpy for :func:`iiwa_solve`'s small batches)."""
    # Vectors as 3 separate component tensors: every step below is elementwise over the batch.
    sx, sy, sz = sw[..., 0], sw[..., 1], sw[..., 2]
    dist = safe_norm2(safe_norm2(sx, sy, ops), sz, ops)
    theta4, c4, s4, reachable = _elbow(geo, sw, tol, ops, dist)
    u = (sx / dist, sy / dist, sz / dist)
    v_ref, w_ref = _reference(u, ops)
    cp, sp = ops.cos(psi), ops.sin(psi)
    v = tuple(cp * p + sp * q for p, q in zip(v_ref, w_ref))  # elbow direction off the SW line
    n = tuple(cp * q - sp * p for p, q in zip(v_ref, w_ref))  # u x v: normal of the S, E, W plane
    # Angle alpha at S between u and the upper arm e, from theta4 itself (so that E and
    # theta4 agree exactly): dist u = d3 e + d5 f with e.f = -s3 s4 cos(theta4), |e x f| = |sin theta4|.
    sig = geo.sig
    cos_a = (geo.d3 - sig[2] * sig[3] * geo.d5 * c4) / dist
    sin_a = geo.d5 * abs(s4[..., 0]) / dist
    e = tuple(cos_a * p + sin_a * q for p, q in zip(u, v))  # upper arm, z_2
    x_dir = tuple(sin_a * p - cos_a * q for p, q in zip(u, v))  # e x n
    # Columns of R_03, per elbow branch (last dim): x3 = s3 kappa (e x n), y3 = s3 e, z3 = kappa n
    # with kappa = s3 s4 sign(sin theta4).
    kappa = sig[2] * sig[3] * ops.signs(sw)
    x3 = tuple(sig[2] * kappa * p[..., None] for p in x_dir)  # (..., 2)
    y3 = tuple(sig[2] * p[..., None] for p in e)  # (..., 1)
    z3 = tuple(kappa * p[..., None] for p in n)  # (..., 2)
    # Shoulder: R_03 Rx(alpha3)^T = Rz(theta1) Rx(alpha1) Rz(theta2) Rx(alpha2) Rz(theta3), columns x3, s3 y3.
    t1, t2, t3 = decompose_zxzxz([[x3[k], sig[2] * y3[k]] for k in range(3)], sig[0], sig[1], ops)  # (..., 1|2, 2)
    # Wrist: R_04 = R_03 Rz(theta4) Rx(alpha4), then columns 0, 2 of R_04^T R.
    c4 = c4[..., None]
    r04 = (
        tuple(c4 * p + s4 * q for p, q in zip(x3, y3)),
        tuple(sig[3] * p for p in z3),
        tuple(sig[3] * (s4 * p - c4 * q) for p, q in zip(x3, y3)),
    )
    cols = entries(rot[..., :, 0:3:2], ops)  # 3 x 2, per pose
    cols = [tuple(cols[k][j][..., None] for k in range(3)) for j in range(2)]
    m = [[_dot(r04[i], cols[j]) for j in range(2)] for i in range(3)]
    t5, t6, t7 = decompose_zxzxz(m, sig[4], sig[5], ops)  # (..., 2, 2)
    shoulder = [ops.swap(t)[..., None] for t in (t1, t2, t3)]
    thetas = [*shoulder, theta4[..., None, :, None], *(t[..., None, :, :] for t in (t5, t6, t7))]
    return thetas, reachable[..., None, None, None]


def iiwa_arm_angle(chain: DHChain, q: Tensor) -> Tensor:
    """Arm angle of configurations: ``q (..., 7) -> psi (...)`` radians in ``(-pi, pi]``
    (module doc; the inverse of :func:`iiwa`: ``iiwa(chain, chain.fk(q), iiwa_arm_angle(chain, q))``
    contains ``q``). 0 where the arm is stretched (elbow on the shoulder-wrist line)."""
    Geometry(chain)
    link_frames = chain.fk_all(q)  # world frame; bring S, E, W back into frame 0
    base_rot = chain.base[:3, :3].to(q.dtype)
    points = (link_frames[..., [1, 3, 5], :3, 3] - chain.base[:3, 3].to(q.dtype)) @ base_rot
    return arm_angle_of_points(*points.unbind(-2))


def arm_angle_of_points(s, e, w, ops=TORCH):
    """The arm angle from the points ``S, E, W (..., 3)`` in frame 0 (arrays of ``ops``)."""
    sw, se = w - s, e - s
    sx, sy, sz = sw[..., 0], sw[..., 1], sw[..., 2]
    dist = safe_norm2(safe_norm2(sx, sy, ops), sz, ops)
    v_ref, w_ref = _reference((sx / dist, sy / dist, sz / dist), ops)
    se = (se[..., 0], se[..., 1], se[..., 2])
    return safe_atan2(_dot(se, w_ref), _dot(se, v_ref), ops)


def _locked_shoulder(geo: Geometry, sw: Tensor, theta3: Tensor, theta4: Tensor, tol: float):
    """:func:`iiwa_q3_locked`'s shoulder: ``sw (..., 3)`` and ``theta3, theta4 (..., 2 elbow)`` (rad) ->
    ``theta1, theta2 (..., 2 elbow, 2 shoulder)`` and ``ok (..., 2 elbow)``, where joint 2 can
    turn ``W - S`` to the height of ``W``."""
    sig = geo.sig
    c3, s3, c4, s4 = torch.cos(theta3), torch.sin(theta3), torch.cos(theta4), torch.sin(theta4)
    # p = W - S in frame 2, then p' = Rx(alpha2) p.
    px = geo.d5 * sig[3] * s4 * c3
    py = geo.d5 * sig[3] * s4 * s3
    pz = geo.d3 - geo.d5 * sig[2] * sig[3] * c4
    a, b, c = px, -sig[1] * pz, sig[1] * py  # p'
    height = (sig[0] * sw[..., 2])[..., None]
    cos_d, sin_d, ok = acos_pair(height / safe_norm2(a, b), tol)
    delta = torch.atan2(sin_d[..., None] * torch.tensor([1.0, -1.0], dtype=a.dtype, device=a.device), cos_d[..., None])
    theta2 = safe_atan2(a, b)[..., None] + delta  # (..., 2 elbow, 2 shoulder)
    c2, s2 = torch.cos(theta2), torch.sin(theta2)
    vx, vz = c2 * a[..., None] - s2 * b[..., None], c[..., None].expand_as(c2)
    theta1 = safe_atan2(sw[..., 1], sw[..., 0])[..., None, None] - safe_atan2(-sig[0] * vz, vx)
    return theta1, theta2, ok


def iiwa_q3_locked(
    chain: DHChain,
    target: Tensor,
    q3=0.0,
    *,
    world: World | None = None,
    margin: float = 0.0,
    capsules: Capsules | None = None,
) -> AnalyticSolutions:
    """All 8 IK branches of the iiwa with joint 3 held at ``q3`` (seed 002's 6-DOF arm).

    Args:
        chain: as for :func:`iiwa`.
        target: ``(..., 4, 4)`` end-effector poses in the world frame (m).
        q3: the locked joint angle (rad), a float or a tensor broadcastable to ``(...)``.
        world, margin, capsules: as for :func:`iiwa`.

    Returns:
        :class:`AnalyticSolutions` with ``q (..., 8, 7)`` (``q[..., 2] == q3``), branch
        ``k = 4 shoulder + 2 elbow + wrist``: elbow and wrist as in :func:`iiwa`, shoulder 0
        for ``theta_2 = g + acos(...)``, 1 for ``g - acos(...)`` (below).

    With ``theta_3, theta_4`` fixed, ``W - S`` seen from frame 2 is a fixed vector ``p``;
    joint 2 must turn it to the height of ``W``: ``A sin(theta_2) + B cos(theta_2) = C``,
    ``theta_2 = g +- acos(C / sqrt(A^2 + B^2))`` with ``g = atan2(A, B)``; joint 1 then turns
    it about the base z axis onto ``W``. Unreachable also when ``|C| > sqrt(A^2 + B^2)``.
    """
    geo = Geometry(chain)
    rot, sw = wrist_frame(chain, target)
    theta3 = as_values(q3, "q3", target.dtype, target.device, target.shape[:-2]) + float(chain.dh[2, 3])
    tol = reach_tol(target.dtype)
    sig = geo.sig
    theta4, _, _, reachable = _elbow(geo, sw, tol)  # (..., 2)
    theta3 = theta3[..., None].expand(torch.broadcast_shapes(theta3[..., None].shape, theta4.shape))
    theta1, theta2, ok = _locked_shoulder(geo, sw, theta3, theta4, tol)

    # Columns 0, 2 of R_04^T R = R_24^T (R_02^T R), entry by entry over the batch.
    rot_02 = [[v[..., None, None] for v in row] for row in entries(rot[..., :, 0:3:2])]
    y = transpose_times(zxzx(theta1, theta2, sig[0], sig[1]), rot_02)  # (..., 2 e, 2 s)
    r24 = zxzx(theta3[..., None], theta4[..., None], sig[2], sig[3])  # (..., 2 e, 1)
    t5, t6, t7 = decompose_zxzxz(transpose_times(r24, y), sig[4], sig[5])  # (..., 2 elbow, 2 shoulder, 2 wrist)
    # Reorder the branch dims to (..., 2 shoulder, 2 elbow, 2 wrist).
    thetas = [
        theta1.transpose(-1, -2)[..., None],
        theta2.transpose(-1, -2)[..., None],
        theta3[..., None, :, None],
        theta4[..., None, :, None],
        *(t.transpose(-3, -2) for t in (t5, t6, t7)),
    ]
    sol = finish(chain, thetas, (reachable[..., None] & ok)[..., None, :, None], branch_dims=3)
    return with_clearance(chain, sol, sol.valid.ndim - 1, world, margin, capsules)
