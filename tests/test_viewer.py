"""The web viewer: its state without a browser, and what headless Chromium draws of it."""

from __future__ import annotations

import base64
import io
import json
import math
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path
from xml.etree import ElementTree

import numpy as np
import pytest
import torch

pytest.importorskip("viser")

from iiwa_torch import cli, collision, robots, trajectory  # noqa: E402
from iiwa_torch import viewer as viewer_module  # noqa: E402
from iiwa_torch.ik import analytic  # noqa: E402
from iiwa_torch.viewer import Viewer, load_world, show  # noqa: E402
from iiwa_torch.viewer.scene import urdf_parts  # noqa: E402

F64 = torch.float64
Q_FREE = torch.tensor([0.4, 0.7, -0.3, -1.1, 0.5, 0.9, 0.2], dtype=F64)  # clear of itself and the floor


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _rpy_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rz(yaw) Ry(pitch) Rx(roll), written out here."""
    cr, sr, cp, sp, cy, sy = (f(math.radians(a)) for a in (roll, pitch, yaw) for f in (math.cos, math.sin))
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


def _quat_matrix(wxyz) -> np.ndarray:
    """Rotation of a unit quaternion (w, x, y, z), written out here."""
    w, x, y, z = wxyz
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _arm_angle(chain, q: torch.Tensor, points=(1, 3, 5)) -> float:
    """The iiwa's arm angle from its shoulder, elbow and wrist points (the origins of frames
    ``points`` of ``fk_all``), as the closed form's documentation defines it: the angle of the
    elbow about the shoulder-wrist line, from the vertical plane through that line (the base frame
    is the world frame here)."""
    frames = chain.fk_all(q).numpy()
    s, e, w = (frames[i, :3, 3] for i in points)
    u = (w - s) / np.linalg.norm(w - s)
    horizontal = np.array([0.0, 0.0, 1.0]) - u[2] * u  # the base z axis, minus its part along u
    v_ref = horizontal / np.linalg.norm(horizontal)
    w_ref = np.cross(u, v_ref)
    return math.atan2(float((e - s) @ w_ref), float((e - s) @ v_ref))


@pytest.fixture(scope="module")
def chain():
    return robots.iiwa14()


@pytest.fixture(scope="module")
def viewer(chain):
    v = show(chain, port=_free_port(), block=False)
    yield v
    v.stop()


@pytest.fixture(scope="module")
def kuka():
    """pybullet_data's iiwa (``kuka_iiwa/model.urdf``: visual meshes with named colours, an S-R-S
    arm) as ``(file, chain)``."""
    pybullet_data = pytest.importorskip("pybullet_data")
    pytest.importorskip("pytorch_kinematics")
    pytest.importorskip("trimesh")
    file = f"{pybullet_data.getDataPath()}/kuka_iiwa/model.urdf"
    return file, robots.from_urdf(file)


@pytest.fixture(scope="module")
def kuka_viewer(kuka):
    file, chain = kuka
    v = show(chain, port=_free_port(), block=False, urdf=file)  # capsules fitted to its collision meshes
    yield v
    v.stop()


@pytest.fixture
def gradient(viewer):
    viewer.set_ik("gradient")
    return viewer


def test_binds_localhost_by_default(viewer):
    assert viewer.server.get_host() == "127.0.0.1"
    with socket.create_connection(("127.0.0.1", viewer.server.get_port()), timeout=5):
        pass


@pytest.mark.parametrize("host", ["", None])
def test_an_empty_host_means_localhost(host):
    v = Viewer(robots.planar3r(), host=host, port=_free_port())
    try:
        assert v.host == v.server.get_host() == "127.0.0.1"
        with socket.create_connection(("127.0.0.1", v.port), timeout=5):
            pass
    finally:
        v.stop()


def test_a_busy_port_gives_the_port_actually_bound():
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        v = show(robots.planar3r(), port=port, block=False)
        try:
            assert v.port != port
            assert urllib.request.urlopen(f"http://127.0.0.1:{v.port}/", timeout=5).status == 200
        finally:
            v.stop()


def test_port_0_takes_a_free_port():
    v = Viewer(robots.planar3r(), port=0)
    try:
        assert v.port > 0
        assert urllib.request.urlopen(f"http://127.0.0.1:{v.port}/", timeout=5).status == 200
    finally:
        v.stop()


def test_a_host_reachable_from_other_machines_is_warned_about(capsys):
    v = Viewer(robots.planar3r(), host="0.0.0.0", port=_free_port())
    v.stop()
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"anyone who can reach port {v.port} controls it" in err
    Viewer(robots.planar3r(), host="localhost", port=_free_port()).stop()
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize(
    ("host", "port", "error", "message"),
    [
        ("127.0.0.1", 99999, ValueError, "port must be an integer in 0..65535"),
        ("127.0.0.1", -1, ValueError, "port must be an integer in 0..65535"),
        ("127.0.0.1", 8080.0, ValueError, "port must be an integer"),
        ("127.0.0.1", True, ValueError, "port must be an integer"),
        ("999.1.1.1", 8080, ValueError, "host must be an IP address or a host name, got '999.1.1.1'"),
        ("not a host", 8080, ValueError, "host must be an IP address or a host name"),
        (8080, 8080, TypeError, "host must be a str"),
        ("8.8.8.8", 8080, ValueError, "cannot serve on host '8.8.8.8'"),  # not an address of this machine
    ],
)
def test_hosts_and_ports_that_cannot_be_served_are_refused(host, port, error, message):
    with pytest.raises(error, match=re.escape(message)):
        Viewer(robots.planar3r(), host=host, port=port)


def test_set_q_moves_the_readout_to_fk(chain, viewer):
    gen = torch.Generator().manual_seed(11)
    for q in chain.random_q(3, generator=gen):
        viewer.set_q(q)
        pose = chain.fk(q).numpy()
        out = viewer.readout()
        np.testing.assert_allclose(out.xyz, pose[:3, 3], atol=1e-12)
        np.testing.assert_allclose(_rpy_matrix(*out.rpy_deg), pose[:3, :3], atol=1e-9)
        torch.testing.assert_close(viewer.q, q)
        # the sliders show the angles in degrees, to their 0.1 deg step
        np.testing.assert_allclose([s.value for s in viewer.sliders], np.degrees(q.numpy()), atol=0.051)


def test_a_slider_moves_its_joint(chain, viewer):
    viewer.set_q(torch.zeros(7, dtype=F64))
    viewer.sliders[1].value = 30.0  # what a browser's slider does: assign the value, callbacks run
    expected = torch.zeros(7, dtype=F64)
    expected[1] = math.radians(30.0)
    torch.testing.assert_close(viewer.q, expected)
    np.testing.assert_allclose(viewer.readout().xyz, chain.fk(expected)[:3, 3].numpy(), atol=1e-12)


def test_set_q_rejects_bad_input(chain, viewer):
    with pytest.raises(ValueError, match=r"shape \(7,\)"):
        viewer.set_q(torch.zeros(6, dtype=F64))
    with pytest.raises(ValueError, match="joint limits"):
        viewer.set_q(torch.full((7,), 3.0, dtype=F64))
    with pytest.raises(TypeError, match="torch.Tensor"):
        viewer.set_q([0.0] * 7)
    with pytest.raises(ValueError, match="NaN"):
        viewer.set_q(torch.full((7,), float("nan"), dtype=F64))


# ---------------------------------------------------------------------- IK target
def test_gradient_target_reaches_an_fk_pose(chain, gradient):
    gradient.set_q(torch.zeros(7, dtype=F64))
    target = chain.fk(Q_FREE)
    result = gradient.solve_target(target)
    reached = chain.fk(gradient.q)
    assert result.outcome == "reached", gradient.status
    assert float((reached[:3, 3] - target[:3, 3]).norm()) < 1e-4
    assert float((reached[:3, :3] - target[:3, :3]).abs().max()) < 1e-3
    assert gradient.status.startswith("reached")
    np.testing.assert_allclose(gradient.readout().xyz, target[:3, 3].numpy(), atol=1e-4)


def test_dragging_the_target_solves_its_pose(chain, gradient):
    gradient.set_q(torch.zeros(7, dtype=F64))
    target = chain.fk(Q_FREE).numpy()
    w = math.sqrt(1 + np.trace(target[:3, :3])) / 2  # quaternion of the target, written out (w > 0 here)
    m = target[:3, :3]
    wxyz = [w, (m[2, 1] - m[1, 2]) / (4 * w), (m[0, 2] - m[2, 0]) / (4 * w), (m[1, 0] - m[0, 1]) / (4 * w)]
    gradient.drag_target(wxyz, target[:3, 3])
    reached = chain.fk(gradient.q).numpy()
    assert np.linalg.norm(reached[:3, 3] - target[:3, 3]) < 1e-4
    np.testing.assert_allclose(reached[:3, :3], target[:3, :3], atol=1e-3)
    with pytest.raises(ValueError, match="wxyz"):
        gradient.drag_target([1.0, 0.0, 0.0], target[:3, 3])


@pytest.mark.parametrize("method", ["gradient", "analytic"])
def test_unreachable_target_keeps_the_last_configuration(chain, viewer, method):
    viewer.set_ik(method)
    start = torch.full((7,), 0.3, dtype=F64)
    viewer.set_q(start)
    target = chain.fk(start).clone()
    target[0, 3] += 5.0
    result = viewer.solve_target(target)
    assert result.outcome == "unreachable" and viewer.status.startswith("unreachable")
    assert torch.equal(viewer.q, start)
    assert tuple(viewer.scene.target_marker.color) == (220, 30, 30)  # red
    assert all(math.isfinite(v) for v in viewer.readout().xyz + viewer.readout().rpy_deg)
    viewer.set_q(start)  # the target jumps back to the end effector: nothing to report
    assert viewer.outcome is None and tuple(viewer.scene.target_marker.color) == (150, 150, 150)


def test_analytic_nearest_solution_is_the_current_one(chain, viewer):
    """From q, the FK pose of q itself: among the closed form's candidates (the current arm
    angle is one of them) the nearest is q."""
    viewer.set_ik("analytic")
    viewer.set_q(Q_FREE)
    result = viewer.solve_target(chain.fk(Q_FREE))
    assert result.outcome == "reached"
    torch.testing.assert_close(viewer.q, Q_FREE, atol=1e-9, rtol=0)


def test_analytic_target_of_a_6r_arm():
    """The PUMA 560's closed form (Pieper) through the viewer: from q, the FK pose of q gives q back."""
    puma = robots.puma560()
    q = torch.tensor([0.3, -0.5, 0.4, 0.2, 0.6, -0.3], dtype=F64)
    assert float(collision.clearance(puma, q)) > 0.01  # a configuration clear of itself and the floor
    v = Viewer(puma, port=_free_port())
    try:
        assert v.ik_methods == ("gradient", "analytic")
        v.set_ik("analytic")
        v.set_q(q)
        assert v.solve_target(puma.fk(q)).outcome == "reached", v.status
        torch.testing.assert_close(v.q, q, atol=1e-9, rtol=0)
        with pytest.raises(ValueError, match="arm angle"):
            v.set_ik("analytic", arm_angle=0.3)
    finally:
        v.stop()


