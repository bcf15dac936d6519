"""Copy a finished run into ``train/policies/NAME`` with a record of how it was made.

    python -m train.ship --run runs/ppo_reach --name ppo_iiwa_reach

Copies ``model.zip``, ``vecnormalize.pkl`` (removed if the run has none), ``config.yaml``,
``train_info.json`` and ``evaluations.json`` (the learning curve) and writes ``RECORD.md``: the command, seed,
commit, training wall time, steps per second, load average and which checkpoint was shipped, followed by
the ``## Run history`` section of the RECORD.md it replaces, if any (the runs that led to it). By default
the final model is shipped; ``--best`` ships the best one of the periodic evaluation instead (the run's
``best.json``: highest success, collision-free where the env checks collisions, ties to the lower median
distance). Then evaluate it:
``python -m train.evaluate --model train/policies/NAME --goals 1000 --seed 0 --out train/policies/NAME/report``.

    python -m train.ship --run runs/panda --curve train/policies/panda.json --label "PandaReach-v3"

keeps only the learning curve of a run (with its command and machine record), for
``train.evaluate --compare``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import yaml

POLICIES = Path(__file__).resolve().parent / "policies"
FILES = ("model.zip", "vecnormalize.pkl", "config.yaml", "train_info.json", "evaluations.json")


def ship(run: Path, name: str, best: bool = False, root: Path = POLICIES) -> Path:
    """Copy the run's final files (with ``best``: its best model and normaliser instead of the final
    ones) to ``root/<name>`` and write its ``RECORD.md``."""
    from train.run_dir import RunDir

    if not (run / "train_info.json").exists():
        raise FileNotFoundError(f"{run} has no train_info.json: is it a finished train.train run?")
    info = json.loads((run / "train_info.json").read_text())
    source = {f: run / f for f in FILES}
    if best:
        record = RunDir(run).read_best()
        if record is None:
            raise FileNotFoundError(f"{run} has no best.json: it was trained before train.train kept its best model")
        for f in ("model.zip", "vecnormalize.pkl"):
            source[f] = run / record["checkpoint"] / f
        chosen = record["evaluation"]
        which = f"the best periodic evaluation's model ({record['checkpoint']}, python -m train.ship --best)"
    else:
        chosen = info["final_evaluation"] or {"steps": info["num_timesteps"]}
        which = "the final model"
    dest = Path(root) / name
    dest.mkdir(parents=True, exist_ok=True)
    for f, path in source.items():
        if path.exists():
            shutil.copy2(path, dest / f)
        else:  # e.g. no vecnormalize.pkl: a stale one from a previous policy would be loaded with the new model
            (dest / f).unlink(missing_ok=True)
    config = yaml.safe_load((run / "config.yaml").read_text())
    last = info["final_evaluation"] or {}
    load = info["machine"]["loadavg"]
    lines = [
        f"# {name}: {config['algo'].upper()} on {config['env_id']}",
        "",
        "Trained with (from the repository root):",
        "",
        f"    {config['command']}",
        "",
        f"- seed: {config['seed']}",
        f"- commit: {config['commit']}" + (" (\"+dirty\": train/ or envs/ had uncommitted changes when the run started)"
                                           if config["commit"].endswith("+dirty") else ""),
        f"- env steps: {info['num_timesteps']:,}; training wall time: {info['wall_time']:.0f} s "
        f"({info['steps_per_second']:,.0f} env steps/s)",
        f"- machine: {info['machine']['cpu']}, {info['machine']['cpu_count']} CPUs shared with other users, "
        f"load average at the end {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f} (1/5/15 min), "
        f"torch threads {info['machine']['torch_threads']}, torch {info['machine']['torch']}",
        f"- last periodic evaluation (goal-set seed 10,000, {len(json.loads((run / 'evaluations.json').read_text()))}"
        f" evaluations in evaluations.json): success at 1 cm {100 * last.get('success', float('nan')):.1f}%, "
        f"median final distance {1000 * last.get('median_distance', float('nan')):.3g} mm",
        f"- shipped checkpoint: {which}, env step {chosen['steps']:,}"
        + (f": periodic success at 1 cm {100 * chosen['success']:.1f}%, median final distance "
           f"{1000 * chosen['median_distance']:.3g} mm" if "success" in chosen else ""),
        "",
        "The held-out comparison with the IK solvers is in report/ (train.evaluate, 1,000 goals, seed 0).",
        "",
    ]
    (dest / "RECORD.md").write_text("\n".join(lines) + _run_history(dest / "RECORD.md"))
    return dest


HISTORY = "## Run history"  # the heading under which a policy's RECORD.md keeps its earlier runs


def _run_history(record: Path) -> str:
    """The ``## Run history`` section of an existing RECORD.md (to the end of the file), or ``""``:
    a policy shipped again keeps the runs that led to it."""
    text = record.read_text() if record.exists() else ""
    start = text.find(HISTORY)
    return "\n" + text[start:] if start >= 0 else ""


def export_curve(run: Path, out: Path, label: str) -> Path:
    """Write ``{"label", "command", "train_info", "evaluations"}`` of a finished run to ``out``."""
    if not (run / "train_info.json").exists():
        raise FileNotFoundError(f"{run} has no train_info.json: is it a finished train.train run?")
    config = yaml.safe_load((run / "config.yaml").read_text())
    blob = {
        "label": label,
        "command": config["command"],
        "commit": config["commit"],
        "train_info": json.loads((run / "train_info.json").read_text()),
        "evaluations": json.loads((run / "evaluations.json").read_text()),
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(blob, indent=1))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m train.ship", description=__doc__.split("\n\n")[0])
    p.add_argument("--run", required=True, type=Path, help="finished run directory")
    p.add_argument("--name", help="folder name under train/policies/")
    p.add_argument("--best", action="store_true",
                   help="ship the best model of the periodic evaluation, not the final one (with --name)")
    p.add_argument("--curve", type=Path, help="write only the learning curve to this JSON file")
    p.add_argument("--label", help="label of the curve (with --curve)")
    args = p.parse_args(argv)
    if (args.name is None) == (args.curve is None):
        p.error("give either --name (ship the policy) or --curve FILE --label TEXT (keep the learning curve)")
    if args.best and args.name is None:
        p.error("--best picks the model to ship: it goes with --name, not --curve")
    try:
        if args.name:
            print(ship(args.run, args.name, best=args.best))
        else:
            print(export_curve(args.run, args.curve, args.label or args.run.name))
    except FileNotFoundError as err:
        p.error(str(err))
    return 0


if __name__ == "__main__":
    sys.exit(main())
