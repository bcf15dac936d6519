"""Train a stable-baselines3 agent (PPO or SAC+HER) on the batched iiwa reaching env.

    python -m train.train --algo ppo --env IiwaReach-v0 --seed 0 --out runs/ppo_reach
    python -m train.train --resume --out runs/ppo_reach          # after Ctrl-C or a kill
    python -m train.train --config runs/tune/best.yaml --out runs/best   # a run's (or train.tune's) config

Hyper-parameters come from ``train/config/<algo>.yaml`` (one block per env id, as in
rl-baselines3-zoo); ``--timesteps``, ``--n-envs`` and ``--hyperparams key=value ...``
override them. The run directory gets:

- ``config.yaml``: algo, env, seed, the resolved hyper-parameters, the command and commit;
- ``checkpoints/step_<N>/``: model, VecNormalize statistics, replay buffer (off-policy
  algos) and ``state.json`` (steps, wall time, evaluations so far), every
  ``checkpoint_freq`` env steps and on Ctrl-C / SIGTERM; ``--resume`` restarts from the
  newest intact one, so a hard kill loses at most one checkpoint interval;
- ``evaluations.json``: the periodic evaluation (success at 1 cm, median and 95th
  percentile final distance on a fixed seeded goal set) against env steps and wall time;
- ``tb/``: TensorBoard logs;
- at the end, ``model.zip`` with ``vecnormalize.pkl``, ``config.yaml`` and
  ``train_info.json`` (wall time, load average, steps per second) side by side;
- ``.lock``: locked while a process trains here (a second one is refused).

``train.run_dir.RunDir`` owns this layout: atomic writes, the lock, and the resume from the newest
checkpoint whose files all load. Everything is validated before the first write.
"""

from __future__ import annotations

import argparse
import inspect
import json
import os
import shlex
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from train.run_dir import (
    ALGOS,
    CheckpointError,
    RunDir,
    RunLocked,
    check_folder,
    check_model,
    read_yaml,
    validate_config,
)
from train.vec_env import build_venv, wrap_normalize

if TYPE_CHECKING:
    from train.callbacks import EvalAndCheckpoint

CONFIG_DIR = Path(__file__).resolve().parent / "config"
_TRAINER_KEYS = {
    "n_envs", "n_timesteps", "policy", "normalize", "env_kwargs", "features_extractor_kwargs",
    "eval_freq", "eval_goals", "checkpoint_freq", "her", "log_distance_bonus", "features_extractor",
    "clearance_penalty",
}
_EXTRACTORS = ("goal_delta", "joint")
_ACTIVATIONS = ("tanh", "relu", "elu")


# ---------------------------------------------------------------------------- configuration
def load_hyperparams(algo: str, env_id: str, overrides: dict[str, Any] | None = None,
                     path: Path | None = None) -> dict[str, Any]:
    """The YAML block of ``env_id`` in ``config/<algo>.yaml`` (or ``path``), with ``overrides`` applied."""
    if algo not in ALGOS:
        raise ValueError(f"algo must be one of {list(ALGOS)}, got {algo!r}")
    path = CONFIG_DIR / f"{algo}.yaml" if path is None else Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"hyper-parameter file {path} not found")
    table = read_yaml(path)
    if not isinstance(table, dict):
        raise ValueError(f"{path}: expected a mapping of env ids to hyper-parameters, got {type(table).__name__}")
    if env_id not in table:
        raise ValueError(f"no hyper-parameters for env {env_id!r} in {path}; it has {sorted(table)}")
    if not isinstance(table[env_id], dict):
        raise ValueError(f"{path}: the entry of {env_id!r} must be a mapping of hyper-parameters, "
                         f"got {table[env_id]!r}")
    return check_hyperparams({**table[env_id], **(overrides or {})}, env_id)


