"""The ``iiwa-torch`` command's options and :func:`run`, which parses and runs a command (bad input: exit 2)."""

from __future__ import annotations

import argparse
import contextlib
import re

from .. import __version__, robots
from ..checks import MissingExtra
from .arguments import UsageError
from .kinematics import run_fk, run_ik, run_robots
from .motion import run_demo, run_traj
from .output import Elapsed
from .view import run_view
from .workspace import run_workspace

_DESCRIPTION = """\
Forward and inverse kinematics, trajectories, robot tables and a demo.
Angles are degrees unless --rad is given; lengths are metres. --json prints one JSON
object for scripts (always metres and radians).

examples:
  iiwa-torch fk 0 0 0 -90 60 0 0 --flange 0.090
  iiwa-torch ik --pose 0.49 0 0.78 90 30 90 --flange 0.090
  iiwa-torch ik --pose 0.5 0.1 0.4                 (position only: 3 numbers)
  iiwa-torch traj --from-q 0 30 0 -60 0 60 0 --to-pose 0.5 0.2 0.6 180 0 180 --gif line.gif
  iiwa-torch robots iiwa14
  iiwa-torch robots --urdf panda.urdf --end-link panda_hand
  iiwa-torch demo
  iiwa-torch view --world '{"spheres": [[0.5, 0, 0.5, 0.1]]}' --capsules
"""


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser (its subparsers too) reading ``-5.3e-17``, ``-9e1`` and ``-90.`` as numbers: before
    Python 3.13 argparse took them for options, so ``ik --pose`` refused the 16 numbers ``fk --json`` prints."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$")


