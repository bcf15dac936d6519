"""``train.evaluate`` and the periodic evaluation on ``IiwaReachObstacles-v0``: each goal's obstacles
travel with the goal set, every method is checked against them.

Expected values: distances worked out by hand for the upright arm (q = 0: every capsule on the z
axis, end points from ``robot_capsules``: base 0-0.36 m r 0.11, upper arm 0.36-0.78 m r 0.09,
forearm 0.78-1.18 m r 0.08, wrist 1.18-1.306 m r 0.075), counts recounted goal by goal and
configuration by configuration with worlds built by hand, and the env's own observation.
"""

from __future__ import annotations

import json
import math

import gymnasium as gym
import numpy as np
import pytest
import torch

import envs
from envs.world import SLOT_SIZE
from iiwa_torch.collision import World, clearance, pairwise_clearance, robot_capsules
from iiwa_torch.robots import IIWA_HOME
from train import callbacks
from train import evaluate as ev
from train.rollout import GoalSet, PolicyEvaluator, Rollout, held_out_seed, make_goal_set

ENV = "IiwaReachObstacles-v0"
F = torch.float64
SLOTS = 4
UPRIGHT = np.zeros(7)
DOWN = np.array([0.0, 2.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # shoulder at 2 rad: the flange is below the floor


def sphere_slot(centre, radius):
    return [1, 0, *centre, radius, radius, radius, 1, 0]


def box_slot(centre, half, yaw):
    return [1, 1, *centre, *half, math.cos(yaw), math.sin(yaw)]


# Four goals' obstacles, with the upright arm's clearance to them by hand:
# 0: sphere r 0.05 at x = 0.2, z = 0.6 (beside the upper arm): 0.2 - 0.09 - 0.05 = 0.06
# 1: box half (0.1, 0.03, 0.1) turned 90 deg about z at y = 0.25, z = 1.0: its face at y = 0.15, beside
#    the forearm: 0.15 - 0.08 = 0.07 (unturned, the face would be at y = 0.22)
# 2: none: the arm's own closest pair, base top (0.36) to forearm bottom (0.78): 0.42 - 0.11 - 0.08 = 0.23
# 3: a sphere r 0.05 on the axis at z = 1.0 (inside the forearm): -(0.08 + 0.05); and a far box
HAND = [
    [sphere_slot((0.2, 0.0, 0.6), 0.05)],
    [box_slot((0.0, 0.25, 1.0), (0.1, 0.03, 0.1), math.pi / 2)],
    [],
    [box_slot((0.6, -0.6, 0.3), (0.05, 0.05, 0.05), 0.3), sphere_slot((0.0, 0.0, 1.0), 0.05)],
]
UPRIGHT_CLEARANCE = [0.06, 0.07, 0.23, -0.13]


def hand_block() -> np.ndarray:
    block = np.zeros((len(HAND), SLOTS * SLOT_SIZE), dtype=np.float32)
    for i, slots in enumerate(HAND):
        for k, slot in enumerate(slots):
            block[i, k * SLOT_SIZE : (k + 1) * SLOT_SIZE] = slot
    return block


def hand_world(i: int) -> World:
    """Goal ``i``'s world built directly from HAND (not from the slot decoder)."""
    spheres = [s for s in HAND[i] if s[1] == 0]
    boxes = [s for s in HAND[i] if s[1] == 1]
    kw = {}
    if spheres:
        kw["spheres"] = (torch.tensor([s[2:5] for s in spheres], dtype=F),
                         torch.tensor([s[5] for s in spheres], dtype=F))
    if boxes:
        poses = []
        for b in boxes:
            c, s = b[8], b[9]
            poses.append([[c, -s, 0, b[2]], [s, c, 0, b[3]], [0, 0, 1, b[4]], [0, 0, 0, 1]])
        kw["boxes"] = (torch.tensor(poses, dtype=F), torch.tensor([b[5:8] for b in boxes], dtype=F))
    return World(floor=0.0, **kw)


def hand_goals() -> GoalSet:
    chain = envs.make_task(ENV).robot
    n = len(HAND)
    pose = torch.eye(4, dtype=F).expand(n, 4, 4).clone()
    return GoalSet(ENV, 0, {}, np.zeros((n, 3), np.float32), pose, robot=chain, floor=0.0, obstacles=hand_block(),
                   collision_checked=True)


def test_goal_set_world_against_hand_placed_obstacles():
    goals = hand_goals()
    q = torch.zeros(2, goals.n, 7, dtype=F)  # (T + 1, n, nj): upright throughout
    assert goals.world().batch_shape == (goals.n,)
    got = clearance(goals.robot, q, goals.world()).numpy()
    np.testing.assert_allclose(got, np.broadcast_to(UPRIGHT_CLEARANCE, (2, goals.n)), atol=1e-6)
    # each goal drawn alone: only its active obstacles
    for i in range(goals.n):
        w = goals.goal_world(i)
        count = sum(0 if pair is None else pair[1].shape[0] for pair in (w.spheres, w.boxes))
        assert count == len(HAND[i])


def kinds(chain, pairs) -> list[str]:
    names = set(robot_capsules(chain).names)
    return ["self" if b in names else "floor" if b == "floor" else "obstacle" for _, b in pairs]


def test_collision_counts_match_a_configuration_by_configuration_recount():
    goals = hand_goals()
    chain = goals.robot
    rng = np.random.default_rng(0)
    lo, hi = chain.limits.double().numpy()
    q = rng.uniform(lo, hi, size=(6, goals.n, 7))
    q[2, 3] = UPRIGHT  # goal 3 meets its sphere once
    q[4, 1] = DOWN  # goal 1 touches the floor once
    m, floor_hit, collided = ev.collision_metrics(chain, q, goals.world())
    lowest = np.full(goals.n, np.inf)
    by_kind = {k: np.zeros(goals.n, bool) for k in ("self", "floor", "obstacle")}
    for i in range(goals.n):
        for t in range(q.shape[0]):
            d = pairwise_clearance(chain, torch.as_tensor(q[t, i]), hand_world(i))
            lowest[i] = min(lowest[i], d.distance.min().item())
            for kind, dist in zip(kinds(chain, d.pairs), d.distance.tolist()):
                by_kind[kind][i] |= dist < 0
    assert collided.tolist() == (lowest < 0).tolist() and collided[3] and collided[1]
    assert floor_hit.tolist() == by_kind["floor"].tolist()
    assert m["collisions"] == int((lowest < 0).sum())
    for kind in ("self", "floor", "obstacle"):
        assert m[f"{kind}_collisions"] == int(by_kind[kind].sum()), kind
    assert m["obstacle_collisions"] >= 1
    assert m["min_clearance_worst_m"] == pytest.approx(lowest.min(), abs=1e-6)
    assert m["min_clearance_median_m"] == pytest.approx(np.median(lowest), abs=1e-6)
    # without obstacles in the world (the other envs) the key is absent and nothing else changes
    plain, *_ = ev.collision_metrics(chain, q)
    assert "obstacle_collisions" not in plain and plain["floor_collisions"] == m["floor_collisions"]


def test_periodic_summary_counts_collisions_on_the_way():
    goals = hand_goals()
    # goal 2 collides mid-way only, goal 3 at the end only; goal 1 misses (2 cm)
    collision = np.zeros((3, goals.n), bool)
    collision[1, 2] = collision[2, 3] = True
    distance = np.array([[0.3] * 4, [0.1] * 4, [0.001, 0.02, 0.005, 0.0]])
    q = np.zeros((3, goals.n, 7))
    s = PolicyEvaluator(goals, 0.01).summary(Rollout(distance, np.zeros_like(distance), q, 0.0, 0.0, collision))
    assert s["success"] == 0.75  # goals 0, 2, 3
    assert s["collisions"] == 0.5  # goals 2, 3
    assert s["success_collision_free"] == 0.25  # goal 0 alone
    # pose goals: success needs the angle too (goal 0 is 0.2 rad off)
    angle = np.zeros_like(distance)
    angle[-1, 0] = 0.2
    pose = PolicyEvaluator(goals, 0.01, 0.1).summary(Rollout(distance, angle, q, 0.0, 0.0, collision))
    assert (pose["success"], pose["success_collision_free"]) == (0.5, 0.0)
    # an env without collision checks: no flags, no keys
    assert "collisions" not in PolicyEvaluator(goals, 0.01).summary(Rollout(distance, angle, q, 0.0, 0.0))


def test_rollout_flags_are_the_envs_collisions_recounted(step0_model):
    """The rollout's flags (the env's own, float32) against every configuration's clearance recomputed in
    float64 in each goal's world, goal by goal; and none for collision="off"."""
    goals = make_goal_set(ENV, 32, 5, {"collision_penalty": 10.0})
    model, vec_normalize, _ = ev.load_policy(step0_model)
    r = PolicyEvaluator(goals, 0.01).rollout(model, vec_normalize)
    assert r.collision.shape == r.distance.shape and not r.collision[0].any()
    recount = np.stack([clearance(goals.robot, torch.as_tensor(r.q[:, i]), goals.goal_world(i)).numpy() < 0
                        for i in range(goals.n)], 1)
    assert recount.any(), "the untrained policy runs into some obstacle on these goals"
    np.testing.assert_array_equal(r.collision, recount)
    off = make_goal_set("IiwaReach-v0", 4, 0, {"collision": "off"})
    assert off.world() is None and off.goal_world(0) is None
    assert PolicyEvaluator(off, 0.01).rollout(model_for("IiwaReach-v0"), None).collision is None


def model_for(env_id: str):
    from stable_baselines3 import PPO

    from train.vec_env import make_env

    return PPO("MultiInputPolicy", make_env(env_id, 1, 0, {"collision": "off"}), device="cpu", seed=0)


def test_best_model_prefers_collision_free_success():
    def entry(success, free, median):
        return {"success": success, "success_collision_free": free, "median_distance": median}

    best = entry(0.98, 0.90, 0.001)
    assert callbacks.improves(entry(0.95, 0.92, 0.002), best)  # fewer reached, more reached cleanly
    assert not callbacks.improves(entry(1.0, 0.89, 0.0001), best)
    assert callbacks.improves(entry(0.9, 0.90, 0.0005), best)  # tie: the lower median
    assert not callbacks.improves(entry(0.9, 0.90, 0.001), best)  # exact tie keeps the first
    old = {"success": 0.9, "median_distance": 0.001}  # a best recorded before the key existed
    assert not callbacks.improves(entry(0.95, 0.9, 0.002), old) and callbacks.improves(entry(0.95, 0.91, 0.01), old)
    plain = {"success": 0.9, "median_distance": 0.001}  # envs without collision checks: as before
    assert callbacks.improves({"success": 0.91, "median_distance": 0.01}, plain)


def test_goal_set_obstacles_are_the_envs_observation():
    """Goal i's obstacle block is the slice of the observation after cos q, sin q and the joint velocity
    (docs/envs.md) of a gymnasium env seeded as goal i's."""
    n, seed = 5, 2
    goals = make_goal_set(ENV, n, seed)
    assert goals.obstacles.shape == (n, SLOTS * SLOT_SIZE)
    env = gym.make(f"envs:{ENV}", start="home", terminate_on_success=False, collision="penalize")
    for i in range(n):
        obs, _ = env.reset(seed=held_out_seed(seed) + i)
        np.testing.assert_array_equal(goals.obstacles[i], obs["observation"][21 : 21 + SLOTS * SLOT_SIZE])
        np.testing.assert_array_equal(goals.desired_goal[i], obs["desired_goal"])
        slots = goals.obstacles[i].reshape(SLOTS, SLOT_SIZE)
        assert 1 <= int(slots[:, 0].sum()) <= SLOTS and not slots[slots[:, 0] == 0].any()
    # the goal configurations are collision-free with their own obstacles: the goal pose's IK answer is
    ik = ev.run_ik("analytic_ik", goals, goals.robot, np.asarray(IIWA_HOME), 0.05, goals.world())[0]
    assert ik["success@1cm"] == 1.0 and ik["collisions"] == 0


def test_ik_solvers_get_each_goals_obstacles():
    goals = make_goal_set(ENV, 200, 0)
    home = np.asarray(IIWA_HOME, dtype=float)
    for name in ("analytic_ik", "gradient_ik"):
        floor_only, _ = ev.run_ik(name, goals, goals.robot, home, 0.05, World(floor=0.0))
        given, data = ev.run_ik(name, goals, goals.robot, home, 0.05, ev.ik_world(envs.make_task(ENV), goals))
        # blind to the obstacles, answers run into them; given them, none does
        assert floor_only["obstacle_collisions"] > 0, name
        assert given["collisions"] == 0 and given["success@1cm"] >= 0.99, name
        recount = [pairwise_clearance(goals.robot, torch.as_tensor(data["q"][i]), goals.goal_world(i),
                                      goals.capsules).distance.min() for i in range(goals.n)]  # the env's capsules
        assert given["min_clearance_worst_m"] == pytest.approx(min(recount).item(), abs=1e-9), name


def test_picture_goals_pick_a_collision_a_miss_then_crowded_successes():
    collided = np.array([0, 0, 1, 0, 1, 0, 0], bool)
    failed = np.array([1, 0, 1, 0, 0, 0, 1], bool)
    count = np.array([1, 2, 4, 4, 1, 3, 4])
    assert ev.picture_goals(collided, failed, count) == [2, 0, 3, 5]
    assert ev.picture_goals(np.zeros(3, bool), np.zeros(3, bool), np.array([1, 3, 2])) == [1, 2, 0]


@pytest.fixture(scope="module")
def step0_model(tmp_path_factory):
    """The residual policy untrained (its plain DLS step, blind to the obstacles, and an initial
    correction), as a run folder: without the block's velocity damper, so that it collides."""
    from train import train as tr
    from train.run_dir import RunDir

    run = RunDir(tmp_path_factory.mktemp("step0") / "run")
    run.path.mkdir()
    blind = {"env_kwargs": {"terminate_on_success": False, "collision_penalty": 10.0},
             "features_extractor_kwargs": {"scales": [0.3, 0.03, 0.003], "dampings": [0.1, 0.01]}}
    hp = tr.load_hyperparams("ppo", ENV, {"n_envs": 4, "n_steps": 8, "batch_size": 32, **blind})
    config = tr.make_config("ppo", ENV, 0, hp, "test")
    run.write_config(config)
    tr.new_model(run, config).save(run.path / "model.zip")
    return run.path


def test_report_on_the_obstacle_env(step0_model, tmp_path):
    out = tmp_path / "report"
    goals_n = 24
    assert ev.main(["--model", str(step0_model), "--goals", str(goals_n), "--seed", "1", "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert "rollouts_obstacles.png" in report["plots"] and (out / "rollouts_obstacles.png").stat().st_size > 10_000
    assert "floor / self / obstacle" in (out / "report.md").read_text()
    goals = make_goal_set(ENV, goals_n, 1, report["env_kwargs"])
    model, vec_normalize, _ = ev.load_policy(step0_model)
    r = PolicyEvaluator(goals, 0.01).rollout(model, vec_normalize)
    # every rollout configuration against that goal's own obstacles (active ones only), one at a time
    lowest, obstacle = np.full(goals_n, np.inf), np.zeros(goals_n, bool)
    for i in range(goals_n):
        d = pairwise_clearance(goals.robot, torch.as_tensor(r.q[:, i]), goals.goal_world(i))
        lowest[i] = d.distance.min().item()
        names = kinds(goals.robot, d.pairs)
        obstacle[i] = bool((d.distance[:, [k == "obstacle" for k in names]] < 0).any())
    p = report["methods"]["policy"]
    assert p["collisions"] == int((lowest < 0).sum())
    assert p["obstacle_collisions"] == int(obstacle.sum())
    assert p["min_clearance_worst_m"] == pytest.approx(lowest.min(), abs=1e-9)
    free = (r.distance[-1] < 0.01) & (lowest >= 0)
    assert p["success@1cm_collision_free"] == pytest.approx(free.mean())
    for name in ("analytic_ik", "gradient_ik"):
        assert report["methods"][name]["collisions"] == 0, name
