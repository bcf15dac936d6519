"""URDF both ways: :func:`to_urdf` writes any :class:`~iiwa_torch.chain.Chain`; :func:`read_urdf` reads
the serial path between two links of a URDF as float64 data (:class:`UrdfPath`), and
:func:`read_collisions`/:func:`read_visuals` the geometry moving with its frames.

Export: links ``base_link``, the chain's ``link_names``, ``tool0`` (``_1``, ... appended to a name the
chain uses), with a token inertia. A DH chain's link i is the frame just after joint i's rotation (not
DH frame i); a fixed ``tool_joint`` carries the last constant part and the tool.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from xml.etree import ElementTree
from xml.sax.saxutils import quoteattr

import torch

from .chain import Chain, JointKind
from .checks import check_instance, require
from .dh import Convention, DHChain
from .kinematics import elementary_transform
from .so3 import matrix_to_rpy, rpy_to_matrix

__all__ = ["UrdfCollision", "UrdfJoint", "UrdfPath", "read_collisions", "read_urdf", "read_visuals", "to_urdf"]

MOVABLE = ("revolute", "continuous", "prismatic")
_JOINT_ELEMENTS = ("origin", "parent", "child", "axis", "limit", "mimic")  # the kinematic ones


def _origin(matrix: torch.Tensor) -> str:
    xyz = " ".join(repr(v) for v in matrix[:3, 3].tolist())
    rpy = " ".join(repr(v) for v in matrix_to_rpy(matrix[:3, :3]).tolist())
    return f'<origin xyz="{xyz}" rpy="{rpy}"/>'


def _link(name: str) -> str:
    inertia = '<inertia ixx="1e-4" ixy="0" ixz="0" iyy="1e-4" iyz="0" izz="1e-4"/>'
    return f'  <link name={quoteattr(name)}><inertial><mass value="0.1"/>{inertia}</inertial></link>'


def _unused(name: str, taken: list[str]) -> str:
    """``name``, or ``name_1``, ``name_2``, ... if the chain already uses it."""
    candidate, i = name, 0
    while candidate in taken:
        i += 1
        candidate = f"{name}_{i}"
    return candidate


def _dh_joints(chain: DHChain) -> tuple[list[torch.Tensor], list[tuple[float, float, float]], torch.Tensor]:
    """A DH chain's joint origins and axes (z), and the transform left after the last joint: standard DH's
    origin i is the previous row's ``Tz(d) Tx(a) Rx(alpha)`` (the base for joint 1) times ``Rz(offset)``,
    modified DH's ``Tz(d_prev) Rx(alpha) Tx(a) Rz(offset)``."""
    carry = chain.base.detach().cpu().to(torch.float64)  # constant transform waiting to be placed
    origins = []
    for a, alpha, d, offset in chain.dh.detach().cpu().to(torch.float64).tolist():
        if chain.convention is Convention.STANDARD:
            origins.append(carry @ elementary_transform("z", offset))
            carry = elementary_transform("z", 0.0, (0.0, 0.0, d)) @ elementary_transform("x", alpha, (a, 0.0, 0.0))
        else:
            origins.append(carry @ elementary_transform("x", alpha, (a, 0.0, 0.0)) @ elementary_transform("z", offset))
            carry = elementary_transform("z", 0.0, (0.0, 0.0, d))
    return origins, [(0.0, 0.0, 1.0)] * chain.n_joints, carry


