"""URDF reading: read_urdf against the XML text itself (xml.etree, scipy's Euler angles) and its
FK (an independent numpy loop) against pinocchio, on pybullet_data's robots and our own export."""

import math
import pathlib
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import torch
from urdf_samples import pinocchio_q

from iiwa_torch import robots, urdf
from iiwa_torch.urdf import read_urdf

pytest.importorskip("pytorch_kinematics")
pybullet_data = pytest.importorskip("pybullet_data")
DATA = pathlib.Path(pybullet_data.getDataPath())

# (file, end_link, movable joints on the path)
ROBOTS = [
    ("franka_panda/panda.urdf", "panda_hand", 7),
    ("kuka_iiwa/model.urdf", None, 7),
    ("xarm/xarm6_robot.urdf", None, 6),
]


def _rotation(axis, angle):
    """Rodrigues: rotation by angle about the unit axis."""
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def _fk(path, q):
    """base_link -> end_link (4, 4) of one configuration, joint by joint in float64."""
    pose = np.eye(4)
    for joint, value in zip(path.joints, q):
        motion = np.eye(4)
        if joint.kind == "prismatic":
            motion[:3, 3] = value * np.array(joint.axis)
        else:
            motion[:3, :3] = _rotation(joint.axis, value)
        pose = pose @ np.array(joint.origin) @ motion
    return pose @ np.array(path.tool)


def _random_q(path, n, seed):
    rng = np.random.default_rng(seed)
    lower = np.array([j.lower if math.isfinite(j.lower) else -math.pi for j in path.joints])
    upper = np.array([j.upper if math.isfinite(j.upper) else math.pi for j in path.joints])
    return rng.uniform(lower, upper, (n, len(path.joints)))


def _pinocchio_fk(model, path, q):
    """pinocchio's placement of end_link for each row of q (path order); other joints at 0."""
    pin = pytest.importorskip("pinocchio")
    data = model.createData()
    frame = model.getFrameId(path.end_link)
    slots = [model.joints[model.getJointId(j.name)] for j in path.joints]
    out = []
    for row in q:
        full = pinocchio_q(pin, model, slots, row)
        pin.forwardKinematics(model, data, full)
        pin.updateFramePlacements(model, data)
        out.append(data.oMf[frame].homogeneous.copy())
    return np.stack(out)


def _xml_pose(element):
    """(4, 4) of an <origin> element (identity if None): R = Rz(yaw) Ry(pitch) Rx(roll), extrinsic."""
    from scipy.spatial.transform import Rotation

    pose = np.eye(4)
    if element is not None:
        pose[:3, :3] = Rotation.from_euler("xyz", [float(v) for v in element.get("rpy", "0 0 0").split()]).as_matrix()
        pose[:3, 3] = [float(v) for v in element.get("xyz", "0 0 0").split()]
    return pose


def _xml_chain(file, end_link):
    """The <joint> elements from the root to end_link, read by xml.etree."""
    by_child = {j.find("child").get("link"): j for j in ET.parse(file).getroot().findall("joint")}
    chain, link = [], end_link
    while link in by_child:
        chain.append(by_child[link])
        link = by_child[link].find("parent").get("link")
    return chain[::-1]


@pytest.mark.parametrize(("file", "end_link", "n"), ROBOTS, ids=[r[0].split("/")[0] for r in ROBOTS])
def test_joints_match_the_xml(file, end_link, n):
    path = read_urdf(DATA / file, end_link=end_link)
    assert len(path.joints) == n and path.links == tuple(j.child for j in path.joints)
    chain = _xml_chain(DATA / file, path.end_link)
    assert path.robot == ET.parse(DATA / file).getroot().get("name")
    assert path.base_link == chain[0].find("parent").get("link")  # the root: the default base
    carry = np.eye(4)
    got = iter(path.joints)
    for element in chain:
        carry = carry @ _xml_pose(element.find("origin"))
        if element.get("type") == "fixed":
            continue
        joint = next(got)
        limit = element.find("limit")
        axis = np.array([float(v) for v in element.find("axis").get("xyz").split()])
        assert (joint.name, joint.kind, joint.child) == (
            element.get("name"),
            element.get("type"),
            element.find("child").get("link"),
        )
        assert (joint.lower, joint.upper, joint.velocity) == tuple(
            float(limit.get(k)) for k in ("lower", "upper", "velocity")
        )
        np.testing.assert_allclose(joint.axis, axis / np.linalg.norm(axis), rtol=0, atol=1e-15)
        np.testing.assert_allclose(joint.origin, carry, rtol=0, atol=1e-15)
        assert all(type(v) is float for row in joint.origin for v in row)
        carry = np.eye(4)
    np.testing.assert_allclose(path.tool, carry, rtol=0, atol=1e-15)


