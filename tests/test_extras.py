"""A missing optional dependency: every optional import names the extra that installs it
(``iiwa_torch.checks.require``); simulated by ``sys.modules[name] = None``, which makes
``import name`` raise ModuleNotFoundError as if it were not installed."""

from __future__ import annotations

import importlib
import sys

import pytest

from iiwa_torch import robots, urdf
from iiwa_torch.checks import MissingExtra, require
from iiwa_torch.cli import main


def _hide(monkeypatch, name: str) -> None:
    """Make ``name`` and its submodules look uninstalled for this test."""
    for module in [m for m in sys.modules if m.startswith(name + ".")]:
        monkeypatch.setitem(sys.modules, module, None)
    monkeypatch.setitem(sys.modules, name, None)


def _forget(monkeypatch, package: str) -> None:
    """Drop ``package`` and its submodules from ``sys.modules`` for this test (restored after it)."""
    for name in [m for m in sys.modules if m == package or m.startswith(package + ".")]:
        monkeypatch.delitem(sys.modules, name)


def test_require_returns_the_module():
    assert require("json", "viz") is importlib.import_module("json")
    assert require("os.path", "viz") is importlib.import_module("os.path")


def test_require_names_the_extra(monkeypatch):
    _hide(monkeypatch, "viser")
    with pytest.raises(ModuleNotFoundError, match=r"viser is not installed.*pip install 'iiwa-torch\[viewer\]'") as e:
        require("viser", "viewer")
    assert isinstance(e.value, MissingExtra) and e.value.name == "viser"
    _hide(monkeypatch, "matplotlib")
    with pytest.raises(MissingExtra, match=r"matplotlib is not installed.*iiwa-torch\[viz\]"):
        require("matplotlib.figure", "viz")


def test_require_leaves_a_missing_dependency_of_an_installed_package_alone(monkeypatch, tmp_path):
    (tmp_path / "pkg_with_a_missing_dep").mkdir()
    (tmp_path / "pkg_with_a_missing_dep" / "__init__.py").write_text("import dep_not_installed_anywhere\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(ModuleNotFoundError) as e:
        require("pkg_with_a_missing_dep", "viz")
    assert not isinstance(e.value, MissingExtra) and e.value.name == "dep_not_installed_anywhere"


@pytest.mark.parametrize(
    ("hidden", "extra", "call"),
    [
        ("matplotlib", "viz", lambda tmp: importlib.import_module("iiwa_torch.viz").render_rgb(robots.iiwa14(), None)),
        ("PIL", "viz", lambda tmp: importlib.import_module("iiwa_torch.viz").save_png(robots.iiwa14(), None, tmp)),
        ("viser", "viewer", lambda tmp: importlib.import_module("iiwa_torch.viewer").Viewer(robots.iiwa14())),
        ("pytorch_kinematics", "urdf", lambda tmp: robots.from_urdf(urdf.to_urdf(robots.iiwa14()))),
        (
            "matplotlib",
            "viz",
            lambda tmp: importlib.import_module("iiwa_torch.workspace").plot_workspace(
                robots.iiwa14(), tmp, n_samples=1000, h=0.05
            ),
        ),
    ],
)
def test_library_calls_name_the_extra(monkeypatch, tmp_path, hidden, extra, call):
    pytest.importorskip(hidden)  # the call must fail for the hidden module, not for another one
    _hide(monkeypatch, hidden)
    with pytest.raises(MissingExtra, match=rf"pip install 'iiwa-torch\[{extra}\]'"):
        call(tmp_path / "out.png")
    assert not (tmp_path / "out.png").exists()


@pytest.mark.parametrize(
    ("package", "hidden"),
    [("envs", "gymnasium"), ("train", "stable_baselines3"), ("train", "yaml"), ("envs.sb3", "stable_baselines3")],
)
def test_importing_envs_and_train_names_the_rl_extra(monkeypatch, package, hidden):
    _forget(monkeypatch, package.partition(".")[0])
    _hide(monkeypatch, hidden)
    with pytest.raises(MissingExtra, match=rf"{hidden} is not installed.*pip install 'iiwa-torch\[rl\]'"):
        importlib.import_module(package)


def test_tune_names_the_rl_extra(monkeypatch):
    pytest.importorskip("stable_baselines3")
    from train import tune

    _hide(monkeypatch, "optuna")
    with pytest.raises(MissingExtra, match=r"optuna is not installed.*iiwa-torch\[rl\]"):
        tune.counted_states()


def test_cli_view_without_viser_is_one_line_and_exit_2(monkeypatch, capsys):
    _hide(monkeypatch, "viser")
    with pytest.raises(SystemExit) as exit_info:
        main(["view", "--port", "1"])
    assert exit_info.value.code == 2
    captured = capsys.readouterr()
    assert captured.out == ""  # no URL of a server that never starts
    assert captured.err == (
        "iiwa-torch view: error: viser is not installed; it comes with the viewer extra: "
        "pip install 'iiwa-torch[viewer]'\n"
    )


def test_cli_urdf_without_the_urdf_extra_is_one_line_and_exit_2(monkeypatch, capsys, tmp_path):
    path = tmp_path / "arm.urdf"
    path.write_text(urdf.to_urdf(robots.iiwa14()))
    _hide(monkeypatch, "pytorch_kinematics")
    with pytest.raises(SystemExit) as exit_info:
        main(["robots", "--urdf", str(path)])
    assert exit_info.value.code == 2
    assert capsys.readouterr().err.endswith("pytorch_kinematics is not installed; it comes with the urdf extra: "
                                            "pip install 'iiwa-torch[urdf]'\n")


def test_cli_policy_playback_without_the_rl_extra_is_one_line(monkeypatch, capsys):
    pytest.importorskip("viser")
    _forget(monkeypatch, "envs")
    _forget(monkeypatch, "train")
    _hide(monkeypatch, "gymnasium")
    with pytest.raises(SystemExit) as exit_info:
        main(["view", "--policy", "train/policies/ppo_iiwa_reach"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "pip install 'iiwa-torch[rl]'" in err


def test_numba_missing_is_silently_off():
    """numba (the fast extra) is the one optional import that is not an error: the kernels are off."""
    import subprocess

    code = "import sys; sys.modules['numba'] = None; from iiwa_torch import compiled; print(compiled.ENABLED)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False" and out.stderr == ""
