"""Any serial chain: URDF robots against pinocchio (double precision, the same files), every
kernel path against the others, the iiwa's URDF against its DH preset, and the model itself
(continuous and prismatic joints, limits, state dict, URDF round trip)."""

import math
import pathlib
import warnings

import numpy as np
import pytest
import torch
from urdf_samples import ODD_URDF, pinocchio_q

from iiwa_torch import Chain, ik, robots, urdf
from iiwa_torch.dh import DHChain
from iiwa_torch.ik.lm_compiled import COMPILED_BATCH

pin = pytest.importorskip("pinocchio")
pytest.importorskip("pytorch_kinematics")
pybullet_data = pytest.importorskip("pybullet_data")
DATA = pathlib.Path(pybullet_data.getDataPath())
F64 = torch.float64

# (file, end_link)
FILES = {
    "panda": ("franka_panda/panda.urdf", "panda_hand"),
    "iiwa": ("kuka_iiwa/model.urdf", None),
    "xarm6": ("xarm/xarm6_robot.urdf", None),
}

def _chain(name: str) -> Chain:
    if name == "odd":
        return robots.from_urdf(ODD_URDF, end_link="tip")
    file, end = FILES[name]
    return robots.from_urdf(DATA / file, end_link=end)


def _model(name: str):
    if name == "odd":
        return pin.buildModelFromXML(ODD_URDF)
    return pin.buildModelFromUrdf(str(DATA / FILES[name][0]))


