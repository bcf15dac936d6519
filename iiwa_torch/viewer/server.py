"""The running viewer: :class:`Viewer` (a viser server, its scene, panel and state) and :func:`show`.

The state lives in :class:`Viewer`, so it can be driven without a browser; the scene and the panel
only draw and report what the user does.
"""

from __future__ import annotations

import contextlib
import errno
import io
import ipaddress
import math
import os
import re
import socket
import sys
import threading

import numpy as np
import torch

from .. import collision, so3
from ..chain import Chain
from ..checks import check_bool, require
from .controls import Controls, Guard, Readout
from .ik_panel import IKPanel, TargetResult, TargetSolver
from .playback import Player, checked_paths
from .scene import ArmScene, urdf_parts
from .world import unbatched

_F64 = torch.float64
_LABEL = r"[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
_HOSTNAME = re.compile(rf"(?:{_LABEL}\.)*{_LABEL}\.?")  # RFC 1123 host name syntax


def _listen_address(host, port) -> tuple[str, bool]:
    """``(host, loopback)``: ``host`` ('' or None: 127.0.0.1) and ``port`` checked before viser starts
    (viser moves on from a port it cannot bind, and waits forever when it binds none); a busy port is
    left to viser. ``loopback`` is False if other machines could reach it. ValueError/TypeError."""
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


def _check_options(chain, world, capsules, show_capsules, show_frames) -> None:
    if not isinstance(chain, Chain):
        raise TypeError(f"chain must be an iiwa_torch Chain (a preset or robots.from_urdf), got {type(chain).__name__}")
    if world is not None and not isinstance(world, collision.World):
        raise TypeError(f"world must be an iiwa_torch.collision.World, got {type(world).__name__}")
    if capsules is not None and not isinstance(capsules, collision.Capsules):
        raise TypeError(f"capsules must be an iiwa_torch.collision.Capsules, got {type(capsules).__name__}")
    check_bool(show_capsules, "show_capsules")
    check_bool(show_frames, "show_frames")


def _preset_capsules(chain: Chain, world: collision.World | None) -> collision.Capsules | None:
    """``chain``'s preset capsule model; None for another arm (ValueError if ``world`` needs one)."""
    try:
        return collision.robot_capsules(chain)
    except ValueError:
        if world is not None:
            raise ValueError(
                f"no capsule model for {chain.name!r}: pass capsules= to check it against the world"
            ) from None
        return None


