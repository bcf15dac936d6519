"""train.tune on a shared database: two workers on PostgreSQL, one killed with SIGKILL mid-trial; workers
creating the tables at once; the heartbeat flags.

A throwaway server (``initdb`` and ``pg_ctl`` in a temporary folder, listening on 127.0.0.1 only,
password authentication) holds the study; it is stopped and its folder removed afterwards. The
test skips, saying why, where the server binaries or the driver (``psycopg``) cannot be had;
``.ci/run`` installs the binaries with apt-get, the test extra the driver. As root (CI), the server
runs as the ``postgres`` user, since ``initdb`` refuses root. The study is read back through
Optuna's API and compared with the trials' run directories, which the trainings wrote.
"""

from __future__ import annotations

import contextlib
import glob
import json
import os
import pwd
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import yaml

optuna = pytest.importorskip("optuna")

from optuna.storages import RetryHeartbeatStaleTrialCallback  # noqa: E402
from optuna.trial import TrialState  # noqa: E402
from sqlalchemy.exc import IntegrityError  # noqa: E402

from train import tune  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
HANG_GUARD = 300  # s: not a timing assumption, only the end of a test whose subprocess hangs
STUDY = "ppo-IiwaReach-v0"
STEPS = 1024  # env steps per trial; evaluations every 128


def server_binaries() -> Path:
    """The folder of ``initdb`` and ``pg_ctl`` (on PATH, else Debian's newest), or skip."""
    found = shutil.which("pg_ctl")
    if found and shutil.which("initdb"):
        return Path(found).parent
    debian = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"), key=lambda p: int(Path(p).parts[-3]))
    if not debian:
        pytest.skip("no PostgreSQL server binaries (initdb, pg_ctl): apt-get install postgresql")
    return Path(debian[-1]).parent


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def throwaway_postgres(password: str):
    """A PostgreSQL server in a new temporary folder, superuser ``tune`` with ``password``, on 127.0.0.1 only:
    yields ``(url, folder, port)``; stops the server and removes the folder on exit."""
    pytest.importorskip("psycopg", reason="the PostgreSQL driver psycopg is not installed: pip install "
                        "'psycopg[binary]' (the test extra)")
    bin_dir = server_binaries()
    as_user: list[str] = []
    owner = None
    if os.geteuid() == 0:  # initdb refuses root: the server runs as the postgres user
        try:
            owner = pwd.getpwnam("postgres")
        except KeyError:
            pytest.skip("running as root and no 'postgres' user to run the PostgreSQL server as")
        as_user = ["runuser", "-u", "postgres", "--"]
    folder = Path(tempfile.mkdtemp(prefix="iiwa-tune-pg-"))
    data, log = folder / "data", folder / "server.log"
    pg_ctl = [*as_user, str(bin_dir / "pg_ctl"), "-D", str(data)]
    try:
        (folder / "password").write_text(password)
        if owner is not None:
            for path in (folder, folder / "password"):
                os.chown(path, owner.pw_uid, owner.pw_gid)
        subprocess.run([*as_user, str(bin_dir / "initdb"), "-D", str(data), "-U", "tune", "--auth=scram-sha-256",
                        f"--pwfile={folder / 'password'}", "--no-sync"], check=True, capture_output=True)
        port = free_port()
        options = f"-c listen_addresses=127.0.0.1 -p {port} -k {folder} -c fsync=off"
        started = subprocess.run([*pg_ctl, "-l", str(log), "-o", options, "-w", "-t", "60", "start"],
                                 capture_output=True, text=True)
        assert started.returncode == 0, started.stderr + (log.read_text() if log.exists() else "")
        yield f"postgresql+psycopg://tune:{password}@127.0.0.1:{port}/postgres", folder, port
    finally:
        if (data / "postmaster.pid").exists():
            subprocess.run([*pg_ctl, "-m", "immediate", "-w", "stop"], capture_output=True)
        shutil.rmtree(folder, ignore_errors=True)


def evaluated_steps(out: Path, number: int) -> list[int]:
    path = out / STUDY / f"trial_{number:04d}" / "evaluations.json"
    try:
        return [e["steps"] for e in json.loads(path.read_text())]
    except (FileNotFoundError, json.JSONDecodeError):  # not written yet (it is replaced atomically)
        return []