@pytest.mark.parametrize(("branch", "psi_deg"), [(0, 40.0), (2, -70.0), (5, 120.0)])
def test_analytic_branch_and_arm_angle_are_the_ones_chosen(chain, viewer, branch, psi_deg):
    viewer.set_q(torch.zeros(7, dtype=F64))
    target = torch.eye(4, dtype=F64)
    target[:3, :3] = torch.tensor(_rpy_matrix(180.0, 0.0, 0.0))  # flange pointing down
    target[:3, 3] = torch.tensor([0.5, 0.1, 0.45])
    viewer.set_ik("analytic", branch=branch, arm_angle=math.radians(psi_deg))
    result = viewer.solve_target(target)
    if result.outcome == "outside the joint limits":  # this branch cannot take this arm angle
        assert torch.equal(viewer.q, torch.zeros(7, dtype=F64))
        return
    assert result.outcome == "reached", viewer.status
    q = viewer.q
    np.testing.assert_allclose(chain.fk(q).numpy(), target.numpy(), atol=1e-9)
    assert _arm_angle(chain, q) == pytest.approx(math.radians(psi_deg), abs=1e-7)
    # branch k = 4 shoulder + 2 elbow + wrist, bit set where sin(q2), sin(q4), sin(q6) < 0
    signs = [int(math.sin(v) < 0) for v in q[[1, 3, 5]].tolist()]
    assert 4 * signs[0] + 2 * signs[1] + signs[2] == branch
    assert viewer.ik_panel.branch.value.startswith(str(branch))  # the panel shows the choice
    assert viewer.ik_panel.psi_slider.value == pytest.approx(psi_deg)


def test_moving_the_arm_angle_slider_moves_the_elbow_not_the_hand(chain, viewer):
    viewer.set_ik("analytic")
    viewer.set_q(Q_FREE)
    hand = chain.fk(Q_FREE)
    viewer.ik_panel.hold_psi.value = True  # what the browser's widgets do
    psi = _arm_angle(chain, Q_FREE) + math.radians(20.0)
    viewer.ik_panel.psi_slider.value = math.degrees(psi)
    q = viewer.q
    assert viewer.outcome == "reached", viewer.status
    np.testing.assert_allclose(chain.fk(q).numpy(), hand.numpy(), atol=1e-9)
    assert _arm_angle(chain, q) == pytest.approx(psi, abs=1e-7)
    viewer.set_ik("gradient")


