"""Playback of joint paths: the panel's "playback" folder and a thread stepping through a path in real time."""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np
import torch

from ..chain import Chain
from ..checks import check_finite, check_float_tensor, check_positive

_F64 = torch.float64


def checked_paths(chain: Chain, q, dt, goals) -> tuple[torch.Tensor, np.ndarray | None, float]:
    """``Viewer.set_path``'s arguments checked: ``(paths (B, T, n) float64, goals (B, 3) numpy or None, dt s)``."""
    check_float_tensor(q, "q", "(T, n) or (B, T, n)")
    n = chain.n_joints
    if q.ndim not in (2, 3) or q.shape[-1] != n or q.shape[-2] < 1:
        raise ValueError(f"q must have shape (T, {n}) or (B, T, {n}) with T >= 1, got {tuple(q.shape)}")
    check_positive(dt, "dt")
    paths = q.detach().to("cpu", _F64).reshape(-1, q.shape[-2], n)
    chain.check_q(paths, "q")
    if not bool(chain.within_limits(paths, tol=1e-6).all()):
        raise ValueError("q must be within the joint limits at every step")
    if goals is not None:
        check_float_tensor(goals, "goals", f"({paths.shape[0]}, 3)")
        if goals.shape != (paths.shape[0], 3):
            raise ValueError(f"goals must have shape ({paths.shape[0]}, 3), one per path, got {tuple(goals.shape)}")
        check_finite(goals, "goals")
        goals = goals.detach().to("cpu", _F64).numpy()
    return chain.clamp(paths), goals, float(dt)


class Player:
    """The loaded ``paths (B, T, n)``, ``goals``, ``dt``, the ``path`` and ``step`` shown, the widgets and the
    playing thread; ``seek(step, path=None)`` is the viewer's. Methods run under ``guard.lock``."""

    def __init__(self, gui, guard, seek: Callable[..., None]):
        self._guard, self._seek = guard, seek
        self.paths: torch.Tensor | None = None
        self.goals: np.ndarray | None = None
        self.dt = 0.05
        self.path, self.step = 0, 0
        self._playing = threading.Event()
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None
        self.folder = gui.add_folder("playback", visible=False)
        with self.folder:
            self.play_button = gui.add_button("play")
            self.play_button.on_click(lambda _: self.pause() if self.playing else self.play())
            self.loop = gui.add_checkbox("loop", False)
            self.time_slider = gui.add_slider("time (s)", min=0.0, max=1.0, step=0.05, initial_value=0.0)
            self.time_slider.on_update(guard.callback(lambda: seek(self._time_step())))
            self.path_slider = gui.add_slider("path", min=0, max=1, step=1, initial_value=0, visible=False)
            self.path_slider.on_update(guard.callback(lambda: seek(self._time_step(), int(self.path_slider.value))))

    @property
    def playing(self) -> bool:
        return self._playing.is_set()

    def _time_step(self) -> int:
        return min(max(round(self.time_slider.value / self.dt), 0), self.paths.shape[1] - 1)

    def load(self, paths: torch.Tensor, goals: np.ndarray | None, dt: float) -> None:
        """Take :func:`checked_paths`' result, paused."""
        with self._guard.lock:
            self.pause()
            self.paths, self.goals, self.dt = paths, goals, dt
            with self._guard.quiet():
                self.time_slider.max = max((paths.shape[1] - 1) * dt, 1e-9)
                self.time_slider.step = dt
                self.path_slider.max = max(paths.shape[0] - 1, 1)
                self.path_slider.visible = paths.shape[0] > 1
            self.folder.visible = True

    def checked(self, step, path) -> tuple[int, int]:
        """``(step, path)`` of a seek (``path`` None: the current one), checked against the paths."""
        if self.paths is None:
            raise ValueError("no path loaded: call set_path first")
        b, t = self.paths.shape[:2]
        path = self.path if path is None else path
        for value, size, name in ((step, t, "step"), (path, b, "path")):
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < size:
                raise ValueError(f"{name} must be an int in [0, {size}), got {value!r}")
        return step, path

    def moved_to(self, step: int, path: int) -> torch.Tensor:
        """Record the step shown and move the sliders there; its configuration ``(n,)``."""
        self.step, self.path = step, path
        with self._guard.quiet():
            self.time_slider.value = step * self.dt
            self.path_slider.value = path
        return self.paths[path, step].clone()

    def play(self) -> None:
        """Play in real time (from the start once at the end), looping if the box is ticked."""
        if self.paths is None:
            raise ValueError("no path loaded: call set_path first")
        with self._guard.lock:
            if self.step == self.paths.shape[1] - 1:
                self._seek(0)
            self._playing.set()
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="viewer-player", daemon=True)
                self._thread.start()
            self.play_button.label = "pause"

    def pause(self) -> None:
        with self._guard.lock:
            self._playing.clear()
            self.play_button.label = "play"

    def _run(self) -> None:
        while not self._closing.is_set():
            if not self._playing.wait(timeout=0.2):
                continue
            if self._closing.wait(self.dt):
                return
            with self._guard.lock:
                if not self._playing.is_set() or self.paths is None:
                    continue
                if self.step < self.paths.shape[1] - 1:
                    self._seek(self.step + 1)
                elif self.loop.value:
                    self._seek(0)
                else:
                    self.pause()

    def stop(self) -> None:
        """Stop the thread (for good)."""
        self._closing.set()
        self._playing.clear()
        if self._thread is not None:
            self._thread.join(timeout=5)
