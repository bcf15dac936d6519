"""The report's figures: final errors, success against tolerance, times, path lengths, learning curves
and, for an env with obstacles, a few rollouts drawn among them."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from iiwa_torch.checks import require

from .metrics import FLOOR_SPACINGS, TOLERANCES

__all__ = ["make_plots", "picture_goals", "PICTURE_GOALS"]


def make_plots(out: Path, data: dict[str, dict[str, np.ndarray]], report: dict[str, Any],
               evaluations: list[dict], compare: dict[str, list[dict]], goals=None) -> list[str]:
    """Write the report's PNGs into ``out``; returns their file names. With ``goals`` (the
    :class:`train.rollout.GoalSet`) of an env with obstacles, also ``rollouts_obstacles.png``."""
    matplotlib = require("matplotlib", "viz")
    matplotlib.use("Agg")
    plt = require("matplotlib.pyplot", "viz")
    errors = {n: d["final_error"] for n, d in data.items()}
    figures = {
        "final_error.png": _plot_final_error(plt, errors, report),
        "success_vs_tolerance.png": _plot_failure_rate(plt, matplotlib.ticker, errors, report),
        "time_per_goal.png": _plot_times(plt, list(data), report),
        "path_length.png": _plot_paths(plt, data),
    }
    if evaluations:
        figures["learning_curve.png"] = _learning_curves(plt, report, evaluations, compare)
    for name, fig in figures.items():
        fig.tight_layout()
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
    written = list(figures)
    if goals is not None and goals.obstacles is not None and "q_path" in data.get("policy", {}):
        fig = _rollouts_obstacles(goals, data, report)
        fig.savefig(out / "rollouts_obstacles.png", dpi=100)
        written.append("rollouts_obstacles.png")
    return written


def _error_range(errors: dict[str, np.ndarray]) -> tuple[float, float]:
    """Decades ``(lo, hi)`` (m) that hold every non-zero final error, and 1 cm."""
    positive = np.concatenate([e[e > 0] for e in errors.values()])
    lo = 10.0 ** math.floor(math.log10(positive.min())) if positive.size else 1e-9  # no non-zero error is clipped
    hi = 10.0 ** math.ceil(math.log10(max(positive.max(), 0.011))) if positive.size else 1.0
    return lo, hi


def _plot_final_error(plt, errors: dict[str, np.ndarray], report: dict[str, Any]):
    """Histogram of each method's final position error, log bins, exact zeros in a bin of their own."""
    lo, hi = _error_range(errors)
    per_decade = 4
    bins = np.logspace(math.log10(lo), math.log10(hi), round(per_decade * math.log10(hi / lo)) + 1)
    zero_at = lo * 10 ** (-4 / per_decade)  # exact zeros: a bin of their own, left of the first bin, with a gap
    has_zero = any((e == 0).any() for e in errors.values())
    fig, ax = plt.subplots(figsize=(9, 4.2))
    for i, (n, e) in enumerate(errors.items()):
        counts, _ = np.histogram(e[e > 0], bins=bins)
        line = ax.stairs(counts, bins, lw=1.6, label=n, color=f"C{i}")
        if has_zero and (e == 0).any():
            ax.stairs([int((e == 0).sum())], zero_at * 10 ** (np.array([-0.5, 0.5]) / per_decade), lw=1.6,
                      color=line.get_edgecolor(), hatch="///")
    _floor_bands(ax, report.get("number_spacing_m"), lo)
    ax.axvline(TOLERANCES["1cm"], color="k", ls=":", lw=1.2, label="1 cm (the env's success)")
    ax.set(xscale="log", xlabel="final position error (m)", ylabel="goals", xlim=(zero_at / 3 if has_zero else lo, hi),
           title=f"Final error per method ({report['goals']} goals; {per_decade} bins per decade, none clipped)")
    if has_zero:
        ticks = [t for t in ax.get_xticks() if lo <= t <= hi]
        ax.set_xticks([zero_at, *ticks], ["0\n(exact)", *[f"$10^{{{round(math.log10(t))}}}$" for t in ticks]])
        ax.axvline(lo * 10 ** (-2 / per_decade), color="0.4", lw=0.8)  # the axis break before the zero bin
    ax.legend(fontsize=8, loc="upper right")
    return fig