@pytest.mark.parametrize("value", ["no", None, 1, 0.0])
def test_boolean_options_take_only_booleans(chain, viewer, value):
    for name in ("show_capsules", "show_frames", "block"):
        with pytest.raises(TypeError, match=f"{name} must be True or False"):
            show(chain, port=_free_port(), **{name: value})
    with pytest.raises(TypeError, match="move_target must be True or False"):
        viewer.set_q(viewer.q, move_target=value)


def test_set_ik_rejects_bad_choices(viewer):
    with pytest.raises(ValueError, match="method"):
        viewer.set_ik("newton")
    with pytest.raises(ValueError, match="branch"):
        viewer.set_ik("analytic", branch=8)
    with pytest.raises(ValueError, match="arm_angle"):
        viewer.set_ik("analytic", arm_angle=float("nan"))
    planar = Viewer(robots.planar3r(), port=_free_port())
    try:
        assert planar.ik_methods == ("gradient",)
        with pytest.raises(ValueError, match="method"):
            planar.set_ik("analytic")
    finally:
        planar.stop()


# ---------------------------------------------------------------------- any arm, from its URDF
def _pybullet_link_frames(file: str, values: dict[str, float]) -> dict[str, np.ndarray]:
    """pybullet's world frame ``(4, 4)`` of every link of the URDF ``file`` (loaded at the origin), with
    the joints named in ``values`` set and the others at 0."""
    import pybullet as p

    cid = p.connect(p.DIRECT)
    try:
        robot = p.loadURDF(file, useFixedBase=True, physicsClientId=cid)
        frames = {p.getBodyInfo(robot, physicsClientId=cid)[0].decode(): np.eye(4)}
        count = p.getNumJoints(robot, physicsClientId=cid)
        infos = [p.getJointInfo(robot, i, physicsClientId=cid) for i in range(count)]
        for i, info in enumerate(infos):
            p.resetJointState(robot, i, values.get(info[1].decode(), 0.0), physicsClientId=cid)
        for i, info in enumerate(infos):
            state = p.getLinkState(robot, i, computeForwardKinematics=True, physicsClientId=cid)
            frame = np.eye(4)
            frame[:3, :3] = np.reshape(p.getMatrixFromQuaternion(state[5]), (3, 3))
            frame[:3, 3] = state[4]
            frames[info[12].decode()] = frame
        return frames
    finally:
        p.disconnect(cid)


def _visual_origins(file: str) -> dict[str, np.ndarray]:
    """Each link's ``<visual>`` origin ``(4, 4)`` in its link frame, as the XML writes it (these files
    have at most one visual per link)."""
    origins = {}
    for link in ElementTree.parse(file).getroot().iter("link"):
        origin, matrix = link.find("visual/origin"), np.eye(4)
        if origin is not None:
            matrix[:3, :3] = _rpy_matrix(*np.degrees([float(v) for v in origin.get("rpy", "0 0 0").split()]))
            matrix[:3, 3] = [float(v) for v in origin.get("xyz", "0 0 0").split()]
        origins[link.get("name")] = matrix
    return origins


def _assert_visuals_at_pybullet_frames(v: Viewer, file: str, q: torch.Tensor) -> None:
    """Every visual node of ``v`` at ``q`` sits at pybullet's frame of its link times the visual's
    origin in the XML (joints off the path, a gripper's fingers, at 0, their lower limit)."""
    pytest.importorskip("pybullet")
    v.set_q(q)
    frames = _pybullet_link_frames(file, dict(zip(v.chain.joint_names, q.tolist())))
    origins = _visual_origins(file)
    for element, node in v.visual_nodes:  # pybullet's frames are good to about 1e-8 (float32 steps inside)
        expected = frames[element.link] @ origins[element.link]
        np.testing.assert_allclose(node.position, expected[:3, 3], atol=1e-6, err_msg=element.link)
        np.testing.assert_allclose(_quat_matrix(node.wxyz), expected[:3, :3], atol=1e-6, err_msg=element.link)


def test_a_urdf_arm_is_drawn_with_its_meshes_at_pybullets_link_frames(kuka, kuka_viewer):
    file, chain = kuka
    assert [e.link for e, _ in kuka_viewer.visual_nodes] == [f"lbr_iiwa_link_{i}" for i in range(8)]
    assert tuple(kuka_viewer.visual_nodes[3][1].color) == (255, 108, 10)  # its material "Orange", 1 0.4235 0.0392
    assert not any(node.visible for node in kuka_viewer.scene.links + kuka_viewer.scene.joints)  # the skeleton: hidden
    for q in chain.random_q(2, generator=torch.Generator().manual_seed(5)):
        _assert_visuals_at_pybullet_frames(kuka_viewer, file, q)


def test_the_pandas_hand_and_fingers_follow_its_last_link():
    """pybullet_data's Panda to panda_hand: the hand hangs off link 7 by fixed joints, the fingers by
    prismatic joints off the path; the meshes keep their own (textured) colours."""
    pybullet_data = pytest.importorskip("pybullet_data")
    pytest.importorskip("pytorch_kinematics")
    pytest.importorskip("trimesh")
    file = f"{pybullet_data.getDataPath()}/franka_panda/panda.urdf"
    chain = robots.from_urdf(file, end_link="panda_hand")
    hand = collision.Capsules.build(chain, ["hand"], [7], np.zeros((1, 2, 3)), [0.05], pairs=(), floor=[True])
    v = show(chain, port=_free_port(), block=False, urdf=file, capsules=hand)  # capsules given: none fitted
    try:
        assert v.capsules is hand and v.ik_methods == ("gradient",)  # axes 6 and 7 do not meet: no closed form
        assert {e.link for e, _ in v.visual_nodes} >= {"panda_hand", "panda_leftfinger", "panda_rightfinger"}
        _assert_visuals_at_pybullet_frames(v, file, torch.tensor([0.3, -0.4, 0.2, -2.0, 0.4, 1.9, 0.6], dtype=F64))
    finally:
        v.stop()


