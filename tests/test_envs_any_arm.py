"""The reaching envs for any arm: the Franka Panda ids (pybullet_data's URDF), the robot option's forms
and errors, and panda-gym's task option.

Expected values come from elsewhere: pybullet's link state of ``panda_grasptarget`` (the point panda-gym
reaches with), the URDF's own numbers, points sampled along the capsules by hand, panda-gym's own env,
and N single envs for the vector envs."""

from __future__ import annotations

import os
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch

import envs
from envs.core import ReachTask
from envs.goals import PANDA_GYM_BOX
from envs.robot import resolve_robot
from envs.sb3 import IiwaReachVecEnv
from iiwa_torch.robots import from_urdf, iiwa14

pybullet = pytest.importorskip("pybullet")
pybullet_data = pytest.importorskip("pybullet_data")

PANDA_URDF = os.path.join(pybullet_data.getDataPath(), "franka_panda/panda.urdf")
GRASP_LINK = 11  # pybullet's index of panda_grasptarget (panda-gym's ee_link)
FRANKA_IDS = ("FrankaReach-v0", "FrankaReachPose-v0", "FrankaReachPandaGym-v0")
SAMPLES = np.linspace(0.0, 1.0, 81)


@pytest.fixture(scope="module")
def bullet():
    """A pybullet client (no GUI) with the Panda fixed at the origin -> ``link_pose(q)``: the position
    ``(3,)`` and rotation matrix ``(3, 3)`` of panda_grasptarget's frame."""
    client = pybullet.connect(pybullet.DIRECT)
    body = pybullet.loadURDF(PANDA_URDF, useFixedBase=True, physicsClientId=client)

    def link_pose(q):
        for i, angle in enumerate(q):
            pybullet.resetJointState(body, i, float(angle), physicsClientId=client)
        state = pybullet.getLinkState(body, GRASP_LINK, computeForwardKinematics=True, physicsClientId=client)
        rotation = np.array(pybullet.getMatrixFromQuaternion(state[5])).reshape(3, 3)
        return np.array(state[4]), rotation

    yield link_pose
    pybullet.disconnect(client)


def _drive(env, steps: int, seed: int):
    """Random actions, joint 2 pushed forward (towards the floor) and joint 4 folded on alternate steps
    (into the floor and the arm itself): -> per step the joint angles after it, its observation and info."""
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    out = []
    for t in range(steps):
        action = rng.uniform(-1, 1, 7).astype(np.float32)
        if t % 2 == 0:
            action[1] = 1.0
        else:
            action[3] = -1.0
        obs, _, term, trunc, info = env.step(action)
        out.append((env.unwrapped.joint_angles.copy(), obs, info))
        if term or trunc:
            env.reset()
    return out


# ------------------------------------------------------------------ ids, checkers, kinematics
def test_franka_ids_are_registered_apart_from_panda_gyms():
    assert set(FRANKA_IDS) <= set(envs.ENV_IDS) and "PandaReach-v3" not in envs.ENV_IDS
    for env_id in FRANKA_IDS:
        assert gym.spec(env_id).max_episode_steps == 50
        task = gym.make(env_id).unwrapped.task
        assert task.robot.name == "panda" and task.robot.link_names[-1] == "panda_link7"
        np.testing.assert_allclose(task.arm.home.numpy(), [0, 0.41, 0, -1.85, 0, 2.26, 0.79], atol=1e-7)
        assert task.world is not None and task.world.floor == 0.0  # floor and self-collision on


@pytest.mark.parametrize("env_id", FRANKA_IDS)
def test_gymnasium_and_sb3_checkers(env_id):
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(gym.make(env_id).unwrapped, skip_render_check=True)
        sb3_check_env(gym.make(env_id).unwrapped)


@pytest.mark.parametrize("env_id", ["FrankaReach-v0", "FrankaReachPose-v0"])
def test_achieved_goal_is_pybullets_grasp_target(env_id, bullet):
    env = gym.make(env_id, collision="penalize")
    for q, obs, _ in _drive(env, 40, seed=3)[::4]:
        position, rotation = bullet(q)
        want = np.concatenate([position, rotation[:, 0], rotation[:, 1]]) if env_id.endswith("Pose-v0") else position
        np.testing.assert_allclose(obs["achieved_goal"], want, atol=2e-6)


def test_action_scale_and_limits_are_the_urdfs():
    # panda.urdf: joints 1-4 at 2.175 rad/s, 5-7 at 2.61 rad/s; joint 4 in [-3.1416, 0]
    task = gym.make("FrankaReach-v0").unwrapped.task
    np.testing.assert_allclose(task.max_step.numpy(), np.array([2.175] * 4 + [2.61] * 3) * 0.05, rtol=1e-6)
    env = gym.make("FrankaReach-v0", collision="off")
    env.reset(seed=0)
    action = np.zeros(7, dtype=np.float32)
    action[3] = 1.0
    for _ in range(30):  # from -1.85 rad up at 0.10875 rad a step: at 0 (its upper limit) after 18 steps
        env.step(action)
    assert env.unwrapped.joint_angles[3] == 0.0


