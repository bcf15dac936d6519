"""DHChain: the seed paper's validation poses, peer libraries, Jacobians, gradients, bad input."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from iiwa_torch import DHChain, kinematics, robots
from iiwa_torch.so3 import pose_error

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
    q = sample(chain, 70_000, seed=21)  # two blocks of the position kernel (65,536 configurations each)
    got = chain.position(q)
    for i in [0, 1, 500, 65_535, 65_536, 69_999]:
        np.testing.assert_allclose(got[i].numpy(), robot.fkine(q[i].numpy()).t, atol=1e-12)
    for part in (q[:1], q[0], q[:50]):  # one configuration in Python floats; the 4x4-product kernel
        np.testing.assert_allclose(chain.position(part).numpy(), chain.fk(part)[..., :3, 3].numpy(), atol=1e-14)


@pytest.mark.parametrize("make", [robots.iiwa14, robots.lrmate200ic])  # no offsets; an offset of -pi/2
def test_position_reuses_the_callers_cos_sin(make):
    chain = make()
    q = sample(chain, 135, seed=24).T  # (n, b): above 128, the large-batch kernel
    got = chain.position_batch_last(q, (q.cos(), q.sin()))
    torch.testing.assert_close(got, chain.fk(q.T)[:, :3, 3].T, atol=1e-12, rtol=0)


def test_position_gradient_is_the_jacobian():
    chain = robots.iiwa14()
    for q in (sample(chain, 1, seed=22), sample(chain, 129, seed=23)):
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


@pytest.mark.parametrize("batch", [1, 3, 133])
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
    g = chain.geometry()
    assert torch.autograd.gradcheck(lambda x: kinematics.EndPoseFunction.apply(x, g)[..., :3, :], (q,))
    assert torch.autograd.gradgradcheck(lambda x: kinematics.EndPoseFunction.apply(x, g)[..., :3, :], (q,))


def test_closed_form_backward_equals_autograd_through_the_kernels():
    chain = robots.iiwa14(tool=robots.puma560().fk(torch.full((6,), 0.3, dtype=torch.float64)))
    q = sample(chain, 168, seed=16)
    g = chain.geometry()
    weights = torch.randn(q.shape[0], 4, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    grads = []
    for fk in (chain.fk, lambda x: kinematics.end_pose(g, x)):  # closed form, replayed ops
        x = q.clone().requires_grad_()
        (fk(x) * weights).sum().backward()
        grads.append(x.grad)
    torch.testing.assert_close(grads[0], grads[1], atol=1e-12, rtol=0)


def test_batched_equals_looped_across_kernels_and_blocks():
    chain = robots.iiwa14()
    q = sample(chain, 8492, seed=8)  # two blocks of the elementwise kernel (8,192 configurations each)
    poses, frames, jac = chain.fk(q), chain.fk_all(q), chain.jacobian(q)
    for i in [0, 1, 4000, 8191, 8192, 8491]:  # one at a time: the 4x4-product kernel
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
    q = torch.tensor(angles, dtype=torch.float32).expand(129, 7)  # above 128: the elementwise kernel
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
    with pytest.raises(ValueError, match="meta tensor, without values"):
        call(torch.zeros(7, device="meta"))


def test_bad_tables():
    with pytest.raises(ValueError, match=r"shape \(n, 4\)"):
        DHChain([[0, 0, 0]])
    with pytest.raises(ValueError, match="convention must be one of"):
        DHChain([[0, 0, 0, 0]], convention="craig")
    with pytest.raises(ValueError, match="limits must have shape"):
        DHChain([[0, 0, 0, 0]], limits=[[1.0], [-1.0]])
    with pytest.raises(ValueError, match=r"tool must be a rigid transform .* max \|R\^T R - I\| = 3,"):
        DHChain([[0, 0, 0, 0]], tool=torch.diag(torch.tensor([2.0, 2.0, 2.0, 1.0])))
    with pytest.raises(ValueError, match="limits must be finite"):
        DHChain([[0, 0, 0, 0]], limits=[[-math.inf], [1.0]])
    with pytest.raises(ValueError, match="limits must be finite"):
        DHChain([[0, 0, 0, 0]], limits=[[math.nan], [1.0]])


@pytest.mark.parametrize("where", ["base", "tool"])
def test_base_and_tool_must_be_rigid(where):
    bottom = torch.eye(4, dtype=torch.float64)
    bottom[3] = torch.tensor([1.0, 2.0, 3.0, 5.0])
    with pytest.raises(ValueError, match=rf"{where}'s bottom row must be exactly \[0, 0, 0, 1\], got \[1.0, 2.0"):
        DHChain([[0, 0, 0, 0]], **{where: bottom})
    with pytest.raises(ValueError, match=r"max \|R\^T R - I\| = 0, det R = -1,"):  # a mirror: orthonormal, det -1
        DHChain([[0, 0, 0, 0]], **{where: torch.diag(torch.tensor([1.0, 1.0, -1.0, 1.0]))})
    sheared = torch.eye(4, dtype=torch.float64)
    sheared[0, 1] = 1e-5  # beyond the documented 1e-6
    with pytest.raises(ValueError, match=r"max \|R\^T R - I\| = 1e-05, det R = 1,"):
        DHChain([[0, 0, 0, 0]], **{where: sheared})
    sheared[0, 1] = 1e-8  # rounding noise is accepted
    DHChain([[0, 0, 0, 0]], **{where: sheared})


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_rejected(dtype):
    chain = robots.iiwa14()
    for call in (chain.fk, chain.position, chain.jacobian, chain.fk_all):
        with pytest.raises(TypeError, match=f"float32 or float64 tensor, got {dtype}"):
            call(torch.zeros(7, dtype=dtype))
    with pytest.raises(TypeError, match="float32 or float64"):
        chain.random_q(3, dtype=dtype)


def test_random_q_bad_arguments():
    chain = robots.iiwa14()
    for shape in [(2.5,), (-1,), (3, -2), (True,)]:
        with pytest.raises(ValueError, match="non-negative integers, got"):
            chain.random_q(*shape)
    with pytest.raises(TypeError, match="float32 or float64, got torch.int64"):
        chain.random_q(3, dtype=torch.int64)
    assert chain.random_q(0).shape == (0, 7) and chain.random_q().shape == (7,)


def test_meta_and_vmap_give_clear_errors():
    chain = robots.iiwa14().to("meta")
    with pytest.raises(ValueError, match="meta tensor, without values"):
        chain.fk(torch.zeros(3, 7, device="meta"))
    with pytest.raises(ValueError, match=r"q is on cpu but the chain is on meta; use chain.to\('cpu'\)"):
        chain.fk(torch.zeros(3, 7))
    chain, q = robots.iiwa14(), sample(robots.iiwa14(), 4, seed=30)
    with pytest.raises(ValueError, match="meta tensor, without values"):  # not "use chain.to('meta')"
        chain.fk(torch.zeros(3, 7, device="meta"))
    for method in (chain.fk, chain.position, chain.jacobian):
        with pytest.raises(TypeError, match=r"torch.func.vmap.*leading dimensions"):
            torch.func.vmap(method)(q)


@pytest.mark.parametrize("batch", [3, 200])  # the compiled kernels' sizes, and the elementwise kernel's
def test_torch_compile_traces_the_torch_path(batch):
    """torch.compile cannot trace into numba: under its tracing every call takes the torch path (Dynamo
    alone, backend="eager": it is Dynamo that failed)."""
    chain, q = robots.iiwa14(), sample(robots.iiwa14(), batch, seed=31)
    for method in (chain.fk, chain.jacobian):
        torch.testing.assert_close(torch.compile(method, backend="eager")(q), method(q), atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.compile(chain.fk, backend="eager")(q[0]), chain.fk(q[0]), atol=1e-12, rtol=0)


# ---------------------------------------------------------------- every kernel against the reference
# Batch sizes across every kernel switch the docs name: up to 128 (compiled, or 4x4 products),
# above (elementwise), above 8,192 (blocks), above 65,536 (position blocks).
BATCHES = [1, 2, 33, 100, 128, 129, 1000, 8193, 20000]


def _reference_fk(dh, q, modified=False, base=None, tool=None):
    """The DH definition, written out: ``q (..., n)`` -> ``(..., n + 2, 4, 4)``: the base, the link frames
    ``base A_1 ... A_i``, then the end pose (tool applied), ``A_i = Rz(theta) Tz(d) Tx(a) Rx(alpha)``
    (standard) or ``Rx(alpha) Tx(a) Rz(theta) Tz(d)`` (modified), in ``q``'s dtype."""
    dh = dh.to(q)
    eye = torch.eye(4, dtype=q.dtype, device=q.device)
    frame = (eye if base is None else base.to(q)).expand(*q.shape[:-1], 4, 4)
    frames = [frame]
    for i, (a, alpha, d, offset) in enumerate(dh.unbind(0)):
        theta = q[..., i] + offset
        c, s, zero, one = theta.cos(), theta.sin(), torch.zeros_like(theta), torch.ones_like(theta)
        rz = torch.stack([c, -s, zero, zero, s, c, zero, zero, zero, zero, one, zero, zero, zero, zero, one], -1)
        rz = rz.reshape(*theta.shape, 4, 4)
        tz, tx, rx = eye.clone(), eye.clone(), eye.clone()
        tz[2, 3], tx[0, 3] = d, a
        rx[1, 1], rx[1, 2], rx[2, 1], rx[2, 2] = alpha.cos(), -alpha.sin(), alpha.sin(), alpha.cos()
        link = rx @ tx @ rz @ tz if modified else rz @ tz @ tx @ rx
        frame = frame @ link
        frames.append(frame)
    frames.append(frame @ (eye if tool is None else tool.to(q)))
    return torch.stack(frames, -3)