@pytest.mark.parametrize(("file", "end_link", "n"), ROBOTS, ids=[r[0].split("/")[0] for r in ROBOTS])
def test_fk_matches_pinocchio(file, end_link, n):
    pin = pytest.importorskip("pinocchio")
    path = read_urdf(str(DATA / file), end_link=end_link)
    model = pin.buildModelFromUrdf(str(DATA / file))
    q = _random_q(path, 1000, seed=n)
    got = np.stack([_fk(path, row) for row in q])
    np.testing.assert_allclose(got, _pinocchio_fk(model, path, q), rtol=0, atol=1e-12)


def test_xarm_with_its_transmission_loads():
    text = (DATA / "xarm/xarm6_robot.urdf").read_text()
    assert "<transmission" in text and "encoding=" in text  # what pk's parser fails on, given the raw text
    path = read_urdf(text)  # the XML text itself (with its encoding declaration), not the path
    assert [j.name for j in path.joints] == [f"joint{i}" for i in range(1, 7)]
    assert (path.base_link, path.end_link) == ("world", "link6")


def test_panda_mimic_finger():
    file = DATA / "franka_panda/panda.urdf"
    assert [j.name for j in read_urdf(file, end_link="panda_leftfinger").joints][-1] == "panda_finger_joint1"
    with pytest.raises(ValueError, match="'panda_finger_joint2' mimics 'panda_finger_joint1': mimic joints are not"):
        read_urdf(file, end_link="panda_rightfinger")
    with pytest.raises(ValueError, match=r"3 leaf links .*panda_leftfinger.*pass end_link="):
        read_urdf(file)


def test_own_export_round_trips():
    arm = robots.iiwa14()
    path = read_urdf(urdf.to_urdf(arm))
    assert [j.kind for j in path.joints] == ["revolute"] * 7 and path.end_link == "tool0"
    assert [j.name for j in path.joints] == list(arm.joint_names)
    np.testing.assert_array_equal([[j.lower, j.upper] for j in path.joints], arm.limits.T.numpy())
    np.testing.assert_array_equal([j.velocity for j in path.joints], arm.velocity_limits.numpy())
    q = arm.random_q(1000, generator=torch.Generator().manual_seed(0))
    got = np.stack([_fk(path, row) for row in q.numpy()])
    np.testing.assert_allclose(got, arm.fk(q).numpy(), rtol=0, atol=1e-12)


def _robot(body, links="ab"):
    declared = "".join(f'<link name="{name}"/>' for name in links)
    return f'<robot name="t">{declared}{body}</robot>'


def _joint(name, parent, child, kind="revolute", extra='<limit lower="-1" upper="1" effort="1" velocity="1"/>'):
    return f'<joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>{extra}</joint>'


def test_prismatic_continuous_fixed_and_branches():
    """Every joint kind, a non-unit and a default axis, rpy, branches off the path (a floating
    and a mimic joint there are ignored): FK against pinocchio."""
    pin = pytest.importorskip("pinocchio")
    text = _robot(
        _joint("j1", "a", "b", "continuous", '<origin xyz="0.1 -0.2 0.3" rpy="0.4 -0.5 0.6"/><axis xyz="0 3 4"/>')
        + _joint("f", "b", "c", "fixed", '<origin xyz="0.05 0 0.2" rpy="1.1 0.2 -0.3"/>')
        + _joint(
            "j2",
            "c",
            "d",
            "prismatic",
            '<origin rpy="0 1.5 0"/><axis xyz="1 1 1"/><limit lower="-0.2" upper="0.3" effort="1" velocity="0"/>',
        )
        + _joint("j3", "d", "e", extra='<origin xyz="0 0.3 0"/><limit lower="-2" upper="2" effort="1" velocity="2"/>')
        + _joint("t", "e", "tip", "fixed", '<origin xyz="0 0 0.1" rpy="0.3 0.2 0.1"/>')
        + _joint("off", "b", "g", "floating")
        + _joint("m", "c", "h", extra='<mimic joint="j2"/><limit lower="-1" upper="1" effort="1" velocity="1"/>'),
        links=["a", "b", "c", "d", "e", "g", "h", "tip"],
    )
    path = read_urdf("\n  " + text, end_link="tip")
    assert [(j.name, j.kind) for j in path.joints] == [("j1", "continuous"), ("j2", "prismatic"), ("j3", "revolute")]
    assert (path.joints[0].lower, path.joints[0].upper, path.joints[0].velocity) == (-math.inf, math.inf, None)
    assert path.joints[1].velocity is None and path.joints[2].velocity == 2.0  # velocity 0 -> None
    np.testing.assert_allclose(path.joints[0].axis, (0, 0.6, 0.8), atol=1e-16)
    assert path.joints[2].axis == (1.0, 0.0, 0.0)  # URDF's default
    model = pin.buildModelFromXML(text)
    q = _random_q(path, 1000, seed=1)
    got = np.stack([_fk(path, row) for row in q])
    np.testing.assert_allclose(got, _pinocchio_fk(model, path, q), rtol=0, atol=1e-12)
    mid = read_urdf(text, end_link="d", base_link="c")
    assert [j.name for j in mid.joints] == ["j2"] and mid.base_link == "c"


