"""Every backend held to the torch path, for DH presets and URDF chains (every joint kind).

Kinematics: the elementwise and 4x4-product torch kernels, Horner's position and the compiled
(numba) recursion give the same end poses, frames, joint axes and Jacobians. The torch path
itself is held to the DH reference (test_dh.py) and to pinocchio (test_chain.py). Then the
other compiled kernels (the LM rounds of ik.solve, the closed forms' sweeps, the clearances),
each run twice: with the kernels enabled and switched off (``compiled.ENABLED`` monkeypatched
to False), so the reference is the code they restate. Without numba only the fallback tests run.
"""

import importlib.util
import math
import os
import re
import subprocess
import sys

import numpy as np
import pytest
import torch
from urdf_samples import ODD_URDF

from iiwa_torch import collision, compiled, robots, so3
from iiwa_torch import kinematics as kin
from iiwa_torch.dh import DHChain
from iiwa_torch.ik import analytic, lm, lm_compiled, lm_setup, solve

F64 = torch.float64


def _chains():
    chains = {name: robots.PRESETS[name]() for name in ("iiwa14", "puma560", "lrmate200ic")}
    chains["odd"] = robots.from_urdf(ODD_URDF, end_link="tip")  # tilted axes, prismatic, continuous
    if importlib.util.find_spec("pybullet_data"):
        import pybullet_data

        chains["panda"] = robots.from_urdf(f"{pybullet_data.getDataPath()}/franka_panda/panda.urdf",
                                           end_link="panda_hand")
    return chains


CHAINS = _chains()


def _torch_path(chain, q):
    """End poses, link frames and Jacobians by the torch 4x4 products (autograd on, so no shortcut)."""
    g = chain.geometry(q.dtype)
    x = q.clone().requires_grad_()
    with torch.enable_grad():
        return (kin.end_pose_matmul(g, x).detach(), kin.all_poses(g, x).detach(), kin.jacobian(g, x).detach())


def _elementwise(chain, q):
    g = chain.geometry(q.dtype)
    frames, axes = kin.frames_batch_last(g, q.T.contiguous().requires_grad_())
    end = kin.tool_frame_batch_last(g, frames[-1])
    stack = torch.stack([torch.stack(f, 1) for f in frames]).detach()  # (F, 3, 4, b)
    return torch.stack(end, 1).detach().permute(2, 0, 1), stack.permute(3, 0, 1, 2), axes


def _compiled_or_skip():
    if not compiled.ENABLED:
        pytest.skip("numba (the fast extra) is not installed")


@pytest.mark.parametrize("name", list(CHAINS))
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_torch_kernels_agree(name, dtype):
    """The elementwise kernel (frames, end pose, joint axes) and Horner's position against the 4x4 products."""
    chain = CHAINS[name]
    q = chain.random_q(40, generator=torch.Generator().manual_seed(0), dtype=dtype)
    tol = 1e-12 if dtype == F64 else 3e-6
    pose, frames, jac = _torch_path(chain, q)
    g = chain.geometry(dtype)
    end, every, axes = _elementwise(chain, q)
    torch.testing.assert_close(end, pose[:, :3], atol=tol, rtol=0)
    torch.testing.assert_close(every, frames[:, :, :3], atol=tol, rtol=0)
    torch.testing.assert_close(kin.jacobian(g, q.repeat(5, 1)), jac.repeat(5, 1, 1), atol=tol, rtol=0)  # > 128
    z = torch.stack([a[0] for a in axes]).detach().permute(2, 1, 0)  # (b, 3, n)
    slides = g.prismatic[:, 0]  # a prismatic joint's axis is its linear column, a revolute one's its angular
    torch.testing.assert_close(z, torch.where(slides, jac[:, :3], jac[:, 3:]), atol=tol, rtol=0)
    torch.testing.assert_close(kin.position_horner(g, q.T.contiguous()).T, pose[:, :3, 3], atol=tol, rtol=0)