def check_hyperparams(hp: dict[str, Any], env_id: str) -> dict[str, Any]:
    """``hp`` with its step counts as ints and, for the joint features, the env's robot and ``max_step``
    filled in; ValueError (TypeError for a non-boolean ``normalize``) names a bad entry."""
    from iiwa_torch.checks import check_bool  # here: torch only after main has set OpenMP's wait policy

    hp = dict(hp)
    for key in ("n_envs", "n_timesteps", "eval_freq", "eval_goals", "checkpoint_freq"):
        value = hp.get(key)
        if isinstance(value, str):  # YAML 1.1 reads 1.5e7 (no exponent sign) as a string
            try:
                value = float(value)
            except ValueError:
                pass
        if not isinstance(value, (int, float)) or isinstance(value, bool) or value <= 0 or int(value) != value:
            raise ValueError(f"{key} must be a positive integer, got {value!r}")
        hp[key] = int(value)
    check_bool(hp.get("normalize", False), "normalize")
    kind = hp.get("features_extractor", "goal_delta")
    if kind not in _EXTRACTORS:
        raise ValueError(f"features_extractor must be one of {list(_EXTRACTORS)}, got {kind!r}")
    if kind == "joint":
        if hp.get("normalize", False):
            raise ValueError("features_extractor 'joint' reads cos q, sin q from the raw observation: "
                             "set normalize: false")
        hp["features_extractor_kwargs"] = {**joint_feature_defaults(env_id, hp.get("env_kwargs")),
                                           **(hp.get("features_extractor_kwargs") or {})}
    return hp


def joint_feature_defaults(env_id: str, env_kwargs: dict[str, Any] | None = None) -> dict[str, Any]:
    """The env's robot (``PRESETS`` name), ``max_step`` (rad per step) and, if it observes them, where its
    clearances are (``clearance_rows``), for ``JointGoalExtractor``."""
    import envs

    if env_id not in envs.ENV_IDS:
        raise ValueError(f"features_extractor 'joint' needs one of our envs {list(envs.ENV_IDS)}, got {env_id!r}")
    task = envs.make_task(env_id, **(env_kwargs or {}))
    defaults = {"robot": task.robot.name, "max_step": [round(float(s), 7) for s in task.max_step]}
    if task.transport.clearance_size:
        defaults["clearance_rows"] = [3 * task.arm.n_joints + task.transport.obstacle_size,
                                      len(task.world.capsules.names)]
    return defaults


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``["learning_rate=3e-4", "policy_kwargs={net_arch: [64, 64]}"]`` -> dict (values parsed as YAML)."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--hyperparams items must look like key=value, got {item!r}")
        try:
            out[key] = yaml.safe_load(value)
        except yaml.YAMLError as err:
            raise ValueError(f"--hyperparams {item!r}: the value is not valid YAML ({err.problem or err})") from None
    return out


def _schedule(key: str, value):
    """``"lin_1e-3"`` -> a linear decay to 0 (SB3 passes the remaining progress 1 -> 0; it goes below 0 in
    the last rollout, which SB3 always completes, and is held at 0 there); numbers unchanged.
    ValueError names ``key`` if ``value`` is neither a number nor ``lin_<number>``."""
    text = value[4:] if isinstance(value, str) and value.startswith("lin_") else value
    try:
        start = float(text) if isinstance(text, str) else text
    except ValueError:
        start = None
    if isinstance(start, bool) or not isinstance(start, (int, float)):
        raise ValueError(f"{key} must be a number or lin_<number> (a linear decay), got {value!r}")
    return (lambda progress: max(progress, 0.0) * start) if text is not value else start


