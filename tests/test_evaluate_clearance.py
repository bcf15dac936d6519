"""The collision columns of ``train.evaluate``: by hand on configurations whose flange is known to be
below the floor, and on a small evaluation of a shipped policy, recomputed with ``collision.clearance``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

import envs
from iiwa_torch.collision import clearance, pairwise_clearance, robot_capsules
from train import evaluate as ev
from train.rollout import PolicyEvaluator, make_goal_set

# a policy that reads no clearance rows, so that it also runs with collision="off"
POLICY = Path(__file__).resolve().parents[1] / "train" / "policies" / "ppo_iiwa_reach_mlp"
GOALS, SEED = 64, 3


def clearance_of(chain, q: np.ndarray, columns: list[bool]) -> np.ndarray:
    """``q (..., 7)`` -> ``(...)`` smallest distance over the pairs marked in ``columns``."""
    return pairwise_clearance(chain, torch.as_tensor(q)).distance[..., columns].amin(-1).numpy()


def _chain():
    return envs.make_task("IiwaReach-v0").robot


def test_a_step_below_the_floor_is_counted_for_the_path_not_the_final_configuration():
    chain = _chain()
    home = torch.zeros(7, dtype=torch.float64)  # upright
    down = torch.tensor([0.0, 2.0, 0.0, 0.0, 0.0, 0.0, 0.0], dtype=torch.float64)  # shoulder 2 rad, within limits
    flange_z = chain.fk(down[None])[0, 2, 3].item()
    # independent of the capsule model: the flange itself is below z = 0, so its capsule is too
    assert flange_z < 0 and bool(chain.within_limits(down[None]).all())
    path = torch.stack([torch.stack([home, home]), torch.stack([down, home]), torch.stack([home, home])])  # (3, 2, 7)
    m, floor_hit, collided = ev.collision_metrics(chain, path.numpy())
    assert floor_hit.tolist() == [True, False] and collided.tolist() == [True, False]
    assert (m["collisions"], m["floor_collisions"], m["self_collisions"], m["final_collisions"]) == (1, 1, 0, 0)
    assert m["collision_share"] == 0.5
    assert m["min_clearance_worst_m"] <= flange_z
    lowest = clearance(chain, path, capsules=robot_capsules(chain)).amin(0)
    assert np.isclose(m["min_clearance_median_m"], lowest.mean().item(), atol=1e-12)
    ended_down, *_ = ev.collision_metrics(chain, torch.stack([home, down])[None].numpy())
    assert (ended_down["collisions"], ended_down["final_collisions"]) == (1, 1)


def test_report_collision_fields_agree_with_a_recomputation(tmp_path):
    out = tmp_path / "report"
    # collision=off: goals over the whole joint range, some below the floor (the default env draws none there)
    assert ev.main(["--model", str(POLICY), "--goals", str(GOALS), "--seed", str(SEED), "--out", str(out),
                    "--env-kwargs", "collision='off'"]) == 0  # quoted: YAML reads a bare off as False
    report = json.loads((out / "report.json").read_text())
    assert report["env_kwargs"]["collision"] == "off"
    finals = np.load(out / "final_q.npz")
    chain = _chain()
    capsules = robot_capsules(chain)
    goals = make_goal_set("IiwaReach-v0", GOALS, SEED, report["env_kwargs"])  # the goals train.evaluate used
    below = (goals.pose[:, 2, 3] < 0).numpy()
    assert below.any(), "this goal set must hold a goal below the floor for the check to mean something"
    assert report["goals_below_floor"] == int(below.sum())
    for name in ev.METHODS:
        m = report["methods"][name]
        final = clearance(chain, torch.as_tensor(finals[name]), capsules=capsules).numpy()
        assert m["final_collisions"] == int((final < 0).sum()), name
        assert (final[below] < 0).all(), name  # a reached goal below the floor collides
        assert m["final_collisions"] >= int(below.sum()), name
        assert m["floor_collisions"] + m["self_collisions"] >= m["collisions"] >= m["final_collisions"], name
        if name != "policy":
            assert m["collisions"] == m["final_collisions"], name
            assert np.isclose(m["min_clearance_median_m"], np.median(final), atol=1e-9), name
            assert np.isclose(m["min_clearance_worst_m"], final.min(), atol=1e-9), name
    # the policy's whole rollout, run again (deterministic) and checked at every step
    model, vec_normalize, _ = ev.load_policy(POLICY)
    r = PolicyEvaluator(goals, ev.TOLERANCES["1cm"]).rollout(model, vec_normalize)
    assert np.allclose(r.q[-1], finals["policy"], atol=1e-9)
    lowest = clearance(chain, torch.as_tensor(r.q), capsules=capsules).amin(0).numpy()
    p = report["methods"]["policy"]
    assert p["collisions"] == int((lowest < 0).sum())
    assert np.isclose(p["collision_share"], np.mean(lowest < 0))
    assert np.isclose(p["min_clearance_median_m"], np.median(lowest), atol=1e-9)
    assert np.isclose(p["min_clearance_worst_m"], lowest.min(), atol=1e-9)
    # goal by goal: the floor contacts only one side has, recounted; and |A - B| - |B - A| = |A| - |B|
    floor = [b == "floor" for _, b in pairwise_clearance(chain, torch.as_tensor(r.q[:1]), capsules=capsules).pairs]
    policy_hit = clearance_of(chain, r.q, floor).min(0) < 0
    for name in ("analytic_ik", "gradient_ik"):
        v = report["methods"][name]
        ik_hit = clearance_of(chain, finals[name][None], floor)[0] < 0
        assert v["floor_policy_only"] == int((policy_hit & ~ik_hit).sum()), name
        assert v["floor_ik_only"] == int((ik_hit & ~policy_hit).sum()), name
        assert v["floor_policy_only"] - v["floor_ik_only"] == p["floor_collisions"] - v["floor_collisions"], name
    table = (out / "report.md").read_text()
    assert "min clearance" in table and any("Collisions (capsule model" in line for line in report["verdict"])