@pytest.mark.parametrize("name", list(CHAINS))
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_compiled_kernels_give_the_torch_paths_numbers(name, dtype):
    """Every small-batch entry point the compiled recursion serves (float64 inside, the result in
    ``q``'s dtype) against the torch 4x4 products: end poses, every frame, Jacobians, the
    batch-last frames and axes, the position, and one configuration's frames as Python floats."""
    _compiled_or_skip()
    chain = CHAINS[name]
    q = chain.random_q(40, generator=torch.Generator().manual_seed(0), dtype=dtype)
    tol = 1e-12 if dtype == F64 else 3e-6
    pose, frames, jac = _torch_path(chain, q)
    g = chain.geometry(dtype)
    assert kin.compilable(q)
    for got, want in ((kin.end_pose(g, q), pose), (kin.all_poses(g, q), frames), (kin.jacobian(g, q), jac)):
        assert got.dtype == dtype
        torch.testing.assert_close(got, want, atol=tol, rtol=0)
    for keep in (True, False):
        (fast, fast_axes), (slow, slow_axes) = kin.frames_batch_last(g, q.T), _grad_frames_batch_last(g, q.T)
        if not keep:
            (fast, fast_axes), slow, slow_axes = kin.frames_batch_last(g, q.T, keep=False), slow[-1:], []
        assert len(fast) == len(slow) and len(fast_axes) == len(slow_axes)
        for a, b in zip([*fast, *fast_axes], [*slow, *slow_axes]):
            torch.testing.assert_close(torch.stack(a), torch.stack(b), atol=tol, rtol=0)
    torch.testing.assert_close(kin.position_batch_last(g, q.T), pose[:, :3, 3].T, atol=tol, rtol=0)
    for i in (0, 17):
        _check_frame_lists(g, q[i], frames[i], pose[i], tol)


def _grad_frames_batch_last(g, q):
    """:func:`kin.frames_batch_last` through the elementwise torch kernel (autograd on), detached."""
    frames, axes = kin.frames_batch_last(g, q.contiguous().requires_grad_())
    return [tuple(t.detach() for t in f) for f in frames], [tuple(t.detach() for t in a) for a in axes]


def _check_frame_lists(g, q, frames, pose, tol):
    """``frame_lists`` of ``q (n,)``, and of the same numbers as the envs hold them, a column ``(n, 1)``."""
    for layout in (q, q[:, None]):
        lists, end = kin.frame_lists(g, layout)
        as_matrix = [torch.tensor(f, dtype=F64).T for f in lists]  # (3, 4): axis columns and origin
        torch.testing.assert_close(torch.stack(as_matrix), frames[:, :3].double(), atol=tol, rtol=0)
        torch.testing.assert_close(torch.tensor(end, dtype=F64).T, pose[:3].double(), atol=tol, rtol=0)


@pytest.mark.parametrize("name", list(CHAINS))
def test_frame_lists_without_the_compiled_kernels(name, monkeypatch):
    """Without numba, one configuration's frames as Python floats come from the torch kernels."""
    monkeypatch.setattr(compiled, "ENABLED", False)
    chain = CHAINS[name]
    q = chain.random_q(3, generator=torch.Generator().manual_seed(4))
    pose, frames, _ = _torch_path(chain, q)
    _check_frame_lists(chain.geometry(F64), q[1], frames[1], pose[1], 1e-12)


needs_numba = pytest.mark.skipif(not compiled.ENABLED, reason="numba not installed or IIWA_TORCH_NUMBA=0")
kernels = compiled.kernels() if compiled.ENABLED else None


def _tilted(angle: float, shift) -> torch.Tensor:
    t = torch.eye(4, dtype=torch.float64)
    c, s = math.cos(angle), math.sin(angle)
    t[:2, :2] = torch.tensor([[c, -s], [s, c]])
    t[:3, 3] = torch.tensor(shift)
    return t


