"""The SB3 callback of ``train.train``: periodic evaluation and checkpoints on one training clock."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

from train.rollout import PolicyEvaluator, make_goal_set, summarise_finals
from train.run_dir import RunDir

EVAL_SEED = 10_000  # goal-set seed of the periodic evaluation; train.evaluate defaults to another


@dataclass
class TrainClock:
    """Training wall time across resumes (s) and the evaluations so far."""

    elapsed: float = 0.0  # seconds trained before this process started
    evaluations: list[dict[str, Any]] = field(default_factory=list)
    start: float = field(default_factory=time.perf_counter)

    def wall(self) -> float:
        return self.elapsed + time.perf_counter() - self.start


def improves(entry: dict[str, Any], best: dict[str, Any] | None) -> bool:
    """True if evaluation ``entry`` beats ``best`` (None: nothing yet): higher success, or the same
    success and a lower median final distance. Success is ``success_collision_free`` when the entry
    has it (an env that checks collisions); a best recorded without it (a run resumed across this
    change) is compared by its ``success``, an upper bound of its collision-free success."""
    if best is None:
        return True
    key = "success_collision_free" if "success_collision_free" in entry else "success"
    return (entry[key], -entry["median_distance"]) > (best.get(key, best["success"]), -best["median_distance"])


class EvalAndCheckpoint(BaseCallback):
    """Every ``eval_freq`` env steps: success on a fixed goal set, and the model saved as the run's
    best when it improves (``improves``); every ``checkpoint_freq``: a checkpoint."""

    def __init__(self, run: RunDir, hp: dict[str, Any], env_id: str, env_kwargs: dict[str, Any],
                 clock: TrainClock, verbose: int = 1):
        super().__init__(verbose=verbose)
        self.run, self.hp, self.env_id, self.env_kwargs, self.clock = run, hp, env_id, env_kwargs, clock
        self.evaluator, self.task = None, None
        best = run.read_best()  # after --resume: the best so far, possibly from past the resumed checkpoint
        self.best = None if best is None else best["evaluation"]

    def _on_training_start(self) -> None:
        import envs

        env_id, env_kwargs, hp = self.env_id, self.env_kwargs, self.hp
        if env_id in envs.ENV_IDS:
            self.task = envs.make_task(env_id, **env_kwargs)
            pose = self.task.goal_kind.value == "pose"
            self.evaluator = PolicyEvaluator(make_goal_set(env_id, hp["eval_goals"], EVAL_SEED, env_kwargs),
                                             self.task.distance_threshold,
                                             self.task.orientation_threshold if pose else None)
        self.next_eval = (self.num_timesteps // hp["eval_freq"] + 1) * hp["eval_freq"]
        self.next_ckpt = (self.num_timesteps // hp["checkpoint_freq"] + 1) * hp["checkpoint_freq"]
        if not self.clock.evaluations:
            self.evaluate()

    def _other_env_metrics(self) -> tuple[dict[str, float], float]:
        """Another goal env (e.g. panda-gym): ``eval_goals`` seeded episodes, as it defines them."""
        from train.vec_env import make_env

        start = time.perf_counter()
        vec_normalize = self.model.get_vec_normalize_env()
        env = make_env(self.env_id, 1, EVAL_SEED, self.env_kwargs)
        obs, final = env.reset(), []
        while len(final) < self.hp["eval_goals"]:
            if vec_normalize is not None:
                obs = vec_normalize.normalize_obs(obs)
            action, _ = self.model.predict(obs, deterministic=True)
            obs, _, done, infos = env.step(action)
            if done[0]:
                last = infos[0]["terminal_observation"]
                final.append(float(np.linalg.norm(last["achieved_goal"] - last["desired_goal"])))
        threshold = float(env.get_attr("unwrapped")[0].task.distance_threshold)  # panda-gym's task attribute
        env.close()
        return summarise_finals(np.array(final), threshold), time.perf_counter() - start

    def evaluate(self) -> dict[str, Any]:
        """Evaluate now; append to the clock's evaluations, ``evaluations.json`` and TensorBoard."""
        wall = self.clock.wall()
        metrics, seconds = self.evaluator(self.model, self.model.get_vec_normalize_env()) if self.evaluator \
            else self._other_env_metrics()
        entry = {"steps": int(self.num_timesteps), "wall_time": round(wall, 2), **metrics,
                 "eval_seconds": round(seconds, 3), "loadavg": os.getloadavg()[0]}
        self.clock.evaluations.append(entry)
        self.run.write_json("evaluations.json", self.clock.evaluations)
        new_best = improves(entry, self.best)
        if new_best:
            self.run.save_best(self.model, entry)
            self.best = entry
        for key in ("success", "median_distance", "p95_distance", "collisions", "success_collision_free"):
            if key in entry:
                self.logger.record(f"eval/{key}", entry[key])
        if self.verbose:
            collisions = f" collisions={entry['collisions']:.3f} collision-free success=" \
                f"{entry['success_collision_free']:.3f}" if "collisions" in entry else ""
            print(f"[eval] steps={entry['steps']} wall={entry['wall_time']:.0f}s success={entry['success']:.3f} "
                  f"median={1000 * entry['median_distance']:.1f}mm p95={1000 * entry['p95_distance']:.1f}mm"
                  f"{collisions}{' (best so far: saved)' if new_best else ''}", flush=True)
        return entry

    def checkpoint(self) -> Path:
        state = {"num_timesteps": int(self.model.num_timesteps), "elapsed": self.clock.wall(),
                 "evaluations": self.clock.evaluations}
        return self.run.save_checkpoint(self.model, state)

    def _on_step(self) -> bool:
        if self.num_timesteps >= self.next_eval:
            self.next_eval += self.hp["eval_freq"]
            self.evaluate()
        if self.num_timesteps >= self.next_ckpt:
            self.next_ckpt += self.hp["checkpoint_freq"]
            self.checkpoint()
        return True