def to_urdf(chain: Chain, name: str | None = None) -> str:
    """The chain as a URDF string, with kinds, limits and speeds; ``from_urdf(to_urdf(c))`` has ``c``'s frames."""
    check_instance(chain, Chain, "chain")
    robot = name or chain.name
    if isinstance(chain, DHChain):
        origins, axes, carry = _dh_joints(chain)
    else:
        origins = list(chain.origins.detach().cpu().to(torch.float64))
        origins[0] = chain.base.detach().cpu().to(torch.float64) @ origins[0]
        axes, carry = [tuple(a) for a in chain.axes.tolist()], torch.eye(4, dtype=torch.float64)
    lower, upper = chain.limits.detach().cpu().tolist()
    speeds = chain.velocity_limits.tolist() if chain.velocity_limits is not None else [10.0] * chain.n_joints
    links = [_unused("base_link", chain.link_names), *chain.link_names, _unused("tool0", chain.link_names)]
    tool_joint = _unused("tool_joint", chain.joint_names)
    lines = ['<?xml version="1.0"?>', f"<robot name={quoteattr(robot)}>"]
    lines += [_link(link) for link in links]
    for i, (joint, kind, origin, axis) in enumerate(zip(chain.joint_names, chain.kinds, origins, axes)):
        limit = "" if kind is JointKind.CONTINUOUS else f'lower="{lower[i]!r}" upper="{upper[i]!r}" '
        lines.append(
            f'  <joint name={quoteattr(joint)} type="{kind.value}">'
            f'<parent link={quoteattr(links[i])}/><child link={quoteattr(links[i + 1])}/>{_origin(origin)}'
            f'<axis xyz="{" ".join(repr(v) for v in axis)}"/><limit {limit}'
            f'effort="100" velocity="{speeds[i]!r}"/></joint>'
        )
    tool = carry @ chain.tool.detach().cpu().to(torch.float64)
    lines += [f'  <joint name={quoteattr(tool_joint)} type="fixed"><parent link={quoteattr(links[-2])}/>'
              f'<child link={quoteattr(links[-1])}/>{_origin(tool)}</joint>', "</robot>"]
    return "\n".join(lines) + "\n"


Matrix = tuple[tuple[float, float, float, float], ...]  # 4x4, row-major


@dataclass(frozen=True)
class UrdfJoint:
    """One movable joint of a :class:`UrdfPath`: ``origin`` the 4x4 from the previous movable joint's child
    link at q = 0 (fixed joints folded in), unit ``axis``, limits in rad or m (infinite for continuous),
    ``velocity`` (rad/s or m/s; None if absent or 0)."""

    name: str
    kind: str  # "revolute", "continuous" or "prismatic"
    origin: Matrix
    axis: tuple[float, float, float]
    lower: float
    upper: float
    velocity: float | None
    child: str
    parent: str


@dataclass(frozen=True)
class UrdfPath:
    """A URDF's path from ``base_link`` to ``end_link``: movable ``joints``, ``tool`` (4x4 from the last
    joint's child link to ``end_link``) and ``links`` (the joints' child links)."""

    robot: str
    base_link: str
    end_link: str
    joints: tuple[UrdfJoint, ...]
    tool: Matrix
    links: tuple[str, ...]


def _document(source: str | os.PathLike) -> str | bytes:
    if isinstance(source, str) and source.lstrip().lstrip("\ufeff").lstrip().startswith("<"):
        return source.lstrip().lstrip("\ufeff")  # text read with encoding="utf-8" keeps a byte-order mark
    if not isinstance(source, (str, os.PathLike)):
        raise TypeError(f"source must be a URDF file path or URDF XML text, got {type(source).__name__}")
    path = os.fspath(source)
    if os.path.isdir(path):
        raise ValueError(f"source: {path!r} is a folder; pass the URDF file in it (or the XML text itself)")
    if not os.path.isfile(path):
        raise ValueError(f"source: no URDF file at {path!r} (pass a file path or the XML text itself)")
    with open(path, "rb") as file:  # bytes: the parser reads the encoding declaration itself
        return file.read()


def _kinematic_xml(document: str | bytes) -> str:
    """The robot's links (names only) and joints (kinematic elements only), so a parser strict about
    transmissions, gazebo blocks and the like cannot fail on them."""
    try:
        robot = ElementTree.fromstring(document)
    except ElementTree.ParseError as err:
        raise ValueError(f"source is not well-formed XML: {err}") from None
    if robot.tag != "robot":
        raise ValueError(f"source must be a URDF, whose root element is <robot>, got <{robot.tag}>")
    kept = ElementTree.Element("robot", robot.attrib)
    for element in robot:
        if element.tag == "link":
            ElementTree.SubElement(kept, "link", element.attrib)
        elif element.tag == "joint":
            joint = ElementTree.SubElement(kept, "joint", element.attrib)
            joint.extend(child for child in element if child.tag in _JOINT_ELEMENTS)
    return ElementTree.tostring(kept, encoding="unicode")


