"""The viewer's 3-D scene: the skeleton (cylinders between frame origins and along the joint axes) or a
URDF's visuals, the frames, the target gizmo, the capsules, the obstacles and the playback trace."""

from __future__ import annotations

import os
from collections.abc import Callable

import numpy as np
import torch

from .. import capsule_fit, collision, so3
from .. import urdf as urdf_io
from ..chain import Chain, z_onto
from ..dh import Convention, DHChain

_F64 = torch.float64
_LINK_COLOUR = (170, 175, 185)
_JOINT_COLOUR = (240, 130, 30)
_OBSTACLE_RGB = (90, 140, 200)
_CAPSULE_RGB = (60, 180, 120)
_HIT_RGB = (220, 30, 30)
_IDLE_RGB = (150, 150, 150)  # the target ball with nothing to report
_TRACE_COLOUR = (200, 40, 200)
_TARGET_RGB = {"reached": (40, 180, 60), "colliding": (250, 170, 0)}  # any other outcome: _HIT_RGB
_MIN_SEGMENT = 1e-6  # metres: consecutive frame origins closer than this get no link cylinder


def _segment_quaternions(direction: np.ndarray) -> np.ndarray:
    """Unit directions ``(k, 3)`` -> quaternions ``(k, 4)`` (w, x, y, z) turning +z onto each one."""
    w = 1.0 + direction[:, 2]
    quat = np.stack([w, -direction[:, 1], direction[:, 0], np.zeros_like(w)], 1)
    flipped = w < 1e-9  # direction = -z: any half turn about a horizontal axis
    quat[flipped] = (0.0, 1.0, 0.0, 0.0)
    return quat / np.linalg.norm(quat, axis=1, keepdims=True)


def _quaternions(rot: torch.Tensor) -> np.ndarray:
    """Rotations ``(..., 3, 3)`` -> ``(..., 4)`` (w, x, y, z) numpy, viser's order."""
    return so3.matrix_to_quaternion(rot).cpu().numpy()


