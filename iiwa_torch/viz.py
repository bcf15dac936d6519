"""Matplotlib drawings of a chain: stick figures, off-screen RGB images, GIF/MP4 animations, capsules
and obstacles.

matplotlib and Pillow (the ``viz`` extra) are imported when drawing. Pyplot is never used: each
picture has its own Agg canvas, so rendering is safe in environments, workers and tests.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import torch

from .chain import Chain
from .checks import check_positive, require
from .collision import Capsules, World, pairwise_clearance, robot_capsules

__all__ = [
    "draw_chain",
    "render_rgb",
    "save_png",
    "animate",
    "side_view",
    "draw_capsules",
    "draw_obstacles",
    "plot_world",
]

_FRAME_COLOURS = ("tab:red", "tab:green", "tab:blue")  # x, y, z axes of a frame


def _as_q(chain: Chain, q, one: str | None = None) -> torch.Tensor:
    """Joint angles (tensor, array or list), ``(n,)`` or ``(k, n)`` -> ``(k, n)`` float64 tensor;
    ``one``: the caller's name, which draws one configuration only (``k = 1``)."""
    q = torch.as_tensor(q, dtype=torch.float64, device=chain.limits.device)
    if q.ndim == 1:
        q = q[None]
    if q.ndim != 2:
        raise ValueError(f"q must have shape ({chain.n_joints},) or (k, {chain.n_joints}), got {tuple(q.shape)}")
    chain.check_q(q)
    if q.shape[0] == 0:
        raise ValueError(f"q must hold at least one configuration to draw, got {tuple(q.shape)}")
    if one and q.shape[0] != 1:
        raise ValueError(f"{one} draws one configuration ({chain.n_joints},), got {q.shape[0]} configurations")
    return q