def _transform(origin, joint: str) -> torch.Tensor:
    """``(4, 4)`` float64 of a parsed ``<origin>`` (identity if absent)."""
    xyz, rpy = (origin.xyz, origin.rpy) if origin is not None else ((0.0,) * 3, (0.0,) * 3)
    if not all(map(math.isfinite, (*xyz, *rpy))):
        raise ValueError(f"joint {joint!r}: origin must be finite, got xyz={xyz}, rpy={rpy}")
    return _pose(xyz, rpy)


def _pose(xyz, rpy) -> torch.Tensor:
    """``(4, 4)`` float64 of a translation and roll-pitch-yaw."""
    matrix = torch.eye(4, dtype=torch.float64)
    matrix[:3, :3] = rpy_to_matrix(torch.tensor(rpy, dtype=torch.float64))
    matrix[:3, 3] = torch.tensor(xyz, dtype=torch.float64)
    return matrix


def _rows(matrix: torch.Tensor) -> Matrix:
    return tuple(map(tuple, matrix.tolist()))


def _movable(joint, origin: torch.Tensor) -> UrdfJoint:
    """A parsed revolute/continuous/prismatic joint, its origin already folded."""
    axis = tuple(joint.axis) if joint.axis is not None else (1.0, 0.0, 0.0)  # URDF's default
    norm = math.hypot(*axis)
    if not (math.isfinite(norm) and norm > 0):
        raise ValueError(f"joint {joint.name!r}: axis must be a nonzero finite vector, got {axis}")
    limit = joint.limit
    if joint.type == "continuous":
        lower, upper = -math.inf, math.inf
    elif limit is None:
        raise ValueError(f"joint {joint.name!r} is {joint.type} and has no <limit> (URDF requires one)")
    else:
        lower, upper = limit.lower, limit.upper
        if not (math.isfinite(lower) and math.isfinite(upper) and lower <= upper):
            raise ValueError(f"joint {joint.name!r}: limits must be finite with lower <= upper, got {lower}, {upper}")
    velocity = limit.velocity if limit is not None else None
    if velocity is not None and not (velocity >= 0 and math.isfinite(velocity)):
        raise ValueError(f"joint {joint.name!r}: velocity limit must be finite and >= 0, got {velocity}")
    return UrdfJoint(joint.name, joint.type, _rows(origin), tuple(v / norm for v in axis), lower, upper,
                     velocity or None, joint.child, joint.parent)


def _known_link(name, argument: str, links: list[str]) -> str:
    if not isinstance(name, str):
        raise TypeError(f"{argument} must be a link name (str) or None, got {type(name).__name__}")
    if name not in links:
        shown = ", ".join(links[:6]) + (", ..." if len(links) > 6 else "")
        raise ValueError(f"{argument} {name!r} is not a link of this URDF (links: {shown})")
    return name


def _below(top: str, children: dict[str, list[str]]) -> list[str]:
    """``top`` and every link under it, depth first."""
    found, stack = [], [top]
    while stack:
        found.append(stack.pop())
        stack.extend(reversed(children[found[-1]]))
    return found


