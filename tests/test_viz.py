"""Drawing and animation: off-screen images of the right size, no pyplot state, GIF frame counts."""

import math
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch

from iiwa_torch import robots, viz

F64 = torch.float64
Q_VALIDATION = torch.tensor([0, 0, 0, -math.pi / 2, math.pi / 3, 0, 0], dtype=F64)


@pytest.fixture(scope="module")
def arm():
    return robots.iiwa14(flange=0.090)


def test_import_is_lazy():
    code = (
        "import sys, iiwa_torch, iiwa_torch.viz, iiwa_torch.trajectory, iiwa_torch.cli\n"
        "assert 'matplotlib' not in sys.modules, 'matplotlib imported with iiwa_torch'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_rendering_leaves_pyplot_alone(arm):
    had_pyplot = "matplotlib.pyplot" in sys.modules
    before = sys.modules["matplotlib.pyplot"].get_fignums() if had_pyplot else None
    viz.render_rgb(arm, Q_VALIDATION, size=(64, 64))
    if had_pyplot:  # another test imported it: no figure may have been added to its registry
        assert sys.modules["matplotlib.pyplot"].get_fignums() == before
    else:
        assert "matplotlib.pyplot" not in sys.modules


def test_render_rgb_size_dtype_and_content(arm):
    img = viz.render_rgb(arm, Q_VALIDATION, size=(320, 240))
    assert img.shape == (240, 320, 3) and img.dtype == np.uint8
    orange = (img[..., 0] > 200) & (img[..., 1] > 100) & (img[..., 1] < 170) & (img[..., 2] < 60)
    assert orange.sum() > 200  # the links are drawn (tab:orange)
    with_goal = viz.render_rgb(arm, Q_VALIDATION, goal=torch.tensor([0.3, -0.4, 0.5], dtype=F64), size=(320, 240))
    red = (with_goal[..., 0] > 180) & (with_goal[..., 1] < 80) & (with_goal[..., 2] < 80)
    assert red.sum() > 20 and ((img[..., 0] > 180) & (img[..., 1] < 80) & (img[..., 2] < 80)).sum() < red.sum()


def test_draw_chain_overlays_configurations_at_the_fk_points(arm):
    from matplotlib.figure import Figure

    ax = Figure().add_subplot(projection="3d")
    qs = torch.stack([Q_VALIDATION, torch.zeros(7, dtype=F64), Q_VALIDATION * 0.5])
    artists = viz.draw_chain(ax, arm, qs, color="k", alpha=0.5, label="arm")
    lines = [a for a in artists if a in ax.lines]
    assert len(lines) == 3  # one polyline per configuration
    assert [line.get_label() for line in lines][0] == "arm" and lines[1].get_label().startswith("_")
    for line, q in zip(lines, qs):
        x, y, z = line.get_data_3d()
        assert (x[0], y[0], z[0]) == (0.0, 0.0, 0.0)  # the base
        np.testing.assert_allclose([x[-1], y[-1], z[-1]], arm.fk(q)[:3, 3].numpy(), atol=1e-12)  # the flange
    # the validation pose's flange, from the seed paper: (0.490, 0, 0.780)
    np.testing.assert_allclose([a[-1] for a in lines[0].get_data_3d()], [0.49, 0.0, 0.78], atol=1e-12)
    with_frames = viz.draw_chain(ax, arm, Q_VALIDATION, frames=True)
    assert len(with_frames) == 3 + 3 * 8  # links, joints, end effector, 3 axes of 8 frames


def test_draw_chain_default_colour_follows_the_cycle(arm):
    from matplotlib.figure import Figure

    ax = Figure().add_subplot(projection="3d")
    first = viz.draw_chain(ax, arm, torch.zeros(2, 7, dtype=F64))
    second = viz.draw_chain(ax, arm, Q_VALIDATION)
    assert first[0].get_color() == first[3].get_color()  # both configurations of one call
    assert second[0].get_color() != first[0].get_color()  # the next call: the next colour


def test_draw_chain_rejects_bad_shapes(arm):
    from matplotlib.figure import Figure

    ax = Figure().add_subplot(projection="3d")
    with pytest.raises(ValueError, match=r"\(7,\) or \(k, 7\)"):
        viz.draw_chain(ax, arm, torch.zeros(2, 3, 7, dtype=F64))
    with pytest.raises(ValueError, match=r"\(\.\.\., 7\)"):
        viz.draw_chain(ax, arm, torch.zeros(6, dtype=F64))


def test_animate_gif_has_one_frame_per_step(arm, tmp_path):
    from PIL import Image

    qs = Q_VALIDATION + torch.linspace(0, 0.6, 7, dtype=F64)[:, None]
    out = viz.animate(arm, qs, tmp_path / "move.gif", fps=10, size=(160, 160))
    with Image.open(out) as gif:
        assert gif.n_frames == 7
        assert gif.size == (160, 160)
        assert gif.info["duration"] == 100
    assert out.stat().st_size < 200_000


def test_animate_rejects_bad_files_and_rates(arm, tmp_path):
    qs = torch.zeros(3, 7, dtype=F64)
    with pytest.raises(ValueError, match=r"\.gif or \.mp4"):
        viz.animate(arm, qs, tmp_path / "x.avi")
    for fps in (0, float("nan"), float("inf"), "10"):  # NaN failed only after every frame was drawn
        with pytest.raises(ValueError, match="fps must be a positive number"):
            viz.animate(arm, qs, tmp_path / "x.gif", fps=fps)
    with pytest.raises(ValueError, match=r"q must hold at least one configuration to draw, got \(0, 7\)"):
        viz.animate(arm, qs[:0], tmp_path / "x.gif")
    with pytest.raises(ValueError, match=r"path must be positions .* got \(4, 2\)"):
        viz.animate(arm, qs, tmp_path / "x.gif", path=torch.zeros(4, 2, dtype=F64))
    with pytest.raises(ValueError, match="goal contains NaN or inf"):
        viz.save_png(arm, qs[0], tmp_path / "x.png", goal=torch.full((3,), float("nan"), dtype=F64))
    with pytest.raises(ValueError, match="dpi must be a positive number"):
        viz.save_png(arm, qs[0], tmp_path / "x.png", dpi=0)
    if shutil.which("ffmpeg") is None:
        with pytest.raises(RuntimeError, match="ffmpeg"):
            viz.animate(arm, qs, tmp_path / "x.mp4")
    else:
        assert viz.animate(arm, qs, tmp_path / "x.mp4", size=(96, 96)).stat().st_size > 0


def test_save_png(arm, tmp_path):
    from PIL import Image

    out = viz.save_png(arm, Q_VALIDATION, tmp_path / "arm.png", size=(200, 150), frames=True, title="validation")
    with Image.open(out) as png:
        assert png.size == (200, 150)


def _surfaces(fig, prefix="capsule:"):
    return [c for ax in fig.axes for c in ax.collections if (c.get_gid() or "").startswith(prefix)]


def _is_red(surface):
    rgb = np.asarray(surface.get_facecolor())[:, :3]
    return bool((rgb[:, 0] > 1.8 * rgb[:, 1:].max(1)).all())


def test_plot_world_draws_capsules_obstacles_and_the_clearance(arm, tmp_path):
    from PIL import Image

    from iiwa_torch.collision import World, clearance, robot_capsules

    box = torch.eye(4, dtype=F64)
    box[:3, 3] = torch.tensor([0.6, 0.3, 0.15], dtype=F64)
    world = World(
        floor=0.0,
        spheres=(torch.tensor([[0.5, -0.3, 0.4]], dtype=F64), torch.tensor([0.1], dtype=F64)),
        boxes=(box[None], torch.tensor([[0.1, 0.1, 0.15]], dtype=F64)),
        capsules=(torch.tensor([[[-0.5, 0.5, 0.2], [-0.5, -0.5, 0.2]]], dtype=F64), torch.tensor([0.05], dtype=F64)),
    )
    fig = viz.plot_world(arm, Q_VALIDATION, world, path=tmp_path / "world.png", size=(300, 200))
    names = robot_capsules(arm).names
    assert [s.get_gid() for s in _surfaces(fig)] == [f"capsule:{n}" for n in names]  # K = 4 surfaces
    assert {c.get_gid() for c in fig.axes[0].collections} >= {"floor", "sphere0", "box0", "capsule0"}
    d = clearance(arm, Q_VALIDATION, world).item()
    assert d > 0 and not any(_is_red(s) for s in _surfaces(fig))
    title = fig.axes[0].texts[-1].get_text()
    assert f"min clearance {1000 * d:.1f} mm" in title
    ax = fig.axes[0]
    lims = np.array([ax.get_xlim(), ax.get_ylim(), ax.get_zlim()])
    np.testing.assert_allclose(np.diff(lims, axis=1), np.diff(lims[:1], axis=1).repeat(3, 0))  # equal aspect
    inside = [(0.7, 0.4, 0.3), (0.5, -0.4, 0.3), (-0.55, 0.5, 0.15), (0.49, 0.0, 0.78), (0.0, 0.0, 0.0)]
    assert ((lims[:, 0] < np.array(inside)) & (np.array(inside) < lims[:, 1])).all()  # box, sphere, capsule, flange
    with Image.open(tmp_path / "world.png") as png:
        assert png.size == (300, 200)


def test_plot_world_colours_the_colliding_capsules_red(arm):
    from iiwa_torch.collision import World, clearance

    # a 3 cm sphere on the forearm's axis, half way along it: frame 4, z = l_ew / 2 = 0.2 m
    frame4 = arm.fk_all(Q_VALIDATION)[4]
    centre = frame4[:3, 3] + 0.2 * frame4[:3, 2]
    world = World(floor=0.0, spheres=(centre[None], torch.tensor([0.03], dtype=F64)))
    fig = viz.plot_world(arm, Q_VALIDATION, world, size=(200, 200))
    red = {s.get_gid() for s in _surfaces(fig) if _is_red(s)}
    assert red == {"capsule:forearm"}
    assert _is_red(_surfaces(fig, "sphere0")[0])
    d = clearance(arm, Q_VALIDATION, world).item()
    assert -0.111 < d < -0.109  # the forearm's radius 0.08 plus the sphere's 0.03, overlapping
    assert f"min clearance {1000 * d:.1f} mm" in fig.axes[0].texts[-1].get_text()


def test_plot_world_self_collision_and_bad_input(arm):
    from matplotlib.figure import Figure

    from iiwa_torch.collision import pairwise_clearance

    q = torch.tensor([0.0, 2.0, 0.0, -2.0, 0.0, 0.0, 0.0], dtype=F64)  # bent down: forearm into the base and floor
    res = pairwise_clearance(arm, q)
    hit = {name for pair, dist in zip(res.pairs, res.distance.tolist()) if dist < 0 for name in pair} - {"floor"}
    assert hit  # the configuration does collide
    ax = Figure().add_subplot(projection="3d")
    fig = viz.plot_world(arm, q, ax=ax)
    assert fig is ax.figure
    assert {s.get_gid() for s in _surfaces(fig) if _is_red(s)} == {f"capsule:{n}" for n in hit}
    with pytest.raises(ValueError, match="one configuration"):
        viz.plot_world(arm, torch.zeros(2, 7, dtype=F64))


def test_plot_world_float32_world_and_batched_world_rejected(arm):
    from iiwa_torch.collision import World, clearance

    centre = torch.tensor([[0.5, 0.0, 0.6]], dtype=torch.float32)
    world = World(floor=0.0, spheres=(centre, torch.tensor([0.1], dtype=torch.float32)))
    fig = viz.plot_world(arm, Q_VALIDATION, world, size=(120, 120))
    d = clearance(arm, Q_VALIDATION.float(), world).item()
    assert f"min clearance {1000 * d:.1f} mm" in fig.axes[0].texts[-1].get_text()
    batched = World(spheres=(centre.double().expand(2, 1, 3), torch.full((2, 1), 0.1, dtype=F64)))
    with pytest.raises(ValueError, match=r"one world can be drawn, got spheres with batch shape \(2,\)"):
        viz.plot_world(arm, Q_VALIDATION, batched)


def _screen_length(a, b, azim: float, elev: float = 20.0) -> float:
    """Length on screen of the segment ``a``-``b`` (m) under matplotlib's own 3-D projection."""
    from matplotlib.figure import Figure
    from mpl_toolkits.mplot3d import proj3d

    ax = Figure().add_subplot(projection="3d")
    ax.set(xlim=(-1, 1), ylim=(-1, 1), zlim=(-1, 1))
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=elev, azim=azim)
    xs, ys, _ = proj3d.proj_transform(*np.stack([a, b], 1), ax.get_proj())
    return math.hypot(xs[1] - xs[0], ys[1] - ys[0])


@pytest.mark.parametrize(
    "points, expected",
    [
        (np.array([[0.5, y, 0.4] for y in np.linspace(-0.2, 0.3, 9)]), -25.0),  # along y: side view from +x, less 25
        (np.array([[x, -0.4, 0.4] for x in np.linspace(-0.2, 0.3, 9)]), -65.0),  # along x, at y < 0: from -y, +25
        (np.array([[0.5, 0.0, z] for z in np.linspace(0.2, 0.6, 9)]), -60.0),  # vertical: the default
    ],
)
def test_side_view_faces_the_motion(points, expected):
    azim = viz.side_view(points)
    assert azim == pytest.approx(expected, abs=1e-9)
    if expected != -60.0:  # brute force over the camera's azimuth: within cos(25 deg) of the longest on screen
        best = max(_screen_length(points[0], points[-1], a) for a in range(-180, 180, 5))
        assert _screen_length(points[0], points[-1], azim) >= 0.9 * best
