"""Training and evaluation scripts: short runs of each algo, checkpoint + resume, the report, bad flags.

Budget: about two minutes on a shared 2-core machine. Runs are tiny (a few thousand env
steps) and only check the machinery; the shipped policy's quality is checked on its
report (train/policies/*/report.json) by test_shipped_policy_report.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
import yaml

from train import evaluate as ev
from train import train as tr

ROOT = Path(__file__).resolve().parents[1]
POLICIES = ROOT / "train" / "policies"
SMALL = ["eval_goals=32", "policy_kwargs={net_arch: [16, 16]}"]
PPO_SMALL = ["--n-envs", "32", "--hyperparams", "n_steps=16", "batch_size=256", "n_epochs=1",
             "eval_freq=512", "checkpoint_freq=1024", *SMALL]


def sac_small(every: int) -> list[str]:
    """Flags of a tiny SAC+HER run evaluating and checkpointing every ``every`` env steps."""
    return ["--n-envs", "4", "--hyperparams", "learning_starts=200", "batch_size=64", "gradient_steps=1",
            "buffer_size=5000", f"eval_freq={every}", f"checkpoint_freq={every}", *SMALL]


def _params(model) -> torch.Tensor:
    return torch.cat([p.detach().flatten() for p in model.policy.parameters()])


@pytest.mark.parametrize("algo, flags, steps", [("ppo", PPO_SMALL, 2048), ("sac", sac_small(400), 800)])
def test_short_run_writes_checkpoint_and_final_model(tmp_path, algo, flags, steps):
    run = tmp_path / algo
    assert tr.main(["--algo", algo, "--env", "IiwaReach-v0", "--timesteps", str(steps), "--out", str(run),
                    "--no-progress-bar", *flags]) == 0
    for name in ("model.zip", "config.yaml", "evaluations.json", "train_info.json"):
        assert (run / name).is_file(), name
    normalize = yaml.safe_load((run / "config.yaml").read_text())["hyperparams"]["normalize"]
    assert (run / "vecnormalize.pkl").is_file() == normalize
    ckpt = tr.latest_checkpoint(run)
    assert ckpt is not None and (ckpt / "model.zip").is_file() and (ckpt / "vecnormalize.pkl").is_file() == normalize
    assert (ckpt / "replay_buffer.pkl").is_file() == (algo == "sac")
    state = json.loads((ckpt / "state.json").read_text())
    assert state["num_timesteps"] >= steps
    evaluations = json.loads((run / "evaluations.json").read_text())
    assert evaluations[0]["steps"] == 0 and evaluations[-1]["steps"] >= steps
    assert all(0.0 <= e["success"] <= 1.0 and e["median_distance"] > 0 for e in evaluations)
    config = yaml.safe_load((run / "config.yaml").read_text())
    assert config["algo"] == algo and config["hyperparams"]["n_timesteps"] == steps
    assert list(tb for tb in (run / "tb").rglob("events.out.tfevents*")), "no TensorBoard log"


def test_resume_after_kill_restores_steps_and_model(tmp_path):
    """A run killed with SIGKILL resumes from its last checkpoint: same weights, same step counter."""
    run = tmp_path / "killed"
    cmd = [sys.executable, "-m", "train.train", "--algo", "ppo", "--env", "IiwaReach-v0", "--timesteps", "1000000",
           "--out", str(run), "--no-progress-bar", *PPO_SMALL]
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.time() + 90
        while tr.latest_checkpoint(run) is None or tr.latest_checkpoint(run).name < "step_000000002048":
            assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
            assert time.time() < deadline, "no checkpoint within 90 s"
            time.sleep(0.2)
    finally:
        proc.kill()
        proc.wait()
    ckpt = tr.latest_checkpoint(run)
    saved = json.loads((ckpt / "state.json").read_text())["num_timesteps"]
    assert saved >= 2048
    from stable_baselines3 import PPO

    reference = _params(PPO.load(ckpt / "model.zip", device="cpu"))
    # resume to exactly the checkpoint's step count: nothing to learn, the final model is the checkpoint's
    assert tr.main(["--resume", "--out", str(run), "--timesteps", str(saved), "--no-progress-bar"]) == 0
    model, _, _ = ev.load_policy(run)
    assert model.num_timesteps == saved
    assert torch.equal(_params(model), reference)
    # and a longer resume continues the step counter from there
    assert tr.main(["--resume", "--out", str(run), "--timesteps", str(saved + 1024), "--no-progress-bar"]) == 0
    model, _, _ = ev.load_policy(run)
    assert model.num_timesteps == saved + 1024
    assert not torch.equal(_params(model), reference)
    steps = [e["steps"] for e in json.loads((run / "evaluations.json").read_text())]
    assert steps == sorted(steps) and steps[-1] == saved + 1024


def test_sigterm_saves_a_checkpoint_at_the_current_step(tmp_path):
    run = tmp_path / "term"
    cmd = [sys.executable, "-m", "train.train", "--algo", "sac", "--env", "IiwaReach-v0", "--timesteps", "1000000",
           "--out", str(run), "--no-progress-bar", *sac_small(100_000)]
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.time() + 60
    while not (run / "tb").exists():  # training has started
        assert proc.poll() is None and time.time() < deadline, proc.stderr.read().decode()[-2000:]
        time.sleep(0.2)
    time.sleep(3)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err.decode()[-2000:]
    ckpt = tr.latest_checkpoint(run)
    assert ckpt is not None and (ckpt / "replay_buffer.pkl").is_file()
    assert json.loads((ckpt / "state.json").read_text())["num_timesteps"] > 0
    assert b"--resume" in out


def _shipped() -> list[Path]:
    return sorted(p for p in POLICIES.glob("*") if (p / "model.zip").is_file())


def test_evaluate_shipped_policy_writes_documented_report(tmp_path):
    policies = _shipped()
    assert policies, "no shipped policy in train/policies/"
    out = tmp_path / "report"
    assert ev.main(["--model", str(policies[0]), "--goals", "64", "--seed", "3", "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    for key in ("env_id", "algo", "model", "goals", "seed", "methods", "verdict", "plots", "machine"):
        assert key in report, key
    assert set(report["methods"]) == set(ev.METHODS)
    for name, m in report["methods"].items():
        for key in ("success@1cm", "success@5mm", "success@1mm", "median_error_m", "p95_error_m",
                    "median_steps_to_reach", "joint_limit_violations", "median_path_length_rad",
                    "time_per_goal_batched_s", "time_per_goal_single_s"):
            assert key in m, (name, key)
        assert m["joint_limit_violations"] == 0, name
    # the IK solvers are exact on reachable goals: an independent sanity check of the harness
    assert report["methods"]["gradient_ik"]["success@1mm"] > 0.95
    assert report["methods"]["analytic_ik"]["success@1mm"] > 0.95
    for plot in report["plots"]:
        assert (out / plot).stat().st_size > 1000
    assert (out / "report.md").read_text().startswith("# Policy versus IK")


def test_shipped_policy_records_how_it_was_made_and_its_report():
    """Each shipped policy folder has its command, seed, commit, wall time and load, and a 1,000-goal report."""
    policies = _shipped()
    assert policies
    for policy in policies:
        config = yaml.safe_load((policy / "config.yaml").read_text())
        info = json.loads((policy / "train_info.json").read_text())
        assert config["command"].startswith("python -m train.train") and "seed" in config and config["commit"]
        assert info["wall_time"] > 0 and len(info["machine"]["loadavg"]) == 3
        assert "train.train" in (policy / "RECORD.md").read_text()
        report = json.loads((policy / "report" / "report.json").read_text())
        assert report["goals"] == 1000 and report["seed"] == 0 and report["env_id"] == config["env_id"]
        if config["env_id"] == "IiwaReach-v0":  # the figures docs/training.md states (a regression guard)
            m = report["methods"]["policy"]
            assert m["success@1cm"] >= 0.99 and m["median_error_m"] <= 0.003


def test_policy_actor_matches_sb3_predict():
    """The batched torch actor used for evaluation gives model.predict's deterministic actions."""
    import numpy as np

    from train.rollout import _env, policy_actor

    model, vec_normalize, config = ev.load_policy(_shipped()[0])
    obs = _env(config["env_id"], 16, 5, config["hyperparams"].get("env_kwargs")).reset()
    ours = np.clip(policy_actor(model, vec_normalize)(obs), -1, 1)
    theirs, _ = model.predict(obs if vec_normalize is None else vec_normalize.normalize_obs(obs), deterministic=True)
    np.testing.assert_allclose(ours, theirs, atol=1e-5)


