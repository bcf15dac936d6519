"""The ``iiwa-torch`` command: JSON outputs against the validation poses of Pereira et al., fk -> ik round trips,
trajectory files, and clear non-zero exits for bad arguments."""

import csv
import json
import math
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from urdf_samples import ODD_URDF

from iiwa_torch import robots, so3
from iiwa_torch.cli import main

F64 = torch.float64


def _run_json(capsys, *argv):
    assert main([*argv, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def _fails(capsys, *argv) -> str:
    with pytest.raises(SystemExit) as exit_info:
        main(list(argv))
    assert exit_info.value.code != 0
    return capsys.readouterr().err


def test_fk_validation_pose_matches_pereira_et_al(capsys):
    out = _run_json(capsys, "fk", "0", "0", "0", "-90", "60", "0", "0", "--flange", "0.090")
    s3 = math.sqrt(3) / 2
    expected = [[0, 0, 1, 0.490], [s3, 0.5, 0, 0], [-0.5, s3, 0, 0.780], [0, 0, 0, 1]]
    torch.testing.assert_close(
        torch.tensor(out["pose"], dtype=F64), torch.tensor(expected, dtype=F64), rtol=0, atol=1e-12
    )
    assert out["xyz_m"] == pytest.approx([0.49, 0.0, 0.78], abs=1e-12)
    assert out["within_limits"] is True
    rad = _run_json(
        capsys, "fk", *(str(v) for v in [0, 0, 0, -math.pi / 2, math.pi / 3, 0, 0]), "--rad", "--flange", "0.09"
    )
    torch.testing.assert_close(torch.tensor(rad["pose"]), torch.tensor(out["pose"]), rtol=0, atol=1e-12)


def test_fk_prints_a_table_with_xyz_and_rpy(capsys):
    assert main(["fk", "0", "0", "0", "-90", "60", "0", "0", "--flange", "0.090"]) == 0
    text = capsys.readouterr().out
    assert "0.4900 0.0000 0.7800" in text and "rpy (deg)" in text


@pytest.mark.parametrize(("robot", "method"), [("iiwa14", "analytic"), ("iiwa14", "gradient"), ("puma560", "analytic")])
def test_fk_then_ik_returns_the_pose(capsys, robot, method):
    chain = robots.PRESETS[robot]()
    q_deg = [20, 35, -15, -70, 25, 40, 10][: chain.n_joints]
    fk = _run_json(capsys, "fk", *map(str, q_deg), "--robot", robot)
    flat = [str(v) for row in fk["pose"] for v in row]
    extra = ["--psi", "0"] if robot == "iiwa14" and method == "analytic" else []
    ik = _run_json(capsys, "ik", "--pose", *flat, "--robot", robot, "--method", method, *extra)
    target = torch.tensor(fk["pose"], dtype=F64)
    valid = [s for s in ik["solutions"] if s["valid"]]
    assert valid, ik
    if method == "analytic":
        assert len(ik["solutions"]) == 8  # every branch is listed
    for sol in valid:
        q = torch.tensor(sol["q_rad"], dtype=F64)
        pos, rot = so3.pose_error(chain.fk(q), target)  # recomputed here, not read from the output
        assert pos.norm() < 1e-8 and rot.norm() < 1e-8
    if robot == "puma560":  # the configuration we started from is one of the 8 branches
        dist = min(max(abs(a - math.radians(b)) for a, b in zip(s["q_rad"], q_deg)) for s in valid)
        assert dist < 1e-9


def test_ik_from_xyz_rpy(capsys):
    """The validation pose as x y z roll pitch yaw; shoulder and wrist are aligned there
    (q2 = q6 = 0), so only q1 + q3 and q5 + q7 are determined."""
    out = _run_json(capsys, "ik", "--pose", "0.49", "0", "0.78", "90", "30", "90", "--flange", "0.090")
    found = []
    for sol in out["solutions"]:
        q1, q2, q3, q4, q5, q6, q7 = sol["q_rad"]
        found.append(
            sol["valid"] and max(abs(q2), abs(q6), abs(q1 + q3), abs(q4 + math.pi / 2), abs(q5 + q7 - math.pi / 3))
        )
    assert any(f is not False and f < 1e-9 for f in found)


def test_traj_joint_space_writes_csv_and_gif(capsys, tmp_path):
    from PIL import Image

    csv_file, gif = tmp_path / "j.csv", tmp_path / "j.gif"
    start, end = ["0", "30", "0", "-60", "0", "60", "0"], ["40", "30", "0", "-60", "0", "60", "0"]
    files = ["--csv", str(csv_file), "--gif", str(gif), "--size", "96"]
    out = _run_json(capsys, "traj", "--from-q", *start, "--to-q", *end, "--steps", "6", *files)
    assert out["duration_s"] == pytest.approx(15 / 8 * 40 / 85)  # A1 moves 40 deg at 85 deg/s
    with open(csv_file) as f:
        rows = list(csv.reader(f))
    assert len(rows) == 7 and rows[0][0] == "t_s" and float(rows[-1][2]) == pytest.approx(math.radians(30))
    assert float(rows[-1][1]) == pytest.approx(math.radians(40), abs=1e-9)
    with Image.open(gif) as im:
        assert im.n_frames == 6


def test_traj_cartesian_line_is_tracked(capsys, tmp_path):
    start, goal = ["0", "30", "0", "-80", "0", "70", "0"], ["0.5", "0.3", "0.5", "180", "0", "180"]
    out = _run_json(
        capsys, "traj", "--from-q", *start, "--to-pose", *goal, "--steps", "15", "--csv", str(tmp_path / "c.csv")
    )
    assert out["all_success"] and out["max_pos_err_m"] < 1e-9 and out["max_joint_step_rad"] < 0.2
    end = robots.iiwa14().fk(torch.tensor(out["q_rad"][-1], dtype=F64))
    assert end[:3, 3].tolist() == pytest.approx([0.5, 0.3, 0.5], abs=1e-9)


def test_traj_between_poses_solves_the_start_first(capsys):
    start, goal = ["0.5", "0.0", "0.5", "180", "0", "180"], ["0.5", "0.2", "0.5", "180", "0", "180"]
    out = _run_json(capsys, "traj", "--from-pose", *start, "--to-pose", *goal, "--steps", "5", "--method", "gradient")
    ends = robots.iiwa14().fk(torch.tensor(out["q_rad"], dtype=F64)[[0, -1]])[:, :3, 3]
    assert ends.tolist() == [pytest.approx([0.5, 0.0, 0.5], abs=1e-6), pytest.approx([0.5, 0.2, 0.5], abs=1e-6)]


def test_robots_list_and_table(capsys):
    names = [r["name"] for r in _run_json(capsys, "robots")]
    assert names == list(robots.PRESETS)
    table = _run_json(capsys, "robots", "iiwa14")
    assert table["dh_rows_a_alpha_d_offset"][0] == pytest.approx([0, -math.pi / 2, 0.36, 0])
    assert table["velocity_limits_rad_s"][3] == pytest.approx(math.radians(75))
    assert main(["robots", "puma560"]) == 0 and "puma560" in capsys.readouterr().out


def test_robots_prints_a_urdf_arms_joints(capsys, tmp_path):
    path = tmp_path / "odd.urdf"
    path.write_text(ODD_URDF)
    out = _run_json(capsys, "robots", "--urdf", str(path), "--end-link", "tip")
    joints = {j["name"]: j for j in out["joints"]}
    assert list(joints) == ["j1", "j2", "j3", "j4"]  # the fixed joints folded, the side branch left out
    assert [j["kind"] for j in joints.values()] == ["revolute", "prismatic", "continuous", "revolute"]
    # the numbers written in ODD_URDF; the axis normalised
    assert joints["j1"]["axis"] == pytest.approx([0.2 / math.sqrt(1.01), -0.4 / math.sqrt(1.01), 0.9 / math.sqrt(1.01)])
    assert (joints["j2"]["min"], joints["j2"]["max"]) == (-0.1, 0.3)
    assert {j["velocity_limit"] for j in joints.values()} == {None}  # j3 has none: a chain's speeds are all or none
    assert (joints["j3"]["min"], joints["j3"]["max"], joints["j3"]["child_link"]) == (None, None, "d")
    assert main(["robots", "--urdf", str(path), "--end-link", "tip"]) == 0
    table = capsys.readouterr().out
    assert re.search(r"j2 .* prismatic .* 0\.707 0\.707 0 .* -0\.1 .* 0\.3 .* - ", table)
    assert re.search(r"j4 .* revolute .* 0 0 -1 .* -57\.3 .* 57\.3 ", table)  # 1 rad in degrees
    assert "leaf links below 'root' (tip, side); pass --end-link" in _fails(capsys, "robots", "--urdf", str(path))


def test_a_prismatic_joint_is_read_and_shown_in_metres(capsys, tmp_path):
    path = tmp_path / "odd.urdf"
    path.write_text(ODD_URDF)
    odd = ["--urdf", str(path), "--end-link", "tip"]
    out = _run_json(capsys, "fk", "10", "0.1", "20", "30", *odd)  # j2 slides 0.1 m
    assert out["q_rad"] == pytest.approx([math.radians(10), 0.1, math.radians(20), math.radians(30)], abs=1e-15)
    target = [str(v) for v in out["xyz_m"]]
    assert main(["ik", "--pose", *target, *odd, "--seed", "3"]) in (0, 1)
    text = capsys.readouterr().out
    assert "joints in deg, m for prismatic" in text
    row = next(line for line in text.splitlines() if " lm " in line).replace("│", " ").split()
    assert -0.1 <= float(row[2]) <= 0.3  # j2 within its limits in metres (in degrees it would read ~ +-6)


def test_ik_without_psi_finds_an_arm_angle_where_psi_0_has_no_valid_branch(capsys):
    straight_down = ["--pose", "0.5", "0", "0.4", "180", "0", "0"]  # at psi = 0 every branch has a joint at 180 deg
    assert main(["ik", *straight_down, "--psi", "0"]) == 1
    capsys.readouterr()
    out = _run_json(capsys, "ik", *straight_down)
    valid = [torch.tensor(s["q_rad"], dtype=F64) for s in out["solutions"] if s["valid"]]
    arm = robots.iiwa14()
    assert len(valid) == 8 and all(bool(arm.within_limits(q)) for q in valid)
    pose = arm.fk(torch.stack(valid))
    assert (pose[:, :3, 3] - torch.tensor([0.5, 0.0, 0.4], dtype=F64)).norm(dim=-1).max() < 1e-9
    assert (pose[:, :3, 2] - torch.tensor([0.0, 0.0, -1.0], dtype=F64)).norm(dim=-1).max() < 1e-9  # z down


def test_demo_runs(capsys, tmp_path):
    assert main(["demo", "--batch", "64", "--out", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    assert "0.4900 0.0000 0.7800" in text and str(tmp_path / "tracked_line.gif") in text
    assert (tmp_path / "tracked_line.gif").exists()


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["fk", "1", "2", "3"], "needs 7 joint angles for iiwa14, got 3"),
        (["fk", "0", "0", "0", "0", "0", "x", "0"], "invalid float value"),
        (["fk", "0", "0", "0", "0", "0", "0", "0", "--robot", "ur5"], "invalid choice"),
        (["fk", "0", "0", "0", "0", "0", "0", "--robot", "puma560", "--flange", "0.1"], "iiwa presets only"),
        (["ik", "--pose", "1", "2", "3", "4"], "6 numbers"),
        (["ik", "--pose", *["1"] * 16], "not a homogeneous transform"),
        (
            ["ik", "--pose", "1", "0", "0", "0", "0", "-1", "0", "0", "0", "0", "1", "0", "0", "0", "0", "1"],
            "homogeneous",
        ),
        (["fk", "0", "0", "0", "nan", "0", "0", "0"], "NaN or inf"),
        (["ik", "--pose", "0.5", "0", "0.5", "--method", "analytic"], "needs --method gradient"),
        (["traj", "--from-q", *["0"] * 7], "exactly one of"),
        (["traj", "--from-q", *["0"] * 7, "--to-q", *["1"] * 7, "--steps", "1"], "at least 2"),
        (["traj", "--from-q", *["0"] * 7, "--to-q", *["1"] * 7, "--size", "0"], "--size and --fps must be positive"),
        (["traj", "--from-q", *["0"] * 7, "--to-q", *["1"] * 7, "--fps", "0"], "--size and --fps must be positive"),
        (["robots", "abb"], "unknown robot"),
        (["robots", "--robot", "puma560"], "unrecognized arguments: --robot"),  # was ignored: all presets
        (["ik", "--robot", "puma560", "--pose", "0.5", "0", "0.5", "180", "0", "180", "--psi", "10"], "--psi is"),
        (["ik", "--pose", "0.5", "0", "0.5", "180", "0", "180", "--method", "gradient", "--psi", "10"], "--psi is"),
        (["traj", "--from-q", *["0"] * 7, "--to-q", *["1"] * 7, "--duration", "0"], "--duration must be positive"),
        (["traj", "--from-q", *["0"] * 7, "--to-q", *["1"] * 7, "--duration", "-1"], "--duration must be positive"),
        (["frobnicate"], "invalid choice"),
        (["workspace", "--json", "--seed", str(2**70)], "--seed: must be in [0, 2**63)"),  # torch's overflow before
    ],
)
def test_bad_arguments_exit_non_zero_with_a_message(capsys, argv, message):
    assert message in _fails(capsys, *argv)


def test_console_script_exits_non_zero():
    exe = Path(sys.executable).with_name("iiwa-torch")  # installed beside the interpreter
    assert exe.exists(), "the iiwa-torch console script is not installed"
    proc = subprocess.run([str(exe), "fk", "1", "2"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "needs 7 joint angles" in proc.stderr


def test_position_only_ik_reaches_the_point(capsys):
    out = _run_json(capsys, "ik", "--pose", "0.5", "0.1", "0.4")
    (sol,) = out["solutions"]
    q = torch.tensor(sol["q_rad"], dtype=F64)
    assert sol["valid"] is True
    torch.testing.assert_close(robots.iiwa14().position(q), torch.tensor([0.5, 0.1, 0.4], dtype=F64), atol=1e-8, rtol=0)


def test_planar_analytic_ik_hits_the_pose(capsys):
    out = _run_json(capsys, "ik", "--robot", "planar3r", "--pose", "1", "0.5", "0", "0", "0", "30")
    arm = robots.planar3r()
    assert len(out["solutions"]) == 2 and all(s["valid"] for s in out["solutions"])
    for sol in out["solutions"]:
        pose = arm.fk(torch.tensor(sol["q_rad"], dtype=F64))
        assert pose[:2, 3].tolist() == pytest.approx([1.0, 0.5], abs=1e-9)
        assert math.atan2(pose[1, 0], pose[0, 0]) == pytest.approx(math.radians(30), abs=1e-9)


def test_unreachable_ik_exits_1_with_a_message(capsys):
    assert main(["ik", "--pose", "3", "0", "0", "0", "0", "0"]) == 1
    assert "no valid solution" in capsys.readouterr().err
    assert main(["ik", "--pose", "3", "0", "0", "0", "0", "0", "--json"]) == 1
    out = json.loads(capsys.readouterr().out)["solutions"]
    assert all(s["why_invalid"].startswith("misses the target by") for s in out)


IIWA_LIMITS_DEG = (170, 120, 170, 120, 170, 120, 175)  # KUKA's datasheet, LBR iiwa 14 R820


def test_ik_says_why_a_branch_is_invalid(capsys):
    out = _run_json(capsys, "ik", "--pose", "0.49", "0", "0.78", "90", "30", "90", "--flange", "0.090")
    for sol in out["solutions"]:
        deg = [math.degrees(v) for v in sol["q_rad"]]
        limits = enumerate(zip(deg, IIWA_LIMITS_DEG))
        outside = [f"A{j + 1} = {round(d):d} deg outside +-{lim}" for j, (d, lim) in limits if abs(d) > lim]
        assert sol["valid"] == (not outside)
        assert sol["why_invalid"] == (", ".join(outside) or None)
    assert out["solutions"][0]["why_invalid"] == "A3 = -180 deg outside +-170"  # branch +++
    assert main(["ik", "--pose", "0.49", "0", "0.78", "90", "30", "90", "--flange", "0.090"]) == 0
    assert "+++ invalid: A3 = -180 deg outside +-170\n" in capsys.readouterr().out


def test_version(capsys):
    import tomllib

    pyproject = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out == f"iiwa-torch {pyproject['project']['version']}\n"


def test_demo_json(capsys, tmp_path):
    out = _run_json(capsys, "demo", "--batch", "64", "--out", str(tmp_path))
    s3 = math.sqrt(3) / 2  # Pereira et al.'s validation pose
    expected = [[0, 0, 1, 0.490], [s3, 0.5, 0, 0], [-0.5, s3, 0, 0.780], [0, 0, 0, 1]]
    torch.testing.assert_close(torch.tensor(out["validation_pose"]["pose"], dtype=F64),
                               torch.tensor(expected, dtype=F64), rtol=0, atol=1e-12)  # fmt: skip
    assert out["batched_calls"]["batch"] == 64 and out["batched_calls"]["analytic_solved"] == 1.0
    assert out["tracked_line"]["steps"] == 30 and out["tracked_line"]["max_pos_err_m"] < 1e-9
    assert out["files"] == [str(tmp_path / "tracked_line.gif")] and (tmp_path / "tracked_line.gif").exists()


def test_workspace_json_without_a_plot(capsys):
    out = _run_json(capsys, "workspace", "--samples", "200000")
    # KUKA's datasheet (iiwa 14): the wrist centre reaches B = 1180 mm up and G = 820 mm out; samples stay within
    assert 1.15 < out["z_max_m"] <= 1.180 + 1e-9 and 0.79 < out["r_max_m"] <= 0.820 + 1e-9
    assert out["point"] == "wrist" and out["files"] == []
    assert "give --plot PNG" in _fails(capsys, "workspace")


@pytest.mark.parametrize(
    "argv",
    [
        [
            "traj",
            "--from-q",
            "0",
            "0",
            "0",
            "0",
            "0",
            "0",
            "0",
            "--to-q",
            "0",
            "10",
            "0",
            "0",
            "0",
            "0",
            "0",
            "--csv",
            "no_such_folder/x.csv",
        ],
        ["fk", "0", "0", "0", "0", "0", "0", "0", "--plot", "no_such_folder/x.png"],
        ["demo", "--batch", "0"],
        ["demo", "--batch", "-1"],
    ],
)
def test_bad_paths_and_batches_exit_2(capsys, tmp_path, monkeypatch, argv):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "error:" in err and ("no_such_folder" in err or "--batch" in err)


def test_mp4_without_ffmpeg_is_a_usage_error(capsys, tmp_path, monkeypatch):
    monkeypatch.setattr("shutil.which", lambda name: None)
    argv = ["traj", "--from-q", *"0000000", "--to-q", "0", "10", *"00000", "--gif", str(tmp_path / "x.mp4")]
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    assert "ffmpeg" in capsys.readouterr().err


def test_rpy_never_prints_negative_zero(capsys):
    assert main(["fk", "0", "0", "0", "0", "0", "0", "0"]) == 0
    assert "-0.000" not in capsys.readouterr().out


def test_help_has_no_rest_markup_and_every_option_has_help(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    top = capsys.readouterr().out
    assert "``" not in top and "::" not in top
    from iiwa_torch.cli.parser import build_parser

    for sub in build_parser()._subparsers._group_actions[0].choices.values():
        for action in sub._actions:
            assert action.help, f"{sub.prog} {action.option_strings or action.dest} has no help text"


def test_launcher_sets_the_wait_policy_before_torch_loads():
    code = (
        "import iiwa_torch.cli as cli, os, sys; assert 'torch' not in sys.modules; "
        "sys.argv = ['iiwa-torch', 'robots']; cli.main(); print(os.environ['OMP_WAIT_POLICY'])"
    )
    env = {k: v for k, v in __import__("os").environ.items() if k != "OMP_WAIT_POLICY"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True).stdout
    assert out.strip().endswith("PASSIVE")


def test_drawing_without_the_viz_extra_names_the_extra(capsys, monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ModuleNotFoundError
    with pytest.raises(SystemExit) as exit_info:
        main(["fk", *"0000000", "--plot", str(tmp_path / "arm.png")])
    assert exit_info.value.code == 2
    assert "iiwa-torch[viz]" in capsys.readouterr().err
    assert not (tmp_path / "arm.png").exists()


def test_workspace_writes_the_side_view_and_rejects_a_missing_folder(capsys, tmp_path):
    from PIL import Image

    png = tmp_path / "side.png"
    assert main(["workspace", "--plot", str(png), "--samples", "200000", "--h", "0.02"]) == 0
    assert Image.open(png).size[0] > 400
    assert "does not exist" in _fails(capsys, "workspace", "--plot", str(tmp_path / "no" / "side.png"))
    assert "positive" in _fails(capsys, "workspace", "--plot", str(png), "--samples", "0")
    assert "positive" in _fails(capsys, "workspace", "--json", "--h", "nan")
    # matplotlib adds .png to another name: the file written would not be the one named (or reported)
    assert "--plot must name a .png file" in _fails(capsys, "workspace", "--plot", str(tmp_path / "side"))
    assert "--plot must name a .png file" in _fails(capsys, "workspace", "--plot", str(tmp_path))
    assert "--point wrist is the wrist centre of a 6- or 7-joint DH preset; use --point flange for planar3r" in _fails(
        capsys, "workspace", "--json", "--robot", "planar3r", "--point", "wrist")


def test_view_serves_on_localhost_and_stops_on_ctrl_c(tmp_path):
    pytest.importorskip("viser")
    import signal
    import socket
    import urllib.request

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen(
        [sys.executable, "-m", "iiwa_torch.cli", "view", "--port", str(port)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),  # a background shell may ignore Ctrl-C
    )
    try:
        banner = proc.stdout.readline()
        assert f"http://127.0.0.1:{port} (Ctrl-C" in banner
        for _ in range(600):  # wait for the server itself, not for a fixed time
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}", timeout=1) as page:
                    assert page.status == 200
                break
            except OSError:
                if proc.poll() is not None:
                    pytest.fail(f"the viewer exited: {proc.stdout.read()}")
                time.sleep(0.1)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=60) == 0
        assert (banner + proc.stdout.read()).count("http://") == 1  # the address, printed once
    finally:
        proc.kill()


def test_demo_larger_than_memory_is_refused_with_its_size(capsys, monkeypatch):
    from iiwa_torch import checks

    monkeypatch.setattr(checks, "available_memory", lambda: 10**9)
    err = _fails(capsys, "demo", "--no-gif", "--batch", str(10**6)).strip().splitlines()[-1]
    needed = float(re.search(r"demo --batch 1000000 needs about ([\d.]+) GB", err).group(1))
    assert needed >= 10**6 * (7 + 16) * 8 / 1e9  # at least its q and poses in float64
    assert "1 GB available" in err


def test_a_long_command_says_it_is_running_on_stderr_only(capsys):
    from iiwa_torch.cli.output import Elapsed

    with Elapsed("workspace", delay=0.05):
        time.sleep(0.3)  # the command's work
    out, err = capsys.readouterr()
    assert out == "" and "iiwa-torch workspace: running for 0 s" in err
    with Elapsed("fk"):  # a quick command prints nothing
        pass
    assert capsys.readouterr() == ("", "")


def test_any_arm_from_its_urdf(capsys):
    """fk and ik of a URDF robot: the pose of robots.from_urdf on the same file; the kuka_iiwa file is
    solved in closed form (its axes make an S-R-S arm), the Panda by the gradient IK; bad files and
    options are one-line usage errors."""
    pybullet_data = pytest.importorskip("pybullet_data")
    pytest.importorskip("pytorch_kinematics")
    data = Path(pybullet_data.getDataPath())
    panda_file = str(data / "franka_panda/panda.urdf")
    panda = robots.from_urdf(panda_file, end_link="panda_hand")
    q_deg = [10, 30, -20, -90, 15, 100, 40]
    out = _run_json(capsys, "fk", *map(str, q_deg), "--urdf", panda_file, "--end-link", "panda_hand")
    expected = panda.fk(torch.tensor([math.radians(v) for v in q_deg], dtype=F64))
    torch.testing.assert_close(torch.tensor(out["pose"], dtype=F64), expected, rtol=0, atol=1e-12)
    flat = [str(v) for row in out["pose"] for v in row]
    ik = _run_json(capsys, "ik", "--pose", *flat, "--urdf", panda_file, "--end-link", "panda_hand")
    assert ik["method"] == "gradient" and any(s["valid"] for s in ik["solutions"])
    kuka_file = str(data / "kuka_iiwa/model.urdf")
    kuka = robots.from_urdf(kuka_file)
    pose = kuka.fk(kuka.random_q(1, generator=torch.Generator().manual_seed(3))[0])
    ik = _run_json(capsys, "ik", "--pose", *map(str, pose.flatten().tolist()), "--urdf", kuka_file)
    assert ik["method"] == "analytic"
    valid = [s for s in ik["solutions"] if s["valid"]]
    assert valid
    for s in valid:
        reached = kuka.fk(torch.tensor(s["q_rad"], dtype=F64))
        assert (reached - pose).abs().max() < 1e-9
    traj = _run_json(capsys, "traj", "--urdf", panda_file, "--end-link", "panda_hand", "--from-q", *map(str, q_deg),
                     "--to-pose", "0.4", "0.1", "0.4", "180", "0", "0", "--steps", "10")
    assert traj["kind"] == "Cartesian line tracked by gradient IK" and traj["max_pos_err_m"] < 1e-6
    reach = _run_json(capsys, "workspace", "--urdf", panda_file, "--end-link", "panda_hand", "--samples", "20000")
    assert reach["point"] == "flange" and 0.7 < reach["r_max_m"] < 1.0  # the Panda's reach is about 0.855 m
    assert "no URDF file" in _fails(capsys, "fk", "0", "--urdf", "/no/such.urdf")
    if Path("/proc/self/mem").exists():  # a file that is there but cannot be read, even by root
        assert "cannot read it: Input/output error" in _fails(capsys, "fk", "0", "--urdf", "/proc/self/mem")
    assert "pass --end-link to choose" in _fails(capsys, "fk", "0", "--urdf", panda_file)
    assert "presets only" in _fails(capsys, "fk", "0", "--urdf", panda_file, "--robot", "iiwa14")
    assert "--urdf only" in _fails(capsys, "fk", "0", "--end-link", "tool0")
    assert "do not meet" in _fails(capsys, "ik", "--pose", *flat, "--urdf", panda_file, "--end-link", "panda_hand",
                                   "--method", "analytic")


def test_negative_numbers_in_e_notation_are_numbers_not_options(capsys):
    fk = _run_json(capsys, "fk", "0", "0", "0", "-9e1", "60", "-0.", "0")
    pose = [repr(v) for row in fk["pose"] for v in row]
    assert any("e-" in v and v.startswith("-") for v in pose)  # what fk --json prints, e.g. -5.3e-17
    ik = _run_json(capsys, "ik", "--pose", *pose)
    assert any(s["valid"] for s in ik["solutions"])
