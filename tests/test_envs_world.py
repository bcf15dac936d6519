"""The reaching envs' world: the floor on by default, collisions flagged and ending episodes, obstacles.

Expected values come from brute force: points sampled along each capsule's segment (from
``fk_all``'s frames), checked against the floor, spheres and boxes by hand-written formulas."""

from __future__ import annotations

import math
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch

import envs
from envs.core import ReachTask
from envs.sb3 import IiwaReachVecEnv
from envs.seeding import keys_from_seeds
from iiwa_torch.collision import robot_capsules
from iiwa_torch.robots import iiwa14

CHAIN = iiwa14()
CAPS = robot_capsules(CHAIN)
SAMPLES = np.linspace(0.0, 1.0, 41)


def capsule_points(q: np.ndarray) -> np.ndarray:
    """``q (b, 7)`` -> points ``(b, K, S, 3)`` sampled along each capsule's segment (world frame)."""
    frames = CHAIN.fk_all(torch.as_tensor(q, dtype=torch.float64)).numpy()[:, list(CAPS.frames)]  # (b, K, 4, 4)
    ends = np.einsum("bkij,kej->bkei", frames[..., :3, :3], CAPS.points.numpy()) + frames[:, :, None, :3, 3]
    return ends[:, :, :1] + SAMPLES[None, None, :, None] * (ends[:, :, 1:] - ends[:, :, :1])


def floor_clearance(q: np.ndarray) -> np.ndarray:
    """Lowest point of the floor-checked capsules minus their radius, ``(b,)`` m (floor at z = 0)."""
    pts, r = capsule_points(q), CAPS.radii.numpy()
    low = pts[..., 2].min(-1) - r  # (b, K)
    return low[:, CAPS.floor.numpy()].min(-1)


def self_clearance(q: np.ndarray) -> np.ndarray:
    """Smallest sampled distance between the checked capsule pairs, radii off, ``(b,)`` m."""
    pts, r = capsule_points(q), CAPS.radii.numpy()
    gaps = [np.linalg.norm(pts[:, i, :, None] - pts[:, j, None], axis=-1).min((-1, -2)) - r[i] - r[j]
            for i, j in CAPS.pairs]
    return np.min(gaps, 0)


def test_floor_is_on_by_default_and_starts_and_goals_avoid_it():
    n = 512
    default, off = ReachTask(start="random"), ReachTask(start="random", collision="off")
    state = default.initial_state(keys_from_seeds(range(n)))
    q = state.q.T.double().numpy()
    # brute force on the sampled capsules (an upper bound on the true clearance: never below it)
    assert (floor_clearance(q) > 0).all() and (self_clearance(q) > 0).all()
    goals = state.goal[2].numpy()
    assert (goals > 0).all()  # no goal below the floor
    old = off.initial_state(keys_from_seeds(range(n)))
    assert (old.goal[2] < 0).float().mean() > 0.03  # without checks some are: the test means something
    assert (floor_clearance(old.q.T.double().numpy()) < 0).any()
    for env_id in envs.ENV_IDS:
        assert envs.make_task(env_id).world.floor == 0.0


def _drive_into_floor(env, steps: int = 60):
    """Shoulder (joint 2) forward at full speed from home: the arm swings down into the floor."""
    action = np.zeros(7, dtype=np.float32)
    action[1] = 1.0
    env.reset(seed=0)
    out = []
    for _ in range(steps):
        obs, reward, term, trunc, info = env.step(action)
        out.append((obs, reward, term, trunc, info, env.unwrapped.joint_angles.copy()))
        if term or trunc:
            break
    return out


def test_a_step_into_the_floor_is_flagged_and_ends_the_episode():
    steps = _drive_into_floor(gym.make("IiwaReach-v0"))
    *before, last = steps
    obs, reward, term, trunc, info, q = last
    assert term and not trunc and info["collision"] and not info["is_success"]
    assert floor_clearance(q[None])[0] < 0.005  # the sampled capsule reaches the floor (within sampling)
    assert all(not s[4]["collision"] for s in before)
    assert all(floor_clearance(s[5][None])[0] > 0 and self_clearance(s[5][None])[0] > 0 for s in before)
    # the reward: minus the distance, minus the penalty (1 by default); compute_reward agrees given the info
    assert reward == pytest.approx(-info["distance"] - 1.0, abs=1e-6)
    env = gym.make("IiwaReach-v0").unwrapped
    assert env.compute_reward(obs["achieved_goal"], obs["desired_goal"], info) == np.float32(reward)
    assert env.compute_reward(obs["achieved_goal"], obs["desired_goal"], None) == pytest.approx(reward + 1.0)