# ------------------------------------------------------------------ collisions
def _capsule_clearance_by_samples(chain, capsules, q: np.ndarray, floor: float = 0.0) -> tuple[float, float]:
    """Points sampled along each capsule of one configuration ``q (7,)``: the smallest gap to the floor at
    ``floor`` (floor-checked capsules) and between the checked pairs, m; upper bounds of the exact ones."""
    frames = chain.fk_all(torch.as_tensor(q, dtype=torch.float64)).numpy()[list(capsules.frames)]  # (K, 4, 4)
    ends = np.einsum("kij,kej->kei", frames[:, :3, :3], capsules.points.numpy()) + frames[:, None, :3, 3]
    pts = ends[:, :1] + SAMPLES[None, :, None] * (ends[:, 1:] - ends[:, :1])  # (K, S, 3)
    r = capsules.radii.numpy()
    low = (pts[..., 2].min(-1) - r)[capsules.floor.numpy()].min() - floor
    pairs = min(np.linalg.norm(pts[i, :, None] - pts[j, None], axis=-1).min() - r[i] - r[j] for i, j in capsules.pairs)
    return low, pairs


def test_collision_flags_are_the_capsules_clearance():
    env = gym.make("FrankaReach-v0", collision="penalize", start="random", floor=0.1)  # raised: more hits
    task = env.unwrapped.task
    chain = from_urdf(PANDA_URDF, end_link="panda_grasptarget")
    seen = {"floor": 0, "self": 0, "free": 0}
    for q, _, info in _drive(env, 150, seed=5):
        floor, own = _capsule_clearance_by_samples(chain, task.world.capsules, q, floor=0.1)
        if info["collision"]:
            assert min(floor, own) < 2e-3  # sampling at ~1 cm overestimates a gap by under 1 mm here
            seen["floor" if floor < own else "self"] += 1
        else:
            assert min(floor, own) > 0
            seen["free"] += 1
    assert min(seen.values()) >= 5, seen


def test_starts_and_goals_are_collision_free_for_the_panda():
    task = envs.make_task("FrankaReach-v0", start="random")
    state = task.initial_state(torch.arange(64))
    chain = from_urdf(PANDA_URDF, end_link="panda_grasptarget")
    for q in state.q.T.double().numpy():
        assert min(_capsule_clearance_by_samples(chain, task.world.capsules, q)) > 0
    assert (state.goal[2] > 0).all()


def test_obstacles_work_for_the_panda():
    env = gym.make("FrankaReach-v0", obstacles=3)
    obs, info = env.reset(seed=2)
    block = obs["observation"][21:51].reshape(3, 10)
    assert block[0, 0] == 1 and not info["collision"]
    for _ in range(5):
        env.step(env.action_space.sample())


# ------------------------------------------------------------------ vector envs == single envs
@pytest.mark.parametrize("env_id", ["FrankaReach-v0", "FrankaReachPandaGym-v0"])
def test_vector_and_sb3_envs_match_single_envs(env_id):
    n, steps, seed = 3, 110, 4
    options = {"distance_threshold": 0.05, "collision": "terminate"}
    vec = gym.make_vec(env_id, num_envs=n, **options)
    sb3 = IiwaReachVecEnv(n, env_id, seed=seed, **options)
    singles = [gym.make(env_id, **options) for _ in range(n)]
    obs, _ = vec.reset(seed=seed)
    sb3_obs = sb3.reset()
    for i, env in enumerate(singles):
        one = env.reset(seed=seed + i)[0]
        for k in obs:
            np.testing.assert_allclose(obs[k][i], one[k], atol=1e-6)
            np.testing.assert_array_equal(sb3_obs[k][i], obs[k][i])
    chain = from_urdf(PANDA_URDF, end_link="panda_grasptarget")
    rng = np.random.default_rng(0)
    ends = {"success": 0, "collision": 0, "time": 0}
    for _ in range(steps):
        q = torch.as_tensor(np.arctan2(obs["observation"][:, 7:14], obs["observation"][:, :7]), dtype=torch.float64)
        jac = chain.jacobian(q)[:, :3]  # towards the goal by damped least squares
        err = torch.as_tensor(obs["desired_goal"] - obs["achieved_goal"], dtype=torch.float64)[..., None]
        jt = jac.transpose(1, 2)
        greedy = (jt @ torch.linalg.solve(jac @ jt + 1e-2 * torch.eye(3), err))[..., 0]
        greedy_odds = np.array([[0.7], [0.7], [0.0]])  # the last env random: it times out or collides
        action = np.where(rng.uniform(size=(n, 1)) < greedy_odds, 4 * greedy.numpy(), rng.uniform(-1, 1, (n, 7)))
        action = action.astype(np.float32)
        obs, reward, term, trunc, info = vec.step(action)
        sb3_obs, sb3_reward, done, infos = sb3.step(action)
        np.testing.assert_array_equal(sb3_reward, reward)
        np.testing.assert_array_equal(done, term | trunc)
        for i, env in enumerate(singles):
            o, r, te, tr, inf = env.step(action[i])
            assert (te, tr, inf["is_success"], inf["collision"]) == (term[i], trunc[i], info["is_success"][i],
                                                                     info["collision"][i])
            assert r == pytest.approx(reward[i], rel=5e-6, abs=2e-6)
            if te or tr:
                ends["success" if inf["is_success"] else "collision" if inf["collision"] else "time"] += 1
                o, _ = env.reset()
            for k in obs:
                np.testing.assert_allclose(obs[k][i], o[k], atol=1e-6)
                np.testing.assert_array_equal(sb3_obs[k][i], obs[k][i])
    assert ends["success"] and ends["time"], ends


