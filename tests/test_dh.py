"""DHChain: the seed paper's validation poses, peer libraries, Jacobians, gradients, bad input."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from iiwa_torch import DHChain, robots
from iiwa_torch.dh import _BLOCK, _POSITION_BLOCK, _SMALL_BATCH, _EndPose

ALL = [robots.iiwa14, robots.iiwa7, robots.puma560, robots.lrmate200ic, robots.planar3r]


def sample(chain, n, seed=0, dtype=torch.float64):
    return chain.random_q(n, generator=torch.Generator().manual_seed(seed), dtype=dtype)


# ---------------------------------------------------------------- validation poses (seed 000)
def test_seed_paper_home_pose():
    pose = robots.iiwa14(flange=0.090).fk(torch.zeros(7, dtype=torch.float64))
    torch.testing.assert_close(pose[:3, 3], torch.tensor([0.0, 0.0, 1.270], dtype=torch.float64))
    torch.testing.assert_close(pose[:3, :3], torch.eye(3, dtype=torch.float64))


def test_seed_paper_second_pose():
    q = torch.tensor([0, 0, 0, -math.pi / 2, math.pi / 3, 0, 0], dtype=torch.float64)
    pose = robots.iiwa14(flange=0.090).fk(q)
    r3 = math.sqrt(3) / 2
    expected = torch.tensor([[0, 0, 1], [r3, 0.5, 0], [-0.5, r3, 0]], dtype=torch.float64)
    torch.testing.assert_close(pose[:3, 3], torch.tensor([0.490, 0.0, 0.780], dtype=torch.float64))
    torch.testing.assert_close(pose[:3, :3], expected)


@pytest.mark.parametrize(
    ("preset", "xyz"),
    [(robots.iiwa14, (0, 0, 1.306)), (robots.iiwa7, (0, 0, 1.266)), (robots.lrmate200ic, (0.475, 0, 0.705))],
)
def test_datasheet_home(preset, xyz):
    chain = preset()
    pose = chain.fk(torch.zeros(chain.n_joints, dtype=torch.float64))
    torch.testing.assert_close(pose[:3, 3], torch.tensor(xyz, dtype=torch.float64))


def test_planar_closed_form():
    chain = robots.planar3r(1.0, 0.8, 0.3)
    q = sample(chain, 50)
    c = torch.cumsum(q, -1)
    x = (torch.tensor([1.0, 0.8, 0.3], dtype=torch.float64) * torch.cos(c)).sum(-1)
    y = (torch.tensor([1.0, 0.8, 0.3], dtype=torch.float64) * torch.sin(c)).sum(-1)
    pose = chain.fk(q)
    torch.testing.assert_close(pose[:, 0, 3], x)
    torch.testing.assert_close(pose[:, 1, 3], y)
    torch.testing.assert_close(
        torch.atan2(pose[:, 1, 0], pose[:, 0, 0]), torch.atan2(torch.sin(c[:, -1]), torch.cos(c[:, -1]))
    )


# ---------------------------------------------------------------- peer libraries
def _rtb_robot(chain, modified=False):
    rtb = pytest.importorskip("roboticstoolbox")
    link = rtb.RevoluteMDH if modified else rtb.RevoluteDH
    return rtb.DHRobot([link(a=a, alpha=al, d=d, offset=o) for a, al, d, o in chain.dh.tolist()])


@pytest.mark.parametrize("preset", ALL)
def test_fk_matches_roboticstoolbox(preset):
    chain = preset()
    q = sample(chain, 1000, seed=1)
    robot = _rtb_robot(chain)
    expected = np.stack([robot.fkine(qi).A for qi in q.numpy()])
    np.testing.assert_allclose(chain.fk(q).numpy(), expected, atol=1e-12)
    np.testing.assert_allclose(chain.position(q).numpy(), expected[:, :3, 3], atol=1e-12)


@pytest.mark.parametrize("modified", [False, True])
def test_position_with_base_and_tool_matches_roboticstoolbox(modified):
    sm = pytest.importorskip("spatialmath")
    base = robots.iiwa14().fk(torch.full((7,), 0.2, dtype=torch.float64))
    tool = robots.puma560().fk(torch.full((6,), -0.4, dtype=torch.float64))
    chain = DHChain(robots.lrmate200ic().dh, convention="modified" if modified else "standard", base=base, tool=tool)
    robot = _rtb_robot(chain, modified)
    robot.base, robot.tool = sm.SE3(base.numpy(), check=False), sm.SE3(tool.numpy(), check=False)
    q = sample(chain, _POSITION_BLOCK + 100, seed=21)  # two blocks of the position kernel
    got = chain.position(q)
    for i in [0, 1, 500, _POSITION_BLOCK, _POSITION_BLOCK + 99]:
        np.testing.assert_allclose(got[i].numpy(), robot.fkine(q[i].numpy()).t, atol=1e-12)
    for part in (q[:1], q[0], q[:50]):  # one configuration in Python floats; the 4x4-product kernel
        np.testing.assert_allclose(chain.position(part).numpy(), chain.fk(part)[..., :3, 3].numpy(), atol=1e-14)


@pytest.mark.parametrize("make", [robots.iiwa14, robots.lrmate200ic])  # no offsets; an offset of -pi/2
def test_position_reuses_the_callers_cos_sin(make):
    chain = make()
    q = sample(chain, _SMALL_BATCH + 7, seed=24).T  # (n, b): the large-batch kernel
    got = chain.position_batch_last(q, (q.cos(), q.sin()))
    torch.testing.assert_close(got, chain.fk(q.T)[:, :3, 3].T, atol=1e-12, rtol=0)


def test_position_gradient_is_the_jacobian():
    chain = robots.iiwa14()
    for q in (sample(chain, 1, seed=22), sample(chain, _SMALL_BATCH + 1, seed=23)):
        jac = torch.autograd.functional.jacobian(lambda x: chain.position(x).sum(0), q)  # (3, b, 7)
        torch.testing.assert_close(jac.permute(1, 0, 2), chain.jacobian(q)[:, :3], atol=1e-12, rtol=0)


def test_modified_convention_matches_roboticstoolbox():
    chain = DHChain(robots.lrmate200ic().dh, convention="modified")
    q = sample(chain, 300, seed=2)
    robot = _rtb_robot(chain, modified=True)
    expected = np.stack([robot.fkine(qi).A for qi in q.numpy()])
    np.testing.assert_allclose(chain.fk(q).numpy(), expected, atol=1e-12)
    np.testing.assert_allclose(chain.position(q).numpy(), expected[:, :3, 3], atol=1e-12)


def test_puma_matches_roboticstoolbox_model():
    """rtb's Puma560 has d1 = 0.67183 m, robots.md 0.6718 m: poses differ by exactly that lift."""
    rtb = pytest.importorskip("roboticstoolbox")
    model, chain = rtb.models.DH.Puma560(), robots.puma560()
    q = sample(chain, 1000, seed=3)
    expected = np.stack([model.fkine(qi).A for qi in q.numpy()])
    got = chain.fk(q).numpy()
    lift = model.links[0].d - chain.dh[0, 2].item()
    np.testing.assert_allclose(got[:, :3, :3], expected[:, :3, :3], atol=1e-12)
    np.testing.assert_allclose(got[:, :3, 3] + [0, 0, lift], expected[:, :3, 3], atol=1e-12)