DH_CHAINS = {
    "iiwa14_tool": robots.iiwa14(tool=_tilted(0.3, (0.01, -0.02, 0.05))),
    "puma560": robots.puma560(),
    "lrmate_modified_base": DHChain(robots.lrmate200ic().dh, convention="modified",
                                    base=_tilted(-0.7, (0.1, 0.2, 0.3)), tool=_tilted(0.2, (0.0, 0.0, 0.1))),
    "planar3r": robots.planar3r(),
}  # fmt: skip


def both_ways(monkeypatch, fn, one_seed_per_round: bool = False):
    """``fn()`` with the kernels enabled, then with them switched off (and, if
    ``one_seed_per_round``, the torch rounds of ik.solve one seed wide, as the compiled ones)."""
    fast = fn()
    with monkeypatch.context() as m:
        m.setattr(compiled, "ENABLED", False)
        if one_seed_per_round:
            m.setattr(lm, "round_width", lambda *args: 1)
        slow = fn()
    return fast, slow


@needs_numba
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("name", list(DH_CHAINS))
def test_fk_and_jacobian_of_a_few_configurations(monkeypatch, name, dtype):
    """chain.fk and chain.jacobian, compiled and by torch: one configuration, a few, a batch of two
    dimensions and a transposed (non-contiguous) one; the kernels compute in float64."""
    chain = DH_CHAINS[name]
    gen = torch.Generator().manual_seed(0)
    shapes = ((), (1,), (10,), (2, 5))
    for q in [chain.random_q(*shape, dtype=dtype, generator=gen) for shape in shapes] + [
        chain.random_q(chain.n_joints, 3, dtype=dtype, generator=gen)[:, :, 0].T
    ]:
        for method in (chain.fk, chain.jacobian):
            fast, slow = both_ways(monkeypatch, lambda: method(q))  # noqa: B023
            assert fast.dtype == slow.dtype == dtype and fast.shape == slow.shape
            tol = 1e-6 if dtype == torch.float32 else 1e-14
            assert torch.allclose(fast, slow, atol=tol, rtol=0), (method.__name__, (fast - slow).abs().max())


@needs_numba
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("shape", [(7,), (1, 7)])
def test_one_configuration_shortcut(shape, dtype):
    """fk/jacobian of one plain float64 or float32 configuration skip check_q (Chain._one_by_kernel):
    the same numbers and dtype, bit for bit, as the checked path (taken by a Parameter), the chain's
    current buffers (load_state_dict), and the same errors: the kernel refuses a NaN or inf, so q goes
    to check_q; huge finite values are answered, as the checked path answers them."""
    chain = robots.iiwa14(tool=_tilted(0.3, (0.01, -0.02, 0.05)))
    q = chain.random_q(1, generator=torch.Generator().manual_seed(5), dtype=dtype).reshape(shape)
    assert chain._one_by_kernel(q, "end_pose", (4, 4)) is not None
    for method in (chain.fk, chain.jacobian):
        fast = method(q)
        assert fast.dtype == dtype and torch.equal(fast, method(torch.nn.Parameter(q, requires_grad=False)))
    position = chain.position(q)  # one configuration: fk's translation; the batched kernel's to rounding
    assert position.shape == (*shape[:-1], 3) and torch.equal(position, chain.fk(q)[..., :3, 3])
    torch.testing.assert_close(position, chain.position(torch.nn.Parameter(q, requires_grad=False)))
    other = robots.iiwa7()
    chain.load_state_dict(other.state_dict())
    assert torch.equal(chain.fk(q), other.fk(torch.nn.Parameter(q, requires_grad=False)))
    for bad in (math.nan, math.inf, -math.inf):
        for j in (0, 6):
            x = q.clone()
            x.view(-1)[j] = bad
            index = (j,) if len(shape) == 1 else (0, j)
            for method in (chain.fk, chain.jacobian):
                with pytest.raises(ValueError, match=re.escape(f"q contains NaN or inf (first at index {index})")):
                    method(x)
    huge = torch.full(shape, torch.finfo(dtype).max, dtype=dtype)
    assert chain._one_by_kernel(huge, "end_pose", (4, 4)) is not None
    assert torch.equal(chain.fk(huge), chain.fk(torch.nn.Parameter(huge, requires_grad=False)))
    strided = torch.stack([q.reshape(-1), q.reshape(-1)], -1)[..., 0].reshape(shape)  # not contiguous: the same
    assert not strided.is_contiguous() and torch.equal(chain.fk(strided), chain.fk(q))


