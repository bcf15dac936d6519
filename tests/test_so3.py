"""so3: against scipy's Rotation, closed-form cases, round trips, and edge angles."""

import math

import numpy as np
import pytest
import torch

from iiwa_torch import so3

Rotation = pytest.importorskip("scipy.spatial.transform").Rotation


def random_rotvecs(n, seed=0, max_angle=math.pi):
    g = torch.Generator().manual_seed(seed)
    axis = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1)
    return axis * torch.rand(n, 1, generator=g, dtype=torch.float64) * max_angle


def test_exp_matches_scipy():
    v = random_rotvecs(500)
    np.testing.assert_allclose(so3.exp(v).numpy(), Rotation.from_rotvec(v.numpy()).as_matrix(), atol=1e-13)


def test_quaternion_matches_scipy():
    v = random_rotvecs(500, seed=1)
    rot = so3.exp(v)
    xyzw = Rotation.from_matrix(rot.numpy()).as_quat()
    wxyz = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], 1) * np.sign(xyzw[:, 3:])
    np.testing.assert_allclose(so3.matrix_to_quaternion(rot).numpy(), wxyz, atol=1e-12)
    np.testing.assert_allclose(so3.quaternion_to_matrix(torch.from_numpy(wxyz)).numpy(), rot.numpy(), atol=1e-12)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-4, 1.0, math.pi - 1e-4, math.pi - 1e-9])
def test_log_inverts_exp_at_edge_angles(angle):
    axis = torch.nn.functional.normalize(torch.tensor([[0.3, -0.5, 0.8], [1.0, 0.0, 0.0]], dtype=torch.float64), dim=-1)
    v = axis * angle
    back = so3.log(so3.exp(v))
    torch.testing.assert_close(so3.exp(back), so3.exp(v), atol=1e-12, rtol=0)
    assert torch.allclose(back.norm(dim=-1), torch.full((2,), angle, dtype=torch.float64), atol=1e-7)


def test_log_at_half_turn_gives_pi():
    rot = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))  # pi about x
    v = so3.log(rot)
    torch.testing.assert_close(v.abs(), torch.tensor([math.pi, 0.0, 0.0], dtype=torch.float64))


def test_log_gradient_finite_near_identity_and_half_turn():
    for angle in (0.0, 1e-8, math.pi - 1e-6):
        v = torch.tensor([angle, 0.0, 0.0], dtype=torch.float64, requires_grad=True)
        so3.log(so3.exp(v)).sum().backward()
        assert torch.isfinite(v.grad).all()
    v = random_rotvecs(4, seed=2, max_angle=3.0).requires_grad_()
    assert torch.autograd.gradcheck(lambda x: so3.log(so3.exp(x)), (v,))


def test_rpy_matches_scipy_and_round_trips():
    g = torch.Generator().manual_seed(3)
    rpy = (torch.rand(300, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([2 * math.pi, 3.0, 2 * math.pi])
    rot = so3.rpy_to_matrix(rpy)
    np.testing.assert_allclose(rot.numpy(), Rotation.from_euler("xyz", rpy.numpy()).as_matrix(), atol=1e-13)
    torch.testing.assert_close(so3.matrix_to_rpy(rot), rpy)


@pytest.mark.parametrize("off", [0.0, 1e-13, 1e-10, 1e-7, 1e-6, 1e-4])
@pytest.mark.parametrize("sign", [1, -1])
def test_rpy_at_and_near_gimbal_lock_reproduces_the_rotation(off, sign):
    """Near pitch +-pi/2 too (asin lost half the digits there: 3e-7 at 1e-7 rad from the lock)."""
    rot = so3.rpy_to_matrix(torch.tensor([0.4, sign * (math.pi / 2 - off), -0.3], dtype=torch.float64))
    torch.testing.assert_close(so3.rpy_to_matrix(so3.matrix_to_rpy(rot)), rot, atol=1e-15, rtol=0)
    locked = so3.rpy_to_matrix(torch.tensor([0.4, sign * math.pi / 2, -0.3], dtype=torch.float64))
    locked[:2, 0] = locked[2, 1:] = 0.0  # exactly locked: cos(pitch) = 0 (6e-17 entries zeroed)
    locked[2, 0] = -sign
    torch.testing.assert_close(so3.rpy_to_matrix(so3.matrix_to_rpy(locked)), locked, atol=1e-15, rtol=0)


def test_pose_error_closed_form():
    target = torch.eye(4, dtype=torch.float64)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3] = so3.exp(torch.tensor([0.0, 0.0, 0.3], dtype=torch.float64))
    pose[:3, 3] = torch.tensor([0.1, -0.2, 0.3])
    pos_err, rot_err = so3.pose_error(pose, target)
    torch.testing.assert_close(pos_err, torch.tensor([-0.1, 0.2, -0.3], dtype=torch.float64))
    torch.testing.assert_close(rot_err, torch.tensor([0.0, 0.0, -0.3], dtype=torch.float64))


def test_pose_error_rejects_mismatched_dtypes():
    with pytest.raises(ValueError, match="share dtype and device"):
        so3.pose_error(torch.eye(4), torch.eye(4, dtype=torch.float64))


def test_check_pose():
    so3.check_pose(torch.eye(4).expand(3, 4, 4))
    with pytest.raises(ValueError, match=r"\(\.\.\., 4, 4\), got \(3, 3\)"):
        so3.check_pose(torch.eye(3))
    with pytest.raises(ValueError, match="NaN"):
        so3.check_pose(torch.full((4, 4), float("nan")))
    with pytest.raises(TypeError, match="float32 or float64"):
        so3.check_pose(torch.eye(4, dtype=torch.int32))