@pytest.mark.parametrize("flag", ["yes", 1, [True, "no"], np.array([1, 0])])
def test_compute_reward_refuses_collision_flags_that_are_not_booleans(flag):
    env = gym.make("IiwaReach-v0").unwrapped
    goal = np.zeros(3, dtype=np.float32)
    with pytest.raises(TypeError, match=r"info\['collision'\] must be a bool"):
        env.compute_reward(goal, goal, {"collision": flag})
    with pytest.raises(TypeError, match=r"info\['collision'\] must be a bool"):
        env.compute_reward(goal[None], goal[None], [{"collision": flag}])
    assert env.compute_reward(goal, goal, {"collision": np.True_}) == np.float32(-1.0)  # minus the penalty


def test_compute_reward_names_an_info_it_cannot_read():
    env = gym.make("IiwaReach-v0").unwrapped
    goals = np.zeros((4, 3), dtype=np.float32)
    with pytest.raises(TypeError, match="info must be a dict, a sequence of per-env dicts or None, got 5"):
        env.compute_reward(goals, goals, 5)
    with pytest.raises(ValueError, match=r"info's collision flags \(3,\) do not fit the rewards \(4,\)"):
        env.compute_reward(goals, goals, [{"collision": True}] * 3)


def test_penalize_keeps_the_episode_going():
    steps = _drive_into_floor(gym.make("IiwaReach-v0", collision="penalize", collision_penalty=0.5), steps=40)
    hits = [s for s in steps if s[4]["collision"]]
    assert hits and not any(s[2] for s in steps)
    for _, reward, *_, info, q in hits:
        assert reward == pytest.approx(-info["distance"] - 0.5, abs=1e-6)
        assert floor_clearance(q[None])[0] < 0.005


def _box_sdf(p: np.ndarray, centre, half, yaw) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    d = p - centre
    local = np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1], d[..., 2]], -1)
    excess = np.abs(local) - half
    return np.linalg.norm(np.clip(excess, 0, None), axis=-1) + np.minimum(excess.max(-1), 0)


def test_obstacle_block_layout_and_clear_of_home():
    env = gym.make_vec("IiwaReachObstacles-v0", num_envs=256)
    obs, info = env.reset(seed=0)
    o = obs["observation"]
    assert o.shape == (256, 21 + 40 + 3)
    np.testing.assert_array_equal(o[:, -3:], obs["achieved_goal"])
    block = o[:, 21:61].reshape(256, 4, 10)
    active, is_box = block[..., 0], block[..., 1]
    count = active.sum(1)
    assert set(np.unique(active)) <= {0.0, 1.0} and set(np.unique(is_box)) <= {0.0, 1.0}
    assert count.min() >= 1 and count.max() <= 4 and set(count.astype(int)) == {1, 2, 3, 4}
    np.testing.assert_array_equal(active, np.arange(4)[None] < count[:, None])  # active slots first
    assert (block[active == 0] == 0).all()
    assert 0.3 < is_box[active == 1].mean() < 0.7
    on = block[active == 1]
    np.testing.assert_allclose(on[:, 8] ** 2 + on[:, 9] ** 2, 1.0, atol=1e-6)
    spheres = on[on[:, 1] == 0]
    np.testing.assert_array_equal(spheres[:, 5], spheres[:, 6])
    np.testing.assert_array_equal(spheres[:, 8:], np.tile([1.0, 0.0], (len(spheres), 1)))
    # every obstacle clear of the home configuration (where every episode starts): brute force
    pts = capsule_points(np.asarray(envs.make_task("IiwaReach-v0").arm.home, dtype=np.float64)[None])[0]
    radii = CAPS.radii.numpy()[:, None]
    for row in on:
        centre, size = row[2:5].astype(np.float64), row[5:8].astype(np.float64)
        if row[1] == 0:
            gap = np.linalg.norm(pts - centre, axis=-1) - size[0] - radii
        else:
            gap = _box_sdf(pts, centre, size, math.atan2(row[9], row[8])) - radii
        assert gap.min() > 0.04
    assert "collision" in info and not info["collision"].any()