# ------------------------------------------------------------------ panda-gym's task
def test_panda_gym_goals_fill_its_box():
    task = envs.make_task("FrankaReachPandaGym-v0")
    assert task.distance_threshold == 0.05 and task.goals.reward_kind.value == "sparse"
    goal = task.initial_state(torch.arange(4096)).goal.numpy()  # (3, n)
    low, high = np.array(PANDA_GYM_BOX)
    assert ((goal >= low[:, None]) & (goal <= high[:, None])).all()
    np.testing.assert_allclose(goal.min(1), low, atol=0.01)  # uniform: near every face
    np.testing.assert_allclose(goal.max(1), high, atol=0.01)
    np.testing.assert_allclose(goal.mean(1), (low + high) / 2, atol=0.01)


def test_panda_gym_task_is_panda_gyms():
    """panda-gym's own PandaReach-v3 (its robot's base at x = -0.6): the same goal box relative to the
    base, the same end point at the neutral posture, the same threshold and episode length."""
    pytest.importorskip("panda_gym")
    theirs = gym.make("PandaReach-v3")
    obs, _ = theirs.reset(seed=0)
    base = np.array([-0.6, 0.0, 0.0])
    reach = theirs.unwrapped.task
    np.testing.assert_allclose(reach.goal_range_low - base, PANDA_GYM_BOX[0], atol=1e-12)
    np.testing.assert_allclose(reach.goal_range_high - base, PANDA_GYM_BOX[1], atol=1e-12)
    ours = gym.make("FrankaReachPandaGym-v0")
    mine, _ = ours.reset(seed=0)
    np.testing.assert_allclose(mine["achieved_goal"], obs["achieved_goal"] - base, atol=1e-6)
    assert ours.unwrapped.task.distance_threshold == reach.distance_threshold
    assert gym.spec("FrankaReachPandaGym-v0").max_episode_steps == theirs.spec.max_episode_steps == 50


# ------------------------------------------------------------------ the robot option
def test_robot_as_a_name_a_file_or_a_chain():
    by_name = ReachTask("panda")
    by_file = ReachTask(PANDA_URDF, end_link="panda_grasptarget")
    assert by_file.world.capsules is by_name.world.capsules  # fitted once per file and end link
    chain = from_urdf(PANDA_URDF, end_link="panda_hand")
    by_chain = ReachTask(chain, capsules=by_name.world.capsules)
    q = torch.tensor([0.1, 0.2, -0.3, -1.5, 0.4, 1.9, 0.5])[:, None]
    # the hand is 0.105 m behind the grasp target, along the hand's z axis
    z = chain.fk(q.T.double())[0, :3, 2].float()
    torch.testing.assert_close(by_chain.goal_of(q)[:, 0] + 0.105 * z, by_name.goal_of(q)[:, 0], atol=1e-6, rtol=0)
    torch.testing.assert_close(by_file.goal_of(q), by_name.goal_of(q))
    assert ReachTask("iiwa7").robot.name == "iiwa7"
    np.testing.assert_allclose(ReachTask("iiwa7").arm.home.numpy(), np.radians([0, 30, 0, -60, 0, 30, 0]), atol=1e-7)
    # a chain object through gymnasium's kwargs, for the single and the vector env
    assert gym.make("IiwaReach-v0", robot=chain, collision="off").unwrapped.task.robot.link_names[-1] == "panda_link7"
    vec = gym.make_vec("FrankaReach-v0", num_envs=2, robot=chain, end_link=None, capsules=by_name.world.capsules)
    assert vec.reset(seed=0)[0]["observation"].shape == (2, 24)