def test_ship_needs_a_finished_run(tmp_path, capsys):
    from train import ship

    with pytest.raises(SystemExit):
        ship.main(["--run", str(tmp_path), "--name", "x"])
    assert "no train_info.json" in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["--algo", "ppo", "--env", "NoSuchEnv-v9"], "no hyper-parameters for env 'NoSuchEnv-v9'"),
    (["--algo", "ppo", "--env", "IiwaReach-v0", "--timesteps", "-5"], "--timesteps must be a positive integer"),
    (["--algo", "ppo", "--env", "IiwaReach-v0", "--n-envs", "0"], "--n-envs must be >= 1"),
    (["--env", "IiwaReach-v0"], "--algo and --env are required"),
    (["--algo", "ppo", "--env", "IiwaReach-v0", "--hyperparams", "oops"], "key=value"),
])
def test_bad_train_flags_give_clear_errors(tmp_path, capsys, argv, message):
    with pytest.raises(SystemExit) as exc:
        tr.main([*argv, "--out", str(tmp_path / "run"), "--no-progress-bar"])
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_resume_without_a_run_and_existing_out_are_errors(tmp_path, capsys):
    with pytest.raises(SystemExit):
        tr.main(["--resume", "--out", str(tmp_path / "nothing")])
    assert "config.yaml not found" in capsys.readouterr().err
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    with pytest.raises(SystemExit):
        tr.main(["--algo", "ppo", "--env", "IiwaReach-v0", "--out", str(tmp_path / "full")])
    assert "exists and is not empty" in capsys.readouterr().err


