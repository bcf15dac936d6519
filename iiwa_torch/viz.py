"""Matplotlib drawings of a chain: 3-D stick figures, off-screen RGB frames, animations.

matplotlib (and Pillow, for GIFs) is imported inside the functions, never when
``iiwa_torch`` is imported. Nothing here touches pyplot's global state: pictures are drawn
on a ``matplotlib.figure.Figure`` with its own Agg canvas, so rendering is safe inside
gymnasium environments, worker processes and tests.

- :func:`draw_chain` draws one configuration ``(n,)`` or several ``(k, n)`` on a 3-D axes;
- :func:`render_rgb` returns an ``(H, W, 3)`` uint8 image (for ``render_mode="rgb_array"``);
- :func:`save_png` writes that image to a file;
- :func:`animate` writes a trajectory ``(T, n)`` as a GIF (Pillow) or an MP4 (ffmpeg).
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import torch

from .dh import DHChain

__all__ = ["draw_chain", "render_rgb", "save_png", "animate"]

_FRAME_COLOURS = ("tab:red", "tab:green", "tab:blue")  # x, y, z axes of a frame


def _as_q(chain: DHChain, q) -> torch.Tensor:
    """Joint angles (tensor, array or list), ``(n,)`` or ``(k, n)`` -> ``(k, n)`` float64 tensor."""
    q = torch.as_tensor(q, dtype=torch.float64, device=chain.dh.device)
    if q.ndim == 1:
        q = q[None]
    if q.ndim != 2:
        raise ValueError(f"q must have shape ({chain.n_joints},) or (k, {chain.n_joints}), got {tuple(q.shape)}")
    chain.check_q(q)
    return q


def _reach(chain: DHChain) -> float:
    """An upper bound on the distance from the base origin to the end effector (metres)."""
    links = chain.dh[:, 0].abs().sum() + chain.dh[:, 2].abs().sum()
    return float(links + chain.tool[:3, 3].norm() + chain.base[:3, 3].norm())


def _points(chain: DHChain, q: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """``(k, n)`` -> frame origins plus the end effector ``(k, n + 2, 3)``, and frame rotations
    ``(k, n + 1, 3, 3)``, as numpy arrays (metres)."""
    with torch.no_grad():
        frames = chain.fk_all(q)  # (k, n + 1, 4, 4)
        ee = chain.fk(q)[:, None, :3, 3]  # (k, 1, 3)
    origins = torch.cat([frames[..., :3, 3], ee], 1)
    return origins.cpu().numpy(), frames[..., :3, :3].cpu().numpy()


def draw_chain(ax, chain: DHChain, q, *, frames: bool = False, color=None, alpha: float = 1.0, label=None) -> list:
    """Draw the chain at ``q`` on a 3-D matplotlib axes; return the artists created.

    Args:
        ax: a ``projection="3d"`` axes.
        chain: the robot.
        q: ``(n,)`` or ``(k, n)`` joint angles in radians (tensor, array or list); ``k``
            configurations are drawn overlaid, all with the same ``color`` and ``alpha``.
        frames: also draw every link frame's x, y, z axes (red, green, blue).
        color: links' colour (default: matplotlib's next colour in the cycle).
        alpha: opacity of everything drawn.
        label: legend label, attached to the first configuration's links only.

    Links are lines between consecutive frame origins (``fk_all``), then on to the end
    effector (``fk``, tool included); joints are dots; the end effector is a square.
    """
    q = _as_q(chain, q)
    origins, rotations = _points(chain, q)
    scale = 0.08 * _reach(chain)
    artists = []
    for i, pts in enumerate(origins):
        x, y, z = pts.T
        links = ax.plot(x, y, z, "-", color=color, lw=3, alpha=alpha, label=label if i == 0 else None)
        color = links[0].get_color()  # None picks the axes' next cycle colour, kept for the rest
        artists += links
        artists.append(ax.scatter(x[:-1], y[:-1], z[:-1], color="0.25", s=14, alpha=alpha, depthshade=False))
        artists.append(ax.scatter(x[-1:], y[-1:], z[-1:], color=color, marker="s", s=40, alpha=alpha, depthshade=False))
        if frames:
            for origin, rot in zip(pts[:-1], rotations[i]):
                for axis, axis_colour in zip(rot.T, _FRAME_COLOURS):
                    tip = origin + scale * axis
                    artists += ax.plot(*np.stack([origin, tip], 1), color=axis_colour, lw=1, alpha=alpha)
    return artists


def _scene(chain: DHChain, size: tuple[int, int], dpi: int, elev: float, azim: float):
    """A figure with its own Agg canvas and one 3-D axes, limits fixed to the chain's reach."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    width, height = size
    fig = Figure(figsize=(width / dpi, height / dpi), dpi=dpi)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_subplot(projection="3d")
    fig.subplots_adjust(left=0, right=1, bottom=0, top=1)
    r = _reach(chain)
    centre = chain.base[:3, 3].cpu().numpy()
    ax.set_xlim(centre[0] - 0.6 * r, centre[0] + 0.6 * r)
    ax.set_ylim(centre[1] - 0.6 * r, centre[1] + 0.6 * r)
    ax.set_zlim(centre[2] - 0.1 * r, centre[2] + 1.1 * r)
    ax.set_box_aspect((1, 1, 1), zoom=0.85)
    ax.view_init(elev=elev, azim=azim)
    small = max(5, round(7 * min(size) / 400))
    for name, axis in (("x", ax.xaxis), ("y", ax.yaxis), ("z", ax.zaxis)):
        axis.set_label_text(f"{name} (m)", fontsize=small)
        axis.set_tick_params(labelsize=small - 1, pad=0)
        axis.set_major_locator(_locator())
    base = chain.base[:3, 3].cpu().numpy()
    ax.scatter(*base[:, None], color="0.2", marker="s", s=60, depthshade=False)  # the base
    return fig, canvas, ax