def test_a_urdf_arm_is_solved_in_closed_form_and_checked_against_its_capsules(kuka, kuka_viewer):
    """pybullet's iiwa: its axes make an S-R-S arm, so dragging solves it by the closed form, at the
    arm angle held (measured from its shoulder, elbow and wrist: the origins of link frames 2, 4,
    6) and in the branch asked for (the signs of the DH angles 2, 4, 6 of analytic.structure,
    which here are the file's q2, q4, q6 plus a half turn each)."""
    _, chain = kuka
    v = kuka_viewer
    assert v.ik_methods == ("gradient", "analytic")
    assert v.capsules.names == tuple(f"lbr_iiwa_link_{i}" for i in range(8))
    found = analytic.structure(chain)
    q = torch.tensor([0.4, 0.7, -0.3, -1.1, 0.5, 0.9, 0.2], dtype=F64)  # file's signs + - +: branch 5 (- + -)
    own = _arm_angle(chain, q, points=(2, 4, 6))
    v.set_q(torch.zeros(7, dtype=F64))
    for branch, psi in ((5, own + 0.3), (1, own - 0.3)):  # within the limits at these arm angles
        v.set_ik("analytic", branch=branch, arm_angle=psi)
        result = v.solve_target(chain.fk(q))
        assert result.outcome == "reached", v.status
        np.testing.assert_allclose(chain.fk(v.q).numpy(), chain.fk(q).numpy(), atol=1e-9)
        assert _arm_angle(chain, v.q, points=(2, 4, 6)) == pytest.approx(psi, abs=1e-7)
        theta = found.to_dh(v.q) + found.dh.dh[:, 3]
        signs = [int(math.sin(a) < 0) for a in theta[[1, 3, 5]].tolist()]
        assert 4 * signs[0] + 2 * signs[1] + signs[2] == branch
        assert f"branch {'+-'[signs[0]]}{'+-'[signs[1]]}{'+-'[signs[2]]}" in v.controls.readout.content
        assert result.clearance == pytest.approx(v.clearance()[0]) and result.clearance > 0
    v.set_ik("gradient")
    v.drag_target((0.0, 1.0, 0.0, 0.0), (0.5, 0.1, 0.5))  # flange pointing down
    assert v.outcome == "reached", v.status
    np.testing.assert_allclose(chain.fk(v.q)[:3, 3].numpy(), [0.5, 0.1, 0.5], atol=1e-4)


_ODD_ARM = """<robot name="odd">
  <link name="base"><collision><geometry><box size="0.2 0.2 0.1"/></geometry></collision></link>
  <joint name="turn" type="revolute"><parent link="base"/><child link="l1"/><origin xyz="0 0 0.1"/>
    <axis xyz="0 0 1"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <link name="l1"><collision><origin xyz="0 0 0.2"/><geometry><box size="0.08 0.08 0.4"/></geometry></collision></link>
  <joint name="spin" type="continuous"><parent link="l1"/><child link="l2"/><origin xyz="0 0 0.4" rpy="0.3 0 0"/>
    <axis xyz="0 1 1"/></joint>
  <link name="l2"><collision><origin xyz="0.15 0 0"/><geometry><box size="0.3 0.06 0.06"/></geometry></collision></link>
  <joint name="slide" type="prismatic"><parent link="l2"/><child link="l3"/><origin xyz="0.3 0 0"/>
    <axis xyz="1 0 0"/><limit lower="0" upper="0.2" effort="1" velocity="1"/></joint>
  <link name="l3"><collision><geometry><sphere radius="0.04"/></geometry></collision></link>
</robot>"""


@pytest.fixture(scope="module")
def odd_viewer(tmp_path_factory):
    """A URDF arm with a revolute, a continuous and a prismatic joint, collision boxes and no visuals."""
    pytest.importorskip("pytorch_kinematics")
    file = tmp_path_factory.mktemp("odd") / "odd.urdf"
    file.write_text(_ODD_ARM)
    v = show(robots.from_urdf(file), port=_free_port(), block=False, urdf=file)
    yield v
    v.stop()


def test_a_urdf_without_visuals_is_drawn_with_its_capsules(odd_viewer):
    assert odd_viewer.visual_nodes == []
    assert set(odd_viewer.capsule_nodes) == {"base", "l1", "l2", "l3"}
    assert all(node.visible for cap in odd_viewer.capsule_nodes.values() for node in cap.nodes)
    assert all(node.visible for node in odd_viewer.scene.links + odd_viewer.scene.joints)  # and its skeleton
    assert odd_viewer.controls.show_capsules.value and odd_viewer.ik_methods == ("gradient",)


def test_sliders_of_continuous_and_prismatic_joints(odd_viewer):
    """A continuous joint's slider spans one turn (its middle, 0, is the first value); a prismatic
    joint's is in metres."""
    turn, spin, slide = odd_viewer.sliders
    assert (spin.min, spin.max) == pytest.approx((-180.0, 180.0)) and (slide.min, slide.max) == (0.0, 0.2)
    assert slide.label == "slide (m)" and spin.label == "spin (deg)"
    odd_viewer.set_q(torch.tensor([0.0, 0.0, 0.1], dtype=F64))
    slide.value = 0.15
    spin.value = -150.0
    torch.testing.assert_close(odd_viewer.q, torch.tensor([0.0, math.radians(-150.0), 0.15], dtype=F64))


@pytest.mark.parametrize("which", ["preset", "kuka", "odd"])
def test_joint_cylinders_lie_on_the_joint_axes(request, which):
    """Each joint's cylinder lies along the joint's axis in the world, read from the geometric
    Jacobian: its z axis is the angular column (the linear one for a prismatic joint), and for a
    revolute joint the linear column is that axis crossed with the lever from the cylinder's
    centre to the end effector."""
    v = request.getfixturevalue({"preset": "viewer", "kuka": "kuka_viewer", "odd": "odd_viewer"}[which])
    chain = v.chain
    q = chain.random_q(1, generator=torch.Generator().manual_seed(7))[0]
    v.set_q(q)
    jacobian, end = chain.jacobian(q).numpy(), chain.fk(q)[:3, 3].numpy()
    for i, (node, kind) in enumerate(zip(v.scene.joints, chain.kinds)):
        z = _quat_matrix(node.wxyz)[:, 2]
        linear, angular = jacobian[:3, i], jacobian[3:, i]
        if kind.value == "prismatic":
            np.testing.assert_allclose(z, linear, atol=1e-9)
        else:
            np.testing.assert_allclose(z, angular, atol=1e-9)
            np.testing.assert_allclose(np.cross(angular, end - node.position), linear, atol=1e-9)


def test_a_chain_and_a_urdf_that_do_not_match_are_refused(kuka):
    file, _ = kuka
    with pytest.raises(ValueError, match="not the path of that urdf"):
        Viewer(robots.from_urdf(file, base_link="lbr_iiwa_link_1"), port=_free_port(), urdf=file)
    with pytest.raises(TypeError, match="Chain"):
        Viewer("iiwa14", port=_free_port())


def test_a_chain_read_from_a_link_below_the_root_is_refused(tmp_path):
    """Its frame 0 is that link, not the root the file's visuals hang from (a 1 m pedestal here)."""
    pytest.importorskip("pytorch_kinematics")
    box = '<visual><geometry><box size="0.2 0.2 0.1"/></geometry></visual>'
    joint = '<limit lower="-3" upper="3" effort="1" velocity="1"/><axis xyz="0 0 1"/>'
    file = tmp_path / "pedestal.urdf"
    file.write_text(
        f'<robot name="ped"><link name="world"/><link name="base_link">{box}</link><link name="l1">{box}</link>'
        '<joint name="mount" type="fixed"><parent link="world"/><child link="base_link"/><origin xyz="0 0 1"/></joint>'
        f'<joint name="j1" type="revolute"><parent link="base_link"/><child link="l1"/>{joint}</joint></robot>')
    with pytest.raises(ValueError, match="not the path of that urdf from 'world'"):
        urdf_parts(robots.from_urdf(file, base_link="base_link"), file, None)
    visuals, _ = urdf_parts(robots.from_urdf(file), file, None)
    assert len(visuals) == 2


