"""Capsules fitted to a URDF's collision geometry (iiwa_torch.capsule_fit), held to the meshes
themselves (trimesh: vertices, convex-hull volumes), closed forms for primitives and pair
selection, and pybullet as an independent collision checker of pybullet_data's Panda.

``python tests/test_capsule_fit.py 10000`` runs the pybullet comparison by hand on more
configurations (the numbers in docs/collision.md)."""

import math
import pathlib
import sys

import numpy as np
import pytest
import torch

from iiwa_torch import compiled, robots
from iiwa_torch.capsule_fit import urdf_capsules
from iiwa_torch.collision import World, clearance, segment_distance
from iiwa_torch.urdf import read_collisions

pytest.importorskip("pytorch_kinematics")
trimesh = pytest.importorskip("trimesh")
pybullet_data = pytest.importorskip("pybullet_data")
PANDA = pathlib.Path(pybullet_data.getDataPath()) / "franka_panda" / "panda.urdf"
F = torch.float64


@pytest.fixture(scope="module")
def panda():
    chain = robots.from_urdf(PANDA, end_link="panda_hand")
    return chain, urdf_capsules(chain, PANDA)


def _vertices(element) -> np.ndarray:
    """Every vertex of a mesh element at each of its poses, in its chain frame ``(N, 3)``."""
    mesh = trimesh.load(element.filename, force="mesh")
    local = np.asarray(mesh.vertices) * np.asarray(element.size)
    return np.concatenate([local @ np.asarray(p)[:3, :3].T + np.asarray(p)[:3, 3] for p in element.poses])


def _inside(caps, k: int, points: np.ndarray) -> np.ndarray:
    """Distance from each point to capsule k's segment minus its radius (<= 0 inside)."""
    p = torch.from_numpy(points)
    a, b = caps.points[k]
    return (segment_distance(p, p, a.expand_as(p), b.expand_as(p)) - caps.radii[k]).numpy()


def test_every_mesh_vertex_is_inside_its_capsule(panda):
    _, caps = panda
    elements = read_collisions(PANDA, end_link="panda_link7")
    assert sorted(caps.names) == sorted({e.link for e in elements})  # the hand and the fingers too
    for element in elements:
        k = caps.names.index(element.link)
        assert caps.frames[k] == element.frame
        assert _inside(caps, k, _vertices(element)).max() <= 1e-12, element.link


def test_frames_of_fixed_and_sliding_links(panda):
    """panda_hand hangs off panda_link7 by fixed joints: its capsule is in frame 7, around the hand
    mesh placed by the tool transform (from_urdf to panda_hand); the fingers slide 0..4 cm, and
    their capsules hold the finger mesh at both ends of the slide."""
    chain, caps = panda
    k = caps.names.index("panda_hand")
    hand = trimesh.load(PANDA.parent / "meshes" / "collision" / "hand.obj", force="mesh").vertices
    tool = chain.tool.numpy()
    assert caps.frames[k] == 7
    assert _inside(caps, k, hand @ tool[:3, :3].T + tool[:3, 3]).max() <= 1e-12
    finger = np.asarray(trimesh.load(PANDA.parent / "meshes" / "collision" / "finger.obj", force="mesh").vertices)
    k = caps.names.index("panda_leftfinger")
    for opening in (0.0, 0.02, 0.04):  # the left finger: origin 0.0584 up the hand, sliding along the hand's y
        placed = tool[:3, :3] @ (finger + [0.0, opening, 0.0584]).T
        assert _inside(caps, k, placed.T + tool[:3, 3]).max() <= 1e-12