def algo_kwargs(algo: str, hp: dict[str, Any]) -> dict[str, Any]:
    """The constructor keyword arguments of the SB3 algorithm for these hyper-parameters."""
    import torch
    from stable_baselines3 import HerReplayBuffer

    from train.features import GoalDeltaExtractor, JointGoalExtractor

    kwargs = {k: v for k, v in hp.items() if k not in _TRAINER_KEYS}
    _check_algo_keys(algo, kwargs)
    for key in ("learning_rate", "clip_range"):
        if key in kwargs:
            kwargs[key] = _schedule(key, kwargs[key])
    gamma = kwargs.get("gamma", 0.99)
    if isinstance(gamma, bool) or not isinstance(gamma, (int, float)) or not 0 < gamma <= 1:
        raise ValueError(f"gamma must be a number in (0, 1], got {kwargs['gamma']!r}")
    policy_kwargs = kwargs.pop("policy_kwargs", None) or {}
    if not isinstance(policy_kwargs, dict):
        raise ValueError(f"policy_kwargs must be a mapping (e.g. {{net_arch: [256, 256]}}), got {policy_kwargs!r}")
    policy_kwargs = dict(policy_kwargs)
    if "activation_fn" in policy_kwargs:
        name = policy_kwargs["activation_fn"]
        if name not in _ACTIVATIONS:
            raise ValueError(f"policy_kwargs.activation_fn must be one of {list(_ACTIVATIONS)}, got {name!r}")
        policy_kwargs["activation_fn"] = {"tanh": torch.nn.Tanh, "relu": torch.nn.ReLU, "elu": torch.nn.ELU}[name]
    if "features_extractor_kwargs" in hp:
        extractors = {"goal_delta": GoalDeltaExtractor, "joint": JointGoalExtractor}
        policy_kwargs["features_extractor_class"] = extractors[hp.get("features_extractor", "goal_delta")]
        policy_kwargs["features_extractor_kwargs"] = dict(hp["features_extractor_kwargs"])
    kwargs["policy_kwargs"] = policy_kwargs
    if hp.get("policy") == "ResidualDLSPolicy":
        from train.residual import ResidualDLSPolicy

        kwargs["policy"] = ResidualDLSPolicy
    if hp.get("her") is not None:
        if algo != "sac":
            raise ValueError("her (a replay-buffer option) needs an off-policy algo (sac)")
        for key in ("log_distance_bonus", "clearance_penalty"):
            if hp.get(key) is not None:
                raise ValueError(f"{key} cannot be combined with her: relabelled rewards would not include it")
        kwargs["replay_buffer_class"] = HerReplayBuffer
        kwargs["replay_buffer_kwargs"] = dict(hp["her"])
    return kwargs


def _check_algo_keys(algo: str, kwargs: dict[str, Any]) -> None:
    """Raise if a hyper-parameter is neither a trainer key nor an argument of the SB3 constructor."""
    from stable_baselines3 import PPO, SAC

    cls = {"ppo": PPO, "sac": SAC}[algo]
    accepted = set(inspect.signature(cls.__init__).parameters) - {"self", "env", "_init_setup_model"}
    unknown = sorted(set(kwargs) - accepted)
    if unknown:
        raise ValueError(f"unknown hyper-parameter(s) {unknown} for {algo}: expected trainer keys "
                         f"{sorted(_TRAINER_KEYS)} or {cls.__name__} arguments {sorted(accepted)}")


def her_learning_starts(hp: dict[str, Any], episode_steps: int | None) -> int | None:
    """``learning_starts`` for HER: at least ``n_envs * episode_steps`` env steps, so every env has ended
    its first episode (truncation at ``episode_steps``) before the first sample; None if no HER."""
    if hp.get("her") is None:
        return None
    configured = int(hp.get("learning_starts", 100))  # SAC's default
    if episode_steps is None:
        return configured
    return max(configured, hp["n_envs"] * int(episode_steps))


def episode_steps(venv) -> int | None:
    """The truncation length of the (wrapped) VecEnv's episodes, or None if it has none."""
    inner = venv.unwrapped
    task = getattr(inner, "task", None)
    if task is not None and hasattr(task, "max_episode_steps"):
        return int(task.max_episode_steps)
    spec = inner.get_attr("spec")[0]
    return getattr(spec, "max_episode_steps", None)


