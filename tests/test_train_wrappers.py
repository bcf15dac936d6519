"""The reward wrappers of train/wrappers.py."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from envs.sb3 import IiwaReachVecEnv  # noqa: E402
from train.wrappers import ClearancePenalty  # noqa: E402

N = 64


def _pair(env_id: str, **kwargs):
    """Two identical VecEnvs (same seeds), one wrapped."""
    raw = IiwaReachVecEnv(N, env_id, seed=3, start="random", **kwargs)
    wrapped = ClearancePenalty(IiwaReachVecEnv(N, env_id, seed=3, start="random", **kwargs), margin=0.05, weight=0.3)
    return raw, wrapped


@pytest.mark.parametrize("env_id", ["IiwaReach-v0", "IiwaReachObstacles-v0"])
def test_penalty_is_full_on_the_steps_the_env_flags_as_collisions_and_zero_far_from_everything(env_id):
    raw, wrapped = _pair(env_id)
    raw.reset(), wrapped.reset()
    rng = np.random.default_rng(0)
    hits = clear = partial = 0
    for _ in range(60):
        action = rng.uniform(-1, 1, (N, 7)).astype(np.float32)
        raw.step_async(action), wrapped.step_async(action)
        _, r0, done, infos = raw.step_wait()
        _, r1, _, _ = wrapped.step_wait()
        penalty = (r0.astype(np.float64) - r1) / 0.3
        collision = np.array([i["collision"] for i in infos])
        # the env's own flag (its clearance of the state's q) against the wrapper's, read from
        # the observation (the last one of an episode that ended)
        np.testing.assert_allclose(penalty[collision], 1.0, atol=1e-6)
        assert (penalty[~collision] < 1.0).all()
        assert (penalty >= -1e-6).all()
        hits += collision.sum()
        clear += (np.abs(penalty) < 1e-6).sum()
        partial += ((penalty > 1e-3) & (penalty < 1 - 1e-3)).sum()
    assert hits > 0 and clear > 0 and partial > 0  # every regime was seen


def test_bad_arguments_are_rejected():
    with pytest.raises(ValueError, match="collision checks"):
        ClearancePenalty(IiwaReachVecEnv(2, "IiwaReach-v0", collision="off"))
    for bad in ({"margin": 0.0}, {"weight": -1.0}, {"margin": True}):
        with pytest.raises(ValueError, match="positive number"):
            ClearancePenalty(IiwaReachVecEnv(2, "IiwaReach-v0"), **bad)


@pytest.mark.parametrize("key", ["log_distance_bonus", "clearance_penalty"])
def test_reward_terms_are_refused_with_her(key):
    from train.train import algo_kwargs

    with pytest.raises(ValueError, match=f"{key} cannot be combined with her"):
        algo_kwargs("sac", {"her": {"n_sampled_goal": 4}, key: {}})
