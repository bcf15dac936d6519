"""The reaching task's step, for any number of CPU environments, and one environment's reset, each in
one compiled call (numba; importing this module imports numba).

A step of the task's torch formulas (:meth:`envs.core.ReachTask.step`) is some sixty array
operations: for one environment each costs its call overhead, for many each pass reads and writes
every environment's rows again, and the end point and the clearance each build the arm's frames.
:func:`reach_step` does the whole step of a position-goal task without obstacles in one pass per
block of environments: integration, the frames (once, for the end point and the capsules), the self
and floor clearance, distance, reward and flags, with the library's compiled pieces
(:mod:`iiwa_torch.compiled.clearance_kernels`). It restates the numpy formulas' operations in
the same order: the fused multiply-add as float64 arithmetic rounded once (the float32 product is
exact in float64), the square root in float64 rounded to float32 (correctly rounded either way).
The cosines and sines, of the observation and of the frames, are those of
:func:`~iiwa_torch.compiled.clearance_kernels.sin_cos` (within an ulp or two of libm's in float64),
so the observation's are the correctly rounded float32 values but for rare ties, where torch's
vectorised float32 ones miss the last bit for about 1 angle in 20 (measured). The frames are
:func:`~iiwa_torch.compiled.clearance_kernels.block_capsules`' (float64, products fused into FMAs),
so the end point can differ from the torch step's in its last bit.

:func:`reach_reset_one` starts one environment's episode from home the same way, and
:func:`draw_goals` draws the goals of many: each goal drawn as
:meth:`envs.core.ReachTask` draws it (the counter-based hash of :mod:`envs.seeding` in unsigned
integers, the same float32 operations, the same kernels for the candidates' end points and
clearance, the same rounds of redraws), equal to it bit for bit (tested).
"""

from __future__ import annotations

import math

import numpy as np

from iiwa_torch.compiled.clearance_kernels import (
    LANES,
    SIN_COS_RANGE,
    block_capsules,
    block_minimum,
    half_lengths,
    own_clearance,
    sin_cos,
)
from iiwa_torch.compiled.decorators import inline, jit, jit_nogil
from iiwa_torch.compiled.kinematics_kernels import frames_of

from .seeding import EPISODE_SALT, GOLDEN, MASK32, MIX_MULTIPLIERS

__all__ = ["SETTINGS", "draw_goals", "reach_reset_one", "reach_step"]

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


@jit_nogil
def reach_step(q, action, arm, transforms, params, base, tool, frames, local, first, second, pair_radius, floor,
               floor_radius, settings, goal, t, start, stop, new_q, out, flags):  # fmt: skip
    """The step of environments ``start`` to ``stop`` (columns of the arrays): joint angles ``q (nj, n)``
    float32, finite actions ``(nj, n)`` float32, ``arm (3, nj)`` float32 (lower limits, upper limits,
    rad per step at ``|a| = 1``), the chain's ``float_arrays``, the capsules' ``numpy_tables``
    (``floor``: the floor's capsules, none without a floor), ``settings`` (:data:`SETTINGS`, float64; a
    negative ``max_episode_steps``: none), the goals ``(3, n)`` float32 and the steps taken with this
    one ``t (n,)`` -> the new angles into ``new_q (nj, n)``; into ``out (3 nj + 8, n)`` float32 the
    packed rows of :meth:`envs.transport.Transport.pack`: cos q, sin q, the motion over the speed
    limits, the achieved and desired goals, reward and distance (m); into ``flags (4, n)``
    terminated, truncated, success and collision.

    Blocks of ``LANES`` environments go through each stage as a loop over the block, as
    :func:`~iiwa_torch.compiled.clearance_kernels.own_clearance` does (whose frames, capsules and
    minimum it shares), so LLVM vectorises them; the frames carry on to the end effector."""
    nj, k_all, one = q.shape[0], frames.shape[0], np.float32(1.0)
    checked, on_success, on_collision, sparse = settings[3] != 0, settings[5] != 0, settings[6] != 0, settings[7] != 0
    half = half_lengths(local)
    w = max(1, min(LANES, stop - start))
    angle, cs = np.empty((nj, w)), np.empty((2, nj, w))
    state, ends, distance = np.empty((12, w)), np.empty((k_all, 9, w)), np.empty(w, dtype=np.float32)
    gap, lanes, best = np.empty((first.shape[0], w)), np.empty(w, dtype=np.int64), np.empty(w)
    for row in range(start, stop, w):
        m = min(w, stop - row)
        _integrate(q, action, arm, params, row, m, new_q, out, angle, cs)
        block_capsules(transforms, params, base, frames, local, m, angle, cs, state, ends)
        _errors(tool, state, goal, row, m, 3 * nj, out, distance)
        if checked:
            block_minimum(ends, m, first, second, pair_radius, half, floor, floor_radius, settings[4], gap, lanes,
                          best)  # fmt: skip
        for j in range(m):
            c = row + j
            collision = checked and best[j] < 0
            success = distance[j] < np.float32(settings[0])
            reward = success - one if sparse else -distance[j]
            if collision:
                reward -= np.float32(settings[1])
            out[3 * nj + 6, c] = reward
            flags[0, c] = (on_success and success) or (on_collision and collision)
            flags[1, c] = 0 <= settings[2] <= t[c]
            flags[2, c], flags[3, c] = success, collision


