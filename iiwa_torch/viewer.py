"""Interactive web viewer of any chain (viser): joint sliders, a pose readout, a draggable IK
target, obstacles and clearance, playback of joint paths.

:func:`show` serves a page (default http://127.0.0.1:8080) with the arm drawn as cylinders
between consecutive frame origins and one short cylinder per joint along its axis (the
skeleton), over a floor grid, and optionally an obstacle :class:`~iiwa_torch.collision.World`,
the robot's collision capsules and its frames. A chain read from a URDF file (``urdf=``) is
drawn with the file's ``<visual>`` meshes and shapes (:func:`iiwa_torch.urdf.read_visuals`,
meshes read by trimesh), or with its fitted capsules if it has none. The side panel has one
slider per joint (degrees, metres for a prismatic joint, within the joint's limits), the
end-effector pose (xyz in metres, roll-pitch-yaw in degrees, ``R = Rz Ry Rx``), the clearance,
the IK controls and status, and a player for paths.

Dragging the target gizmo solves its pose by the gradient IK (:func:`iiwa_torch.ik.solve`)
or, for an arm whose joint axes admit one (the iiwa and other S-R-S arms, 6R arms with a
spherical wrist: :func:`iiwa_torch.ik.analytic.structure`), by the closed form (a chosen branch
or the nearest one; for an S-R-S arm a held arm angle or the nearest one). A target that
cannot be reached within the limits, or only in collision, is coloured and named as such and
the arm keeps its last valid configuration.

:class:`Viewer` holds the state, so it can be driven and checked without a browser.
viser is imported here only, never when ``iiwa_torch`` is imported.
"""

from __future__ import annotations

import contextlib
import errno
import io
import ipaddress
import json
import math
import numbers
import os
import re
import socket
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from . import capsule_fit, collision, ik, so3
from . import urdf as urdf_io
from .chain import Chain, JointKind, z_onto
from .checks import check_bool, check_float_tensor, check_positive, require
from .dh import Convention, DHChain
from .ik import analytic

__all__ = ["OUTCOMES", "Readout", "TargetResult", "Viewer", "load_world", "show"]

_F64 = torch.float64
_LINK_COLOUR = (170, 175, 185)
_JOINT_COLOUR = (240, 130, 30)
_OBSTACLE_COLOUR = (90, 140, 200)
_CAPSULE_COLOUR = (60, 180, 120)
_HIT_COLOUR = (220, 30, 30)
_TARGET_COLOURS = {"reached": (40, 180, 60), "colliding": (250, 170, 0)}  # anything else: _HIT_COLOUR
_MIN_SEGMENT = 1e-6  # metres: consecutive frame origins closer than this get no link cylinder
_ARM_ANGLES = 72  # analytic IK with a free arm angle: candidates every 5 degrees, plus the current one
_BRANCH_LABELS = tuple(f"{k} {'+-'[k >> 2 & 1]}{'+-'[k >> 1 & 1]}{'+-'[k & 1]}" for k in range(8))
OUTCOMES = ("reached", "unreachable", "outside the joint limits", "colliding")
_LABEL = r"[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
_HOSTNAME = re.compile(rf"(?:{_LABEL}\.)*{_LABEL}\.?")  # RFC 1123 host name syntax


@dataclass(frozen=True)
class Readout:
    """End-effector pose as shown in the panel: ``xyz`` metres, ``rpy_deg`` roll, pitch, yaw in degrees."""

    xyz: tuple[float, float, float]
    rpy_deg: tuple[float, float, float]

    def text(self) -> str:
        x, y, z = self.xyz
        r, p, w = self.rpy_deg
        return f"xyz (m): {x:+.4f} {y:+.4f} {z:+.4f}  \nrpy (deg): {r:+.2f} {p:+.2f} {w:+.2f}"


@dataclass(frozen=True)
class TargetResult:
    """What a target solve did.

    Attributes:
        outcome: one of :data:`OUTCOMES`; only ``"reached"`` moves the arm.
        q: ``(n,)`` the configuration shown afterwards (radians; the previous one unless reached).
        pos_err, rot_err: of the best candidate against the target (m, rad).
        clearance: of the best candidate (m, negative in collision), None without a capsule model.
    """

    outcome: str
    q: torch.Tensor
    pos_err: float
    rot_err: float
    clearance: float | None


def load_world(spec) -> collision.World:
    """An obstacle world from a dict, a JSON text (starting with ``{``) or a JSON file path.

    Keys, all optional (metres; angles in degrees): ``floor`` (height, or null for none;
    default 0), ``spheres`` ``[[x, y, z, r], ...]``, ``boxes`` ``[[x, y, z, hx, hy, hz], ...]``
    (centre and half extents, optionally followed by roll, pitch, yaw), ``capsules``
    ``[[x1, y1, z1, x2, y2, z2, r], ...]``, ``walls`` ``[[nx, ny, nz, offset], ...]`` (free
    space ``n . x >= offset``; ``n`` is normalised).
    """
    if isinstance(spec, (str, Path)):
        text = str(spec)
        if not text.lstrip().startswith("{"):
            path = Path(text)
            if not path.is_file():
                raise ValueError(f"world {text!r} is neither a JSON object nor an existing file")
            text = path.read_text()
        try:
            spec = json.loads(text)
        except json.JSONDecodeError as err:
            raise ValueError(f"world: invalid JSON ({err})") from None
    if not isinstance(spec, dict):
        raise TypeError(f"world must be a dict, JSON text or file path, got {type(spec).__name__}")
    known = {"floor", "spheres", "boxes", "capsules", "walls"}
    if set(spec) - known:
        raise ValueError(f"world: unknown keys {sorted(set(spec) - known)}; known: {sorted(known)}")

    def rows(kind: str, widths: tuple[int, ...]) -> torch.Tensor | None:
        items = spec.get(kind)
        if not items:
            return None
        if not isinstance(items, (list, tuple)):
            raise ValueError(f"world: {kind} must be a list of rows of numbers, got {items!r}")
        bad = [row for row in items if not isinstance(row, (list, tuple)) or len(row) not in widths]
        if bad:
            raise ValueError(f"world: each of {kind} needs {' or '.join(map(str, widths))} numbers, got {bad[0]}")
        if any(isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Real) for row in items for v in row):
            raise ValueError(f"world: {kind} must hold numbers, got {items}")
        width = max(len(row) for row in items)
        return torch.tensor([list(row) + [0.0] * (width - len(row)) for row in items], dtype=_F64)

    kwargs = {"floor": spec.get("floor", 0.0)}
    if (s := rows("spheres", (4,))) is not None:
        kwargs["spheres"] = (s[:, :3].contiguous(), s[:, 3].contiguous())
    if (b := rows("boxes", (6, 9))) is not None:
        pose = torch.eye(4, dtype=_F64).repeat(len(b), 1, 1)
        pose[:, :3, 3] = b[:, :3]
        if b.shape[1] == 9:
            pose[:, :3, :3] = so3.rpy_to_matrix(torch.deg2rad(b[:, 6:9]))
        kwargs["boxes"] = (pose, b[:, 3:6].contiguous())
    if (c := rows("capsules", (7,))) is not None:
        kwargs["capsules"] = (c[:, :6].reshape(-1, 2, 3), c[:, 6].contiguous())
    if (w := rows("walls", (4,))) is not None:
        norm = w[:, :3].norm(dim=-1, keepdim=True)
        if not bool((norm > 1e-9).all()):
            raise ValueError(f"world: a wall normal must be nonzero, got {w[:, :3].tolist()}")
        kwargs["walls"] = (w[:, :3] / norm, w[:, 3].contiguous())
    return collision.World(**kwargs)


