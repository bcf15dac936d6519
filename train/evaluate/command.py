"""The ``python -m train.evaluate`` command: load a policy, run every method on held-out goals, write the
report (``report.json``, ``report.md``, ``final_q.npz``, the plots)."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from .methods import controller_alone, ik_world, run_ik, run_policy
from .metrics import FLOAT_TYPES, FLOOR_SPACINGS, TOLERANCES, number_spacing
from .plots import make_plots
from .report import design_note, verdict, write_markdown

__all__ = ["load_policy", "read_compare", "evaluate", "run_methods", "float_floors", "write_report", "main"]

DESCRIPTION = "Compare a trained policy with the analytic and the gradient IK on the same held-out goals."


# ---------------------------------------------------------------------------- loading
def load_policy(model_dir: Path):
    """``(model, vec_normalize or None, config dict)`` from a run or shipped-policy folder (a run stopped before
    its end, without ``model.zip``: its newest checkpoint, said on stderr); ValueError if the config is malformed
    or the model is not one of its algo for its env, FileNotFoundError if a file the config needs is missing
    (``vecnormalize.pkl`` with ``normalize: true``)."""
    import pickle

    from train.run_dir import RunDir, check_model
    from train.vec_env import make_env

    run = RunDir(model_dir)
    folder = run.path
    if not (folder / "model.zip").exists() and run.config_path.exists() and run.latest_checkpoint() is not None:
        folder = run.latest_checkpoint()
        print(f"{run.path} has no model.zip (the run did not finish): evaluating its newest checkpoint, "
              f"{folder.relative_to(run.path)}", file=sys.stderr)
    if not (folder / "model.zip").exists() or not run.config_path.exists():
        raise FileNotFoundError(f"{run.path} must hold model.zip and config.yaml (a train.train run or a "
                                f"train/policies/ folder), or config.yaml and checkpoints/ (a stopped run)")
    config = run.read_config()
    env = make_env(config["env_id"], 1, 0, config["hyperparams"].get("env_kwargs"))
    check_model(config["algo"], folder / "model.zip", env.observation_space, env.action_space)
    from stable_baselines3 import PPO, SAC

    # with its env: SB3 cannot rebuild a HER replay buffer without one
    model = {"ppo": PPO, "sac": SAC}[config["algo"]].load(folder / "model.zip", env=env, device="cpu")
    vec_normalize = None
    if config["hyperparams"].get("normalize", False) and not (folder / "vecnormalize.pkl").exists():
        raise FileNotFoundError(f"{folder / 'vecnormalize.pkl'} not found: the config says normalize: true, and "
                                f"the policy needs its observation statistics")
    if (folder / "vecnormalize.pkl").exists():
        try:
            with open(folder / "vecnormalize.pkl", "rb") as f:
                vec_normalize = pickle.load(f)  # SB3's own format (VecNormalize.save pickles the wrapper)
        except (pickle.UnpicklingError, EOFError, AttributeError, ImportError) as err:
            raise ValueError(f"{folder / 'vecnormalize.pkl'} is unreadable ({type(err).__name__}: {err}); "
                             f"expected the VecNormalize file train.train writes") from None
        vec_normalize.training = False
    return model, vec_normalize, config


COMPARE_KEYS = ("steps", "wall_time", "success")  # of each evaluation a learning curve draws


def read_compare(paths: list[Path]) -> dict[str, list[dict]]:
    """Label -> evaluations of each ``--compare`` file: ``{"label", "evaluations"}`` or a run's
    ``evaluations.json`` list (labelled by its folder); ValueError names a file that is neither."""
    compare = {}
    for path in map(Path, paths):
        try:
            blob = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
            raise ValueError(f"--compare {path}: not a readable JSON file ({err})") from None
        label, evaluations = (blob.get("label"), blob.get("evaluations")) if isinstance(blob, dict) \
            else (path.parent.name, blob)
        entry_ok = lambda e: isinstance(e, dict) and all(isinstance(e.get(k), (int, float)) for k in COMPARE_KEYS)
        if not isinstance(label, str) or not isinstance(evaluations, list) or not evaluations \
                or not all(map(entry_ok, evaluations)):
            raise ValueError(f"--compare {path}: expected a run's evaluations.json (a list of entries with steps, "
                             f"wall_time and success) or {{\"label\": ..., \"evaluations\": [...]}}")
        compare[label] = evaluations
    return compare


def evaluate(model_dir: Path, n_goals: int, seed: int, out: Path, compare: dict[str, list[dict]],
             env_overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """The report of the policy in ``model_dir`` on ``n_goals`` held-out goals, written to ``out``, with the
    learning curves of ``compare`` (``read_compare``) beside its own."""
    import torch

    import envs
    from iiwa_torch.runtime import machine_info
    from train.rollout import make_goal_set
    from train.run_dir import RunDir

    torch.set_num_threads(1)
    model, vec_normalize, config = load_policy(model_dir)
    env_id = config["env_id"]
    trained_kwargs = config["hyperparams"].get("env_kwargs") or {}
    env_kwargs = {**trained_kwargs, **(env_overrides or {})}
    task = envs.make_task(env_id, **env_kwargs)
    goals = make_goal_set(env_id, n_goals, seed, env_kwargs)
    below_floor = int((goals.pose[:, 2, 3] < 0).sum())  # the preset's default floor is z = 0
    metrics, data = run_methods(goals, task, model, vec_normalize)
    spacing = float_floors(goals, metrics, data)
    report = {
        "env_id": env_id,
        "algo": config["algo"],
        "model": str(model_dir),
        "goals": n_goals,
        "seed": seed,
        "env_kwargs": env_kwargs,
        "episode_steps": task.max_episode_steps,
        "dt": task.dt,
        "tolerances_m": TOLERANCES,
        "methods": metrics,
        "goals_below_floor": below_floor,
        "number_spacing_m": spacing,
        "verdict": verdict(metrics, below_floor, spacing)
        + design_note(config, envs.make_task(env_id, **trained_kwargs)),
        "training": json.loads((model_dir / "train_info.json").read_text())
        if (model_dir / "train_info.json").exists() else None,
        "machine": machine_info(),
    }
    write_report(out, report, data, RunDir(model_dir).read_evaluations(), compare, goals)
    return report


def run_methods(goals, task, model, vec_normalize) -> tuple[dict[str, dict], dict[str, dict[str, np.ndarray]]]:
    """Every method on ``goals`` (a :class:`train.rollout.GoalSet` of ``task``'s env): ``(metrics, data)`` by
    method name, the IK solvers' rows an ``{"error": ...}`` where they are unavailable, with the floor
    contacts of the policy's rollout against each solver's answer."""
    chain = task.robot
    world = ik_world(task, goals)
    metrics, data = {}, {}
    metrics["policy"], data["policy"] = run_policy(goals, model, vec_normalize, chain)
    alone = controller_alone(model)
    if alone is not None:
        metrics["controller"], data["controller"] = run_policy(goals, alone, vec_normalize, chain)
    for name in ("analytic_ik", "gradient_ik"):
        try:
            metrics[name], data[name] = run_ik(name, goals, chain, data["policy"]["home"], task.dt, world)
        except (ImportError, ValueError) as err:  # not installed, or no closed form for this arm: say so
            metrics[name] = {"error": f"unavailable: {err}"}
            continue
        policy_hit, ik_hit = data["policy"]["floor_hit"], data[name]["floor_hit"]
        metrics[name]["floor_policy_only"] = int((policy_hit & ~ik_hit).sum())
        metrics[name]["floor_ik_only"] = int((ik_hit & ~policy_hit).sum())
    return metrics, data


def float_floors(goals, metrics: dict[str, dict], data: dict[str, dict[str, np.ndarray]]) -> dict[str, float]:
    """The median number spacing (m) at the goals per float format; adds each method's share of goals left
    beyond float32's floor (``FLOOR_SPACINGS`` spacings) to its ``metrics``."""
    spacing = {k: number_spacing(goals.pose[:, :3, 3].numpy(), t) for k, t in FLOAT_TYPES.items()}
    for name, d in data.items():
        metrics[name]["beyond_float32_floor"] = float(np.mean(d["final_error"] > FLOOR_SPACINGS * spacing["float32"]))
    return {k: float(np.median(v)) for k, v in spacing.items()}


def write_report(out: Path, report: dict[str, Any], data: dict[str, dict[str, np.ndarray]], evaluations: list[dict],
                 compare: dict[str, list[dict]], goals) -> None:
    """Write ``report`` into ``out`` (its plots, ``final_q.npz``, ``report.json``, ``report.md``) and print
    its table and verdict."""
    out.mkdir(parents=True, exist_ok=True)
    report["plots"] = make_plots(out, data, report, evaluations, compare, goals)
    np.savez_compressed(out / "final_q.npz", **{name: d["q"] for name, d in data.items()})
    (out / "report.json").write_text(json.dumps(report, indent=1))
    table = write_markdown(report, out / "report.md")
    print(table)
    print()
    for line in report["verdict"]:
        print("- " + line)
    print(f"\nreport: {out / 'report.md'}, {out / 'report.json'}; plots: "
          + ", ".join(str(out / p) for p in report["plots"]))


def main(argv: list[str] | None = None) -> int:
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    p = argparse.ArgumentParser(prog="python -m train.evaluate", description=DESCRIPTION)
    p.add_argument("--model", required=True, type=Path, help="run or policy folder (model.zip + config.yaml)")
    p.add_argument("--goals", type=int, default=1000, help="held-out goals (default 1000)")
    p.add_argument("--seed", type=int, default=0, help="seed of the goal set (default 0)")
    p.add_argument("--out", required=True, type=Path, help="report folder")
    p.add_argument("--compare", nargs="*", type=Path, default=[],
                   help="evaluations JSON of other runs to draw on the learning curve (e.g. panda-gym)")
    p.add_argument("--env-kwargs", nargs="*", default=[], metavar="KEY=VALUE",
                   help="env options over the policy config's (YAML values), e.g. collision=terminate")
    args = p.parse_args(argv)
    import yaml

    from train.run_dir import check_folder

    overrides = {}
    for item in args.env_kwargs:
        key, sep, value = item.partition("=")
        if not sep or not key:
            p.error(f"--env-kwargs: expected KEY=VALUE, got {item!r}")
        overrides[key] = yaml.safe_load(value)
    if args.goals < 1:
        p.error(f"--goals must be >= 1, got {args.goals}")
    for path in args.compare:
        if not path.is_file():
            p.error(f"--compare: {path} not found; expected an evaluations JSON (a run's evaluations.json)")
    try:
        check_folder(args.out)
        evaluate(args.model, args.goals, args.seed, args.out, read_compare(args.compare), overrides)
    except (FileNotFoundError, ValueError, TypeError) as err:
        p.error(str(err))
    return 0