@needs_numba
def test_a_non_finite_configuration_gives_a_nan_pose():
    """The kernels leave no row unwritten: a configuration with a NaN or inf gives an all-NaN pose (and
    ``False`` from the one-configuration kernels), its neighbours their poses."""
    kernels = compiled.kernels()
    chain = robots.iiwa14()
    arrays = chain.geometry().float_arrays
    q = chain.random_q(3, generator=torch.Generator().manual_seed(2)).numpy()
    q[1, 4] = math.inf
    poses = np.zeros((3, 4, 4))
    kernels.end_poses(*arrays, q, poses)
    assert np.isnan(poses[1]).all() and np.array_equal(poses[[0, 2]], chain.fk(torch.from_numpy(q[[0, 2]])).numpy())
    jac = np.zeros((6, 7))
    assert not kernels.jacobian(*arrays, tuple(q[1]), jac) and np.isnan(jac).all()
    assert not kernels.end_pose(*arrays, (math.nan,) * 7, poses[0]) and np.isnan(poses[0]).all()


@needs_numba
def test_one_configuration_shortcut_follows_the_buffers():
    """The shortcut's cached geometry follows every way a buffer changes: an in-place write to any
    geometry buffer, ``.data =``, a buffer assigned or registered anew, a dtype round trip; each
    answer is a fresh chain's, through the checked path (a Parameter)."""
    def same(chain, fresh):
        for q in (torch.full((6,), 0.3, dtype=torch.float64), torch.full((1, 6), -0.7, dtype=torch.float64)):
            for method, other in ((chain.fk, fresh.fk), (chain.jacobian, fresh.jacobian)):
                assert torch.equal(method(q), other(torch.nn.Parameter(q, requires_grad=False)))
                assert chain._one_by_kernel(q, "end_pose", (4, 4)) is not None  # the shortcut again, rebuilt

    chain = robots.puma560()
    same(chain, robots.puma560())
    edits = [
        lambda c: c.dh[2, 2].add_(0.05),
        lambda c: c.tool[:3, 3].copy_(torch.tensor([0.0, 0.1, 0.2])),
        lambda c: c.base[2, 3].fill_(0.4),
        lambda c: setattr(c.dh, "data", c.dh.clone() * 1.01),
        lambda c: setattr(c, "tool", robots.puma560().fk(torch.full((6,), 0.2, dtype=torch.float64))),
        lambda c: c.register_buffer("base", torch.eye(4, dtype=torch.float64)),
        lambda c: c.float().double(),
    ]
    for edit in edits:
        edit(chain)
        fresh = DHChain(chain.dh.clone(), base=chain.base.clone(), tool=chain.tool.clone(), limits=chain.limits.clone())
        same(chain, fresh)
    chain.limits[0, 0] = chain.limits[1, 0] + 1.0  # lower above upper: the next one-configuration call says so
    with pytest.raises(ValueError, match="lower <= upper"):
        chain.fk(torch.zeros(6, dtype=torch.float64))