def _listen_address(host, port) -> tuple[str, bool]:
    """``(host, loopback)``: where the server can listen, checked before viser starts (viser
    moves on from any port it cannot bind, and waits forever when it binds none).

    ``host`` '' or None means 127.0.0.1; otherwise an IP address or a host name of this machine.
    ``port`` 0..65535, 0 for any free port; a busy port is left to viser, which takes the next
    free one. ``loopback`` is False if the server would be reachable from other machines.
    ValueError/TypeError for a malformed host or port, ValueError when it cannot be listened on.
    """
    host = "127.0.0.1" if host is None or host == "" else host
    if not isinstance(host, str):
        raise TypeError(f"host must be a str (an IP address or host name), got {type(host).__name__}")
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise ValueError(f"port must be an integer in 0..65535 (0: any free port), got {port!r}")
    try:
        ipaddress.ip_address(host)
    except ValueError:
        if not _HOSTNAME.fullmatch(host) or host.rstrip(".").rsplit(".", 1)[-1].isdigit():
            raise ValueError(f"host must be an IP address or a host name, got {host!r}") from None
    try:
        addresses = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as err:
        raise ValueError(f"host {host!r} is not known: {err.strerror}") from None
    for family, kind, proto, _, address in addresses:
        with socket.socket(family, kind, proto) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server will
            try:
                probe.bind(address)
            except OSError as err:
                if err.errno != errno.EADDRINUSE:
                    raise ValueError(f"cannot serve on host {host!r}, port {port}: {err.strerror}") from None
    return host, all(ipaddress.ip_address(a[4][0]).is_loopback for a in addresses)


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


def _unbatched(world: collision.World) -> collision.World:
    """``world`` in float64 on the CPU; ValueError if it holds a batch of obstacle sets."""
    parts = {}
    for kind, lead in (("walls", 2), ("spheres", 2), ("boxes", 3), ("capsules", 3)):
        pair = getattr(world, kind)
        if pair is not None:
            if pair[0].ndim != lead:
                raise ValueError(f"the viewer draws one obstacle set: {kind}[0] must have {lead} dims, "
                                 f"got shape {tuple(pair[0].shape)}")  # fmt: skip
            parts[kind] = tuple(t.detach().to("cpu", _F64) for t in pair)
    return collision.World(floor=world.floor, **parts)


class _Capsule:
    """A capsule drawn as a cylinder and two end spheres."""

    def __init__(self, scene, name: str, radius: float, colour, opacity: float | None, visible: bool = True):
        opts = dict(color=colour, opacity=opacity, visible=visible)
        self.body = scene.add_cylinder(f"{name}/body", radius=radius, height=1.0, **opts)
        self.ends = [scene.add_icosphere(f"{name}/end{i}", radius=radius, subdivisions=2, **opts) for i in range(2)]
        self.nodes = [self.body, *self.ends]

    def place(self, a: np.ndarray, b: np.ndarray) -> None:
        mid, quat, length = _segment_placement(a[None], b[None])
        self.body.position, self.body.wxyz = mid[0], quat[0]
        self.body.scale = (1.0, 1.0, max(float(length[0]), _MIN_SEGMENT))
        self.ends[0].position, self.ends[1].position = a, b


def _urdf_parts(chain: Chain, source, capsules: collision.Capsules | None):
    """The ``<visual>`` elements of the URDF ``source`` that ``chain`` was read from (its root as
    the base) with their meshes loaded, ``[(element, trimesh or None)]``, and ``capsules`` or, if
    None, those fitted to its ``<collision>`` geometry (None if it has none)."""
    path = urdf_io.read_urdf(source, end_link=chain.link_names[-1])
    if [j.name for j in path.joints] != list(chain.joint_names):
        raise ValueError(f"chain {chain.name!r} is not the path of urdf {os.fspath(source)!r} from its root link "
                         f"{path.base_link!r}: pass the chain robots.from_urdf reads from the file")  # fmt: skip
    visuals = [(e, e.load_mesh() if e.shape == "mesh" else None) for e in urdf_io.read_visuals(source, path.end_link)]
    if capsules is None and urdf_io.read_collisions(source, end_link=path.end_link):  # after the quick checks
        capsules = capsule_fit.urdf_capsules(chain, source)
    return visuals, capsules


def _add_visual(scene, name: str, element: urdf_io.UrdfCollision, mesh):
    """A scene node of a URDF ``<visual>`` element, in its own frame: its material colour if it
    names one, else a mesh's own colours (or grey)."""
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