def git_commit() -> str:
    """The current commit of the repository (``unknown`` outside git), ``+dirty`` if train/ has changes."""
    root = Path(__file__).resolve().parents[1]
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, check=True)
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "train", "envs"], cwd=root,
                               capture_output=True, text=True, check=True)
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return sha.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")


# ---------------------------------------------------------------------------- main
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m train.train", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--algo", choices=ALGOS, help="RL algorithm (required unless --config or --resume)")
    p.add_argument("--env", dest="env_id", help="env id, e.g. IiwaReach-v0 (required unless --config or --resume)")
    p.add_argument("--out", required=True, type=Path, help="run directory (created; must be new unless --resume)")
    p.add_argument("--seed", type=int, help="seed of the algorithm and the envs (default 0, or the --config's)")
    p.add_argument("-n", "--timesteps", type=float, help="total env steps (default: n_timesteps of the YAML)")
    p.add_argument("--n-envs", type=int, help="parallel envs (default: n_envs of the YAML)")
    p.add_argument("--conf-file", type=Path, help="YAML of hyper-parameters (default train/config/<algo>.yaml)")
    p.add_argument("--config", type=Path, help="a run's config.yaml (e.g. train.tune's best trial): train it anew, "
                   "with the overrides of --timesteps, --n-envs, --seed and --hyperparams")
    p.add_argument("--hyperparams", "-params", nargs="+", default=[], metavar="KEY=VALUE",
                   help="override hyper-parameters, values parsed as YAML (e.g. learning_rate=3e-4)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its newest checkpoint")
    p.add_argument("--progress-bar", action=argparse.BooleanOptionalAction, default=sys.stderr.isatty(),
                   help="show a progress bar (default: when stderr is a terminal)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1: the machine is shared)")
    p.add_argument("-v", "--verbose", type=int, default=0, help="SB3 verbosity (0, 1, 2)")
    return p


def make_config(algo: str, env_id: str, seed: int, hyperparams: dict[str, Any], command: str) -> dict[str, Any]:
    """A run's config (``config.yaml``): algo, env id, seed, checked hyper-parameters, command and commit."""
    return {
        "algo": algo,
        "env_id": env_id,
        "seed": seed,
        "hyperparams": check_hyperparams(hyperparams, env_id),
        "command": command,
        "commit": git_commit(),
    }


def _config_from_args(args: argparse.Namespace) -> dict[str, Any]:
    overrides = parse_overrides(args.hyperparams)
    if args.timesteps is not None:
        overrides["n_timesteps"] = args.timesteps
    if args.n_envs is not None:
        overrides["n_envs"] = args.n_envs
    command = "python -m train.train " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    if args.config is not None:
        if args.algo is not None or args.env_id is not None or args.conf_file is not None:
            raise ValueError("--config names the algo, env and hyper-parameters: drop --algo, --env and --conf-file")
        base = validate_config(read_yaml(args.config), str(args.config))
        seed = base["seed"] if args.seed is None else args.seed
        return make_config(base["algo"], base["env_id"], seed, {**base["hyperparams"], **overrides}, command)
    if args.algo is None or args.env_id is None:
        raise ValueError("--algo and --env are required for a new run (or use --config or --resume)")
    hp = load_hyperparams(args.algo, args.env_id, overrides, args.conf_file)
    return make_config(args.algo, args.env_id, 0 if args.seed is None else args.seed, hp, command)


def _sigterm_as_interrupt(signum, frame):
    raise KeyboardInterrupt(f"signal {signum}")


def _algo_class(algo: str):
    from stable_baselines3 import PPO, SAC

    return {"ppo": PPO, "sac": SAC}[algo]