def _primitive_urdf() -> str:
    """Two revolute joints; the base a box, link1 a cylinder, link2 a sphere, a fixed tip a sphere."""
    joint = '<axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/>'
    return f"""<robot name="prim">
      <link name="base"><collision><origin xyz="0 0 0.05"/><geometry><box size="0.2 0.1 0.1"/></geometry>
      </collision></link>
      <link name="l1"><collision><origin xyz="0.25 0 0" rpy="0 1.5707963267948966 0"/>
        <geometry><cylinder radius="0.04" length="0.3"/></geometry></collision></link>
      <link name="l2"><collision><origin xyz="0.1 0.02 0"/><geometry><sphere radius="0.05"/></geometry>
      </collision></link>
      <link name="tip"><collision><geometry><sphere radius="0.03"/></geometry></collision></link>
      <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/><origin xyz="0 0 0.2"/>{joint}</joint>
      <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/><origin xyz="0.5 0 0"/>{joint}</joint>
      <joint name="fix" type="fixed"><parent link="l2"/><child link="tip"/><origin xyz="0.3 0 0.1"/></joint>
    </robot>"""


def test_primitives_exact():
    text = _primitive_urdf()
    chain = robots.from_urdf(text, end_link="tip")
    caps = urdf_capsules(chain, text)
    assert caps.names == ("base", "l1", "l2", "tip") and caps.frames == (0, 1, 2, 2)
    by_name = dict(zip(caps.names, zip(caps.points, caps.radii.tolist())))
    ends, radius = by_name["l1"]  # the cylinder: its axis (x from 0.1 to 0.4) and its radius
    assert radius == pytest.approx(0.04, abs=1e-9)
    assert sorted(ends[:, 0].tolist()) == pytest.approx([0.1, 0.4], abs=1e-6)
    assert ends[:, 1:].abs().max() < 1e-6
    for name, centre, r in (("l2", [0.1, 0.02, 0.0], 0.05), ("tip", chain.tool[:3, 3].tolist(), 0.03)):
        ends, radius = by_name[name]  # a sphere: its centre, its radius
        assert radius == pytest.approx(r, abs=1e-9)
        assert torch.allclose(ends, torch.tensor([centre, centre], dtype=F), atol=1e-6)
    ends, radius = by_name["base"]  # a box: every corner inside, no larger than its circumscribed sphere
    corners = np.array([[x, y, z] for x in (-0.1, 0.1) for y in (-0.05, 0.05) for z in (0.0, 0.1)])
    assert _inside(caps, 0, corners).max() <= 1e-12
    assert radius <= math.sqrt(0.1**2 + 0.05**2 * 2) + 1e-12
    assert caps.floor.tolist() == [False, True, True, True]  # the base stands on the floor


def _sliding_urdf(lower: float, upper: float, far_radius: float) -> str:
    """base -> a -> b along x by two prismatic joints in [lower, upper]; spheres at the link origins."""
    def joint(name, parent, child):
        return (f'<joint name="{name}" type="prismatic"><parent link="{parent}"/><child link="{child}"/>'
                f'<axis xyz="1 0 0"/><limit lower="{lower}" upper="{upper}" effort="1" velocity="1"/></joint>')

    def link(name, r):
        return f'<link name="{name}"><collision><geometry><sphere radius="{r}"/></geometry></collision></link>'

    return (f'<robot name="slide">{link("base", 0.1)}{link("a", 0.1)}{link("b", far_radius)}'
            f'{joint("ja", "base", "a")}{joint("jb", "a", "b")}</robot>')


@pytest.mark.parametrize(
    ("lower", "upper", "far_radius", "kept"),
    [
        (0.0, 1.0, 0.1, True),  # base-b distance 0..2 minus 0.2: sometimes overlapping
        (0.5, 1.0, 0.1, False),  # 1..2 minus 0.2: never within 5 cm
        (0.0, 1.0, 3.0, False),  # 0..2 minus 3.1: always overlapping
        (0.5, 1.0, 0.9, True),  # 1..2 minus 1.0: never overlapping, within 5 cm below 1.05
    ],
)
def test_pair_selection_rules(lower, upper, far_radius, kept):
    text = _sliding_urdf(lower, upper, far_radius)
    chain = robots.from_urdf(text)
    caps = urdf_capsules(chain, text, samples=2000)
    assert caps.names == ("base", "a", "b")
    assert caps.pairs == (((0, 2),) if kept else ())  # base-a and a-b are adjacent: never checked