def test_file_path_and_text_agree(tmp_path):
    text = urdf.to_urdf(robots.puma560())
    (tmp_path / "puma.urdf").write_text(text)
    assert read_urdf(tmp_path / "puma.urdf") == read_urdf(str(tmp_path / "puma.urdf")) == read_urdf(text)
    (tmp_path / "bom.urdf").write_text(text, encoding="utf-8-sig")  # read back as text, the mark stays
    assert read_urdf((tmp_path / "bom.urdf").read_text(encoding="utf-8")) == read_urdf(text)


LIMIT = '<limit lower="-1" upper="1" effort="1" velocity="1"/>'
J = _joint("j", "a", "b")  # the one-joint robot a -> b
ERRORS = {  # (URDF, read_urdf's arguments, message)
    "not xml": (_robot("<joint>"), {}, "not well-formed XML"),
    "not a robot": ("<sdf/>", {}, "root element is <robot>"),
    "missing file": ("/nonexistent/robot.urdf", {}, "no URDF file at '/nonexistent/robot.urdf'"),
    "a folder": ("/", {}, "'/' is a folder; pass the URDF file in it"),
    "unknown end": (
        _robot(J + _joint("k", "a", "c"), "abc"),
        {"end_link": "z"},
        r"end_link 'z' is not a link .*links: a, b, c",
    ),
    "unknown base": (_robot(J, "ab"), {"base_link": "z"}, "base_link 'z' is not a link"),
    "floating": (_robot(_joint("j", "a", "b", "floating"), "ab"), {}, "'j' between 'a' and 'b' is floating"),
    "planar": (_robot(_joint("j", "a", "b", "planar"), "ab"), {}, "'j' between 'a' and 'b' is planar"),
    "mimic": (
        _robot(J + _joint("k", "b", "c", extra=f'<mimic joint="j"/>{LIMIT}'), "abc"),
        {},
        "joint 'k' mimics 'j': mimic joints are not supported",
    ),
    "zero axis": (_robot(_joint("j", "a", "b", extra=f'<axis xyz="0 0 0"/>{LIMIT}'), "ab"), {}, "nonzero finite"),
    "not below": (
        _robot(J + _joint("k", "a", "c"), "abc"),
        {"base_link": "b", "end_link": "c"},
        "end_link 'c' is not below base_link 'b'",
    ),
    "above": (_robot(J, "ab"), {"base_link": "b", "end_link": "a"}, "end_link 'a' is not below base_link 'b'"),
    "fixed only": (_robot(_joint("j", "a", "b", "fixed", ""), "ab"), {}, "no movable joint between base_link 'a' and"),
    "same link": (_robot(J, "ab"), {"base_link": "b"}, "no movable joint between base_link 'b' and end_link 'b'"),
    "leaves": (_robot(J + _joint("k", "a", "c"), "abc"), {}, r"2 leaf links below 'a' \(b, c\); pass end_link="),
    "no limit": (_robot(_joint("j", "a", "b", extra=""), "ab"), {}, "'j' is revolute and has no <limit>"),
    "inverted limit": (
        _robot(_joint("j", "a", "b", extra='<limit lower="1" upper="-1" effort="1" velocity="1"/>'), "ab"),
        {},
        "lower <= upper",
    ),
    "undeclared link": (_robot(J, "a"), {}, "names link 'b', which the URDF does not declare"),
    "two roots": (_robot(J, "abc"), {"end_link": "b"}, "one root link .* 2: \\['a', 'c'\\]"),
    "two parents": (_robot(J + _joint("k", "c", "b"), "abc"), {}, "'b' is the child of two joints, 'j' and 'k'"),
    "cycle": (_robot(J + _joint("k", "c", "d") + _joint("l", "d", "c"), "abcd"), {}, "cycle"),
    "same link twice": (_robot(J, "abb"), {}, r"link names must be unique, got \['b'\] more than once"),
    "same joint twice": (_robot(J + _joint("j", "b", "c"), "abc"), {}, r"joint names must be unique, got \['j'\]"),
    "bad joint type": (_robot(_joint("j", "a", "b", "hinge"), "ab"), {}, "not a valid URDF: .*Invalid joint type"),
    "bad number": (_robot(_joint("j", "a", "b", extra='<origin xyz="0 x 0"/>'), "ab"), {}, "not a valid URDF"),
    "nan origin": (_robot(_joint("j", "a", "b", extra=f'<origin xyz="0 nan 0"/>{LIMIT}'), "ab"), {}, "origin must be"),
}


