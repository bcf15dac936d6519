"""Hyper-parameter search for ``train.train`` with Optuna (the rl-baselines3-zoo convention).

    python -m train.tune --algo ppo --env IiwaReach-v0 --trials 50 --timesteps 1e6 --out runs/tune

Each trial samples hyper-parameters (``SAMPLERS``; the search spaces are listed in
docs/training.md) over the env's block of ``train/config/<algo>.yaml`` and trains them as a
``train.train`` run in ``<out>/<study>/trial_<N>/``. Its periodic evaluation reports ``--metric``
to the trial; Optuna's median pruner stops a trial that falls below the median of earlier ones at
the same env step. After every trial ``<out>/<study>/best.yaml`` holds the best trial's run config,
which ``python -m train.train --config <out>/<study>/best.yaml --out DIR`` trains again.

The study lives in ``--storage`` (default ``sqlite:///<out>/study.db``) and is loaded if it
exists, so the same command resumes an interrupted study; run on several machines against one
shared database (e.g. ``postgresql://user@host/db``) it is a distributed sweep. ``--trials`` is
the study's total: completed, pruned and running trials of every worker count towards it.
"""

from __future__ import annotations

import argparse
import functools
import logging
import os
import re
import shlex
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import yaml

from iiwa_torch.checks import MissingExtra, require
from train.run_dir import ALGOS, RunDir, RunLocked, atomic_write_text

METRICS = {"success": "maximize", "median_distance": "minimize", "p95_distance": "minimize"}
HEARTBEAT = 60  # s between a running trial's heartbeats in the storage (default of --heartbeat)
GRACE = 180  # s without a heartbeat after which another worker fails a killed process's trial (--grace)
RETRIES = 2  # times a trial failed that way is run again with its parameters
_CONNECT_ATTEMPTS = 5  # tries to open a storage whose tables another worker is creating at the same moment
_PPO_NETS = {"small": [64, 64], "medium": [128, 128], "large": [256, 256]}
_SAC_NETS = {"small": [64, 64], "medium": [256, 256]}