@pytest.mark.parametrize("preset", [robots.iiwa14, robots.puma560, robots.lrmate200ic])
def test_fk_matches_pytorch_kinematics_via_urdf(preset):
    pk = pytest.importorskip("pytorch_kinematics")
    from iiwa_torch.urdf import to_urdf

    chain = preset()
    serial = pk.build_serial_chain_from_urdf(to_urdf(chain).encode(), "tool0").to(dtype=torch.float64)
    q = sample(chain, 1000, seed=4)
    # pytorch_kinematics parses URDF origins in float32, hence the 1e-6 tolerance.
    torch.testing.assert_close(chain.fk(q), serial.forward_kinematics(q).get_matrix(), atol=1e-6, rtol=0)


@pytest.mark.parametrize("preset", [robots.iiwa14, robots.puma560])
def test_jacobian_matches_pytorch_kinematics(preset):
    pk = pytest.importorskip("pytorch_kinematics")
    from iiwa_torch.urdf import to_urdf

    chain = preset()
    serial = pk.build_serial_chain_from_urdf(to_urdf(chain).encode(), "tool0").to(dtype=torch.float64)
    q = sample(chain, 200, seed=5)
    torch.testing.assert_close(chain.jacobian(q), serial.jacobian(q), atol=1e-6, rtol=0)


