"""Compare a trained policy with the analytic and the gradient IK on the same held-out goals.

    python -m train.evaluate --model train/policies/ppo_reach --goals 1000 --seed 0 --out reports/ppo_reach

``--env-kwargs key=value ...`` overrides the env options of the policy's config (values are
YAML), e.g. ``--env-kwargs collision=terminate`` to evaluate a policy trained without
collision checks on the default env (collision-free goals).

``--model`` is a run directory of ``train.train`` (or a shipped policy folder) holding
``model.zip``, ``config.yaml`` and, if the run normalised observations, ``vecnormalize.pkl``.
The goals are the FK of ``--goals`` configurations drawn within the joint limits with
``--seed`` (a stream separate from the training's), every arm starting at home.

Methods, each on every goal:

- ``policy``: the deterministic policy, closed loop for the env's 50 steps (2.5 s at
  dt = 0.05 s), no early stop: the final error says whether it reached the goal and stayed;
- ``controller`` (residual policies, :class:`train.residual.ResidualDLSPolicy`, only): the same
  policy with its learned correction set to zero, i.e. the DLS step and its safety layer alone:
  what the network adds is the difference between the two rows;
- ``analytic_ik``: ``iiwa_torch.ik.analytic.iiwa_solve`` (arm-angle sweep, within limits),
  nearest solution to home. It solves the full pose: for position goals it is given the
  pose the goal was drawn from (a harder problem than the position alone);
- ``gradient_ik``: ``iiwa_torch.ik.solve`` from home, position-only for position goals.

The IK answers are end configurations, not motions: their "steps to reach" is the number
of env steps a straight full-speed joint move from home needs, and their path length the
straight-line joint distance. Collisions: the capsule model of ``iiwa_torch.collision`` in the
env's world (``GoalSet.world()``: its floor and, for ``IiwaReachObstacles-v0``, each goal's own
obstacles, which both IK solvers are given too; with ``collision="off"``, the preset's floor at
z = 0); the policy is checked at every step of its rollout (and at its final configuration
alone), the IK at its solution. Outputs in ``--out``: ``report.json`` (keys in
docs/training.md), ``report.md``, ``final_q.npz`` (each method's final joint angles, rad) and
PNG plots (``rollouts_obstacles.png`` for an env with obstacles).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from iiwa_torch.checks import require

TOLERANCES = {"1cm": 0.01, "5mm": 0.005, "1mm": 0.001}
METHODS = ("policy", "analytic_ik", "gradient_ik")  # and "controller" for a residual policy
SINGLE_GOALS = 20  # goals timed one at a time for the "single" wall time
BATCHED_REPEATS = 3  # batched runs over all goals; the median time is reported (the machine is shared)
ORIENTATION_TOL = 0.1  # rad: the pose env's default orientation threshold
# An error within this many number spacings of the goal's coordinates is rounding, not accuracy:
# float32 FK of the iiwa alone differs from float64 by up to 6 spacings on 10,000 random configurations.
FLOOR_SPACINGS = 8
FLOAT_TYPES = {"float32": np.float32, "float64": np.float64}


# ---------------------------------------------------------------------------- loading
def load_policy(model_dir: Path):
    """``(model, vec_normalize or None, config dict)`` from a run or shipped-policy folder (a run stopped before
    its end, without ``model.zip``: its newest checkpoint, said on stderr); ValueError if the config is malformed
    or the model is not one of its algo for its env, FileNotFoundError if a file the config needs is missing
    (``vecnormalize.pkl`` with ``normalize: true``)."""
    import pickle

    from train.run_dir import RunDir, check_model
    from train.vec_env import make_env

    run = RunDir(model_dir)
    folder = run.path
    if not (folder / "model.zip").exists() and run.config_path.exists() and run.latest_checkpoint() is not None:
        folder = run.latest_checkpoint()
        print(f"{run.path} has no model.zip (the run did not finish): evaluating its newest checkpoint, "
              f"{folder.relative_to(run.path)}", file=sys.stderr)
    if not (folder / "model.zip").exists() or not run.config_path.exists():
        raise FileNotFoundError(f"{run.path} must hold model.zip and config.yaml (a train.train run or a "
                                f"train/policies/ folder), or config.yaml and checkpoints/ (a stopped run)")
    config = run.read_config()
    env = make_env(config["env_id"], 1, 0, config["hyperparams"].get("env_kwargs"))
    check_model(config["algo"], folder / "model.zip", env.observation_space, env.action_space)
    from stable_baselines3 import PPO, SAC

    # with its env: SB3 cannot rebuild a HER replay buffer without one
    model = {"ppo": PPO, "sac": SAC}[config["algo"]].load(folder / "model.zip", env=env, device="cpu")
    vec_normalize = None
    if config["hyperparams"].get("normalize", False) and not (folder / "vecnormalize.pkl").exists():
        raise FileNotFoundError(f"{folder / 'vecnormalize.pkl'} not found: the config says normalize: true, and "
                                f"the policy needs its observation statistics")
    if (folder / "vecnormalize.pkl").exists():
        try:
            with open(folder / "vecnormalize.pkl", "rb") as f:
                vec_normalize = pickle.load(f)  # SB3's own format (VecNormalize.save pickles the wrapper)
        except (pickle.UnpicklingError, EOFError, AttributeError, ImportError) as err:
            raise ValueError(f"{folder / 'vecnormalize.pkl'} is unreadable ({type(err).__name__}: {err}); "
                             f"expected the VecNormalize file train.train writes") from None
        vec_normalize.training = False
    return model, vec_normalize, config


# ---------------------------------------------------------------------------- metrics
def _steps_to_reach(distance: np.ndarray, tol: float) -> np.ndarray:
    """``(T + 1, n)`` distances -> ``(n,)`` first step index below ``tol`` (NaN if never)."""
    hit = distance < tol
    first = hit.argmax(0).astype(float)
    first[~hit.any(0)] = np.nan
    return first


def number_spacing(xyz: np.ndarray, dtype) -> np.ndarray:
    """``(n, 3)`` positions (m) -> ``(n,)`` length (m) of the vector of the number spacings of each
    coordinate in ``dtype`` (``np.spacing``: one unit in the last place): the smallest error that
    format resolves at that point."""
    return np.linalg.norm(np.spacing(np.abs(np.asarray(xyz)).astype(dtype)).astype(np.float64), axis=-1)


def summarise(final_error: np.ndarray, steps: np.ndarray, path: np.ndarray, violations: int,
              batched: float, single: float, n: int) -> dict[str, Any]:
    """The metrics of one method (errors in metres, times in seconds per goal, path in radians)."""
    out = {f"success@{k}": float(np.mean(final_error < v)) for k, v in TOLERANCES.items()}
    reached = steps[np.isfinite(steps)]
    out.update({
        "median_error_m": float(np.median(final_error)),
        "p95_error_m": float(np.percentile(final_error, 95)),
        "max_error_m": float(np.max(final_error)),
        "median_steps_to_reach": float(np.median(reached)) if reached.size else None,
        "mean_steps_to_reach": float(np.mean(reached)) if reached.size else None,
        "reached_1cm": float(reached.size / n),
        "joint_limit_violations": int(violations),
        "median_path_length_rad": float(np.median(path)),
        "time_per_goal_batched_s": batched,
        "time_per_goal_single_s": single,
    })
    return out


def _limit_violations(chain, q) -> int:
    """Configurations (rows of ``q (..., nj)``) outside the joint limits by more than 1e-9 rad."""
    import torch

    return int((~chain.within_limits(torch.as_tensor(q, dtype=torch.float64), tol=1e-9)).sum())


def collision_metrics(chain, q_path: np.ndarray, world=None, capsules=None) -> tuple[dict, np.ndarray,
                                                                                   np.ndarray]:
    """Collisions along ``q_path (T + 1, n, nj)`` (rad; ``T = 0`` for an end configuration alone) with
    ``capsules`` (default the preset's) in ``world`` (an :class:`iiwa_torch.collision.World`, batch ``()``
    or ``(n,)``: goal ``i``'s obstacles; None: the preset's default world, the floor at z = 0): a goal
    collides if any of its configurations has a signed distance below 0. Counts over goals, clearances
    (m) of the per-goal minimum over the path; with obstacles in the world also ``obstacle_collisions``.
    ``(metrics, floor_hit (n,) bool, collided (n,) bool)``: which goals touch the floor, which collide at all."""
    import torch

    from iiwa_torch.collision import pairwise_clearance, robot_capsules

    capsules = robot_capsules(chain) if capsules is None else capsules
    q = torch.as_tensor(q_path, dtype=torch.float64)
    pairs = pairwise_clearance(chain, q, world, capsules=capsules)  # one batched call over (T + 1, n)
    kind = ["self" if k < len(capsules.pairs) else "floor" if b == "floor" else "obstacle"
            for k, (_, b) in enumerate(pairs.pairs)]
    per_goal = pairs.distance.amin(0)  # (n, P): the worst moment of each pair
    lowest = per_goal.amin(-1).numpy()

    def lowest_of(name: str) -> np.ndarray:
        mask = torch.tensor([k == name for k in kind])
        return per_goal[:, mask].amin(-1).numpy() if mask.any() else np.full(len(lowest), np.inf)

    floor_min, self_min = lowest_of("floor"), lowest_of("self")
    final = pairs.distance[-1].amin(-1).numpy()
    metrics = {
        "collisions": int((lowest < 0).sum()),
        "collision_share": float(np.mean(lowest < 0)),
        "floor_collisions": int((floor_min < 0).sum()),
        "self_collisions": int((self_min < 0).sum()),
        "final_collisions": int((final < 0).sum()),
        "min_clearance_median_m": float(np.median(lowest)),
        "min_clearance_worst_m": float(lowest.min()),
    }
    if "obstacle" in kind:
        metrics["obstacle_collisions"] = int((lowest_of("obstacle") < 0).sum())
    return metrics, floor_min < 0, lowest < 0


def _median_time(fn, reps: int) -> float:
    times = []
    for i in range(reps):
        start = time.perf_counter()
        fn(i)
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def run_policy(goals, model, vec_normalize, chain) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The deterministic policy on every goal (one batched rollout), then ``SINGLE_GOALS`` single-goal rollouts
    (each timed from its env's reset to its last step, as the batched one: the env's construction is not the
    policy's time, as an IK solver's set-up is not its solve's).
    Collisions are counted at every configuration of the rollout in ``goals.world()`` (the preset's default
    floor if the env checks none)."""
    from train.rollout import PolicyEvaluator, make_goal_set, policy_actor, rollout

    pose = goals.pose_goals
    evaluator = PolicyEvaluator(goals, TOLERANCES["1cm"],
                                goals.env_kwargs.get("orientation_threshold", ORIENTATION_TOL) if pose else None)
    runs = [evaluator.rollout(model, vec_normalize) for _ in range(BATCHED_REPEATS)]  # deterministic: the same
    r = runs[0]
    act = policy_actor(model, vec_normalize)
    one = make_goal_set(goals.env_id, 1, goals.seed, goals.env_kwargs)
    single = float(np.median([rollout(one, act).seconds for _ in range(SINGLE_GOALS)]))  # from reset: not the build
    final = r.distance[-1]
    path = np.linalg.norm(np.diff(r.q, axis=0), axis=-1).sum(0)  # (n,) rad
    steps_hit = _steps_to_reach(r.distance, TOLERANCES["1cm"])
    batched = float(np.median([x.seconds for x in runs])) / goals.n
    metrics = summarise(final, steps_hit, path, _limit_violations(chain, r.q), batched, single, goals.n)
    # the policy network alone, all steps
    metrics["network_time_per_goal_batched_s"] = float(np.median([x.act_seconds for x in runs])) / goals.n
    lo, hi = chain.limits.numpy()
    collisions, floor_hit, collided = collision_metrics(chain, r.q, goals.world(), goals.capsules)
    metrics.update(collisions)
    # what the default env (collision="terminate") counts: reached, and never a collision on the way
    metrics["success@1cm_collision_free"] = float(np.mean((final < TOLERANCES["1cm"]) & ~collided))
    metrics["touched_a_limit"] = float(np.mean(((r.q - lo < 1e-4) | (hi - r.q < 1e-4)).any(axis=(0, 2))))
    if pose:
        summary = evaluator.summary(r)
        metrics["median_angle_rad"], metrics["success_pose"] = summary["median_angle"], summary["success"]
    failed = final >= TOLERANCES["1cm"]
    if failed.any():
        radius = np.linalg.norm(goals.desired_goal[:, :2], axis=-1)
        metrics["failures"] = {
            "count": int(failed.sum()),
            "median_final_error_m": float(np.median(final[failed])),
            "median_goal_radius_m": float(np.median(radius[failed])),
            "median_goal_radius_all_m": float(np.median(radius)),
        }
    return metrics, {"final_error": final, "path": path, "home": r.q[0, 0], "q": r.q[-1], "floor_hit": floor_hit,
                     "q_path": r.q, "collided": collided}


