"""Closed-form IK of a planar 3R arm: both elbow branches (seed 001's algebraic solution)."""

from __future__ import annotations

import functools

import torch

from ...checks import broadcast_shapes, check_float_tensor
from ...collision import Capsules, World
from ...dh import DHChain
from ._common import (
    AnalyticSolutions,
    as_values,
    check_chain,
    finish,
    reach_tol,
    safe_atan2,
    safe_norm2,
    triangle,
    with_clearance,
)

__all__ = ["planar3r"]

Tensor = torch.Tensor

_LINK = {"twist0": True, "a+": True}
PLANAR_ROWS = [_LINK, _LINK, {"twist0": True}]  # the rows planar3r needs (``_common.check_chain``)


def _check_planar_transform(matrix: Tensor, name: str) -> None:
    if abs(float(matrix[2, 2]) - 1.0) > 1e-12:
        raise ValueError(
            f"the planar 3R closed form needs a {name} that rotates about z only, got {matrix[:3, :3].tolist()}"
        )


def _pose_values(chain: DHChain, x, y, phi) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`planar3r`'s ``x, y, phi`` (tensors or numbers), checked, as tensors broadcast together
    on the chain's device, in the tensors' promoted float dtype (float64 for plain numbers)."""
    named = (("x", x), ("y", y), ("phi", phi))
    for name, v in named:
        if isinstance(v, torch.Tensor):
            check_float_tensor(v, name, "(...)")
    floats = [v.dtype for v in (x, y, phi) if isinstance(v, torch.Tensor)]
    dtype = functools.reduce(torch.promote_types, floats) if floats else chain.dh.dtype  # numbers: float64
    x, y, phi = (as_values(v, name, dtype, chain.dh.device) for name, v in named)
    broadcast_shapes({"x": x.shape, "y": y.shape, "phi": phi.shape})
    return tuple(torch.broadcast_tensors(x, y, phi))


def planar3r(
    chain: DHChain, x, y, phi, *, world: World | None = None, margin: float = 0.0, capsules: Capsules | None = None
) -> AnalyticSolutions:
    """Both IK solutions of a planar 3R arm for the end-effector pose ``(x, y, phi)``.

    Args:
        chain: three joints about parallel z axes (standard DH rows ``(a_i, 0, d_i, offset_i)``,
            ``a_1, a_2 > 0``), with a base and tool that rotate about z only (e.g.
            :func:`iiwa_torch.robots.planar3r`).
        x, y: end-effector position (m) in the world xy plane, broadcastable tensors or floats
            (the result takes the tensors' float dtype, float64 for plain numbers).
        phi: end-effector heading (rad): the angle of its x axis from the world x axis.
        world, margin, capsules: optional obstacles, margin and capsule model, as in
            :func:`~iiwa_torch.ik.analytic.pieper` (the arm lies in the z = 0 plane: use
            ``World(floor=None, ...)``).

    Returns:
        :class:`AnalyticSolutions` with ``q (..., 2, 3)``; branch 0 has the elbow angle
        ``q2 + offset_2`` in ``[0, pi]`` ("elbow down" for ``x > 0``), branch 1 in ``[-pi, 0]``.

    The wrist point (frame 2's origin) is ``w = p - a_3 (cos h, sin h)`` for frame 3's heading
    ``h``; ``theta_2`` follows by the law of cosines, ``theta_1 = atan2(w_y, w_x) - atan2(a_2 sin
    theta_2, a_1 + a_2 cos theta_2)``, ``theta_3 = h - theta_1 - theta_2``. Out of reach: not
    ``reachable``, the arm stretched towards the target. Stretched or folded: singular.
    """
    rows = check_chain(chain, 3, PLANAR_ROWS, "planar 3R")
    _check_planar_transform(chain.base, "base")
    _check_planar_transform(chain.tool, "tool")
    x, y, phi = _pose_values(chain, x, y, phi)
    dtype = x.dtype

    # Pose of frame 3 in frame 0 (base and tool stripped), in the plane: heading h, origin p.
    base, tool = chain.base.to(dtype), chain.tool.to(dtype)
    base_heading = torch.atan2(base[1, 0], base[0, 0])
    tool_heading = torch.atan2(tool[1, 0], tool[0, 0])
    h = phi - base_heading - tool_heading
    cb, sb = torch.cos(base_heading), torch.sin(base_heading)
    px0, py0 = x - base[0, 3], y - base[1, 3]
    px, py = cb * px0 + sb * py0, -sb * px0 + cb * py0  # into frame 0
    ch, sh = torch.cos(h), torch.sin(h)
    (a1, *_), (a2, *_), (a3, *_) = rows
    # Tool offset and the last link, along frame 3's x and y: the wrist point (frame 2 origin).
    reach_x, reach_y = a3 + tool[0, 3], tool[1, 3]
    wx = px - ch * reach_x + sh * reach_y
    wy = py - sh * reach_x - ch * reach_y

    c2, s2_abs, ok = triangle(safe_norm2(wx, wy), a1, a2, reach_tol(dtype))
    sign = torch.tensor([1.0, -1.0], dtype=dtype, device=x.device)
    s2 = s2_abs[..., None] * sign  # (..., 2)
    c2 = c2[..., None].expand_as(s2)
    theta2 = torch.atan2(s2, c2)
    theta1 = safe_atan2(wy, wx)[..., None] - safe_atan2(a2 * s2, a1 + a2 * c2)
    theta3 = h[..., None] - theta1 - theta2
    sol = finish(chain, [theta1, theta2, theta3], ok[..., None], branch_dims=1)
    return with_clearance(chain, sol, x.ndim, world, margin, capsules)
