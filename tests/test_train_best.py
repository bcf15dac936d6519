"""The run's best model: train.train keeps it at each improving periodic evaluation, across --resume,
atomically, and train.ship ships it with --best. In-process tiny SAC runs (a few hundred env steps).

Where the test needs to know which evaluation is best, it replaces the periodic evaluator with a
scripted one (success and median per env step) that also snapshots the weights it was shown.
"""

from __future__ import annotations

import json
import pickle
import shutil
from pathlib import Path

import pytest
import torch

import envs
from train import callbacks, ship, vec_env
from train import evaluate as ev
from train import train as tr
from train.rollout import PolicyEvaluator, make_goal_set
from train.run_dir import RunDir

TINY = ["eval_goals=8", "policy_kwargs={net_arch: [8]}", "batch_size=32", "buffer_size=2000"]


def sac_run(out: Path, steps: int, every: int) -> list[str]:
    return ["--algo", "sac", "--env", "IiwaReach-v0", "--n-envs", "4", "--timesteps", str(steps), "--out", str(out),
            "--no-progress-bar", "--hyperparams", "learning_starts=200", f"eval_freq={every}",
            f"checkpoint_freq={every}", *TINY]


def params(model) -> torch.Tensor:
    return torch.cat([p.detach().flatten() for p in model.policy.parameters()])


def load(folder: Path):
    """The SAC model in ``folder`` (a ``best/step_N`` of a run) on an env of its run's config."""
    from stable_baselines3 import SAC

    env_kwargs = RunDir(folder.parents[1]).read_config()["hyperparams"].get("env_kwargs")
    return SAC.load(folder / "model.zip", env=vec_env.make_env("IiwaReach-v0", 1, 0, env_kwargs), device="cpu")


class Scripted:
    """Stands in for PolicyEvaluator: ``metrics[step] = (success, median m)``; keeps the weights per step."""

    def __init__(self, metrics: dict[int, tuple[float, float]]):
        self.metrics, self.seen = metrics, {}

    def __call__(self, goals, distance_threshold, orientation_threshold):  # the constructor the callback calls
        return self.evaluate

    def evaluate(self, model, vec_normalize):
        self.seen[model.num_timesteps] = params(model).clone()
        success, median = self.metrics[model.num_timesteps]
        return {"success": success, "median_distance": median, "p95_distance": 2 * median}, 0.0


@pytest.fixture(scope="module")
def scripted_run(tmp_path_factory):
    """400 steps, evaluated every 100: the best is step 200 (the tie at 0.9 goes to the lower median;
    step 400 ties step 200 exactly and does not replace it)."""
    metrics = {0: (0.5, 0.004), 100: (0.9, 0.002), 200: (0.9, 0.001), 300: (0.8, 0.0005), 400: (0.9, 0.001)}
    script = Scripted(metrics)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(callbacks, "PolicyEvaluator", script)
        run = tmp_path_factory.mktemp("best") / "sac"
        assert tr.main(sac_run(run, 400, 100)) == 0
    return run, script


def test_best_is_the_improving_evaluation_and_its_weights(scripted_run):
    run, script = scripted_run
    best = RunDir(run).read_best()
    assert best["checkpoint"] == "best/step_000000000200"
    by_step = {e["steps"]: e for e in json.loads((run / "evaluations.json").read_text())}
    assert best["evaluation"] == by_step[200]
    assert [p.name for p in (run / "best").iterdir()] == ["step_000000000200"]  # older bests are removed
    model = load(run / best["checkpoint"])
    assert model.num_timesteps == 200
    assert torch.equal(params(model), script.seen[200])
    assert not torch.equal(params(model), script.seen[400])


def test_best_survives_resume_and_moves_only_when_beaten(scripted_run, tmp_path, monkeypatch):
    run = tmp_path / "run"
    shutil.copytree(scripted_run[0], run)
    before = (run / "best" / "step_000000000200" / "model.zip").read_bytes()
    script = Scripted({500: (0.85, 0.0001), 600: (0.9, 0.0011)})  # neither beats step 200's (0.9, 1 mm)
    monkeypatch.setattr(callbacks, "PolicyEvaluator", script)
    assert tr.main(["--resume", "--out", str(run), "--timesteps", "600", "--no-progress-bar"]) == 0
    assert RunDir(run).read_best()["evaluation"]["steps"] == 200
    assert (run / "best" / "step_000000000200" / "model.zip").read_bytes() == before

    script.metrics = {700: (0.95, 0.003)}
    assert tr.main(["--resume", "--out", str(run), "--timesteps", "700", "--no-progress-bar"]) == 0
    best = RunDir(run).read_best()
    assert best["evaluation"]["steps"] == 700 and best["evaluation"]["success"] == 0.95
    assert [p.name for p in (run / "best").iterdir()] == ["step_000000000700"]
    assert torch.equal(params(load(run / best["checkpoint"])), script.seen[700])