def _tree(links: list[str], joints: list) -> tuple[str, dict, dict[str, list[str]]]:
    """The root link, each link's parent joint and child links, checked to be one tree of unique names."""
    for kind, names in (("link", links), ("joint", [joint.name for joint in joints])):
        twice = sorted({name for name in names if names.count(name) > 1})
        if twice:
            raise ValueError(f"{kind} names must be unique, got {twice} more than once")
    parent_joint, children = {}, {name: [] for name in links}
    for joint in joints:
        for name in (joint.parent, joint.child):
            if name not in children:
                raise ValueError(f"joint {joint.name!r} names link {name!r}, which the URDF does not declare")
        if joint.child in parent_joint:
            raise ValueError(f"link {joint.child!r} is the child of two joints, {parent_joint[joint.child].name!r} "
                             f"and {joint.name!r}: a URDF is a tree")
        parent_joint[joint.child] = joint
        children[joint.parent].append(joint.child)
    roots = [name for name in links if name not in parent_joint]
    if len(roots) != 1:
        raise ValueError(f"a URDF has one root link (no parent joint), this one has {len(roots)}: {roots}")
    cut = set(links) - set(_below(roots[0], children))
    if cut:
        raise ValueError(f"links {sorted(cut)} hang off a cycle of joints, not off the root {roots[0]!r}")
    return roots[0], parent_joint, children


def _parse(document: str | bytes) -> tuple:
    """The robot parsed by pytorch_kinematics (kinematic elements only), its link names and :func:`_tree`."""
    kinematic = _kinematic_xml(document)
    urdf = require("pytorch_kinematics.urdf_parser_py.urdf", "urdf")
    try:
        robot = urdf.URDF.from_xml_string(kinematic)
    except Exception as err:  # the parser raises its ParseError, AssertionError or a bare Exception
        raise ValueError(f"source is not a valid URDF: {err}".replace("\n", " ")) from None
    links = [link.name for link in robot.links]
    return (robot, links, *_tree(links, robot.joints))


def read_urdf(source: str | os.PathLike, end_link: str | None = None, base_link: str | None = None) -> UrdfPath:
    """The serial path of a URDF from ``base_link`` (default the root) to ``end_link`` (default the only
    leaf below it), in float64; fixed joints folded into the next origin or the tool.

    ``source``: a ``.urdf`` path or the XML text (parsed by pytorch_kinematics, the ``urdf`` extra).
    Raises ``ValueError`` for a malformed file, unknown links, an ``end_link`` not below
    ``base_link``, a floating, planar or mimic joint on the path, a zero axis, or no movable joint.
    """
    return _path(_parse(_document(source)), end_link, base_link)


def _path(parsed: tuple, end_link: str | None, base_link: str | None) -> UrdfPath:
    """:func:`read_urdf` of a robot as :func:`_parse` returns it."""
    robot, links, root, parent_joint, children = parsed
    base = root if base_link is None else _known_link(base_link, "base_link", links)
    if end_link is None:
        leaves = [name for name in _below(base, children) if not children[name]]
        if len(leaves) != 1:
            raise ValueError(f"the URDF has {len(leaves)} leaf links below {base!r} ({', '.join(leaves)}); "
                             "pass end_link= to choose one")
        end = leaves[0]
    else:
        end = _known_link(end_link, "end_link", links)

    path, link = [], end
    while link != base:
        if link not in parent_joint:
            raise ValueError(f"end_link {end!r} is not below base_link {base!r}")
        path.append(parent_joint[link])
        link = parent_joint[link].parent
    carry, joints = torch.eye(4, dtype=torch.float64), []  # carry: fixed transforms waiting for a joint
    for joint in reversed(path):
        if joint.mimic is not None:
            raise ValueError(f"joint {joint.name!r} mimics {joint.mimic.joint!r}: mimic joints are not supported")
        if joint.type not in (*MOVABLE, "fixed"):
            raise ValueError(f"joint {joint.name!r} between {base!r} and {end!r} is {joint.type}; "
                             f"supported are {', '.join(MOVABLE)} and fixed joints")
        carry = carry @ _transform(joint.origin, joint.name)
        if joint.type != "fixed":
            joints.append(_movable(joint, carry))
            carry = torch.eye(4, dtype=torch.float64)
    if not joints:
        raise ValueError(f"no movable joint between base_link {base!r} and end_link {end!r}")
    return UrdfPath(robot.name or "", base, end, tuple(joints), _rows(carry), tuple(j.child for j in joints))