class Viewer:
    """A running viser server showing ``chain`` at ``q`` (default: the middle of the limits).

    Args:
        chain: the robot, any :class:`~iiwa_torch.chain.Chain` (its float64 buffers are used).
        q: ``(n,)`` initial joint values in radians (metres for prismatic joints), within the
            limits (default: their middle; 0 for a continuous joint).
        host, port: where the server listens: ``127.0.0.1`` (also for '' or None) is this
            machine only; any other address warns on stderr, as anyone who reaches the port
            controls the viewer. Port 0 takes any free port, and a busy one the next free one.
        world: obstacles to draw and to check the clearance against (one set, no batch
            dimension; see :func:`load_world`); None: the capsule model's own floor.
        capsules: the robot's collision model (default: :func:`~iiwa_torch.collision.robot_capsules`
            of a preset, :func:`~iiwa_torch.capsule_fit.urdf_capsules` of ``urdf``; no
            clearance for other chains unless given).
        urdf: the URDF file ``chain`` was read from (:func:`~iiwa_torch.robots.from_urdf`, from
            its root link): its ``<visual>`` elements are drawn (links past off-path prismatic
            joints, a gripper's fingers, at those joints' lower limits) and the skeleton hidden (a
            panel checkbox shows it); a file without visuals shows its capsules.
        show_capsules, show_frames: draw the collision capsules, every link frame (also
            checkboxes in the panel).

    Attributes ``host`` and ``port`` say where it listens (the port actually bound).
    The state is guarded by a lock: GUI callbacks run on viser's thread pool.
    """

    def __init__(
        self,
        chain: Chain,
        q: torch.Tensor | None = None,
        host: str = "127.0.0.1",
        port: int = 8080,
        *,
        world: collision.World | None = None,
        capsules: collision.Capsules | None = None,
        urdf: str | os.PathLike | None = None,
        show_capsules: bool = False,
        show_frames: bool = False,
    ):
        viser = require("viser", "viewer")
        _check_options(chain, world, capsules, show_capsules, show_frames)
        host, loopback = _listen_address(host, port)
        self.chain = chain
        self._lock = threading.RLock()
        self._syncing = False  # set while the viewer writes its own widgets, whose callbacks then do nothing
        self._target_seq = 0
        self._limits = chain.limits.to(_F64)
        self._q = self._checked(self._limits.nan_to_num(posinf=math.pi, neginf=-math.pi).mean(0) if q is None else q)
        self._visuals = []  # [(URDF <visual> element, its trimesh or None)], read before the server starts
        if urdf is not None:
            self._visuals, capsules = _urdf_parts(chain, urdf, capsules)
            show_capsules = show_capsules or not self._visuals  # no visuals: the capsules are the body
        self.capsules = _preset_capsules(chain, world) if capsules is None else capsules
        self.world = None if world is None else _unbatched(world)
        self._analytic, self._dh, self._signs = self._closed_form()
        self._method, self._branch, self._arm_angle = "gradient", None, None
        self.status = "drag the target gizmo"
        self.outcome: str | None = None
        self._target_pose = chain.fk(self._q).to(_F64)
        self._paths: torch.Tensor | None = None
        self._goals: np.ndarray | None = None
        self._dt = 0.05
        self._path_index, self._step = 0, 0
        self._playing = threading.Event()
        self._closing = threading.Event()
        self._player: threading.Thread | None = None

        with contextlib.redirect_stdout(io.StringIO()):  # viser's own banner: show() prints the address once
            self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.host, self.port = host, self.server.get_port()
        if not loopback:
            print(f"warning: the viewer on {host} has no login: anyone who can reach port {self.port} controls it",
                  file=sys.stderr)  # fmt: skip
        try:
            self._build_scene(show_capsules, show_frames)
            self._build_gui(show_capsules, show_frames)
            self._draw(move_target=True)
        except BaseException:  # also Ctrl-C: the server's threads must not outlive a half-built viewer
            self.server.stop()
            raise

    # ------------------------------------------------------------------ state
    @property
    def q(self) -> torch.Tensor:
        """``(n,)`` current joint angles, radians (a copy)."""
        return self._q.clone()

    def _checked(self, q, name: str = "q") -> torch.Tensor:
        n = self.chain.n_joints
        if not isinstance(q, torch.Tensor):
            raise TypeError(f"{name} must be a torch.Tensor of shape ({n},), got {type(q).__name__}")
        if q.shape != (n,):
            raise ValueError(f"{name} must have shape ({n},), got {tuple(q.shape)}")
        q = q.detach().to("cpu", _F64, copy=True)
        self.chain.check_q(q, name)
        if not bool(self.chain.within_limits(q, tol=1e-9)):
            raise ValueError(f"{name} must be within the joint limits {self._limits.tolist()}, got {q.tolist()}")
        return self.chain.clamp(q)

    def set_q(self, q: torch.Tensor, move_target: bool = True) -> None:
        """Show the arm at ``q (n,)`` radians (within the limits); the sliders and the readout follow,
        and the target gizmo jumps to the new end-effector pose unless ``move_target`` is False."""
        q = self._checked(q)
        check_bool(move_target, "move_target")
        with self._lock:
            self._q = q
            self._draw(move_target)

    def readout(self) -> Readout:
        """The end-effector pose at the current angles, as the panel shows it."""
        with torch.no_grad():
            pose = self.chain.fk(self._q)
        rpy = torch.rad2deg(so3.matrix_to_rpy(pose[:3, :3]))
        return Readout(tuple(pose[:3, 3].tolist()), tuple(rpy.tolist()))

    def clearance(self, q: torch.Tensor | None = None) -> tuple[float, tuple[str, str]] | None:
        """Smallest signed distance (m, negative in collision) at ``q (n,)`` (default the current
        angles) and the names of its pair (:func:`~iiwa_torch.collision.pairwise_clearance`);
        None without a capsule model."""
        result = self._pairwise(self._q if q is None else q)
        if result is None:
            return None
        k = int(result.distance.argmin())
        return float(result.distance[k]), result.pairs[k]

    def _pairwise(self, q: torch.Tensor) -> collision.Clearances | None:
        if self.capsules is None:
            return None
        with torch.no_grad():
            return collision.pairwise_clearance(self.chain, q.to(_F64), self.world, self.capsules)

    # ------------------------------------------------------------------ IK
    def _closed_form(self) -> tuple[str | None, DHChain | None, torch.Tensor | None]:
        """The chain's closed form: ``"iiwa"`` (S-R-S) or ``"pieper"``, the DH chain it runs on and
        ``(n,)`` signs (``q_dh = signs * q``); a DH preset's own table and branches, else those of
        :func:`~iiwa_torch.ik.analytic.structure`. ``(None, None, None)`` if there is none."""
        n = self.chain.n_joints
        if n not in (6, 7):
            return None, None, None
        kind = "iiwa" if n == 7 else "pieper"
        if isinstance(self.chain, DHChain):
            pose = self.chain.fk(self._q)
            try:
                if n == 7:
                    analytic.iiwa(self.chain, pose, 0.0)
                else:
                    analytic.pieper(self.chain, pose)
                return kind, self.chain, torch.ones(n, dtype=_F64)
            except ValueError:  # its table has other rows than the closed form needs: try its axes
                pass
        try:
            found = analytic.structure(self.chain)
        except ValueError:  # its axes admit no closed form
            return None, None, None
        return kind, found.dh, found.signs

    def _current_arm_angle(self) -> torch.Tensor:
        """The S-R-S arm angle (rad, a 0-dim tensor) of the current angles, in the closed form's DH chain."""
        return analytic.iiwa_arm_angle(self._dh, self._q * self._signs)

    @property
    def ik_methods(self) -> tuple[str, ...]:
        """The IK methods this chain offers: ``"gradient"``, and ``"analytic"`` where a closed form exists."""
        return ("gradient", "analytic") if self._analytic else ("gradient",)

    def set_ik(self, method: str, branch: int | None = None, arm_angle: float | None = None) -> None:
        """Choose how targets are solved (also the panel's IK controls).

        Args:
            method: ``"gradient"`` or ``"analytic"`` (see :attr:`ik_methods`).
            branch: analytic only: 0..7 (``k = 4 shoulder + 2 elbow + wrist`` of
                :func:`~iiwa_torch.ik.analytic.iiwa`/``pieper``), or None for the valid branch
                nearest the current angles.
            arm_angle: iiwa analytic only: the arm angle ``psi`` held (radians), or None to
                take the nearest solution over the whole circle.
        """
        if method not in self.ik_methods:
            raise ValueError(f"method must be one of {list(self.ik_methods)} for {self.chain.name}, got {method!r}")
        if branch is not None and (isinstance(branch, bool) or branch not in range(8)):
            raise ValueError(f"branch must be None or an int 0..7, got {branch!r}")
        if arm_angle is not None:
            if self._analytic != "iiwa":
                raise ValueError(f"an arm angle applies to S-R-S arms like the iiwa only, not to {self.chain.name}")
            if isinstance(arm_angle, bool) or not isinstance(arm_angle, (int, float)) or not math.isfinite(arm_angle):
                raise ValueError(f"arm_angle must be a finite number of radians or None, got {arm_angle!r}")
        with self._lock:
            self._method, self._branch = method, branch
            self._arm_angle = None if arm_angle is None else math.remainder(float(arm_angle), 2 * math.pi)
            self._sync_ik_widgets()

    def solve_target(self, pose: torch.Tensor) -> TargetResult:
        """Solve the IK for ``pose (4, 4)`` (metres, world frame) with the chosen method, from the
        current angles. Only a solution within the limits, within 0.1 mm / 1 mrad and free of
        collision moves the arm; otherwise it keeps its angles and ``outcome`` says why."""
        so3.check_pose(pose, "pose")
        if pose.shape != (4, 4):
            raise ValueError(f"pose must have shape (4, 4), got {tuple(pose.shape)}")
        pose = pose.detach().to("cpu", _F64)
        with self._lock:
            self._target_pose = pose
            candidates, outcome = self._candidates(pose)
            result = self._choose(pose, candidates, outcome)
            self.outcome = result.outcome
            self.status = self._status_text(result)
            self._q = result.q.clone()
            self._draw(move_target=False)
        return result

    def _candidates(self, pose: torch.Tensor) -> tuple[torch.Tensor, str | None]:
        """``(m, n)`` candidate configurations within the limits that reproduce ``pose``, or the
        best attempt ``(1, n)`` and the outcome that rules it out."""
        if self._method == "gradient":
            result = ik.solve(self.chain, pose, self._q)
            q = result.q.to(_F64)[None]
            ok = bool(result.success) and bool(self.chain.within_limits(q[0], tol=1e-9))
            return self.chain.clamp(q), None if ok else "unreachable"
        if self._analytic == "iiwa":
            if self._arm_angle is None:
                grid = torch.linspace(-math.pi, math.pi, _ARM_ANGLES + 1, dtype=_F64)[:-1]
                psi = torch.cat([self._current_arm_angle()[None], grid])
            else:
                psi = torch.tensor([self._arm_angle], dtype=_F64)
            sol = analytic.iiwa(self._dh, pose, psi)  # q (K, 8, 7), of the DH chain
        else:
            sol = analytic.pieper(self._dh, pose)  # q (8, 6)
        n = self.chain.n_joints
        q = (sol.q * self._signs).reshape(-1, 8, n)
        reachable, within = sol.reachable.reshape(-1, 8), sol.within_limits.reshape(-1, 8)
        if self._branch is not None:
            q, reachable, within = q[:, self._branch], reachable[:, self._branch], within[:, self._branch]
        q, reachable, within = q.reshape(-1, n), reachable.reshape(-1), within.reshape(-1)
        valid = reachable & within
        if bool(valid.any()):
            return q[valid], None
        if bool(reachable.any()):
            return self.chain.clamp(q[reachable][:1]), "outside the joint limits"
        return self.chain.clamp(q[:1]), "unreachable"

    def _choose(self, pose: torch.Tensor, q: torch.Tensor, outcome: str | None) -> TargetResult:
        """The candidate nearest the current angles among the collision-free ones (all of them
        without a capsule model) as a :class:`TargetResult`; the arm keeps its angles unless reached."""
        cost = (q - self._q).square().sum(-1)
        gaps = None
        if self.capsules is not None:
            with torch.no_grad():
                gaps = collision.clearance(self.chain, q, self.world, self.capsules)
            if outcome is None and not bool((gaps >= 0).any()):
                outcome = "colliding"
            cost = torch.where(gaps >= 0, cost, torch.inf) if outcome is None else -gaps  # else the least colliding
        k = int(cost.argmin())
        pos_vec, rot_vec = so3.pose_error(self.chain.fk(q[k]), pose)
        pos_err, rot_err = float(pos_vec.norm()), float(rot_vec.norm())
        if outcome is None and (pos_err > 1e-4 or rot_err > 1e-3):
            outcome = "unreachable"
        outcome = outcome or "reached"
        shown = q[k].clone() if outcome == "reached" else self._q.clone()
        return TargetResult(outcome, shown, pos_err, rot_err, None if gaps is None else float(gaps[k]))

    @staticmethod
    def _status_text(result: TargetResult) -> str:
        text = f"{result.outcome} (error {1000 * result.pos_err:.2f} mm, {math.degrees(result.rot_err):.2f} deg"
        if result.clearance is not None:
            text += f", clearance {1000 * result.clearance:+.1f} mm"
        return text + ")"

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
        pose = torch.eye(4, dtype=_F64)
        pose[:3, :3] = so3.quaternion_to_matrix(torch.as_tensor(wxyz))
        pose[:3, 3] = torch.as_tensor(position)
        with self._lock:
            if seq == self._target_seq:
                self.solve_target(pose)

    # ------------------------------------------------------------------ playback
    def set_path(self, q: torch.Tensor, dt: float = 0.05, goals: torch.Tensor | None = None) -> None:
        """Load joint paths for playback and show their first step.

        Args:
            q: ``(T, n)`` one path or ``(B, T, n)`` B of them (radians, within the limits),
                e.g. ``jtraj(...).q``, ``track(...).q`` or a policy's rollouts.
            dt: seconds between steps.
            goals: optional ``(B, 3)`` positions (m) drawn as a marker with each path.
        """
        check_float_tensor(q, "q", "(T, n) or (B, T, n)")
        n = self.chain.n_joints
        if q.ndim not in (2, 3) or q.shape[-1] != n or q.shape[-2] < 1:
            raise ValueError(f"q must have shape (T, {n}) or (B, T, {n}) with T >= 1, got {tuple(q.shape)}")
        check_positive(dt, "dt")
        paths = q.detach().to("cpu", _F64).reshape(-1, q.shape[-2], n)
        self.chain.check_q(paths, "q")
        if not bool(self.chain.within_limits(paths, tol=1e-6).all()):
            raise ValueError("q must be within the joint limits at every step")
        if goals is not None:
            check_float_tensor(goals, "goals", f"({paths.shape[0]}, 3)")
            if goals.shape != (paths.shape[0], 3):
                raise ValueError(f"goals must have shape ({paths.shape[0]}, 3), one per path, got {tuple(goals.shape)}")
            goals = goals.detach().to("cpu", _F64).numpy()
        with self._lock:
            self.pause()
            self._paths, self._goals, self._dt = self.chain.clamp(paths), goals, float(dt)
            with self._quiet():
                self._time_slider.max = max((paths.shape[1] - 1) * dt, 1e-9)
                self._time_slider.step = dt
                self._path_slider.max = max(paths.shape[0] - 1, 1)
                self._path_slider.visible = paths.shape[0] > 1
            self._player_folder.visible = True
            self.seek(0, 0)

    @property
    def step(self) -> int:
        """The step of the path shown."""
        return self._step

    @property
    def playing(self) -> bool:
        return self._playing.is_set()

    def seek(self, step: int, path: int | None = None) -> None:
        """Show step ``step`` (0..T-1) of path ``path`` (0..B-1, default the current one)."""
        if self._paths is None:
            raise ValueError("no path loaded: call set_path first")
        b, t = self._paths.shape[:2]
        path = self._path_index if path is None else path
        for value, size, name in ((step, t, "step"), (path, b, "path")):
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < size:
                raise ValueError(f"{name} must be an int in [0, {size}), got {value!r}")
        with self._lock:
            if path != self._path_index or self._trace is None:
                self._path_index = path
                self._draw_trace()
            self._step = step
            self._q = self._paths[path, step].clone()
            with self._quiet():
                self._time_slider.value = step * self._dt
                self._path_slider.value = path
            self._draw(move_target=True)

    def play(self) -> None:
        """Step through the path in real time (from the start once the end is shown), looping if
        the panel's loop box is ticked."""
        if self._paths is None:
            raise ValueError("no path loaded: call set_path first")
        with self._lock:
            if self._step == self._paths.shape[1] - 1:
                self.seek(0)
            self._playing.set()
            if self._player is None:
                self._player = threading.Thread(target=self._play_loop, name="viewer-player", daemon=True)
                self._player.start()
            self._play_button.label = "pause"

    def pause(self) -> None:
        with self._lock:
            self._playing.clear()
            self._play_button.label = "play"

    def _play_loop(self) -> None:
        while not self._closing.is_set():
            if not self._playing.wait(timeout=0.2):
                continue
            if self._closing.wait(self._dt):
                return
            with self._lock:
                if not self._playing.is_set() or self._paths is None:
                    continue
                last = self._paths.shape[1] - 1
                if self._step < last:
                    self.seek(self._step + 1)
                elif self._loop.value:
                    self.seek(0)
                else:
                    self.pause()

    def stop(self) -> None:
        """Stop the player and the server (and their threads)."""
        self._closing.set()
        self._playing.clear()
        if self._player is not None:
            self._player.join(timeout=5)
        self.server.stop()

    # ------------------------------------------------------------------ scene
    def _frames(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(n + 1, 4, 4)`` base and link frames and the ``(4, 4)`` end-effector pose at ``q``."""
        with torch.no_grad():
            return self.chain.fk_all(self._q), self.chain.fk(self._q)

    def _origins(self, frames: torch.Tensor, end: torch.Tensor) -> np.ndarray:
        """``(n + 2, 3)`` frame origins, then the end effector (metres)."""
        return torch.cat([frames[:, :3, 3], end[None, :3, 3]]).cpu().numpy()

    def _build_scene(self, show_capsules: bool, show_frames: bool) -> None:
        chain, scene = self.chain, self.server.scene
        frames, end = self._frames()
        points = self._origins(frames, end)
        lengths = np.linalg.norm(np.diff(points, axis=0), axis=1)  # fixed by the geometry, not by q
        self._segments = np.flatnonzero(lengths > _MIN_SEGMENT)
        reach = max(float(lengths.sum()), 0.1)
        self._reach = reach
        radius = 0.03 * reach
        scene.set_up_direction("+z")
        floor = 0.0 if self.world is None or self.world.floor is None else float(self.world.floor)
        scene.add_grid(
            "/floor", width=3 * reach, height=3 * reach, cell_size=reach / 10, section_size=reach / 2,
            position=(0.0, 0.0, floor),
        )  # fmt: skip
        skeleton = dict(visible=not self._visuals)  # inside the meshes where there are some
        self._links = [
            scene.add_cylinder(f"/arm/link{i}", radius=radius, height=float(lengths[i]), color=_LINK_COLOUR, **skeleton)
            for i in self._segments
        ]
        # Joint i turns about the z axis of frame i - 1 (standard DH) or of frame i (modified DH);
        # in any other chain about its axis in its child link's frame i.
        n = chain.n_joints
        if isinstance(chain, DHChain):
            first = 0 if chain.convention == Convention.STANDARD else 1
            self._axis_frames, turns = list(range(first, first + n)), torch.eye(3, dtype=_F64).expand(n, 3, 3)
        else:
            self._axis_frames, turns = list(range(1, n + 1)), torch.stack([z_onto(a) for a in chain.axes.to(_F64)])
        self._axis_turns = turns  # (n, 3, 3): the joint cylinder's z onto the axis, in its frame
        self._joints = [
            scene.add_cylinder(f"/arm/joint{i + 1}", radius=1.5 * radius, height=5 * radius, color=_JOINT_COLOUR,
                               **skeleton)  # fmt: skip
            for i in range(n)
        ]
        self.visual_nodes = [  # (URDF <visual> element, its scene node), placed at every draw
            (element, _add_visual(scene, f"/visuals/{i}_{element.link}", element, mesh))
            for i, (element, mesh) in enumerate(self._visuals)
        ]
        self._visual_frames = [element.frame for element, _ in self._visuals]
        poses = [element.poses[0] for element, _ in self._visuals]  # off-path prismatic joints at their lower limits
        self._visual_poses = torch.tensor(poses, dtype=_F64).reshape(-1, 4, 4)
        axes = dict(axes_length=0.12 * reach, axes_radius=0.006 * reach, visible=show_frames)
        self._frame_nodes = [scene.add_frame(f"/frames/f{i}", **axes) for i in range(chain.n_joints + 1)]
        self._frame_nodes.append(scene.add_frame("/frames/end", **axes))
        self._end_node = scene.add_frame("/end_effector", axes_length=0.08 * reach, axes_radius=0.008 * reach)
        self._target = scene.add_transform_controls("/target", scale=0.25 * reach)
        self._target_marker = scene.add_icosphere("/target/marker", radius=0.025 * reach, color=(150, 150, 150))
        self._target.on_update(lambda event: self.drag_target(event.target.wxyz, event.target.position))
        self.capsule_nodes = {}  # capsule name -> _Capsule, placed at every draw
        if self.capsules is not None:
            for name, r in zip(self.capsules.names, self.capsules.radii.tolist()):
                self.capsule_nodes[name] = _Capsule(scene, f"/capsules/{name}", r, _CAPSULE_COLOUR, 0.45, show_capsules)
        self.world_nodes = self._build_world(scene, reach)
        self._trace = None
        self._goal_marker = scene.add_icosphere(
            "/playback/goal", radius=0.02 * reach, color=(200, 40, 200), visible=False
        )
        cam = self.server.initial_camera
        cam.position = (1.1 * reach, -1.2 * reach, 0.8 * reach)
        cam.look_at = (0.1 * reach, 0.0, 0.4 * reach)

    def _build_world(self, scene, reach: float) -> dict[str, list]:
        """Draw the obstacles; ``{name: [scene handles]}`` with the names of
        :func:`~iiwa_torch.collision.pairwise_clearance` (``floor``, ``sphere0``, ...)."""
        world, nodes = self.world, {}
        if world is None:
            return nodes
        opts = dict(color=_OBSTACLE_COLOUR, opacity=0.6)
        if world.floor is not None:
            thick = 0.01 * reach
            nodes["floor"] = [scene.add_box(
                "/world/floor", dimensions=(3 * reach, 3 * reach, thick), position=(0.0, 0.0, world.floor - thick),
                color=_OBSTACLE_COLOUR, opacity=0.15,
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
                cap = _Capsule(scene, f"/world/capsule{i}", r, _OBSTACLE_COLOUR, 0.6)
                cap.place(ends[0], ends[1])
                nodes[f"capsule{i}"] = cap.nodes
        if world.walls is not None:
            thick = 0.01 * reach
            for i, (n, offset) in enumerate(zip(world.walls[0].numpy(), world.walls[1].tolist())):
                nodes[f"wall{i}"] = [scene.add_box(
                    f"/world/wall{i}", dimensions=(3 * reach, 3 * reach, thick), position=n * (offset - thick / 2),
                    wxyz=_segment_quaternions(n[None])[0], color=_OBSTACLE_COLOUR, opacity=0.25,
                )]  # fmt: skip
        return nodes

    def _draw_trace(self) -> None:
        """The end-effector path of the current playback path, and its goal."""
        if self._trace is not None:
            self._trace.remove()
        with torch.no_grad():
            tip = self.chain.fk(self._paths[self._path_index])[:, :3, 3].numpy()
        segments = np.stack([tip[:-1], tip[1:]], 1) if len(tip) > 1 else np.stack([tip, tip], 1)
        self._trace = self.server.scene.add_line_segments(
            "/playback/trace", segments, colors=(200, 40, 200), thickness=0.004 * self._reach
        )
        if self._goals is not None:
            self._goal_marker.position = self._goals[self._path_index]
            self._goal_marker.visible = True

    # ------------------------------------------------------------------ panel
    def _quiet(self):
        """Context in which the viewer's own widget writes run no callback."""
        viewer = self

        class Quiet:
            def __enter__(self):
                self.before, viewer._syncing = viewer._syncing, True

            def __exit__(self, *exc):
                viewer._syncing = self.before

        return Quiet()

    def _callback(self, action):
        """A widget callback that runs ``action()`` under the lock, unless the viewer itself wrote the widget."""

        def run(_event) -> None:
            with self._lock:
                if not self._syncing:
                    action()

        return run

    def _build_gui(self, show_capsules: bool, show_frames: bool) -> None:
        gui = self.server.gui
        gui.add_markdown(f"**{self.chain.name}**: drag the target or move the sliders")
        self.sliders = []  # one viser slider per joint, degrees (metres); assigning a value moves that joint
        prismatic = [kind is JointKind.PRISMATIC for kind in self.chain.kinds]
        self._slider_scale = torch.tensor([1.0 if p else math.degrees(1.0) for p in prismatic], dtype=_F64)
        self._slider_digits = [3 if p else 1 for p in prismatic]  # rounded to the slider's step
        ranges = self._limits.nan_to_num(posinf=math.pi, neginf=-math.pi) * self._slider_scale  # continuous: a turn
        for i, name in enumerate(self.chain.joint_names):
            lo, hi = ranges[:, i].tolist()
            scale = 10.0 ** self._slider_digits[i]  # the ends rounded inwards to the step, if the range allows
            if math.ceil(lo * scale - 1e-6) <= math.floor(hi * scale + 1e-6):
                lo, hi = math.ceil(lo * scale - 1e-6) / scale, math.floor(hi * scale + 1e-6) / scale
            slider = gui.add_slider(f"{name} ({'m' if prismatic[i] else 'deg'})", min=lo, max=hi,
                                    step=10.0 ** -self._slider_digits[i], initial_value=(lo + hi) / 2)  # fmt: skip
            slider.on_update(self._callback(lambda i=i: self._move_joint(i)))
            self.sliders.append(slider)
        self._readout_md = gui.add_markdown("")
        self._clearance_md = gui.add_markdown("")
        with gui.add_folder("IK target"):
            self._method_dd = gui.add_dropdown("method", self.ik_methods, initial_value="gradient")
            self._branch_dd = gui.add_dropdown("branch", ("nearest", *_BRANCH_LABELS), initial_value="nearest")
            iiwa = self._analytic == "iiwa"
            self._hold_psi = gui.add_checkbox("hold arm angle", False, visible=iiwa)
            self._psi_slider = gui.add_slider("arm angle (deg)", min=-180, max=180, step=0.5, initial_value=0.0,
                                              visible=iiwa)  # fmt: skip
            self._status_md = gui.add_markdown("")
        for widget in (self._method_dd, self._branch_dd, self._hold_psi, self._psi_slider):
            widget.on_update(self._callback(self._ik_widgets_changed))
        self._show_skeleton = gui.add_checkbox("show skeleton", not self._visuals, visible=bool(self._visuals))
        skeleton = self._links + self._joints
        self._show_skeleton.on_update(lambda _: self._set_visible(skeleton, self._show_skeleton.value))
        self._show_frames = gui.add_checkbox("show frames", show_frames)
        self._show_frames.on_update(lambda _: self._set_visible(self._frame_nodes, self._show_frames.value))
        self._show_capsules = gui.add_checkbox(
            "show collision capsules", show_capsules, visible=bool(self.capsule_nodes)
        )
        nodes = [node for cap in self.capsule_nodes.values() for node in cap.nodes]
        self._show_capsules.on_update(lambda _: self._set_visible(nodes, self._show_capsules.value))
        self._player_folder = gui.add_folder("playback", visible=False)
        with self._player_folder:
            self._play_button = gui.add_button("play")
            self._play_button.on_click(lambda _: self.pause() if self.playing else self.play())
            self._loop = gui.add_checkbox("loop", False)
            self._time_slider = gui.add_slider("time (s)", min=0.0, max=1.0, step=0.05, initial_value=0.0)
            self._time_slider.on_update(self._callback(lambda: self.seek(self._time_step())))
            self._path_slider = gui.add_slider("path", min=0, max=1, step=1, initial_value=0, visible=False)
            self._path_slider.on_update(
                self._callback(lambda: self.seek(self._time_step(), int(self._path_slider.value)))
            )
        self._sync_ik_widgets()

    def _time_step(self) -> int:
        return min(max(round(self._time_slider.value / self._dt), 0), self._paths.shape[1] - 1)

    def _move_joint(self, i: int) -> None:
        q = self._q.clone()
        q[i] = self.sliders[i].value / float(self._slider_scale[i])
        self._q = self.chain.clamp(q)
        self._draw(move_target=True)

    def _ik_widgets_changed(self) -> None:
        """The panel's IK controls changed: take them over and re-solve the last target."""
        branch = None if self._branch_dd.value == "nearest" else _BRANCH_LABELS.index(self._branch_dd.value)
        psi = math.radians(self._psi_slider.value) if self._hold_psi.value else None
        self.set_ik(self._method_dd.value, branch, psi if self._analytic == "iiwa" else None)
        self.solve_target(self._target_pose)

    def _sync_ik_widgets(self) -> None:
        with self._quiet():
            self._method_dd.value = self._method
            self._branch_dd.value = "nearest" if self._branch is None else _BRANCH_LABELS[self._branch]
            self._hold_psi.value = self._arm_angle is not None
            if self._arm_angle is not None:
                self._psi_slider.value = math.degrees(self._arm_angle)
            analytic_on = self._method == "analytic"
            self._branch_dd.disabled = not analytic_on
            self._hold_psi.disabled = self._psi_slider.disabled = not analytic_on

    @staticmethod
    def _set_visible(nodes, visible: bool) -> None:
        for node in nodes:
            node.visible = visible

    def _arm_text(self, psi: float) -> str:
        """The S-R-S arm angle ``psi`` (degrees) and branch signs at the current angles (module doc
        of the closed form), in the closed form's DH chain."""
        theta = (self._q * self._signs + self._dh.dh[:, 3].to(_F64))[[1, 3, 5]]
        signs = "".join("+" if math.sin(t) >= 0 else "-" for t in theta.tolist())
        return f"  \narm angle (deg): {psi:+.1f}, branch {signs}"

    def _draw_collisions(self, frames: torch.Tensor, hits: set[str]) -> None:
        """Place the capsules at the link ``frames (n + 1, 4, 4)``; colour the capsules and obstacles
        named in ``hits`` as colliding."""
        if self.capsules is not None:
            world_frames = frames[list(self.capsules.frames)]
            rot, origin = world_frames[:, None, :3, :3], world_frames[:, None, :3, 3]
            ends = (rot @ self.capsules.points[..., None])[..., 0] + origin  # (K, 2, 3)
            for (name, cap), (a, b) in zip(self.capsule_nodes.items(), ends.numpy()):
                cap.place(a, b)
                for node in cap.nodes:
                    node.color = _HIT_COLOUR if name in hits else _CAPSULE_COLOUR
        for name, nodes in self.world_nodes.items():
            for node in nodes:
                node.color = _HIT_COLOUR if name in hits else _OBSTACLE_COLOUR

    def _draw(self, move_target: bool) -> None:
        """Send the arm, sliders, readout, clearance and status for the current ``q``."""
        frames, end = self._frames()
        points = self._origins(frames, end)
        mids, quats, _ = _segment_placement(points[self._segments], points[self._segments + 1])
        frame_quats = _quaternions(torch.cat([frames[:, :3, :3], end[None, :3, :3]]))
        joint_quats = _quaternions(frames[self._axis_frames, :3, :3] @ self._axis_turns)
        visual_poses = frames[self._visual_frames] @ self._visual_poses  # (V, 4, 4)
        visual_points, visual_quats = visual_poses[:, :3, 3].numpy(), _quaternions(visual_poses[:, :3, :3])
        result = self._pairwise(self._q)
        hits = set()
        if result is not None:
            distances = result.distance.tolist()
            hits = {name for pair, d in zip(result.pairs, distances) if d < 0 for name in pair}
            k = int(np.argmin(distances))
            gap = (distances[k], result.pairs[k])
        if move_target:  # the target is back at the end effector: nothing left to report
            self.outcome, self.status = None, "drag the target gizmo"
        with self.server.atomic():
            for node, mid, quat in zip(self._links, mids, quats):
                node.position, node.wxyz = mid, quat
            for node, f, quat in zip(self._joints, self._axis_frames, joint_quats):
                node.position, node.wxyz = points[f], quat
            for (_, node), p, quat in zip(self.visual_nodes, visual_points, visual_quats):
                node.position, node.wxyz = p, quat
            for node, p, quat in zip(self._frame_nodes, points, frame_quats):
                node.position, node.wxyz = p, quat
            self._end_node.position, self._end_node.wxyz = points[-1], frame_quats[-1]
            if move_target:
                self._target.position, self._target.wxyz = points[-1], frame_quats[-1]
                self._target_pose = end.clone()
            self._draw_collisions(frames, hits)
            colour = (150, 150, 150) if self.outcome is None else _TARGET_COLOURS.get(self.outcome, _HIT_COLOUR)
            self._target_marker.color = colour
            with self._quiet():
                for slider, value, digits in zip(self.sliders, (self._q * self._slider_scale).tolist(),
                                                 self._slider_digits):  # fmt: skip
                    slider.value = min(max(round(value, digits), slider.min), slider.max)
            arm = ""
            if self._analytic == "iiwa":
                psi = math.degrees(float(self._current_arm_angle()))
                arm = self._arm_text(psi)
                if self._arm_angle is None:  # the slider follows the arm, so holding starts from here
                    with self._quiet():
                        self._psi_slider.value = psi
            self._readout_md.content = self.readout().text() + arm
            if result is None:
                self._clearance_md.content = "clearance: no capsule model"
            else:
                state = "**COLLIDING**" if gap[0] < 0 else "clearance"
                self._clearance_md.content = f"{state} {1000 * gap[0]:+.1f} mm ({gap[1][0]} - {gap[1][1]})"
            self._status_md.content = f"IK: {self.status}"


def _check_options(chain, world, capsules, show_capsules, show_frames) -> None:
    """:class:`Viewer`'s argument types, checked before anything is built."""
    if not isinstance(chain, Chain):
        raise TypeError(f"chain must be an iiwa_torch Chain (a preset or robots.from_urdf), got {type(chain).__name__}")
    if world is not None and not isinstance(world, collision.World):
        raise TypeError(f"world must be an iiwa_torch.collision.World, got {type(world).__name__}")
    if capsules is not None and not isinstance(capsules, collision.Capsules):
        raise TypeError(f"capsules must be an iiwa_torch.collision.Capsules, got {type(capsules).__name__}")
    check_bool(show_capsules, "show_capsules")
    check_bool(show_frames, "show_frames")


def _preset_capsules(chain: Chain, world: collision.World | None) -> collision.Capsules | None:
    """The preset capsule model of ``chain``, or ``None`` for another arm (an error if a ``world``
    needs one)."""
    try:
        return collision.robot_capsules(chain)
    except ValueError:
        if world is not None:
            raise ValueError(f"no capsule model for {chain.name!r}: pass capsules= to check it against the world") \
                from None
        return None


def show(
    chain: Chain,
    q: torch.Tensor | None = None,
    host: str = "127.0.0.1",
    port: int = 8080,
    block: bool = True,
    *,
    world: collision.World | None = None,
    capsules: collision.Capsules | None = None,
    urdf: str | os.PathLike | None = None,
    show_capsules: bool = False,
    show_frames: bool = False,
    path: torch.Tensor | None = None,
    dt: float = 0.05,
    goals: torch.Tensor | None = None,
):
    """Serve the viewer of ``chain`` at ``http://host:port``.

    ``q`` is the first configuration (radians, default mid-limits). ``host="0.0.0.0"`` makes
    it reachable from other machines (with a warning); ``host``, ``port`` as for :class:`Viewer`,
    which says where the server listens (its ``host`` and ``port``). ``world``, ``capsules``, ``urdf``,
    ``show_capsules``, ``show_frames`` as for :class:`Viewer`; ``path`` ``(T, n)`` or ``(B, T, n)``, ``dt`` (s)
    and ``goals`` ``(B, 3)`` as for :meth:`Viewer.set_path`. With ``block=True`` it runs until
    Ctrl-C, then stops the server and returns None; with ``block=False`` it returns the
    running :class:`Viewer` (call its ``stop()``).
    """
    check_bool(block, "block")
    viewer, handed_over = None, False
    try:  # Ctrl-C may come as soon as the page is served, while the scene is still being built
        viewer = Viewer(
            chain, q, host=host, port=port, world=world, capsules=capsules, urdf=urdf, show_capsules=show_capsules,
            show_frames=show_frames,
        )  # fmt: skip
        if path is not None:
            viewer.set_path(path, dt, goals)
        if not block:
            handed_over = True
            return viewer
        address = f"[{viewer.host}]" if ":" in viewer.host else viewer.host
        print(f"iiwa-torch viewer of {chain.name} at http://{address}:{viewer.port} (Ctrl-C to stop)", flush=True)
        threading.Event().wait()
    except KeyboardInterrupt:
        if not block:
            raise
    finally:
        if viewer is not None and not handed_over:
            viewer.stop()
    return None
