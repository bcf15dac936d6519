"""``train.residual.ResidualDLSPolicy``: the action is the DLS step plus a gated correction, and a
saved model loads in a fresh process (the custom classes are found by their import path)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from train import train as tr
from train import vec_env

ROOT = Path(__file__).resolve().parents[1]
HP = {"features_extractor": "joint", "normalize": False, "policy": "ResidualDLSPolicy", "n_envs": 8,
      "n_steps": 8, "batch_size": 64, "policy_kwargs": {"net_arch": [16, 16], "gate_distance": 0.02}}


def _model():
    """The residual policy without the velocity damper (no clearance observed)."""
    from stable_baselines3 import PPO

    plain = {"env_kwargs": {"terminate_on_success": False},
             "features_extractor_kwargs": {"scales": [0.3, 0.03, 0.003], "dampings": [0.1, 0.01]}}
    hp = tr.load_hyperparams("ppo", "IiwaReach-v0", {**HP, **plain})
    kwargs = tr.algo_kwargs("ppo", hp)
    policy = kwargs.pop("policy")
    return PPO(policy, vec_env.build_venv("IiwaReach-v0", hp, 0), device="cpu", seed=0, **kwargs)


def test_action_is_dls_step_plus_gated_correction():
    """With the last layer's weights zero and bias c: mean = step + d / (d + 0.02) * c, d the goal distance."""
    model = _model()
    obs = model.env.reset()
    ext = model.policy.features_extractor
    x = {k: torch.as_tensor(v) for k, v in obs.items()}
    step = ext(x)[:, ext.step_columns[0] : ext.step_columns[1]].numpy()
    d = np.linalg.norm(obs["desired_goal"] - obs["achieved_goal"], axis=-1, keepdims=True)
    linear = model.policy.action_net.linear
    c = np.linspace(-0.5, 0.5, 7).astype(np.float32)
    with torch.no_grad():
        linear.weight.zero_()
        linear.bias.copy_(torch.from_numpy(c))
    mean = model.policy.get_distribution(model.policy.obs_to_tensor(obs)[0]).distribution.mean.detach().numpy()
    np.testing.assert_allclose(mean, step + d / (d + 0.02) * c, atol=1e-5)
    # on the goal the correction vanishes: the action is the DLS step alone (zero error: zero step)
    on_goal = {**obs, "desired_goal": obs["achieved_goal"].copy()}
    action, _ = model.predict(on_goal, deterministic=True)
    np.testing.assert_allclose(action, 0.0, atol=1e-6)


def test_saved_model_loads_and_acts_the_same_in_a_fresh_process(tmp_path):
    model = _model()
    model.save(tmp_path / "model.zip")
    obs = model.env.reset()
    np.savez(tmp_path / "obs.npz", **obs)
    expected, _ = model.predict(obs, deterministic=True)
    code = ("import sys, numpy as np; from stable_baselines3 import PPO; "
            "m = PPO.load(sys.argv[1] + '/model.zip', device='cpu'); o = dict(np.load(sys.argv[1] + '/obs.npz')); "
            "np.save(sys.argv[1] + '/act.npy', m.predict(o, deterministic=True)[0]); "
            "print(type(m.policy).__name__, m.policy.gate_distance)")
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path)], cwd=ROOT, capture_output=True, text=True,
                         env={"OMP_WAIT_POLICY": "PASSIVE", "PATH": "/usr/bin:/bin"}, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["ResidualDLSPolicy", "0.02"]
    np.testing.assert_array_equal(np.load(tmp_path / "act.npy"), expected)


def test_residual_policy_needs_the_joint_extractor_and_a_positive_gate():
    from stable_baselines3 import PPO

    hp = tr.load_hyperparams("ppo", "IiwaReach-v0", {**HP, "features_extractor": "goal_delta",
                                                          "features_extractor_kwargs": {"scales": [0.3]}})
    kwargs = tr.algo_kwargs("ppo", hp)
    policy = kwargs.pop("policy")
    with pytest.raises(ValueError, match="needs a shared JointGoalExtractor"):
        PPO(policy, vec_env.build_venv("IiwaReach-v0", hp, 0), device="cpu", **kwargs)
    with pytest.raises(ValueError, match="gate_distance must be a positive"):
        _bad = {**HP, "policy_kwargs": {"gate_distance": 0}}
        hp = tr.load_hyperparams("ppo", "IiwaReach-v0", _bad)
        kwargs = tr.algo_kwargs("ppo", hp)
        PPO(kwargs.pop("policy"), vec_env.build_venv("IiwaReach-v0", hp, 0), device="cpu", **kwargs)