def test_evaluate_missing_model_is_a_clear_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        ev.main(["--model", str(tmp_path / "none"), "--out", str(tmp_path / "r")])
    assert exc.value.code == 2
    assert "must hold model.zip and config.yaml" in capsys.readouterr().err


def test_unknown_gymnasium_id_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown env id 'NoSuchEnv-v9'"):
        tr.make_env("NoSuchEnv-v9", 1, 0)


def test_goal_delta_features_follow_relabelled_goals():
    """The extractor's delta is desired - achieved at each scale (checked by hand), clipped to [-1, 1]."""
    from gymnasium import spaces

    from train.features import GoalDeltaExtractor

    box = lambda n: spaces.Box(-10, 10, (n,))
    space = spaces.Dict({"observation": box(2), "achieved_goal": box(3), "desired_goal": box(3)})
    ext = GoalDeltaExtractor(space, scales=[1.0, 0.01])
    obs = {"observation": torch.zeros(1, 2), "achieved_goal": torch.tensor([[0.5, 0.5, 0.5]]),
           "desired_goal": torch.tensor([[0.505, 0.3, 0.5]])}
    out = ext(obs)
    assert out.shape == (1, ext.features_dim) == (1, 2 + 3 + 3 + 6)
    expected = torch.tensor([0.005, -0.2, 0.0, 0.5, -1.0, 0.0])
    assert torch.allclose(out[0, 8:], expected, atol=1e-6)
    with pytest.raises(ValueError, match="positive"):
        GoalDeltaExtractor(space, scales=[0.0])
