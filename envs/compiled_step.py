"""One CPU environment's step and reset, each in one compiled call (numba; importing this module
imports numba).

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

:func:`reach_reset_one` starts an episode from home the same way: the goal drawn as
:meth:`envs.core.ReachTask` draws it (the counter-based hash of :mod:`envs.seeding` in unsigned
integers, the same float32 operations, the same kernels for the candidates' end points and
clearance, the same rounds of redraws), equal to it bit for bit (tested).
"""

from __future__ import annotations

import math

import numpy as np

from iiwa_torch.compiled.clearance_kernels import own_clearance
from iiwa_torch.compiled.decorators import jit
from iiwa_torch.compiled.kinematics_kernels import frames_of

from .seeding import EPISODE_SALT, GOLDEN, MASK32, MIX_MULTIPLIERS

__all__ = ["SETTINGS", "reach_reset_one", "reach_step_one"]

#: the entries of ``settings`` (float64) of :func:`reach_step_one`
SETTINGS = ("distance_threshold", "collision_penalty", "max_episode_steps", "check_clearance", "floor_height",
            "terminate_on_success", "terminate_on_collision", "sparse")

# the hash's numbers as unsigned 64-bit integers (numba keeps an expression of uint64 in uint64)
_MASK, _FIRST, _SECOND = np.uint64(MASK32), np.uint64(MIX_MULTIPLIERS[0]), np.uint64(MIX_MULTIPLIERS[1])
_GOLDEN, _SALT = np.uint64(GOLDEN), np.uint64(EPISODE_SALT)


@jit
def _mix32(x):
    """MurmurHash3's finaliser as :mod:`envs.seeding` applies it, of a uint64 ``x`` in ``[0, 2**32)``: a
    product of two numbers below ``2**32`` wraps modulo ``2**64``, which keeps it modulo ``2**32``."""
    x ^= x >> np.uint64(16)
    x = (x * _FIRST) & _MASK
    x ^= x >> np.uint64(13)
    x = (x * _SECOND) & _MASK
    return x ^ (x >> np.uint64(16))


@jit
def _uniform(base, j):
    """Draw number ``j`` of the stream starting at ``base`` (:func:`envs.seeding.uniform`), float32."""
    h = _mix32((base + ((np.uint64(j) * _GOLDEN) & _MASK)) & _MASK)
    return np.float32(h >> np.uint64(8)) * np.float32(2.0**-24)


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


@jit
def reach_reset_one(key, episode, draw, home, home_goal, transforms, params, base, tool, frames, local, first, second,
                    pair_radius, floor, floor_radius, settings, box, rounds, redraws, out, flags):  # fmt: skip
    """A new episode from home for key ``key`` and episode ``episode`` (ints): the goal, then what
    :meth:`envs.core.ReachTask.reset_transition` packs, into ``out (3 nj + 8, 1)`` float32 (cos and sin
    of ``home (nj, 1)``, zero motion, the achieved goal ``home_goal (3, 1)``, the goal, reward and
    distance) and ``flags (4,)`` (success the third). ``draw (2, nj)`` float32: where configurations
    are drawn; ``box (2, 3)`` float32: panda-gym's goal box (low, high corners; ``(0, 3)``: goals are
    the end points of random configurations, up to ``rounds`` rounds of candidates, collision-free
    when ``settings`` checks clearance, else home's; later rounds' draws from ``redraws`` on). The
    other arguments as :func:`reach_step_one`'s."""
    nj, achieved = home.shape[0], 3 * home.shape[0]
    stream = _mix32(np.uint64(key) ^ _mix32((np.uint64(episode) & _MASK) ^ _SALT))
    for c in range(3):
        out[achieved + c, 0] = home_goal[c, 0]
    if box.shape[0]:  # draws nj, nj + 1, nj + 2
        for c in range(3):
            out[achieved + 3 + c, 0] = box[0, c] + _uniform(stream, nj + c) * (box[1, c] - box[0, c])
    else:
        _draw_goal(stream, draw, home_goal, transforms, params, base, tool, frames, local, first, second, pair_radius,
                   floor, floor_radius, settings, rounds, redraws, out[achieved + 3 : achieved + 6, 0])
    sum_sq = np.float32(0.0)
    for i in range(nj):
        out[i, 0], out[nj + i, 0], out[2 * nj + i, 0] = math.cos(np.float64(home[i, 0])), \
            math.sin(np.float64(home[i, 0])), 0.0
    for c in range(3):
        d = out[achieved + c, 0] - out[achieved + 3 + c, 0]
        sum_sq += d * d
    distance = np.float32(math.sqrt(np.float64(sum_sq)))
    success = distance < np.float32(settings[0])
    out[achieved + 6, 0] = success - np.float32(1.0) if settings[7] else -distance
    out[achieved + 7, 0] = distance
    flags[0], flags[1], flags[2], flags[3] = False, False, success, False


@jit
def _draw_goal(stream, draw, home_goal, transforms, params, base, tool, frames, local, first, second, pair_radius,
               floor, floor_radius, settings, rounds, redraws, goal):  # fmt: skip
    """The goal of a reset from home into ``goal (3,)``: per round the end point of the first of ``k``
    random configurations that is clear (``k = 2`` with clearance checked, else 1, always clear),
    round 0 from draw ``nj`` on, round ``r`` from ``redraws + r k nj``; home's goal if none is."""
    nj = draw.shape[1]
    k = 2 if settings[3] else 1
    x, pose, none = np.empty((k, nj)), np.empty((4, 4)), np.empty((0, 3))
    clearance = np.empty(k)
    for r in range(rounds):
        start = nj if r == 0 else redraws + r * k * nj
        for c in range(k):
            for i in range(nj):
                u = _uniform(stream, start + c * nj + i)
                x[c, i] = draw[0, i] + u * (draw[1, i] - draw[0, i])
        if settings[3]:
            own_clearance(x, transforms, params, base, frames, local, first, second, pair_radius, floor, floor_radius,
                          settings[4], clearance)
        for c in range(k):
            if not settings[3] or clearance[c] > 0:
                frames_of(transforms, params, base, tool, x[c], pose, none, none, np.empty((0, 4, 3)))
                for j in range(3):
                    goal[j] = pose[j, 3]
                return
    for j in range(3):
        goal[j] = home_goal[j, 0]
