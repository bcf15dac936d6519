"""Run-directory guarantees of train.train and the one-line errors of train.train / train.evaluate.

Atomic checkpoints, resume from the newest intact checkpoint, the run lock, validation before
any write, HER's learning_starts for many envs, and bad or mismatched configs and models. All
in-process through ``main(argv)`` on tiny runs (a few hundred env steps).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml

from train import evaluate as ev
from train import train as tr
from train.run_dir import RunDir, atomic_write_text

ROOT = Path(__file__).resolve().parents[1]
SHIPPED_PPO = ROOT / "train" / "policies" / "ppo_iiwa_reach"
TINY = ["eval_goals=8", "policy_kwargs={net_arch: [8]}", "batch_size=32", "buffer_size=2000"]


def sac_run(out: Path, n_envs: int = 4, steps: int = 400, every: int = 200, extra=()) -> list[str]:
    return ["--algo", "sac", "--env", "IiwaReach-v0", "--n-envs", str(n_envs), "--timesteps", str(steps),
            "--out", str(out), "--no-progress-bar", "--hyperparams", "learning_starts=200",
            f"eval_freq={every}", f"checkpoint_freq={every}", *TINY, *extra]


def error_of(capsys, main, argv) -> str:
    """The stderr of ``main(argv)``, which must exit with status 2 and no traceback."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    """A finished tiny SAC+HER run with checkpoints at steps 200 and 400."""
    run = tmp_path_factory.mktemp("finished") / "sac"
    assert tr.main(sac_run(run)) == 0
    assert [p.name for p in RunDir(run).checkpoints()] == ["step_000000000400", "step_000000000200"]
    return run


@pytest.fixture
def run_copy(finished, tmp_path) -> Path:
    shutil.copytree(finished, tmp_path / "run")
    return tmp_path / "run"


# ---------------------------------------------------------------------------- 16.7: HER and many envs
def test_her_learning_starts_covers_the_first_episodes_of_every_env(tmp_path, capsys):
    """16 envs of 50-step episodes end their first ones after 800 env steps: learning_starts=200 would
    make HER sample before any episode ends (SB3: 'Unable to sample before the end of the first episode')."""
    run = tmp_path / "many"
    assert tr.main(sac_run(run, n_envs=16, steps=1000, every=500)) == 0
    assert "learning_starts 200 -> 800" in capsys.readouterr().out
    assert yaml.safe_load((run / "config.yaml").read_text())["hyperparams"]["learning_starts"] == 16 * 50
    assert tr.her_learning_starts({"her": {}, "n_envs": 64, "learning_starts": 5000}, 50) == 5000
    assert tr.her_learning_starts({"n_envs": 64, "learning_starts": 10}, 50) is None  # no HER: no episodes needed


# ---------------------------------------------------------------------------- 16.9: damaged checkpoints
@pytest.mark.parametrize("name", ["model.zip", "vecnormalize.pkl", "replay_buffer.pkl", "state.json"])
def test_resume_skips_a_damaged_newest_checkpoint(run_copy, capsys, name):
    bad = run_copy / "checkpoints" / "step_000000000400" / name
    bad.write_bytes(bad.read_bytes()[: bad.stat().st_size // 2])  # a truncated file
    assert tr.main(["--resume", "--out", str(run_copy), "--timesteps", "200", "--no-progress-bar"]) == 0
    out = capsys.readouterr()
    assert f"{bad} is unreadable" in out.err
    assert "from step_000000000200 (the newest intact one, not step_000000000400)" in out.out
    model, _, _ = ev.load_policy(run_copy)
    assert model.num_timesteps == 200


def test_resume_with_no_intact_checkpoint_is_a_clear_error(run_copy, capsys):
    for ckpt in RunDir(run_copy).checkpoints():
        (ckpt / "model.zip").write_bytes(b"not a zip")
    err = error_of(capsys, tr.main, ["--resume", "--out", str(run_copy), "--no-progress-bar"])
    assert "no intact checkpoint in" in err and "model.zip is unreadable" not in err.splitlines()[-1]


def test_resume_refuses_checkpoints_without_the_normalisation_statistics(run_copy, capsys):
    """The run normalises observations (sac.yaml: normalize: true): a checkpoint without vecnormalize.pkl
    would go on with fresh statistics, so it counts as damaged."""
    assert yaml.safe_load((run_copy / "config.yaml").read_text())["hyperparams"]["normalize"] is True
    newest, older = RunDir(run_copy).checkpoints()
    (newest / "vecnormalize.pkl").unlink()
    assert tr.main(["--resume", "--out", str(run_copy), "--timesteps", "200", "--no-progress-bar"]) == 0
    out = capsys.readouterr()
    assert f"{newest / 'vecnormalize.pkl'} is missing (the config says normalize: true)" in out.err
    assert "from step_000000000200 (the newest intact one, not step_000000000400)" in out.out
    (older / "vecnormalize.pkl").unlink()
    err = error_of(capsys, tr.main, ["--resume", "--out", str(run_copy), "--no-progress-bar"])
    assert "no intact checkpoint in" in err


def test_evaluate_refuses_a_normalised_run_without_its_statistics(run_copy, capsys):
    (run_copy / "vecnormalize.pkl").unlink()
    err = error_of(capsys, ev.main, ["--model", str(run_copy), "--goals", "4", "--out", str(run_copy / "r")])
    assert f"{run_copy / 'vecnormalize.pkl'} not found: the config says normalize: true" in err.splitlines()[-1]
    assert not (run_copy / "r").exists()


@pytest.mark.parametrize(("text", "value"), [("maybe", "maybe"), ("'no'", "no"), ("1", 1), ("null", None)])
def test_normalize_must_be_a_boolean(run_copy, tmp_path, capsys, text, value):
    err = error_of(capsys, tr.main, sac_run(tmp_path / "new", extra=[f"normalize={text}"]))
    assert "normalize must be True or False" in err.splitlines()[-1]
    _edit_config(run_copy, lambda c: c["hyperparams"].update(normalize=value))
    err = error_of(capsys, ev.main, ["--model", str(run_copy), "--goals", "4", "--out", str(run_copy / "r")])
    assert "config.yaml: normalize must be True or False" in err.splitlines()[-1]


def test_a_non_boolean_env_option_is_a_one_line_error(tmp_path, capsys):
    err = error_of(capsys, tr.main, sac_run(tmp_path / "new", extra=["env_kwargs={terminate_on_success: 'no'}"]))
    assert "terminate_on_success must be True or False, got 'no'" in err.splitlines()[-1]


class _Interrupted(Exception):
    pass


def test_a_save_cut_short_leaves_the_previous_checkpoint_newest(run_copy):
    """A save that dies after the model file (here: an exception; a kill leaves the same files) leaves
    only a temporary folder, which is not a checkpoint."""
    run = RunDir(run_copy)
    model, _, _ = ev.load_policy(run_copy)
    model.num_timesteps = 600

    def dies(path):
        raise _Interrupted

    model.save_replay_buffer = dies
    with pytest.raises(_Interrupted):
        run.save_checkpoint(model, {"num_timesteps": 600, "elapsed": 0.0, "evaluations": []})
    assert (run_copy / "checkpoints" / ".tmp_step_000000000600" / "model.zip").is_file()
    assert run.latest_checkpoint().name == "step_000000000400"
    del model.save_replay_buffer  # the next save (of the same process) clears the leftover
    model.num_timesteps = 800
    run.save_checkpoint(model, {"num_timesteps": 800, "elapsed": 0.0, "evaluations": []})
    assert sorted(p.name for p in run.checkpoint_root.iterdir()) == ["step_000000000400", "step_000000000800"]


def test_ctrl_c_during_a_save_is_held_until_the_checkpoint_is_complete(run_copy):
    """A Ctrl-C that arrives while the replay buffer is written (inside torch's zip writer it would abort
    the process) is held: the checkpoint is completed and renamed, then the interrupt is raised."""
    import signal

    run = RunDir(run_copy)
    model, _, _ = ev.load_policy(run_copy)
    model.num_timesteps = 600
    save = model.save_replay_buffer

    def interrupted(path):
        signal.raise_signal(signal.SIGINT)
        save(path)

    model.save_replay_buffer = interrupted
    inherited = signal.signal(signal.SIGINT, signal.default_int_handler)  # a background shell may ignore Ctrl-C
    try:
        with pytest.raises(KeyboardInterrupt):
            run.save_checkpoint(model, {"num_timesteps": 600, "elapsed": 0.0, "evaluations": []})
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, inherited)
    assert run.latest_checkpoint().name == "step_000000000600"
    assert (run.latest_checkpoint() / "replay_buffer.pkl").is_file()


def test_atomic_write_keeps_the_old_file_when_writing_fails(tmp_path):
    from train.run_dir import atomic_save

    path = tmp_path / "evaluations.json"
    atomic_write_text(path, "[1]")

    def half(tmp):
        tmp.write_text("[1, 2")
        raise _Interrupted

    with pytest.raises(_Interrupted):
        atomic_save(path, half)
    assert path.read_text() == "[1]" and [p.name for p in tmp_path.iterdir()] == ["evaluations.json"]


# ---------------------------------------------------------------------------- 16.10: the lock
def test_a_locked_run_directory_is_refused_and_nothing_is_written(tmp_path, capsys):
    """While a process holds the lock (here this one), a new run and a resume are refused with status 2."""
    run = RunDir(tmp_path / "busy")
    with run.lock():
        err = error_of(capsys, tr.main, sac_run(run.path))
        assert f"{run.path} is in use by pid" in err
        assert [p.name for p in run.path.iterdir()] == [".lock"]
    assert tr.main(sac_run(run.path, steps=200)) == 0  # released: the same directory now trains
    with run.lock():
        assert "is in use" in error_of(capsys, tr.main, ["--resume", "--out", str(run.path)])


# ---------------------------------------------------------------------------- 16.11: validate before writing
@pytest.mark.parametrize("extra, flags, message", [
    (["no_such_option=1"], [], "unknown hyper-parameter(s) ['no_such_option'] for sac"),
    (["her={n_sampled_goal: 4, no_such_option: 1}"], [], "hyper-parameters rejected by SAC"),
    (["policy_kwargs={net_arch: [8"], [], "the value is not valid YAML"),
    ([], ["--threads", "0"], "--threads must be >= 1, got 0"),
    ([], ["--conf-file", "BAD"], "bad.yaml: not valid YAML at line 3"),
    ([], ["--conf-file", "MISSING"], "hyper-parameter file"),
])
def test_a_failed_start_writes_nothing(tmp_path, capsys, extra, flags, message):
    bad = tmp_path / "bad.yaml"
    bad.write_text("IiwaReach-v0:\n  n_envs: [1,\n")
    flags = [{"BAD": str(bad), "MISSING": str(tmp_path / "none.yaml")}.get(f, f) for f in flags]
    run = tmp_path / "run"
    assert message in error_of(capsys, tr.main, [*sac_run(run, extra=extra), *flags])
    assert not run.exists()


@pytest.mark.parametrize("flags, message", [
    ([], "missing key(s) ['seed', 'hyperparams']"),
    (["--algo", "ppo"], "drop --algo, --env and --conf-file"),
    (["--resume"], "drop --config"),
])
def test_bad_config_flag_is_a_one_line_error(tmp_path, capsys, flags, message):
    config = tmp_path / "c.yaml"
    config.write_text("algo: ppo\nenv_id: IiwaReach-v0\n")
    run = tmp_path / "run"
    assert message in error_of(capsys, tr.main, ["--config", str(config), "--out", str(run), *flags])
    assert not run.exists()


# ---------------------------------------------------------------------------- 16.12: bad configs and models
def _edit_config(run: Path, edit) -> None:
    config = yaml.safe_load((run / "config.yaml").read_text())
    edit(config)
    (run / "config.yaml").write_text(yaml.safe_dump(config))


@pytest.mark.parametrize("edit, message", [
    (lambda c: c.pop("env_id"), "missing key(s) ['env_id']"),
    (lambda c: c.update(algo="td3"), "algo must be one of ['ppo', 'sac'], got 'td3'"),
    (lambda c: c.update(env_id="IiwaReachPose-v0"), "was trained for another env"),
    (lambda c: c.update(algo="ppo"), "sac.policies.MultiInputPolicy policy, which is not a PPO policy"),
])
def test_mismatched_config_is_a_one_line_error(run_copy, capsys, edit, message):
    _edit_config(run_copy, edit)
    assert message in error_of(capsys, ev.main, ["--model", str(run_copy), "--goals", "4", "--out",
                                                 str(run_copy / "report")])
    assert message in error_of(capsys, tr.main, ["--resume", "--out", str(run_copy), "--no-progress-bar"])


def test_ppo_model_with_algo_sac_is_a_one_line_error(tmp_path, capsys):
    policy = tmp_path / "policy"
    policy.mkdir()
    for name in ("model.zip", "config.yaml"):
        shutil.copy(SHIPPED_PPO / name, policy / name)
    _edit_config(policy, lambda c: c.update(algo="sac"))
    err = error_of(capsys, ev.main, ["--model", str(policy), "--goals", "4", "--out", str(tmp_path / "r")])
    assert "is not a SAC policy: the config says algo: sac" in err


def test_unparsable_config_and_model_are_one_line_errors(run_copy, capsys):
    (run_copy / "config.yaml").write_text("algo: sac\nenv_id: [\n")
    for main, argv in ((ev.main, ["--model", str(run_copy), "--out", str(run_copy / "r")]),
                       (tr.main, ["--resume", "--out", str(run_copy)])):
        assert "config.yaml: not valid YAML at line" in error_of(capsys, main, argv)
    shutil.copy(SHIPPED_PPO / "config.yaml", run_copy / "config.yaml")
    (run_copy / "model.zip").write_bytes(b"PK truncated")
    err = error_of(capsys, ev.main, ["--model", str(run_copy), "--out", str(run_copy / "r")])
    assert "model.zip is unreadable (not an SB3 model" in err


def test_compare_file_missing_is_a_one_line_error(tmp_path, capsys):
    err = error_of(capsys, ev.main, ["--model", str(SHIPPED_PPO), "--goals", "2", "--out", str(tmp_path / "r"),
                                     "--compare", str(tmp_path / "none.json")])
    assert "none.json" in err


@pytest.mark.parametrize("text, message", [
    ("{bad", "not a readable JSON file"),
    ('{"evaluations": []}', "expected a run's evaluations.json"),
    ('[{"steps": 0}]', "expected a run's evaluations.json"),
    ("[]", "expected a run's evaluations.json"),
])
def test_compare_file_malformed_is_a_one_line_error_naming_it(tmp_path, capsys, text, message):
    (tmp_path / "bad.json").write_text(text)
    err = error_of(capsys, ev.main, ["--model", str(SHIPPED_PPO), "--goals", "2", "--out", str(tmp_path / "r"),
                                     "--compare", str(tmp_path / "bad.json")])
    assert f"--compare {tmp_path / 'bad.json'}: {message}" in err
    assert not (tmp_path / "r").exists()  # refused before the rollouts



def test_a_run_killed_during_its_first_config_write_can_be_started_again(tmp_path, capsys):
    """What ``kill -9`` inside the first ``atomic_write_text(config.yaml)`` leaves: the lock file and the
    half-written temporary file, no config.yaml. --resume says what happened; a new run takes the folder."""
    run = tmp_path / "run"
    run.mkdir()
    (run / ".lock").write_text("pid 123")
    (run / ".tmp_123_config.yaml").write_text("algo: pp")
    err = error_of(capsys, tr.main, ["--resume", "--out", str(run)])
    assert "its first write was cut short" in err and "without --resume" in err
    assert tr.main(["--algo", "ppo", "--env", "IiwaReach-v0", "--out", str(run), "--timesteps", "64", "--n-envs", "4",
                    "--hyperparams", "n_steps=16", "batch_size=64", "eval_goals=8", "--no-progress-bar"]) == 0
    assert RunDir(run).read_config()["hyperparams"]["n_timesteps"] == 64 and (run / "model.zip").is_file()