def new_model(run: RunDir, config: dict[str, Any], verbose: int = 0):
    """A fresh model on fresh envs; raises on an unknown hyper-parameter before anything is written.
    For HER it raises ``learning_starts`` to the first episodes of every env (recorded in ``config``)."""
    hp, algo, seed = config["hyperparams"], config["algo"], config["seed"]
    rollout = hp["n_envs"] * hp.get("n_steps", 2048)  # SB3's PPO default
    if algo == "ppo" and hp["n_timesteps"] < rollout:  # a smoke run may want that: said, not refused
        print(f"warning: n_timesteps {hp['n_timesteps']} is less than one PPO rollout (n_envs x n_steps = {rollout}):"
              " SB3 runs the whole rollout, and a lin_ learning rate has decayed to 0 by its one update", flush=True)
    venv = build_venv(config["env_id"], hp, seed)
    starts = her_learning_starts(hp, episode_steps(venv)) if algo == "sac" else None  # PPO: algo_kwargs refuses her
    if starts is not None and starts != hp.get("learning_starts"):
        print(f"learning_starts {hp.get('learning_starts', 100)} -> {starts}: HER samples only finished episodes, "
              f"and {hp['n_envs']} envs end their first ones after {starts} env steps", flush=True)
        hp["learning_starts"] = starts
    kwargs = algo_kwargs(algo, hp)
    venv = wrap_normalize(venv, hp, kwargs.get("gamma", 0.99))
    policy = kwargs.pop("policy", hp["policy"])
    try:
        return _algo_class(algo)(policy, venv, seed=seed, device="cpu", verbose=verbose,
                                 tensorboard_log=str(run.path / "tb"), **kwargs)
    except (TypeError, AssertionError) as err:  # a nested option the policy or buffer does not take (TypeError);
        # SB3 checks sizes such as n_steps and batch_size with assert
        raise ValueError(f"hyper-parameters rejected by {algo.upper()}: {err}") from None


def _load_file(path: Path, load):
    """``load(path)``; any failure to read it becomes a ``CheckpointError`` naming the file."""
    try:
        return load(path)
    except CheckpointError:
        raise
    except Exception as err:  # truncated pickles, zips and JSON fail in many ways: all mean "unreadable"
        raise CheckpointError(f"{path} is unreadable ({type(err).__name__}: {err})") from None


def _load_checkpoint(run: RunDir, ckpt: Path, config: dict[str, Any], verbose: int):
    """``(model, TrainClock)`` from one checkpoint folder; ``CheckpointError`` names a damaged file."""
    from stable_baselines3.common.vec_env import VecNormalize

    from train.callbacks import TrainClock

    hp, algo, env_id, seed = config["hyperparams"], config["algo"], config["env_id"], config["seed"]
    state = _load_file(ckpt / "state.json", lambda p: json.loads(p.read_text()))
    if not isinstance(state, dict) or not {"num_timesteps", "elapsed", "evaluations"} <= set(state):
        raise CheckpointError(f"{ckpt / 'state.json'} lacks num_timesteps, elapsed or evaluations")
    # new episodes after a resume: do not replay the seeds of the first start
    venv = build_venv(env_id, hp, seed + state["num_timesteps"])
    check_model(algo, ckpt / "model.zip", venv.observation_space, venv.action_space)
    if hp.get("normalize", False) and not (ckpt / "vecnormalize.pkl").exists():  # not fresh statistics
        raise CheckpointError(f"{ckpt / 'vecnormalize.pkl'} is missing (the config says normalize: true)")
    if (ckpt / "vecnormalize.pkl").exists():
        venv = _load_file(ckpt / "vecnormalize.pkl", lambda p: VecNormalize.load(str(p), venv))
    model = _load_file(ckpt / "model.zip", lambda p: _algo_class(algo).load(
        p, env=venv, device="cpu", tensorboard_log=str(run.path / "tb"), verbose=verbose))
    if (ckpt / "replay_buffer.pkl").exists():
        _load_file(ckpt / "replay_buffer.pkl", model.load_replay_buffer)
    return model, TrainClock(elapsed=state["elapsed"], evaluations=state["evaluations"])