def _segment_placement(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Segments ``a, b (k, 3)`` -> midpoints, quaternions turning +z along them, lengths ``(k,)``."""
    d = b - a
    length = np.linalg.norm(d, axis=1)
    unit = np.where(length[:, None] > _MIN_SEGMENT, d / np.maximum(length, _MIN_SEGMENT)[:, None], (0.0, 0.0, 1.0))
    return (a + b) / 2, _segment_quaternions(unit), length


def _origins(frames: torch.Tensor, end: torch.Tensor) -> np.ndarray:
    """``(n + 2, 3)`` origins of the frames ``(n + 1, 4, 4)``, then of the end effector ``end (4, 4)`` (metres)."""
    return torch.cat([frames[:, :3, 3], end[None, :3, 3]]).cpu().numpy()


class _CapsuleNodes:
    """A capsule drawn as a cylinder and two end spheres."""

    def __init__(self, scene, name: str, radius: float, colour, opacity: float | None, visible: bool = True):
        opts = dict(color=colour, opacity=opacity, visible=visible)
        self.body = scene.add_cylinder(f"{name}/body", radius=radius, height=1.0, **opts)
        self.ends = [scene.add_icosphere(f"{name}/end{i}", radius=radius, subdivisions=2, **opts) for i in range(2)]
        self.nodes = [self.body, *self.ends]

    def place(self, a: np.ndarray, b: np.ndarray) -> None:
        """Between the end points ``a, b (3,)`` (metres)."""
        mid, quat, length = _segment_placement(a[None], b[None])
        self.body.position, self.body.wxyz = mid[0], quat[0]
        self.body.scale = (1.0, 1.0, max(float(length[0]), _MIN_SEGMENT))
        self.ends[0].position, self.ends[1].position = a, b


def urdf_parts(chain: Chain, source, capsules: collision.Capsules | None):
    """``([(URDF <visual> element, its trimesh or None)], capsules)`` of the file ``chain`` was read from;
    ``capsules=None``: those fitted to its ``<collision>`` geometry, if any."""
    read_from = f"pass the chain robots.from_urdf reads from the file {os.fspath(source)!r}"
    try:
        path = urdf_io.read_urdf(source, end_link=chain.link_names[-1])
    except ValueError as err:  # e.g. a preset's last link is not in the file
        raise ValueError(f"urdf= draws the file chain {chain.name!r} was read from ({err}); {read_from}") from None
    first = torch.tensor(path.joints[0].origin, dtype=torch.float64)  # differs if read from a link below the root
    if [j.name for j in path.joints] != list(chain.joint_names) or not torch.allclose(
            chain.base.double().cpu() @ chain.origins[0].double().cpu(), first, rtol=0, atol=1e-12):
        raise ValueError(f"chain {chain.name!r} is not the path of that urdf from {path.base_link!r}; {read_from}")
    visuals = [(e, e.load_mesh() if e.shape == "mesh" else None) for e in urdf_io.read_visuals(source, path.end_link)]
    if capsules is None and urdf_io.read_collisions(source, end_link=path.end_link):  # after the quick checks
        capsules = capsule_fit.urdf_capsules(chain, source)
    return visuals, capsules


def _add_visual(scene, name: str, element: urdf_io.UrdfCollision, mesh):
    """A scene node of a URDF ``<visual>`` element: its material colour, else a mesh's own (or grey)."""
    colour = _LINK_COLOUR if element.rgba is None else tuple(round(255 * v) for v in element.rgba[:3])
    opts = dict(color=colour, opacity=None if element.rgba is None or element.rgba[3] >= 1 else element.rgba[3])
    size = element.size
    if element.shape == "mesh":
        if element.rgba is None:
            if mesh.visual.kind == "texture":  # our own copy: colours sampled at the vertices, no image to send
                mesh.visual = mesh.visual.to_color()
            return scene.add_mesh_trimesh(name, mesh, scale=size)
        return scene.add_mesh_simple(name, np.asarray(mesh.vertices), np.asarray(mesh.faces), scale=size, **opts)
    if element.shape == "box":
        return scene.add_box(name, dimensions=size, **opts)
    if element.shape == "cylinder":
        return scene.add_cylinder(name, radius=size[0], height=size[1], **opts)
    return scene.add_icosphere(name, radius=size[0], **opts)


class ArmScene:
    """Every node of ``chain``'s scene, sized by the link ``frames (n + 1, 4, 4)`` and ``end (4, 4)`` of a first
    configuration. ``visuals`` as :func:`urdf_parts` gives (with some, the skeleton starts hidden);
    ``on_drag(wxyz, position)``: the target gizmo was dragged.

    Nodes: ``links``, ``joints`` (the skeleton), ``visual_nodes`` ``[(element, node)]``, ``frame_nodes``,
    ``capsule_nodes`` ``{name: capsule}``, ``world_nodes`` ``{name: [nodes]}``, ``target``,
    ``target_marker``, ``goal_marker``, ``trace`` (None until :meth:`draw_trace`).
    """

    def __init__(self, server, chain: Chain, frames: torch.Tensor, end: torch.Tensor, *, visuals, capsules,
                 world, show_capsules: bool, show_frames: bool, on_drag: Callable):  # fmt: skip
        self.chain, self.capsules, self.world = chain, capsules, world
        self.server, scene = server, server.scene
        points = _origins(frames, end)
        lengths = np.linalg.norm(np.diff(points, axis=0), axis=1)  # fixed by the geometry, not by q
        self._segments = np.flatnonzero(lengths > _MIN_SEGMENT)
        self.reach = reach = max(float(lengths.sum()), 0.1)
        scene.set_up_direction("+z")
        floor = 0.0 if world is None or world.floor is None else float(world.floor)
        scene.add_grid(
            "/floor", width=3 * reach, height=3 * reach, cell_size=reach / 10, section_size=reach / 2,
            position=(0.0, 0.0, floor),
        )  # fmt: skip
        self._build_skeleton(scene, lengths, visible=not visuals)  # inside the meshes where there are some
        self._build_visuals(scene, visuals)
        self._build_markers(scene, show_frames, on_drag)
        self.capsule_nodes = {}  # capsule name -> _CapsuleNodes, placed at every draw
        if capsules is not None:
            for name, r in zip(capsules.names, capsules.radii.tolist()):
                self.capsule_nodes[name] = _CapsuleNodes(scene, f"/capsules/{name}", r, _CAPSULE_RGB, 0.45,
                                                        show_capsules)  # fmt: skip
        self.world_nodes = self._build_world(scene)
        self.trace = None
        cam = server.initial_camera
        cam.position = (1.1 * reach, -1.2 * reach, 0.8 * reach)
        cam.look_at = (0.1 * reach, 0.0, 0.4 * reach)

    def _build_skeleton(self, scene, lengths: np.ndarray, visible: bool) -> None:
        """A grey cylinder per link segment, an orange one along each joint axis."""
        radius = 0.03 * self.reach
        self.links = [
            scene.add_cylinder(
                f"/arm/link{i}", radius=radius, height=float(lengths[i]), color=_LINK_COLOUR, visible=visible
            )
            for i in self._segments
        ]
        # Joint i turns about the z axis of frame i - 1 (standard DH) or of frame i (modified DH);
        # in any other chain about its axis in its child link's frame i.
        chain, n = self.chain, self.chain.n_joints
        if isinstance(chain, DHChain):
            first = 0 if chain.convention == Convention.STANDARD else 1
            self._axis_frames, turns = list(range(first, first + n)), torch.eye(3, dtype=_F64).expand(n, 3, 3)
        else:
            self._axis_frames, turns = list(range(1, n + 1)), torch.stack([z_onto(a) for a in chain.axes.to(_F64)])
        self._axis_turns = turns  # (n, 3, 3): the joint cylinder's z onto the axis, in its frame
        self.joints = [
            scene.add_cylinder(
                f"/arm/joint{i + 1}", radius=1.5 * radius, height=5 * radius, color=_JOINT_COLOUR, visible=visible
            )
            for i in range(n)
        ]

    def _build_visuals(self, scene, visuals) -> None:
        self.visual_nodes = [  # (URDF <visual> element, its scene node), placed at every draw
            (element, _add_visual(scene, f"/visuals/{i}_{element.link}", element, mesh))
            for i, (element, mesh) in enumerate(visuals)
        ]
        self._visual_frames = [element.frame for element, _ in visuals]
        poses = [element.poses[0] for element, _ in visuals]  # off-path prismatic joints at their lower limits
        self._visual_poses = torch.tensor(poses, dtype=_F64).reshape(-1, 4, 4)

    def _build_markers(self, scene, show_frames: bool, on_drag: Callable) -> None:
        """The link and end-effector frames, the target gizmo with its ball, the playback goal."""
        reach = self.reach
        axes = dict(axes_length=0.12 * reach, axes_radius=0.006 * reach, visible=show_frames)
        self.frame_nodes = [scene.add_frame(f"/frames/f{i}", **axes) for i in range(self.chain.n_joints + 1)]
        self.frame_nodes.append(scene.add_frame("/frames/end", **axes))
        self._end_node = scene.add_frame("/end_effector", axes_length=0.08 * reach, axes_radius=0.008 * reach)
        self.target = scene.add_transform_controls("/target", scale=0.25 * reach)
        self.target_marker = scene.add_icosphere("/target/marker", radius=0.025 * reach, color=_IDLE_RGB)
        self.target.on_update(lambda event: on_drag(event.target.wxyz, event.target.position))
        self.goal_marker = scene.add_icosphere("/playback/goal", radius=0.02 * reach, color=_TRACE_COLOUR,
                                               visible=False)  # fmt: skip

    def _build_world(self, scene) -> dict[str, list]:
        """Draw the obstacles; ``{name: [nodes]}`` by pairwise_clearance's names (``floor``, ``sphere0``, ...)."""
        world, nodes, reach = self.world, {}, self.reach
        if world is None:
            return nodes
        opts = dict(color=_OBSTACLE_RGB, opacity=0.6)
        thick = 0.01 * reach
        if world.floor is not None:
            nodes["floor"] = [scene.add_box(
                "/world/floor", dimensions=(3 * reach, 3 * reach, thick), position=(0.0, 0.0, world.floor - thick),
                color=_OBSTACLE_RGB, opacity=0.15,
            )]  # fmt: skip
        if world.spheres is not None:
            for i, (c, r) in enumerate(zip(world.spheres[0].numpy(), world.spheres[1].tolist())):
                nodes[f"sphere{i}"] = [scene.add_icosphere(f"/world/sphere{i}", radius=r, position=c, **opts)]
        if world.boxes is not None:
            for i, (pose, half) in enumerate(zip(world.boxes[0], world.boxes[1].numpy())):
                nodes[f"box{i}"] = [scene.add_box(
                    f"/world/box{i}", dimensions=2 * half, position=pose[:3, 3].numpy(),
                    wxyz=_quaternions(pose[:3, :3]), **opts,
                )]  # fmt: skip
        if world.capsules is not None:
            for i, (ends, r) in enumerate(zip(world.capsules[0].numpy(), world.capsules[1].tolist())):
                cap = _CapsuleNodes(scene, f"/world/capsule{i}", r, _OBSTACLE_RGB, 0.6)
                cap.place(ends[0], ends[1])
                nodes[f"capsule{i}"] = cap.nodes
        if world.walls is not None:
            for i, (n, offset) in enumerate(zip(world.walls[0].numpy(), world.walls[1].tolist())):
                nodes[f"wall{i}"] = [scene.add_box(
                    f"/world/wall{i}", dimensions=(3 * reach, 3 * reach, thick), position=n * (offset - thick / 2),
                    wxyz=_segment_quaternions(n[None])[0], color=_OBSTACLE_RGB, opacity=0.25,
                )]  # fmt: skip
        return nodes

    def place(self, frames: torch.Tensor, end: torch.Tensor, move_target: bool) -> None:
        """Move the arm's nodes to ``frames (n + 1, 4, 4)`` and ``end (4, 4)``, and the gizmo if ``move_target``."""
        points = _origins(frames, end)
        mids, quats, _ = _segment_placement(points[self._segments], points[self._segments + 1])
        frame_quats = _quaternions(torch.cat([frames[:, :3, :3], end[None, :3, :3]]))
        joint_quats = _quaternions(frames[self._axis_frames, :3, :3] @ self._axis_turns)
        visual_poses = frames[self._visual_frames] @ self._visual_poses  # (V, 4, 4)
        visual_points, visual_quats = visual_poses[:, :3, 3].numpy(), _quaternions(visual_poses[:, :3, :3])
        for node, mid, quat in zip(self.links, mids, quats):
            node.position, node.wxyz = mid, quat
        for node, f, quat in zip(self.joints, self._axis_frames, joint_quats):
            node.position, node.wxyz = points[f], quat
        for (_, node), p, quat in zip(self.visual_nodes, visual_points, visual_quats):
            node.position, node.wxyz = p, quat
        for node, p, quat in zip(self.frame_nodes, points, frame_quats):
            node.position, node.wxyz = p, quat
        self._end_node.position, self._end_node.wxyz = points[-1], frame_quats[-1]
        if move_target:
            self.target.position, self.target.wxyz = points[-1], frame_quats[-1]

    def colour(self, frames: torch.Tensor, hits: set[str], outcome: str | None) -> None:
        """Place the capsules at ``frames (n + 1, 4, 4)``, colour those and the obstacles in ``hits`` red and
        the target ball by ``outcome``."""
        if self.capsules is not None:
            world_frames = frames[list(self.capsules.frames)]
            rot, origin = world_frames[:, None, :3, :3], world_frames[:, None, :3, 3]
            ends = (rot @ self.capsules.points[..., None])[..., 0] + origin  # (K, 2, 3)
            for (name, cap), (a, b) in zip(self.capsule_nodes.items(), ends.numpy()):
                cap.place(a, b)
                for node in cap.nodes:
                    node.color = _HIT_RGB if name in hits else _CAPSULE_RGB
        for name, nodes in self.world_nodes.items():
            for node in nodes:
                node.color = _HIT_RGB if name in hits else _OBSTACLE_RGB
        self.target_marker.color = _IDLE_RGB if outcome is None else _TARGET_RGB.get(outcome, _HIT_RGB)

    def draw_trace(self, tip: np.ndarray, goal: np.ndarray | None) -> None:
        """A playback path's end-effector trace ``tip (T, 3)`` m, and its ``goal (3,)`` if any."""
        if self.trace is not None:
            self.trace.remove()
        segments = np.stack([tip[:-1], tip[1:]], 1) if len(tip) > 1 else np.stack([tip, tip], 1)
        self.trace = self.server.scene.add_line_segments(
            "/playback/trace", segments, colors=_TRACE_COLOUR, thickness=0.004 * self.reach
        )
        if goal is not None:
            self.goal_marker.position = goal
            self.goal_marker.visible = True