def _plot_failure_rate(plt, ticker, errors: dict[str, np.ndarray], report: dict[str, Any]):
    """Each method's share of goals beyond a tolerance, against the tolerance."""
    lo, hi = _error_range(errors)
    fig, ax = plt.subplots(figsize=(9, 4.2))
    tol = np.logspace(math.log10(lo), math.log10(hi), 400)
    styles = ("-", "--", "-.", ":")
    for i, (n, e) in enumerate(errors.items()):
        beyond = 100 * (e[:, None] >= tol).mean(0)
        ax.plot(tol, beyond, styles[i % len(styles)], lw=2.2 - 0.4 * i, color=f"C{i}", label=n)
    _floor_bands(ax, report.get("number_spacing_m"), lo)
    for t, label in ((TOLERANCES["1mm"], "1 mm"), (TOLERANCES["1cm"], "1 cm")):
        ax.axvline(t, color="k", ls=":", lw=1)
        ax.text(t, 30, f" {label}", fontsize=8)
    one_goal = 100 / report["goals"]
    ax.set_yscale("symlog", linthresh=one_goal, linscale=0.5)
    ax.set(xscale="log", xlim=(lo, hi), ylim=(0, 100), xlabel="tolerance (m)",
           ylabel="goals beyond the tolerance (%)",
           title=f"Failure rate against tolerance (100% - success; one goal = {one_goal:.2g}%)")
    ax.yaxis.set_major_formatter(ticker.FuncFormatter(lambda y, _: f"{y:g}%"))
    ax.legend(fontsize=8, loc="lower left", bbox_to_anchor=(0.2, 0.08))
    return fig


def _plot_times(plt, names: list[str], report: dict[str, Any]):
    """Wall time per goal of each method, batched and one goal at a time."""
    fig, ax = plt.subplots(figsize=(7, 4))
    x = np.arange(len(names))
    m = report["methods"]
    ax.bar(x - 0.2, [m[n]["time_per_goal_batched_s"] * 1e3 for n in names], 0.4, label=f"batched ({report['goals']})")
    ax.bar(x + 0.2, [m[n]["time_per_goal_single_s"] * 1e3 for n in names], 0.4, label="single goal")
    ax.set(yscale="log", xticks=x, xticklabels=names, ylabel="ms per goal",
           title="Wall time per goal (policy: all 50 steps)")
    ax.legend()
    return fig


def _plot_paths(plt, data: dict[str, dict[str, np.ndarray]]):
    """Histogram of each method's joint-space path length."""
    fig, ax = plt.subplots(figsize=(7, 4))
    top = max(float(np.percentile(d["path"], 99.5)) for d in data.values())
    for n, d in data.items():
        ax.hist(d["path"], bins=np.linspace(0, top, 50), histtype="step", lw=1.5, label=n)
    ax.set(xlabel="joint-space path length (rad)", ylabel="goals",
           title="Joint-space path length (IK: straight move from home)")
    ax.legend()
    return fig

PICTURE_GOALS = 4  # rollouts drawn in rollouts_obstacles.png


def picture_goals(collided: np.ndarray, failed: np.ndarray, obstacle_count: np.ndarray, k: int = PICTURE_GOALS
                  ) -> list[int]:
    """Up to ``k`` goal indices to draw: the first goal whose rollout collided, the first that failed
    (if any), then the successful collision-free goals with the most obstacles (lowest index first)."""
    chosen = []
    for mask in (collided, failed & ~collided):
        hits = np.flatnonzero(mask)
        if hits.size and len(chosen) < k:
            chosen.append(int(hits[0]))
    clean = np.flatnonzero(~collided & ~failed)
    for i in clean[np.argsort(-obstacle_count[clean], kind="stable")]:
        if len(chosen) == k:
            break
        chosen.append(int(i))
    return chosen