@needs_numba
@pytest.mark.parametrize("name", ["iiwa14", "puma560", "lrmate200ic"])
def test_capsule_clearance_of_one_configuration(monkeypatch, name):
    """collision.capsule_clearance of one CPU configuration against the floor (three heights, or
    none) and itself: the compiled closed form gives autograd's distances and gradients through the
    torch formulas, in float64 and float32."""
    chain = getattr(robots, name)()
    capsules = collision.robot_capsules(chain)
    q = chain.random_q(40, generator=torch.Generator().manual_seed(2))
    # where two segments cross, the gap's direction (and so its gradient) is undefined: keep configurations
    # whose self pairs are 1 mm apart or more
    radius = dict(zip(capsules.names, capsules.radii.tolist()))
    d = collision.pairwise_clearance(chain, q, collision.World(floor=None), capsules)
    gap = d.distance + torch.tensor([radius[a] + radius[b] for a, b in d.pairs], dtype=q.dtype)
    q = q[(gap > 1e-3).all(-1)][:20]
    assert q.shape[0] >= 10
    for i in range(q.shape[0]):
        for floor in (None, 0.0, -0.1):
            for x in (q[i : i + 1], q[i].float()):
                world = collision.World(floor=floor)
                d1, g1 = collision.capsule_clearance(chain, x, world, capsules)
                with monkeypatch.context() as m:  # torch in float64, as the kernel computes: near ties pick one pair
                    m.setattr(compiled, "ENABLED", False)
                    d0, g0 = (t.to(x.dtype) for t in collision.capsule_clearance(chain, x.double(), world, capsules))
                assert d1.dtype == x.dtype and d1.shape == d0.shape and g1.shape == g0.shape
                tol = 1e-12 if x.dtype == torch.float64 else 1e-6
                torch.testing.assert_close(d1, d0, atol=tol, rtol=0)
                torch.testing.assert_close(g1, g0, atol=tol, rtol=0)


@pytest.mark.parametrize("name", ["iiwa14", "panda"])
@pytest.mark.parametrize("kernels", ["compiled", "torch"])
def test_own_clearance_of_one_configuration(monkeypatch, name, kernels):
    """collision.own_clearance_of_one (the single env's collision flag) against the torch path of
    collision.clearance in float64, with the floor at three heights or none: the compiled kernel,
    or without numba torch's own distances."""
    if name not in CHAINS:
        pytest.skip("pybullet_data (the Panda's URDF) not installed")
    if kernels == "compiled":
        _compiled_or_skip()
    chain = CHAINS[name]
    if name == "panda":
        import envs

        capsules = envs.make_task("FrankaReach-v0").world.capsules  # fitted to the URDF's meshes
    else:
        capsules = collision.robot_capsules(chain)
    monkeypatch.setattr(compiled, "ENABLED", kernels == "compiled" and compiled.ENABLED)
    q = chain.random_q(30, generator=torch.Generator().manual_seed(5))
    for floor in (None, 0.0, 0.3):
        with torch.enable_grad():  # autograd on: clearance takes its torch path
            world = collision.World(floor=floor)
            want = collision.clearance(chain, q.clone().requires_grad_(), world, capsules).detach()
        for i in range(q.shape[0]):
            for x in (q[i], q[i, :, None].float()):  # a row, and one env's float32 column (n, 1)
                got = collision.own_clearance_of_one(chain, x, floor, capsules)
                assert isinstance(got, float)
                assert got == pytest.approx(float(want[i]), abs=1e-12 if x.dtype == F64 else 1e-5)