def test_panda_pairs_leave_out_adjacent_and_rigid_links(panda):
    chain, caps = panda
    names = [(caps.names[i], caps.names[j]) for i, j in caps.pairs]
    adjacent = {frozenset(p) for p in zip(["panda_link0", *chain.link_names[:-1]], chain.link_names)}
    assert not adjacent & {frozenset(p) for p in names}
    assert all(caps.frames[i] != caps.frames[j] for i, j in caps.pairs)
    assert ("panda_link2", "panda_link5") in names and ("panda_link0", "panda_hand") in names


def test_user_pairs_are_honoured(panda):
    chain, _ = panda
    text = _primitive_urdf()
    prim = robots.from_urdf(text, end_link="tip")
    caps = urdf_capsules(prim, text, pairs=[("tip", "base"), ("l2", "base")])
    assert caps.pairs == ((0, 3), (0, 2))
    with pytest.raises(ValueError, match="pairs"):
        urdf_capsules(prim, text, pairs=[("tip", "nope")])
    with pytest.raises(ValueError, match="chain"):
        urdf_capsules(chain, text)  # the Panda is not this file's path


def test_mesh_files_are_found_or_named(tmp_path):
    """package:// names resolve under the URDF's folder (pybullet_data's Panda above); a mesh
    that is not there, or a relative one in URDF text (no folder to look in), is a ValueError."""
    mesh = '<link name="a"><collision><geometry><mesh filename="{}"/></geometry></collision></link>'
    joint = ('<joint name="j" type="revolute"><parent link="a"/><child link="b"/><axis xyz="0 0 1"/>'
             '<limit lower="-1" upper="1" effort="1" velocity="1"/></joint><link name="b"/>')
    text = f'<robot name="m">{mesh.format("package://meshes/nope.obj")}{joint}</robot>'
    (tmp_path / "m.urdf").write_text(text)
    chain = robots.from_urdf(text)
    with pytest.raises(ValueError, match="nope.obj.* not found"):
        urdf_capsules(chain, tmp_path / "m.urdf")
    with pytest.raises(ValueError, match="relative.*file path"):
        urdf_capsules(chain, text)
    with pytest.raises(ValueError, match="sizes must be positive"):
        text = text.replace(mesh.format("package://meshes/nope.obj"), mesh.format("x").replace(
            '<mesh filename="x"/>', '<sphere radius="0"/>'))
        urdf_capsules(chain, text)


def _pybullet_contacts(chain, q: torch.Tensor, fingers: torch.Tensor) -> np.ndarray:
    """Per configuration, whether pybullet finds the Panda (fingers at ``fingers``) in contact
    deeper than 1 mm with itself or the floor, leaving out parent-child links, the pairs that
    always touch (panda_link0-floor, panda_hand-panda_link7) and the two fingers, whose pads touch
    when the gripper is closed: a contact inside the gripper that no arm joint changes (our
    model holds both in frame 7 and checks neither against the other)."""
    import pybullet as p

    cid = p.connect(p.DIRECT)
    try:
        plane = p.loadURDF(str(pathlib.Path(pybullet_data.getDataPath()) / "plane.urdf"), physicsClientId=cid)
        robot = p.loadURDF(str(PANDA), useFixedBase=True, flags=p.URDF_USE_SELF_COLLISION, physicsClientId=cid)
        names, parent, index = {-1: "panda_link0"}, {}, {}
        for i in range(p.getNumJoints(robot, physicsClientId=cid)):
            info = p.getJointInfo(robot, i, physicsClientId=cid)
            names[i], parent[i], index[info[1].decode()] = info[12].decode(), info[16], i
        slots = [index[n] for n in (*chain.joint_names, "panda_finger_joint1", "panda_finger_joint2")]
        skip = {("floor", "panda_link0"), ("panda_hand", "panda_link7"), ("panda_leftfinger", "panda_rightfinger")}
        found = np.zeros(len(q), dtype=bool)
        for k, values in enumerate(torch.cat([q, fingers], 1).tolist()):
            for slot, value in zip(slots, values):
                p.resetJointState(robot, slot, value, physicsClientId=cid)
            p.performCollisionDetection(physicsClientId=cid)
            for c in p.getContactPoints(bodyA=robot, physicsClientId=cid):
                a, b = c[3], c[4]
                if c[8] > -1e-3 or (c[2] == robot and (parent.get(a) == b or parent.get(b) == a)):
                    continue
                pair = tuple(sorted((names[a], "floor" if c[2] == plane else names[b])))
                found[k] |= pair not in skip
        return found
    finally:
        p.disconnect(cid)