class Viewer:
    """A running viser server showing ``chain`` at ``q (n,)`` rad (default: mid-limits; 0 if continuous).

    Args:
        host, port: ``127.0.0.1`` ('' or None too) serves this machine only; any other address warns,
            as whoever reaches the port controls the viewer. Port 0: any free one; busy: the next free.
        world: obstacles (one set; :func:`~iiwa_torch.viewer.load_world`); None: the capsules' floor.
        capsules: default ``robot_capsules`` of a preset, or those fitted to ``urdf``; else no clearance.
        urdf: the file ``chain`` was read from: its ``<visual>`` elements are drawn instead of the
            skeleton (its capsules if it has none).
        show_capsules, show_frames: draw the collision capsules, every link frame.

    ``host`` and ``port`` say where it listens; ``scene``, ``controls``, ``ik_panel`` and ``player`` are
    its parts. The state is under a lock: GUI callbacks run on viser's thread pool.
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
        self._guard = Guard()
        self._target_seq = 0
        self._limits = chain.limits.to(_F64)
        self._q = self._checked(self._limits.nan_to_num(posinf=math.pi, neginf=-math.pi).mean(0) if q is None else q)
        visuals = []  # [(URDF <visual> element, its trimesh or None)], read before the server starts
        if urdf is not None:
            visuals, capsules = urdf_parts(chain, urdf, capsules)
            show_capsules = show_capsules or not visuals  # no visuals: the capsules are the body
        self.capsules = _preset_capsules(chain, world) if capsules is None else capsules
        self.world = None if world is None else unbatched(world)
        self._solver = TargetSolver(chain, self._q, self.capsules, self.world)
        self.status = "drag the target gizmo"
        self.outcome: str | None = None
        self._target_pose = chain.fk(self._q).to(_F64)

        with contextlib.redirect_stdout(io.StringIO()):  # viser's own banner: show() prints the address once
            self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.host, self.port = host, self.server.get_port()
        if not loopback:
            print(f"warning: the viewer on {host} has no login: anyone who can reach port {self.port} controls it",
                  file=sys.stderr)  # fmt: skip
        try:
            self._build(visuals, show_capsules, show_frames)
            self._draw(move_target=True)
        except BaseException:  # also Ctrl-C: the server's threads must not outlive a half-built viewer
            self.server.stop()
            raise

    def _build(self, visuals, show_capsules: bool, show_frames: bool) -> None:
        """The scene, then the panel from top to bottom."""
        frames, end = self._frames()
        self.scene = ArmScene(self.server, self.chain, frames, end, visuals=visuals, capsules=self.capsules,
                              world=self.world, show_capsules=show_capsules, show_frames=show_frames,
                              on_drag=self.drag_target)  # fmt: skip
        gui = self.server.gui
        self.controls = Controls(gui, self._guard, self.chain, self._limits, self._move_joint)
        self.ik_panel = IKPanel(gui, self._guard, self._solver, self._ik_widgets_changed)
        self.controls.add_toggles(self.scene, show_capsules, show_frames)
        self.player = Player(gui, self._guard, self.seek)
        self.ik_panel.sync()

    # the scene's and the panel's public parts, by their old names
    sliders = property(lambda self: self.controls.sliders, doc="One viser slider per joint (degrees; metres).")
    visual_nodes = property(lambda self: self.scene.visual_nodes, doc="``[(URDF <visual> element, node)]``.")
    capsule_nodes = property(lambda self: self.scene.capsule_nodes, doc="``{capsule name: its nodes}``.")
    world_nodes = property(lambda self: self.scene.world_nodes, doc="``{obstacle name: [nodes]}``.")

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
        """Show the arm at ``q (n,)`` rad (within the limits); the target follows unless ``move_target`` is False."""
        q = self._checked(q)
        check_bool(move_target, "move_target")
        with self._guard.lock:
            self._q = q
            self._draw(move_target)

    def _move_joint(self, i: int) -> None:
        q = self._q.clone()
        q[i] = self.controls.joint_value(i)
        self._q = self.chain.clamp(q)
        self._draw(move_target=True)

    def readout(self) -> Readout:
        """The end-effector pose at the current angles, as the panel shows it."""
        with torch.no_grad():
            pose = self.chain.fk(self._q)
        rpy = torch.rad2deg(so3.matrix_to_rpy(pose[:3, :3]))
        return Readout(tuple(pose[:3, 3].tolist()), tuple(rpy.tolist()))

    def clearance(self, q: torch.Tensor | None = None) -> tuple[float, tuple[str, str]] | None:
        """``(smallest signed distance m, its pair's names)`` at ``q (n,)`` (default the current angles);
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
    @property
    def ik_methods(self) -> tuple[str, ...]:
        """``"gradient"``, and ``"analytic"`` where a closed form exists."""
        return self._solver.methods

    def set_ik(self, method: str, branch: int | None = None, arm_angle: float | None = None) -> None:
        """Choose how targets are solved: ``method`` (:attr:`ik_methods`); for ``"analytic"``, ``branch``
        0..7 (``4 shoulder + 2 elbow + wrist``) and, on S-R-S arms, ``arm_angle`` held (rad); None: nearest."""
        with self._guard.lock:
            self._solver.choose(method, branch, arm_angle)
            self.ik_panel.sync()

    def _ik_widgets_changed(self) -> None:
        self.set_ik(*self.ik_panel.chosen())
        self.solve_target(self._target_pose)

    def solve_target(self, pose: torch.Tensor) -> TargetResult:
        """Solve ``pose (4, 4)`` (m) from the current angles. Only a solution within the limits, 0.1 mm /
        1 mrad and free of collision moves the arm; ``outcome`` says why not."""
        so3.check_pose(pose, "pose")
        if pose.shape != (4, 4):
            raise ValueError(f"pose must have shape (4, 4), got {tuple(pose.shape)}")
        pose = pose.detach().to("cpu", _F64)
        with self._guard.lock:
            self._target_pose = pose
            result = self._solver.solve(pose, self._q)
            self.outcome, self.status = result.outcome, result.text()
            self._q = result.q.clone()
            self._draw(move_target=False)
        return result

    def drag_target(self, wxyz, position) -> None:
        """:meth:`solve_target` of the gizmo's pose ``wxyz (4,)``, ``position (3,)`` m, unless a newer drag
        came meanwhile (drags arrive faster than solves end: only the newest waiting one is solved)."""
        wxyz, position = np.asarray(wxyz, dtype=np.float64), np.asarray(position, dtype=np.float64)
        if wxyz.shape != (4,) or position.shape != (3,) or not np.isfinite(np.r_[wxyz, position]).all():
            raise ValueError(f"wxyz must be 4 and position 3 finite numbers, got {wxyz.tolist()}, {position.tolist()}")
        if not np.linalg.norm(wxyz) > 1e-9:
            raise ValueError(f"wxyz must be a nonzero quaternion, got {wxyz.tolist()}")
        with self._guard.lock:
            self._target_seq += 1
            seq = self._target_seq
        pose = torch.eye(4, dtype=_F64)
        pose[:3, :3] = so3.quaternion_to_matrix(torch.as_tensor(wxyz))
        pose[:3, 3] = torch.as_tensor(position)
        with self._guard.lock:
            if seq == self._target_seq:
                self.solve_target(pose)

    # ------------------------------------------------------------------ playback
    def set_path(self, q: torch.Tensor, dt: float = 0.05, goals: torch.Tensor | None = None) -> None:
        """Load paths ``q (T, n)`` or ``(B, T, n)`` rad, ``dt`` s apart, with optional ``goals (B, 3)`` m
        drawn as markers; show their first step."""
        paths, goals, dt = checked_paths(self.chain, q, dt, goals)
        with self._guard.lock:
            self.player.load(paths, goals, dt)
            self.seek(0, 0)

    @property
    def step(self) -> int:
        """The step of the path shown."""
        return self.player.step

    @property
    def playing(self) -> bool:
        return self.player.playing

    def seek(self, step: int, path: int | None = None) -> None:
        """Show step ``step`` (0..T-1) of path ``path`` (0..B-1, default the current one)."""
        player = self.player
        step, path = player.checked(step, path)
        with self._guard.lock:
            if path != player.path or self.scene.trace is None:  # the new path's end-effector trace
                with torch.no_grad():
                    tip = self.chain.fk(player.paths[path])[:, :3, 3].numpy()
                self.scene.draw_trace(tip, None if player.goals is None else player.goals[path])
            self._q = player.moved_to(step, path)
            self._draw(move_target=True)

    def play(self) -> None:
        """Play the path in real time (from the start once at its end), looping if the box is ticked."""
        self.player.play()

    def pause(self) -> None:
        self.player.pause()

    def stop(self) -> None:
        """Stop the player and the server (and their threads)."""
        self.player.stop()
        self.server.stop()

    # ------------------------------------------------------------------ drawing
    def _frames(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(n + 1, 4, 4)`` frames and the ``(4, 4)`` end-effector pose at the current angles."""
        with torch.no_grad():
            return self.chain.fk_all(self._q), self.chain.fk(self._q)

    def _draw(self, move_target: bool) -> None:
        """Send the arm, sliders, readout, clearance and status for the current ``q``."""
        frames, end = self._frames()
        result = self._pairwise(self._q)
        hits, clearance = set(), "clearance: no capsule model"
        if result is not None:
            distances = result.distance.tolist()
            hits = {name for pair, d in zip(result.pairs, distances) if d < 0 for name in pair}
            k = int(np.argmin(distances))
            state = "**COLLIDING**" if distances[k] < 0 else "clearance"
            clearance = f"{state} {1000 * distances[k]:+.1f} mm ({result.pairs[k][0]} - {result.pairs[k][1]})"
        if move_target:  # the target is back at the end effector: nothing left to report
            self.outcome, self.status = None, "drag the target gizmo"
            self._target_pose = end.clone()
        with self.server.atomic():
            self.scene.place(frames, end, move_target)
            self.scene.colour(frames, hits, self.outcome)
            arm = ""
            if self._solver.kind == "iiwa":
                psi = math.degrees(float(self._solver.arm_angle_at(self._q)))
                arm = self._solver.arm_text(self._q, psi)
                self.ik_panel.follow(psi)
            self.controls.show(self._q, self.readout().text() + arm, clearance)
            self.ik_panel.status.content = f"IK: {self.status}"


def show(
    chain: Chain,
    q: torch.Tensor | None = None,
    host: str = "127.0.0.1",
    port: int = 8080,
    block: bool = True,
    *,
    path: torch.Tensor | None = None,
    dt: float = 0.05,
    goals: torch.Tensor | None = None,
    **options,
):
    """Serve the viewer of ``chain`` at ``http://host:port``.

    ``q``, ``host``, ``port`` and ``options`` (``world``, ``capsules``, ``urdf``, ``show_capsules``,
    ``show_frames``) as for :class:`Viewer`; ``path``, ``dt``, ``goals`` as for :meth:`Viewer.set_path`.
    ``block=True`` runs until Ctrl-C, then stops and returns None; ``block=False`` returns the running
    :class:`Viewer` (call its ``stop()``).
    """
    check_bool(block, "block")
    if goals is not None and path is None:
        raise ValueError("goals are the targets of path=: pass path too")
    viewer, handed_over = None, False
    try:  # Ctrl-C may come as soon as the page is served, while the scene is still being built
        viewer = Viewer(chain, q, host=host, port=port, **options)
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
