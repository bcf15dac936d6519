"""The methods compared on one goal set: the policy (and a residual policy's controller alone) in closed
loop, and the analytic and gradient IK solvers, each batched and one goal at a time."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from .metrics import ORIENTATION_TOL, TOLERANCES, collision_metrics, limit_violations, steps_to_reach, summarise

__all__ = ["METHODS", "SINGLE_GOALS", "BATCHED_REPEATS", "run_policy", "controller_alone", "ik_world", "run_ik"]

METHODS = ("policy", "analytic_ik", "gradient_ik")  # and "controller" for a residual policy
SINGLE_GOALS = 20  # goals timed one at a time for the "single" wall time
BATCHED_REPEATS = 3  # batched runs over all goals; the median time is reported (the machine is shared)


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
    from envs.transport import ANGLE_TOL
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
    steps_hit = steps_to_reach(r.distance, TOLERANCES["1cm"])
    batched = float(np.median([x.seconds for x in runs])) / goals.n
    metrics = summarise(final, steps_hit, path, limit_violations(chain, r.q, ANGLE_TOL), batched, single, goals.n)
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
    metrics = summarise(final, steps, path, limit_violations(chain, q), batched, single, goals.n)
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