def _restore(run: RunDir, config: dict[str, Any], verbose: int):
    """``(model, TrainClock)`` from the newest intact checkpoint, saying which damaged ones it skipped."""
    from train.callbacks import TrainClock

    checkpoints = run.checkpoints()
    if not checkpoints:
        print(f"resuming {run.path}: no checkpoint yet, starting from step 0", flush=True)
        return new_model(run, config, verbose), TrainClock()
    for ckpt in checkpoints:
        try:
            model, clock = _load_checkpoint(run, ckpt, config, verbose)
        except CheckpointError as err:
            print(f"checkpoint {ckpt.name} is damaged: {err}; trying an older one", file=sys.stderr, flush=True)
            continue
        skipped = "" if ckpt == checkpoints[0] else f" (the newest intact one, not {checkpoints[0].name})"
        print(f"resuming {run.path} from {ckpt.name}{skipped}: {model.num_timesteps} of "
              f"{config['hyperparams']['n_timesteps']} steps", flush=True)
        return model, clock
    raise CheckpointError(f"no intact checkpoint in {run.checkpoint_root} (see above); move that folder "
                          f"away to restart the run from step 0")


def _learn(model, callback, total: int, progress_bar: bool) -> bool:
    """Train to ``total`` env steps; False if interrupted (Ctrl-C or SIGTERM)."""
    previous = signal.signal(signal.SIGTERM, _sigterm_as_interrupt)
    try:
        # learn(0) still starts the callback (goal set, clock) when the run is already complete
        model.learn(max(total - model.num_timesteps, 0), callback=callback, reset_num_timesteps=False,
                    progress_bar=progress_bar, tb_log_name="run")
    except KeyboardInterrupt:
        return False
    finally:
        signal.signal(signal.SIGTERM, previous)
    return True


def _checkpoint_ignoring_interrupts(callback) -> Path:
    """The interrupted run's checkpoint with further Ctrl-C presses and SIGTERMs ignored until it is
    written and the old ones pruned (a second press showed a traceback and left the pruning undone)."""
    ignored = (signal.SIGINT, signal.SIGTERM)
    previous = {s: signal.signal(s, signal.SIG_IGN) for s in ignored}
    try:
        return callback.checkpoint()
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def _finish(run: RunDir, model, callback) -> None:
    """The final evaluation, checkpoint, model and ``train_info.json``."""
    from iiwa_torch.runtime import machine_info

    evaluations = callback.clock.evaluations
    if not evaluations or evaluations[-1]["steps"] != model.num_timesteps:
        callback.evaluate()
    callback.checkpoint()
    wall = callback.clock.wall()
    run.save_final(model)
    run.write_json("train_info.json", {
        "num_timesteps": int(model.num_timesteps),
        "wall_time": round(wall, 1),
        "steps_per_second": round(model.num_timesteps / wall, 1),
        "final_evaluation": evaluations[-1] if evaluations else None,
        "finished": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": machine_info(),
        "python": sys.version.split()[0],
    })
    print(f"done: {model.num_timesteps} steps in {wall:.0f}s; model in {run.path / 'model.zip'}", flush=True)


def _check_new(run: RunDir) -> None:
    check_folder(run.path)
    if not run.is_empty():
        raise FileExistsError(f"{run.path} exists and is not empty: pick a new --out, or pass --resume")


class Interrupted(KeyboardInterrupt):
    """Ctrl-C or SIGTERM stopped the training at env step ``step``; ``checkpoint`` holds that state."""

    def __init__(self, step: int, checkpoint: Path):
        super().__init__(f"interrupted at step {step}")
        self.step, self.checkpoint = step, checkpoint


