"""The SB3 vector envs training runs on: the batched env of our ids (one torch step for every arm),
SB3's ``make_vec_env`` for any other gymnasium id, with monitoring, the optional reward terms
and observation normalisation. Used by the trainer, its evaluation callback and ``train.evaluate``."""

from __future__ import annotations

import importlib
from typing import Any

__all__ = ["build_venv", "make_env", "wrap_normalize"]


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
    hyper-parameters ask, the ``LogDistanceBonus`` and ``ClearancePenalty`` reward terms (before any
    normalisation)."""
    from stable_baselines3.common.vec_env import VecMonitor

    from train.wrappers import ClearancePenalty, LogDistanceBonus

    venv = VecMonitor(make_env(env_id, hp["n_envs"], seed, hp.get("env_kwargs")))
    for key, wrapper in (("log_distance_bonus", LogDistanceBonus), ("clearance_penalty", ClearancePenalty)):
        options = hp.get(key)
        if options is None:
            continue
        if not isinstance(options, dict):
            raise ValueError(f"{key} must be a mapping of its options, got {options!r}")
        try:
            venv = wrapper(venv, **options)
        except (TypeError, ValueError) as err:  # the option's own message, said as whose it is
            raise ValueError(f"{key}: {err}") from None
    return venv


def wrap_normalize(venv, hp: dict[str, Any], gamma: float):
    """VecNormalize on the ``observation`` key (goals stay in metres for the goal-delta features)."""
    from stable_baselines3.common.vec_env import VecNormalize

    if not hp.get("normalize", False):
        return venv
    return VecNormalize(venv, norm_obs_keys=["observation"], norm_reward=False, gamma=gamma)