@dataclass(frozen=True)
class UrdfCollision:
    """A ``<collision>`` (or ``<visual>``) element of a link moving with chain frame ``frame`` (0 the
    base, i the child link of joint i), through fixed joints or off-path prismatic ones.

    ``poses``: 4x4s from that frame to the element: one, or one per corner of the off-path
    prismatic joints' limits (2**k, the first at the lower limits). ``shape`` and ``size`` (m):
    ``box`` (x, y, z edges), ``cylinder`` (radius, length along z), ``sphere`` (radius,), ``mesh``
    (x, y, z scale of ``filename``). ``rgba``: a visual's material colour (0..1) or None.
    """

    link: str
    frame: int
    poses: tuple[Matrix, ...]
    shape: str
    size: tuple[float, ...]
    filename: str | None = None
    rgba: tuple[float, float, float, float] | None = None

    def load_mesh(self):
        """The unscaled ``trimesh.Trimesh`` of a mesh element; ValueError if unreadable or empty."""
        if self.shape != "mesh":
            raise ValueError(f"link {self.link!r}: a {self.shape} element has no mesh file")
        trimesh = require("trimesh", "urdf")
        try:
            mesh = trimesh.load(self.filename, force="mesh")
        except Exception as err:  # trimesh raises many kinds of errors for a file it cannot read
            raise ValueError(f"link {self.link!r}: mesh {self.filename!r} cannot be read: {err}") from None
        if len(getattr(mesh, "vertices", ())) == 0:
            raise ValueError(f"link {self.link!r}: mesh {self.filename!r} has no vertices")
        return mesh


_SIZES = {  # each shape's size attributes: (name, count, default)
    "box": (("size", 3, ""),),
    "cylinder": (("radius", 1, ""), ("length", 1, "")),
    "sphere": (("radius", 1, ""),),
    "mesh": (("scale", 3, "1 1 1"),),
}


def _numbers(element, attribute: str, count: int, default: str, where: str) -> tuple[float, ...]:
    text = element.get(attribute, default)
    try:
        values = tuple(float(v) for v in text.split())
    except ValueError:
        values = ()
    if len(values) != count or not all(map(math.isfinite, values)):
        raise ValueError(f"{where}: {attribute} must be {count} finite numbers, got {text!r}")
    return values


def _mesh_file(name: str, directory: str | None, where: str) -> str:
    """The file of a mesh ``filename``: absolute, ``file://``, relative to the URDF's directory, or
    ``package://pkg/rest`` found as ``rest`` or ``pkg/rest`` under that directory or a parent."""
    name = name.removeprefix("file://")
    tried = [name] if os.path.isabs(name) else []
    if directory is not None and not tried:
        folders = [directory]
        while os.path.dirname(folders[-1]) != folders[-1]:
            folders.append(os.path.dirname(folders[-1]))
        if name.startswith("package://"):
            rest = name.removeprefix("package://")
            tried = [os.path.join(d, r) for r in (rest, rest.partition("/")[2]) if r for d in folders]
        else:
            tried = [os.path.join(directory, name)]
    for path in tried:
        if os.path.isfile(path):
            return path
    if directory is None and not tried:
        raise ValueError(f"{where}: mesh {name!r} is relative; pass the URDF as a file path so it can be found")
    raise ValueError(f"{where}: mesh {name!r} not found (looked at {', '.join(tried[:4])})")


def _colour(material, named: dict, where: str) -> tuple[float, float, float, float] | None:
    """The rgba (0..1) of a ``<material>`` element: its ``<color>``, else the robot's material of its name."""
    if material is None:
        return None
    colour = material.find("color")
    if colour is None:
        return named.get(material.get("name"))
    rgba = _numbers(colour, "rgba", 4, "", f"{where} <material>")
    if not all(0 <= v <= 1 for v in rgba):
        raise ValueError(f"{where} <material>: rgba must be 4 numbers in 0..1, got {rgba}")
    return rgba


