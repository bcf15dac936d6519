"""Robots: the presets (DH chains with limits and speeds, sources in docs/robots.md) and
:func:`from_urdf` for any serial arm in a URDF file. Each returns a fresh float64 chain.
"""

from __future__ import annotations

import math
import os

from .chain import Chain
from .checks import check_nonnegative, check_positive
from .dh import Convention, DHChain

__all__ = ["iiwa14", "iiwa7", "puma560", "lrmate200ic", "planar3r", "from_urdf", "PRESETS", "IIWA_HOME"]

_PI2 = math.pi / 2
_IIWA_LIMITS_DEG = (170, 120, 170, 120, 170, 120, 175)

#: Home posture of both iiwa presets (radians): elbow and wrist bent, away from the
#: stretched-out singularity at q = 0.
IIWA_HOME = tuple(math.radians(v) for v in (0.0, 30.0, 0.0, -60.0, 0.0, 30.0, 0.0))


def _deg(values) -> list[float]:
    return [math.radians(v) for v in values]


def _iiwa(name: str, l_bs: float, l_se: float, l_ew: float, flange: float, speeds_deg, tool) -> DHChain:
    check_nonnegative(flange, "flange")
    table = [
        (0, -_PI2, l_bs, 0),
        (0, _PI2, 0, 0),
        (0, _PI2, l_se, 0),
        (0, -_PI2, 0, 0),
        (0, -_PI2, l_ew, 0),
        (0, _PI2, 0, 0),
        (0, 0, flange, 0),
    ]
    limits = [_deg(-v for v in _IIWA_LIMITS_DEG), _deg(_IIWA_LIMITS_DEG)]
    return DHChain(
        table,
        convention=Convention.STANDARD,
        limits=limits,
        joint_names=[f"A{i}" for i in range(1, 8)],
        velocity_limits=_deg(speeds_deg),
        tool=tool,
        name=name,
    )


def iiwa14(flange: float = 0.126, tool=None) -> DHChain:
    """KUKA LBR iiwa 14 R820, 7 joints (A1..A7).

    ``flange`` is the wrist-centre-to-flange distance: 0.126 m per KUKA's datasheet (height
    1306 mm at home); the DH model of Pereira et al. uses 0.090. ``tool`` is an optional ``(4, 4)``
    flange-to-tool transform.
    """
    return _iiwa("iiwa14", 0.360, 0.420, 0.400, flange, (85, 85, 100, 75, 130, 135, 135), tool)


def iiwa7(flange: float = 0.126, tool=None) -> DHChain:
    """KUKA LBR iiwa 7 R800, 7 joints (datasheet: height 1266 mm at home)."""
    return _iiwa("iiwa7", 0.340, 0.400, 0.400, flange, (98, 98, 100, 130, 140, 180, 180), tool)


def puma560() -> DHChain:
    """Unimation PUMA 560 in standard DH (P. Corke's table), 6 joints, spherical wrist."""
    table = [
        (0, _PI2, 0.6718, 0),
        (0.4318, 0, 0, 0),
        (0.0203, -_PI2, 0.15005, 0),
        (0, _PI2, 0.4318, 0),
        (0, -_PI2, 0, 0),
        (0, 0, 0, 0),
    ]
    limits = [_deg([-160, -45, -225, -110, -100, -266]), _deg([160, 225, 45, 170, 100, 266])]
    return DHChain(table, limits=limits, name="puma560")


def lrmate200ic() -> DHChain:
    """FANUC LR Mate 200iC in standard DH (plain joint angles, not the controller's J2/J3
    coupling), 6 joints, spherical wrist, flange 0.080 m past the wrist centre."""
    table = [
        (0.075, -_PI2, 0.330, 0),
        (0.300, 0, 0, -_PI2),
        (0.075, -_PI2, 0, 0),
        (0, _PI2, 0.320, 0),
        (0, -_PI2, 0, 0),
        (0, 0, 0.080, 0),
    ]
    limits = [_deg([-170, -100, -70, -190, -125, -360]), _deg([170, 145, 205, 190, 125, 360])]
    return DHChain(table, limits=limits, name="lrmate200ic")


def planar3r(l1: float = 1.0, l2: float = 1.0, l3: float = 0.5) -> DHChain:
    """Planar arm of three revolute joints about parallel z axes, links ``l1, l2, l3`` (m).

    The end effector moves in the base's xy plane; its heading is ``q1 + q2 + q3``.
    """
    for value, name in ((l1, "l1"), (l2, "l2"), (l3, "l3")):
        check_positive(value, name)
    table = [(l1, 0, 0, 0), (l2, 0, 0, 0), (l3, 0, 0, 0)]
    return DHChain(table, name="planar3r")


PRESETS = {"iiwa14": iiwa14, "iiwa7": iiwa7, "puma560": puma560, "lrmate200ic": lrmate200ic, "planar3r": planar3r}


def from_urdf(source: str | os.PathLike, end_link: str | None = None, base_link: str | None = None) -> Chain:
    """The chain of a URDF (a path or the XML text; the ``urdf`` extra) from ``base_link`` (default the
    root) to ``end_link`` (default the only leaf), as :func:`iiwa_torch.urdf.read_urdf` reads it:
    fixed joints folded in, limits and speeds from ``<limit>``. ``fk_all`` gives the base link, then
    each movable joint's child link.
    """
    from .urdf import read_urdf

    path = read_urdf(source, end_link=end_link, base_link=base_link)
    joints = path.joints
    speeds = [j.velocity for j in joints]
    return Chain(
        [j.origin for j in joints],
        [j.axis for j in joints],
        kinds=[j.kind for j in joints],
        limits=[[j.lower for j in joints], [j.upper for j in joints]],
        joint_names=[j.name for j in joints],
        link_names=list(path.links),
        tool=path.tool,
        velocity_limits=None if None in speeds else speeds,
        name=path.robot,
    )