def _reference(chain, q):
    return _reference_fk(chain.dh, q, chain.convention.value == "modified", chain.base, chain.tool)


def _with_base_and_tool(modified=False):
    base = robots.iiwa14().fk(torch.full((7,), 0.2, dtype=torch.float64))
    tool = robots.puma560().fk(torch.full((6,), -0.4, dtype=torch.float64))
    return DHChain(robots.lrmate200ic().dh, convention="modified" if modified else "standard", base=base, tool=tool)


def test_reference_matches_roboticstoolbox():
    modified_chain = DHChain(robots.lrmate200ic().dh, convention="modified")
    for chain, modified in [(robots.lrmate200ic(), False), (modified_chain, True)]:
        q = sample(chain, 20, seed=31)
        robot = _rtb_robot(chain, modified)
        expected = np.stack([robot.fkine(qi).A for qi in q.numpy()])
        np.testing.assert_allclose(_reference(chain, q)[:, -1].numpy(), expected, atol=1e-12)


@pytest.mark.parametrize("make", [robots.iiwa14, lambda: _with_base_and_tool(False), lambda: _with_base_and_tool(True)])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_every_fast_path_matches_the_reference(make, dtype, small_kernel):
    chain = make()
    tol = 1e-12 if dtype == torch.float64 else 2e-5
    q_all = sample(chain, max(BATCHES), seed=32)
    for b in BATCHES:
        q = q_all[:b]
        ref = _reference(chain, q).to(dtype)  # computed in float64
        qd = q.to(dtype)
        torch.testing.assert_close(chain.fk(qd), ref[:, -1], atol=tol, rtol=0)
        torch.testing.assert_close(chain.fk_all(qd), ref[:, :-1], atol=tol, rtol=0)
        torch.testing.assert_close(chain.position(qd), ref[:, -1, :3, 3], atol=tol, rtol=0)
        torch.testing.assert_close(kinematics.end_pose_matmul(chain.geometry(dtype), qd), ref[:, -1], atol=tol, rtol=0)
        torch.testing.assert_close(kinematics.position_horner(chain.geometry(dtype), qd.T), ref[:, -1, :3, 3].T,
                                   atol=tol, rtol=0)
        # batch last: frames, tool frame and position (with the caller's cos/sin)
        frames, axes = chain.frames_batch_last(qd.T)
        got = torch.stack([torch.stack(f, 1) for f in frames])  # (n + 1, 3, 4, b)
        torch.testing.assert_close(got, ref[:, :-1, :3].permute(1, 2, 3, 0), atol=tol, rtol=0)
        tool = torch.stack(chain.tool_frame_batch_last(frames[-1]), 1)
        torch.testing.assert_close(tool, ref[:, -1, :3].permute(1, 2, 0), atol=tol, rtol=0)
        trig = (qd.T.cos(), qd.T.sin())
        torch.testing.assert_close(chain.position_batch_last(qd.T, trig), ref[:, -1, :3, 3].T, atol=tol, rtol=0)
    one = q_all[0].to(dtype)  # one configuration, unbatched
    ref = _reference(chain, q_all[0]).to(dtype)
    torch.testing.assert_close(chain.fk(one), ref[-1], atol=tol, rtol=0)
    torch.testing.assert_close(chain.position(one), ref[-1, :3, 3], atol=tol, rtol=0)


