"""The metrics of each method on a goal set: success at the tolerances, errors, steps, path length,
joint-limit violations and collisions (errors in metres, times in seconds, angles in radians)."""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["TOLERANCES", "ORIENTATION_TOL", "FLOOR_SPACINGS", "FLOAT_TYPES", "steps_to_reach", "number_spacing",
           "summarise", "limit_violations", "collision_metrics"]

TOLERANCES = {"1cm": 0.01, "5mm": 0.005, "1mm": 0.001}
ORIENTATION_TOL = 0.1  # rad: the pose env's default orientation threshold
# An error within this many number spacings of the goal's coordinates is rounding, not accuracy:
# float32 FK of the iiwa alone differs from float64 by up to 6 spacings on 10,000 random configurations.
FLOOR_SPACINGS = 8
FLOAT_TYPES = {"float32": np.float32, "float64": np.float64}


def steps_to_reach(distance: np.ndarray, tol: float) -> np.ndarray:
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


def limit_violations(chain, q, tol: float = 1e-9) -> int:
    """Configurations (rows of ``q (..., nj)``) outside the joint limits by more than ``tol`` rad (a policy's
    angles, read back from its float32 observation, need the precision of that reading:
    ``envs.transport.ANGLE_TOL``)."""
    import torch

    return int((~chain.within_limits(torch.as_tensor(q, dtype=torch.float64), tol=tol)).sum())


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
