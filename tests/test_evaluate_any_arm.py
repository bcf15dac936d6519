"""train.evaluate's goal sets and IK rows on an arm other than the iiwa (the Franka Panda of
pybullet_data): its own capsules, goal poses drawn by the same env with pose goals, the gradient
IK with the env's world, and the closed form refused with its reason."""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("pybullet_data")
pytest.importorskip("stable_baselines3")

import envs  # noqa: E402
import train.evaluate as ev  # noqa: E402
from iiwa_torch import collision  # noqa: E402
from train.rollout import make_goal_set  # noqa: E402


@pytest.fixture(scope="module")
def panda_goals():
    return make_goal_set("FrankaReach-v0", 12, seed=0), envs.make_task("FrankaReach-v0")


def test_goal_set_of_the_panda(panda_goals):
    goals, task = panda_goals
    assert not goals.pose_goals and goals.capsules is task.world.capsules
    # the goal poses (for the IK) are FK of the configurations whose positions the env observes
    np.testing.assert_allclose(goals.pose[:, :3, 3].numpy(), goals.desired_goal, atol=1e-6)
    torch.testing.assert_close(goals.pose[:, :3, :3] @ goals.pose[:, :3, :3].mT,
                               torch.eye(3, dtype=torch.float64).expand(12, 3, 3), atol=1e-6, rtol=0)


def test_ik_rows_of_the_panda(panda_goals):
    goals, task = panda_goals
    home = task.arm.home.double().numpy()
    world = ev.ik_world(task, goals)
    metrics, data = ev.run_ik("gradient_ik", goals, task.robot, home, task.dt, world)
    assert metrics["success@1cm"] == 1.0 and metrics["collisions"] == 0
    # checked independently: FK of the answers, and their clearance with the env's capsules
    q = torch.as_tensor(data["q"])
    assert (task.robot.double().fk(q)[:, :3, 3] - goals.pose[:, :3, 3]).norm(dim=-1).max() < 0.01
    assert collision.clearance(task.robot.double(), q, world, goals.capsules).min() >= 0
    with pytest.raises(ValueError, match="gradient IK"):
        ev.run_ik("analytic_ik", goals, task.robot, home, task.dt, world)


def test_rollout_reads_joints_past_pi(panda_goals):
    """The rollout's joint angles come from the observation's cos and sin: a joint whose range runs past
    pi (the Panda's joint 6, up to 3.82 rad, from its URDF) is read within its limits, not wrapped."""
    from train.rollout import rollout

    goals, task = panda_goals
    upper = float(task.robot.double().limits[1, 5])
    assert upper > np.pi

    def joint_6_up(observation):
        action = np.zeros((goals.n, task.arm.n_joints), dtype=np.float32)
        action[:, 5] = 1.0
        return action

    q = rollout(goals, joint_6_up).q  # (T + 1, n, nj)
    np.testing.assert_allclose(q[-1, :, 5], upper, atol=1e-5)  # driven onto its upper limit
    assert task.robot.double().within_limits(torch.as_tensor(q), tol=1e-5).all()


def test_a_joint_on_its_limit_read_through_float32_is_not_a_violation():
    """A policy's joint angles are read back by atan2 of its float32 observation's cos and sin: near
    the Panda's joint 6 upper limit (3.8223 rad) that reading is off by up to about 1e-7 rad, so a joint
    clamped onto its limit can read past it (6.4e-8 rad in a held-out rollout). Counted with the
    reading's tolerance, that is not a violation; a real overshoot of 1 mrad still is."""
    from envs.transport import ANGLE_TOL, joint_angles
    from train.evaluate.metrics import limit_violations

    task = envs.make_task("FrankaReach-v0")
    lower, upper = (x.double().numpy() for x in (task.arm.lower, task.arm.upper))
    angles = upper[5] - np.linspace(0.0, 1e-6, 1001)
    q = task.arm.home.double().numpy()[None].repeat(len(angles), 0)
    q[:, 5] = angles
    observation = np.concatenate([np.cos(q), np.sin(q)], -1).astype(np.float32)
    error = np.abs(joint_angles(observation, lower, upper)[:, 5] - angles).max()
    assert 1e-9 < error < ANGLE_TOL
    past = q[:3].copy()
    past[:, 5] = upper[5] + np.array([6.4e-8, 1e-6, 1e-3])
    assert limit_violations(task.robot, past) == 3
    assert limit_violations(task.robot, past, ANGLE_TOL) == 1