# ---------------------------------------------------------------------------- search spaces
def sample_ppo(trial, hp: dict[str, Any]) -> dict[str, Any]:
    """PPO hyper-parameters drawn by ``trial`` (replacing those of the YAML block ``hp``).

    ``batch_size`` is a rollout (``n_steps * n_envs`` samples) split in ``n_minibatches``;
    ``gamma``, ``gae_lambda`` are drawn as ``1 - value`` on a log scale, as in rl-zoo.
    """
    n_steps = trial.suggest_categorical("n_steps", [16, 32, 64])
    n_minibatches = trial.suggest_categorical("n_minibatches", [1, 2, 4, 8])
    learning_rate = trial.suggest_float("learning_rate", 1e-4, 3e-3, log=True)
    linear = trial.suggest_categorical("lr_schedule", ["linear", "constant"]) == "linear"
    net = trial.suggest_categorical("net_arch", list(_PPO_NETS))
    return {
        "n_steps": n_steps,
        "batch_size": max(n_steps * hp["n_envs"] // n_minibatches, 2),
        "n_epochs": trial.suggest_categorical("n_epochs", [3, 5, 10]),
        "gamma": 1.0 - trial.suggest_float("one_minus_gamma", 0.005, 0.1, log=True),
        "gae_lambda": 1.0 - trial.suggest_float("one_minus_gae_lambda", 0.01, 0.2, log=True),
        "learning_rate": f"lin_{learning_rate:.4g}" if linear else learning_rate,
        "clip_range": trial.suggest_categorical("clip_range", [0.1, 0.2, 0.3]),
        "ent_coef": trial.suggest_float("ent_coef", 1e-8, 1e-2, log=True),
        "max_grad_norm": trial.suggest_float("max_grad_norm", 0.3, 2.0),
        "policy_kwargs": {**(hp.get("policy_kwargs") or {}), "net_arch": _PPO_NETS[net],
                          "log_std_init": trial.suggest_float("log_std_init", -3.0, 0.0)},
    }


def sample_sac(trial, hp: dict[str, Any]) -> dict[str, Any]:
    """SAC hyper-parameters drawn by ``trial`` (replacing those of the YAML block ``hp``); with HER in
    ``hp``, also its ``n_sampled_goal``."""
    net = trial.suggest_categorical("net_arch", list(_SAC_NETS))
    out = {
        "gamma": trial.suggest_categorical("gamma", [0.9, 0.95, 0.98, 0.99]),
        "learning_rate": trial.suggest_float("learning_rate", 1e-4, 3e-3, log=True),
        "batch_size": trial.suggest_categorical("batch_size", [128, 256, 512]),
        "tau": trial.suggest_categorical("tau", [0.005, 0.01, 0.02, 0.05]),
        "gradient_steps": trial.suggest_categorical("gradient_steps", [1, 2, 4]),
        "policy_kwargs": {**(hp.get("policy_kwargs") or {}), "net_arch": _SAC_NETS[net]},
    }
    if hp.get("her") is not None:
        out["her"] = {**hp["her"], "n_sampled_goal": trial.suggest_categorical("n_sampled_goal", [2, 4, 8])}
    return out


SAMPLERS = {"ppo": sample_ppo, "sac": sample_sac}


# ---------------------------------------------------------------------------- trials
def _trial_callback_class():
    """``TrialEvalAndCheckpoint``, defined on first use: its base class imports stable-baselines3."""
    from train.callbacks import EvalAndCheckpoint

    class TrialEvalAndCheckpoint(EvalAndCheckpoint):
        """``EvalAndCheckpoint`` that reports ``metric`` of each evaluation to an Optuna ``trial`` (at its env
        step) and stops the training when the trial's pruner says so (``pruned``)."""

        def __init__(self, trial, metric: str, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.trial, self.metric, self.pruned = trial, metric, False

        def evaluate(self) -> dict[str, Any]:
            entry = super().evaluate()
            self.trial.report(entry[self.metric], entry["steps"])
            self.pruned = self.trial.should_prune()
            return entry

        def _on_step(self) -> bool:
            return super()._on_step() and not self.pruned

    return TrialEvalAndCheckpoint


def study_folder(out: Path, study_name: str) -> Path:
    """``<out>/<study_name>``: the trials' run directories and ``best.yaml``."""
    return Path(out) / study_name


def objective(trial, sweep: dict[str, Any], out: Path, command: str, verbose: int = 0) -> float:
    """Train one trial's hyper-parameters in ``<out>/<study>/trial_<N>``; the ``metric`` of its last evaluation.

    ``sweep``: algo, env_id, seed, metric and the ``overrides`` of the YAML block (n_timesteps, n_envs and
    ``--hyperparams``) in every trial.
    The trial's run config goes to its user attribute ``config`` (so any worker can write the best one).
    Raises ``optuna.TrialPruned`` when pruned, or when the training fails with a ValueError (NaN
    parameters from extreme hyper-parameters), whose message goes to the user attribute ``error``.
    On Ctrl-C or SIGTERM the run directory goes to the user attribute ``interrupted``; a trial that
    ``tune`` enqueued with the user attribute ``resumes`` (``{"trial", "run"}``, same parameters)
    continues that run from its newest checkpoint, its evaluations so far reported again.
    """
    optuna = require("optuna", "rl")

    from train.train import load_hyperparams, make_config, new_model, run_training

    algo, env_id = sweep["algo"], sweep["env_id"]
    base = load_hyperparams(algo, env_id, sweep["overrides"])
    config = make_config(algo, env_id, sweep["seed"], {**base, **SAMPLERS[algo](trial, base)},
                         f"{command}  # trial {trial.number}")
    resumes = trial.user_attrs.get("resumes")
    resuming = resumes is not None and RunDir(resumes["run"]).config_path.exists()
    own = study_folder(out, trial.study.study_name) / f"trial_{trial.number:04d}"
    run = RunDir(resumes["run"] if resuming else own)
    if resuming:
        config = run.read_config()
        for entry in run.read_evaluations():
            trial.report(entry[sweep["metric"]], entry["steps"])
    trial.set_user_attr("config", config)
    model = None if resuming else new_model(run, config, verbose)  # None: run_training resumes the run
    callback = functools.partial(_trial_callback_class(), trial, sweep["metric"])
    try:
        cb = run_training(run, config, model, verbose=verbose, callback=callback)
    except KeyboardInterrupt:
        trial.set_user_attr("interrupted", str(run.path))
        raise
    except ValueError as err:
        trial.set_user_attr("error", str(err))
        raise optuna.TrialPruned(f"training failed: {err}") from None
    if cb.pruned:
        raise optuna.TrialPruned(f"at step {cb.num_timesteps}")
    return cb.clock.evaluations[-1][sweep["metric"]]


class _NoTraceback(logging.Filter):
    """Keep Optuna's line on a failed trial, without the traceback it adds: ``main`` says what went wrong
    in one line (a bad hyper-parameter, an interrupt)."""

    def filter(self, record: logging.LogRecord) -> bool:
        record.exc_info = record.exc_text = None
        return True


NO_TRACEBACK = _NoTraceback()


# ---------------------------------------------------------------------------- storage and study
def hide_password(url: str) -> str:
    """``url`` with the password of ``user:password@host`` replaced by ``***``."""
    return re.sub(r"(//[^/:@]*:)[^/@]*@", r"\1***@", url)


def open_storage(url: str, heartbeat: int = HEARTBEAT, grace: int = GRACE):
    """Optuna's RDB storage at ``url`` (SQLAlchemy form); ValueError if it cannot be opened.

    Running trials record a heartbeat every ``heartbeat`` s; one without a heartbeat for ``grace`` s (its
    process was killed) is failed by the next worker that starts a trial and queued again, ``RETRIES`` times.
    """
    import optuna
    from sqlalchemy.exc import IntegrityError, ProgrammingError

    def connect():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            retry = optuna.storages.RetryHeartbeatStaleTrialCallback(max_retry=RETRIES)
            return optuna.storages.RDBStorage(url, heartbeat_interval=heartbeat, grace_period=grace,
                                              heartbeat_stale_trial_callback=retry)

    shown = hide_password(url)
    try:
        for attempt in range(1, _CONNECT_ATTEMPTS + 1):
            try:
                return connect()
            except (IntegrityError, ProgrammingError):  # another worker is creating Optuna's tables right now
                if attempt == _CONNECT_ATTEMPTS:
                    raise
                time.sleep(0.25 * attempt)  # then they exist (seen: a second attempt at once can race again)
    except ImportError as err:
        cause = err.__cause__ or err
        raise ValueError(f"storage {shown}: its database driver is not installed ({cause}): pip install it") from None
    except Exception as err:  # SQLAlchemy's parse, dialect and connection errors
        first = str(err).strip().splitlines()[0] if str(err).strip() else ""
        raise ValueError(f"storage {shown} cannot be opened ({type(err).__name__}: {hide_password(first)}); "
                         f"expected an SQLAlchemy URL such as sqlite:///study.db or "
                         f"postgresql://user:password@host/db") from None


def load_study(storage, study_name: str, sweep: dict[str, Any], shown: str):
    """The study ``study_name`` in ``storage``, created if missing; ValueError if it exists for another sweep."""
    optuna = require("optuna", "rl")

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        sampler = optuna.samplers.TPESampler(n_startup_trials=5, multivariate=True)
    pruner = optuna.pruners.MedianPruner(n_startup_trials=3, n_warmup_steps=sweep["overrides"]["n_timesteps"] // 3)
    study = optuna.create_study(storage=storage, study_name=study_name, sampler=sampler, pruner=pruner,
                                direction=METRICS[sweep["metric"]], load_if_exists=True)
    found = study.user_attrs.get("sweep")
    if found is not None and found != sweep and not study.get_trials(deepcopy=False, states=counted_states()):
        print(f"study {study_name!r}: none of its trials of the sweep {found} completed; it now runs {sweep}",
              flush=True)  # e.g. the first command had a hyper-parameter that every trial failed on
        found = None
    if found is None:
        study.set_user_attr("sweep", sweep)
    elif found != sweep:
        raise ValueError(f"study {study_name!r} in {shown} is a sweep of {found}, not {sweep}: "
                         f"pick another --study-name")
    return study


def resume_interrupted(study) -> None:
    """Enqueue, ahead of new trials, the parameters of each trial interrupted by Ctrl-C or SIGTERM
    (user attribute ``interrupted``) that no trial resumes yet; ``objective`` continues its run."""
    taken = {t.user_attrs["resumes"]["trial"] for t in study.get_trials(deepcopy=False) if "resumes" in t.user_attrs}
    for t in study.get_trials(deepcopy=False):
        if "interrupted" in t.user_attrs and t.number not in taken:
            resumes = {"trial": t.number, "run": t.user_attrs["interrupted"]}
            study.enqueue_trial(t.params, user_attrs={"resumes": resumes})
            print(f"trial {t.number} was interrupted: the next trial resumes it (its parameters, and its run "
                  f"{t.user_attrs['interrupted']} from the newest checkpoint if it has one)", flush=True)


def counted_states() -> tuple:
    """The trial states that count towards ``--trials``: completed, pruned and running."""
    TrialState = require("optuna.trial", "rl").TrialState
    return TrialState.COMPLETE, TrialState.PRUNED, TrialState.RUNNING


def counted_trials(study) -> int:
    """How many trials of ``study`` count towards ``--trials`` (``counted_states``), once the running trials
    whose heartbeat is stale (of killed workers) are failed, and so queued again."""
    import optuna

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        optuna.storages.fail_stale_trials(study)
    return len(study.get_trials(deepcopy=False, states=counted_states()))


def stop_when_counted(study, trials: int) -> None:
    """``study.optimize`` callback: stop once ``trials`` are counted (``counted_trials``)."""
    if counted_trials(study) >= trials:
        study.stop()


def write_best(study, out: Path, storage: str) -> Path | None:
    """``<out>/<study>/best.yaml``: the best completed trial's run config plus a ``tune`` entry (study,
    ``storage`` URL without password, trial, metric, value); None while no trial has completed."""
    TrialState = require("optuna.trial", "rl").TrialState
    if not study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)):
        return None
    best = study.best_trial
    config = dict(best.user_attrs["config"])
    config["tune"] = {"study": study.study_name, "storage": storage, "trial": best.number,
                      "metric": study.user_attrs["sweep"]["metric"], "value": best.value}
    path = study_folder(out, study.study_name) / "best.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, yaml.safe_dump(config, sort_keys=False))
    return path


# ---------------------------------------------------------------------------- main
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m train.tune", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--algo", choices=ALGOS, required=True, help="RL algorithm")
    p.add_argument("--env", dest="env_id", required=True, help="env id, e.g. IiwaReach-v0")
    p.add_argument("--trials", type=int, required=True, help="trials of the study in total, over all workers")
    p.add_argument("--storage", help="Optuna RDB storage URL (default sqlite:///<out>/study.db); one shared "
                   "database (e.g. postgresql://user@host/db) for a sweep on several machines")
    p.add_argument("--heartbeat", type=int, default=HEARTBEAT, metavar="S",
                   help=f"seconds between a running trial's heartbeats in the storage (default {HEARTBEAT})")
    p.add_argument("--grace", type=int, default=GRACE, metavar="S",
                   help=f"seconds without a heartbeat after which a killed worker's trial is failed and run "
                   f"again (default {GRACE})")
    p.add_argument("--study-name", help="study name (default <algo>-<env>)")
    p.add_argument("--out", type=Path, default=Path("runs/tune"), help="folder of the trials (default runs/tune)")
    p.add_argument("-n", "--timesteps", type=float, help="env steps per trial (default: n_timesteps of the YAML)")
    p.add_argument("--n-envs", type=int, help="parallel envs per trial (default: n_envs of the YAML)")
    p.add_argument("--hyperparams", "-params", nargs="+", default=[], metavar="KEY=VALUE",
                   help="fixed hyper-parameters of every trial, values parsed as YAML (e.g. eval_goals=100); "
                   "the sampled ones replace them")
    p.add_argument("--metric", choices=list(METRICS), default="success",
                   help="evaluation entry to optimise (default success; distances are minimised)")
    p.add_argument("--seed", type=int, default=0, help="seed of every trial's training (default 0)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1: the machine is shared)")
    p.add_argument("-v", "--verbose", type=int, default=0, help="SB3 verbosity (0, 1, 2)")
    return p


