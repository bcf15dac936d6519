"""The ``iiwa-torch`` command."""

from __future__ import annotations

import argparse
import math
import sys

import torch


def _demo(args: argparse.Namespace) -> int:
    from . import robots

    chain = robots.iiwa14(flange=0.090)
    q = torch.zeros(7, dtype=torch.float64)
    q[3], q[4] = -math.pi / 2, math.pi / 3
    torch.set_printoptions(precision=4, sci_mode=False)
    print(chain)
    print("seed paper's validation pose, q4 = -90 deg, q5 = 60 deg, flange 0.090 m:")
    print(chain.fk(q))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="iiwa-torch", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("demo", help="an end-to-end demonstration").set_defaults(func=_demo)
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
