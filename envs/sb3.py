"""A stable-baselines3 ``VecEnv`` over the batched iiwa reaching task (no per-env Python step).

stable-baselines3 does not accept gymnasium ``VectorEnv`` s, so this implements SB3's own
``VecEnv`` contract (``stable_baselines3/common/vec_env/base_vec_env.py``) over the same pure
step as :class:`envs.reach.IiwaReachVectorEnv`: one batched torch call and one transfer to
numpy per step, same-step auto-reset with ``infos[i]["terminal_observation"]`` and
``infos[i]["TimeLimit.truncated"]`` as ``DummyVecEnv`` gives, and
``env_method("compute_reward", ...)`` for ``HerReplayBuffer``.

Example::

    from stable_baselines3 import SAC, HerReplayBuffer
    from envs.sb3 import IiwaReachVecEnv

    env = IiwaReachVecEnv(64, "IiwaReachSparse-v0", seed=0)
    model = SAC("MultiInputPolicy", env, replay_buffer_class=HerReplayBuffer)
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium
import numpy as np
import torch

from iiwa_torch.checks import is_integer, require

from . import MAX_EPISODE_STEPS, make_task
from .core import ReachState
from .goals import GoalKind
from .reach import goal_env_spaces
from .seeding import keys_from_seeds

__all__ = ["IiwaReachVecEnv"]

_base_vec_env = require("stable_baselines3.common.vec_env.base_vec_env", "rl")
VecEnv, VecEnvIndices = _base_vec_env.VecEnv, _base_vec_env.VecEnvIndices


class IiwaReachVecEnv(VecEnv):
    """``num_envs`` iiwa reaching tasks as a stable-baselines3 ``VecEnv``.

    Args:
        num_envs: number of environments.
        env_id: one of :data:`envs.ENV_IDS`, whose registered options (goal, reward) are the
            defaults; ``task_options`` override them.
        seed: seeds environment ``i`` with ``seed + i`` at the first ``reset()`` (like
            ``VecEnv.seed``); ``None``: random.
        device: torch device of the batched state (``"cpu"`` by default).
        max_episode_steps: truncation (default 50, as the registered ids).
        render_mode: ``None`` or ``"rgb_array"`` (one image per environment, tiled by SB3).
        **task_options: any option of :class:`envs.core.ReachTask` (``dt``,
            ``distance_threshold``, ``start``, ``goal_min_distance``, ...).

    All environments share one task, so ``get_attr`` returns the same value for every
    index, ``set_attr`` sets it for all (a subset of indices is an error) and
    ``env_method`` calls the shared method once per index. Each ``infos[i]`` holds
    ``is_success``, ``distance`` (m), ``TimeLimit.truncated`` and, for pose goals,
    ``orientation_error`` (rad); finished environments also get ``terminal_observation``.
    """

    def __init__(
        self,
        num_envs: int,
        env_id: str = "IiwaReach-v0",
        *,
        seed: int | None = None,
        device: torch.device | str | None = None,
        max_episode_steps: int | None = MAX_EPISODE_STEPS,
        render_mode: str | None = None,
        **task_options: Any,
    ) -> None:
        if not is_integer(num_envs) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive int, got {num_envs!r}")
        if render_mode is not None and render_mode != "rgb_array":
            raise ValueError(f"render_mode must be 'rgb_array' or None, got {render_mode!r}")
        self.task = make_task(env_id, max_episode_steps=max_episode_steps, device=device, **task_options)
        self.env_id = env_id
        self.render_mode = render_mode  # read by VecEnv.__init__ through get_attr
        observation_space, action_space = goal_env_spaces(self.task)
        super().__init__(int(num_envs), observation_space, action_space)
        self._state: ReachState | None = None
        self._actions: torch.Tensor | None = None
        if seed is not None:
            keys_from_seeds([seed])  # our check and message first (numpy's rng also takes the seed)
        self._rng = np.random.default_rng(seed)  # only for unseeded resets
        if seed is not None:
            self.seed(seed)

    # ------------------------------------------------------------------ stepping
    @torch.inference_mode()
    def reset(self):
        """Reset every environment (with the seeds of ``seed()``, if any, used once)."""
        if any(self._options):
            raise ValueError(f"IiwaReachVecEnv.reset takes no options, got {self._options[0]!r}")
        self._state = self.task.reset_all(self._state, self._seeds, self._rng)
        self._reset_seeds()
        self._reset_options()
        tr = self.task.reset_transition(self._state)
        self.reset_infos = [{"is_success": s, "distance": d} for s, d in zip(tr.success.tolist(), tr.distance.tolist())]
        if tr.collision is not None:
            for info, hit in zip(self.reset_infos, tr.collision.tolist()):
                info["collision"] = hit
        return tr.obs

    def step_async(self, actions: np.ndarray) -> None:
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        self._actions = self.task.transport.check_action(actions, self.num_envs)

    @torch.inference_mode()
    def step_wait(self):
        self._state, tr = self.task.step_autoreset(self._state, self._actions)
        # dict literals: 3x faster than dict(zip(...)) per environment (measured at N = 4,096)
        rows = zip(tr.success.tolist(), tr.distance.tolist(), (tr.truncated & ~tr.terminated).tolist())
        infos = [{"is_success": s, "distance": d, "TimeLimit.truncated": t} for s, d, t in rows]
        if self.task.goal_kind is GoalKind.POSE:
            for info, angle in zip(infos, tr.angle.tolist()):
                info["orientation_error"] = angle
        if tr.collision is not None:
            for info, hit in zip(infos, tr.collision.tolist()):
                info["collision"] = hit
        finished = self.task.transport.obs_per_env(tr.final_obs)  # finished environments only
        for i, last in zip(tr.final_index.tolist(), finished):
            infos[i]["terminal_observation"] = last
        return tr.obs, tr.reward, tr.terminated | tr.truncated, infos

    def compute_reward(self, achieved_goal, desired_goal, info=None):
        """Batched reward: goals ``(..., g)``, numpy or torch -> ``(...)`` float32 numpy; the collision
        penalty is taken from ``info`` (per-env dicts, as HER passes them;
        :meth:`envs.core.ReachTask.compute_reward`)."""
        return self.task.compute_reward(achieved_goal, desired_goal, info)

    def close(self) -> None:
        self._state = None

    # ------------------------------------------------------------------ the VecEnv attribute API
    def _get_indices(self, indices: VecEnvIndices) -> list[int]:
        """SB3's, checked: an index beyond the environments is an ``IndexError`` (SB3 lists it anyway)."""
        chosen = list(super()._get_indices(indices))
        if any(not -self.num_envs <= i < self.num_envs for i in chosen):
            raise IndexError(f"indices {chosen} out of range for {self.num_envs} environments")
        return chosen

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        value = getattr(self, attr_name)  # AttributeError if missing, as VecEnv.has_attr expects
        return [value for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        if sorted(self._get_indices(indices)) != list(range(self.num_envs)):
            raise ValueError("the environments share one task: set_attr must target all of them (indices=None)")
        setattr(self, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices: VecEnvIndices = None, **method_kwargs) -> list[Any]:
        method = getattr(self, method_name)
        return [method(*method_args, **method_kwargs) for _ in self._get_indices(indices)]

    def env_is_wrapped(self, wrapper_class: type[gymnasium.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    def get_images(self) -> Sequence[np.ndarray | None]:
        """One ``(H, W, 3)`` image per environment (slow for many environments)."""
        if self.render_mode != "rgb_array" or self._state is None:
            return [None for _ in range(self.num_envs)]
        from iiwa_torch.viz import render_rgb

        state = self._state
        return [render_rgb(self.task.robot, q, goal=g[:3]) for q, g in zip(state.q.T, state.goal.T)]
