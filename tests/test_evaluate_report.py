"""The report's accuracy figures: the README's comparison row recomputed, number spacings by hand,
and a verdict that does not rank rounding against rounding."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

import envs
from train import evaluate as ev
from train.rollout import make_goal_set

ROOT = Path(__file__).resolve().parents[1]
POLICY = ROOT / "train" / "policies" / "ppo_iiwa_reach"
README_ROWS = {
    "policy": "policy (50 closed-loop steps)",
    "controller": "controller: DLS step + damper alone (no network)",
    "analytic_ik": "analytic IK (arm-angle sweep, with the floor)",
    "gradient_ik": "gradient IK (with the floor)",
}


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def _readme_rows() -> dict[str, list[str]]:
    rows = {}
    for line in (ROOT / "README.md").read_text().splitlines():
        cells = _cells(line) if line.startswith("|") else []
        for name, label in README_ROWS.items():
            if cells and cells[0] == label:
                rows[name] = cells
    return rows


# float32's spacing at the goals' 0.5-2 m is 6e-8-1.2e-7 m a coordinate (float64's: 1.1e-16-2.2e-16 m): a
# median error below 1e-6 m (about 10 float32 spacings; the success tolerances are 1 mm and 1 cm) is the
# rounding of the number format (the analytic IK's float64, the gradient IK's float32 iterations), whose last
# digits follow the CPU's vector kernels: the README's 1.25e-13 mm and 8.25e-05 mm (an Intel Xeon) are 1.27e-13 mm
# and 8.2e-05 mm on an AMD EPYC with AVX-512, from the same code.
ROUNDING_FLOOR_M = 1e-6


def _assert_same_median(readme: str, printed: str, name: str) -> None:
    """The README's median-error cell is the printed one, as text; for an error that is rounding (both below
    :data:`ROUNDING_FLOOR_M`) the README's cell is in the command's format (3 significant digits, mm) and
    within a factor of 2 of the printed value: its magnitude is checked, its last digits are not."""
    if readme == printed:
        return
    message = f"{name}: README says {readme}, the command prints {printed}"
    shown, got = (float(cell.removesuffix(" mm")) * 1e-3 for cell in (readme, printed))
    assert readme == f"{shown * 1e3:.3g} mm" and printed == f"{got * 1e3:.3g} mm", message
    assert max(shown, got) < ROUNDING_FLOOR_M, message
    assert max(shown, got) <= 2 * min(shown, got), message


def test_readme_comparison_row_is_what_the_shipped_command_prints(tmp_path):
    """The README's row is the printed table of ``python -m train.evaluate --model train/policies/ppo_iiwa_reach
    --goals 1000 --seed 0``: this runs that evaluation's methods on the same 1,000 goals (single-threaded, as
    the command is) and formats them with the command's own table. The wall-time column is not checked: it
    is a measurement of the machine; nor are the last digits of a median error that is rounding (they follow
    the CPU: :func:`_assert_same_median`). Every other cell is compared as text."""
    readme = _readme_rows()
    assert set(readme) == set(README_ROWS), "the README's comparison table lost a row"
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as evaluate(): the reduction order, hence the float32 rounding, follows it
    try:
        model, vec_normalize, config = ev.load_policy(POLICY)
        env_kwargs = config["hyperparams"].get("env_kwargs") or {}  # as the command: the env it was trained on
        task = envs.make_task(config["env_id"], **env_kwargs)
        goals = make_goal_set(config["env_id"], 1000, 0, env_kwargs)
        metrics, data = {}, {}
        metrics["policy"], data["policy"] = ev.run_policy(goals, model, vec_normalize, task.robot)
        metrics["controller"], _ = ev.run_policy(goals, ev.controller_alone(model), vec_normalize, task.robot)
        for name in ("analytic_ik", "gradient_ik"):
            metrics[name], _ = ev.run_ik(name, goals, task.robot, data["policy"]["home"], task.dt, ev.ik_world(task))
    finally:
        torch.set_num_threads(threads)
    report = {"goals": 1000, "env_id": config["env_id"], "model": str(POLICY), "algo": "ppo", "seed": 0,
              "machine": {"loadavg": [0.0], "cpu_count": 1, "cpu": "-", "torch_threads": 1},
              "methods": metrics, "verdict": [], "plots": []}
    table = ev.write_markdown(report, tmp_path / "report.md").splitlines()
    header = _cells(table[0])
    printed = {_cells(line)[0]: dict(zip(header, _cells(line))) for line in table[2:]}
    for name, cells in readme.items():
        row = printed[name]
        assert cells[1:3] == [row["success @1 cm"], row["@1 mm"]], name
        _assert_same_median(cells[3], row["median error"], name)
        share = 100 * metrics[name]["collision_share"]
        assert cells[5].startswith(f"{share:.1f}% of"), name


def test_number_spacing_by_hand():
    """float32 stores 0.5 = 2^-1 with 23 fraction bits, so its spacing there is 2^-24; 0.25: 2^-25; 1.0: 2^-23
    (float64: 52 bits)."""
    xyz = np.array([[0.5, -0.25, 1.0]])
    expected32 = np.sqrt(2.0**-48 + 2.0**-50 + 2.0**-46)
    expected64 = np.sqrt(2.0**-106 + 2.0**-108 + 2.0**-104)
    np.testing.assert_allclose(ev.number_spacing(xyz, np.float32), [expected32], rtol=1e-15)
    np.testing.assert_allclose(ev.number_spacing(xyz, np.float64), [expected64], rtol=1e-15)


def _method(median: float, p95: float, success_1mm: float = 1.0) -> dict:
    return {"median_error_m": median, "p95_error_m": p95, "success@1cm": 1.0, "success@1mm": success_1mm,
            "median_steps_to_reach": None, "time_per_goal_batched_s": 1e-4, "network_time_per_goal_batched_s": 1e-4,
            "time_per_goal_single_s": 1e-2, "median_path_length_rad": 1.0, "collisions": 0, "collision_share": 0.0,
            "floor_collisions": 0, "self_collisions": 0, "final_collisions": 0, "min_clearance_median_m": 0.2,
            "min_clearance_worst_m": 0.1, "floor_policy_only": 0, "floor_ik_only": 0}


SPACING = {"float32": 7.3e-8, "float64": 1.36e-16}  # about the median spacings at 0.5-1 m


def _accuracy(policy: dict, other: dict) -> str:
    lines = ev.verdict({"policy": policy, "other_ik": other}, 0, SPACING)
    return next(line for line in lines if line.startswith("Accuracy against other_ik"))


def test_verdict_does_not_rank_float32_rounding_against_float64_rounding():
    line = _accuracy(_method(3.7e-8, 4.7e-5, 0.986), _method(1.3e-16, 3.2e-16))
    assert "orders of magnitude" not in line
    assert "the policy's is 0.5 float32 spacings" in line and "other_ik's 1.0 float64 spacings" in line
    assert "the gap between them is the number format" in line
    assert "at 1 mm 98.6% against 100.0%" in line  # what is real still compared
    assert "3.2e-13 mm (at float64's floor)" in line


def test_verdict_calls_two_float32_medians_a_tie():
    line = _accuracy(_method(3.7e-8, 4.7e-5), _method(8.2e-8, 2.9e-5))
    assert "both are float32 rounding" in line and "do not rank" in line
    assert "orders of magnitude" not in line and "times" not in line


@pytest.mark.parametrize("policy, other, words", [
    (2e-3, 2e-5, "2.0 orders of magnitude above other_ik's"),  # both far above float32's floor
    (3e-5, 1e-5, "3 times other_ik's"),
    (2e-3, 1e-16, "other_ik's is float64 rounding (0.7 spacings at the goal) and the policy's is not"),
])
def test_verdict_compares_real_errors(policy, other, words):
    assert words in _accuracy(_method(policy, 1e-2), _method(other, 1e-2))