def run_training(run: RunDir, config: dict[str, Any], model=None, *, verbose: int = 0, progress_bar: bool = False,
                 callback: Callable[..., EvalAndCheckpoint] | None = None) -> EvalAndCheckpoint:
    """Train ``model`` (a fresh one from ``new_model``) in the new run directory ``run``, or, with
    ``model=None``, resume the run there from its newest intact checkpoint; returns the callback.

    ``callback(run, hp, env_id, env_kwargs, clock)`` builds the evaluation-and-checkpoint callback
    (default ``EvalAndCheckpoint``). If it stops the training early, a checkpoint is saved (so
    ``--resume`` can continue) instead of the final model. Raises ``Interrupted`` on Ctrl-C or SIGTERM
    after saving a checkpoint, and ``RunLocked`` if another process trains in ``run``.
    """
    from train.callbacks import EvalAndCheckpoint, TrainClock

    with run.lock():
        if model is None:
            model, clock = _restore(run, config, verbose)
            run.write_config(config)  # a new -n is the run's total from now on
        else:
            _check_new(run)  # again under the lock: another process may have started here meanwhile
            run.write_config(config)
            clock = TrainClock()
        run.write_json("evaluations.json", clock.evaluations)
        hp = config["hyperparams"]
        cb = (callback or EvalAndCheckpoint)(run, hp, config["env_id"], dict(hp.get("env_kwargs") or {}), clock)
        if not _learn(model, cb, hp["n_timesteps"], progress_bar):
            raise Interrupted(model.num_timesteps, _checkpoint_ignoring_interrupts(cb))
        if model.num_timesteps < hp["n_timesteps"]:
            path = cb.checkpoint()
            print(f"stopped by the callback at step {model.num_timesteps}: checkpoint {path}", flush=True)
        else:
            _finish(run, model, cb)
    return cb


def train(args: argparse.Namespace) -> Path:
    """Run (or resume) a training; returns the run directory. Everything is validated (and a new run's
    model built) before the first write; the run directory is locked while this process trains in it."""
    import torch

    torch.set_num_threads(args.threads)
    run = RunDir(args.out)
    model = None
    if args.resume:
        given = [flag for flag, value in (("--config", args.config), ("--algo", args.algo), ("--env", args.env_id),
                                          ("--seed", args.seed), ("--n-envs", args.n_envs),
                                          ("--conf-file", args.conf_file), ("--hyperparams", args.hyperparams or None))
                 if value is not None]
        if given:
            raise ValueError(f"--resume continues the config.yaml in --out (only -n may change): drop "
                             f"{', '.join(given)}")
        config = run.read_config()
        if args.timesteps is not None:
            config["hyperparams"]["n_timesteps"] = int(args.timesteps)
    else:
        config = _config_from_args(args)
        _check_new(run)
        model = new_model(run, config, args.verbose)
    try:
        run_training(run, config, model, verbose=args.verbose, progress_bar=args.progress_bar)
    except Interrupted as stop:
        print(f"interrupted at step {stop.step}: checkpoint {stop.checkpoint}; continue with "
              f"python -m train.train --resume --out {run.path}", flush=True)
        raise SystemExit(130) from None
    return run.path


def check_run_args(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Exit with status 2 and one line on a bad ``--timesteps``, ``--n-envs`` or ``--threads``
    (the options ``train.train`` and ``train.tune`` share)."""
    if args.timesteps is not None and (args.timesteps <= 0 or int(args.timesteps) != args.timesteps):
        parser.error(f"--timesteps must be a positive integer, got {args.timesteps:g}")
    if args.n_envs is not None and args.n_envs < 1:
        parser.error(f"--n-envs must be >= 1, got {args.n_envs}")
    if args.threads < 1:
        parser.error(f"--threads must be >= 1, got {args.threads}")


def main(argv: list[str] | None = None) -> int:
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    parser = build_parser()
    args = parser.parse_args(argv)
    check_run_args(parser, args)
    try:
        train(args)
    except (ValueError, TypeError, FileNotFoundError, FileExistsError, RunLocked) as err:
        parser.error(str(err))
    return 0


if __name__ == "__main__":
    sys.exit(main())