# ---------------------------------------------------------------- Jacobian and gradients
def _numeric_jacobian(chain, q, fn):
    """Geometric Jacobian ``(6, n)`` from ``fn(q) -> (4, 4)`` derivatives: linear rows are
    dp/dq, angular rows the axial vector of dR/dq R^T."""
    dT = fn(q)  # (4, 4, n)
    rot = chain.fk(q)[:3, :3]
    cols = []
    for i in range(chain.n_joints):
        w = dT[:3, :3, i] @ rot.T
        cols.append(torch.cat([dT[:3, 3, i], torch.stack([w[2, 1], w[0, 2], w[1, 0]])]))
    return torch.stack(cols, 1)


@pytest.mark.parametrize("preset", ALL)
def test_jacobian_equals_autograd_and_finite_differences(preset):
    tool = robots.puma560().fk(torch.full((6,), 0.3, dtype=torch.float64))
    chain = preset(tool=tool) if preset in (robots.iiwa14, robots.iiwa7) else preset()
    eye = torch.eye(chain.n_joints, dtype=torch.float64)

    def central(x, h=1e-6):
        return torch.stack([(chain.fk(x + h * e) - chain.fk(x - h * e)) / (2 * h) for e in eye], -1)

    for q in sample(chain, 5, seed=6):
        auto = _numeric_jacobian(chain, q, lambda x: torch.autograd.functional.jacobian(chain.fk, x))
        fd = _numeric_jacobian(chain, q, central)
        torch.testing.assert_close(chain.jacobian(q), auto, atol=1e-12, rtol=0)
        torch.testing.assert_close(chain.jacobian(q), fd, atol=1e-8, rtol=0)


@pytest.mark.parametrize("batch", [1, 3, _SMALL_BATCH + 5])
def test_gradcheck_fk(batch):
    chain = robots.iiwa14()
    q = sample(chain, batch, seed=7).requires_grad_()
    assert torch.autograd.gradcheck(lambda x: chain.fk(x)[..., :3, :], (q,))
    assert torch.autograd.gradcheck(lambda x: chain.jacobian(x), (q[:2],))


def test_second_derivatives_through_fk():
    chain = robots.lrmate200ic()
    q = sample(chain, 2, seed=15).requires_grad_()
    assert torch.autograd.gradgradcheck(lambda x: chain.fk(x)[..., :3, :], (q,))  # autograd through the kernel
    # the closed-form backward that fk takes above 128 configurations, on a batch small enough to check
    assert torch.autograd.gradcheck(lambda x: _EndPose.apply(x, chain)[..., :3, :], (q,))
    assert torch.autograd.gradgradcheck(lambda x: _EndPose.apply(x, chain)[..., :3, :], (q,))