# ---------------------------------------------------------------------- obstacles
_WORLD = {
    "floor": 0.0,
    "spheres": [[0.5, -0.35, 0.5, 0.1]],
    "boxes": [[0.3, -0.65, 0.2, 0.1, 0.15, 0.2, 0.0, 0.0, 30.0]],
    "capsules": [[-0.4, 0.4, 0.0, -0.4, 0.4, 0.7, 0.06]],
    "walls": [[-1.0, 0.0, 0.0, -0.9]],
}


@pytest.fixture(scope="module")
def world_viewer(chain):
    v = show(chain, port=_free_port(), block=False, world=load_world(_WORLD), show_capsules=True)
    yield v
    v.stop()


def test_load_world_reads_every_kind(tmp_path):
    file = tmp_path / "world.json"
    file.write_text(json.dumps(_WORLD))
    for spec in (_WORLD, json.dumps(_WORLD), str(file)):
        world = load_world(spec)
        assert world.floor == 0.0
        np.testing.assert_allclose(world.spheres[0].numpy(), [[0.5, -0.35, 0.5]])
        np.testing.assert_allclose(world.boxes[0][0, :3, :3].numpy(), _rpy_matrix(0, 0, 30), atol=1e-12)
        np.testing.assert_allclose(world.boxes[1].numpy(), [[0.1, 0.15, 0.2]])
        np.testing.assert_allclose(world.capsules[0].numpy(), [[[-0.4, 0.4, 0.0], [-0.4, 0.4, 0.7]]])
        np.testing.assert_allclose(world.walls[0].numpy(), [[-1.0, 0.0, 0.0]])
    assert load_world({"floor": None}).floor is None
    np.testing.assert_allclose(load_world({"walls": [[0, 3, 4, 0.5]]}).walls[0].numpy(), [[0, 0.6, 0.8]])


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ({"sphere": []}, "unknown keys"),
        ({"spheres": [[0, 0, 0]]}, "4 numbers"),
        ({"spheres": 5}, "spheres must be a list of rows of numbers, got 5"),
        ({"walls": "x"}, "walls must be a list of rows"),
        ({"boxes": [[0, 0, 0, 1, 1]]}, "6 or 9 numbers"),
        ({"spheres": [[0, 0, 0, -1]]}, "radii must be positive"),
        ({"walls": [[0, 0, 0, 1]]}, "nonzero"),
        ('{"spheres": [[true, 0, 0, true]]}', "spheres must hold numbers"),
        ({"boxes": [[0, 0, "1", 1, 1, 1]]}, "boxes must hold numbers"),
        ({"floor": True}, "floor must be a height in metres"),
        ("{not json", "invalid JSON"),
        ("no/such/file.json", "neither a JSON object nor an existing file"),
        ({"walls": [[float("nan"), 0, 0, 1]]}, "walls must be finite numbers"),  # was "a wall normal must be nonzero"
        ({"spheres": [[0, 0, 0, float("inf")]]}, "spheres must be finite numbers"),
    ],
)
def test_load_world_rejects_bad_specs(spec, message):
    with pytest.raises(ValueError, match=message):
        load_world(spec)


def test_load_world_names_a_binary_file(tmp_path):
    (tmp_path / "world.json").write_bytes(bytes(range(256)))
    with pytest.raises(ValueError, match="is not JSON text"):
        load_world(str(tmp_path / "world.json"))


def test_the_world_is_drawn_where_it_is(world_viewer):
    nodes = world_viewer.world_nodes
    assert set(nodes) == {"floor", "sphere0", "box0", "capsule0", "wall0"}
    (sphere,) = nodes["sphere0"]
    np.testing.assert_allclose(sphere.position, [0.5, -0.35, 0.5])
    (box,) = nodes["box0"]
    np.testing.assert_allclose(box.position, [0.3, -0.65, 0.2])
    np.testing.assert_allclose(_quat_matrix(box.wxyz), _rpy_matrix(0, 0, 30), atol=1e-9)
    body, end0, end1 = nodes["capsule0"]
    np.testing.assert_allclose(end0.position, [-0.4, 0.4, 0.0])
    np.testing.assert_allclose(end1.position, [-0.4, 0.4, 0.7])
    np.testing.assert_allclose(body.position, [-0.4, 0.4, 0.35])
    np.testing.assert_allclose(_quat_matrix(body.wxyz)[:, 2], [0, 0, 1], atol=1e-12)  # the cylinder's axis
    (wall,) = nodes["wall0"]
    np.testing.assert_allclose(_quat_matrix(wall.wxyz)[:, 2], [-1, 0, 0], atol=1e-12)  # facing the free side
    assert wall.position[0] > 0.9 - 1e-9  # the plane x = 0.9, the slab behind it


def test_robot_capsules_follow_the_arm(chain, world_viewer):
    world_viewer.set_q(Q_FREE)
    frames = chain.fk_all(Q_FREE).numpy()
    model = collision.robot_capsules(chain)
    for name, frame, ends in zip(model.names, model.frames, model.points.numpy()):
        cap = world_viewer.capsule_nodes[name]
        for node, point in zip(cap.ends, ends):
            np.testing.assert_allclose(node.position, frames[frame, :3, :3] @ point + frames[frame, :3, 3], atol=1e-12)


def test_a_colliding_target_and_configuration_are_shown(chain, world_viewer):
    # the flange inside the sphere: the wrist capsule, which ends there, overlaps it in every solution
    target = torch.eye(4, dtype=F64)
    target[:3, :3] = torch.tensor(_rpy_matrix(0.0, 90.0, 0.0))
    target[:3, 3] = torch.tensor([0.5, -0.35, 0.5])
    world_viewer.set_ik("analytic")
    world_viewer.set_q(torch.zeros(7, dtype=F64))
    result = world_viewer.solve_target(target)
    assert result.outcome == "colliding" and result.clearance < 0
    assert torch.equal(world_viewer.q, torch.zeros(7, dtype=F64))  # the arm stays where it was
    assert tuple(world_viewer.scene.target_marker.color) == (250, 170, 0)
    # the sliders are not refused: driven into the sphere, the arm and the sphere turn red
    sol = analytic.iiwa(chain, target, torch.linspace(-math.pi, math.pi, 37, dtype=F64))
    world_viewer.set_q(sol.q[sol.valid][0])
    assert tuple(world_viewer.world_nodes["sphere0"][0].color) == (220, 30, 30)
    assert all(tuple(n.color) == (220, 30, 30) for n in world_viewer.capsule_nodes["wrist"].nodes)
    assert tuple(world_viewer.capsule_nodes["base"].body.color) != (220, 30, 30)
    assert world_viewer.controls.clearance.content.startswith("**COLLIDING**")
    world_viewer.set_q(Q_FREE)
    assert tuple(world_viewer.world_nodes["sphere0"][0].color) != (220, 30, 30)
    assert world_viewer.controls.clearance.content.startswith("clearance +")
    world_viewer.set_ik("gradient")


