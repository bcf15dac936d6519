"""Train a stable-baselines3 agent (PPO or SAC+HER) on the batched iiwa reaching env.

    python -m train.train --algo ppo --env IiwaReach-v0 --seed 0 --out runs/ppo_reach
    python -m train.train --resume --out runs/ppo_reach          # after Ctrl-C or a kill

Hyper-parameters come from ``train/config/<algo>.yaml`` (one block per env id, as in
rl-baselines3-zoo); ``--timesteps``, ``--n-envs`` and ``--hyperparams key=value ...``
override them. The run directory gets:

- ``config.yaml``: algo, env, seed, the resolved hyper-parameters, the command and commit;
- ``checkpoints/step_<N>/``: model, VecNormalize statistics, replay buffer (off-policy
  algos) and ``state.json`` (steps, wall time, evaluations so far), every
  ``checkpoint_freq`` env steps and on Ctrl-C / SIGTERM; ``--resume`` restarts from the
  newest one, so a hard kill loses at most one checkpoint interval;
- ``evaluations.json``: the periodic evaluation (success at 1 cm, median and 95th
  percentile final distance on a fixed seeded goal set) against env steps and wall time;
- ``tb/``: TensorBoard logs;
- at the end, ``model.zip`` with ``vecnormalize.pkl``, ``config.yaml`` and
  ``train_info.json`` (wall time, load average, steps per second) side by side.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

ALGOS = ("ppo", "sac")
CONFIG_DIR = Path(__file__).resolve().parent / "config"
_TRAINER_KEYS = {
    "n_envs", "n_timesteps", "policy", "normalize", "env_kwargs", "features_extractor_kwargs",
    "eval_freq", "eval_goals", "checkpoint_freq", "her", "log_distance_bonus", "features_extractor",
}
_EXTRACTORS = ("goal_delta", "joint")
_ACTIVATIONS = ("tanh", "relu", "elu")
EVAL_SEED = 10_000  # goal-set seed of the periodic evaluation; train.evaluate defaults to another


# ---------------------------------------------------------------------------- configuration
def load_hyperparams(algo: str, env_id: str, overrides: dict[str, Any] | None = None,
                     path: Path | None = None) -> dict[str, Any]:
    """The YAML block of ``env_id`` in ``config/<algo>.yaml`` (or ``path``), with ``overrides`` applied."""
    if algo not in ALGOS:
        raise ValueError(f"algo must be one of {list(ALGOS)}, got {algo!r}")
    path = CONFIG_DIR / f"{algo}.yaml" if path is None else Path(path)
    table = yaml.safe_load(path.read_text())
    if env_id not in table:
        raise ValueError(f"no hyper-parameters for env {env_id!r} in {path}; it has {sorted(table)}")
    hp = {**table[env_id], **(overrides or {})}
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
    """The env's robot (``PRESETS`` name) and ``max_step`` (rad per step) for ``JointGoalExtractor``."""
    import envs

    if env_id not in envs.ENV_IDS:
        raise ValueError(f"features_extractor 'joint' needs one of our envs {list(envs.ENV_IDS)}, got {env_id!r}")
    task = envs.make_task(env_id, **(env_kwargs or {}))
    return {"robot": task.robot.name, "max_step": [round(float(s), 7) for s in task.max_step]}


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``["learning_rate=3e-4", "policy_kwargs={net_arch: [64, 64]}"]`` -> dict (values parsed as YAML)."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--hyperparams items must look like key=value, got {item!r}")
        out[key] = yaml.safe_load(value)
    return out


def _schedule(value):
    """``"lin_1e-3"`` -> a linear decay to 0 (SB3 passes the remaining progress 1 -> 0); numbers unchanged."""
    if isinstance(value, str) and value.startswith("lin_"):
        start = float(value[4:])
        return lambda progress: progress * start
    return float(value) if isinstance(value, str) else value