def _reference_jacobian(chain, q):
    """``(n,) -> (6, n)`` from autograd through the reference: the linear rows are dp/dq, the
    angular rows the axial vector of dR/dq_i R^T."""
    d = torch.autograd.functional.jacobian(lambda x: _reference(chain, x)[-1], q)  # (4, 4, n)
    rot = _reference(chain, q)[-1, :3, :3]
    w = torch.einsum("ijn,kj->nik", d[:3, :3], rot)  # (n, 3, 3): dR/dq_i R^T, skew
    return torch.cat([d[:3, 3], torch.stack([w[:, 2, 1], w[:, 0, 2], w[:, 1, 0]])], 0)


_TWISTED = [[0.1, 0.3, 0.2, 0.1], [0.2, -1.1, 0.0, 0.0], [0.05, math.pi, 0.1, -0.2], [0.0, 0.0, 0.3, 0.0]]


@pytest.mark.parametrize("make", [robots.iiwa14, lambda: _with_base_and_tool(False), lambda: _with_base_and_tool(True),
                                  lambda: DHChain(_TWISTED), lambda: DHChain(_TWISTED, convention="modified")])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_small_cpu_paths_match_the_torch_kernels_and_the_reference(make, dtype, small_kernel):
    chain = make()
    n, tol = chain.n_joints, 1e-12 if dtype == torch.float64 else 2e-5
    q2 = sample(chain, 2, seed=36)
    ref_pose, ref_jac = _reference(chain, q2[0])[-1], _reference_jacobian(chain, q2[0])
    # the torch 4x4-product kernels: a batch, under autograd (the fast paths are for neither)
    q_grad = q2.to(dtype).clone().requires_grad_()
    batched_pose, batched_jac = chain.fk(q_grad)[0].detach(), chain.jacobian(q_grad)[0]
    assert not kinematics.untracked_cpu(q_grad)
    q10 = sample(chain, 10, seed=37).to(dtype)  # a few: compiled, or the 4x4 products
    x10 = q10.clone().requires_grad_()
    torch.testing.assert_close(chain.fk(q10), chain.fk(x10).detach(), atol=tol, rtol=0)
    torch.testing.assert_close(chain.jacobian(q10), chain.jacobian(x10), atol=tol, rtol=0)
    ref10 = torch.stack([_reference_jacobian(chain, x) for x in q10.double()]).to(dtype)
    torch.testing.assert_close(chain.jacobian(q10), ref10, atol=tol, rtol=0)
    for keep in (True, False):  # the small-batch batch-last frames against the elementwise kernel
        fast, slow = chain.frames_batch_last(q10.T, keep), chain.frames_batch_last(x10.T, keep)
        for got, want in zip(fast, slow):  # frames, then axes (none without keep)
            assert len(got) == len(want)
            for g, w in zip(got, want):
                torch.testing.assert_close(torch.stack(g), torch.stack(w).detach(), atol=tol, rtol=0)
    for shape in ((n,), (1, n), (1, 1, n)):
        one = q2[0].to(dtype).reshape(shape)
        assert kinematics.untracked_cpu(one)
        pose, jac = chain.fk(one), chain.jacobian(one)
        assert pose.shape == (*shape[:-1], 4, 4) and jac.shape == (*shape[:-1], 6, n)
        assert pose.dtype == jac.dtype == dtype and pose.is_contiguous() and jac.is_contiguous()
        torch.testing.assert_close(pose.reshape(4, 4), batched_pose, atol=tol, rtol=0)
        torch.testing.assert_close(jac.reshape(6, n), batched_jac, atol=tol, rtol=0)
        torch.testing.assert_close(pose.reshape(4, 4), ref_pose.to(dtype), atol=tol, rtol=0)
        torch.testing.assert_close(jac.reshape(6, n), ref_jac.to(dtype), atol=tol, rtol=0)
    with torch.inference_mode():
        torch.testing.assert_close(chain.fk(q2[0].to(dtype)), ref_pose.to(dtype), atol=tol, rtol=0)
    # With something to differentiate, the torch kernels run and autograd sees them.
    x = q2[0].to(dtype).requires_grad_()
    assert not kinematics.untracked_cpu(x)
    pose = chain.fk(x)
    assert pose.grad_fn is not None
    (grad,) = torch.autograd.grad(pose[:3, 3].sum(), x)
    torch.testing.assert_close(grad, ref_jac[:3].sum(0).to(dtype), atol=10 * tol, rtol=0)
    with torch.no_grad():
        assert kinematics.untracked_cpu(x)
        torch.testing.assert_close(chain.fk(x), ref_pose.to(dtype), atol=tol, rtol=0)
    # Bad input is refused as before.
    with pytest.raises(ValueError, match="NaN or inf"):
        chain.jacobian(torch.full((n,), math.nan, dtype=dtype))
    with pytest.raises(ValueError, match=r"shape \(\.\.\., "):
        chain.fk(torch.zeros(n + 1, dtype=dtype))