def _element(element, link: str, frame: int, poses: list[torch.Tensor], directory: str | None,
             named: dict | None) -> UrdfCollision:
    """A ``<collision>`` or ``<visual>`` element of ``link`` at ``poses`` in the chain frame; ``named``:
    the robot's material colours (visuals), None for collisions."""
    where = f"link {link!r}: <{element.tag}>"
    origin = element.find("origin")
    if origin is not None:
        local = _pose(_numbers(origin, "xyz", 3, "0 0 0", where), _numbers(origin, "rpy", 3, "0 0 0", where))
        poses = [pose @ local for pose in poses]
    geometry = element.find("geometry")
    shapes = [] if geometry is None else [g for g in geometry if g.tag in _SIZES]
    if len(shapes) != 1:
        raise ValueError(f"{where} must have one <geometry> of {', '.join(_SIZES)}")
    shape = shapes[0]
    size = tuple(v for name, count, default in _SIZES[shape.tag] for v in _numbers(shape, name, count, default, where))
    filename = _mesh_file(shape.get("filename", ""), directory, where) if shape.tag == "mesh" else None
    if not all(v > 0 for v in size):
        raise ValueError(f"{where}: {shape.tag} sizes must be positive, got {size}")
    rgba = None if named is None else _colour(element.find("material"), named, where)
    return UrdfCollision(link, frame, tuple(_rows(p) for p in poses), shape.tag, size, filename, rgba)


def read_collisions(source: str | os.PathLike, end_link: str | None = None,
                    base_link: str | None = None) -> tuple[UrdfCollision, ...]:
    """The ``<collision>`` elements of the links moving with :func:`read_urdf`'s frames (same arguments):
    through fixed joints, or off-path prismatic ones (swept over their limits). Meshes are found
    from the URDF's directory, so they need ``source`` as a file path."""
    return _elements(source, end_link, base_link, "collision")


def read_visuals(source: str | os.PathLike, end_link: str | None = None,
                 base_link: str | None = None) -> tuple[UrdfCollision, ...]:
    """The ``<visual>`` elements of :func:`read_collisions`' links, with their colours (``rgba``)."""
    return _elements(source, end_link, base_link, "visual")


def _elements(source, end_link, base_link, tag: str) -> tuple[UrdfCollision, ...]:
    document = _document(source)
    parsed = _parse(document)
    path = _path(parsed, end_link, base_link)
    parent_joint, children = parsed[3:]
    directory = None if document is source else os.path.dirname(os.path.abspath(os.fspath(source)))
    robot = ElementTree.fromstring(document)
    elements = {link.get("name"): link.findall(tag) for link in robot.iter("link")}
    named = ({m.get("name"): _colour(m, {}, f"material {m.get('name')!r}") for m in robot.findall("material")}
             if tag == "visual" else None)  # collisions have no colour
    on_path = {joint.name for joint in path.joints}
    found = []
    for frame, top in enumerate((path.base_link, *path.links)):
        seen, stack = {top}, [(top, [torch.eye(4, dtype=torch.float64)])]
        while stack:
            link, poses = stack.pop()
            found += [_element(e, link, frame, poses, directory, named) for e in elements.get(link, [])]
            steps = []  # (neighbour, its link frame from this one: one or two transforms)
            up = parent_joint.get(link)
            if up is not None and up.type == "fixed":
                steps.append((up.parent, [torch.linalg.inv(_transform(up.origin, up.name))]))
            for child in children[link]:
                joint = parent_joint[child]
                origin = _transform(joint.origin, joint.name)
                if joint.type == "fixed":
                    steps.append((child, [origin]))
                elif joint.type == "prismatic" and joint.name not in on_path:
                    slide = _movable(joint, origin)
                    ends = [torch.eye(4, dtype=torch.float64) for _ in range(2)]
                    for end, value in zip(ends, (slide.lower, slide.upper)):
                        end[:3, 3] = torch.tensor(slide.axis, dtype=torch.float64) * value
                    steps.append((child, [origin @ end for end in ends]))
            for neighbour, moves in steps:
                if neighbour not in seen:
                    seen.add(neighbour)
                    stack.append((neighbour, [pose @ move for pose in poses for move in moves]))
    return tuple(found)
