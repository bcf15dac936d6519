"""Training and evaluation scripts: short runs of each algo, checkpoint + resume, the report, bad flags.

Budget: about two minutes on a shared 2-core machine. Runs are tiny (a few thousand env
steps) and only check the machinery; the shipped policies' quality is recomputed on a small
held-out goal set. Tests that run a training are marked ``slow``: ``pytest -m "not slow"``
skips them. Subprocess tests wait on events (a checkpoint folder, an evaluation at some step),
never on sleeps; ``HANG_GUARD`` only stops a hung test.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from train import evaluate as ev
from train import train as tr
from train import vec_env
from train.run_dir import RunDir

ROOT = Path(__file__).resolve().parents[1]
POLICIES = ROOT / "train" / "policies"
SMALL = ["eval_goals=32", "policy_kwargs={net_arch: [16, 16]}"]
HANG_GUARD = 600  # s: not a timing assumption, only the end of a test whose subprocess hangs
PPO_SMALL = ["--n-envs", "32", "--hyperparams", "n_steps=16", "batch_size=256", "n_epochs=1",
             "eval_freq=512", "checkpoint_freq=1024", *SMALL]


def sac_small(every: int, eval_every: int | None = None) -> list[str]:
    """Flags of a tiny SAC+HER run checkpointing (and evaluating, unless ``eval_every``) every ``every`` env steps."""
    return ["--n-envs", "4", "--hyperparams", "learning_starts=200", "batch_size=64", "gradient_steps=1",
            "buffer_size=5000", f"eval_freq={eval_every or every}", f"checkpoint_freq={every}", *SMALL]


def wait_until(predicate, proc: subprocess.Popen, what: str) -> None:
    """Poll ``predicate()`` (a file or a step count appearing) until true; fail if ``proc`` exits first."""
    guard = time.monotonic() + HANG_GUARD
    while not predicate():
        assert proc.poll() is None, f"exited before {what}: " + proc.stderr.read().decode()[-2000:]
        assert time.monotonic() < guard, f"hung: no {what}"
        time.sleep(0.05)


def evaluated_at(run: Path, steps: int) -> bool:
    """True once ``evaluations.json`` (written atomically) holds an evaluation at ``steps`` or later."""
    path = run / "evaluations.json"
    return path.exists() and any(e["steps"] >= steps for e in json.loads(path.read_text()))


def _params(model) -> torch.Tensor:
    return torch.cat([p.detach().flatten() for p in model.policy.parameters()])


@pytest.mark.slow
@pytest.mark.parametrize("algo, flags, steps", [("ppo", PPO_SMALL, 2048), ("sac", sac_small(400), 800)])
def test_short_run_writes_checkpoint_and_final_model(tmp_path, algo, flags, steps):
    run = tmp_path / algo
    assert tr.main(["--algo", algo, "--env", "IiwaReach-v0", "--timesteps", str(steps), "--out", str(run),
                    "--no-progress-bar", *flags]) == 0
    for name in ("model.zip", "config.yaml", "evaluations.json", "train_info.json"):
        assert (run / name).is_file(), name
    normalize = yaml.safe_load((run / "config.yaml").read_text())["hyperparams"]["normalize"]
    assert (run / "vecnormalize.pkl").is_file() == normalize
    ckpt = RunDir(run).latest_checkpoint()
    assert ckpt is not None and (ckpt / "model.zip").is_file() and (ckpt / "vecnormalize.pkl").is_file() == normalize
    assert (ckpt / "replay_buffer.pkl").is_file() == (algo == "sac")
    state = json.loads((ckpt / "state.json").read_text())
    assert state["num_timesteps"] >= steps
    evaluations = json.loads((run / "evaluations.json").read_text())
    assert evaluations[0]["steps"] == 0 and evaluations[-1]["steps"] >= steps
    # >= 0: the goals and the arm's position come from the same FK kernel, so an arm at its goal's
    # configuration is at distance 0 exactly
    assert all(0.0 <= e["success"] <= 1.0 and e["median_distance"] >= 0 for e in evaluations)
    config = yaml.safe_load((run / "config.yaml").read_text())
    assert config["algo"] == algo and config["hyperparams"]["n_timesteps"] == steps
    assert list(tb for tb in (run / "tb").rglob("events.out.tfevents*")), "no TensorBoard log"


@pytest.mark.slow
def test_resume_after_kill_restores_steps_and_model(tmp_path, capsys):
    """A run killed with SIGKILL resumes from its last checkpoint: same weights, same step counter. While it
    runs, a second process on its directory is refused; once it is dead, its lock file does not block."""
    run = tmp_path / "killed"
    cmd = [sys.executable, "-m", "train.train", "--algo", "ppo", "--env", "IiwaReach-v0", "--timesteps", "1000000",
           "--out", str(run), "--no-progress-bar", *PPO_SMALL]
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        checkpoint = lambda: RunDir(run).latest_checkpoint()
        wait_until(lambda: checkpoint() is not None and checkpoint().name >= "step_000000002048", proc,
                   "checkpoint at step 2048")
        for argv in (["--resume"], ["--algo", "ppo", "--env", "IiwaReach-v0"]):
            with pytest.raises(SystemExit) as exc:
                tr.main([*argv, "--out", str(run), "--no-progress-bar"])
            assert exc.value.code == 2
        err = capsys.readouterr().err
        assert f"{run} is in use by pid {proc.pid}" in err and "exists and is not empty" in err
        assert proc.poll() is None
    finally:
        proc.kill()
        proc.wait()
    assert (run / ".lock").exists()  # left by the killed run: stale, it must not block the resume
    ckpt = RunDir(run).latest_checkpoint()
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
    assert yaml.safe_load((run / "config.yaml").read_text())["hyperparams"]["n_timesteps"] == saved + 1024
    with pytest.raises(SystemExit):  # the run's own settings: only -n may change on --resume
        tr.main(["--resume", "--out", str(run), "--n-envs", "8", "--seed", "5", "--hyperparams", "gamma=0.9"])
    assert "(only -n may change): drop --seed, --n-envs, --hyperparams" in capsys.readouterr().err


def test_a_second_ctrl_c_while_the_checkpoint_is_saved_is_ignored(tmp_path, capsys, monkeypatch):
    """The first press stops the run; a second one during its checkpoint no longer cuts the message (and
    the pruning) short with a traceback."""
    from train.callbacks import EvalAndCheckpoint

    steps = {"n": 0}
    on_step, checkpoint = EvalAndCheckpoint._on_step, EvalAndCheckpoint.checkpoint

    def pressed_once(self):
        steps["n"] += 1
        if steps["n"] == 40:
            raise KeyboardInterrupt
        return on_step(self)

    def pressed_again(self):
        signal.raise_signal(signal.SIGINT)
        return checkpoint(self)

    monkeypatch.setattr(EvalAndCheckpoint, "_on_step", pressed_once)
    monkeypatch.setattr(EvalAndCheckpoint, "checkpoint", pressed_again)
    inherited = signal.signal(signal.SIGINT, signal.default_int_handler)  # a background shell may ignore Ctrl-C
    try:
        with pytest.raises(SystemExit) as exc:
            tr.main(["--algo", "sac", "--env", "IiwaReach-v0", "--out", str(tmp_path / "run"), "--timesteps", "4000",
                     "--no-progress-bar", *sac_small(100_000)])
    finally:
        signal.signal(signal.SIGINT, inherited)
    assert exc.value.code == 130 and "--resume" in capsys.readouterr().out
    assert RunDir(tmp_path / "run").latest_checkpoint() is not None


@pytest.mark.slow
def test_sigterm_saves_a_checkpoint_at_the_current_step(tmp_path):
    run = tmp_path / "term"
    flags = sac_small(100_000, eval_every=200)  # the event to wait for: an evaluation past step 0
    cmd = [sys.executable, "-m", "train.train", "--algo", "sac", "--env", "IiwaReach-v0", "--timesteps", "1000000",
           "--out", str(run), "--no-progress-bar", *flags]
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        wait_until(lambda: evaluated_at(run, 400), proc, "evaluation at step 400")
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=HANG_GUARD)
    finally:
        proc.kill()
    assert proc.returncode == 130, err.decode()[-2000:]
    ckpt = RunDir(run).latest_checkpoint()
    assert ckpt is not None and (ckpt / "replay_buffer.pkl").is_file()
    assert json.loads((ckpt / "state.json").read_text())["num_timesteps"] >= 400
    assert b"--resume" in out


def _shipped() -> list[Path]:
    return sorted(p for p in POLICIES.glob("*") if (p / "model.zip").is_file())


def test_evaluate_shipped_policy_writes_documented_report(tmp_path):
    policies = [p for p in _shipped() if p.name.startswith("ppo_iiwa")]  # the iiwa has both IK rows
    assert policies, "no shipped policy in train/policies/"
    out = tmp_path / "report"
    assert ev.main(["--model", str(policies[0]), "--goals", "64", "--seed", "3", "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    for key in ("env_id", "algo", "model", "goals", "seed", "goals_below_floor", "methods", "verdict", "plots",
                "machine"):
        assert key in report, key
    residual = yaml.safe_load((policies[0] / "config.yaml").read_text())["hyperparams"]["policy"] == "ResidualDLSPolicy"
    assert set(report["methods"]) == set(ev.METHODS) | ({"controller"} if residual else set())
    for name, m in report["methods"].items():
        for key in ("success@1cm", "success@5mm", "success@1mm", "median_error_m", "p95_error_m",
                    "median_steps_to_reach", "joint_limit_violations", "median_path_length_rad",
                    "time_per_goal_batched_s", "time_per_goal_single_s", "collisions", "collision_share",
                    "floor_collisions", "self_collisions", "final_collisions", "min_clearance_median_m",
                    "min_clearance_worst_m"):
            assert key in m, (name, key)
        assert m["joint_limit_violations"] == 0, name
    # the IK solvers are exact on reachable goals: an independent sanity check of the harness
    assert report["methods"]["gradient_ik"]["success@1mm"] > 0.95
    assert report["methods"]["analytic_ik"]["success@1mm"] > 0.95
    for plot in report["plots"]:
        assert (out / plot).stat().st_size > 1000
    assert (out / "report.md").read_text().startswith("# Policy versus IK")
    # the verdict names the training env's collision setting, read here from the config's own text
    trained = yaml.safe_load((policies[0] / "config.yaml").read_text())["hyperparams"]["env_kwargs"]
    assert sum(f"collision='{trained.get('collision', 'terminate')}'" in line for line in report["verdict"]) == 1


@pytest.mark.parametrize("name, minimum, median, collisions", [
    ("ppo_iiwa_reach", 0.97, 1e-3, 0.01), ("ppo_iiwa_reach_pose", 0.93, 1e-3, 0.01),
    ("ppo_iiwa_reach_obstacles", 0.94, 1e-3, 0.02), ("ppo_iiwa_reach_mlp", 0.93, 5e-3, 0.02),
    ("ppo_franka_reach_mlp", 0.93, 5e-3, 0.02), ("ppo_franka_reach", 0.97, 1e-3, 0.01),
])
def test_shipped_policy_still_reaches_held_out_goals(name, minimum, median, collisions):
    """Recomputed, not read from its report: the shipped policy on 200 held-out goals (seed 0, as the
    report) with today's env and rollout code. The minimums are at least 4 binomial standard deviations
    of 200 goals below each 1,000-goal report's success (the README's table of shipped policies; the
    pose policy's at 1 cm and 0.1 rad), the collision bounds as many above its share of colliding
    rollouts, the median bounds a few times the reports' medians."""
    from train.rollout import PolicyEvaluator, make_goal_set

    model, vec_normalize, config = ev.load_policy(POLICIES / name)
    env_kwargs = config["hyperparams"].get("env_kwargs") or {}
    pose = config["env_id"] == "IiwaReachPose-v0"
    evaluator = PolicyEvaluator(make_goal_set(config["env_id"], 200, 0, env_kwargs), ev.TOLERANCES["1cm"],
                                env_kwargs.get("orientation_threshold", ev.ORIENTATION_TOL) if pose else None)
    metrics, _ = evaluator(model, vec_normalize)
    assert metrics["success"] >= minimum, metrics
    assert metrics["median_distance"] < median, metrics
    assert metrics["collisions"] <= collisions, metrics


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
    (["--algo", "ppo", "--env", "IiwaReach-v0", "--hyperparams", "n_steps=-1"],
     "hyper-parameters rejected by PPO: `n_steps * n_envs` must be greater than 1"),
    (["--algo", "ppo", "--env", "IiwaReach-v0", "--hyperparams", "batch_size=0"],
     "hyper-parameters rejected by PPO: `batch_size` must be greater than 1"),
    (["--algo", "ppo", "--env", "IiwaReach-v0", "--hyperparams", "learning_rate=abc"],
     "learning_rate must be a number or lin_<number> (a linear decay), got 'abc'"),
    (["--algo", "sac", "--env", "IiwaReach-v0", "--hyperparams", "learning_rate=lin_x"],
     "learning_rate must be a number or lin_<number> (a linear decay), got 'lin_x'"),
    (["--algo", "ppo", "--env", "IiwaReach-v0", "--hyperparams", "her={n_sampled_goal: 4}"],
     "her (a replay-buffer option) needs an off-policy algo (sac)"),
    (["--algo", "ppo", "--env", "IiwaReach-v0", "--hyperparams", "policy_kwargs=5"],
     "policy_kwargs must be a mapping (e.g. {net_arch: [256, 256]}), got 5"),
    (["--algo", "sac", "--env", "IiwaReach-v0", "--hyperparams", "gamma=2"], "gamma must be a number in (0, 1], got 2"),
    (["--algo", "ppo", "--env", "IiwaReach-v0", "--hyperparams", "log_distance_bonus={weight: -1}"],
     "log_distance_bonus: weight must be a positive number, got -1"),
    (["--algo", "ppo", "--env", "IiwaReach-v0", "--hyperparams", "clearance_penalty=3"],
     "clearance_penalty must be a mapping of its options, got 3"),
])
def test_bad_train_flags_give_clear_errors(tmp_path, capsys, argv, message):
    with pytest.raises(SystemExit) as exc:
        tr.main([*argv, "--out", str(tmp_path / "run"), "--no-progress-bar"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not (tmp_path / "run").exists()


def test_an_out_that_is_a_file_is_a_clear_error(tmp_path, capsys):
    (tmp_path / "file").write_text("x")
    for main, argv in ((tr.main, ["--algo", "ppo", "--env", "IiwaReach-v0"]),
                       (ev.main, ["--model", str(_shipped()[0]), "--goals", "2"])):
        for out in (tmp_path / "file", tmp_path / "file" / "below"):
            with pytest.raises(SystemExit) as exc:
                main([*argv, "--out", str(out)])
            assert exc.value.code == 2
            err = capsys.readouterr().err
            assert f"--out {out}: {tmp_path / 'file'} is a file, not a folder" in err and "Traceback" not in err


def test_a_linear_schedule_stops_at_zero():
    """SB3 completes the last rollout past n_timesteps: the remaining progress goes below 0 there."""
    lr = tr._schedule("learning_rate", "lin_1e-3")
    assert lr(1.0) == 1e-3 and lr(0.25) == 2.5e-4 and lr(0.0) == 0.0 and lr(-15.4) == 0.0


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


def test_evaluate_a_stopped_run_uses_its_newest_checkpoint(tmp_path, capsys):
    """A run stopped before its end has config.yaml and checkpoints/, no model.zip: the newest checkpoint is
    evaluated (an older one holding a broken model shows the newest was loaded, not the first found)."""
    import shutil

    shipped = POLICIES / "ppo_iiwa_reach"
    run = tmp_path / "run"
    for step, model in ((1024, b"not a model"), (2048, (shipped / "model.zip").read_bytes())):
        folder = run / "checkpoints" / f"step_{step:012d}"
        folder.mkdir(parents=True)
        (folder / "model.zip").write_bytes(model)
        (folder / "state.json").write_text(json.dumps({"num_timesteps": step}))
    shutil.copy(shipped / "config.yaml", run / "config.yaml")
    model, _, _ = ev.load_policy(run)
    reference, _, _ = ev.load_policy(shipped)
    assert torch.equal(_params(model), _params(reference))
    assert "evaluating its newest checkpoint, checkpoints/step_000000002048" in capsys.readouterr().err


def test_unknown_gymnasium_id_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown env id 'NoSuchEnv-v9'"):
        vec_env.make_env("NoSuchEnv-v9", 1, 0)


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


def test_evaluation_summary_by_hand():
    """Four goals, 1 cm and 0.1 rad: counted and interpolated by hand (p95: 0.02 + 0.85 * 0.48)."""
    from train.rollout import summarise_finals

    final = np.array([0.001, 0.02, 0.005, 0.5])
    out = summarise_finals(final, 0.01)
    assert out == pytest.approx({"success": 0.5, "median_distance": 0.0125, "p95_distance": 0.428})
    out = summarise_finals(final, 0.01, np.array([0.05, 0.01, 0.2, 0.0]), 0.1)
    assert out["success"] == 0.25 and out["success_position"] == 0.5 and out["median_angle"] == pytest.approx(0.03)


def test_evaluate_rejects_malformed_env_kwargs(tmp_path, capsys):
    with pytest.raises(SystemExit):
        ev.main(["--model", str(_shipped()[0]), "--out", str(tmp_path), "--env-kwargs", "collision"])
    assert "expected KEY=VALUE" in capsys.readouterr().err