@inline
def _integrate(q, action, arm, params, row, m, new_q, out, angle, cs):
    """The block's new angles (float32, the numpy formulas' operations) into ``new_q`` and the motion
    rows of ``out``; their cosines and sines into its first rows, and the joints' angles and their
    cosines and sines into ``angle``, ``cs`` (float64) for the frames."""
    nj, one = q.shape[0], np.float32(1.0)
    wide = False
    for i in range(nj):
        for j in range(m):
            c = row + j
            a = min(max(action[i, c], -one), one)
            step = np.float32(np.float64(q[i, c]) + np.float64(a) * np.float64(arm[2, i]))  # fused: one rounding
            new = max(min(step, arm[1, i]), arm[0, i])
            new_q[i, c] = new
            out[2 * nj + i, c] = min(max((new - q[i, c]) / arm[2, i], -one), one)
            angle[i, j] = np.float64(new) + params[i, 0]
            wide |= abs(angle[i, j]) > SIN_COS_RANGE or abs(new) > SIN_COS_RANGE
    for i in range(nj):  # the branches outside the loops: a branch inside would keep them from vectorising
        if wide:  # libm's, beyond the polynomial's range (a continuous joint turned for long)
            for j in range(m):
                cs[0, i, j], cs[1, i, j] = math.cos(angle[i, j]), math.sin(angle[i, j])
        else:
            for j in range(m):
                cs[1, i, j], cs[0, i, j] = sin_cos(angle[i, j])
        if params[i, 0] == 0.0:  # no offset: the frames' cosines and sines are the observation's
            for j in range(m):
                out[i, row + j], out[nj + i, row + j] = cs[0, i, j], cs[1, i, j]
        elif wide:
            for j in range(m):
                out[i, row + j], out[nj + i, row + j] = math.cos(new_q[i, row + j]), math.sin(new_q[i, row + j])
        else:
            for j in range(m):
                out[nj + i, row + j], out[i, row + j] = sin_cos(np.float64(new_q[i, row + j]))


@inline
def _errors(tool, state, goal, row, m, achieved, out, distance):
    """The end points of the block's last frames ``state`` (the tool's origin, rounded to float32) and
    the goals into ``out``'s goal rows (from ``achieved`` on), their distances (float32, the square
    root correctly rounded) into ``distance``."""
    for j in range(m):
        c = row + j
        sum_sq = np.float32(0.0)
        for r in range(3):  # as kinematics_kernels.frames_of: u x + v y + w z, then + p
            p = np.float32(tool[0, 3] * state[r, j] + tool[1, 3] * state[3 + r, j] + tool[2, 3] * state[6 + r, j]
                           + state[9 + r, j])
            out[achieved + r, c], out[achieved + 3 + r, c] = p, goal[r, c]
            d = p - goal[r, c]
            sum_sq += d * d
        distance[j] = math.sqrt(np.float64(sum_sq))
        out[achieved + 7, c] = distance[j]


