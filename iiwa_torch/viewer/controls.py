"""The viewer's side panel, apart from IK and playback: one slider per joint, the pose readout and
clearance lines, the display checkboxes; and the :class:`Guard` every widget callback runs under."""

from __future__ import annotations

import contextlib
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass

import torch

from ..chain import Chain, JointKind

_F64 = torch.float64


class Guard:
    """The lock over a viewer's state (GUI callbacks run on viser's thread pool, the player on its
    own thread) and a flag set while the viewer writes its own widgets, whose callbacks then do nothing."""

    def __init__(self):
        self.lock = threading.RLock()
        self._syncing = False

    @contextlib.contextmanager
    def quiet(self):
        """Context in which the viewer's own widget writes run no callback."""
        before, self._syncing = self._syncing, True
        try:
            yield
        finally:
            self._syncing = before

    def callback(self, action: Callable[[], None]):
        """A widget callback that runs ``action()`` under the lock, unless the viewer itself wrote the widget."""

        def run(_event) -> None:
            with self.lock:
                if not self._syncing:
                    action()

        return run


@dataclass(frozen=True)
class Readout:
    """End-effector pose as shown in the panel: ``xyz`` metres, ``rpy_deg`` roll, pitch, yaw in degrees."""

    xyz: tuple[float, float, float]
    rpy_deg: tuple[float, float, float]

    def text(self) -> str:
        x, y, z = self.xyz
        r, p, w = self.rpy_deg
        return f"xyz (m): {x:+.4f} {y:+.4f} {z:+.4f}  \nrpy (deg): {r:+.2f} {p:+.2f} {w:+.2f}"


class Controls:
    """The panel's title, ``sliders`` (one per joint of ``chain``: degrees, metres for a prismatic
    joint, within ``limits (2, n)``; a continuous joint's spans a turn), then the ``readout`` and
    ``clearance`` lines. ``on_move(i)`` is called when a user moves slider ``i``
    (read it with :meth:`joint_value`). :meth:`add_toggles` adds the display checkboxes."""

    def __init__(self, gui, guard: Guard, chain: Chain, limits: torch.Tensor, on_move: Callable[[int], None]):
        self._gui, self._guard = gui, guard
        gui.add_markdown(f"**{chain.name}**: drag the target or move the sliders")
        prismatic = [kind is JointKind.PRISMATIC for kind in chain.kinds]
        self._scale = torch.tensor([1.0 if p else math.degrees(1.0) for p in prismatic], dtype=_F64)
        self._digits = [3 if p else 1 for p in prismatic]  # rounded to the slider's step
        ranges = limits.nan_to_num(posinf=math.pi, neginf=-math.pi) * self._scale  # continuous: a turn
        self.sliders = []  # one viser slider per joint; assigning a value moves that joint
        for i, name in enumerate(chain.joint_names):
            lo, hi = ranges[:, i].tolist()
            scale = 10.0 ** self._digits[i]  # the ends rounded inwards to the step, if the range allows
            if math.ceil(lo * scale - 1e-6) <= math.floor(hi * scale + 1e-6):
                lo, hi = math.ceil(lo * scale - 1e-6) / scale, math.floor(hi * scale + 1e-6) / scale
            slider = gui.add_slider(f"{name} ({'m' if prismatic[i] else 'deg'})", min=lo, max=hi,
                                    step=10.0 ** -self._digits[i], initial_value=(lo + hi) / 2)  # fmt: skip
            slider.on_update(guard.callback(lambda i=i: on_move(i)))
            self.sliders.append(slider)
        self.readout = gui.add_markdown("")
        self.clearance = gui.add_markdown("")

    def joint_value(self, i: int) -> float:
        """Slider ``i``'s value in radians (metres for a prismatic joint)."""
        return self.sliders[i].value / float(self._scale[i])

    def show(self, q: torch.Tensor, readout: str, clearance: str) -> None:
        """Move the sliders to ``q (n,)`` (radians; no callbacks) and write the two lines."""
        with self._guard.quiet():
            for slider, value, digits in zip(self.sliders, (q * self._scale).tolist(), self._digits):
                slider.value = min(max(round(value, digits), slider.min), slider.max)
        self.readout.content = readout
        self.clearance.content = clearance

    def add_toggles(self, scene, show_capsules: bool, show_frames: bool) -> None:
        """Checkboxes ``show_skeleton`` (offered with URDF visuals), ``show_frames`` and ``show_capsules``
        (offered with a capsule model) over the nodes of the :class:`~iiwa_torch.viewer.scene.ArmScene`."""
        gui, has_visuals = self._gui, bool(scene.visual_nodes)
        self.show_skeleton = gui.add_checkbox("show skeleton", not has_visuals, visible=has_visuals)
        skeleton = scene.links + scene.joints
        self.show_skeleton.on_update(lambda _: _set_visible(skeleton, self.show_skeleton.value))
        self.show_frames = gui.add_checkbox("show frames", show_frames)
        self.show_frames.on_update(lambda _: _set_visible(scene.frame_nodes, self.show_frames.value))
        self.show_capsules = gui.add_checkbox(
            "show collision capsules", show_capsules, visible=bool(scene.capsule_nodes)
        )
        nodes = [node for cap in scene.capsule_nodes.values() for node in cap.nodes]
        self.show_capsules.on_update(lambda _: _set_visible(nodes, self.show_capsules.value))


def _set_visible(nodes, visible: bool) -> None:
    for node in nodes:
        node.visible = visible