@pytest.mark.parametrize("b", [1, 2, 129, 1000, 8193])
def test_gradients_match_autograd_through_the_reference(b):
    chain = _with_base_and_tool(False)
    q = sample(chain, b, seed=33)
    weights = torch.randn(b, 4, 4, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    grads = []
    for fn in (chain.fk, lambda x: _reference(chain, x)[:, -1]):
        x = q.clone().requires_grad_()
        (fn(x) * weights).sum().backward()
        grads.append(x.grad)
    torch.testing.assert_close(grads[0], grads[1], atol=1e-11, rtol=0)
    x = q.clone().requires_grad_()
    (chain.position(x) * weights[:, :3, 0]).sum().backward()
    torch.testing.assert_close(x.grad, (chain.jacobian(q)[:, :3] * weights[:, :3, 0, None]).sum(1), atol=1e-11, rtol=0)


# ---------------------------------------------------------------- the geometry follows the buffers
def _same_kinematics(chain, fresh, dtype=torch.float64, tol=1e-12):
    for b in (1, 100, 1000):
        q = sample(fresh, b, seed=34).to(dtype)
        torch.testing.assert_close(chain.fk(q), fresh.fk(q), atol=tol, rtol=0)
        torch.testing.assert_close(chain.position(q), fresh.position(q), atol=tol, rtol=0)
        torch.testing.assert_close(chain.jacobian(q), fresh.jacobian(q), atol=tol, rtol=0)
        torch.testing.assert_close(chain.fk_all(q), fresh.fk_all(q), atol=tol, rtol=0)


def test_load_state_dict_from_another_flange_rebuilds_the_geometry():
    from iiwa_torch.ik import analytic

    tool = robots.puma560().fk(torch.full((6,), 0.3, dtype=torch.float64))
    chain, other = robots.iiwa14(), robots.iiwa14(flange=0.3, tool=tool)
    _same_kinematics(robots.iiwa14(), chain)  # the old geometry is cached now
    chain.load_state_dict(other.state_dict())
    _same_kinematics(chain, other)
    q = chain.random_q(200, generator=torch.Generator().manual_seed(35))
    target = chain.fk(q)
    sol = analytic.iiwa(chain, target, analytic.iiwa_arm_angle(chain, q))
    assert sol.reachable.all()
    pos, rot = pose_error(chain.fk(sol.q), target[:, None])
    assert pos.norm(dim=-1).max() < 1e-9 and rot.norm(dim=-1).max() < 1e-9


def test_in_place_edits_rebuild_the_geometry():
    chain = robots.lrmate200ic()
    _same_kinematics(chain, robots.lrmate200ic())
    chain.dh[2, 2] += 0.05
    chain.dh[1, 3] = 0.3  # an offset: the small-batch constants and the Horner path
    chain.tool[2, 3] = 0.2
    chain.base[:3, 3] = torch.tensor([0.1, -0.2, 0.3])
    fresh = DHChain(chain.dh.clone(), base=chain.base.clone(), tool=chain.tool.clone(), limits=chain.limits.clone())
    _same_kinematics(chain, fresh)
    chain.limits[1, 0] = -1.0
    assert (chain.random_q(500)[:, 0] <= -1.0).all() and chain.clamp(torch.zeros(6, dtype=torch.float64))[0] == -1.0
    chain.base[3, 0] = 1.0  # no longer rigid: the next call says so
    with pytest.raises(ValueError, match="base's bottom row"):
        chain.fk(torch.zeros(6, dtype=torch.float64))


def test_load_state_dict_checks_what_it_loads():
    chain, state = robots.iiwa14(), robots.iiwa14().state_dict()
    state["tool"] = torch.diag(torch.tensor([1.0, 1.0, -1.0, 1.0], dtype=torch.float64))
    with pytest.raises(ValueError, match="det R = -1"):
        chain.load_state_dict(state)


def test_dtype_moves_rebuild_the_geometry():
    chain, fresh = robots.puma560(), robots.puma560()
    _same_kinematics(chain, fresh)
    chain.float()
    assert chain.geometry().base.dtype == torch.float64  # a float64 view of the float32 buffers
    _same_kinematics(chain, fresh, tol=1e-6)
    chain.double()
    _same_kinematics(chain, fresh, tol=1e-6)


def test_replaced_buffer_data_rebuilds_the_geometry():
    chain = robots.iiwa14()
    _same_kinematics(chain, robots.iiwa14())
    chain.dh.data = robots.iiwa7().dh.clone()  # no version bump: a new storage
    _same_kinematics(chain, robots.iiwa7())


@pytest.mark.parametrize("name", list(robots.PRESETS))
def test_reach_bound_is_never_exceeded(name):
    chain = robots.PRESETS[name]()
    q = chain.random_q(20_000, generator=torch.Generator().manual_seed(0))
    assert float(chain.position(q).norm(dim=-1).max()) <= chain.reach_bound() + 1e-12


def test_reach_bound_of_the_iiwa14_is_its_stretched_height_on_the_datasheet():
    assert robots.iiwa14().reach_bound() == pytest.approx(1.306, abs=1e-12)  # KUKA's dimension A, 1306 mm