@jit
def reach_reset_one(key, episode, draw, home, home_goal, transforms, params, base, tool, frames, local, first, second,
                    pair_radius, floor, floor_radius, settings, box, rounds, redraws, out, flags):  # fmt: skip
    """A new episode from home for the key ``key (1,)`` and episode number ``episode (1,)`` (int64): its goal
    (:func:`draw_goals`), then what :meth:`envs.core.ReachTask.reset_transition` packs, into
    ``out (3 nj + 8, 1)`` float32 (cos and sin of ``home (nj, 1)``, zero motion, the achieved goal
    ``home_goal (3, 1)``, the goal, reward and distance) and ``flags (4,)`` (success the third). The
    other arguments as :func:`draw_goals`'."""
    nj, achieved = home.shape[0], 3 * home.shape[0]
    for c in range(3):
        out[achieved + c, 0] = home_goal[c, 0]
    draw_goals(key, episode, draw, home_goal, transforms, params, base, tool, frames, local, first, second,
               pair_radius, floor, floor_radius, settings, box, rounds, redraws, 0, 1, out[achieved + 3 : achieved + 6])
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


@jit_nogil
def draw_goals(key, episode, draw, home_goal, transforms, params, base, tool, frames, local, first, second,
               pair_radius, floor, floor_radius, settings, box, rounds, redraws, start, stop, goal):  # fmt: skip
    """The goals of new episodes from home of environments ``start`` to ``stop`` into ``goal (3, n)``
    float32, from their keys and episode numbers ``(n,)`` int64, as the torch reset draws them: in
    panda-gym's box ``box (2, 3)`` float32 (low and high corners; draws nj, nj + 1, nj + 2), or (a
    ``(0, 3)`` box) per round the end point of the first of ``k`` random configurations within
    ``draw (2, nj)`` float32 that is clear (``k = 2`` when ``settings`` checks clearance, else 1,
    always clear), round 0 from draw ``nj`` on, round ``r`` from ``redraws + r k nj``, up to
    ``rounds`` rounds, else home's goal ``home_goal (3, 1)``. Each round checks the clearance of
    every pending environment's candidates in one call of the clearance kernel. The other
    arguments as :func:`reach_step`'s."""
    m, nj = stop - start, draw.shape[1]
    stream = np.empty(m, dtype=np.uint64)
    for e in range(m):
        stream[e] = _mix32(np.uint64(key[start + e]) ^ _mix32((np.uint64(episode[start + e]) & _MASK) ^ _SALT))
    if box.shape[0]:
        for e in range(m):
            for c in range(3):
                goal[c, start + e] = box[0, c] + _uniform(stream[e], nj + c) * (box[1, c] - box[0, c])
        return
    k = 2 if settings[3] else 1
    pending, x, clearance = np.arange(m), np.empty((m * k, nj)), np.ones(m * k)
    pose, none = np.empty((4, 4)), np.empty((0, 3))
    count = m
    for r in range(rounds):
        offset = nj if r == 0 else redraws + r * k * nj
        for p in range(count):
            for c in range(k):
                for i in range(nj):
                    u = _uniform(stream[pending[p]], offset + c * nj + i)
                    x[p * k + c, i] = draw[0, i] + u * (draw[1, i] - draw[0, i])  # float32, then exact in float64
        if settings[3]:
            own_clearance(x[: count * k], transforms, params, base, frames, local, first, second, pair_radius, floor,
                          floor_radius, settings[4], clearance[: count * k])
        left = 0
        for p in range(count):
            e, chosen = pending[p], -1
            for c in range(k - 1, -1, -1):  # the first clear candidate
                if clearance[p * k + c] > 0:
                    chosen = c
            if chosen < 0:
                pending[left] = e
                left += 1
                continue
            frames_of(transforms, params, base, tool, x[p * k + chosen], pose, none, none, np.empty((0, 4, 3)))
            for c in range(3):
                goal[c, start + e] = pose[c, 3]
        count = left
        if count == 0:
            return
    for p in range(count):
        for c in range(3):
            goal[c, start + pending[p]] = home_goal[c, 0]
