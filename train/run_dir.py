"""One training run's directory: its config, checkpoints, evaluations and lock.

Guarantees (see docs/training.md, "Run-directory guarantees"):

- every file is written to a temporary name and renamed with ``os.replace``, and a checkpoint
  folder is filled under a temporary name and renamed, so a kill during a save leaves the
  previous file (or checkpoint) intact, never a half-written one under the final name;
- ``RunDir.lock`` holds an exclusive ``fcntl.flock`` on ``.lock`` while a process trains: a
  second process is refused (``RunLocked``); the kernel drops the lock when its holder dies, so
  a lock file left by a killed run does not block;
- ``RunDir.checkpoints`` lists complete checkpoints newest first; the caller loads the newest
  one whose files all load (``CheckpointError`` names a bad file);
- ``RunDir.save_best`` keeps the best model of the periodic evaluation in ``best/step_<N>`` and
  ``best.json`` (its folder and evaluation), replaced atomically in that order.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import shutil
import signal
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import yaml

ALGOS = ("ppo", "sac")
CONFIG_KEYS = ("algo", "env_id", "seed", "hyperparams")
LOCK_NAME = ".lock"
BEST_NAME = "best.json"


class RunLocked(RuntimeError):
    """Another live process trains in this run directory."""


class CheckpointError(ValueError):
    """A checkpoint or model file that cannot be loaded (the message names the file)."""


def atomic_save(path: Path, save: Callable[[Path], Any]) -> None:
    """``save(tmp)`` writes the file at a temporary name next to ``path``, then it replaces ``path``."""
    path = Path(path)
    tmp = path.with_name(f".tmp_{os.getpid()}_{path.name}")
    try:
        save(tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


@contextlib.contextmanager
def signals_held() -> Iterator[None]:
    """Ctrl-C (SIGINT) and SIGTERM held while the block runs (a save) and delivered when it ends: an
    interrupt raised inside torch's zip writer (C++) aborts the process instead of stopping the run
    with its checkpoint. Signals reach only the main thread, so elsewhere this holds nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    held = (signal.SIGINT, signal.SIGTERM)
    previous = {s: signal.signal(s, lambda signum, frame: caught.append(signum)) for s in held}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        if caught:
            signal.raise_signal(caught[0])


def atomic_write_text(path: Path, text: str) -> None:
    atomic_save(path, lambda tmp: tmp.write_text(text))


def check_folder(path: Path, flag: str = "--out") -> None:
    """Raise ValueError if ``path`` or a folder above it is a file, so that ``path`` cannot be a folder."""
    blocking = next((p for p in (path, *path.parents) if p.exists() and not p.is_dir()), None)
    if blocking is not None:
        raise ValueError(f"{flag} {path}: {blocking} is a file, not a folder; pick another {flag}")


def validate_config(config: Any, source: str) -> dict[str, Any]:
    """A run's config dict checked for the keys and values ``train.train`` and ``train.evaluate`` read."""
    from iiwa_torch.checks import check_bool  # here: torch only after main has set OpenMP's wait policy

    if not isinstance(config, dict):
        raise ValueError(f"{source}: expected a mapping with keys {list(CONFIG_KEYS)}, got {type(config).__name__}")
    missing = [k for k in CONFIG_KEYS if k not in config]
    if missing:
        raise ValueError(f"{source}: missing key(s) {missing}; a train.train config has {list(CONFIG_KEYS)}")
    if config["algo"] not in ALGOS:
        raise ValueError(f"{source}: algo must be one of {list(ALGOS)}, got {config['algo']!r}")
    hp = config["hyperparams"]
    if not isinstance(hp, dict) or not isinstance(hp.get("n_timesteps"), int) or not isinstance(hp.get("n_envs"), int):
        raise ValueError(f"{source}: hyperparams must be a mapping with integer n_timesteps and n_envs, got {hp!r}")
    check_bool(hp.get("normalize", False), f"{source}: normalize")
    return config


def read_yaml(path: Path) -> Any:
    """The parsed YAML file; a parse error becomes a one-line ValueError naming the file and the place."""
    try:
        return yaml.safe_load(Path(path).read_text())
    except yaml.YAMLError as err:
        where = getattr(err, "problem_mark", None)
        at = f" at line {where.line + 1}, column {where.column + 1}" if where is not None else ""
        raise ValueError(f"{path}: not valid YAML{at} ({getattr(err, 'problem', None) or err})") from None


