"""One CPU environment's step in one compiled call (numba; importing this module imports numba).

The single env's step is some twenty small array operations (:meth:`envs.core.ReachTask.step` on
numpy views), each a few microseconds of call overhead for seven numbers. :func:`reach_step_one`
does the whole step of a position-goal task without obstacles in one call: it restates the step's
formulas for one environment and calls the library's compiled kernels for the forward kinematics
(:func:`iiwa_torch.compiled.kinematics_kernels.frames_of`) and the self and floor clearance
(:func:`iiwa_torch.compiled.clearance_kernels.own_clearance`). Its results equal the numpy
formulas' bit for bit (tested): the same float32 operations in the same order, the fused
multiply-add as float64 arithmetic rounded once (the float32 product is exact in float64), and the
square root in float64 rounded to float32 (correctly rounded either way). Only the cosine and sine
of the joint angles differ: computed in float64 and rounded, they are the correctly rounded
float32 values, which torch's vectorised float32 functions miss by one unit in the last place for
about 1 angle in 20 (measured); calling torch for them would cost a third of the step.
"""

from __future__ import annotations

import math

import numpy as np

from iiwa_torch.compiled.clearance_kernels import own_clearance
from iiwa_torch.compiled.decorators import jit
from iiwa_torch.compiled.kinematics_kernels import frames_of

__all__ = ["SETTINGS", "reach_step_one"]

#: the entries of ``settings`` (float64) of :func:`reach_step_one`
SETTINGS = ("distance_threshold", "collision_penalty", "max_episode_steps", "check_clearance", "floor_height",
            "terminate_on_success", "terminate_on_collision", "sparse")


@jit
def reach_step_one(q, action, arm, transforms, params, base, tool, frames, local, first, second, pair_radius,
                   floor, floor_radius, settings, goal, t, new_q, out, flags):  # fmt: skip
    """One environment's step: joint angles ``q (nj, 1)`` float32, a finite action ``(nj,)`` float32,
    ``arm (3, nj)`` float32 (lower limits, upper limits, rad per step at ``|a| = 1``), the chain's
    ``float_arrays``, the capsules' ``numpy_tables`` (``floor``: the floor's capsules, none without a
    floor), ``settings`` (:data:`SETTINGS`, float64; a negative ``max_episode_steps``: none), the goal
    ``(3, 1)`` float32 and the steps taken with this one ``t`` -> the new angles into ``new_q (nj, 1)``; into
    ``out (3 nj + 8, 1)`` float32 the packed rows of :meth:`envs.transport.Transport.pack`: cos q, sin q,
    the motion over the speed limits, the achieved and desired goals, reward and distance (m); into
    ``flags (4,)`` terminated, truncated, success and collision."""
    nj = q.shape[0]
    one = np.float32(1.0)
    x = np.empty((1, nj))  # the new angles in float64, as the kernels take them
    for i in range(nj):
        a = min(max(action[i], -one), one)
        step = np.float32(np.float64(q[i, 0]) + np.float64(a) * np.float64(arm[2, i]))  # fused: one rounding
        new = max(min(step, arm[1, i]), arm[0, i])
        new_q[i, 0], x[0, i] = new, new
        out[i, 0], out[nj + i, 0] = math.cos(x[0, i]), math.sin(x[0, i])
        out[2 * nj + i, 0] = min(max((new - q[i, 0]) / arm[2, i], -one), one)
    pose, none = np.empty((4, 4)), np.empty((0, 3))
    frames_of(transforms, params, base, tool, x[0], pose, none, none, np.empty((0, 4, 3)))
    achieved, sum_sq = 3 * nj, np.float32(0.0)
    for k in range(3):
        p = np.float32(pose[k, 3])
        out[achieved + k, 0], out[achieved + 3 + k, 0] = p, goal[k, 0]
        d = p - goal[k, 0]
        sum_sq += d * d
    distance = np.float32(math.sqrt(np.float64(sum_sq)))
    collision = False
    if settings[3]:
        clearance = np.empty(1)
        own_clearance(x, transforms, params, base, frames, local, first, second, pair_radius, floor, floor_radius,
                      settings[4], clearance)
        collision = clearance[0] < 0
    success = distance < np.float32(settings[0])
    reward = success - one if settings[7] else -distance
    if collision:
        reward -= np.float32(settings[1])
    out[achieved + 6, 0], out[achieved + 7, 0] = reward, distance
    flags[0] = (settings[5] and success) or (settings[6] and collision)
    flags[1] = 0 <= settings[2] <= t
    flags[2], flags[3] = success, collision
