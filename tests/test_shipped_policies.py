"""Every shipped policy loads and runs the way a user would run it: the SB3 class's ``load`` on its
``model.zip`` alone (with ``vecnormalize.pkl``, the documented loader ``train.evaluate.load_policy``
and the normaliser's ``normalize_obs``), and ``gym.make`` of its registered id with the env kwargs
its ``config.yaml`` records (the env it was trained in)."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
import yaml

import envs

POLICIES = Path(__file__).resolve().parents[1] / "train" / "policies"
SHIPPED = sorted(p for p in POLICIES.iterdir() if (p / "model.zip").is_file())
GOALS = 8


def test_there_are_shipped_policies():
    assert {p.name for p in SHIPPED} >= {"ppo_iiwa_reach", "ppo_iiwa_reach_pose", "ppo_iiwa_reach_obstacles",
                                         "ppo_iiwa_reach_mlp"}


@pytest.mark.parametrize("policy_dir", SHIPPED, ids=lambda p: p.name)
def test_shipped_policy_runs_on_its_registered_env(policy_dir):
    from stable_baselines3 import PPO, SAC

    config = yaml.safe_load((policy_dir / "config.yaml").read_text())
    assert config["env_id"] in envs.ENV_IDS
    model = {"ppo": PPO, "sac": SAC}[config["algo"]].load(policy_dir / "model.zip", device="cpu")
    normalise = lambda obs: obs  # noqa: E731
    if (policy_dir / "vecnormalize.pkl").exists():
        from train.evaluate import load_policy

        _, vec_normalize, _ = load_policy(policy_dir)
        normalise = vec_normalize.normalize_obs
    env = gym.make(config["env_id"], **(config["hyperparams"].get("env_kwargs") or {}))
    assert env.observation_space == model.observation_space and env.action_space == model.action_space
    reached = 0
    for k in range(GOALS):
        obs, info = env.reset(seed=5000 + k)
        for _ in range(envs.MAX_EPISODE_STEPS):
            action, _ = model.predict(normalise(obs), deterministic=True)
            assert env.action_space.contains(action.astype(env.action_space.dtype))
            obs, _, terminated, truncated, info = env.step(action)
            assert not info.get("collision", False), (policy_dir.name, k)
            if terminated or truncated:
                break
        # positions are the first three entries of both goal encodings (position and pose)
        reached += np.linalg.norm(obs["achieved_goal"][:3] - obs["desired_goal"][:3]) < 0.01
    # held-out success at 1 cm is 89-100% for the shipped policies (their reports): 6 of 8 at least
    assert reached >= 6, (policy_dir.name, reached)
    env.close()




def _episodes(config: dict, act, seeds, dtype) -> tuple[list, list]:
    """Every observation and action of the single env's episodes from ``seeds`` under ``act``, the
    env's state in ``dtype``."""
    env = gym.make(config["env_id"], **(config["hyperparams"].get("env_kwargs") or {}), dtype=dtype)
    observations, actions = [], []
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        for _ in range(envs.MAX_EPISODE_STEPS):
            observations.append(obs)
            actions.append(act({k: v[None] for k, v in obs.items()})[0])
            obs, _, terminated, truncated, _ = env.step(actions[-1])
            if terminated or truncated:
                break
    env.close()
    return observations, actions


@pytest.mark.parametrize("dtype", ["float64", "float32"])
@pytest.mark.parametrize("name", ["ppo_iiwa_reach", "ppo_iiwa_reach_pose", "ppo_iiwa_reach_obstacles"])
def test_one_env_rollouts_equal_those_of_the_batched_paths(name, dtype, monkeypatch, small_kernel):
    """One env's step and the policy on one observation take the small-batch paths (the clearance
    rows' closed-form gradients in float64, the features extractor compiled or in numpy: ``small_kernel``,
    the action head in numpy).
    The same episodes on the batched paths (the clearance of a batch of two copies, by autograd in
    the state's dtype; the network in torch): with a float64 state every observation and action
    agrees to 1e-12; with the default float32 state the first observation to float32 rounding and
    the rest, where the policy feeds those roundings back over 50 steps, to 1e-4 (measured: 7e-6). A head
    that projects every action (``keep_progress``: Hildreth's float32 sums, in another order on each
    path) feeds back float32 rounding with a float64 state too: 1e-4 after the first observation
    (measured: 2.7e-5)."""
    import envs.core
    import train.features
    from iiwa_torch import collision
    from train.evaluate import load_policy
    from train.rollout import policy_actor

    model, vec_normalize, config = load_policy(POLICIES / name)
    act = policy_actor(model, vec_normalize)
    seeds, state_dtype = (11, 12, 13), getattr(torch, dtype)
    fast = _episodes(config, act, seeds, state_dtype)

    def batched_clearance(chain, q, world=None, capsules=None):
        distance, gradient = collision.capsule_clearance(chain, q.expand(2, *q.shape[1:]), world, capsules)
        return distance[:1], gradient[:1]

    monkeypatch.setattr(envs.core, "capsule_clearance", batched_clearance)
    monkeypatch.setattr(train.features, "NUMPY_ROWS", 0)
    slow = _episodes(config, act, seeds, state_dtype)
    assert len(fast[1]) == len(slow[1]) >= len(seeds) * 10
    first, rest = (1e-12, 1e-12) if dtype == "float64" else (1e-6, 1e-4)
    if getattr(model.policy, "keep_progress", False):  # a projection at every step: float32 sums' rounding
        rest = 1e-4
    for step, (a, b) in enumerate(zip(fast[0], slow[0])):
        for key in a:
            np.testing.assert_allclose(a[key], b[key], rtol=0, atol=first if step == 0 else rest)
    np.testing.assert_allclose(np.stack(fast[1]), np.stack(slow[1]), rtol=0, atol=rest)