def test_a_save_cut_short_leaves_the_previous_best(scripted_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(scripted_run[0], run)
    record = (run / "best.json").read_text()

    class Crashing:
        num_timesteps = 900

        def save(self, path):
            Path(path).write_bytes(b"half a zip")
            raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        RunDir(run).save_best(Crashing(), {"steps": 900, "success": 1.0, "median_distance": 0.0})
    assert (run / "best.json").read_text() == record
    assert load(RunDir(run).best_checkpoint()).num_timesteps == 200


def test_ship_best_copies_the_best_model_and_records_its_step(scripted_run, tmp_path):
    run, script = scripted_run
    dest = ship.ship(run, "best_policy", best=True, root=tmp_path)
    assert (dest / "model.zip").read_bytes() == (run / "best" / "step_000000000200" / "model.zip").read_bytes()
    record = (dest / "RECORD.md").read_text()
    assert "shipped checkpoint: the best periodic evaluation's model (best/step_000000000200" in record
    assert "env step 200: periodic success at 1 cm 90.0%, median final distance 1 mm" in record
    model, _, _ = ev.load_policy(dest)
    assert torch.equal(params(model), script.seen[200])
    history = "## Run history\n\nRun 1: what was tried before.\n"
    (dest / "RECORD.md").write_text(record + history)
    ship.ship(run, "best_policy", root=tmp_path)  # shipped again, the final model this time
    again = (dest / "RECORD.md").read_text()
    assert "the final model, env step 400" in again and again.endswith(history) and again.count("## Run") == 1
    final = ship.ship(run, "final_policy", root=tmp_path)
    assert "shipped checkpoint: the final model, env step 400" in (final / "RECORD.md").read_text()
    assert ev.load_policy(final)[0].num_timesteps == 400


def test_ship_best_needs_a_best_record(scripted_run, tmp_path, capsys):
    run = tmp_path / "old"
    shutil.copytree(scripted_run[0], run)
    (run / "best.json").unlink()  # as a run trained before the best model was kept
    with pytest.raises(FileNotFoundError, match="has no best.json"):
        ship.ship(run, "x", best=True, root=tmp_path)
    with pytest.raises(SystemExit):
        ship.main(["--run", str(run), "--curve", str(tmp_path / "c.json"), "--best"])
    assert "--best picks the model to ship" in capsys.readouterr().err


def test_real_best_matches_evaluations_and_reevaluates_the_same(tmp_path):
    """Without a script: the best record is the max of evaluations.json by (collision-free success, -median)
    (the default env checks collisions), found here by sorting, and its model re-evaluated on the periodic goal
    set gives the recorded metrics."""
    run = tmp_path / "sac"
    assert tr.main(sac_run(run, 400, 100)) == 0
    evaluations = json.loads((run / "evaluations.json").read_text())
    assert all({"collisions", "success_collision_free"} <= set(e) for e in evaluations)
    ranked = sorted(evaluations, key=lambda e: (-e["success_collision_free"], e["median_distance"], e["steps"]))
    best = RunDir(run).read_best()
    assert best["evaluation"] == ranked[0]
    env_kwargs = RunDir(run).read_config()["hyperparams"].get("env_kwargs") or {}
    goals = make_goal_set("IiwaReach-v0", 8, callbacks.EVAL_SEED, env_kwargs)
    folder = run / best["checkpoint"]
    model = load(folder)
    assert model.num_timesteps == best["evaluation"]["steps"]
    vec_normalize = None
    if (folder / "vecnormalize.pkl").exists():
        with open(folder / "vecnormalize.pkl", "rb") as f:
            vec_normalize = pickle.load(f)  # SB3's format: the pickled wrapper
    threshold = envs.make_task("IiwaReach-v0", **env_kwargs).distance_threshold
    metrics, _ = PolicyEvaluator(goals, threshold)(model, vec_normalize)
    assert metrics["success"] == best["evaluation"]["success"]
    assert metrics["success_collision_free"] == best["evaluation"]["success_collision_free"]
    assert metrics["median_distance"] == pytest.approx(best["evaluation"]["median_distance"], rel=1e-9)