def controller_alone(model):
    """For a residual policy (:class:`train.residual.ResidualDLSPolicy`), a copy of ``model`` whose learned
    correction is zero: its controller alone (the DLS step and the safety layer); None for any other policy.
    ``model`` itself is left as it is."""
    import copy

    import torch

    from train.residual import ResidualDLSPolicy

    if not isinstance(model.policy, ResidualDLSPolicy):
        return None
    alone = copy.copy(model)
    alone.policy = copy.deepcopy(model.policy)
    with torch.no_grad():
        alone.policy.action_net.linear.weight.zero_()
        alone.policy.action_net.linear.bias.zero_()
    return alone


def ik_world(task, goals=None):
    """The world the IK methods are given for ``task``: when the env checks collisions, its floor and,
    with ``goals`` (a :class:`train.rollout.GoalSet`), each goal's obstacles (``goals.world()``, batch
    ``(n,)`` for the obstacle env); else ``None``."""
    from iiwa_torch.collision import World

    if task.world is None:
        return None
    return World(floor=task.world.floor) if goals is None else goals.world()


def _goal_rows(world, rows: slice):
    """``world`` for the goals ``rows`` of its batch (itself when unbatched or None)."""
    return world if world is None or not world.batch_shape else world.map_batch(lambda t, _: t[rows])


