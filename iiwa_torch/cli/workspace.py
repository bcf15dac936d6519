"""The command ``workspace``: the reachable set's side view and manipulability map, and its extent."""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from ..dh import DHChain
from .arguments import UsageError, chain_of, drawing, writable
from .output import print_json, say


def run_workspace(args: argparse.Namespace) -> int:
    """``iiwa-torch workspace``: the pictures asked for, and the extent as JSON."""
    from .. import workspace

    if args.plot is None and not args.json:
        raise UsageError("give --plot PNG (the side view), --json (the extent), or both")
    if args.plot is not None:
        drawing()  # matplotlib is needed: say which extra if it is missing
    chain = chain_of(args)
    if args.manipulability and args.plot is None:
        raise UsageError("--manipulability is drawn with the side view: give --plot too")
    for option, file in (("--plot", args.plot), ("--manipulability", args.manipulability)):
        if file is not None and Path(file).suffix.lower() != ".png":  # matplotlib would add .png to the name
            raise UsageError(f"{option} must name a .png file, got {file}")
        if file is not None:
            writable(file, option)
    if not (args.samples > 0 and args.h > 0):  # NaN too
        raise UsageError(f"--samples and --h must be positive, got {args.samples} and {args.h}")
    has_wrist = isinstance(chain, DHChain) and chain.n_joints >= 6  # the presets' spherical wrists
    if args.point == "wrist" and not has_wrist:
        raise UsageError(f"--point wrist is the wrist centre of a 6- or 7-joint DH preset; use --point flange "
                         f"for {chain.name}")
    if args.point is None:
        args.point = "wrist" if has_wrist else "flange"
    wrist = args.point == "wrist"
    point = workspace.frame_point(chain, 5) if wrist else None
    if args.plot is not None:
        workspace.plot_workspace(
            chain,
            args.plot,
            manipulability_path=args.manipulability,
            point=point,
            point_label="wrist centre" if wrist else "flange",
            h=args.h,
            n_samples=args.samples,
            datasheet=workspace.DATASHEET.get(chain.name) if wrist else None,
            seed=args.seed,
        )
    if args.json:
        reach = workspace.extent(chain, args.samples, point=point, generator=torch.Generator().manual_seed(args.seed))
        files = [f for f in (args.plot, args.manipulability) if f]
        print_json({"robot": chain.name, "point": args.point, "n_samples": args.samples, "z_max_m": reach.z_max,
                    "z_min_m": reach.z_min, "r_max_m": reach.r_max, "files": files})  # fmt: skip
        return 0
    say(f"side view written to {args.plot}")
    if args.manipulability:
        say(f"manipulability map written to {args.manipulability}")
    return 0