def _space_shapes(space) -> Any:
    spaces = getattr(space, "spaces", None)
    if isinstance(spaces, dict):
        return {k: _space_shapes(v) for k, v in spaces.items()}
    return tuple(space.shape or ())


def check_model(algo: str, path: Path, observation_space=None, action_space=None) -> None:
    """Raise if ``path`` is not a readable SB3 ``algo`` model for these spaces (when given)."""
    from stable_baselines3 import PPO, SAC
    from stable_baselines3.common.save_util import load_from_zip_file

    cls = {"ppo": PPO, "sac": SAC}[algo]
    try:
        data, _, _ = load_from_zip_file(path, device="cpu", print_system_info=False)
    except Exception as err:  # a truncated or foreign file fails in zipfile, json or torch: all mean "unreadable"
        raise CheckpointError(f"{path} is unreadable (not an SB3 model: {type(err).__name__}: {err})") from None
    policy = data.get("policy_class") if data else None
    if not isinstance(policy, type):  # SB3 leaves a dict where it could not unpickle the class
        raise CheckpointError(f"{path} is unreadable (not an SB3 model: no loadable policy class in its data)")
    if not issubclass(policy, tuple(cls.policy_aliases.values())):
        raise ValueError(f"{path} holds a {policy.__module__}.{policy.__qualname__} policy, which is not a "
                         f"{algo.upper()} policy: "
                         f"the config says algo: {algo}")
    for key, space in (("observation_space", observation_space), ("action_space", action_space)):
        if space is not None and _space_shapes(data[key]) != _space_shapes(space):
            raise ValueError(f"{path} was trained for another env: its {key} has shapes {_space_shapes(data[key])}, "
                             f"the env of the config has {_space_shapes(space)}")