def test_obstacles_single_vector_and_sb3_step_alike():
    n, seed = 3, 11
    vec = gym.make_vec("IiwaReachObstacles-v0", num_envs=n)
    sb3 = IiwaReachVecEnv(n, "IiwaReachObstacles-v0", seed=seed)
    singles = [gym.make("IiwaReachObstacles-v0") for _ in range(n)]
    obs, _ = vec.reset(seed=seed)
    sobs = sb3.reset()
    for i, e in enumerate(singles):
        o, _ = e.reset(seed=seed + i)
        for k in o:
            np.testing.assert_allclose(obs[k][i], o[k], atol=1e-6)
            np.testing.assert_allclose(sobs[k][i], o[k], atol=1e-6)
    rng = np.random.default_rng(0)
    hits = ends = 0
    for _ in range(120):
        action = rng.uniform(-1, 1, size=(n, 7)).astype(np.float32)
        action[0, 1] = 1.0  # the first arm swings its shoulder down: into the floor or an obstacle
        obs, reward, term, trunc, info = vec.step(action)
        sobs, sreward, sdone, sinfos = sb3.step(action)
        np.testing.assert_array_equal(info["collision"], [i["collision"] for i in sinfos])
        np.testing.assert_array_equal(term | trunc, sdone)
        np.testing.assert_allclose(reward, sreward, atol=1e-6)
        for i, env in enumerate(singles):
            o, r, te, tr, inf = env.step(action[i])
            assert (te, tr, inf["collision"]) == (term[i], trunc[i], info["collision"][i])
            assert r == pytest.approx(reward[i], abs=1e-5)
            if te or tr:
                o, _ = env.reset()
                ends += 1
            np.testing.assert_allclose(obs["observation"][i], o["observation"], atol=1e-5)
        hits += int(info["collision"].sum())
        going = ~(term | trunc)  # rows whose observation is still of the step's episode
        np.testing.assert_array_equal(vec.compute_reward(obs["achieved_goal"], obs["desired_goal"], info)[going],
                                      reward[going])
    assert hits > 0 and ends > hits  # collisions ended episodes, and so did time-outs


def test_sb3_checker_on_the_obstacle_id():
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(gym.make("IiwaReachObstacles-v0").unwrapped, skip_render_check=True)
    # unwrapped: SB3's checker calls env.compute_reward, which gymnasium's wrappers do not forward
    sb3_check_env(gym.make("IiwaReachObstacles-v0").unwrapped, warn=True)


@pytest.mark.parametrize("options, message", [
    ({"collision": "bounce"}, "collision must be one of"),
    ({"floor": float("nan")}, "floor must be"),
    ({"floor": True}, "floor must be"),
    ({"collision_penalty": -1.0}, "collision_penalty"),
    ({"obstacles": -1}, "obstacles must be"),
    ({"obstacles": 9}, "obstacles must be"),
    ({"obstacles": 2, "collision": "off"}, "obstacles need collision checks"),
    ({"floor": 0.5}, "home"),  # a floor above the home posture
])
def test_bad_world_options(options, message):
    with pytest.raises(ValueError, match=message):
        ReachTask(**options)


def test_observed_clearances_match_brute_force_and_finite_differences():
    """``observe_clearance``: each capsule's clearance row against sampled points (floor and self
    pairs, no obstacles), its gradient rows against central differences of those distances."""
    env = IiwaReachVecEnv(6, "IiwaReach-v0", seed=3, start="random", observe_clearance=True)
    obs = env.reset()["observation"]
    nj, k = 7, len(CAPS.names)
    start = 3 * nj
    assert env.observation_space["observation"].shape == (3 * nj + k * (1 + nj) + 3,)
    q = np.arctan2(obs[:, nj : 2 * nj], obs[:, :nj]).astype(np.float64)

    def per_capsule(q: np.ndarray) -> np.ndarray:  # (b, K) by sampling, saturating at 1 m as observed
        pts, r = capsule_points(q), CAPS.radii.numpy()
        out = np.full((q.shape[0], k), np.inf)
        for c in range(k):
            if CAPS.floor[c]:
                out[:, c] = pts[:, c, :, 2].min(-1) - r[c]
        for i, j in CAPS.pairs:
            gap = np.linalg.norm(pts[:, i, :, None] - pts[:, j, None], axis=-1).min((-1, -2)) - r[i] - r[j]
            out[:, i], out[:, j] = np.minimum(out[:, i], gap), np.minimum(out[:, j], gap)
        return np.minimum(out, 1.0)

    observed = obs[:, start : start + k]
    np.testing.assert_allclose(observed, per_capsule(q), atol=2e-3)  # 41 samples per segment: ~1 mm apart
    gradient = obs[:, start + k : start + k * (1 + nj)].reshape(-1, k, nj)
    from iiwa_torch.collision import capsule_clearance

    h = 1e-5
    for i in range(nj):
        step = np.zeros(nj)
        step[i] = h
        plus, minus = (capsule_clearance(CHAIN, torch.as_tensor(q + s))[0].numpy() for s in (step, -step))
        fd = np.where(observed < 1.0, (plus - minus) / (2 * h), 0.0)
        np.testing.assert_allclose(gradient[:, :, i], fd, atol=2e-4)


