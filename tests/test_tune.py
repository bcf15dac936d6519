"""train.tune: tiny local studies, pruning, an interrupted and resumed study, the best config re-run, bad input.

The study's contents are read back through Optuna's own API (``optuna.load_study``) and compared
with the trials' run directories (``evaluations.json``, written by the training callback), so the
values the study reports are checked against what the trainings measured. Subprocess tests wait on
files (an evaluation at some step), never on sleeps; ``HANG_GUARD`` only stops a hung test.
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
import yaml

optuna = pytest.importorskip("optuna")

from optuna.trial import TrialState  # noqa: E402

from train import train as tr  # noqa: E402
from train import tune  # noqa: E402
from train.run_dir import validate_config  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
HANG_GUARD = 600  # s: not a timing assumption, only the end of a test whose subprocess hangs
FIXED = ["eval_goals=16", "eval_freq=128", "checkpoint_freq=100000"]
STUDY = "ppo-IiwaReach-v0"


def tune_args(out: Path, trials: int, steps: int = 256, *extra: str) -> list[str]:
    return ["--algo", "ppo", "--env", "IiwaReach-v0", "--trials", str(trials), "--timesteps", str(steps),
            "--n-envs", "4", "--out", str(out), *extra, "--hyperparams", *FIXED]


def error_of(capsys, argv) -> str:
    """The stderr of ``tune.main(argv)``, which must exit with status 2 and no traceback."""
    with pytest.raises(SystemExit) as exc:
        tune.main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err


def stored(out: Path):
    return optuna.load_study(study_name=STUDY, storage=f"sqlite:///{out / 'study.db'}")


def last_metric(out: Path, number: int, key: str = "success") -> float:
    path = out / STUDY / f"trial_{number:04d}" / "evaluations.json"
    return json.loads(path.read_text())[-1][key]


def test_two_trials_then_the_best_config_reruns_with_train_train(tmp_path):
    out = tmp_path / "tune"
    assert tune.main(tune_args(out, 2)) == 0
    trials = stored(out).trials
    assert [t.state for t in trials] == [TrialState.COMPLETE] * 2
    for t in trials:  # the study's value is the last periodic evaluation of that trial's training
        assert t.value == last_metric(out, t.number)
        assert max(t.intermediate_values) == 256 and 0 in t.intermediate_values
        assert (out / STUDY / f"trial_{t.number:04d}" / "model.zip").is_file()
    best_path = out / STUDY / "best.yaml"
    best = validate_config(yaml.safe_load(best_path.read_text()), str(best_path))
    winner = max(trials, key=lambda t: (t.value, -t.number))  # Optuna keeps the first of equal values
    assert best["tune"]["trial"] == winner.number and best["tune"]["value"] == winner.value
    trial_config = yaml.safe_load((out / STUDY / f"trial_{winner.number:04d}" / "config.yaml").read_text())
    assert best["hyperparams"] == trial_config["hyperparams"]
    assert best["hyperparams"]["n_steps"] == winner.params["n_steps"]

    rerun = tmp_path / "rerun"
    assert tr.main(["--config", str(best_path), "--out", str(rerun), "--timesteps", "64", "--no-progress-bar"]) == 0
    config = yaml.safe_load((rerun / "config.yaml").read_text())
    assert config["hyperparams"] == {**best["hyperparams"], "n_timesteps": 64}
    assert (config["algo"], config["env_id"], config["seed"]) == ("ppo", "IiwaReach-v0", 0)
    assert (rerun / "model.zip").is_file()


@pytest.mark.slow
def test_an_interrupted_study_resumes_keeping_its_completed_trials(tmp_path):
    """SIGTERM during trial 1 marks it failed (exit 130, no traceback); the same command then resumes it as
    trial 2: its parameters, its run folder continued from the checkpoint the interrupt saved."""
    out = tmp_path / "tune"
    argv = tune_args(out, 2, 2048)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), *sys.path])}
    proc = subprocess.Popen([sys.executable, "-m", "train.tune", *argv], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    evaluations = out / STUDY / "trial_0001" / "evaluations.json"
    guard = time.monotonic() + HANG_GUARD
    while not (evaluations.exists() and any(e["steps"] >= 128 for e in json.loads(evaluations.read_text()))):
        assert proc.poll() is None, "exited before trial 1 trained: " + proc.stderr.read().decode()[-2000:]
        assert time.monotonic() < guard, "hung: trial 1 never evaluated"
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=HANG_GUARD)
    assert proc.returncode == 130, stderr.decode()[-2000:]
    assert "the same command resumes the study" in stdout.decode() and "Traceback" not in stderr.decode()
    before = stored(out).trials
    assert [t.state for t in before] == [TrialState.COMPLETE, TrialState.FAIL]
    assert yaml.safe_load((out / STUDY / "best.yaml").read_text())["tune"]["trial"] == 0
    (checkpoint,) = (out / STUDY / "trial_0001" / "checkpoints").glob("step_*")
    done = json.loads((checkpoint / "state.json").read_text())
    assert 128 <= done["num_timesteps"] < 2048

    assert tune.main(argv) == 0
    after = stored(out).trials
    assert [t.state for t in after] == [TrialState.COMPLETE, TrialState.FAIL, TrialState.COMPLETE]
    assert (after[0].params, after[0].value) == (before[0].params, before[0].value)
    assert after[2].params == before[1].params and after[2].user_attrs["resumes"]["trial"] == 1
    assert not (out / STUDY / "trial_0002").exists()  # trial 2 trained in trial 1's folder
    resumed = json.loads((out / STUDY / "trial_0001" / "evaluations.json").read_text())
    assert resumed[: len(done["evaluations"])] == done["evaluations"]  # kept, not trained again
    assert resumed[-1]["steps"] >= 2048 and after[2].value == resumed[-1]["success"]  # whole rollouts past it
    assert tune.main(argv) == 0  # the study is complete: nothing more runs
    assert len(stored(out).trials) == 3


def _sweep(steps: int) -> dict:
    return {"algo": "ppo", "env_id": "IiwaReach-v0", "seed": 0, "metric": "success",
            "overrides": {"n_timesteps": steps, "n_envs": 4, "eval_goals": 16, "eval_freq": 128}}


def test_a_pruned_trial_stops_at_the_evaluation_and_keeps_a_checkpoint(tmp_path):
    """A pruner that prunes every reported value: training stops after the step-0 evaluation."""
    study = optuna.create_study(direction="maximize", pruner=optuna.pruners.ThresholdPruner(lower=2.0))
    study.optimize(lambda t: tune.objective(t, _sweep(4096), tmp_path, "test"), n_trials=1)
    (trial,) = study.trials
    assert trial.state == TrialState.PRUNED
    run = tmp_path / study.study_name / "trial_0000"
    evaluations = json.loads((run / "evaluations.json").read_text())
    assert [e["steps"] for e in evaluations] == [0]
    assert trial.intermediate_values == {0: evaluations[0]["success"]}
    assert not (run / "model.zip").exists()
    (ckpt,) = (run / "checkpoints").glob("step_*")
    assert json.loads((ckpt / "state.json").read_text())["num_timesteps"] < 4096


def test_a_training_that_fails_with_a_value_error_is_pruned_with_its_message(tmp_path, monkeypatch):
    def diverge(*args, **kwargs):
        raise ValueError("Expected parameter loc to satisfy the constraint Real(), but found nan")

    monkeypatch.setattr(tr, "run_training", diverge)
    study = optuna.create_study(direction="maximize")
    study.optimize(lambda t: tune.objective(t, _sweep(128), tmp_path, "test"), n_trials=1)
    (trial,) = study.trials
    assert trial.state == TrialState.PRUNED and "found nan" in trial.user_attrs["error"]


@pytest.mark.parametrize("algo", ["ppo", "sac"])
def test_sampled_hyper_parameters_are_accepted_by_the_algo(algo):
    base = tr.load_hyperparams(algo, "IiwaReach-v0", {"n_envs": 8})
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    for _ in range(16):
        trial = study.ask()
        hp = tr.check_hyperparams({**base, **tune.SAMPLERS[algo](trial, base)}, "IiwaReach-v0")
        kwargs = tr.algo_kwargs(algo, hp)  # raises on a key the SB3 constructor does not take
        assert 0.9 <= hp["gamma"] < 1.0
        assert kwargs["policy_kwargs"]["net_arch"] in ([64, 64], [128, 128], [256, 256])
        assert {k: v for k, v in hp["policy_kwargs"].items() if k not in ("net_arch", "log_std_init")} == \
            {k: v for k, v in base["policy_kwargs"].items() if k not in ("net_arch", "log_std_init")}
        if algo == "ppo":
            assert hp["batch_size"] * trial.params["n_minibatches"] == trial.params["n_steps"] * 8
            assert hp["learning_rate"] == trial.params["learning_rate"] or \
                hp["learning_rate"] == f"lin_{trial.params['learning_rate']:.4g}"
        else:
            assert hp["her"]["n_sampled_goal"] == trial.params["n_sampled_goal"]
        study.tell(trial, 0.0)


def test_hide_password():
    assert tune.hide_password("postgresql://ann:s3cret@db.example:5432/opt") == "postgresql://ann:***@db.example:5432/opt"
    assert tune.hide_password("sqlite:////tmp/a:b@c.db") == "sqlite:////tmp/a:b@c.db"
    assert tune.hide_password("mysql://ann@host/db") == "mysql://ann@host/db"


@pytest.mark.parametrize("flags, message", [
    (["--storage", "not a url"], "storage not a url cannot be opened"),
    (["--storage", "postgresql://ann:s3cret@localhost/opt"], "postgresql://ann:***@localhost/opt"),
    (["--storage", "sqlite:////no/such/folder/study.db"], "cannot be opened (OperationalError"),
    (["--trials", "0"], "--trials must be >= 1, got 0"),
    (["--algo", "td3"], "argument --algo: invalid choice: 'td3'"),
    (["--study-name", "a/b"], "--study-name names a folder in --out"),
    (["--hyperparams", "eval_goals=0"], "eval_goals must be a positive integer, got 0"),
    (["--hyperparams", "foo=1"], "unknown hyper-parameter(s) ['foo'] for ppo"),
    (["--hyperparams", "learning_rate=abc"], "learning_rate must be a number or lin_<number>"),
])
def test_bad_input_is_a_one_line_error(tmp_path, capsys, flags, message):
    err = error_of(capsys, [*tune_args(tmp_path / "t", 1), *flags])
    assert message in err and "s3cret" not in err
    assert not (tmp_path / "t" / STUDY).exists()


def test_a_study_of_another_sweep_is_refused(tmp_path, capsys):
    out = tmp_path / "t"
    assert tune.main(tune_args(out, 1, 128)) == 0
    err = error_of(capsys, [*tune_args(out, 1, 128), "--metric", "median_distance"])
    assert f"study '{STUDY}'" in err and "pick another --study-name" in err


def test_a_study_whose_trials_all_failed_takes_the_corrected_command(tmp_path, capsys):
    """A policy option the policy does not take passes the checks before the study and fails in SB3's
    constructor: the trial fails; the command without it then runs instead of being refused as another sweep."""
    out = tmp_path / "t"
    err = error_of(capsys, [*tune_args(out, 1, 128), "policy_kwargs={foo: 1}"])
    assert "hyper-parameters rejected by PPO" in err and "foo" in err
    assert [t.state for t in stored(out).trials] == [TrialState.FAIL]
    assert tune.main(tune_args(out, 1, 128)) == 0
    assert f"study '{STUDY}': none of its trials" in capsys.readouterr().out
    assert [t.state for t in stored(out).trials] == [TrialState.FAIL, TrialState.COMPLETE]


def test_missing_optuna_is_a_one_line_error(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "optuna", None)  # import optuna now raises ImportError
    assert "pip install 'iiwa-torch[rl]'" in error_of(capsys, tune_args(tmp_path, 1))



def test_opening_a_storage_waits_out_another_worker_creating_its_tables(monkeypatch, tmp_path):
    """Two workers starting at once on a fresh database both create Optuna's tables; the one that loses
    gets an IntegrityError, and may again at an immediate retry (seen on PostgreSQL): it tries again
    after short waits, and gives a clear error only when the failures go on."""
    from sqlalchemy.exc import IntegrityError

    real, failures = optuna.storages.RDBStorage, []

    def racing(*args, **kwargs):
        if len(failures) < 3:
            failures.append(1)
            raise IntegrityError("CREATE TABLE studies", {}, Exception("duplicate key value"))
        return real(*args, **kwargs)

    monkeypatch.setattr(optuna.storages, "RDBStorage", racing)
    monkeypatch.setattr(tune.time, "sleep", lambda s: None)
    assert tune.open_storage(f"sqlite:///{tmp_path / 'study.db'}") is not None and len(failures) == 3
    failures.clear()
    monkeypatch.setattr(tune, "_CONNECT_ATTEMPTS", 3)
    with pytest.raises(ValueError, match="cannot be opened .*IntegrityError"):
        tune.open_storage(f"sqlite:///{tmp_path / 'other.db'}")
