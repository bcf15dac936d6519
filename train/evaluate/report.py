"""The report's words: the verdict (where the policy loses to the IK solvers and where it wins), what the
policy is built on, and the markdown table."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from .metrics import FLOOR_SPACINGS

__all__ = ["design_note", "verdict", "write_markdown"]


def design_note(config: dict[str, Any], trained_in) -> list[str]:
    """What the policy is built on, when it is not a plain network, and what its training env checked
    (``trained_in``: the :class:`envs.core.ReachTask` of its config), so the comparison stays honest."""
    from envs.core import CollisionKind

    if trained_in.collision is CollisionKind.OFF:
        lines = ["The policy was trained without a floor or a self-collision term (collision='off'): nothing in "
                 "its reward keeps it clear."]
    else:
        what = f"the floor, self-collision and 1-{trained_in.world.slots} obstacles" if trained_in.world.slots \
            else "the floor and self-collision"
        lines = [f"The policy was trained with {what} checked (collision="
                 f"'{trained_in.collision.value}', a colliding step costs {trained_in.collision_penalty:g})."]
    if config["hyperparams"].get("policy") == "ResidualDLSPolicy":
        lines.append("How the policy is built: its action is a damped-least-squares joint step (the library's "
                     "Jacobian, inside the network) plus a learned correction that fades near the goal; the "
                     "row 'controller' is that step alone, without the network.")
        avoidance = (config["hyperparams"].get("features_extractor_kwargs") or {}).get("avoidance")
        if avoidance:
            lines.append("A velocity damper (Faverjon and Tournassoud) keeps that step and the whole action from "
                         "closing any link's clearance by more than {xi:g} of its excess over {safe:g} m per step, "
                         "from the clearances and gradients the env observes (observe_clearance).".format(**avoidance))
    return lines


def _cmp(policy: float, other: float, lower_wins: bool = True) -> str:
    return "wins" if (policy < other) == lower_wins else "loses"


def _floor(value: float, spacing: dict[str, float] | None) -> tuple[str, float] | None:
    """``(format, spacings)`` if the error ``value`` (m) is within ``FLOOR_SPACINGS`` of that format's
    median ``spacing`` (m) at the goals (float64 tried first), else None: rounding, not accuracy."""
    for name in ("float64", "float32") if spacing else ():
        if value <= FLOOR_SPACINGS * spacing[name]:
            return name, value / spacing[name]
    return None


def _error(value: float, spacing: dict[str, float] | None) -> str:
    """An error (m) in mm, with the number format's floor it sits at, if any."""
    floor = _floor(value, spacing)
    return f"{1e3 * value:.3g} mm" + ("" if floor is None or value == 0 else f" (at {floor[0]}'s floor)")


def _median_comparison(p: float, v: float, name: str, spacing: dict[str, float] | None) -> str:
    """How the two median errors (m) compare, without ranking rounding against rounding."""
    pf, vf = _floor(p, spacing), _floor(v, spacing)
    if pf is None and vf is None:
        ratio = p / max(v, 1e-300)
        if 0.1 < ratio < 10:
            return f"{ratio:.2g} times {name}'s"
        return f"{abs(math.log10(ratio)):.1f} orders of magnitude {'above' if ratio > 1 else 'below'} {name}'s"
    if pf is not None and vf is not None:
        if pf[0] == vf[0]:
            return (f"both are {pf[0]} rounding ({pf[1]:.1f} and {vf[1]:.1f} {pf[0]} spacings at the goal), so the "
                    f"medians do not rank the two")
        env = " (its env computes distances in float32)" if pf[0] == "float32" else ""
        return (f"both are rounding, not accuracy: the policy's is {pf[1]:.1f} {pf[0]} spacings at the goal{env}, "
                f"{name}'s {vf[1]:.1f} {vf[0]} spacings; the gap between them is the number format")
    (at, fmt, k), real = (("the policy", *pf), name) if pf is not None else ((name, *vf), "the policy")
    return (f"{at}'s is {fmt} rounding ({k:.1f} spacings at the goal) and {real}'s is not: {real} is the less "
            f"accurate at the median")