def test_analytic_ik_reaches_around_an_obstacle_the_gradient_ik_stays_in(chain):
    """A sphere on the elbow of q: from q, the gradient IK of q's own pose stays at q (colliding);
    the closed form of the redundant iiwa turns the elbow away (another arm angle, same hand pose)."""
    elbow = chain.fk_all(Q_FREE)[3, :3, 3]
    world = collision.World(spheres=(elbow[None].clone(), torch.tensor([0.05], dtype=F64)))
    v = Viewer(chain, Q_FREE, port=_free_port(), world=world)
    try:
        target = chain.fk(Q_FREE)
        assert v.solve_target(target).outcome == "colliding"
        assert torch.equal(v.q, Q_FREE)
        v.set_ik("analytic")
        result = v.solve_target(target)
        assert result.outcome == "reached", v.status
        np.testing.assert_allclose(chain.fk(v.q).numpy(), target.numpy(), atol=1e-9)
        assert float(collision.clearance(chain, v.q, world)) >= 0
        assert abs(_arm_angle(chain, v.q) - _arm_angle(chain, Q_FREE)) > 0.1
        assert tuple(v.scene.target_marker.color) == (40, 180, 60)
    finally:
        v.stop()


def test_a_world_needs_a_capsule_model():
    custom = robots.planar3r()
    custom.name = "custom"
    with pytest.raises(ValueError, match="no capsule model"):
        Viewer(custom, port=_free_port(), world=load_world({"floor": 0.0}))


# ---------------------------------------------------------------------- playback
def test_playback_steps_through_a_jtraj(chain, viewer):
    path = trajectory.jtraj(torch.zeros(7, dtype=F64), Q_FREE, 21).q
    viewer.set_path(path, dt=0.1)
    torch.testing.assert_close(viewer.q, path[0])
    for k in (7, 20, 3):
        viewer.seek(k)
        torch.testing.assert_close(viewer.q, path[k])
        np.testing.assert_allclose(viewer.readout().xyz, chain.fk(path[k])[:3, 3].numpy(), atol=1e-12)
        assert viewer.player.time_slider.value == pytest.approx(0.1 * k)
    viewer.player.time_slider.value = 1.2  # the browser's time slider: step 12
    torch.testing.assert_close(viewer.q, path[12])
    with pytest.raises(ValueError, match="step"):
        viewer.seek(21)


def test_play_advances_in_time_and_stops_at_the_end(viewer):
    path = trajectory.jtraj(torch.zeros(7, dtype=F64), Q_FREE, 6).q
    viewer.set_path(path, dt=0.05)
    viewer.play()
    deadline = time.monotonic() + 10
    while viewer.playing and time.monotonic() < deadline:
        time.sleep(0.02)
    assert not viewer.playing and viewer.step == 5
    torch.testing.assert_close(viewer.q, path[5])
    assert viewer.player.play_button.label == "play"


def test_playback_of_several_paths_with_goals(chain, viewer):
    ends = torch.stack([Q_FREE, -Q_FREE])
    paths = trajectory.jtraj(torch.zeros(2, 7, dtype=F64), ends, 5).q  # (2, 5, 7)
    goals = chain.fk(ends)[:, :3, 3]
    viewer.set_path(paths, dt=0.1, goals=goals)
    viewer.seek(4, 1)
    torch.testing.assert_close(viewer.q, paths[1, 4])
    np.testing.assert_allclose(viewer.scene.goal_marker.position, goals[1].numpy())
    viewer.player.path_slider.value = 0  # the browser's path slider keeps the step
    torch.testing.assert_close(viewer.q, paths[0, 4])


def test_urdf_of_another_chain_says_which_chain_to_pass(kuka):
    file, _ = kuka
    with pytest.raises(ValueError, match=r"urdf= draws the file chain 'iiwa14' was read from .*robots.from_urdf"):
        show(robots.iiwa14(), port=0, block=False, urdf=file)  # a preset: its links are not the file's


def test_set_path_rejects_bad_paths(viewer):
    with pytest.raises(ValueError, match=r"\(T, 7\)"):
        viewer.set_path(torch.zeros(5, 6, dtype=F64))
    with pytest.raises(ValueError, match="joint limits"):
        viewer.set_path(torch.full((5, 7), 3.0, dtype=F64))
    with pytest.raises(ValueError, match="goals"):
        viewer.set_path(torch.zeros(5, 7, dtype=F64), goals=torch.zeros(2, 3, dtype=F64))
    with pytest.raises(ValueError, match="dt"):
        viewer.set_path(torch.zeros(5, 7, dtype=F64), dt=0.0)
    with pytest.raises(ValueError, match="goals contains NaN"):
        viewer.set_path(torch.zeros(5, 7, dtype=F64), goals=torch.full((1, 3), float("nan"), dtype=F64))
    with pytest.raises(ValueError, match="goals are the targets of path=: pass path too"):  # before any server
        show(robots.iiwa14(), port=0, block=False, goals=torch.zeros(1, 3, dtype=F64))


# ---------------------------------------------------------------------- the command
@pytest.fixture
def shown(monkeypatch):
    """Calls of viewer.show made by the CLI, recorded instead of serving."""
    calls = []
    monkeypatch.setattr(viewer_module, "show", lambda *a, **k: calls.append((a, k)))
    return calls


def test_cli_view_passes_world_and_options(shown, tmp_path):
    assert cli.main(["view", "--world", json.dumps(_WORLD), "--capsules", "--frames", "--port", "9999"]) == 0
    ((args, kwargs),) = shown
    assert args[0].name == "iiwa14" and kwargs["port"] == 9999
    assert kwargs["show_capsules"] and kwargs["show_frames"]
    np.testing.assert_allclose(kwargs["world"].spheres[1].numpy(), [0.1])


def test_cli_view_plays_a_traj_csv(shown, tmp_path, capsys):
    csv_file = tmp_path / "t.csv"
    start, end = ["0", "30", "0", "-60", "0", "60", "0"], ["20", "10", "0", "-80", "0", "40", "0"]
    cli.main(["traj", "--from-q", *start, "--to-q", *end, "--steps", "8", "--duration", "1.4", "--csv", str(csv_file),
              "--json"])  # fmt: skip
    out = json.loads(capsys.readouterr().out)
    cli.main(["view", "--path", str(csv_file)])
    ((_, kwargs),) = shown
    np.testing.assert_allclose(kwargs["path"].numpy(), out["q_rad"], atol=1e-8)
    assert kwargs["dt"] == pytest.approx(0.2)