def tune(args: argparse.Namespace) -> Path | None:
    """Run trials until the study holds ``args.trials``; the path of ``best.yaml`` (None: no trial completed)."""
    import torch

    from train.train import algo_kwargs, load_hyperparams, parse_overrides

    torch.set_num_threads(args.threads)
    logging.getLogger("optuna.study._optimize").addFilter(NO_TRACEBACK)  # the logger of the failed-trial line
    study_name = args.study_name or f"{args.algo}-{args.env_id}"
    if not study_name or "/" in study_name or study_name.startswith("."):
        raise ValueError(f"--study-name names a folder in --out: no '/' and no leading '.', got {study_name!r}")
    overrides = parse_overrides(args.hyperparams)
    overrides.update((key, value) for key, value in (("n_timesteps", args.timesteps), ("n_envs", args.n_envs))
                     if value is not None)
    hp = load_hyperparams(args.algo, args.env_id, overrides)  # validates the env id and the overrides
    algo_kwargs(args.algo, hp)  # and the SB3 keys and values, before the study records the sweep
    sweep = {"algo": args.algo, "env_id": args.env_id, "seed": args.seed, "metric": args.metric,
             "overrides": {key: hp[key] for key in ("n_timesteps", "n_envs", *overrides)}}
    if args.storage is None:
        args.out.mkdir(parents=True, exist_ok=True)
    url = args.storage or f"sqlite:///{args.out.resolve() / 'study.db'}"
    shown = hide_password(url)
    storage = open_storage(url, args.heartbeat, args.grace)
    study = load_study(storage, study_name, sweep, shown)
    counted = counted_trials(study)  # fails the trials of killed workers first
    resume_interrupted(study)
    remaining = args.trials - counted
    running = len(study.get_trials(deepcopy=False, states=counted_states()[2:]))
    note = f" ({running} running elsewhere, or left by a killed worker: failed {args.grace} s after its last " \
        f"heartbeat)" if running else ""
    print(f"study {study_name!r} in {shown}: {args.trials - remaining} of {args.trials} trials counted{note}, "
          f"running {max(remaining, 0)} here", flush=True)
    if remaining > 0:
        command = "python -m train.tune " + " ".join(shlex.quote(hide_password(a)) for a in sys.argv[1:])
        study.optimize(lambda trial: objective(trial, sweep, args.out, command, args.verbose), n_trials=args.trials,
                       callbacks=[lambda s, _: write_best(s, args.out, shown),
                                  lambda s, _: stop_when_counted(s, args.trials)])
    best = write_best(study, args.out, shown)
    if best is None:
        print("no trial completed yet", flush=True)
    else:
        print(f"best trial {study.best_trial.number}: {args.metric} {study.best_value:.4g}; config in {best} "
              f"(python -m train.train --config {best} --out DIR)", flush=True)
    return best


def main(argv: list[str] | None = None) -> int:
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.trials < 1:
        parser.error(f"--trials must be >= 1, got {args.trials}")
    if args.heartbeat < 1 or args.grace <= args.heartbeat:
        parser.error(f"--heartbeat must be >= 1 and --grace above it, got {args.heartbeat} and {args.grace}")
    from train.train import check_run_args

    check_run_args(parser, args)
    try:
        require("optuna", "rl")
    except MissingExtra as err:
        parser.error(str(err))
    try:
        tune(args)
    except (ValueError, TypeError, FileNotFoundError, FileExistsError, RunLocked) as err:
        parser.error(str(err))
    except KeyboardInterrupt:
        print("interrupted: the running trial is marked failed; the same command resumes the study, that trial "
              "first (from its newest checkpoint)", flush=True)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