def _rollouts_obstacles(goals, data: dict[str, dict[str, np.ndarray]], report: dict[str, Any]):
    """The figure of a few policy rollouts among their goals' obstacles: per goal, the end effector's path
    from home, the arm at home (faint) and at the end with its capsules, the obstacles, the goal."""
    mlines = require("matplotlib.lines", "viz")
    Figure = require("matplotlib.figure", "viz").Figure

    from envs.world import SLOT_SIZE

    p = data["policy"]
    count = goals.obstacles.reshape(goals.n, -1, SLOT_SIZE)[..., 0].round().sum(-1).astype(int)
    failed = p["final_error"] >= TOLERANCES["1cm"]
    chosen = picture_goals(p["collided"], failed, count)
    why = [w for w, mask in (("the first colliding rollout", p["collided"]),
                             ("the first miss", failed & ~p["collided"])) if mask.any()]
    fig = Figure(figsize=(12, 11.5), dpi=100)
    cols = 2
    rows = math.ceil(len(chosen) / cols)
    for k, i in enumerate(chosen):
        ax = fig.add_subplot(rows, cols, k + 1, projection="3d")
        path_clearance = _draw_rollout(ax, goals, p, i)
        reached = "reached" if not failed[i] else "missed"
        hit = "collided on the way" if p["collided"][i] else "no collision"
        ax.set_title(f"goal {i} ({count[i]} obstacle{'s' if count[i] != 1 else ''}): {reached}, final error "
                     f"{1e3 * p['final_error'][i]:.3g} mm;\n{hit}, min clearance along the path "
                     f"{1e3 * path_clearance:.0f} mm", fontsize=9)
    handles = [mlines.Line2D([], [], color="tab:purple", ls="--", lw=2, label="end-effector path from home (dot)"),
               mlines.Line2D([], [], color="0.6", lw=3, label="arm at home (start)"),
               mlines.Line2D([], [], color="tab:orange", lw=3, label="arm at the end, capsules blue"),
               mlines.Line2D([], [], color="tab:red", marker="*", ls="", ms=14, label="goal"),
               mlines.Line2D([], [], color="0.55", marker="s", ls="", ms=10, label="obstacles (spheres, boxes)"),
               mlines.Line2D([], [], color="tab:red", marker="s", ls="", ms=10, alpha=0.6,
                             label="in collision at the end")]
    fig.legend(handles=handles, loc="lower center", ncol=3, fontsize=9, frameon=False)
    fig.suptitle(f"Policy rollouts among the obstacles ({report['env_id']}, {report['algo'].upper()}; "
                 f"{len(chosen)} of {report['goals']} goals: {', '.join(why + ['the most crowded successes'])})",
                 fontsize=11)
    fig.subplots_adjust(left=0.02, right=0.98, bottom=0.07, top=0.93, wspace=0.05, hspace=0.12)
    return fig


def _draw_rollout(ax, goals, p: dict[str, np.ndarray], i: int) -> float:
    """Draw the policy's rollout ``i`` (``p``: its data) on the 3-D axes ``ax``: the end effector's path, the
    arm at home and at the end, goal ``i``'s world and the goal; -> the least clearance along the path (m)."""
    import torch

    from iiwa_torch.collision import clearance
    from iiwa_torch.viz import draw_chain, plot_world, side_view

    chain = goals.robot
    q = torch.as_tensor(p["q_path"][:, i], dtype=torch.float64)
    ee = chain.fk(q)[:, :3, 3].double().numpy()  # (T + 1, 3)
    world = goals.goal_world(i)
    with torch.no_grad():
        joints = chain.fk_all(q[[0, -1]])[..., :3, 3].double().numpy().reshape(-1, 3)
    goal = goals.desired_goal[i, :3].astype(np.float64)
    points = [ee, joints, goal[None], np.zeros((1, 3))]
    for centre, size in ((world.spheres[0], world.spheres[1][:, None]), (world.boxes[0][:, :3, 3], world.boxes[1])):
        pad = size.numpy().max(-1, keepdims=True) * math.sqrt(3) if size.numel() else size.numpy()
        points += [centre.numpy() - pad, centre.numpy() + pad]
    pts = np.concatenate([x.reshape(-1, 3) for x in points])
    lo, hi = pts.min(0), pts.max(0)
    lo[2] = min(lo[2], goals.floor if goals.floor is not None else lo[2])
    centre, half = (lo + hi) / 2, 0.55 * (hi - lo).max()
    ax.set(xlim=(centre[0] - half, centre[0] + half), ylim=(centre[1] - half, centre[1] + half),
           zlim=(max(centre[2] - half, (goals.floor or 0.0) - 0.05), centre[2] + half))
    ax.set_box_aspect((1, 1, 1), zoom=0.9)
    ax.view_init(elev=22, azim=side_view(ee))
    # drawn in order, not depth-sorted: the path and the goal stay visible in front of arm and obstacles
    ax.computed_zorder = False
    plot_world(chain, q[-1], world, ax=ax, title="end")
    draw_chain(ax, chain, q[0], color="0.6", alpha=0.5)
    ax.plot(*ee.T, "--", color="tab:purple", lw=2)
    ax.scatter(*ee[0, :, None], color="tab:purple", marker="o", s=30, depthshade=False)
    ax.scatter(*goal[:, None], color="tab:red", marker="*", s=220, depthshade=False)
    for name in "xyz":
        getattr(ax, f"set_{name}label")(f"{name} (m)", fontsize=8)
    ax.tick_params(labelsize=7)
    return clearance(chain, q, world).min().item()