@pytest.mark.parametrize(("world", "message"), [('{"spheres": [[1, 2]]}', "4 numbers"), ("array", "world must be")])
def test_cli_view_rejects_a_bad_world(capsys, tmp_path, world, message):
    if world == "array":  # a file holding a JSON array where the object belongs (a traceback, exit 1, before)
        world = str(tmp_path / "world.json")
        Path(world).write_text("[1, 2]")
    with pytest.raises(SystemExit) as exc:
        cli.main(["view", "--world", world])
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--port", "99999"], "port must be an integer in 0..65535"),
        (["--port", "-1"], "port must be an integer in 0..65535"),
        (["--host", "999.1.1.1"], "host must be an IP address"),
        (["--host", "not a host"], "host must be an IP address"),
        (["--host", "8.8.8.8"], "cannot serve on host '8.8.8.8'"),
        (["--q", "0", "0", "200"], "--q: joint3 = 200 deg outside +-180"),  # in the user's units
        (["--goals", "3"], "--goals and --seed choose --policy's rollouts: give --policy too"),  # was ignored
    ],
)
def test_cli_view_refuses_what_it_cannot_serve(capsys, argv, message):
    with pytest.raises(SystemExit) as exc:
        cli.main(["view", "--robot", "planar3r", *argv])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert message in err.splitlines()[-1]


def test_cli_view_of_a_urdf_arm(shown, kuka):
    file, chain = kuka
    assert cli.main(["view", "--urdf", file, "--q", "10", "20", "0", "-40", "0", "30", "0"]) == 0
    ((args, kwargs),) = shown
    assert args[0].joint_names == chain.joint_names and kwargs["urdf"] == file
    torch.testing.assert_close(args[1], torch.tensor([10.0, 20, 0, -40, 0, 30, 0], dtype=F64).deg2rad())


def test_cli_view_of_files_it_cannot_read(tmp_path, capsys, kuka):
    """Exit status 2 and the problem on the last line, no traceback: a missing, binary or unreadable
    URDF, a mesh that is missing or not a mesh (found before any server starts)."""
    file, _ = kuka
    (tmp_path / "binary.urdf").write_bytes(bytes(range(256)))
    model = Path(file).read_text()
    (tmp_path / "meshes").mkdir()
    for mesh in Path(file).parent.joinpath("meshes").glob("link_*"):
        (tmp_path / "meshes" / mesh.name).symlink_to(mesh)
    (tmp_path / "meshes" / "bad.obj").write_bytes(b"\x00\xff" * 100)
    (tmp_path / "bad.urdf").write_text(model.replace("meshes/link_3.obj", "meshes/bad.obj"))
    (tmp_path / "missing.urdf").write_text(model.replace("meshes/link_3.obj", "meshes/gone.obj"))
    cases = [
        ("/no/such.urdf", "no URDF file at '/no/such.urdf'"),
        (str(tmp_path / "binary.urdf"), "not well-formed XML"),
        (str(tmp_path / "missing.urdf"), "mesh 'meshes/gone.obj' not found"),
        (str(tmp_path / "bad.urdf"), "bad.obj'"),
    ]
    if os.path.exists("/proc/self/mem"):  # a file that is there but cannot be read (even by root)
        cases.append(("/proc/self/mem", "cannot read it: Input/output error"))
    for source, message in cases:
        with pytest.raises(SystemExit) as exc:
            cli.main(["view", "--urdf", source, "--port", "0"])
        err = capsys.readouterr().err
        assert exc.value.code == 2 and "Traceback" not in err, err
        assert err.splitlines()[-1].startswith("iiwa-torch view: error: ") and message in err.splitlines()[-1], err


def test_cli_view_rolls_out_the_shipped_policy(chain, shown):
    pytest.importorskip("stable_baselines3")
    policy = Path(__file__).resolve().parents[1] / "train" / "policies" / "ppo_iiwa_reach"
    assert cli.main(["view", "--policy", str(policy), "--goals", "3"]) == 0
    ((_, kwargs),) = shown
    path, goals = kwargs["path"], kwargs["goals"]
    assert path.shape[0] == 3 and path.shape[2] == 7 and goals.shape == (3, 3)
    assert kwargs["dt"] == pytest.approx(0.05)
    torch.testing.assert_close(path[:, 0], torch.tensor(robots.IIWA_HOME, dtype=F64).expand(3, 7), atol=1e-6, rtol=0)
    # the shipped policy reaches its goals (within 1 cm, its success threshold) and the path ends there
    tip = chain.fk(path[:, -1])[:, :3, 3]
    assert float((tip - goals).norm(dim=-1).max()) < 0.01


# ---------------------------------------------------------------------- a real browser
_CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
_BROWSER_SECONDS = 90  # hard limit of the whole browser test; it takes 5-15 s


class _Chromium:
    """Headless Chromium driven through the DevTools protocol (over websockets, which viser
    needs anyway). It runs in its own session and is killed with its whole process group:
    Chromium's renderer and GPU processes outlive a kill of the main one, and a pipe they
    still hold open keeps a reader waiting forever."""

    def __init__(self, deadline: float):
        from websockets.sync.client import connect

        self.deadline = deadline
        self.profile = tempfile.mkdtemp(prefix="chromium-")
        self.log = open(os.path.join(self.profile, "stderr.txt"), "w+")
        self.proc = subprocess.Popen(
            [
                _CHROMIUM, "--headless=new", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
                "--no-first-run", "--disable-background-networking", "--disable-component-update",
                "--disable-sync", "--disable-extensions", "--mute-audio", f"--user-data-dir={self.profile}",
                "--remote-debugging-port=0", "--window-size=800,600", "about:blank",
            ],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=self.log, start_new_session=True,
        )  # fmt: skip
        url = self._wait(lambda: re.search(r"DevTools listening on (ws://\S+)", Path(self.log.name).read_text()))
        port = int(re.search(r":(\d+)/", url.group(1)).group(1))
        pages = json.load(urllib.request.urlopen(f"http://127.0.0.1:{port}/json", timeout=5))
        page = next(p for p in pages if p["type"] == "page")
        self.ws = connect(page["webSocketDebuggerUrl"], max_size=None, open_timeout=5)
        self.calls = 0
        self.call("Emulation.setDeviceMetricsOverride", width=800, height=600, deviceScaleFactor=1, mobile=False)

    def _wait(self, found, what: str = "Chromium to start"):
        while True:
            value = found()
            if value:
                return value
            if self.proc.poll() is not None:
                log = Path(self.log.name).read_text()[-2000:]
                raise RuntimeError(f"Chromium exited ({self.proc.returncode}): {log}")
            if time.monotonic() > self.deadline:
                raise TimeoutError(f"gave up waiting for {what}")
            time.sleep(0.1)

    def call(self, method: str, **params):
        self.calls += 1
        self.ws.send(json.dumps({"id": self.calls, "method": method, "params": params}))
        while True:
            message = json.loads(self.ws.recv(timeout=max(self.deadline - time.monotonic(), 0.1)))
            if message.get("id") == self.calls:
                if "error" in message:
                    raise RuntimeError(f"{method}: {message['error']}")
                return message["result"]

    def text(self) -> str:
        result = self.call("Runtime.evaluate", expression="document.body ? document.body.innerText : ''")
        return result["result"].get("value", "")

    def wait_for_text(self, text: str) -> None:
        self._wait(lambda: text in self.text(), f"the page to show {text!r}")

    def screenshot(self) -> np.ndarray:
        from PIL import Image

        data = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))

    def settled_screenshot(self) -> np.ndarray:
        """A screenshot once two in a row are the same (the scene fades in and loads its lights)."""
        last = self.screenshot()
        while True:
            time.sleep(0.3)
            shot = self.screenshot()
            if np.array_equal(shot, last) and _orange(shot).sum() > 0:
                return shot
            if time.monotonic() > self.deadline:
                raise TimeoutError("the page kept changing")
            last = shot

    def close(self) -> None:
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.proc.wait(timeout=10)
        self.log.close()
        shutil.rmtree(self.profile, ignore_errors=True)