def test_clearance_rows_of_one_env_are_its_column_of_a_batch():
    """One CPU env's clearance rows (numpy ops) equal its column of a batch's (torch ops), to the
    rounding between capsule_clearance's closed form for one configuration and autograd's."""
    env = IiwaReachVecEnv(4, "IiwaReach-v0", seed=8, start="random", observe_clearance=True)
    env.reset()
    task, state = env.task, env._state
    rows = task.clearance_rows(state.q, state.obstacles)[0]
    assert (rows[: len(CAPS.names)] < 1.0).any()  # some capsule near something: gradient rows not all zero
    for i in range(4):
        one = task.clearance_rows(state.q[:, i : i + 1].contiguous(), state.obstacles[:, i : i + 1])[0]
        assert one.dtype == rows.dtype
        torch.testing.assert_close(one[:, 0], rows[:, i], atol=1e-6, rtol=0)


@pytest.mark.parametrize("env_id", ["IiwaReach-v0", "IiwaReachObstacles-v0"])
def test_collision_flag_of_the_clearance_rows_is_the_worlds(env_id):
    """With observed clearances the step's collision flag comes from the rows' capsule clearances: on
    random configurations (some through the floor, the arm or an obstacle) it is ``world.clearance(q) < 0``
    (the pairwise minimum, another function), for a batch and for one env."""
    n = 512
    env = IiwaReachVecEnv(n, env_id, seed=3, observe_clearance=True)
    env.reset()
    task = env.task
    q = task.arm.configurations(torch.rand(n, 7, dtype=task.dtype, generator=torch.Generator().manual_seed(0)))
    obstacles = env._state.obstacles
    expected = task.world.clearance(q, obstacles if task.world.slots else None) < 0
    assert int(expected.sum()) >= 10
    assert torch.equal(task.clearance_rows(q.T.contiguous(), obstacles)[1], expected)
    some = torch.cat([expected.nonzero()[:8, 0], (~expected).nonzero()[:8, 0]])
    for i in some.tolist():
        one = task.clearance_rows(q[i : i + 1].T.contiguous(), obstacles[:, i : i + 1])[1]
        assert bool(one[0]) == bool(expected[i])


def test_observed_clearances_with_obstacles_single_and_vector_env_alike():
    single = gym.make("IiwaReachObstacles-v0", observe_clearance=True)
    vector = IiwaReachVecEnv(1, "IiwaReachObstacles-v0", seed=5, observe_clearance=True)
    o1, _ = single.reset(seed=5)
    o2 = vector.reset()
    np.testing.assert_array_equal(o1["observation"], o2["observation"][0])
    rng = np.random.default_rng(0)
    for _ in range(10):
        a = rng.uniform(-1, 1, 7).astype(np.float32)
        o1, *_ = single.step(a)
        o2, *_ = vector.step(a[None])
        assert single.observation_space.contains(o1)
        np.testing.assert_allclose(o1["observation"], o2["observation"][0], atol=1e-6)
    # the smallest observed clearance is the env's clearance (the one collisions are flagged by)
    task = vector.task
    nj = 7
    obs = o2["observation"][0]
    q = torch.as_tensor(np.arctan2(obs[nj : 2 * nj], obs[:nj]), dtype=torch.float64)
    block = torch.as_tensor(obs[3 * nj : 3 * nj + task.world.block_size], dtype=torch.float64)[:, None]
    from envs.world import obstacle_world
    from iiwa_torch.collision import clearance

    expected = float(clearance(CHAIN, q[None], obstacle_world(block, 0.0)))
    start = 3 * nj + task.world.block_size
    assert obs[start : start + len(CAPS.names)].min() == pytest.approx(min(expected, 1.0), abs=1e-5)


def test_observe_clearance_needs_a_world():
    with pytest.raises(ValueError, match="observe_clearance needs collision checks"):
        ReachTask(observe_clearance=True, collision="off")
    with pytest.raises(TypeError, match="observe_clearance must be True or False"):
        ReachTask(observe_clearance=1)