def _points(chain: Chain, q: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """``(k, n)`` -> frame origins plus the end effector ``(k, n + 2, 3)``, and frame rotations
    ``(k, n + 1, 3, 3)``, as numpy arrays (metres)."""
    with torch.no_grad():
        frames = chain.fk_all(q)  # (k, n + 1, 4, 4)
        ee = chain.fk(q)[:, None, :3, 3]  # (k, 1, 3)
    origins = torch.cat([frames[..., :3, 3], ee], 1)
    return origins.cpu().numpy(), frames[..., :3, :3].cpu().numpy()


def draw_chain(ax, chain: Chain, q, *, frames: bool = False, color=None, alpha: float = 1.0, label=None) -> list:
    """Draw the chain at ``q (n,)`` or ``(k, n)`` rad (overlaid) on a 3-D axes; return the artists.

    Links are lines between the frame origins and on to the end effector (a square), joints dots;
    ``frames`` adds each frame's x, y, z axes. ``color`` defaults to the axes' next cycle colour;
    ``label`` goes on the first configuration's links.
    """
    q = _as_q(chain, q)
    origins, rotations = _points(chain, q)
    scale = 0.08 * chain.reach_bound()
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


def _scene(chain: Chain, size: tuple[int, int], dpi: int, elev: float, azim: float):
    """A figure with its own Agg canvas and one 3-D axes, limits fixed to the chain's reach."""
    FigureCanvasAgg = require("matplotlib.backends.backend_agg", "viz").FigureCanvasAgg
    Figure = require("matplotlib.figure", "viz").Figure

    check_positive(dpi, "dpi")
    width, height = size
    fig = Figure(figsize=(width / dpi, height / dpi), dpi=dpi)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_subplot(projection="3d")
    fig.subplots_adjust(left=0, right=1, bottom=0, top=1)
    r = chain.reach_bound()
    base = chain.base[:3, 3].cpu().numpy()
    ax.set_xlim(base[0] - 0.6 * r, base[0] + 0.6 * r)
    ax.set_ylim(base[1] - 0.6 * r, base[1] + 0.6 * r)
    ax.set_zlim(base[2] - 0.1 * r, base[2] + 1.1 * r)
    ax.set_box_aspect((1, 1, 1), zoom=0.85)
    ax.view_init(elev=elev, azim=azim)
    small = max(5, round(7 * min(size) / 400))
    for name, axis in (("x", ax.xaxis), ("y", ax.yaxis), ("z", ax.zaxis)):
        axis.set_label_text(f"{name} (m)", fontsize=small)
        axis.set_tick_params(labelsize=small - 1, pad=0)
        axis.set_major_locator(require("matplotlib.ticker", "viz").MaxNLocator(5))
    ax.scatter(*base[:, None], color="0.2", marker="s", s=60, depthshade=False)  # the base
    return fig, canvas, ax


def _positions(x, name: str) -> np.ndarray:
    """Positions ``(k, 3)`` or poses ``(k, 4, 4)`` (or one of either) -> positions ``(k, 3)`` (numpy, m)."""
    x = torch.as_tensor(x, dtype=torch.float64).cpu()
    p = (x[..., :3, 3] if x.shape[-2:] == (4, 4) else x).numpy()
    if p.ndim not in (1, 2) or p.shape[-1] != 3:
        raise ValueError(f"{name} must be positions (3,) / (k, 3) or poses (4, 4) / (k, 4, 4), got {tuple(x.shape)}")
    if not np.isfinite(p).all():
        raise ValueError(f"{name} contains NaN or inf")
    return p.reshape(-1, 3)


def _draw_extras(ax, goal, path, title):
    artists = []
    if path is not None:
        p = _positions(path, "path")
        artists += ax.plot(p[:, 0], p[:, 1], p[:, 2], "--", color="tab:purple", lw=2)
    if goal is not None:
        g = _positions(goal, "goal")
        artists.append(ax.scatter(g[:, 0], g[:, 1], g[:, 2], color="tab:red", marker="*", s=160, depthshade=False))
    if title:
        artists.append(ax.text2D(0.02, 0.99, title, transform=ax.transAxes, fontsize=9, va="top"))
    return artists


def _to_rgb(canvas) -> np.ndarray:
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def render_rgb(
    chain: Chain,
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
    """The chain at ``q (n,)`` or ``(k, n)`` rad as an ``(H, W, 3)`` uint8 image, ``size = (W, H)`` pixels.

    ``goal``: positions ``(3,)``/``(k, 3)`` or poses ``(4, 4)``/``(k, 4, 4)``, red stars; ``path``:
    ``(T, 3)`` or ``(T, 4, 4)``, dashed; ``title`` top left; ``elev``, ``azim``: camera, degrees.
    """
    fig, canvas, ax = _scene(chain, size, dpi, elev, azim)
    draw_chain(ax, chain, q, frames=frames, color="tab:orange")
    _draw_extras(ax, goal, path, title)
    return _to_rgb(canvas)


def save_png(chain: Chain, q, file, **kwargs) -> Path:
    """Render with :func:`render_rgb` (same keyword arguments) and write a PNG; returns the path."""
    Image = require("PIL.Image", "viz")
    file = Path(file)
    Image.fromarray(render_rgb(chain, q, **kwargs)).save(file)
    return file


def animate(
    chain: Chain,
    qs,
    file,
    *,
    fps: int = 20,
    goal=None,
    path=None,
    size: tuple[int, int] = (400, 400),
    frames: bool = False,
    elev: float = 20.0,
    azim: float | None = None,
    dpi: int = 100,
) -> Path:
    """Write ``qs (T, n)`` rad as a ``T``-frame ``.gif`` (Pillow) or ``.mp4`` (ffmpeg, else RuntimeError);
    returns the file.

    ``path`` ``(T, 3)`` or ``(T, 4, 4)`` is drawn dashed, the end effector's trace so far solid;
    ``azim=None`` looks from :func:`side_view` of the trace. The axes fit the whole trajectory.
    """
    file = Path(file)
    suffix = file.suffix.lower()
    if suffix not in (".gif", ".mp4"):
        raise ValueError(f"animation file must end in .gif or .mp4, got {file.name!r}")
    if suffix == ".mp4" and shutil.which("ffmpeg") is None:
        raise RuntimeError("writing .mp4 needs the ffmpeg executable on the PATH; write a .gif instead")
    check_positive(fps, "fps")
    q = _as_q(chain, qs)
    joints = _points(chain, q)[0]  # (T, joints, 3)
    trace = joints[:, -1]  # (T, 3) end-effector positions
    base = chain.base[:3, 3].cpu().numpy()
    fig, canvas, ax = _scene(chain, size, dpi, elev, side_view(trace, base) if azim is None else azim)
    drawn = [joints.reshape(-1, 3), base[None]] + ([] if goal is None else [_positions(goal, "goal")])
    if path is not None:
        drawn.append(_positions(path, "path"))
    everything = np.concatenate(drawn)
    _fit_cube(ax, np.stack([everything.min(0), everything.max(0)]), margin=0.15)
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


def side_view(points, centre=(0.0, 0.0, 0.0), offset: float = 25.0) -> float:
    """Camera azimuth (degrees) seeing the motion through ``points (T, 3)`` m from the side away from
    ``centre``, turned ``offset`` degrees towards matplotlib's default -60 (also the answer for points
    that move less than 1 mm horizontally)."""
    xy = np.asarray(points, dtype=float)[:, :2]
    spread = xy - xy.mean(0)
    if np.abs(spread).max() < 1e-3:
        return -60.0
    direction = np.linalg.svd(spread, full_matrices=False)[2][0]  # the principal horizontal axis
    normal = np.array([-direction[1], direction[0]])
    if normal @ (xy.mean(0) - np.asarray(centre, dtype=float)[:2]) < 0:
        normal = -normal
    facing = np.degrees(np.arctan2(normal[1], normal[0]))
    turn = (-60.0 - facing + 180.0) % 360.0 - 180.0  # signed angle from the side view to the default
    return float(facing + np.sign(turn) * min(offset, abs(turn)))


def _write_gif(images: list[np.ndarray], file: Path, fps: int) -> None:
    Image = require("PIL.Image", "viz")
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


# ---------------------------------------------------------------------------- collision geometry
_CAPSULE_COLOUR = "tab:blue"
_COLLISION_COLOUR = "tab:red"
_OBSTACLE_COLOUR = "0.55"
_BOX_FACES = ((0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5))


def _capsule_mesh(a: np.ndarray, b: np.ndarray, radius: float, n: int = 20) -> np.ndarray:
    """Surface grid ``(2m, n, 3)`` of the capsule ``a -> b`` (m): two hemispheres joined at their
    equators (``a == b``: a sphere)."""
    axis = b - a
    length = float(np.linalg.norm(axis))
    u = axis / length if length > 0 else np.array([0.0, 0.0, 1.0])
    e1 = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    lat = np.linspace(-np.pi / 2, np.pi / 2, 2 * (n // 4) + 1)
    lat = np.concatenate([lat[lat <= 0], lat[lat >= 0]])  # the equator twice: once per cap
    along = radius * np.sin(lat) + np.where(np.arange(lat.size) >= lat.size // 2, length, 0.0)
    rho = radius * np.cos(lat)
    lon = np.linspace(0.0, 2 * np.pi, n)
    ring = np.cos(lon)[:, None] * e1 + np.sin(lon)[:, None] * e2  # (n, 3)
    return a + along[:, None, None] * u + rho[:, None, None] * ring


def _surface(ax, mesh: np.ndarray, colour, alpha: float, gid: str):
    return ax.plot_surface(*mesh.transpose(2, 0, 1), color=colour, alpha=alpha, shade=True, linewidth=0, gid=gid)


def _segments(chain: Chain, capsules: Capsules, q: torch.Tensor) -> np.ndarray:
    """Capsule end points ``(K, 2, 3)`` in the world frame at one configuration, metres."""
    with torch.no_grad():
        frames = chain.fk_all(q)[0, list(capsules.frames)]  # (K, 4, 4)
        pts = capsules.points.to(frames) @ frames[:, :3, :3].transpose(-1, -2) + frames[:, None, :3, 3]
    return pts.cpu().numpy()


def draw_capsules(ax, chain: Chain, q, capsules: Capsules | None = None, *, colliding=(), alpha: float = 0.35) -> list:
    """Draw the capsules (default ``robot_capsules(chain)``) at ``q (n,)`` rad; return one surface per
    capsule, ``gid = "capsule:<name>"``, red if its name is in ``colliding``."""
    q = _as_q(chain, q, one="draw_capsules")
    capsules = robot_capsules(chain) if capsules is None else capsules
    ends = _segments(chain, capsules, q)
    colliding = set(colliding)
    return [
        _surface(
            ax,
            _capsule_mesh(a, b, r),
            _COLLISION_COLOUR if name in colliding else _CAPSULE_COLOUR,
            min(1.0, 1.6 * alpha) if name in colliding else alpha,
            f"capsule:{name}",
        )
        for name, (a, b), r in zip(capsules.names, ends, capsules.radii.tolist())
    ]


def draw_obstacles(ax, world: World, *, colliding=(), alpha: float = 0.6) -> list:
    """Draw an unbatched :class:`~iiwa_torch.collision.World` (no walls) on a 3-D axes; return the artists.

    The floor spans the axes' x/y limits; the shapes' ``gid`` are ``floor``, ``sphere<i>``, ``box<i>``,
    ``capsule<i>``, red when in ``colliding``.
    """
    Poly3DCollection = require("mpl_toolkits.mplot3d.art3d", "viz").Poly3DCollection

    _check_one_world(world)
    colliding = set(colliding)

    def colour(label):
        return _COLLISION_COLOUR if label in colliding else _OBSTACLE_COLOUR

    artists = []
    if world.floor is not None:
        (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
        square = [[(x0, y0, world.floor), (x1, y0, world.floor), (x1, y1, world.floor), (x0, y1, world.floor)]]
        floor = Poly3DCollection(square, facecolor="tab:olive", edgecolor="0.4", alpha=0.15, gid="floor")
        ax.add_collection3d(floor)
        artists.append(floor)
    for kind in ("sphere", "capsule"):  # a sphere is a capsule with both ends at its centre
        if getattr(world, kind + "s") is not None:
            for i, (p, r) in enumerate(zip(*_numpy(getattr(world, kind + "s")))):
                a, b = (p, p) if kind == "sphere" else p
                artists.append(_surface(ax, _capsule_mesh(a, b, float(r)), colour(f"{kind}{i}"), alpha, f"{kind}{i}"))
    if world.boxes is not None:
        for i, corners in enumerate(_box_corners(world)):
            faces = [corners[list(f)] for f in _BOX_FACES]
            shaded = _shade(faces, colour(f"box{i}"), alpha)
            box = Poly3DCollection(faces, facecolor=shaded, edgecolor="0.3", lw=0.5, gid=f"box{i}")
            ax.add_collection3d(box)
            artists.append(box)
    return artists


def _check_one_world(world: World) -> None:
    for kind in ("walls", "spheres", "boxes", "capsules"):
        pair = getattr(world, kind)
        if pair is not None and pair[1].ndim != (2 if kind == "boxes" else 1):
            batch = tuple(pair[1].shape[: -2 if kind == "boxes" else -1])
            raise ValueError(f"only one world can be drawn, got {kind} with batch shape {batch}")


def _numpy(pair) -> list[np.ndarray]:
    """One of a world's tensor pairs as float64 numpy arrays."""
    return [t.detach().cpu().double().numpy() for t in pair]


def _box_corners(world: World) -> np.ndarray:
    """Corners ``(B, 8, 3)`` of an unbatched world's boxes, metres (bit 2, 1, 0 of the index: x, y, z side)."""
    pose, half = _numpy(world.boxes)
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
    return (signs * half[:, None]) @ pose[:, :3, :3].transpose(0, 2, 1) + pose[:, None, :3, 3]


def _bounds(chain: Chain, q: torch.Tensor, world: World, capsules: Capsules) -> np.ndarray:
    """Lower and upper corners ``(2, 3)`` of a box holding the capsules, the base, the obstacles and
    the floor's height."""
    ends = _segments(chain, capsules, q)
    r = capsules.radii.numpy()[:, None, None]
    points = [ends - r, ends + r, chain.base[None, :3, 3].cpu().numpy()]
    for kind in ("spheres", "capsules"):  # centres (S, 3) or end points (C, 2, 3), radii (S,) or (C,)
        if getattr(world, kind) is not None:
            centres, radii = _numpy(getattr(world, kind))
            pad = radii.reshape(radii.shape + (1,) * (centres.ndim - 1))
            points += [centres - pad, centres + pad]
    if world.boxes is not None:
        points.append(_box_corners(world))
    points = np.concatenate([p.reshape(-1, 3) for p in points])
    if world.floor is not None:
        points = np.concatenate([points, [[points[0, 0], points[0, 1], world.floor]]])
    return np.stack([points.min(0), points.max(0)])


def _fit_cube(ax, bounds: np.ndarray, margin: float = 0.08) -> None:
    """Equal-aspect limits: a cube ``margin`` (fraction) wider than the box ``bounds (2, 3)``."""
    centre, half = bounds.mean(0), (1 + margin) * (bounds[1] - bounds[0]).max() / 2
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_zlim(centre[2] - half, centre[2] + half)


def _shade(faces, colour, alpha: float) -> np.ndarray:
    """Face colours lit like matplotlib's shaded surfaces (lighter facing the default light)."""
    colors = require("matplotlib.colors", "viz")
    LightSource, to_rgba = colors.LightSource, colors.to_rgba

    normals = np.array([np.cross(f[1] - f[0], f[2] - f[0]) for f in faces])
    centre = np.mean([f.mean(0) for f in faces], 0)
    outward = np.sign(np.einsum("ij,ij->i", normals, [f.mean(0) - centre for f in faces]))[:, None]
    normals = normals * outward / np.linalg.norm(normals, axis=1, keepdims=True)
    light = LightSource(azdeg=225, altdeg=19.4712).direction
    level = 0.35 + 0.65 * (normals @ light).clip(0, 1)
    rgba = np.array(to_rgba(colour, alpha))
    return np.concatenate([rgba[:3] * level[:, None], np.full((len(faces), 1), alpha)], 1)


def plot_world(
    chain: Chain,
    q,
    world: World | None = None,
    capsules: Capsules | None = None,
    *,
    ax=None,
    path=None,
    title: str | None = None,
    size: tuple[int, int] = (640, 640),
    elev: float = 20.0,
    azim: float = -60.0,
    dpi: int = 100,
):
    """Draw the arm at ``q (n,)`` rad with its capsules and the obstacles, shapes in collision red and
    the minimum clearance (mm) in the title; return the figure.

    ``world=None``: the capsule model's floor; ``capsules=None``: ``robot_capsules(chain)``; ``ax``: a
    3-D axes (default a new figure of ``size`` pixels); ``path``: also write a PNG there.
    """
    q = _as_q(chain, q, one="plot_world")
    capsules = robot_capsules(chain) if capsules is None else capsules
    world = World(floor=capsules.floor_height) if world is None else world
    _check_one_world(world)
    obstacles = world.tensors()
    res = pairwise_clearance(chain, q[0].to(obstacles[0]) if obstacles else q[0], world, capsules)
    robot_hits, obstacle_hits = set(), set()
    for k, ((a, b), d) in enumerate(zip(res.pairs, res.distance.tolist())):
        if d < 0:  # the self pairs come first, then (capsule, obstacle) pairs
            robot_hits.add(a)
            (robot_hits if k < len(capsules.pairs) else obstacle_hits).add(b)
    if ax is None:
        _, _, ax = _scene(chain, size, dpi, elev, azim)
        _fit_cube(ax, _bounds(chain, q, world, capsules))
    draw_obstacles(ax, world, colliding=obstacle_hits)
    draw_chain(ax, chain, q, color="tab:orange")
    draw_capsules(ax, chain, q, capsules, colliding=robot_hits)
    worst = int(res.distance.argmin())
    text = f"min clearance {1000 * res.distance[worst].item():.1f} mm ({' - '.join(res.pairs[worst])})"
    _draw_extras(ax, None, None, f"{title}: {text}" if title else text)
    if path is not None:
        ax.figure.savefig(path, dpi=dpi)
    return ax.figure