def test_default_home_of_any_arm():
    # the Panda at zeros collides with itself, so the middle of panda.urdf's limits
    panda = ReachTask("panda")
    lower = np.array([-2.9671, -1.8326, -2.9671, -3.1416, -2.9671, -0.0873, -2.9671])
    upper = np.array([2.9671, 1.8326, 2.9671, 0.0, 2.9671, 3.8223, 2.9671])
    np.testing.assert_allclose(panda.arm.home.numpy(), (lower + upper) / 2, atol=1e-6)
    np.testing.assert_array_equal(ReachTask("panda", collision="off").arm.home.numpy(), np.zeros(7))
    upper_arm = from_urdf(PANDA_URDF, end_link="panda_link4")
    np.testing.assert_array_equal(ReachTask(upper_arm, collision="off").arm.home.numpy(), np.zeros(4))
    home = [0.0, 0.5, 0.0, -2.0, 0.0, 2.5, 0.8]
    np.testing.assert_allclose(ReachTask("panda", home=home).arm.home.numpy(), home, atol=1e-7)


@pytest.mark.parametrize("options, error, message", [
    ({"robot": "pnada"}, ValueError, "preset name .*'pnada' \\(no such file\\)"),
    ({"robot": "/no/such/arm.urdf"}, ValueError, "no such file"),
    ({"robot": PANDA_URDF}, ValueError, "pass end_link="),
    ({"robot": PANDA_URDF, "end_link": "panda_elbow"}, ValueError, "panda_elbow"),
    ({"robot": "iiwa14", "end_link": "tool0"}, ValueError, "end_link applies to a URDF robot"),
    ({"robot": 7}, TypeError, "robot must be a preset name, a URDF path or a Chain"),
    ({"robot": "panda", "collision": "off", "capsules": "x"}, TypeError, "capsules"),
    ({"robot": "iiwa14", "collision": "off", "capsules": None, "obstacles": 0, "home": [0.0] * 6}, ValueError,
     "home must be 7"),
    ({"robot": "panda", "goal": "pose", "goal_region": "panda_gym"}, ValueError, "goal_region='panda_gym'"),
    ({"robot": "panda", "goal_region": "box"}, ValueError, "goal_region must be one of"),
])
def test_bad_robot_options(options, error, message):
    with pytest.raises(error, match=message):
        ReachTask(**options)


def test_a_franka_id_with_another_robot_says_whose_home_it_has():
    with pytest.raises(ValueError, match=r"within the limits of 'iiwa14', .* \(home=None takes the robot's default"):
        gym.make("FrankaReachPandaGym-v0", robot="iiwa14")
    assert gym.make("FrankaReachPandaGym-v0", robot="iiwa14", home=None).reset(seed=0)[0]["observation"].shape


def test_a_chain_without_capsules_needs_them_or_no_collisions():
    chain = from_urdf(PANDA_URDF, end_link="panda_hand")
    with pytest.raises(ValueError, match="pass capsules= .* or collision='off'"):
        ReachTask(chain)
    with pytest.raises(ValueError, match="capsules are for collision checks"):
        ReachTask(chain, collision="off", capsules=ReachTask("panda").world.capsules)
    with pytest.raises(ValueError, match="capsules index frames up to 7"):
        ReachTask(from_urdf(PANDA_URDF, end_link="panda_link4"), capsules=ReachTask("panda").world.capsules)
    assert resolve_robot(iiwa14())[1].names == ("base", "upper_arm", "forearm", "wrist")  # a preset's own model


def test_a_preset_without_joint_speeds_drives_the_env_once_given_some():
    """The PUMA 560 preset has no joint speeds (its sources give none): the env says how to give it
    some, and then runs it with a 6-entry action that moves each joint by at most speed * dt."""
    from gymnasium.utils.env_checker import check_env

    from iiwa_torch.robots import puma560

    with pytest.raises(ValueError, match="chain.velocity_limits = torch.full"):
        ReachTask("puma560")
    arm = puma560()
    arm.velocity_limits = torch.full((6,), 2.0, dtype=torch.float64)
    env = gym.make("IiwaReach-v0", robot=arm, collision="off")
    obs, _ = env.reset(seed=0)
    assert env.action_space.shape == (6,) and obs["observation"].shape == (21,)
    q0 = np.arctan2(obs["observation"][6:12], obs["observation"][:6])
    obs, *_ = env.step(np.ones(6, dtype=np.float32))
    step = np.arctan2(obs["observation"][6:12], obs["observation"][:6]) - q0
    dt = env.unwrapped.task.dt
    assert np.all(np.abs(step) <= 2.0 * dt + 1e-5) and np.abs(step).max() > 0.5 * 2.0 * dt
    check_env(gym.make("IiwaReach-v0", robot=arm).unwrapped, skip_render_check=True)