@needs_numba
def test_answer_errors_and_into_limits():
    rng = np.random.default_rng(1)
    chain = robots.iiwa14()
    q = chain.random_q(50, generator=torch.Generator().manual_seed(2))
    pose = chain.fk(q).numpy()
    target = chain.fk(chain.random_q(50, generator=torch.Generator().manual_seed(3))).numpy()
    target[:3] = pose[:3]  # zero error
    target[3, :3, :3] = pose[3, :3, :3] @ np.diag([-1.0, -1.0, 1.0])  # a half turn
    target[5] = pose[5]
    target[5, 0, 3] += 5e-5  # within 1e-4 m and 1e-3 rad: a success
    pos, rot = np.ascontiguousarray(target[:, :3, 3]), np.ascontiguousarray(target[:, :3, :3])
    pos_ref, rot_ref = (v.norm(dim=-1).numpy() for v in so3.pose_error(torch.from_numpy(pose),
                                                                         torch.from_numpy(target)))
    arrays = chain.geometry(torch.float64).float_arrays
    pos_err, rot_err, success = kernels.answer_errors(*arrays, q.numpy(), pos, rot, 1e-7, False, 1e-4, 1e-3)
    assert np.allclose(pos_err, pos_ref, atol=1e-15) and np.allclose(rot_err, rot_ref, atol=1e-7)
    assert abs(rot_err[3] - math.pi) < 1e-7 and np.allclose(rot_err[4:], rot_ref[4:], atol=1e-13)
    assert success.tolist() == [True] * 3 + [False, False, True] + [False] * 44
    pos_err, rot_err, success = kernels.answer_errors(*arrays, q.numpy(), pos, np.empty((0, 3, 3)), 1e-7, False, 1e-4,
                                                      1e-3)  # fmt: skip
    assert np.allclose(pos_err, pos_ref, atol=1e-15) and not rot_err.any()
    assert success.tolist() == [True] * 3 + [False, False, True] + [False] * 44
    # float32: the pose rounded as chain.fk rounds it, before the errors
    q32 = q.float()
    pose32 = chain.float().fk(q32).double()
    pos32 = so3.pose_error(pose32, torch.from_numpy(target))[0].norm(dim=-1).numpy()
    arrays32 = chain.float().geometry(torch.float32).float_arrays
    pos_err, _, _ = kernels.answer_errors(*arrays32, q32.double().numpy(), pos, rot, 1e-7, True, 1e-4, 1e-3)
    assert np.allclose(pos_err, pos32, atol=1e-15) and not np.allclose(pos_err[:3], 0.0, atol=1e-12)
    lo, hi = chain.limits.numpy()
    q = rng.uniform(-12.0, 12.0, (400, 7))  # mostly outside the limits, by up to two turns
    expected = lm_setup.into_limits(q, lo, hi)  # numpy in: numpy's remainder, as the kernel's
    got = np.array([[kernels.into_limits(x, lo[i], hi[i]) for i, x in enumerate(row)] for row in q])
    assert np.array_equal(got, expected)
    # torch's remainder rounds differently in float64 (a - b floor(a / b)): the same within 1e-14
    torch_answer = lm_setup.into_limits(torch.from_numpy(q), chain.limits[0], chain.limits[1]).numpy()
    assert np.allclose(got, torch_answer, atol=1e-14, rtol=0)
    assert ((got >= lo) & (got <= hi)).all()


def _solve_cases():
    iiwa = robots.iiwa14()
    target, q = _targets(iiwa, 24, 5, "pose")
    q0 = q + 0.1 * torch.randn(q.shape, generator=torch.Generator().manual_seed(6), dtype=q.dtype)
    q0[::3, 0] += 2 * math.pi
    yield "iiwa pose", iiwa, target, {}
    yield "iiwa q0 rest weight", iiwa, target, dict(q0=q0, rest=q, rest_gain=0.1, rot_weight=0.5, seeds=3,
                                                    iterations=12, check_every=3)  # fmt: skip
    yield "iiwa float32 tight", iiwa, target.float(), dict(pos_tol=1e-5, rot_tol=1e-4, precision="input")
    yield "iiwa position", iiwa, _targets(iiwa, 24, 7, "position")[0], dict(mode="position")
    yield "iiwa own generator", iiwa, target[:5], dict(generator=torch.Generator().manual_seed(9))
    puma = robots.puma560()
    yield "puma pose", puma, _targets(puma, 24, 8, "pose")[0], {}
    planar = robots.planar3r()
    yield "planar position", planar, _targets(planar, 24, 9, "position")[0], dict(mode="position")


def _targets(chain, count, seed, mode):
    q = chain.random_q(count, generator=torch.Generator().manual_seed(seed))
    pose = chain.fk(q)
    return (pose if mode == "pose" else pose[:, :3, 3]), q