def verdict(m: dict[str, dict[str, Any]], below_floor: int = 0, spacing: dict[str, float] | None = None) -> list[str]:
    """Plain sentences: where the policy loses to the IK solvers and where it wins. ``below_floor``: how many
    goals lie below the floor (z < 0), where every exact answer collides; ``spacing``: the median number
    spacing (m) at the goals per format (``{"float32": ..., "float64": ...}``), below which (times
    ``FLOOR_SPACINGS``) an error is rounding and is not compared in ratios."""
    p = m["policy"]
    ik = {k: v for k, v in m.items() if k not in ("policy", "controller") and "error" not in v}
    lines = []
    if "controller" in m:
        c = m["controller"]
        pose = (f" (pose success {100 * p['success_pose']:.1f}% against {100 * c['success_pose']:.1f}%)"
                if "success_pose" in p else "")
        lines.append(f"What the network adds to its controller (the DLS step and safety layer alone, the correction "
                     f"set to zero): success at 1 cm {100 * p['success@1cm']:.1f}% against "
                     f"{100 * c['success@1cm']:.1f}%{pose}, at 1 mm {100 * p['success@1mm']:.1f}% against "
                     f"{100 * c['success@1mm']:.1f}%; rollouts colliding {p['collisions']} against "
                     f"{c['collisions']}.")
    for name, v in ik.items():
        beyond = ""
        if spacing and "beyond_float32_floor" in p and "beyond_float32_floor" in v:
            beyond = (f"; goals left beyond float32's floor {100 * p['beyond_float32_floor']:.1f}% against "
                      f"{100 * v['beyond_float32_floor']:.1f}%")
        lines.append(f"Accuracy against {name}: median final error {1e3 * p['median_error_m']:.3g} mm against "
                     f"{1e3 * v['median_error_m']:.3g} mm: "
                     f"{_median_comparison(p['median_error_m'], v['median_error_m'], name, spacing)}. "
                     f"What separates them: success at 1 cm {100 * p['success@1cm']:.1f}% against "
                     f"{100 * v['success@1cm']:.1f}%, at 1 mm {100 * p['success@1mm']:.1f}% against "
                     f"{100 * v['success@1mm']:.1f}%{beyond}; p95 final error {_error(p['p95_error_m'], spacing)} "
                     f"against {_error(v['p95_error_m'], spacing)}.")
    for name, v in ik.items():
        if p["median_steps_to_reach"] is not None and v["median_steps_to_reach"] is not None:
            won = _cmp(p["median_steps_to_reach"], v["median_steps_to_reach"])
            lines.append(f"Steps to within 1 cm: the policy {won} against {name}: median "
                         f"{p['median_steps_to_reach']:.0f} steps against "
                         f"{v['median_steps_to_reach']:.0f} for a straight full-speed joint move to its solution.")
        lines.append(f"Wall time per goal against {name}: batched, the policy "
                     f"{_cmp(p['time_per_goal_batched_s'], v['time_per_goal_batched_s'])} "
                     f"({1e6 * p['time_per_goal_batched_s']:.0f} us for all its closed-loop steps, of which "
                     f"{1e6 * p['network_time_per_goal_batched_s']:.0f} us in the network, against "
                     f"{1e6 * v['time_per_goal_batched_s']:.0f} us for one solve); one goal at a time it "
                     f"{_cmp(p['time_per_goal_single_s'], v['time_per_goal_single_s'])} "
                     f"({1e3 * p['time_per_goal_single_s']:.1f} ms against "
                     f"{1e3 * v['time_per_goal_single_s']:.1f} ms).")
        lines.append(f"Joint-space path against {name}: the policy "
                     f"{_cmp(p['median_path_length_rad'], v['median_path_length_rad'])} (median "
                     f"{p['median_path_length_rad']:.2f} rad against {v['median_path_length_rad']:.2f} rad "
                     f"for the straight move).")
    lines += _collision_verdict(p, ik, below_floor)
    if "failures" in p:
        f = p["failures"]
        goals = "goal ends" if f["count"] == 1 else "goals end"
        lines.append(f"Where the policy fails ({f['count']} {goals} beyond 1 cm): at a median "
                     f"{1e3 * f['median_final_error_m']:.0f} mm from the goal; their median distance from the base "
                     f"axis is {f['median_goal_radius_m']:.2f} m against {f['median_goal_radius_all_m']:.2f} m for "
                     f"all goals. The IK solvers have no such tail on these reachable goals.")
    lines.append("What the policy is and the IK is not: a closed-loop controller that produces the whole motion "
                 "within the joint speed limits and corrects itself every step (a goal that moves is just a new "
                 "observation), at one small network evaluation per step. The IK gives an end configuration only; "
                 "the motion to it (and its timing) is left to a trajectory generator.")
    return lines


