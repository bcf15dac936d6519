"""Between the torch state and the envs' numpy: actions in, observations and step results out.

Observations travel as one ``(D, n)`` float32 block per step, ``D = packed_size`` rows: the
observation (cos q, sin q, normalised joint velocity, the obstacle block if any, the clearance rows if
any, achieved goal),
then the desired goal;
the envs' observation dicts are views of its numpy transpose.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from iiwa_torch.checks import all_finite

__all__ = ["Transition", "Transport", "joint_angles"]

Tensor = torch.Tensor

TURN = 2 * np.pi
ANGLE_TOL = 1e-5  # rad: a joint on its limit, read back through float32 cos and sin, is not turned


def joint_angles(observation, lower: np.ndarray, upper: np.ndarray):
    """The joint angles ``(..., nj)`` (rad) of observations ``(..., D)``, which start with ``cos q``, ``sin q``,
    within the limits ``lower``, ``upper`` (``(nj,)`` numpy arrays, rad): ``atan2``'s ``(-pi, pi]``, turned by a
    full turn where a joint's range reaches past pi (the Franka Panda's joint 6 runs to 3.82 rad). A numpy
    array in: numpy out, in the wider dtype of the observation's and the limits'; a tensor in: a tensor
    (torch's ``atan2``) in its dtype. Arms whose limits lie within ``[-pi, pi]`` skip the turn (a policy
    step reads the angles of one env: a few ops fewer)."""
    nj = lower.shape[-1]
    cos, sin = observation[..., :nj], observation[..., nj : 2 * nj]
    if isinstance(observation, np.ndarray):
        q, where = np.arctan2(sin, cos).astype(np.result_type(observation, lower)), np.where
    else:
        q, where = torch.atan2(sin, cos), torch.where
    if not ((lower < -np.pi).any() or (upper > np.pi).any()):
        return q
    if where is torch.where:
        lower, upper = (torch.as_tensor(x, dtype=q.dtype, device=q.device) for x in (lower, upper))
    return where(q < lower - ANGLE_TOL, q + TURN, where(q > upper + ANGLE_TOL, q - TURN, q))


class Transition(NamedTuple):
    """A batched step as numpy, for the envs: ``obs`` dict of ``(n, ...)`` float32 arrays
    (after auto-reset), ``reward`` ``(n,)`` float32, ``terminated``/``truncated``/``success``
    ``(n,)`` bool, ``distance`` (m) and ``angle`` (rad; ``None`` for position goals) ``(n,)``
    float32, ``final_index`` the ``(m,)`` rows that finished and ``final_obs`` their last
    observations ``(m, ...)``, ``collision`` ``(n,)`` bool (``None`` when collisions are off)."""

    obs: dict
    reward: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    success: np.ndarray
    distance: np.ndarray
    angle: np.ndarray | None
    final_index: np.ndarray
    final_obs: dict
    collision: np.ndarray | None = None


class Transport:
    """Conversions for a task of ``n_joints`` joints, goals of ``goal_size`` numbers and an
    obstacle block of ``obstacle_size`` numbers and ``clearance_size`` clearance rows (the state's
    ``clearance``) whose state is in ``dtype`` on ``device``."""

    def __init__(self, n_joints: int, goal_size: int, dtype: torch.dtype, device: torch.device,
                 obstacle_size: int = 0, clearance_size: int = 0) -> None:
        self.n_joints, self.goal_size, self.dtype, self.device = n_joints, goal_size, dtype, device
        self.obstacle_size, self.clearance_size = obstacle_size, clearance_size
        #: length of ``observation``: cos q, sin q, joint velocity (normalised), obstacles, clearances, achieved goal
        self.observation_size = 3 * n_joints + obstacle_size + clearance_size + goal_size
        #: rows of :meth:`observe`: the observation, then the desired goal
        self.packed_size = self.observation_size + goal_size

    def _rows(self, state) -> list[Tensor]:
        block = ([state.obstacles] if self.obstacle_size else []) + ([state.clearance] if self.clearance_size else [])
        return [state.cos_q, state.sin_q, state.velocity, *block, state.achieved, state.goal]

    def observe(self, state) -> Tensor:
        """A :class:`~envs.core.ReachState` -> ``(D, n)`` float32: the observation rows, then
        the desired goal; :meth:`split` makes the observation dict of its numpy transpose."""
        return torch.cat(self._rows(state), 0).float()

    def pack(self, state, result) -> tuple[Tensor, Tensor]:
        """Everything a step returns, for two transfers: ``(D + k, n)`` float32, the observation
        rows then reward, distance and, for pose goals, angle (``k`` = 2 or 3); and ``(3, n)``
        bool, terminated, truncated and success, plus collision when it is checked.

        Each is one ``cat``/``stack`` of rows of one dtype, written once, with no type promotion
        (a mixed bool and float ``stack`` costs 4x a plain one for one env). ``out=`` writes into
        the rows of a preallocated buffer would save ~0.5 ms of the cat's ~2 ms at ``n = 65,536``
        but cost more for one env (and into strided views, 3-10x more)."""
        status = [result.reward, result.distance] + ([] if result.angle is None else [result.angle])
        floats = torch.cat([*self._rows(state), torch.stack(status)], 0)
        floats = floats if floats.dtype == torch.float32 else floats.float()
        flags = [result.terminated, result.truncated, result.success]
        return floats, torch.stack(flags if result.collision is None else [*flags, result.collision])

    def unpack(self, floats: np.ndarray, flags: np.ndarray) -> Transition:
        """``pack``'s outputs as numpy -> a :class:`Transition` without finished episodes.

        The observation arrays are ``(n, ...)`` views of ``floats.T`` (Fortran-ordered: one
        memory row per component); rewards and flags are contiguous rows."""
        d = self.packed_size
        return Transition(
            obs=self.split(floats[:d].T),
            reward=floats[d],
            terminated=flags[0],
            truncated=flags[1],
            success=flags[2],
            distance=floats[d + 1],
            angle=floats[d + 2] if floats.shape[0] > d + 2 else None,
            final_index=np.zeros(0, dtype=np.int64),
            final_obs=self.split(floats[:d, :0].T),
            collision=flags[3] if flags.shape[0] > 3 else None,
        )

    def split(self, packed: np.ndarray) -> dict[str, np.ndarray]:
        """Split observations ``(..., D)`` (last axis) into the goal-env observation dict.

        The arrays are views of ``packed`` (no copy), and the achieved goal is stored once:
        the end of ``observation`` and ``achieved_goal`` are the same memory. Every step
        packs into a new array, so a returned observation is never overwritten later."""
        o, g = self.observation_size, self.goal_size
        return {
            "observation": packed[..., :o],
            "achieved_goal": packed[..., o - g : o],
            "desired_goal": packed[..., o : o + g],
        }

    def obstacles_of(self, observation: np.ndarray) -> np.ndarray:
        """The obstacle block of observations ``(..., observation_size)`` -> ``(..., obstacle_size)``
        (a view; the slot layout is :mod:`envs.world`'s; ``(..., 0)`` without obstacles)."""
        start = 3 * self.n_joints
        return observation[..., start : start + self.obstacle_size]

    @staticmethod
    def obs_per_env(obs: dict[str, np.ndarray]) -> list[dict[str, np.ndarray]]:
        """An observation dict of ``(m, ...)`` arrays -> ``m`` per-environment dicts of row views
        (for the finished episodes' last observations; dict literals over zipped rows: 1.7x a
        dict of indexed arrays per environment)."""
        keys = ("observation", "achieved_goal", "desired_goal")
        return [{"observation": o, "achieved_goal": a, "desired_goal": d} for o, a, d in zip(*(obs[k] for k in keys))]

    def check_action(self, action, n: int) -> Tensor:
        """Actions ``(n, nj)`` (or ``(nj,)`` for one env), numpy or torch -> the ``(nj, n)``
        tensor the step takes, in the state's dtype and device.

        Raises ``ValueError`` on a wrong shape, a NaN/inf entry or one beyond the state dtype's
        range (finite values outside ``[-1, 1]`` are fine: the step clips them).
        """
        a = self._checked(action, n)
        if isinstance(a, torch.Tensor):
            return a.reshape(n, self.n_joints).T.contiguous()
        columns = torch.from_numpy(np.ascontiguousarray(a.reshape(n, self.n_joints).T))
        return columns if self.device.type == "cpu" else columns.to(self.device)

    def check_action_one(self, action) -> np.ndarray:
        """One CPU env's action ``(nj,)`` (or ``(1, nj)``), numpy or torch -> a finite ``(nj,)`` numpy
        array in the state's dtype (the caller's memory where it already is one); errors as
        :meth:`check_action`."""
        a = self._checked(action, 1)
        return (a.detach().numpy() if isinstance(a, torch.Tensor) else a).reshape(self.n_joints)

    def _checked(self, action, n: int):
        """:meth:`check_action`'s checks -> the action as a numpy array or a tensor, in the state's
        dtype (a tensor on its device), in the shape given."""
        nj = self.n_joints
        real = f"action must be real numbers of shape ({n}, {nj})"
        if isinstance(action, torch.Tensor):
            if action.is_meta or action.is_complex() or action.dtype == torch.bool:
                raise ValueError(f"{real}, got a {'meta' if action.is_meta else action.dtype} tensor")
            a = action.to(self.device, self.dtype)
        else:  # numpy all the way to the transposed copy: a fraction of torch's per-call cost
            try:
                given = np.asarray(action)
            except ValueError:  # ragged
                given = np.asarray(None)
            if given.dtype.kind not in "fiu":  # bools, complex numbers (imaginary parts dropped), objects
                raise ValueError(f"{real}, got {action!r} ({given.dtype})")
            with np.errstate(over="ignore"):  # a number beyond the dtype's range becomes inf: reported below
                a = given.astype(np.float32 if self.dtype == torch.float32 else np.float64, copy=False)
        if tuple(a.shape) != (n, nj) and not (n == 1 and tuple(a.shape) == (nj,)):
            single = f" (or ({nj},))" if n == 1 else ""
            raise ValueError(f"action must have shape ({n}, {nj}){single}, got {tuple(a.shape)}")
        if not all_finite(a):
            raise ValueError(self._non_finite_message(action))
        return a

    def _non_finite_message(self, action) -> str:
        """Why an action that became non-finite in the state's dtype was rejected."""
        given = action.detach().cpu().double().numpy() if isinstance(action, torch.Tensor) else np.asarray(action)
        hint = "actions must be finite (values outside [-1, 1] are clipped)"
        if not np.isfinite(given.astype(np.float64)).all():
            return f"action contains NaN or inf; {hint}"
        kind = str(self.dtype).removeprefix("torch.")
        return (f"action has entries beyond {kind}'s range (largest |a| = {np.abs(given).max():.3g}); {hint}")
