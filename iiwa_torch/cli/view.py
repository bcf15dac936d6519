"""The command ``view``: the browser viewer, optionally playing a ``traj --csv`` path or a policy's rollouts."""

from __future__ import annotations

import argparse
import csv
from importlib.metadata import entry_points
from pathlib import Path

import torch

from ..chain import Chain
from ..checks import require
from .arguments import F64, UsageError, chain_of, joint_angles, outside_limits
from .output import say


def run_view(args: argparse.Namespace) -> int:
    """``iiwa-torch view``: serve the viewer until Ctrl-C."""
    require("viser", "viewer")  # before any work
    from .. import viewer

    chain = chain_of(args)
    q = None if args.q is None else joint_angles(chain, args.q, args.rad, "view")
    if q is not None and outside_limits(chain, q.tolist(), args.rad):
        raise UsageError(f"--q: {outside_limits(chain, q.tolist(), args.rad)}")
    try:
        world = None if args.world is None else viewer.load_world(args.world)
    except TypeError as err:  # e.g. a JSON array where the object of obstacles belongs
        raise UsageError(f"--world {args.world}: {err}") from None
    if args.policy is not None and args.path is not None:
        raise UsageError("give at most one of --policy and --path")
    if args.policy is None and (args.goals is not None or args.seed is not None):
        raise UsageError("--goals and --seed choose --policy's rollouts: give --policy too")
    path, dt, goals = None, 0.05, None
    if args.path is not None:
        path, dt = _csv_path(chain, args.path)
    elif args.policy is not None:
        count, seed = 4 if args.goals is None else args.goals, 0 if args.seed is None else args.seed
        path, dt, goals = _policy_rollouts(chain, args.policy, count, seed)
        say(f"{count} rollouts of {args.policy}: pick one with the playback panel's path slider")
    viewer.show(
        chain, q, host=args.host, port=args.port, world=world, urdf=args.urdf, show_capsules=args.capsules,
        show_frames=args.frames, path=path, dt=dt, goals=goals,
    )  # fmt: skip
    return 0


def _csv_path(chain: Chain, file: str) -> tuple[torch.Tensor, float]:
    """The joint path ``(T, n)`` and time step (s) of a CSV written by ``iiwa-torch traj --csv``."""
    try:
        with open(file, newline="") as f:
            rows = list(csv.DictReader(f))
    except OSError as err:
        raise UsageError(f"--path {file}: {err.strerror}") from None
    columns = [f"{name}_rad" for name in chain.joint_names]
    if len(rows) < 2 or any(c not in rows[0] for c in ["t_s", *columns]):
        raise UsageError(f"--path {file}: expected 2+ rows with columns t_s, {', '.join(columns)} (traj --csv)")
    try:
        q = torch.tensor([[float(r[c]) for c in columns] for r in rows], dtype=F64)
        t = [float(r["t_s"]) for r in rows]
    except ValueError as err:
        raise UsageError(f"--path {file}: {err}") from None
    return q, (t[-1] - t[0]) / (len(t) - 1)


def _policy_rollouts(chain: Chain, policy: str, n_goals: int, seed: int):
    """``(q (n_goals, T + 1, n), dt s, goals (n_goals, 3) m)``: a policy's rollouts on held-out goals,
    by the ``iiwa_torch.playback`` entry point (``train.playback.policy_rollouts``)."""
    if n_goals < 1:
        raise UsageError(f"--goals must be a positive integer, got {n_goals}")
    found = entry_points(group="iiwa_torch.playback", name="policy")
    if not found:
        raise UsageError("--policy needs iiwa-torch's training code (train/), installed from its repository")
    try:
        robot, q, dt, goals = next(iter(found)).load()(Path(policy), n_goals, seed)
    except FileNotFoundError as err:
        raise UsageError(f"--policy: {err}") from None
    if robot != chain.name:
        raise UsageError(f"--policy {policy} drives {robot}, not {chain.name}: use --robot {robot}")
    return q, dt, goals