def _collision_verdict(p: dict[str, Any], ik: dict[str, dict[str, Any]], below_floor: int) -> list[str]:
    """Sentences on collisions with the floor and with itself: the policy's rollouts against the IK's solutions."""
    def clear(m):
        return (f"minimum clearance {1e3 * m['min_clearance_median_m']:.0f} mm at the median goal, "
                f"{1e3 * m['min_clearance_worst_m']:.0f} mm at the worst")

    def obstacle(m):
        return f", obstacles {m['obstacle_collisions']}" if "obstacle_collisions" in m else ""

    world = "floor at z = 0, each goal's obstacles" if "obstacle_collisions" in p else "floor at z = 0"
    lines = [f"Collisions (capsule model, {world}): the policy's rollout collides on {p['collisions']} goals "
             f"({100 * p['collision_share']:.1f}%; floor {p['floor_collisions']}, self {p['self_collisions']}"
             f"{obstacle(p)}), its final configuration on {p['final_collisions']}; {clear(p)}."
             + (f" {below_floor} of the goals lie below the floor (z < 0): every exact answer to them collides."
                if below_floor else "")]
    for name, v in ik.items():
        lines.append(f"Collisions of {name}: its solution collides on {v['collisions']} goals "
                     f"({100 * v['collision_share']:.1f}%; floor {v['floor_collisions']}, self "
                     f"{v['self_collisions']}{obstacle(v)}); {clear(v)}.")
        lines.append(f"Goal by goal against {name}: the policy's rollout touches the floor where {name}'s "
                     f"solution does not on {v['floor_policy_only']} goals; {name}'s solution touches it where the "
                     f"policy does not on {v['floor_ik_only']}.")
    return lines


def _fmt(value, scale=1.0, digits=2, unit="") -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return f"{value * scale:.{digits}f}{unit}"


def write_markdown(report: dict[str, Any], path: Path) -> str:
    obstacles = any("obstacle_collisions" in m for m in report["methods"].values())
    split = "floor / self / obstacle" if obstacles else "floor / self"
    rows = [
        "| method | success @1 cm | @5 mm | @1 mm | median error | p95 error | steps to 1 cm (median) "
        "| limit violations | path (rad, median) | time/goal batched | time/goal single "
        f"| collisions: all ({split}; final) | min clearance median / worst |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, m in report["methods"].items():
        if "error" in m:
            rows.append(f"| {name} | {m['error']} |" + " |" * 12)
            continue
        rows.append(
            f"| {name} | {_fmt(m['success@1cm'], 100, 1, '%')} | {_fmt(m['success@5mm'], 100, 1, '%')} "
            f"| {_fmt(m['success@1mm'], 100, 1, '%')} | {m['median_error_m'] * 1e3:.3g} mm "
            f"| {m['p95_error_m'] * 1e3:.3g} mm "
            f"| {_fmt(m['median_steps_to_reach'], 1, 0)} | {m['joint_limit_violations']} "
            f"| {_fmt(m['median_path_length_rad'])} | {m['time_per_goal_batched_s'] * 1e6:.1f} us "
            f"| {m['time_per_goal_single_s'] * 1e3:.2f} ms "
            f"| {m['collisions']} ({m['floor_collisions']} / {m['self_collisions']}"
            f"{' / ' + str(m['obstacle_collisions']) if obstacles else ''}; {m['final_collisions']}) "
            f"| {m['min_clearance_median_m'] * 1e3:.0f} / {m['min_clearance_worst_m'] * 1e3:.0f} mm |")
    table = "\n".join(rows)
    text = [
        f"# Policy versus IK on {report['goals']} held-out goals ({report['env_id']})",
        "",
        f"Model: `{report['model']}` ({report['algo']}); goals seed {report['seed']}; "
        f"load average {report['machine']['loadavg'][0]:.1f} on {report['machine']['cpu_count']} CPUs "
        f"({report['machine']['cpu']}), torch threads {report['machine']['torch_threads']}.",
        "",
        table,
        "",
        "## Where the policy loses and where it wins",
        "",
        *[f"- {line}" for line in report["verdict"]],
        "",
        "## Plots",
        "",
        *[f"- `{p}`" for p in report["plots"]],
        "",
    ]
    path.write_text("\n".join(text))
    return table