def _orange(rgb: np.ndarray) -> np.ndarray:
    """``(H, W)`` bool: pixels of the joint housings' orange hue (red > green > blue, however light or
    shaded), outside the page's fixed overlays (the control panel on the right, the software-rendering
    notice top left)."""
    rgb = rgb.astype(float)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    spread = r - b
    mask = (spread > 25) & (g - b > 0.2 * spread) & (g - b < 0.8 * spread)
    h, w = mask.shape
    mask[:, w - 360 :] = False
    mask[:170, :330] = False
    return mask


def _readout_xyz(chain, q: torch.Tensor) -> str:
    x, y, z = chain.fk(q)[:3, 3].tolist()
    return f"xyz (m): {x:+.4f} {y:+.4f} {z:+.4f}"


@pytest.mark.skipif(_CHROMIUM is None, reason="no chromium on this machine (apt-get install chromium): "
                                               "the viewer's rendering in a browser is not checked")  # fmt: skip
@pytest.mark.parametrize("robot", ["preset", "urdf"])
def test_headless_chromium_draws_the_arm_and_follows_the_sliders(request, robot):
    """The iiwa 14 preset (its skeleton's orange joints) and pybullet's iiwa from its URDF (its
    meshes, two of them orange by their material, the skeleton hidden)."""
    if robot == "urdf":
        file, chain = request.getfixturevalue("kuka")
        kwargs = dict(urdf=file, capsules=request.getfixturevalue("kuka_viewer").capsules)  # fitted once
    else:
        chain, kwargs = request.getfixturevalue("chain"), {}
    deadline = time.monotonic() + _BROWSER_SECONDS
    q0 = torch.zeros(7, dtype=F64)
    q1 = torch.tensor([70.0, 50.0, 0.0, -80.0, 0.0, 35.0, 0.0], dtype=F64).deg2rad()
    v = Viewer(chain, q0, port=_free_port(), **kwargs)
    assert any(node.visible for node in v.scene.joints) == (robot == "preset")
    # Software WebGL takes 2-20 s (machine load) to prefilter viser's environment map for the first
    # frame; plain lights without shadows draw the same arm in well under a second.
    v.server.scene.configure_environment_map(hdri=None)
    v.server.scene.configure_default_lights(cast_shadow=False)
    browser = None
    try:
        browser = _Chromium(deadline)
        browser.call("Page.navigate", url=f"http://127.0.0.1:{v.server.get_port()}")
        browser.wait_for_text(_readout_xyz(chain, q0))
        first = browser.settled_screenshot()
        for slider, angle in zip(v.sliders, np.degrees(q1.numpy())):  # as the browser's sliders do
            slider.value = float(angle)
        torch.testing.assert_close(v.q, q1)
        browser.wait_for_text(_readout_xyz(chain, q1))  # the open page follows, no reload
        second = browser.settled_screenshot()
    finally:
        if browser is not None:
            browser.close()
        v.stop()
    colours = len(np.unique(first.reshape(-1, 3), axis=0))
    assert colours > 200, f"the page looks blank ({colours} distinct colours): WebGL did not render"
    masks = [_orange(s) for s in (first, second)]
    for name, m in zip(("first", "second"), masks):
        assert m.sum() > 300, f"{name} screenshot: only {m.sum()} orange pixels, the arm is not drawn"
    overlap = (masks[0] & masks[1]).sum() / (masks[0] | masks[1]).sum()
    assert overlap < 0.5, f"the two configurations look alike (orange overlap {overlap:.2f})"


def _serve_then_ctrl_c(argv: list[str]) -> tuple[int, str, int]:
    """Run ``python argv`` until it prints its viewer's URL, check the page is served there,
    then send Ctrl-C: ``(exit status, output, port of the URL)``."""
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    proc = subprocess.Popen(
        [sys.executable, *argv],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),  # a background shell may ignore it
    )  # fmt: skip
    try:
        # Ctrl-C is handled once show() says so (earlier, Python's usual traceback is the answer);
        # a reader thread keeps a hung start from hanging the test.
        lines: list[str] = []

        def read() -> None:
            for line in proc.stdout:
                lines.append(line)

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        deadline = time.monotonic() + 60  # a loaded 2-core machine needs far more than the usual 2 s
        while not any("Ctrl-C to stop" in line for line in lines):
            assert proc.poll() is None and time.monotonic() < deadline, f"the viewer did not start: {lines}"
            time.sleep(0.1)
        (url_port,) = {int(m) for line in lines for m in re.findall(r"http://127\.0\.0\.1:(\d+) \(Ctrl-C", line)}
        assert urllib.request.urlopen(f"http://127.0.0.1:{url_port}/", timeout=5).status == 200
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=20)
        reader.join(timeout=5)
    finally:
        proc.kill()
    return proc.returncode, "".join(lines), url_port


def test_ctrl_c_stops_the_server_cleanly():
    port = _free_port()
    code = f"from iiwa_torch import robots, viewer\nviewer.show(robots.planar3r(), port={port})\nprint('stopped')"
    status, out, url_port = _serve_then_ctrl_c(["-c", code])
    assert status == 0, out
    assert url_port == port and out.rstrip().endswith("stopped"), out


def test_cli_view_prints_the_port_it_serves_on_when_the_one_asked_is_busy():
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        status, out, url_port = _serve_then_ctrl_c(["-m", "iiwa_torch.cli", "view", "--robot", "planar3r",
                                                     "--port", str(port)])  # fmt: skip
    assert status == 0, out
    assert url_port != port, out


def test_importing_the_module_does_not_import_viser_or_train():
    code = "import sys, iiwa_torch.viewer; print(sorted({'viser', 'train', 'stable_baselines3'} & set(sys.modules)))"
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr
