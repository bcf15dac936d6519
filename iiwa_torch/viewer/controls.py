"""The viewer's panel apart from IK and playback (joint sliders, readout, checkboxes), and the
:class:`Guard` every widget callback runs under."""

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
    """The lock over a viewer's state (callbacks run on viser's threads, the player on its own), and a
    flag that silences callbacks while the viewer writes its own widgets."""

    def __init__(self):
        self.lock = threading.RLock()
        self._syncing = False

    @contextlib.contextmanager
    def quiet(self):
        before, self._syncing = self._syncing, True
        try:
            yield
        finally:
            self._syncing = before

    def callback(self, action: Callable[[], None]):
        """A callback running ``action()`` under the lock, unless the viewer itself wrote the widget."""

        def run(_event) -> None:
            with self.lock:
                if not self._syncing:
                    action()

        return run


@dataclass(frozen=True)
class Readout:
    """End-effector pose as the panel shows it: ``xyz`` m, ``rpy_deg`` roll, pitch, yaw in degrees."""

    xyz: tuple[float, float, float]
    rpy_deg: tuple[float, float, float]

    def text(self) -> str:
        x, y, z = self.xyz
        r, p, w = self.rpy_deg
        return f"xyz (m): {x:+.4f} {y:+.4f} {z:+.4f}  \nrpy (deg): {r:+.2f} {p:+.2f} {w:+.2f}"


class Controls:
    """The panel's title, ``sliders`` (one per joint, degrees or metres, within ``limits (2, n)``; a
    continuous joint's spans a turn), ``readout`` and ``clearance``. ``on_move(i)``: a user moved slider ``i``."""

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
        """Checkboxes ``show_skeleton`` (with URDF visuals), ``show_frames``, ``show_capsules`` (with capsules)."""
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