class RunDir:
    """The directory ``path`` of one training run (see ``train.train`` for its layout)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self._lock_file = None

    def __repr__(self) -> str:
        return f"RunDir({str(self.path)!r})"

    @property
    def config_path(self) -> Path:
        return self.path / "config.yaml"

    @property
    def checkpoint_root(self) -> Path:
        return self.path / "checkpoints"

    def is_empty(self) -> bool:
        """True if the directory is missing or holds nothing but a lock file and the temporary files of
        writes cut short (a kill during the first ``config.yaml`` write leaves only those)."""
        return not self.path.exists() or all(p.name == LOCK_NAME or p.name.startswith(".tmp_")
                                             for p in self.path.iterdir())

    # -------------------------------------------------------------------- config and evaluations
    def read_config(self) -> dict[str, Any]:
        if not self.config_path.exists():
            hint = (" (its first write was cut short: nothing was trained; start the run again without --resume)"
                    if self.path.is_dir() and self.is_empty() else f"; is {self.path} a train.train run directory?")
            raise FileNotFoundError(f"{self.config_path} not found{hint}")
        return validate_config(read_yaml(self.config_path), str(self.config_path))

    def write_config(self, config: dict[str, Any]) -> None:
        atomic_write_text(self.config_path, yaml.safe_dump(config, sort_keys=False))

    def write_json(self, name: str, value: Any) -> None:
        atomic_write_text(self.path / name, json.dumps(value, indent=1))

    def read_evaluations(self) -> list[dict[str, Any]]:
        path = self.path / "evaluations.json"
        if not path.exists():
            return []
        try:
            return json.loads(path.read_text())
        except json.JSONDecodeError as err:
            raise ValueError(f"{path}: not valid JSON ({err}); expected the list train.train writes") from None

    # -------------------------------------------------------------------- lock
    @contextlib.contextmanager
    def lock(self) -> Iterator[None]:
        """Hold the run's exclusive lock for the ``with`` block; ``RunLocked`` if a live process holds it."""
        self.path.mkdir(parents=True, exist_ok=True)
        f = open(self.path / LOCK_NAME, "a+")
        try:
            try:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                f.seek(0)
                holder = f.read().strip() or "another process"
                raise RunLocked(f"{self.path} is in use by {holder}: wait for it to finish (or stop it), "
                                f"or pick another --out") from None
            f.seek(0)
            f.truncate()
            f.write(f"pid {os.getpid()}")
            f.flush()
            yield
        finally:
            f.close()  # closing the descriptor releases the flock

    # -------------------------------------------------------------------- checkpoints
    def checkpoints(self) -> list[Path]:
        """Complete checkpoint folders (``state.json`` present), newest first."""
        found = [p for p in self.checkpoint_root.glob("step_*") if (p / "state.json").exists()]
        return sorted(found, reverse=True)

    def latest_checkpoint(self) -> Path | None:
        found = self.checkpoints()
        return found[0] if found else None

    def _save_folder(self, model, final: Path, state: dict[str, Any], replay_buffer: bool) -> None:
        """Model, normaliser, replay buffer (if asked and off-policy) and ``state.json`` into the folder
        ``final``, filled under a temporary name next to it and renamed."""
        tmp = final.with_name(f".tmp_{final.name}")
        for stale in final.parent.glob(".tmp_*"):  # saves cut short; only the lock holder saves
            shutil.rmtree(stale, ignore_errors=True)
        with signals_held():
            tmp.mkdir(parents=True)
            model.save(tmp / "model.zip")
            vec_normalize = model.get_vec_normalize_env()
            if vec_normalize is not None:
                vec_normalize.save(str(tmp / "vecnormalize.pkl"))
            if replay_buffer and getattr(model, "replay_buffer", None) is not None:
                model.save_replay_buffer(tmp / "replay_buffer.pkl")
            (tmp / "state.json").write_text(json.dumps(state, indent=1))  # last: marks the folder complete
            for f in tmp.iterdir():
                with open(f, "rb") as fh:
                    os.fsync(fh.fileno())
            shutil.rmtree(final, ignore_errors=True)
            os.replace(tmp, final)

    def save_checkpoint(self, model, state: dict[str, Any], keep: int = 2) -> Path:
        """Model, normaliser, replay buffer (off-policy) and ``state.json`` into ``checkpoints/step_<N>``,
        filled under a temporary name and renamed; keeps the ``keep`` newest."""
        final = self.checkpoint_root / f"step_{model.num_timesteps:012d}"
        self._save_folder(model, final, state, replay_buffer=True)
        for old in self.checkpoints()[keep:]:
            shutil.rmtree(old, ignore_errors=True)
        return final

    # -------------------------------------------------------------------- best model
    @property
    def best_root(self) -> Path:
        return self.path / "best"

    def read_best(self) -> dict[str, Any] | None:
        """``{"checkpoint": folder relative to the run, "evaluation": the periodic evaluation that made
        it best}`` from ``best.json``, or None before the first evaluation."""
        path = self.path / BEST_NAME
        if not path.exists():
            return None
        try:
            best = json.loads(path.read_text())
        except json.JSONDecodeError as err:
            raise ValueError(f"{path}: not valid JSON ({err}); expected the record train.train writes") from None
        if not isinstance(best, dict) or not {"checkpoint", "evaluation"} <= set(best):
            raise ValueError(f"{path}: expected a mapping with keys checkpoint and evaluation, got {best!r}")
        return best

    def best_checkpoint(self) -> Path | None:
        """The folder of the best model so far (``model.zip``, ``vecnormalize.pkl`` if any, ``state.json``)."""
        best = self.read_best()
        return None if best is None else self.path / best["checkpoint"]

    def save_best(self, model, evaluation: dict[str, Any]) -> Path:
        """The model and normaliser as ``best/step_<N>``, then ``best.json`` pointing at it (an atomic
        replace: a kill at any moment leaves ``best.json`` naming a complete folder), then older folders go."""
        final = self.best_root / f"step_{model.num_timesteps:012d}"
        self._save_folder(model, final, {"evaluation": evaluation}, replay_buffer=False)
        self.write_json(BEST_NAME, {"checkpoint": str(final.relative_to(self.path)), "evaluation": evaluation})
        for old in self.best_root.glob("step_*"):
            if old != final:
                shutil.rmtree(old, ignore_errors=True)
        return final

    def save_final(self, model) -> None:
        """The finished run's ``model.zip`` (and ``vecnormalize.pkl``) next to ``config.yaml``."""
        with signals_held():
            atomic_save(self.path / "model.zip", model.save)
            vec_normalize = model.get_vec_normalize_env()
            if vec_normalize is not None:
                atomic_save(self.path / "vecnormalize.pkl", lambda tmp: vec_normalize.save(str(tmp)))