def _locator():
    from matplotlib.ticker import MaxNLocator

    return MaxNLocator(5)


def _goal_xyz(goal) -> np.ndarray:
    """Goal as ``(3,)``, ``(4, 4)``, ``(k, 3)`` or ``(k, 4, 4)`` -> ``(k, 3)`` positions."""
    g = torch.as_tensor(goal, dtype=torch.float64).cpu()
    if g.shape[-2:] == (4, 4):
        g = g[..., :3, 3]
    if g.shape[-1] != 3 or g.ndim > 2:
        raise ValueError(f"goal must be a position (3,) / (k, 3) or a pose (4, 4) / (k, 4, 4), got {tuple(g.shape)}")
    return g.reshape(-1, 3).numpy()


def _draw_extras(ax, goal, path, title):
    artists = []
    if path is not None:
        p = np.asarray(torch.as_tensor(path, dtype=torch.float64).cpu())
        p = p[..., :3, 3] if p.shape[-2:] == (4, 4) else p
        artists += ax.plot(p[:, 0], p[:, 1], p[:, 2], "--", color="tab:purple", lw=2)
    if goal is not None:
        g = _goal_xyz(goal)
        artists.append(ax.scatter(g[:, 0], g[:, 1], g[:, 2], color="tab:red", marker="*", s=160, depthshade=False))
    if title:
        artists.append(ax.text2D(0.02, 0.99, title, transform=ax.transAxes, fontsize=9, va="top"))
    return artists


def _to_rgb(canvas) -> np.ndarray:
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def render_rgb(
    chain: DHChain,
    q,
    goal=None,
    size: tuple[int, int] = (480, 480),
    *,
    path=None,
    frames: bool = False,
    title: str | None = None,
    elev: float = 20.0,
    azim: float = -60.0,
    dpi: int = 100,
) -> np.ndarray:
    """Render the chain off screen: returns an ``(H, W, 3)`` uint8 RGB image, ``size = (W, H)`` pixels.

    Args:
        q: ``(n,)`` or ``(k, n)`` joint angles in radians (``k`` arms overlaid).
        goal: optional target, a position ``(3,)`` / ``(k, 3)`` or a pose ``(4, 4)`` /
            ``(k, 4, 4)``, drawn as a red star.
        path: optional ``(T, 3)`` positions or ``(T, 4, 4)`` poses, drawn as a dashed line.
        frames: draw every link frame's axes.
        title: text in the top-left corner.
        elev, azim: camera angles in degrees.
    """
    fig, canvas, ax = _scene(chain, size, dpi, elev, azim)
    draw_chain(ax, chain, q, frames=frames, color="tab:orange")
    _draw_extras(ax, goal, path, title)
    return _to_rgb(canvas)