def _seed(text: str) -> int:
    """``--seed``: an integer torch's generators take, 0 <= seed < 2**63."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer, got {text!r}") from None
    if not 0 <= value < 2**63:
        raise argparse.ArgumentTypeError(f"must be in [0, 2**63), got {value}")
    return value


def _common_options() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--robot", choices=list(robots.PRESETS), help="robot preset (default iiwa14)")
    common.add_argument("--urdf", metavar="FILE", help="any serial arm from its URDF file instead of a preset")
    common.add_argument(
        "--end-link", metavar="LINK", help="with --urdf: the end effector's link (default: the only leaf)"
    )
    common.add_argument(
        "--flange",
        type=float,
        help="iiwa wrist-to-flange length in m (default 0.126, the datasheet; Pereira et al.: 0.090)",
    )
    common.add_argument("--rad", action="store_true", help="angles in radians (default: degrees)")
    common.add_argument("--json", action="store_true", help="print JSON (metres, radians) instead of tables")
    return common


def _add_fk(sub, common: argparse.ArgumentParser) -> None:
    p = sub.add_parser("fk", parents=[common], help="joint angles -> end-effector pose")
    p.add_argument("q", nargs="+", type=float, help="joint values (deg unless --rad; m for a prismatic joint)")
    p.add_argument("--plot", metavar="PNG", help="also draw the arm to this PNG file")
    p.set_defaults(func=run_fk, parser=p)


def _add_ik(sub, common: argparse.ArgumentParser) -> None:
    p = sub.add_parser("ik", parents=[common], help="pose -> joint angles (all analytic branches, or gradient)")
    p.add_argument(
        "--pose",
        nargs="+",
        type=float,
        required=True,
        metavar="V",
        help="x y z roll pitch yaw, 16 numbers of a row-major 4x4, or x y z alone (position only)",
    )
    p.add_argument(
        "--method",
        choices=["analytic", "gradient"],
        help="closed form (all branches) or gradient IK (default: analytic; gradient for x y z)",
    )
    p.add_argument("--psi", type=float, help="iiwa arm angle for the analytic solver (default 0; where no branch "
                   "is valid at 0, the arm angle of a gradient IK solution)")
    p.add_argument("--seed", type=_seed, default=0, help="random seed of the gradient solver")
    p.set_defaults(func=run_ik, parser=p)


def _add_traj(sub, common: argparse.ArgumentParser) -> None:
    p = sub.add_parser("traj", parents=[common], help="trajectory between configurations or poses -> CSV, animation")
    p.add_argument("--from-q", nargs="+", type=float, metavar="Q",
                   help="start joint values (deg unless --rad; m for a prismatic joint)")
    p.add_argument("--from-pose", nargs="+", type=float, metavar="V", help="start pose: x y z roll pitch yaw, or a 4x4")
    p.add_argument("--to-q", nargs="+", type=float, metavar="Q", help="goal joint angles (a joint-space quintic)")
    p.add_argument("--to-pose", nargs="+", type=float, metavar="V", help="goal pose (a straight line tracked by IK)")
    p.add_argument("--steps", type=int, default=50, help="samples along the trajectory (default 50)")
    p.add_argument("--duration", type=float, help="seconds (default: the shortest within the speed limits)")
    p.add_argument(
        "--method",
        choices=["analytic", "gradient"],
        help="IK for Cartesian lines (default: analytic for the presets, gradient for a --urdf arm)",
    )
    p.add_argument("--csv", metavar="FILE", help="write t, joint angles (rad) and end-effector xyz")
    p.add_argument("--gif", metavar="FILE", help="write an animation (.gif, or .mp4 with ffmpeg)")
    p.add_argument("--fps", type=int, help="animation frame rate (default: real time)")
    p.add_argument("--size", type=int, default=360, help="animation size in pixels")
    p.set_defaults(func=run_traj, parser=p)


def _add_robots(sub, common: argparse.ArgumentParser) -> None:
    p = sub.add_parser("robots", help="list presets, print one's DH table, or a URDF arm's joints")
    p.add_argument("name", nargs="?", help="a preset name")
    p.add_argument("--urdf", metavar="FILE", help="print the joints of this URDF file's arm instead")
    p.add_argument("--end-link", metavar="LINK", help="with --urdf: the end effector's link (default: the only leaf)")
    p.add_argument("--json", action="store_true", help="print JSON (metres, radians) instead of tables")
    p.set_defaults(func=run_robots, parser=p, robot=None, flange=None)  # chain_of reads them


def _add_demo(sub, common: argparse.ArgumentParser) -> None:
    p = sub.add_parser("demo", help="FK at the validation pose, batched FK/IK timing, a tracked line")
    p.add_argument("--out", default="reports/demo", help="directory for the animation (default reports/demo)")
    p.add_argument("--batch", type=int, default=10_000, help="configurations in the timing (default 10000)")
    p.add_argument("--no-gif", action="store_true", help="skip writing the animation")
    p.add_argument("--json", action="store_true", help="print JSON (metres, radians, ms) instead of tables")
    p.set_defaults(func=run_demo, parser=p)


def _add_view(sub, common: argparse.ArgumentParser) -> None:
    p = sub.add_parser("view", parents=[common], help="browser viewer: joint sliders, pose read-out, IK target")
    p.add_argument("--q", nargs="+", type=float, metavar="Q",
                   help="first configuration (deg unless --rad; m for a prismatic joint)")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=int, default=8080, help="port (default 8080; 0: any free one; busy: the next free)")
    p.add_argument(
        "--world", metavar="JSON",
        help='obstacles: a JSON file or text, e.g. \'{"spheres": [[0.5, 0, 0.5, 0.1]]}\' (keys: docs/viewer.md)',
    )  # fmt: skip
    p.add_argument("--capsules", action="store_true", help="draw the robot's collision capsules")
    p.add_argument("--frames", action="store_true", help="draw every link frame")
    p.add_argument("--path", metavar="CSV", help="play back a joint path written by `iiwa-torch traj --csv`")
    p.add_argument("--policy", metavar="DIR", help="play back a policy's rollouts, e.g. train/policies/ppo_iiwa_reach")
    p.add_argument("--goals", type=int, help="--policy: number of held-out goals (default 4)")
    p.add_argument("--seed", type=_seed, help="--policy: goal-set seed (default 0)")
    p.set_defaults(func=run_view, parser=p)


def _add_workspace(sub, common: argparse.ArgumentParser) -> None:
    p = sub.add_parser("workspace", parents=[common], help="reachable set: side-view envelope, manipulability map")
    p.add_argument("--plot", metavar="PNG", help="write the side view (r-z plane) to this PNG")
    p.add_argument("--manipulability", metavar="PNG", help="also write a manipulability map to this PNG")
    p.add_argument(
        "--point",
        choices=["wrist", "flange"],
        help="the point whose reach is drawn (default: the wrist centre KUKA's datasheet draws, for the presets; "
        "the flange for a --urdf arm)",
    )
    p.add_argument("--h", type=float, default=0.005, help="grid cell size in m (default 0.005)")
    p.add_argument("--samples", type=int, default=1 << 23, help="sampled configurations (default 8388608)")
    p.add_argument("--seed", type=_seed, default=0, help="random seed of the sampling")
    p.set_defaults(func=run_workspace, parser=p)


def build_parser() -> argparse.ArgumentParser:
    common = _common_options()
    parser = _Parser(
        prog="iiwa-torch", description=_DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in (_add_fk, _add_ik, _add_traj, _add_robots, _add_demo, _add_view, _add_workspace):
        add(sub, common)
    return parser


def run(argv: list[str] | None = None) -> int:
    """Parse ``argv`` (default ``sys.argv[1:]``) and run its command; its exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    # `view` serves until stopped: no running time over its own messages
    running = contextlib.nullcontext() if args.func is run_view else Elapsed(args.parser.prog.split()[-1])
    try:
        with running:
            return args.func(args)
    except (UsageError, ValueError) as err:  # the library's ValueErrors name the bad input too
        args.parser.error(str(err))  # the subcommand's usage and the message; exit status 2
    except MissingExtra as err:  # one line naming the extra to install
        args.parser.exit(2, f"{args.parser.prog}: error: {err}\n")
