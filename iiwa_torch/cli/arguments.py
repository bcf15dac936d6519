"""The options turned into what the library takes: the robot, angles and poses (degrees unless
``--rad``), output files; a bad combination raises :class:`UsageError` (exit status 2)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import torch

from .. import robots, so3
from ..chain import Chain, JointKind
from ..checks import require

F64 = torch.float64


class UsageError(Exception):
    """A bad combination of arguments (exit status 2)."""


def chain_of(args: argparse.Namespace) -> Chain:
    """The preset of ``--robot`` (default iiwa14), or the chain of ``--urdf`` up to ``--end-link``."""
    if args.urdf is not None:
        if args.robot is not None or args.flange is not None:
            raise UsageError("--urdf gives the robot: --robot and --flange apply to the presets only")
        try:
            return robots.from_urdf(args.urdf, end_link=args.end_link)
        except OSError as err:  # a file that exists but cannot be read
            raise UsageError(f"--urdf {args.urdf}: cannot read it: {err.strerror or err}") from None
        except (ValueError, TypeError) as err:  # the library's keyword end_link= is this option here
            raise UsageError(f"--urdf {args.urdf}: {str(err).replace('end_link=', '--end-link')}") from None
    if args.end_link is not None:
        raise UsageError("--end-link applies to --urdf only")
    robot = args.robot or "iiwa14"
    if args.flange is not None:
        if robot not in ("iiwa14", "iiwa7"):
            raise UsageError(f"--flange applies to the iiwa presets only, not to {robot}")
        return robots.PRESETS[robot](flange=args.flange)
    return robots.PRESETS[robot]()


def writable(path: str, option: str) -> Path:
    """``path`` as a Path whose folder exists (else a usage error naming ``option``)."""
    folder = Path(path).resolve().parent
    if not folder.is_dir():
        raise UsageError(f"{option} {path}: the folder {folder} does not exist")
    return Path(path)


def drawing():
    """:mod:`iiwa_torch.viz`, once matplotlib and Pillow are known to be installed (checked before any work)."""
    require("matplotlib", "viz")
    require("PIL", "viz")
    from .. import viz

    return viz


def radians(values: list[float], rad: bool) -> list[float]:
    """Command-line angles in radians (they are degrees unless ``rad``)."""
    return list(values) if rad else [math.radians(v) for v in values]


def joint_scales(chain: Chain, rad: bool) -> list[float]:
    """Per joint of ``chain``, its command-line unit in the chain's: 1 (radians, or a prismatic joint's
    metres) or ``pi / 180`` (degrees)."""
    return [1.0 if rad or kind is JointKind.PRISMATIC else math.pi / 180 for kind in chain.kinds]


def joint_unit(chain: Chain, rad: bool) -> str:
    """The command line's joint unit for ``chain``: ``deg`` or ``rad``, and metres for prismatic joints."""
    return ("rad" if rad else "deg") + (", m for prismatic" if JointKind.PRISMATIC in chain.kinds else "")


def outside_limits(chain: Chain, q: list[float], rad: bool) -> str:
    """The joints of ``q`` (rad, m) outside their limits in the command line's units, e.g.
    ``A3 = -180 deg outside +-170``; empty if none is."""
    outside = []
    limits = zip(*chain.limits.tolist())
    for name, kind, k, v, (lo, hi) in zip(chain.joint_names, chain.kinds, joint_scales(chain, rad), q, limits):
        if not lo <= v <= hi:
            unit = "m" if kind is JointKind.PRISMATIC else "rad" if rad else "deg"
            lo, v, hi = (f"{round(x / k, 4 if k == 1.0 else 2):g}" for x in (lo, v, hi))
            span = f"+-{hi}" if lo == f"-{hi}" else f"[{lo}, {hi}]"
            outside.append(f"{name} = {v} {unit} outside {span}")
    return ", ".join(outside)


def joint_angles(chain: Chain, values: list[float], rad: bool, name: str) -> torch.Tensor:
    """``(n,)`` float64 joint values (rad, m) of the option ``name``'s ``values``, one per joint of ``chain``."""
    if len(values) != chain.n_joints:
        raise UsageError(f"{name} needs {chain.n_joints} joint angles for {chain.name}, got {len(values)}")
    return torch.tensor([v * s for v, s in zip(values, joint_scales(chain, rad))], dtype=F64)


def pose_of(values: list[float], rad: bool, name: str) -> torch.Tensor:
    """``x y z roll pitch yaw`` (6 numbers) or a row-major 4x4 matrix (16 numbers) -> (4, 4)."""
    if any(not math.isfinite(v) for v in values):
        raise UsageError(f"{name} must be finite numbers, got {values}")
    if len(values) == 16:
        pose = torch.tensor(values, dtype=F64).reshape(4, 4)
        rot = pose[:3, :3]
        orthonormal = torch.allclose(rot @ rot.T, torch.eye(3, dtype=F64), atol=1e-6)
        bottom = torch.allclose(pose[3], torch.tensor([0.0, 0, 0, 1], dtype=F64))
        if not (orthonormal and bottom and torch.linalg.det(rot) > 0):
            raise UsageError(f"{name}: the 16 numbers are not a homogeneous transform with a rotation part")
        return pose
    if len(values) != 6:
        raise UsageError(
            f"{name} needs x y z roll pitch yaw (6 numbers) or a 4x4 matrix (16 numbers), got {len(values)}"
        )
    pose = torch.eye(4, dtype=F64)
    pose[:3, 3] = torch.tensor(values[:3], dtype=F64)
    pose[:3, :3] = so3.rpy_to_matrix(torch.tensor(radians(values[3:], rad), dtype=F64))
    return pose