def save_png(chain: DHChain, q, file, **kwargs) -> Path:
    """Render with :func:`render_rgb` (same keyword arguments) and write a PNG; returns the path."""
    from PIL import Image

    file = Path(file)
    Image.fromarray(render_rgb(chain, q, **kwargs)).save(file)
    return file


def animate(
    chain: DHChain,
    qs,
    file,
    *,
    fps: int = 20,
    goal=None,
    path=None,
    size: tuple[int, int] = (400, 400),
    frames: bool = False,
    elev: float = 20.0,
    azim: float = -60.0,
    dpi: int = 100,
) -> Path:
    """Write the trajectory ``qs`` ``(T, n)`` (radians) as an animation with exactly ``T`` frames.

    The format follows the file's suffix: ``.gif`` (Pillow, looping) or ``.mp4`` (needs the
    ``ffmpeg`` executable on the PATH; a clear ``RuntimeError`` otherwise). ``path`` (``(T, 3)``
    positions or ``(T, 4, 4)`` poses, e.g. the Cartesian path being tracked) is drawn dashed,
    and the end effector's trace so far as a solid line. Returns the path written.
    """
    file = Path(file)
    suffix = file.suffix.lower()
    if suffix not in (".gif", ".mp4"):
        raise ValueError(f"animation file must end in .gif or .mp4, got {file.name!r}")
    if suffix == ".mp4" and shutil.which("ffmpeg") is None:
        raise RuntimeError("writing .mp4 needs the ffmpeg executable on the PATH; write a .gif instead")
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    q = _as_q(chain, qs)
    trace = _points(chain, q)[0][:, -1]  # (T, 3) end-effector positions
    fig, canvas, ax = _scene(chain, size, dpi, elev, azim)
    _draw_extras(ax, goal, path, None)
    images = []
    for t in range(q.shape[0]):
        drawn = draw_chain(ax, chain, q[t], frames=frames, color="tab:orange")
        drawn += ax.plot(trace[: t + 1, 0], trace[: t + 1, 1], trace[: t + 1, 2], color="tab:blue", lw=2.5)
        drawn.append(ax.text2D(0.02, 0.99, f"step {t + 1}/{q.shape[0]}", transform=ax.transAxes, fontsize=9, va="top"))
        images.append(_to_rgb(canvas))
        for artist in drawn:
            artist.remove()
    if suffix == ".gif":
        _write_gif(images, file, fps)
    else:
        _write_mp4(images, file, fps)
    return file


def _write_gif(images: list[np.ndarray], file: Path, fps: int) -> None:
    from PIL import Image

    # One palette, from the first and last frames (the trace drawn so far is complete in the
    # last), keeps the file small; frames are not merged (disposal 1 + no optimize).
    both = Image.fromarray(np.concatenate([images[0], images[-1]], 0))
    palette = both.quantize(colors=64, method=Image.Quantize.MEDIANCUT)
    frames = [Image.fromarray(im).quantize(palette=palette, dither=Image.Dither.NONE) for im in images]
    frames[0].save(
        file, save_all=True, append_images=frames[1:], duration=round(1000 / fps), loop=0, optimize=False, disposal=1
    )


def _write_mp4(images: list[np.ndarray], file: Path, fps: int) -> None:
    h, w, _ = images[0].shape
    cmd = "ffmpeg -loglevel error -y -f rawvideo -pix_fmt rgb24".split() + ["-s", f"{w}x{h}", "-r", str(fps)]
    cmd += ["-i", "-", "-pix_fmt", "yuv420p", "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2", str(file)]
    subprocess.run(cmd, input=b"".join(im.tobytes() for im in images), check=True)