def test_joint_features_need_raw_observations():
    with pytest.raises(ValueError, match="set normalize: false"):
        tr.load_hyperparams("ppo", "IiwaReach-v0", {**HP, "normalize": True})


def test_with_avoidance_the_whole_mean_keeps_the_damper_constraints():
    """A large learned correction cannot push the mean through the velocity damper: for every
    capsule near something, ``normal . mean >= bound`` (the constraints in actions the extractor
    computed from the env's observed clearances), and the mean stays in [-1, 1]."""
    from stable_baselines3 import PPO

    hp = tr.load_hyperparams("ppo", "IiwaReachObstacles-v0", {**HP, "n_envs": 64, "n_steps": 4, "batch_size": 256})
    kwargs = tr.algo_kwargs("ppo", hp)
    policy = kwargs.pop("policy")
    venv = vec_env.build_venv("IiwaReachObstacles-v0", hp, 0)
    model = PPO(policy, venv, device="cpu", seed=0, **kwargs)
    ext = model.policy.features_extractor
    assert ext.damper_columns is not None
    rng = np.random.default_rng(0)
    obs = venv.reset()
    for _ in range(20):  # random motion: some arms come near their obstacles
        obs, *_ = venv.step(rng.uniform(-1, 1, (64, 7)).astype(np.float32))
    with torch.no_grad():
        model.policy.action_net.linear.bias.copy_(torch.from_numpy(rng.uniform(-3, 3, 7).astype(np.float32)))
        x = {k: torch.as_tensor(v) for k, v in obs.items()}
        f = ext(x).double()
        mean = model.policy.get_distribution(model.policy.obs_to_tensor(obs)[0]).distribution.mean.double()
    start, k = ext.damper_columns
    normal, bound = f[:, start : start + 7 * k].view(-1, k, 7), f[:, start + 7 * k : start + 8 * k]
    near = bound > -1.0
    assert near.any()
    slack = (normal * mean[:, None]).sum(-1) - bound
    assert (slack[near] >= -1e-4).all()
    assert (mean.abs() <= 1.0 + 1e-6).all()


def test_one_row_head_in_numpy_equals_the_torch_path(monkeypatch, small_kernel):
    """At inference on a few rows the head's mean (hildreth, the shrink) runs in numpy, or compiled
    (``small_kernel``): the torch path (NUMPY_ROWS = 0) gives the same means to float32 rounding, row by
    row, on a batch whose large corrections the damper's constraints have to hold back. The
    deterministic ``_predict`` (its own route to the head on few rows) is the mode of SB3's Gaussian."""
    import train.features
    from train.evaluate import load_policy

    model, _, config = load_policy(ROOT / "train" / "policies" / "ppo_iiwa_reach_obstacles")
    policy, venv = model.policy, vec_env.build_venv(config["env_id"], {**config["hyperparams"], "n_envs": 64}, 0)
    head, rng = policy.action_net, np.random.default_rng(1)
    obs = venv.reset()
    for _ in range(20):  # random motion: some arms come near their obstacles
        obs, *_ = venv.step(rng.uniform(-1, 1, (64, 7)).astype(np.float32))
    with torch.no_grad():
        x = policy.obs_to_tensor(obs)[0]
        features = policy.extract_features(x)
        latent = policy.mlp_extractor.forward_actor(features)
        head.linear.bias.add_(torch.from_numpy(rng.uniform(-3, 3, 7).astype(np.float32)))
        fast = torch.cat([head(latent[i : i + 1]) for i in range(64)])
        first = {key: v[:3] for key, v in x.items()}
        assert torch.equal(policy._predict(first, True), policy.get_distribution(first).mode())
        with monkeypatch.context() as patch:
            patch.setattr(train.features, "NUMPY_ROWS", 0)
            slow = head(latent)
            patch.setattr(head, "constraints", 0)
            unconstrained = head(latent)
    torch.testing.assert_close(fast, slow, rtol=0, atol=1e-6)
    start, k = policy.features_extractor.damper_columns
    normal, bound = features[:, start : start + 7 * k].view(-1, k, 7), features[:, start + 7 * k : start + 8 * k]
    held = ((normal * unconstrained[:, None]).sum(-1) < bound - 1e-3).any(-1)
    assert held.sum() >= 3 and not torch.allclose(fast[held], unconstrained[held].clamp(-1, 1), atol=1e-3)


