"""Gymnasium reaching environments for any arm (the KUKA LBR iiwa, the Franka Panda), registered in one place.

``import envs`` registers the ids in :data:`ENV_IDS`; ``gymnasium.make("envs:IiwaReach-v0")``
imports this package itself. ``gymnasium.make_vec(id, num_envs=N)`` returns the natively
batched :class:`envs.reach.IiwaReachVectorEnv`; ``envs.sb3.IiwaReachVecEnv`` is the
stable-baselines3 ``VecEnv``; :func:`make_task` gives an id's task alone.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from iiwa_torch.checks import require

if TYPE_CHECKING:
    from .core import ReachTask

gymnasium = require("gymnasium", "rl")  # first: every module here imports it

__all__ = ["ENV_IDS", "MAX_EPISODE_STEPS", "PANDA_HOME", "register_envs", "make_task", "registered_options"]

#: Episode length of the registered ids: from the home posture, a straight full-speed joint
#: move reaches any configuration within the limits in 48 steps (see ``docs/envs.md``).
MAX_EPISODE_STEPS = 50

#: panda-gym's neutral posture of the Panda (rad), the home of the ``Franka*`` ids (their
#: ``robot="panda"``: pybullet_data's URDF, its end effector between the fingertips).
PANDA_HOME = (0.0, 0.41, 0.0, -1.85, 0.0, 2.26, 0.79)
_PANDA = {"robot": "panda", "home": PANDA_HOME}

_VARIANTS = {
    "IiwaReach-v0": {"goal": "position", "reward": "dense"},
    "IiwaReachSparse-v0": {"goal": "position", "reward": "sparse"},
    "IiwaReachPose-v0": {"goal": "pose", "reward": "dense"},
    "IiwaReachObstacles-v0": {"goal": "position", "reward": "dense", "obstacles": 4},
    "FrankaReach-v0": {**_PANDA, "goal": "position", "reward": "dense"},
    "FrankaReachPose-v0": {**_PANDA, "goal": "pose", "reward": "dense"},
    # panda-gym's PandaReach-v3 task: goals in its box, success within 5 cm, sparse reward (50 steps as all)
    "FrankaReachPandaGym-v0": {**_PANDA, "goal_region": "panda_gym", "distance_threshold": 0.05, "reward": "sparse"},
}

#: Every registered environment id.
ENV_IDS = tuple(_VARIANTS)


def register_envs() -> None:
    """Register :data:`ENV_IDS` with gymnasium (idempotent: ids already registered are kept)."""
    for env_id, kwargs in _VARIANTS.items():
        if env_id in gymnasium.registry:
            continue
        gymnasium.register(
            id=env_id,
            entry_point="envs.reach:IiwaReachEnv",
            vector_entry_point="envs.reach:IiwaReachVectorEnv",
            max_episode_steps=MAX_EPISODE_STEPS,
            kwargs=dict(kwargs),
        )


def registered_options(env_id: str) -> dict:
    """The ``ReachTask`` options ``env_id`` (one of :data:`ENV_IDS`) is registered with."""
    if env_id not in _VARIANTS:
        raise ValueError(f"env_id must be one of {list(ENV_IDS)}, got {env_id!r}")
    return dict(_VARIANTS[env_id])


def make_task(env_id: str, **env_kwargs) -> ReachTask:
    """The :class:`envs.core.ReachTask` of ``env_id`` (one of :data:`ENV_IDS`): the id's
    registered options and ``max_episode_steps``, overridden by ``env_kwargs`` (any
    ``ReachTask`` option), without building an env."""
    from .core import ReachTask

    return ReachTask(**{**registered_options(env_id), "max_episode_steps": MAX_EPISODE_STEPS, **env_kwargs})


register_envs()
