"""Interactive web viewer of a chain (viser): joint sliders, a pose readout, a draggable IK target.

:func:`show` serves a page (default http://127.0.0.1:8080) with the arm drawn as cylinders
between consecutive frame origins and one short cylinder per joint along its axis, over a
floor grid. The side panel has one slider per joint (degrees, within the joint's limits),
the end-effector pose (xyz in metres, roll-pitch-yaw in degrees, ``R = Rz Ry Rx``), a
checkbox that shows every frame, and the IK status. Dragging the target gizmo solves the
gradient IK (:func:`iiwa_torch.ik.solve`) seeded from the current angles; an unreachable
target leaves the arm at the solver's best answer and says so.

:class:`Viewer` holds the state, so it can be driven and checked without a browser.
viser is imported here only, never when ``iiwa_torch`` is imported.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np
import torch

from . import ik, so3
from .dh import Convention, DHChain

__all__ = ["Readout", "Viewer", "show"]

_LINK_COLOUR = (170, 175, 185)
_JOINT_COLOUR = (240, 130, 30)
_MIN_SEGMENT = 1e-6  # metres: consecutive frame origins closer than this get no link cylinder


@dataclass(frozen=True)
class Readout:
    """End-effector pose as shown in the panel: ``xyz`` metres, ``rpy_deg`` roll, pitch, yaw in degrees."""

    xyz: tuple[float, float, float]
    rpy_deg: tuple[float, float, float]

    def text(self) -> str:
        x, y, z = self.xyz
        r, p, w = self.rpy_deg
        return f"xyz (m): {x:+.4f} {y:+.4f} {z:+.4f}  \nrpy (deg): {r:+.2f} {p:+.2f} {w:+.2f}"


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


class Viewer:
    """A running viser server showing ``chain`` at ``q`` (default: the middle of the limits).

    Args:
        chain: the robot (its float64 buffers are used; results follow its device).
        q: ``(n,)`` initial joint angles in radians, within the limits.
        host, port: where the server listens (``127.0.0.1``: this machine only).

    The state is guarded by a lock: GUI callbacks run on viser's thread pool.
    """

    def __init__(self, chain: DHChain, q: torch.Tensor | None = None, host: str = "127.0.0.1", port: int = 8080):
        import viser

        if not isinstance(chain, DHChain):
            raise TypeError(f"chain must be a DHChain, got {type(chain).__name__}")
        self.chain = chain
        self._lock = threading.RLock()
        self._syncing = False  # set while set_q writes the sliders, whose callbacks then do nothing
        self._target_seq = 0
        self._limits = chain.limits.to(torch.float64)
        q = self._limits.mean(0) if q is None else q
        self._q = self._checked(q)
        self.status = "drag the target gizmo"

        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self._build_scene()
        self._build_gui()
        self._draw(move_target=True)

    # ------------------------------------------------------------------ state
    @property
    def q(self) -> torch.Tensor:
        """``(n,)`` current joint angles, radians (a copy)."""
        return self._q.clone()

    def _checked(self, q) -> torch.Tensor:
        n = self.chain.n_joints
        if not isinstance(q, torch.Tensor):
            raise TypeError(f"q must be a torch.Tensor of shape ({n},), got {type(q).__name__}")
        if q.shape != (n,):
            raise ValueError(f"q must have shape ({n},), got {tuple(q.shape)}")
        q = q.detach().to(torch.float64, copy=True)
        self.chain.check_q(q)
        if not bool(self.chain.within_limits(q, tol=1e-9)):
            raise ValueError(f"q must be within the joint limits {self._limits.tolist()}, got {q.tolist()}")
        return self.chain.clamp(q)

    def set_q(self, q: torch.Tensor, move_target: bool = True) -> None:
        """Show the arm at ``q (n,)`` radians (within the limits); the sliders and the readout follow,
        and the target gizmo jumps to the new end-effector pose unless ``move_target`` is False."""
        q = self._checked(q)
        with self._lock:
            self._q = q
            self._draw(move_target)

    def readout(self) -> Readout:
        """The end-effector pose at the current angles, as the panel shows it."""
        with torch.no_grad():
            pose = self.chain.fk(self._q)
        rpy = torch.rad2deg(so3.matrix_to_rpy(pose[:3, :3]))
        return Readout(tuple(pose[:3, 3].tolist()), tuple(rpy.tolist()))

    def solve_target(self, pose: torch.Tensor) -> ik.IKResult:
        """Solve the IK for ``pose (4, 4)`` (metres, world frame) from the current angles and show
        the answer. ``status`` becomes ``"reached"`` or ``"unreachable"`` plus the errors; the arm
        moves to the solver's best configuration (always finite, within the limits)."""
        so3.check_pose(pose, "pose")
        if pose.shape != (4, 4):
            raise ValueError(f"pose must have shape (4, 4), got {tuple(pose.shape)}")
        pose = pose.detach().to(torch.float64)
        with self._lock:
            result = ik.solve(self.chain, pose, self._q)
            ok = bool(result.success)
            pos_mm, rot_deg = 1000 * float(result.pos_err), math.degrees(float(result.rot_err))
            self.status = f"{'reached' if ok else 'unreachable'} (error {pos_mm:.2f} mm, {rot_deg:.2f} deg)"
            if bool(torch.isfinite(result.q).all()):
                self._q = self.chain.clamp(result.q.to(torch.float64))
            self._draw(move_target=False)
        return result

    def stop(self) -> None:
        """Stop the server (and its threads)."""
        self.server.stop()

    # ------------------------------------------------------------------ drawing
    def _frames(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(n + 1, 4, 4)`` base and link frames and the ``(4, 4)`` end-effector pose at ``q``."""
        with torch.no_grad():
            return self.chain.fk_all(self._q), self.chain.fk(self._q)

    def _origins(self, frames: torch.Tensor, end: torch.Tensor) -> np.ndarray:
        """``(n + 2, 3)`` frame origins, then the end effector (metres)."""
        return torch.cat([frames[:, :3, 3], end[None, :3, 3]]).cpu().numpy()

    def _build_scene(self) -> None:
        chain, scene = self.chain, self.server.scene
        frames, end = self._frames()
        points = self._origins(frames, end)
        lengths = np.linalg.norm(np.diff(points, axis=0), axis=1)  # fixed by the geometry, not by q
        self._segments = np.flatnonzero(lengths > _MIN_SEGMENT)
        reach = max(float(lengths.sum()), 0.1)
        self._reach = reach
        radius = 0.03 * reach
        scene.set_up_direction("+z")
        scene.add_grid("/floor", width=3 * reach, height=3 * reach, cell_size=reach / 10, section_size=reach / 2)
        self._links = [
            scene.add_cylinder(f"/arm/link{i}", radius=radius, height=float(lengths[i]), color=_LINK_COLOUR)
            for i in self._segments
        ]
        # Joint i turns about the z axis of frame i - 1 (standard DH) or of frame i (modified DH).
        first = 0 if chain.convention == Convention.STANDARD else 1
        self._axis_frames = list(range(first, first + chain.n_joints))
        self._joints = [
            scene.add_cylinder(f"/arm/joint{i + 1}", radius=1.5 * radius, height=5 * radius, color=_JOINT_COLOUR)
            for i in range(chain.n_joints)
        ]
        axes = dict(axes_length=0.12 * reach, axes_radius=0.006 * reach)
        self._frame_nodes = [scene.add_frame(f"/frames/f{i}", visible=False, **axes) for i in range(chain.n_joints + 1)]
        self._frame_nodes.append(scene.add_frame("/frames/end", visible=False, **axes))
        self._end_node = scene.add_frame("/end_effector", axes_length=0.08 * reach, axes_radius=0.008 * reach)
        self._target = scene.add_transform_controls("/target", scale=0.25 * reach)
        self._target.on_update(self._on_target)
        cam = self.server.initial_camera
        cam.position = (1.1 * reach, -1.2 * reach, 0.8 * reach)
        cam.look_at = (0.1 * reach, 0.0, 0.4 * reach)

    def _build_gui(self) -> None:
        gui = self.server.gui
        gui.add_markdown(f"**{self.chain.name}**: drag the target or move the sliders")
        self.sliders = []  # one viser slider per joint, degrees; assigning a value moves that joint
        for i, name in enumerate(self.chain.joint_names):
            lo, hi = (math.degrees(v) for v in self._limits[:, i].tolist())
            slider = gui.add_slider(f"{name} (deg)", min=lo, max=hi, step=0.1, initial_value=(lo + hi) / 2)
            slider.on_update(self._slider_callback(i))
            self.sliders.append(slider)
        self._readout_md = gui.add_markdown("")
        self._status_md = gui.add_markdown("")
        self._show_frames = gui.add_checkbox("show frames", False)
        self._show_frames.on_update(lambda _: self._set_frames_visible(self._show_frames.value))

    def _slider_callback(self, i: int):
        def on_slider(_event) -> None:
            with self._lock:
                if self._syncing:
                    return
                q = self._q.clone()
                q[i] = math.radians(self.sliders[i].value)
                self._q = self.chain.clamp(q)
                self._draw(move_target=True)

        return on_slider

    def _on_target(self, event) -> None:
        self.drag_target(event.target.wxyz, event.target.position)

    def drag_target(self, wxyz, position) -> None:
        """What a drag of the target gizmo does: :meth:`solve_target` for the pose with quaternion
        ``wxyz (4,)`` (w, x, y, z) and ``position (3,)`` metres, unless a newer drag came meanwhile.

        Drag updates arrive faster than solves end: each call records its turn and only the
        newest one still waiting when the lock frees is solved.
        """
        wxyz, position = np.asarray(wxyz, dtype=np.float64), np.asarray(position, dtype=np.float64)
        if wxyz.shape != (4,) or position.shape != (3,) or not np.isfinite(np.r_[wxyz, position]).all():
            raise ValueError(f"wxyz must be 4 and position 3 finite numbers, got {wxyz.tolist()}, {position.tolist()}")
        if not np.linalg.norm(wxyz) > 1e-9:
            raise ValueError(f"wxyz must be a nonzero quaternion, got {wxyz.tolist()}")
        with self._lock:
            self._target_seq += 1
            seq = self._target_seq
        pose = torch.eye(4, dtype=torch.float64)
        pose[:3, :3] = so3.quaternion_to_matrix(torch.as_tensor(wxyz))
        pose[:3, 3] = torch.as_tensor(position)
        with self._lock:
            if seq == self._target_seq:
                self.solve_target(pose)

    def _set_frames_visible(self, visible: bool) -> None:
        for node in self._frame_nodes:
            node.visible = visible

    def _draw(self, move_target: bool) -> None:
        """Send the arm, sliders, readout and status for the current ``q``."""
        frames, end = self._frames()
        points = self._origins(frames, end)
        starts, stops = points[self._segments], points[self._segments + 1]
        directions = stops - starts
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        quats = _segment_quaternions(directions)
        frame_quats = _quaternions(torch.cat([frames[:, :3, :3], end[None, :3, :3]]))
        with self.server.atomic():
            for node, a, b, quat in zip(self._links, starts, stops, quats):
                node.position, node.wxyz = (a + b) / 2, quat
            for node, f in zip(self._joints, self._axis_frames):
                node.position, node.wxyz = points[f], frame_quats[f]
            for node, p, quat in zip(self._frame_nodes, points, frame_quats):
                node.position, node.wxyz = p, quat
            self._end_node.position, self._end_node.wxyz = points[-1], frame_quats[-1]
            if move_target:
                self._target.position, self._target.wxyz = points[-1], frame_quats[-1]
            self._syncing = True
            try:
                for slider, angle in zip(self.sliders, torch.rad2deg(self._q).tolist()):
                    slider.value = min(max(round(angle, 1), slider.min), slider.max)
            finally:
                self._syncing = False
            self._readout_md.content = self.readout().text()
            self._status_md.content = f"IK: {self.status}"


def show(chain: DHChain, q: torch.Tensor | None = None, host: str = "127.0.0.1", port: int = 8080, block: bool = True):
    """Serve the viewer of ``chain`` at ``http://host:port``.

    ``q`` is the first configuration (radians, default mid-limits). ``host="0.0.0.0"`` makes
    it reachable from other machines. With ``block=True`` it runs until Ctrl-C, then stops
    the server and returns None; with ``block=False`` it returns the running :class:`Viewer`
    (call its ``stop()``).
    """
    viewer = Viewer(chain, q, host=host, port=port)
    if not block:
        return viewer
    try:
        print(f"iiwa-torch viewer of {chain.name} at http://{host}:{port} (Ctrl-C to stop)", flush=True)
        threading.Event().wait()
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()
    return None