def _floor_bands(ax, spacing: dict[str, float] | None, lo: float) -> None:
    """Shade, per number format, the errors from ``lo`` (m) up to its floor, ``FLOOR_SPACINGS`` median spacings
    at the goals: rounding in that format (the float64 band lies inside the float32 one)."""
    for (name, value), colour in zip((spacing or {}).items(), ("0.93", "0.82")):
        ax.axvspan(lo, FLOOR_SPACINGS * value, color=colour, lw=0, zorder=0,
                   label=f"below {name}'s floor ({FLOOR_SPACINGS} spacings at the goals): rounding")


GAP_SHARE = 0.12  # a segment wider than this share of the axis and than 3 of its curve's median ones is a gap


def _plot_evaluations(ax, x: np.ndarray, y: np.ndarray, colour: str, label: str) -> None:
    """Markers at each evaluation, solid lines between neighbours, dotted across gaps: segments much wider
    than the curve's usual ones, in the axis' own scale (a log axis stretches the interval after step 0)."""
    t = ax.xaxis.get_transform().transform(x)
    lo, hi = ax.xaxis.get_transform().transform(np.array(ax.get_xlim()))
    span = np.abs(np.diff(t))
    wide = span > max(GAP_SHARE * abs(hi - lo), 3 * float(np.median(span))) if span.size else span.astype(bool)
    ax.plot(x, y, "o", ms=3.5, color=colour)
    ax.plot([], [], "o-", ms=3.5, color=colour, label=label)
    for i in range(len(x) - 1):
        ax.plot(x[i : i + 2], y[i : i + 2], ":" if wide[i] else "-", color=colour, lw=1 if wide[i] else 1.6)


def _learning_curves(plt, report: dict[str, Any], evaluations: list[dict], compare: dict[str, list[dict]]):
    """The figure of success against training wall time and env steps, this run and ``compare``'s."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    ours = f"{report['env_id']} (ours, {report['algo'].upper()}, {100 * TOLERANCES['1cm']:.0f} cm)"
    curves = {ours: evaluations, **compare}
    steps = np.concatenate([[e["steps"] for e in ev] for ev in curves.values()]).astype(float)
    walls = np.concatenate([[e["wall_time"] for e in ev] for ev in curves.values()]).astype(float)
    first = steps[steps > 0].min() if (steps > 0).any() else 1.0
    # symlog: linear up to the first non-zero evaluation, so step 0 (an untrained policy) is on the axis
    axes[1].set_xscale("symlog", linthresh=first, linscale=0.6)
    axes[0].set_xlim(0, 1.03 * walls.max())
    axes[1].set_xlim(0, 1.5 * steps.max())
    decades = 10.0 ** np.arange(math.ceil(math.log10(first)), math.floor(math.log10(1.5 * steps.max())) + 1)
    axes[1].set_xticks([0, *decades])
    for i, (label, ev) in enumerate(curves.items()):
        success = np.array([100 * e["success"] for e in ev])
        _plot_evaluations(axes[0], np.array([e["wall_time"] for e in ev], float), success, f"C{i}", label)
        _plot_evaluations(axes[1], np.array([e["steps"] for e in ev], float), success, f"C{i}", label)
    axes[0].set(xlabel="training wall time (s)", ylabel="success (%)", title="Learning curve against wall time")
    axes[1].set(xlabel=f"env steps (linear up to {first:,.0f}, then log)", ylabel="success (%)",
                title="Learning curve against env steps")
    for a in axes:
        a.plot([], [], ":", color="0.4", label="a long stretch without an evaluation")
        a.legend(fontsize=8, loc="lower right")
        a.set_ylim(0, 102)
    return fig