def test_controller_alone_is_the_dls_step_and_leaves_the_model_as_it_was():
    """``train.evaluate.controller_alone``: the residual policy with its correction zeroed acts as the DLS
    step the extractor computes; the trained model still acts with its correction; other policies: None."""
    from types import SimpleNamespace

    from train.evaluate import controller_alone

    model = _model()
    with torch.no_grad():
        model.policy.action_net.linear.bias.fill_(0.3)  # a correction that moves every joint
    obs = model.env.reset()
    before, _ = model.predict(obs, deterministic=True)
    ext = model.policy.features_extractor
    step = ext({k: torch.as_tensor(v) for k, v in obs.items()})[:, ext.step_columns[0] : ext.step_columns[1]]
    alone = controller_alone(model)
    np.testing.assert_allclose(alone.predict(obs, deterministic=True)[0], step.numpy(), atol=1e-6)
    assert not np.allclose(before, step.numpy(), atol=1e-3)
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], before)
    assert controller_alone(SimpleNamespace(policy=object())) is None


def test_keep_progress_keeps_the_dls_steps_first_order_progress(small_kernel):
    """``keep_progress``: the head's mean has a first-order progress ``g . mean`` (``g = J^T e / |e|`` in
    actions) of at least the DLS step's where it needs no shrink into [-1, 1], and never a negative one
    (on 256 random head inputs with random corrections); without it the same corrections slow some
    approaches. The one-row paths (numpy or compiled: ``small_kernel``) give the batch's means, on the
    head and on the whole policy (64 arms after random motion)."""
    from stable_baselines3 import PPO

    rng = np.random.default_rng(3)
    n, nj = 256, 7
    step = rng.uniform(-0.3, 0.3, (n, nj))
    distance, gradient = rng.uniform(0.005, 0.5, (n, 1)), rng.normal(size=(n, nj))
    bias = torch.from_numpy(rng.uniform(-0.5, 0.5, nj).astype(np.float32))
    means = {}
    for keep in (True, False):
        hp = tr.load_hyperparams("ppo", "IiwaReach-v0", {**HP, "n_envs": 64, "policy_kwargs": {
            **HP["policy_kwargs"], "keep_progress": keep}, "env_kwargs": {"terminate_on_success": False},
            "features_extractor_kwargs": {"scales": [0.3, 0.03, 0.003], "dampings": [0.1, 0.01]}})
        kwargs = tr.algo_kwargs("ppo", hp)
        policy = kwargs.pop("policy")
        venv = vec_env.build_venv("IiwaReach-v0", hp, 0)
        model = PPO(policy, venv, device="cpu", seed=0, **kwargs)
        head = model.policy.action_net
        parts = [rng.normal(size=(n, head.linear.in_features)), step, distance] + ([gradient] if keep else [])
        latent = torch.from_numpy(np.concatenate(parts, -1).astype(np.float32))
        with torch.no_grad():
            head.linear.bias.copy_(bias)
            means[keep] = head(latent).double()
            torch.testing.assert_close(torch.cat([head(latent[i : i + 1]) for i in range(n)]).double(), means[keep],
                                       rtol=0, atol=1e-5)
            obs = venv.reset()
            for _ in range(5):
                obs, *_ = venv.step(rng.uniform(-1, 1, (64, nj)).astype(np.float32))
            x = model.policy.obs_to_tensor(obs)[0]
            rows = torch.cat([model.policy._predict({k: v[i : i + 1] for k, v in x.items()}, True) for i in range(64)])
            torch.testing.assert_close(rows, model.policy._predict(x, True), rtol=0, atol=1e-5)
    g = torch.from_numpy(gradient) * model.policy.features_extractor.max_step
    base = (g * torch.from_numpy(step)).sum(-1)
    ahead = {keep: (g * mean).sum(-1) for keep, mean in means.items()}
    unshrunk = means[True].abs().amax(-1) < 1 - 1e-6
    assert unshrunk.sum() >= 50
    assert bool((ahead[True][unshrunk] >= base[unshrunk] - 1e-5).all())
    assert bool((ahead[True][base > 0] >= -1e-6).all())
    assert bool((ahead[False] < base - 1e-3).sum() >= 50)


def test_keep_progress_must_be_a_bool():
    from stable_baselines3 import PPO

    bad = {**HP, "policy_kwargs": {**HP["policy_kwargs"], "keep_progress": 1}}
    hp = tr.load_hyperparams("ppo", "IiwaReach-v0", bad)
    kwargs = tr.algo_kwargs("ppo", hp)
    policy = kwargs.pop("policy")
    with pytest.raises(TypeError, match="keep_progress must be True or False"):
        PPO(policy, vec_env.build_venv("IiwaReach-v0", hp, 0), device="cpu", seed=0, **kwargs)