def _pinocchio(name: str, chain: Chain, q: np.ndarray, end_link: str):
    """pinocchio's end pose, link frames (the chain's ``link_names``) and world-aligned Jacobian of
    ``end_link`` for each row of ``q`` (the chain's joint order); joints off the path at 0."""
    model = _model(name)
    data = model.createData()
    slots = [model.joints[model.getJointId(j)] for j in chain.joint_names]
    end, links = model.getFrameId(end_link), [model.getFrameId(link) for link in chain.link_names]
    poses, frames, jacobians = [], [], []
    for row in q:
        full = pinocchio_q(pin, model, slots, row)
        pin.forwardKinematics(model, data, full)
        pin.updateFramePlacements(model, data)
        poses.append(data.oMf[end].homogeneous.copy())
        frames.append(np.stack([data.oMf[f].homogeneous for f in links]))
        jac = pin.computeFrameJacobian(model, data, full, end, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
        jacobians.append(np.stack([jac[:, slot.idx_v] for slot in slots], 1))
    return np.stack(poses), np.stack(frames), np.stack(jacobians)


def _end_link(name: str, chain: Chain) -> str:
    return "tip" if name == "odd" else (FILES[name][1] or urdf.read_urdf(DATA / FILES[name][0]).end_link)


@pytest.mark.parametrize("name", ["panda", "iiwa", "xarm6", "odd"])
def test_fk_frames_and_jacobian_match_pinocchio(name):
    chain = _chain(name)
    q = chain.random_q(1000, generator=torch.Generator().manual_seed(0))
    if name == "odd":  # beyond one turn too: continuous joints have no limit
        q[:, 2] = torch.linspace(-9.0, 9.0, 1000, dtype=F64)
    pose, frames, jac = _pinocchio(name, chain, q[:300].numpy(), _end_link(name, chain))
    np.testing.assert_allclose(chain.fk(q[:300]).numpy(), pose, rtol=0, atol=1e-12)
    all_frames = chain.fk_all(q[:300])
    np.testing.assert_allclose(all_frames[:, 1:].numpy(), frames, rtol=0, atol=1e-12)
    np.testing.assert_allclose(all_frames[:, 0].numpy(), np.broadcast_to(np.eye(4), (300, 4, 4)), rtol=0, atol=0)
    np.testing.assert_allclose(chain.jacobian(q[:300]).numpy(), jac, rtol=0, atol=1e-12)
    # every batch path (one, small, elementwise, blocks) agrees with the reference at 1e-12
    pose_all, _, _ = _pinocchio(name, chain, q.numpy(), _end_link(name, chain))
    for size in (1, 7, 129, 1000):
        np.testing.assert_allclose(chain.fk(q[:size]).numpy(), pose_all[:size], rtol=0, atol=1e-12)
        np.testing.assert_allclose(chain.position(q[:size]).numpy(), pose_all[:size, :3, 3], rtol=0, atol=1e-12)
    np.testing.assert_allclose(chain.fk(q[5]).numpy(), pose_all[5], rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", ["panda", "odd"])
def test_jacobian_is_the_derivative_and_gradients_check(name):
    chain = _chain(name)
    q = chain.random_q(4, generator=torch.Generator().manual_seed(1))
    jac = chain.jacobian(q)
    h = 1e-6
    for i in range(chain.n_joints):
        step = torch.zeros(chain.n_joints, dtype=F64)
        step[i] = h
        plus, minus = chain.fk(q + step), chain.fk(q - step)
        np.testing.assert_allclose(((plus - minus)[:, :3, 3] / (2 * h)).numpy(), jac[:, :3, i].numpy(), atol=1e-8)
        spin = (plus[:, :3, :3] - minus[:, :3, :3]) / (2 * h) @ chain.fk(q)[:, :3, :3].transpose(1, 2)  # [w]x
        w = torch.stack([spin[:, 2, 1], spin[:, 0, 2], spin[:, 1, 0]], -1)
        np.testing.assert_allclose(w.numpy(), jac[:, 3:, i].numpy(), atol=1e-8)
    for batch in (3, 200):  # the small-batch ops, and the closed-form backward above 128
        x = chain.random_q(batch, generator=torch.Generator().manual_seed(2)).requires_grad_()
        weights = torch.randn(batch, 4, 4, dtype=F64, generator=torch.Generator().manual_seed(3))
        assert torch.autograd.gradcheck(lambda v, w=weights: (chain.fk(v) * w).sum(), (x,))


def test_float32_matches_pytorch_kinematics():
    pk = pytest.importorskip("pytorch_kinematics")
    file, end = FILES["panda"]
    theirs = pk.build_serial_chain_from_urdf((DATA / file).read_bytes(), end)
    chain = _chain("panda")
    q = chain.random_q(5000, generator=torch.Generator().manual_seed(4))
    expected = theirs.forward_kinematics(q.float()).get_matrix()
    assert (chain.fk(q.float()) - expected).abs().max() < 2e-6  # pk rounds the file's origins to float32
    assert chain.fk(q.float()).dtype == torch.float32


def test_kuka_iiwa_urdf_is_the_iiwa14_preset_up_to_the_flange():
    """pybullet_data's iiwa and the DH preset: the same joint axes (each up to its sign) and, once
    the flange offset is matched at q = 0, the same pose for every configuration."""
    theirs, ours = _chain("iiwa"), robots.iiwa14()
    zero = torch.zeros(7, dtype=F64)
    z_theirs, z_ours = theirs.jacobian(zero)[3:], ours.jacobian(zero)[3:]
    sign = (z_theirs * z_ours).sum(0)
    np.testing.assert_allclose(sign.abs().numpy(), np.ones(7), atol=1e-12)
    flange = torch.linalg.inv(theirs.fk(zero)) @ ours.fk(zero)
    q = ours.random_q(1000, generator=torch.Generator().manual_seed(5))
    # the file writes pi/2 as 1.57079632679 (5e-12 rad short), which moves the hand by up to 2e-11 m
    np.testing.assert_allclose((theirs.fk(q * sign) @ flange).numpy(), ours.fk(q).numpy(), rtol=0, atol=1e-10)


@pytest.mark.parametrize("name", ["panda", "odd", "iiwa14", "lrmate200ic"])
def test_urdf_round_trip(name):
    chain = robots.PRESETS[name]() if name in robots.PRESETS else _chain(name)
    again = robots.from_urdf(urdf.to_urdf(chain))
    q = chain.random_q(200, generator=torch.Generator().manual_seed(6))
    np.testing.assert_allclose(again.fk(q).numpy(), chain.fk(q).numpy(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(again.jacobian(q).numpy(), chain.jacobian(q).numpy(), rtol=0, atol=1e-12)
    if name not in robots.PRESETS:  # a DH chain's link frames are its DH frames, a URDF's its joint frames
        np.testing.assert_allclose(again.fk_all(q).numpy(), chain.fk_all(q).numpy(), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(again.limits.numpy(), chain.limits.numpy())
    assert again.joint_names == chain.joint_names and again.kinds == chain.kinds


def test_continuous_and_prismatic_joints():
    chain = _chain("odd")
    assert [k.value for k in chain.kinds] == ["revolute", "prismatic", "continuous", "revolute"]
    assert chain.limits[:, 2].tolist() == [-math.inf, math.inf]
    q = chain.random_q(10_000, generator=torch.Generator().manual_seed(7))
    assert (q[:, 2].abs() <= math.pi).all() and q[:, 2].abs().max() > 3.1  # one turn, documented
    far = q.clone()
    far[:, 2] += 20.0
    assert chain.within_limits(far).all() and torch.equal(chain.clamp(far)[:, 2], far[:, 2])
    # a prismatic joint moves the end along its axis, in closed form
    zero = torch.zeros(4, dtype=F64)
    slide = zero.clone()
    slide[1] = 0.2
    axis = chain.fk_all(zero)[2, :3, :3] @ torch.tensor([1.0, 1.0, 0.0], dtype=F64) / math.sqrt(2)
    np.testing.assert_allclose((chain.fk(slide) - chain.fk(zero))[:3, 3].numpy(), (0.2 * axis).numpy(), atol=1e-15)
    with pytest.raises(ValueError, match="prismatic"):
        Chain(torch.eye(4)[None], [[0.0, 0.0, 1.0]], kinds=["prismatic"])



@pytest.mark.parametrize("axis", [[0, 0, -1], [1e-6, 0, -1], [2e-6, 0, -1], [0, 3e-6, -1], [1e-6, -2e-6, -0.5],
                                  [1e-4, 0, -1], [2e-6, 0, 1], [1, 0, 0], [0.3, -0.4, 0.5]])
def test_a_joint_turns_by_the_exponential_of_its_axis(axis):
    """Every axis turns by exp(q [a]x), also one a hair off -z (CAD exports write such axes)."""
    a = torch.tensor(axis, dtype=F64) / torch.tensor(axis, dtype=F64).norm()
    skew = torch.tensor([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]], dtype=F64)
    chain = Chain(torch.eye(4, dtype=F64)[None], [axis])
    for q in (0.3, 1.0, -2.5):
        expected = torch.linalg.matrix_exp(skew * q)
        np.testing.assert_allclose(chain.fk(torch.tensor([q], dtype=F64))[:3, :3].numpy(), expected.numpy(), atol=2e-15)

def test_repr_keeps_long_joint_names_apart_from_their_columns():
    names = ["a_rather_long_joint_name_1", "j2"]
    chain = Chain(torch.eye(4).repeat(2, 1, 1), [[0.0, 0.0, 1.0], [0.0, -1.0, 0.0]], joint_names=names)
    rows = repr(chain).splitlines()[3:5]
    assert [row.split()[:3] for row in rows] == [[names[0], "revolute", "(0,"], ["j2", "revolute", "(0,"]]
    assert "(0, -1, 0)" in rows[1] and "-0" not in rows[0]
    dh = DHChain([[-1e-17, -math.pi / 2, 0.36, 0.0]], joint_names=["A1_of_a_long_name"])
    assert repr(dh).splitlines()[3].split()[:4] == ["A1_of_a_long_name", "0.0000", "-90.0", "0.3600"]


def test_a_parameter_in_place_of_a_buffer_is_refused_and_loses_nothing():
    for chain in (_chain("odd"), robots.iiwa14()):
        q = chain.random_q(generator=torch.Generator().manual_seed(1))
        before = chain.fk(q)
        for name in ("tool", "base", "limits"):
            with pytest.raises(TypeError, match=f"chain.{name} is a buffer: assign a plain tensor"):
                setattr(chain, name, torch.nn.Parameter(getattr(chain, name).clone()))
        torch.testing.assert_close(chain.fk(q), before, atol=0, rtol=0)


@pytest.mark.parametrize("bad", [[0.0] * 7, [math.nan] * 7, [math.inf] * 7, [-1.0] * 7, [1.0] * 5])
def test_velocity_limits_are_checked_when_assigned_or_loaded(bad):
    """The envs and trajectories divide by them: NaN observations followed from zeros."""
    arm = robots.iiwa14()
    kept = arm.velocity_limits.clone()
    with pytest.raises(ValueError, match="velocity_limits must be 7 positive finite speeds"):
        arm.velocity_limits = torch.tensor(bad, dtype=F64)
    assert torch.equal(arm.velocity_limits, kept)
    with pytest.raises(ValueError, match="velocity_limits must be 7 positive finite speeds"):
        Chain(torch.eye(4).repeat(7, 1, 1), [[0.0, 0.0, 1.0]] * 7, velocity_limits=bad)
    if len(bad) == 7:
        state = {**robots.iiwa14().state_dict(), "velocity_limits": torch.tensor(bad, dtype=F64)}
        with pytest.raises(ValueError, match="velocity_limits must be 7 positive finite speeds"):
            arm.load_state_dict(state)


def test_buffers_are_the_truth():
    chain = _chain("panda")
    q = chain.random_q(50, generator=torch.Generator().manual_seed(8))
    pose = chain.fk(q)
    copy = _chain("panda")
    with torch.no_grad():
        copy.origins[0, 2, 3] += 0.5  # raise the arm in place: the next call sees it
    np.testing.assert_allclose((copy.fk(q) - pose)[:, 2, 3].numpy(), 0.5, atol=1e-12)
    copy.load_state_dict(chain.state_dict())
    np.testing.assert_allclose(copy.fk(q).numpy(), pose.numpy(), rtol=0, atol=0)
    single = chain.to(torch.float32)
    assert single.fk(q.float()).dtype == torch.float32
    with pytest.raises(ValueError, match="origins"):
        bad = _chain("panda")
        with torch.no_grad():
            bad.origins[1, :3, :3] *= 2
        bad.fk(q)


def test_gradient_ik_solves_the_panda():
    panda = _chain("panda")
    target = panda.fk(panda.random_q(300, generator=torch.Generator().manual_seed(9)))
    result = ik.solve(panda, target, pos_tol=1e-5, rot_tol=1e-5, generator=torch.Generator().manual_seed(0))
    assert result.success.float().mean() >= 0.99
    assert panda.within_limits(result.q).all()
    reached = panda.fk(result.q[result.success])
    assert (reached[:, :3, 3] - target[result.success][:, :3, 3]).norm(dim=-1).max() <= 1e-5


def test_arm_specific_pieces_say_so():
    """The closed forms and the preset capsule models are for the DH presets: another arm gets an
    error that says what to use instead."""
    from iiwa_torch import collision
    from iiwa_torch.ik import analytic

    panda = _chain("panda")
    q = panda.random_q(2, generator=torch.Generator().manual_seed(10))
    for call in (lambda: analytic.iiwa(panda, panda.fk(q), 0.0), lambda: analytic.pieper(panda, panda.fk(q)),
                 lambda: analytic.iiwa_solve(panda, panda.fk(q))):
        with pytest.raises(ValueError, match=r"'panda' is a Chain .* ik\.solve"):
            call()
    with pytest.raises(ValueError, match="no preset capsule model.*capsules="):
        collision.clearance(panda, q)


def test_link_frames_match_pybullet():
    """pybullet's own link frames (``getLinkState``, URDF link frames) on the same file: within its
    float32 rounding of the origins."""
    pybullet = pytest.importorskip("pybullet")
    panda = _chain("panda")
    client = pybullet.connect(pybullet.DIRECT)
    try:
        body = pybullet.loadURDF(str(DATA / FILES["panda"][0]), useFixedBase=True, physicsClientId=client)
        index = {pybullet.getJointInfo(body, j, physicsClientId=client)[1].decode(): j
                 for j in range(pybullet.getNumJoints(body, physicsClientId=client))}
        joints = [index[name] for name in panda.joint_names]
        q = panda.random_q(100, generator=torch.Generator().manual_seed(11))
        frames = panda.fk_all(q)
        for row, expected in zip(q.tolist(), frames):
            for j, value in zip(joints, row):
                pybullet.resetJointState(body, j, value, physicsClientId=client)
            for k, j in enumerate(joints):
                state = pybullet.getLinkState(body, j, computeForwardKinematics=True, physicsClientId=client)
                position, quaternion = np.array(state[4]), np.array(state[5])  # the URDF link frame
                rotation = np.array(pybullet.getMatrixFromQuaternion(quaternion)).reshape(3, 3)
                np.testing.assert_allclose(position, expected[k + 1, :3, 3].numpy(), atol=1e-6)
                np.testing.assert_allclose(rotation, expected[k + 1, :3, :3].numpy(), atol=1e-6)
    finally:
        pybullet.disconnect(client)


@pytest.mark.parametrize("mode", ["position", "pose"])
@pytest.mark.parametrize("count", [3, COMPILED_BATCH + 1, "grad"])  # the compiled and the torch solver
def test_gradient_ik_with_continuous_and_prismatic_joints(count, mode):
    odd = _chain("odd")
    q = odd.random_q(200 if count == "grad" else count, generator=torch.Generator().manual_seed(12))
    q[:, 2] += 7.0  # the continuous joint beyond a turn
    target = odd.fk(q) if mode == "pose" else odd.fk(q)[:, :3, 3]
    if count == "grad":  # a target that requires grad takes the torch solver at any size
        target.requires_grad_(True)
    result = ik.solve(odd, target, mode=mode)
    assert result.success.all() and odd.within_limits(result.q).all()
    assert (odd.fk(result.q)[:, :3, 3] - target[..., :3, 3] if mode == "pose" else odd.position(result.q) - target
            ).norm(dim=-1).max() <= 1e-4
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning of the continuous joint's infinite limits
        assert ik.solve(odd, target, q0=q, mode=mode).success.all()