def trainer_pid(out: Path, number: int) -> int:
    """The pid of the process that trained trial ``number`` (its run directory's lock file)."""
    return int((out / STUDY / f"trial_{number:04d}" / ".lock").read_text().split()[1])


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::optuna.exceptions.ExperimentalWarning")
def test_two_workers_on_postgres_one_killed_mid_trial(tmp_path):
    """Workers A and B start together on a study of 2 trials (heartbeat 1 s, grace 2 s); the one training
    trial 0 is killed with SIGKILL. The other finishes trial 1, then fails trial 0 (stale heartbeat) and runs
    it again with the same parameters as trial 2: 2 trials completed, none counted twice."""
    password = secrets.token_hex(12)
    out = tmp_path / "tune"
    with throwaway_postgres(password) as (url, folder, port):
        argv = ["--algo", "ppo", "--env", "IiwaReach-v0", "--trials", "2", "--timesteps", str(STEPS),
                "--n-envs", "4", "--out", str(out), "--storage", url, "--heartbeat", "1", "--grace", "2",
                "--hyperparams", "eval_goals=16", "eval_freq=128", "checkpoint_freq=100000"]
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), *sys.path])}
        logs = [(tmp_path / f"worker{i}.out", tmp_path / f"worker{i}.err") for i in range(2)]
        workers = []
        for stdout, stderr in logs:
            with open(stdout, "wb") as o, open(stderr, "wb") as e:
                workers.append(subprocess.Popen([sys.executable, "-m", "train.tune", *argv], cwd=ROOT, env=env,
                                                stdout=o, stderr=e))
        try:
            guard = time.monotonic() + HANG_GUARD
            while not (any(s >= 128 for s in evaluated_steps(out, 0)) and evaluated_steps(out, 1)):
                assert all(w.poll() is None for w in workers), \
                    "a worker exited early: " + "".join(err.read_text()[-2000:] for _, err in logs)
                assert time.monotonic() < guard, "hung: trials 0 and 1 never trained"
                time.sleep(0.05)
            (victim,) = [w for w in workers if w.pid == trainer_pid(out, 0)]
            (survivor,) = [w for w in workers if w is not victim]
            assert trainer_pid(out, 1) == survivor.pid
            killed_at = max(evaluated_steps(out, 0))
            victim.send_signal(signal.SIGKILL)
            assert victim.wait(timeout=HANG_GUARD) == -signal.SIGKILL
            assert survivor.wait(timeout=HANG_GUARD) == 0, logs[workers.index(survivor)][1].read_text()[-3000:]
        finally:
            for w in workers:
                if w.poll() is None:
                    w.kill()
                    w.wait()

        trials = optuna.load_study(study_name=STUDY, storage=url).trials
        assert [t.state for t in trials] == [TrialState.FAIL, TrialState.COMPLETE, TrialState.COMPLETE], \
            "the survivor fails the killed trial 0 and runs it again (its own trial 1 outlasting the grace period)"
        killed, first, retry = trials
        assert killed.value is None and max(killed.intermediate_values) <= killed_at < STEPS  # stopped mid-trial
        assert RetryHeartbeatStaleTrialCallback.retried_trial_number(retry) == 0
        assert retry.params == killed.params and retry.distributions == killed.distributions
        assert first.params != killed.params
        for t in (first, retry):  # complete records: the values and curves the trainings measured
            evaluations = json.loads((out / STUDY / f"trial_{t.number:04d}" / "evaluations.json").read_text())
            assert t.value == evaluations[-1]["success"]
            assert t.intermediate_values == {e["steps"]: e["success"] for e in evaluations}
            assert max(t.intermediate_values) == STEPS
            assert trainer_pid(out, t.number) == survivor.pid
            assert t.user_attrs["config"]["hyperparams"]["n_steps"] == t.params["n_steps"]
        best = yaml.safe_load((out / STUDY / "best.yaml").read_text())["tune"]
        assert best["storage"] == url.replace(password, "***")

        written = [path for path in out.rglob("*") if path.is_file()]  # configs, best.yaml, models, logs
        assert written and not [p for p in written + [f for pair in logs for f in pair]
                                if password.encode() in p.read_bytes()]
        assert password not in repr([(t.user_attrs, t.system_attrs) for t in trials])
        assert "tune:***@127.0.0.1" in logs[workers.index(survivor)][0].read_text()
    assert not folder.exists()
    with pytest.raises(ConnectionRefusedError), socket.create_connection(("127.0.0.1", port), timeout=10):
        pass


def test_tables_created_by_another_worker_at_the_same_time_are_used(tmp_path, monkeypatch):
    """Two workers starting on an empty database both create Optuna's tables; the slower one's CREATE fails
    (PostgreSQL: a unique violation) after the other's committed, and it opens the storage again."""
    url, real, calls = f"sqlite:///{tmp_path / 'study.db'}", optuna.storages.RDBStorage, []

    def racing(*args, **kwargs):
        calls.append(args)
        if len(calls) == 1:
            real(*args, **kwargs)  # the other worker's tables, committed
            raise IntegrityError("CREATE TYPE", {}, Exception('duplicate key value violates unique constraint'))
        return real(*args, **kwargs)

    monkeypatch.setattr(optuna.storages, "RDBStorage", racing)
    storage = tune.open_storage(url, heartbeat=5, grace=20)
    assert len(calls) == 2 and isinstance(storage, real)
    assert (storage.heartbeat_interval, storage.grace_period) == (5, 20)


@pytest.mark.parametrize("flags, message", [
    (["--heartbeat", "0"], "--heartbeat must be >= 1 and --grace above it, got 0 and 180"),
    (["--heartbeat", "60", "--grace", "60"], "--heartbeat must be >= 1 and --grace above it, got 60 and 60"),
    (["--grace", "1.5"], "argument --grace: invalid int value: '1.5'"),
])
def test_bad_heartbeat_flags_are_a_one_line_error(tmp_path, capsys, flags, message):
    argv = ["--algo", "ppo", "--env", "IiwaReach-v0", "--trials", "1", "--out", str(tmp_path / "t"), *flags]
    with pytest.raises(SystemExit) as exc:
        tune.main(argv)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and message in err and "Traceback" not in err
    assert not (tmp_path / "t").exists()
