"""Joint angles read back from the observation (``envs.transport.joint_angles``) on the Franka Panda,
whose joint 6 runs to 3.82 rad, past pi: the function itself, the joint features and the clearance
penalty that read them. Expected angles are the env's own state (``env.unwrapped.joint_angles``)."""

from __future__ import annotations

import math

import gymnasium
import numpy as np
import pytest
import torch

pytest.importorskip("pybullet_data")
pytest.importorskip("stable_baselines3")

import envs  # noqa: E402, F401 (registers the ids)
from envs.sb3 import IiwaReachVecEnv  # noqa: E402
from envs.transport import joint_angles  # noqa: E402
from iiwa_torch import collision  # noqa: E402
from train import features  # noqa: E402
from train.features import JointGoalExtractor  # noqa: E402
from train.wrappers import ClearancePenalty  # noqa: E402

OPTIONS = {"terminate_on_success": False, "collision": "penalize"}


@pytest.fixture(scope="module")
def past_pi():
    """The Panda after 12 full-speed steps of joint 6 up from home (2.26 rad, 0.13 rad a step: on its
    upper limit, 3.82 rad): ``(observation dict, q (7,) float64 of the env's state, task)``."""
    env = gymnasium.make("FrankaReach-v0", **OPTIONS)
    obs, _ = env.reset(seed=3)
    action = np.zeros(7, dtype=np.float32)
    action[5] = 1.0
    for _ in range(12):
        obs, *_ = env.step(action)
    q = env.unwrapped.joint_angles
    assert q[5] > math.pi + 0.5  # beyond atan2's range
    return obs, q, env.unwrapped.task


def test_joint_angles_past_pi(past_pi):
    obs, q, task = past_pi
    lower, upper = task.arm.lower, task.arm.upper
    got = joint_angles(obs["observation"][None], lower.double().numpy(), upper.double().numpy())
    np.testing.assert_allclose(got[0], q, atol=1e-5, rtol=0)
    assert got.dtype == np.float64
    tensor = joint_angles(torch.as_tensor(obs["observation"][None]), lower.double().numpy(), upper.double().numpy())
    np.testing.assert_allclose(tensor[0].double().numpy(), q, atol=1e-5, rtol=0)
    # a joint inside (-pi, pi] is read as atan2 reads it: the other six
    naive = np.arctan2(obs["observation"][7:14], obs["observation"][:7])
    np.testing.assert_array_equal(got[0, [0, 1, 2, 3, 4, 6]], naive[[0, 1, 2, 3, 4, 6]].astype(np.float64))


@pytest.mark.parametrize("rows", ["numpy", "torch"])
def test_joint_features_of_the_panda_past_pi(past_pi, rows, monkeypatch):
    """The extractor runs on the Panda's env and places joint 6 at its upper limit (+1), as the env's q says."""
    obs, q, task = past_pi
    if rows == "torch":
        monkeypatch.setattr(features, "NUMPY_ROWS", 0)
    space = gymnasium.make("FrankaReach-v0", **OPTIONS).observation_space
    ext = JointGoalExtractor(space, "panda", [float(s) for s in task.max_step])
    batch = {key: torch.as_tensor(value[None]) for key, value in obs.items()}
    out = ext(batch)[0].double().numpy()
    start = ext.gradient_columns[1]
    lower, upper = task.arm.lower.double().numpy(), task.arm.upper.double().numpy()
    expected = 2 * (q - lower) / (upper - lower) - 1
    np.testing.assert_allclose(out[start : start + 7], expected, atol=1e-5, rtol=0)
    assert out[start + 5] > 0.99


def test_clearance_penalty_of_the_panda_past_pi(past_pi):
    """ClearancePenalty's clearance of the observation is that of the env's own configuration."""
    obs, q, task = past_pi
    penalty = ClearancePenalty(IiwaReachVecEnv(1, "FrankaReach-v0", seed=0, **OPTIONS))
    got = penalty.clearance(obs["observation"][None])
    world = collision.World(floor=task.world.floor)
    expected = collision.clearance(task.robot, torch.as_tensor(q, dtype=task.dtype), world, task.world.capsules)
    np.testing.assert_allclose(got, [float(expected)], atol=1e-4, rtol=0)