@needs_numba
@pytest.mark.parametrize("case", list(_solve_cases()), ids=lambda case: case[0])
def test_solve_takes_the_same_steps(monkeypatch, case):
    """The same method: the same answers (to rounding), iterations and success as the torch loop
    taking one seed per round as the compiled rounds do (the width changes no answer:
    test_ik_lm_compiled.py::test_round_width_changes_no_answer), iterating in float64 as they do."""
    _, chain, target, options = case
    options = dict(options)
    q0 = options.pop("q0", None)
    generator = options.pop("generator", None)

    def run():
        gen = None if generator is None else generator.clone_state()
        return solve(chain, target, q0, generator=gen, **{"precision": "input", **options})

    fast, slow = both_ways(monkeypatch, run, one_seed_per_round=True)
    assert torch.equal(fast.success, slow.success)
    assert torch.equal(fast.iterations, slow.iterations)
    assert fast.q.dtype == slow.q.dtype and fast.pos_err.dtype == slow.pos_err.dtype
    # float32 targets: the torch loop iterates in float32, the kernel in float64 (with float32's eps)
    tol = 1e-4 if target.dtype == torch.float32 else 1e-9
    assert (fast.q - slow.q).abs().max() < tol
    assert (fast.pos_err - slow.pos_err).abs().max() < (1e-5 if target.dtype == torch.float32 else 1e-12)
    assert fast.success.float().mean() > 0.7


@needs_numba
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("with_q0", [False, True])
def test_iiwa_solve_sweeps_the_same(monkeypatch, with_q0, dtype):
    """The compiled arm-angle sweep (numba_kernels.iiwa_sweep) against the numpy one it restates: the
    same answers to rounding, on random poses, unreachable ones and with a single arm angle (most
    poses then take the retry with 16 angles). The batched torch path holds both in
    test_iiwa_solve_numpy.py."""
    chain = robots.iiwa14(tool=_tilted(0.3, (0.01, -0.02, 0.05)))
    target, q = _targets(chain, 40, 12, "pose")
    target[:5, :3, 3] *= 3.0  # out of reach
    target, q = target.to(dtype), q.to(dtype)
    for num_psi in (16, 1):
        q0 = q + 0.05 if with_q0 else None
        fast, slow = both_ways(monkeypatch, lambda: analytic.iiwa_solve(chain, target, q0, num_psi=num_psi))  # noqa: B023
        assert torch.equal(fast.success, slow.success) and fast.q.dtype == slow.q.dtype == dtype
        tol = 1e-5 if dtype == torch.float32 else 1e-12
        assert (fast.q - slow.q).abs().max() < tol
        assert (fast.pos_err - slow.pos_err).abs().max() < tol and fast.success[5:].all()


@needs_numba
@pytest.mark.parametrize("name", ["puma560", "lrmate_base_tool"])
def test_pieper_branches_are_the_numpy_ones(monkeypatch, name):
    """The compiled closed form of pieper (numba_kernels.pieper_branches) against the numpy one it
    restates, on every branch of random, unreachable and wrist-aligned poses: the same flags, joints
    within 1e-12 rad where rounding does not decide (away from +-pi and the limits). The batched
    torch path holds both in test_pieper_numpy.py."""
    chain = robots.puma560() if name == "puma560" else robots.lrmate200ic()
    if name == "lrmate_base_tool":
        chain.base.copy_(_tilted(-0.7, (0.1, 0.2, 0.3)))
        chain.tool.copy_(_tilted(0.2, (0.0, 0.0, 0.1)))
    q = chain.random_q(60, generator=torch.Generator().manual_seed(13))
    q[40:, 4] = -chain.dh[4, 3]  # wrist aligned
    target = chain.fk(q)
    target[:5, :3, 3] *= 5.0  # out of reach
    fast, slow = both_ways(monkeypatch, lambda: analytic.pieper(chain, target))
    for field in ("valid", "reachable", "within_limits"):
        assert torch.equal(getattr(fast, field), getattr(slow, field)), field
    assert fast.q.stride() == slow.q.stride() and fast.q.dtype == slow.q.dtype
    lo, hi = chain.limits
    clear = ((slow.q.abs() - math.pi).abs() > 1e-9) & ((slow.q - lo).abs() > 1e-9) & ((slow.q - hi).abs() > 1e-9)
    aligned = torch.zeros_like(clear)
    aligned[40:] = True  # at sin(theta5) = 0 rounding splits theta4 +- theta6
    keep = clear.all(-1, keepdim=True) & ~aligned
    assert keep.float().mean() > 0.5
    assert (fast.q - slow.q).abs()[keep.expand_as(fast.q)].max() < 1e-12
    assert slow.reachable[5:].any(-1).all() and not slow.reachable[:5].any()