def algo_kwargs(algo: str, hp: dict[str, Any]) -> dict[str, Any]:
    """The constructor keyword arguments of the SB3 algorithm for these hyper-parameters."""
    import torch
    from stable_baselines3 import HerReplayBuffer

    from train.features import GoalDeltaExtractor, JointGoalExtractor

    kwargs = {k: v for k, v in hp.items() if k not in _TRAINER_KEYS}
    for key in ("learning_rate", "clip_range"):
        if key in kwargs:
            kwargs[key] = _schedule(kwargs[key])
    policy_kwargs = dict(kwargs.pop("policy_kwargs", None) or {})
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
        if hp.get("log_distance_bonus") is not None:
            raise ValueError("log_distance_bonus cannot be combined with her: relabelled rewards would not include it")
        kwargs["replay_buffer_class"] = HerReplayBuffer
        kwargs["replay_buffer_kwargs"] = dict(hp["her"])
    return kwargs


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


# ---------------------------------------------------------------------------- environments
def make_env(env_id: str, n_envs: int, seed: int, env_kwargs: dict[str, Any] | None = None):
    """The SB3 VecEnv: the batched ``envs.sb3.IiwaReachVecEnv`` for our ids, else SB3's
    ``make_vec_env`` on a gymnasium id (e.g. ``panda_gym:PandaReach-v3``)."""
    import envs
    from envs.sb3 import IiwaReachVecEnv

    if env_id in envs.ENV_IDS:
        return IiwaReachVecEnv(n_envs, env_id, seed=seed, **(env_kwargs or {}))
    import gymnasium
    from stable_baselines3.common.env_util import make_vec_env

    module, _, name = env_id.rpartition(":")
    try:
        if module:
            importlib.import_module(module)  # registers its ids, as gymnasium.make("module:Id") does
        gymnasium.spec(name)
    except (gymnasium.error.Error, ImportError) as err:
        raise ValueError(f"unknown env id {env_id!r}: use one of {list(envs.ENV_IDS)} or a registered "
                         f"gymnasium id ('module:Id' imports the module first) ({err})") from None
    return make_vec_env(name, n_envs=n_envs, seed=seed, env_kwargs=env_kwargs)


def build_venv(env_id: str, hp: dict[str, Any], seed: int):
    """``make_env`` plus ``VecMonitor`` (episode return, length and success in the logs) and, if the
    hyper-parameters ask, the ``LogDistanceBonus`` reward term (before any normalisation)."""
    from stable_baselines3.common.vec_env import VecMonitor

    from train.wrappers import LogDistanceBonus

    venv = VecMonitor(make_env(env_id, hp["n_envs"], seed, hp.get("env_kwargs")))
    if hp.get("log_distance_bonus") is not None:
        venv = LogDistanceBonus(venv, **hp["log_distance_bonus"])
    return venv


def wrap_normalize(venv, hp: dict[str, Any], gamma: float):
    """VecNormalize on the ``observation`` key (goals stay in metres for the goal-delta features)."""
    from stable_baselines3.common.vec_env import VecNormalize

    if not hp.get("normalize", False):
        return venv
    return VecNormalize(venv, norm_obs_keys=["observation"], norm_reward=False, gamma=gamma)


# ---------------------------------------------------------------------------- checkpoints
def save_checkpoint(model, run: Path, state: dict[str, Any], keep: int = 2) -> Path:
    """Write model, normaliser, replay buffer and ``state.json`` to ``checkpoints/step_<N>`` atomically
    (written to a temporary folder, then renamed); keep the ``keep`` newest."""
    root = run / "checkpoints"
    final = root / f"step_{model.num_timesteps:012d}"
    tmp = root / f".tmp_{final.name}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    model.save(tmp / "model.zip")
    vec_normalize = model.get_vec_normalize_env()
    if vec_normalize is not None:
        vec_normalize.save(str(tmp / "vecnormalize.pkl"))
    if getattr(model, "replay_buffer", None) is not None:
        model.save_replay_buffer(tmp / "replay_buffer.pkl")
    (tmp / "state.json").write_text(json.dumps(state, indent=1))
    shutil.rmtree(final, ignore_errors=True)
    os.replace(tmp, final)
    for old in sorted(p for p in root.glob("step_*") if p.is_dir())[:-keep]:
        shutil.rmtree(old, ignore_errors=True)
    return final