def test_closed_form_backward_equals_autograd_through_the_kernels():
    chain = robots.iiwa14(tool=robots.puma560().fk(torch.full((6,), 0.3, dtype=torch.float64)))
    q = sample(chain, _SMALL_BATCH + 40, seed=16)
    weights = torch.randn(q.shape[0], 4, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    grads = []
    for fk in (chain.fk, lambda x: chain._blockwise(x, (4, 4), chain._end_pose)):  # closed form, replayed ops
        x = q.clone().requires_grad_()
        (fk(x) * weights).sum().backward()
        grads.append(x.grad)
    torch.testing.assert_close(grads[0], grads[1], atol=1e-12, rtol=0)


def test_batched_equals_looped_across_kernels_and_blocks():
    chain = robots.iiwa14()
    q = sample(chain, _BLOCK + 300, seed=8)  # two blocks of the elementwise kernel
    poses, frames, jac = chain.fk(q), chain.fk_all(q), chain.jacobian(q)
    for i in [0, 1, 4000, _BLOCK - 1, _BLOCK, _BLOCK + 299]:  # one at a time: the 4x4-product kernel
        torch.testing.assert_close(poses[i], chain.fk(q[i]), atol=1e-14, rtol=0)
        torch.testing.assert_close(frames[i], chain.fk_all(q[i]), atol=1e-14, rtol=0)
        torch.testing.assert_close(jac[i], chain.jacobian(q[i]), atol=1e-14, rtol=0)


def test_leading_batch_shapes():
    chain = robots.puma560()
    q = sample(chain, 2 * 3 * 5, seed=9).reshape(2, 3, 5, 6)
    assert chain.fk(q).shape == (2, 3, 5, 4, 4)
    assert chain.fk_all(q).shape == (2, 3, 5, 7, 4, 4)
    assert chain.jacobian(q).shape == (2, 3, 5, 6, 6)
    assert chain.position(q).shape == (2, 3, 5, 3)
    torch.testing.assert_close(chain.position(q)[1, 2, 3], chain.position(q[1, 2, 3]))
    torch.testing.assert_close(chain.fk(q)[1, 2, 3], chain.fk(q[1, 2, 3]))
    assert chain.fk(q[:0]).shape == (0, 3, 5, 4, 4)


def test_fk_all_ends_with_fk_and_starts_at_base():
    base = robots.iiwa14().fk(torch.full((7,), 0.2, dtype=torch.float64))
    tool = robots.puma560().fk(torch.full((6,), -0.4, dtype=torch.float64))
    chain = DHChain(robots.iiwa14().dh, base=base, tool=tool)
    q = sample(chain, 300, seed=10)
    frames = chain.fk_all(q)
    torch.testing.assert_close(frames[:, 0], base.expand(300, 4, 4))
    torch.testing.assert_close(frames[:, -1] @ tool, chain.fk(q))
    torch.testing.assert_close(chain.fk(q), base @ robots.iiwa14(flange=0.0).fk(q) @ _tz(0.126) @ tool)


def _tz(d):
    m = torch.eye(4, dtype=torch.float64)
    m[2, 3] = d
    return m


def test_modified_equals_shifted_standard_table():
    """Standard row i (a_i, alpha_i) moves to modified row i + 1; the last one becomes a tool."""
    std = robots.lrmate200ic()
    rows = std.dh.clone()
    mdh = torch.zeros_like(rows)
    mdh[1:, :2] = rows[:-1, :2]
    mdh[:, 2:] = rows[:, 2:]
    a, alpha = rows[-1, :2].tolist()
    tool = torch.tensor(
        [
            [1, 0, 0, a],
            [0, math.cos(alpha), -math.sin(alpha), 0],
            [0, math.sin(alpha), math.cos(alpha), 0],
            [0, 0, 0, 1],
        ],
        dtype=torch.float64,
    )
    modified = DHChain(mdh, convention="modified", tool=tool)
    q = sample(std, 500, seed=11)
    torch.testing.assert_close(modified.fk(q), std.fk(q))
    torch.testing.assert_close(modified.jacobian(q), std.jacobian(q))


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(-3.0, 3.0), min_size=7, max_size=7))
def test_float32_rotations_orthonormal(angles):
    chain = robots.iiwa14()
    q = torch.tensor(angles, dtype=torch.float32).expand(_SMALL_BATCH + 1, 7)  # elementwise kernel
    for pose in (chain.fk(q), chain.fk(q[0])):
        rot = pose[..., :3, :3]
        eye = torch.eye(3).expand_as(rot)
        torch.testing.assert_close(rot @ rot.transpose(-1, -2), eye, atol=2e-6, rtol=0)
        torch.testing.assert_close(torch.linalg.det(rot), torch.ones(rot.shape[:-2]), atol=2e-6, rtol=0)