@pytest.mark.parametrize("case", ERRORS)
def test_errors(case):
    source, kwargs, message = ERRORS[case]
    with pytest.raises(ValueError, match=message):
        read_urdf(source, **kwargs)


@pytest.mark.parametrize(("kwargs", "message"), [({"source": 3}, "source must be"), ({"end_link": 3}, "end_link must")])
def test_type_errors(kwargs, message):
    with pytest.raises(TypeError, match=message):
        read_urdf(**{"source": _robot(J), **kwargs})


VISUALS = """<robot name="v">
  <material name="Teal"><color rgba="0 0.5 0.5 1"/></material>
  <link name="a"><visual><geometry><box size="0.1 0.2 0.3"/></geometry><material name="Teal"/></visual>
    <collision><geometry><sphere radius="0.5"/></geometry></collision></link>
  <joint name="j" type="revolute"><parent link="a"/><child link="b"/><origin xyz="0 0 1"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <link name="b"><visual><origin xyz="0.1 0 0" rpy="0 0 1.5"/><geometry><cylinder radius="0.05" length="0.4"/>
    </geometry><material name="own"><color rgba="1 0 0 0.5"/></material></visual></link>
  <joint name="f" type="fixed"><parent link="b"/><child link="c"/><origin xyz="0 0.2 0"/></joint>
  <link name="c"><visual><geometry><mesh filename="m.obj" scale="2 2 2"/></geometry></visual></link>
</robot>"""


def test_visuals_as_the_xml_writes_them(tmp_path):
    """read_visuals: each <visual>, its frame, its origin (through a fixed joint too), its size and its
    material colour, inline or named at the robot level; read_collisions of the same file keeps to
    <collision>."""
    (tmp_path / "m.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (tmp_path / "v.urdf").write_text(VISUALS)
    box, cylinder, mesh = urdf.read_visuals(tmp_path / "v.urdf")
    assert (box.link, box.frame, box.shape, box.size, box.rgba) == ("a", 0, "box", (0.1, 0.2, 0.3), (0, 0.5, 0.5, 1))
    assert (cylinder.link, cylinder.frame, cylinder.size, cylinder.rgba) == ("b", 1, (0.05, 0.4), (1, 0, 0, 0.5))
    c, s = math.cos(1.5), math.sin(1.5)
    np.testing.assert_allclose(cylinder.poses[0], [[c, -s, 0, 0.1], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
                               atol=1e-15)  # fmt: skip
    assert (mesh.link, mesh.frame, mesh.size, mesh.rgba) == ("c", 1, (2.0, 2.0, 2.0), None)
    np.testing.assert_allclose(np.array(mesh.poses[0])[:3, 3], [0, 0.2, 0])
    np.testing.assert_allclose(mesh.load_mesh().vertices, [[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    assert [e.shape for e in urdf.read_collisions(tmp_path / "v.urdf")] == ["sphere"]
    with pytest.raises(ValueError, match="rgba must be 4 numbers in 0..1"):
        urdf.read_visuals(VISUALS.replace("1 0 0 0.5", "255 0 0 1"))
    with pytest.raises(ValueError, match="a box element has no mesh file"):
        box.load_mesh()
    (tmp_path / "m.obj").write_bytes(b"\x00\xff" * 50)
    with pytest.raises(ValueError, match="m.obj' (has no vertices|cannot be read)"):
        mesh.load_mesh()


def test_kuka_visuals_sit_on_their_links():
    """pybullet's iiwa: link i's visual mesh at frame i, with the colour its named material gives."""
    elements = urdf.read_visuals(DATA / "kuka_iiwa/model.urdf")
    assert [(e.link, e.frame) for e in elements] == [(f"lbr_iiwa_link_{i}", i) for i in range(8)]
    grey, orange, blue = (0.2, 0.2, 0.2, 1.0), (1.0, 0.423529411765, 0.0392156862745, 1.0), (0.5, 0.7, 1.0, 1.0)
    assert [e.rgba for e in elements] == [grey, blue, blue, orange, blue, blue, orange, grey]
    assert all(e.filename.endswith(f"meshes/link_{i}.obj") for i, e in enumerate(elements))