def test_fallback_without_the_kernels(monkeypatch):
    """Switched off, solve takes the torch loop for a few targets, and fk and jacobian of one
    configuration the torch kernels, which agree with those under autograd."""
    monkeypatch.setattr(compiled, "ENABLED", False)
    chain = robots.iiwa14()
    target, q = _targets(chain, 10, 11, "pose")
    assert not lm_compiled.handles(target, None, None, None, 10)
    assert solve(chain, target).success.float().mean() > 0.8
    with torch.enable_grad():  # the torch kernels, through autograd
        q_grad = q[:1].clone().requires_grad_(True)
        reference = chain.fk(q_grad).detach(), chain.jacobian(q_grad).detach()
    assert torch.allclose(chain.fk(q[:1]), reference[0], atol=1e-14)
    assert torch.allclose(chain.jacobian(q[:1]), reference[1], atol=1e-14)


def _run(code: str, **env) -> list[str]:
    environ = {k: v for k, v in os.environ.items() if k != "IIWA_TORCH_NUMBA"} | env
    return subprocess.run([sys.executable, "-c", code], env=environ, capture_output=True, text=True,
                          check=True).stdout.split()  # fmt: skip


def test_nothing_compiled_or_imported_at_import():
    """``import iiwa_torch`` (and its subpackages) loads no numba; the first small-batch call does,
    if enabled; IIWA_TORCH_NUMBA=0 keeps it out even then."""
    code = (
        "import sys, torch, iiwa_torch, iiwa_torch.ik, iiwa_torch.ik.analytic, iiwa_torch.trajectory\n"
        "from iiwa_torch import robots; from iiwa_torch.ik import solve\n"
        "print('numba' in sys.modules)\n"
        "arm = robots.iiwa14(); solve(arm, arm.fk(arm.random_q(1)))\n"
        "from iiwa_torch import compiled; print(compiled.ENABLED, 'numba' in sys.modules)\n"
    )
    assert _run(code, IIWA_TORCH_NUMBA="0") == ["False", "False", "False"]
    enabled = str(importlib.util.find_spec("numba") is not None)  # the child runs without the switch
    assert _run(code) == ["False", enabled, enabled]


@needs_numba
def test_sine_and_cosine_of_the_clearance_kernel():
    """The clearance kernel's branch-free sine and cosine against libm's (numpy's) over its range,
    including angles next to multiples of pi/2 (where the reduction cancels) and the quadrant ends."""
    rng = np.random.default_rng(3)
    edges = np.arange(-60000, 60001, 7) * (math.pi / 2)
    x = np.concatenate([rng.uniform(-1e5, 1e5, 200_000), rng.uniform(-7, 7, 100_000), edges,
                        np.nextafter(edges, np.inf), np.nextafter(edges, -np.inf), [0.0, -0.0, 1e5, -1e5]])
    sin, cos = np.array([kernels.sin_cos(v) for v in x]).T
    assert np.abs(sin - np.sin(x)).max() <= 2.3e-16 and np.abs(cos - np.cos(x)).max() <= 2.3e-16