def test_float32_close_to_float64_and_dtype_followed():
    chain = robots.iiwa14()
    q = sample(chain, 2000, seed=12)
    out32 = chain.fk(q.float())
    assert out32.dtype == torch.float32 and chain.jacobian(q.float()).dtype == torch.float32
    torch.testing.assert_close(out32.double(), chain.fk(q), atol=5e-6, rtol=0)


def test_chain_to_float32_keeps_results():
    chain = robots.iiwa14().to(torch.float32)
    assert chain.limits.dtype == torch.float32
    q = sample(robots.iiwa14(), 10, seed=13)
    torch.testing.assert_close(chain.fk(q), robots.iiwa14().fk(q))


# ---------------------------------------------------------------- helpers and presets
def test_random_q_within_limits_and_reproducible():
    chain = robots.puma560()
    a, b = sample(chain, 1000, seed=14), sample(chain, 1000, seed=14)
    torch.testing.assert_close(a, b)
    assert chain.within_limits(a).all()
    assert (a.min(0).values < chain.limits[0] + 0.1).all() and (a.max(0).values > chain.limits[1] - 0.1).all()


def test_clamp_and_within_limits():
    chain = robots.iiwa14()
    q = torch.full((7,), 4.0, dtype=torch.float64)
    assert not chain.within_limits(q)
    torch.testing.assert_close(chain.clamp(q), chain.limits[1])
    assert chain.within_limits(chain.clamp(q))


def test_presets_limits_and_speeds():
    chain = robots.iiwa14()
    assert chain.n_joints == 7 and chain.limits.shape == (2, 7)
    torch.testing.assert_close(
        torch.rad2deg(chain.limits[1]), torch.tensor([170, 120, 170, 120, 170, 120, 175.0], dtype=torch.float64)
    )
    torch.testing.assert_close(
        torch.rad2deg(chain.velocity_limits), torch.tensor([85, 85, 100, 75, 130, 135, 135.0], dtype=torch.float64)
    )
    assert "A4" in repr(chain) and "-90.0" in repr(chain) and "0.4200" in repr(chain)


# ---------------------------------------------------------------- bad input
@pytest.mark.parametrize("method", ["fk", "fk_all", "jacobian", "position"])
def test_bad_input(method):
    chain = robots.iiwa14()
    call = getattr(chain, method)
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 7\), got \(3, 6\)"):
        call(torch.zeros(3, 6))
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 7\), got \(\)"):
        call(torch.tensor(0.0))
    with pytest.raises(TypeError, match="float32 or float64 tensor, got torch.int64"):
        call(torch.zeros(3, 7, dtype=torch.int64))
    with pytest.raises(TypeError, match="torch.Tensor"):
        call([0.0] * 7)
    q = torch.zeros(4, 7)
    q[2, 3] = float("nan")
    with pytest.raises(ValueError, match=r"NaN or inf \(first at index \(2, 3\)\)"):
        call(q)
    q[2, 3] = float("inf")
    with pytest.raises(ValueError, match="NaN or inf"):
        call(q)
    with pytest.raises(ValueError, match="is on meta but the chain is on cpu"):
        call(torch.zeros(7, device="meta"))


def test_bad_tables():
    with pytest.raises(ValueError, match=r"shape \(n, 4\)"):
        DHChain([[0, 0, 0]])
    with pytest.raises(ValueError, match="convention must be one of"):
        DHChain([[0, 0, 0, 0]], convention="craig")
    with pytest.raises(ValueError, match="limits must have shape"):
        DHChain([[0, 0, 0, 0]], limits=[[1.0], [-1.0]])
    with pytest.raises(ValueError, match="orthonormal"):
        DHChain([[0, 0, 0, 0]], tool=torch.full((4, 4), 2.0))