def latest_checkpoint(run: Path) -> Path | None:
    """The newest complete checkpoint folder of a run, or None."""
    done = sorted(p for p in (run / "checkpoints").glob("step_*") if (p / "state.json").exists())
    return done[-1] if done else None


def _callbacks(run: Path, hp: dict[str, Any], env_id: str, env_kwargs: dict[str, Any], clock: dict[str, Any]):
    """The periodic evaluation and checkpoint callbacks (one class: both need the shared clock)."""
    from stable_baselines3.common.callbacks import BaseCallback

    from train.rollout import make_goal_set, policy_actor, rollout

    class EvalAndCheckpoint(BaseCallback):
        """Every ``eval_freq`` env steps: success on a fixed goal set; every ``checkpoint_freq``: a checkpoint."""

        def _on_training_start(self) -> None:
            import envs

            self.goals, self.task = None, None
            if env_id in envs.ENV_IDS:
                self.task = envs.make_task(env_id, **env_kwargs)
                self.goals = make_goal_set(env_id, hp["eval_goals"], EVAL_SEED, env_kwargs)
            self.next_eval = (self.num_timesteps // hp["eval_freq"] + 1) * hp["eval_freq"]
            self.next_ckpt = (self.num_timesteps // hp["checkpoint_freq"] + 1) * hp["checkpoint_freq"]
            if not clock["evaluations"]:
                self._evaluate()

        def _final_distances(self) -> tuple[np.ndarray, float, float, np.ndarray | None]:
            """Final distances (m), success threshold (m), seconds and final angles (rad; None for position
            goals): our task on the fixed goal set;
            another goal env (e.g. panda-gym) by ``eval_goals`` seeded episodes, as it defines them."""
            vec_normalize = self.model.get_vec_normalize_env()
            if self.task is not None:
                r = rollout(self.goals, policy_actor(self.model, vec_normalize))
                angle = r.angle[-1] if self.task.goal_kind.value == "pose" else None
                return r.distance[-1], self.task.distance_threshold, r.seconds, angle
            start = time.perf_counter()
            env = make_env(env_id, 1, EVAL_SEED, env_kwargs)
            obs, final = env.reset(), []
            while len(final) < hp["eval_goals"]:
                if vec_normalize is not None:
                    obs = vec_normalize.normalize_obs(obs)
                action, _ = self.model.predict(obs, deterministic=True)
                obs, _, done, infos = env.step(action)
                if done[0]:
                    last = infos[0]["terminal_observation"]
                    final.append(float(np.linalg.norm(last["achieved_goal"] - last["desired_goal"])))
            threshold = float(env.get_attr("unwrapped")[0].task.distance_threshold)  # panda-gym's task attribute
            env.close()
            return np.array(final), threshold, time.perf_counter() - start, None

        def _evaluate(self) -> None:
            wall = clock["elapsed"] + time.perf_counter() - clock["start"]
            final, threshold, seconds, angle = self._final_distances()
            entry = {
                "steps": int(self.num_timesteps),
                "wall_time": round(wall, 2),
                "success": float(np.mean(final < threshold)),
                "median_distance": float(np.median(final)),
                "p95_distance": float(np.percentile(final, 95)),
                "eval_seconds": round(seconds, 3),
                "loadavg": os.getloadavg()[0],
            }
            if angle is not None:  # pose goals: success needs the orientation too
                entry["success_position"] = entry["success"]
                entry["success"] = float(np.mean((final < threshold) & (angle < self.task.orientation_threshold)))
                entry["median_angle"] = float(np.median(angle))
            clock["evaluations"].append(entry)
            (run / "evaluations.json").write_text(json.dumps(clock["evaluations"], indent=1))
            for key in ("success", "median_distance", "p95_distance"):
                self.logger.record(f"eval/{key}", entry[key])
            if self.verbose:
                print(f"[eval] steps={entry['steps']} wall={entry['wall_time']:.0f}s "
                      f"success={entry['success']:.3f} "
                      f"median={1000 * entry['median_distance']:.1f}mm p95={1000 * entry['p95_distance']:.1f}mm",
                      flush=True)

        def checkpoint(self) -> Path:
            state = {
                "num_timesteps": int(self.model.num_timesteps),
                "elapsed": clock["elapsed"] + time.perf_counter() - clock["start"],
                "evaluations": clock["evaluations"],
            }
            return save_checkpoint(self.model, run, state)

        def _on_step(self) -> bool:
            if self.num_timesteps >= self.next_eval:
                self.next_eval += hp["eval_freq"]
                self._evaluate()
            if self.num_timesteps >= self.next_ckpt:
                self.next_ckpt += hp["checkpoint_freq"]
                self.checkpoint()
            return True

    return EvalAndCheckpoint(verbose=1)


# ---------------------------------------------------------------------------- main
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m train.train", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--algo", choices=ALGOS, help="RL algorithm (required unless --resume)")
    p.add_argument("--env", dest="env_id", help="env id, e.g. IiwaReach-v0 (required unless --resume)")
    p.add_argument("--out", required=True, type=Path, help="run directory (created; must be new unless --resume)")
    p.add_argument("--seed", type=int, default=0, help="seed of the algorithm and the envs (default 0)")
    p.add_argument("-n", "--timesteps", type=float, help="total env steps (default: n_timesteps of the YAML)")
    p.add_argument("--n-envs", type=int, help="parallel envs (default: n_envs of the YAML)")
    p.add_argument("--conf-file", type=Path, help="YAML of hyper-parameters (default train/config/<algo>.yaml)")
    p.add_argument("--hyperparams", "-params", nargs="+", default=[], metavar="KEY=VALUE",
                   help="override hyper-parameters, values parsed as YAML (e.g. learning_rate=3e-4)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its newest checkpoint")
    p.add_argument("--progress-bar", action=argparse.BooleanOptionalAction, default=sys.stderr.isatty(),
                   help="show a progress bar (default: when stderr is a terminal)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1: the machine is shared)")
    p.add_argument("-v", "--verbose", type=int, default=0, help="SB3 verbosity (0, 1, 2)")
    return p


def _config_from_args(args: argparse.Namespace) -> dict[str, Any]:
    if args.algo is None or args.env_id is None:
        raise ValueError("--algo and --env are required for a new run (or use --resume)")
    overrides = parse_overrides(args.hyperparams)
    if args.timesteps is not None:
        overrides["n_timesteps"] = args.timesteps
    if args.n_envs is not None:
        overrides["n_envs"] = args.n_envs
    hp = load_hyperparams(args.algo, args.env_id, overrides, args.conf_file)
    return {
        "algo": args.algo,
        "env_id": args.env_id,
        "seed": args.seed,
        "hyperparams": hp,
        "command": "python -m train.train " + " ".join(shlex.quote(a) for a in sys.argv[1:]),
        "commit": git_commit(),
    }


def _sigterm_as_interrupt(signum, frame):
    raise KeyboardInterrupt(f"signal {signum}")


def train(args: argparse.Namespace) -> Path:
    """Run (or resume) a training; returns the run directory."""
    import torch

    torch.set_num_threads(args.threads)
    from stable_baselines3 import PPO, SAC

    algo_class = {"ppo": PPO, "sac": SAC}
    run: Path = args.out
    checkpoint = None
    if args.resume:
        if not (run / "config.yaml").exists():
            raise FileNotFoundError(f"--resume: {run}/config.yaml not found; is {run} a run directory?")
        config = yaml.safe_load((run / "config.yaml").read_text())
        if args.timesteps is not None:
            config["hyperparams"]["n_timesteps"] = int(args.timesteps)
        checkpoint = latest_checkpoint(run)
    else:
        config = _config_from_args(args)
        if run.exists() and any(run.iterdir()):
            raise FileExistsError(f"{run} exists and is not empty: pick a new --out, or pass --resume")
        run.mkdir(parents=True, exist_ok=True)
        (run / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    hp, algo, env_id, seed = config["hyperparams"], config["algo"], config["env_id"], config["seed"]
    total = hp["n_timesteps"]
    env_kwargs = dict(hp.get("env_kwargs") or {})

    clock = {"start": time.perf_counter(), "elapsed": 0.0, "evaluations": []}
    if checkpoint is not None:
        state = json.loads((checkpoint / "state.json").read_text())
        clock["elapsed"], clock["evaluations"] = state["elapsed"], state["evaluations"]
        steps_done = state["num_timesteps"]
        # new episodes after a resume: do not replay the seeds of the first start
        venv = build_venv(env_id, hp, seed + steps_done)
        if (checkpoint / "vecnormalize.pkl").exists():
            from stable_baselines3.common.vec_env import VecNormalize

            venv = VecNormalize.load(str(checkpoint / "vecnormalize.pkl"), venv)
        model = algo_class[algo].load(checkpoint / "model.zip", env=venv, device="cpu",
                                      tensorboard_log=str(run / "tb"))
        if (checkpoint / "replay_buffer.pkl").exists():
            model.load_replay_buffer(checkpoint / "replay_buffer.pkl")
        print(f"resuming {run} from {checkpoint.name}: {model.num_timesteps} of {total} steps", flush=True)
    else:
        kwargs = algo_kwargs(algo, hp)
        venv = wrap_normalize(build_venv(env_id, hp, seed), hp, kwargs.get("gamma", 0.99))
        policy = kwargs.pop("policy", hp["policy"])
        model = algo_class[algo](policy, venv, seed=seed, device="cpu", verbose=args.verbose,
                                 tensorboard_log=str(run / "tb"), **kwargs)
        if args.resume:
            print(f"resuming {run}: no checkpoint yet, starting from step 0", flush=True)
    (run / "evaluations.json").write_text(json.dumps(clock["evaluations"], indent=1))

    callback = _callbacks(run, hp, env_id, env_kwargs, clock)
    previous = signal.signal(signal.SIGTERM, _sigterm_as_interrupt)
    interrupted = False
    try:
        # learn(0) still starts the callback (goal set, clock) when the run is already complete
        model.learn(max(total - model.num_timesteps, 0), callback=callback, reset_num_timesteps=False,
                    progress_bar=args.progress_bar, tb_log_name="run")
    except KeyboardInterrupt:
        interrupted = True
    finally:
        signal.signal(signal.SIGTERM, previous)
    if interrupted:
        path = callback.checkpoint()
        print(f"interrupted at step {model.num_timesteps}: checkpoint {path}; continue with "
              f"python -m train.train --resume --out {run}", flush=True)
        raise SystemExit(130)

    if not clock["evaluations"] or clock["evaluations"][-1]["steps"] != model.num_timesteps:
        callback._evaluate()
    callback.checkpoint()
    wall = clock["elapsed"] + time.perf_counter() - clock["start"]
    model.save(run / "model.zip")
    if model.get_vec_normalize_env() is not None:
        model.get_vec_normalize_env().save(str(run / "vecnormalize.pkl"))
    from iiwa_torch.runtime import machine_info

    info = {
        "num_timesteps": int(model.num_timesteps),
        "wall_time": round(wall, 1),
        "steps_per_second": round(model.num_timesteps / wall, 1),
        "final_evaluation": clock["evaluations"][-1] if clock["evaluations"] else None,
        "finished": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": machine_info(),
        "python": sys.version.split()[0],
    }
    (run / "train_info.json").write_text(json.dumps(info, indent=1))
    print(f"done: {model.num_timesteps} steps in {wall:.0f}s; model in {run / 'model.zip'}", flush=True)
    return run


def main(argv: list[str] | None = None) -> int:
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.timesteps is not None and (args.timesteps <= 0 or int(args.timesteps) != args.timesteps):
        parser.error(f"--timesteps must be a positive integer, got {args.timesteps:g}")
    if args.n_envs is not None and args.n_envs < 1:
        parser.error(f"--n-envs must be >= 1, got {args.n_envs}")
    try:
        train(args)
    except (ValueError, FileNotFoundError, FileExistsError) as err:
        parser.error(str(err))
    return 0


if __name__ == "__main__":
    sys.exit(main())