def run_ik(
    name: str, goals, chain, home: np.ndarray, dt: float, world=None
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """One IK method on every goal from ``home``: batched once, then ``SINGLE_GOALS`` goals one by one.
    ``world`` (an :class:`iiwa_torch.collision.World`, e.g. the env's floor, or a batch ``(n,)`` of one
    world per goal) makes both solvers collision-aware: the analytic one searches the arm angle, the
    gradient one adds clearance; the answers' collisions are counted in it too."""
    import torch

    home = torch.as_tensor(home, dtype=torch.float64)
    position_only = not goals.pose_goals
    if name == "analytic_ik":
        from iiwa_torch.ik.analytic import iiwa_solve

        def solve(pose, world):
            return iiwa_solve(chain, pose, home.expand(pose.shape[0], -1), world=world)
    else:
        from iiwa_torch.ik import solve as gradient_solve

        def solve(pose, world):
            target = pose[:, :3, 3] if position_only else pose
            return gradient_solve(chain, target, home.expand(pose.shape[0], -1), mode="position" if position_only
                                  else "pose", generator=torch.Generator().manual_seed(0), world=world,
                                  capsules=goals.capsules if world is not None else None)

    result = solve(goals.pose, world)
    batched = _median_time(lambda i: solve(goals.pose, world), BATCHED_REPEATS) / goals.n
    single = _median_time(lambda i: solve(goals.pose[i : i + 1], _goal_rows(world, slice(i, i + 1))), SINGLE_GOALS)
    q = result.q.double()
    pose = chain.fk(q)
    final = (pose[:, :3, 3] - goals.pose[:, :3, 3]).norm(dim=-1).numpy()
    delta = (q - home).numpy()
    path = np.linalg.norm(delta, axis=-1)
    max_step = chain.velocity_limits.double().numpy() * dt  # rad per env step at full speed
    steps = np.ceil(np.max(np.abs(delta) / max_step, axis=-1))  # a straight full-speed joint move
    steps[final >= TOLERANCES["1cm"]] = np.nan
    metrics = summarise(final, steps, path, _limit_violations(chain, q), batched, single, goals.n)
    collisions, floor_hit, collided = collision_metrics(chain, q.numpy()[None], goals.world(), goals.capsules)
    metrics.update(collisions)
    metrics["success@1cm_collision_free"] = float(np.mean((final < TOLERANCES["1cm"]) & ~collided))
    metrics["solver_success"] = float(result.success.double().mean())
    if not position_only:
        from iiwa_torch.so3 import pose_error

        _, rot = pose_error(pose, goals.pose)
        angle = rot.norm(dim=-1).numpy()
        metrics["median_angle_rad"] = float(np.median(angle))
        ok = (final < TOLERANCES["1cm"]) & (angle < goals.env_kwargs.get("orientation_threshold", ORIENTATION_TOL))
        metrics["success_pose"] = float(np.mean(ok))
    return metrics, {"final_error": final, "path": path, "q": q.numpy(), "floor_hit": floor_hit}


# ---------------------------------------------------------------------------- verdict and report
def _design_note(config: dict[str, Any], trained_in) -> list[str]:
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
    import torch

    mlines = require("matplotlib.lines", "viz")
    Figure = require("matplotlib.figure", "viz").Figure

    from envs.world import SLOT_SIZE
    from iiwa_torch.collision import clearance
    from iiwa_torch.viz import draw_chain, plot_world, side_view

    chain = goals.robot
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
        q = torch.as_tensor(p["q_path"][:, i], dtype=torch.float64)
        ee = chain.fk(q)[:, :3, 3].double().numpy()  # (T + 1, 3)
        world = goals.goal_world(i)
        path_clearance = clearance(chain, q, world).min().item()  # m
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


COMPARE_KEYS = ("steps", "wall_time", "success")  # of each evaluation a learning curve draws


def read_compare(paths: list[Path]) -> dict[str, list[dict]]:
    """Label -> evaluations of each ``--compare`` file: ``{"label", "evaluations"}`` or a run's
    ``evaluations.json`` list (labelled by its folder); ValueError names a file that is neither."""
    compare = {}
    for path in map(Path, paths):
        try:
            blob = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
            raise ValueError(f"--compare {path}: not a readable JSON file ({err})") from None
        label, evaluations = (blob.get("label"), blob.get("evaluations")) if isinstance(blob, dict) \
            else (path.parent.name, blob)
        entry_ok = lambda e: isinstance(e, dict) and all(isinstance(e.get(k), (int, float)) for k in COMPARE_KEYS)
        if not isinstance(label, str) or not isinstance(evaluations, list) or not evaluations \
                or not all(map(entry_ok, evaluations)):
            raise ValueError(f"--compare {path}: expected a run's evaluations.json (a list of entries with steps, "
                             f"wall_time and success) or {{\"label\": ..., \"evaluations\": [...]}}")
        compare[label] = evaluations
    return compare


def evaluate(model_dir: Path, n_goals: int, seed: int, out: Path, compare: dict[str, list[dict]],
             env_overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """The report of the policy in ``model_dir`` on ``n_goals`` held-out goals, written to ``out``, with the
    learning curves of ``compare`` (``read_compare``) beside its own."""
    import torch

    import envs
    from iiwa_torch.runtime import machine_info
    from train.rollout import make_goal_set
    from train.run_dir import RunDir

    torch.set_num_threads(1)
    model, vec_normalize, config = load_policy(model_dir)
    env_id = config["env_id"]
    env_kwargs = {**(config["hyperparams"].get("env_kwargs") or {}), **(env_overrides or {})}
    task = envs.make_task(env_id, **env_kwargs)
    chain, dt = task.robot, task.dt
    goals = make_goal_set(env_id, n_goals, seed, env_kwargs)
    below_floor = int((goals.pose[:, 2, 3] < 0).sum())  # the preset's default floor is z = 0

    world = ik_world(task, goals)
    metrics, data = {}, {}
    metrics["policy"], data["policy"] = run_policy(goals, model, vec_normalize, chain)
    alone = controller_alone(model)
    if alone is not None:
        metrics["controller"], data["controller"] = run_policy(goals, alone, vec_normalize, chain)
    for name in ("analytic_ik", "gradient_ik"):
        try:
            metrics[name], data[name] = run_ik(name, goals, chain, data["policy"]["home"], dt, world)
        except (ImportError, ValueError) as err:  # not installed, or no closed form for this arm: say so
            metrics[name] = {"error": f"unavailable: {err}"}
            continue
        policy_hit, ik_hit = data["policy"]["floor_hit"], data[name]["floor_hit"]
        metrics[name]["floor_policy_only"] = int((policy_hit & ~ik_hit).sum())
        metrics[name]["floor_ik_only"] = int((ik_hit & ~policy_hit).sum())
    spacing = {k: number_spacing(goals.pose[:, :3, 3].numpy(), t) for k, t in FLOAT_TYPES.items()}
    for name, d in data.items():
        metrics[name]["beyond_float32_floor"] = float(np.mean(d["final_error"] > FLOOR_SPACINGS * spacing["float32"]))
    spacing = {k: float(np.median(v)) for k, v in spacing.items()}
    evaluations = RunDir(model_dir).read_evaluations()
    out.mkdir(parents=True, exist_ok=True)
    report = {
        "env_id": env_id,
        "algo": config["algo"],
        "model": str(model_dir),
        "goals": n_goals,
        "seed": seed,
        "env_kwargs": env_kwargs,
        "episode_steps": task.max_episode_steps,
        "dt": dt,
        "tolerances_m": TOLERANCES,
        "methods": metrics,
        "goals_below_floor": below_floor,
        "number_spacing_m": spacing,
        "verdict": verdict(metrics, below_floor, spacing)
        + _design_note(config, envs.make_task(env_id, **(config["hyperparams"].get("env_kwargs") or {}))),
        "training": json.loads((model_dir / "train_info.json").read_text())
        if (model_dir / "train_info.json").exists() else None,
        "machine": machine_info(),
    }
    report["plots"] = make_plots(out, data, report, evaluations, compare, goals)
    np.savez_compressed(out / "final_q.npz", **{name: d["q"] for name, d in data.items()})
    (out / "report.json").write_text(json.dumps(report, indent=1))
    table = write_markdown(report, out / "report.md")
    print(table)
    print()
    for line in report["verdict"]:
        print("- " + line)
    print(f"\nreport: {out / 'report.md'}, {out / 'report.json'}; plots: "
          + ", ".join(str(out / p) for p in report["plots"]))
    return report


def main(argv: list[str] | None = None) -> int:
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    p = argparse.ArgumentParser(prog="python -m train.evaluate", description=__doc__.split("\n\n")[0])
    p.add_argument("--model", required=True, type=Path, help="run or policy folder (model.zip + config.yaml)")
    p.add_argument("--goals", type=int, default=1000, help="held-out goals (default 1000)")
    p.add_argument("--seed", type=int, default=0, help="seed of the goal set (default 0)")
    p.add_argument("--out", required=True, type=Path, help="report folder")
    p.add_argument("--compare", nargs="*", type=Path, default=[],
                   help="evaluations JSON of other runs to draw on the learning curve (e.g. panda-gym)")
    p.add_argument("--env-kwargs", nargs="*", default=[], metavar="KEY=VALUE",
                   help="env options over the policy config's (YAML values), e.g. collision=terminate")
    args = p.parse_args(argv)
    import yaml

    from train.run_dir import check_folder

    overrides = {}
    for item in args.env_kwargs:
        key, sep, value = item.partition("=")
        if not sep or not key:
            p.error(f"--env-kwargs: expected KEY=VALUE, got {item!r}")
        overrides[key] = yaml.safe_load(value)
    if args.goals < 1:
        p.error(f"--goals must be >= 1, got {args.goals}")
    for path in args.compare:
        if not path.is_file():
            p.error(f"--compare: {path} not found; expected an evaluations JSON (a run's evaluations.json)")
    try:
        check_folder(args.out)
        evaluate(args.model, args.goals, args.seed, args.out, read_compare(args.compare), overrides)
    except (FileNotFoundError, ValueError, TypeError) as err:
        p.error(str(err))
    return 0


if __name__ == "__main__":
    sys.exit(main())