def compare_with_pybullet(chain, caps, n: int, seed: int = 1) -> tuple[int, int, int, int]:
    """(configurations pybullet finds in contact, of those ours reports clear, pybullet-clear ones,
    of those ours flags) over ``n`` uniform configurations, fingers open 0..4 cm at random."""
    generator = torch.Generator().manual_seed(seed)
    q = chain.random_q(n, generator=generator)
    fingers = torch.rand(n, 2, generator=generator, dtype=F) * 0.04
    contact = _pybullet_contacts(chain, q, fingers)
    clear = (clearance(chain, q, World(floor=0.0), caps) >= 0).numpy()
    return int(contact.sum()), int((contact & clear).sum()), int((~contact).sum()), int((~contact & ~clear).sum())


def test_conservative_against_pybullet(panda):
    pytest.importorskip("pybullet")
    chain, caps = panda
    contact, missed, free, flagged = compare_with_pybullet(*panda, 2000)
    assert contact > 200  # the comparison has teeth: uniform Panda postures often collide
    assert missed == 0
    assert flagged < 0.5 * free  # the price of capsules: measured ~27% (docs/collision.md)


def test_volume_against_convex_hulls(panda):
    """Each capsule's volume over the convex hull of its link's vertices (both ends of a finger's
    slide); the mean over the Panda's 11 links at most 2.5."""
    _, caps = panda
    elements = read_collisions(PANDA, end_link="panda_link7")
    ratios = []
    for k, name in enumerate(caps.names):
        points = np.concatenate([_vertices(e) for e in elements if e.link == name])
        a, b = caps.points[k]
        r, length = float(caps.radii[k]), float((b - a).norm())
        ratios.append((math.pi * r * r * length + 4 / 3 * math.pi * r**3) / trimesh.convex.convex_hull(points).volume)
    assert min(ratios) > 1.0  # a capsule holding a hull is larger than it
    assert np.mean(ratios) <= 2.5


def test_clearance_batched_and_differentiable(panda):
    chain, caps = panda
    q = chain.random_q(6, generator=torch.Generator().manual_seed(3)).requires_grad_(True)
    world = World(floor=0.0)
    batched = clearance(chain, q.reshape(2, 3, 7), world, caps)
    looped = torch.stack([clearance(chain, x, world, caps) for x in q])
    assert torch.allclose(batched.flatten(), looped, atol=1e-12)
    assert torch.autograd.gradcheck(lambda x: clearance(chain, x, world, caps), (q,))


@pytest.mark.skipif(not compiled.ENABLED, reason="numba not installed or IIWA_TORCH_NUMBA=0")
def test_compiled_path_matches_torch(panda):
    chain, caps = panda
    q = chain.random_q(5000, generator=torch.Generator().manual_seed(4))
    fast = clearance(chain, q, World(floor=0.0), caps)  # a big CPU batch without gradients: compiled
    torch_path = clearance(chain, q.clone().requires_grad_(True), World(floor=0.0), caps).detach()
    assert torch.allclose(fast, torch_path, atol=1e-12, rtol=0)
    assert (fast < 0).any() and (fast > 0).any()


if __name__ == "__main__":
    arm = robots.from_urdf(PANDA, end_link="panda_hand")
    counts = compare_with_pybullet(arm, urdf_capsules(arm, PANDA), int(sys.argv[1]) if len(sys.argv) > 1 else 10000)
    print("pybullet contact {}, ours clear among them {}; pybullet clear {}, ours flags {}".format(*counts))
