"""Gymnasium reaching environments for any arm (the KUKA LBR iiwa by default): a single env and a batched
vector env.

Both are thin shells over :class:`envs.core.ReachTask`: the same pure, batched torch step
(integrate joint velocities, clamp to the limits, forward kinematics, reward) runs for a
batch of one (``IiwaReachEnv``) or of ``num_envs`` (``IiwaReachVectorEnv``).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from iiwa_torch.checks import is_integer, require

from .core import ReachState, ReachTask
from .goals import GoalKind

__all__ = ["IiwaReachEnv", "IiwaReachVectorEnv", "goal_env_spaces"]

_RENDER_MODES = ["human", "rgb_array"]
_RENDER_FPS = 20  # 1 / dt at the default dt = 0.05 s


def goal_env_spaces(task: ReachTask) -> tuple[spaces.Dict, spaces.Box]:
    """The observation space ``Dict(observation, achieved_goal, desired_goal)`` and the action space."""
    nj, g = task.arm.n_joints, task.goals.size
    goal_high = np.full(g, 1.0, dtype=np.float32)
    goal_high[:3] = task.arm.position_bound
    # the obstacle block: flags, cos and sin in [0, 1] or [-1, 1], positions and sizes within reach
    block_high = np.full(task.transport.obstacle_size, max(1.0, task.arm.position_bound), dtype=np.float32)
    # the clearance rows (m, then m/rad): below CLEARANCE_RANGE, and a point's speed per joint speed
    sensed_high = np.full(task.transport.clearance_size, max(1.0, task.arm.position_bound), dtype=np.float32)
    obs_high = np.concatenate([np.ones(3 * nj, dtype=np.float32), block_high, sensed_high, goal_high])
    observation = spaces.Dict(
        {
            "observation": spaces.Box(-obs_high, obs_high, dtype=np.float32),
            "achieved_goal": spaces.Box(-goal_high, goal_high, dtype=np.float32),
            "desired_goal": spaces.Box(-goal_high, goal_high, dtype=np.float32),
        }
    )
    return observation, spaces.Box(-1.0, 1.0, shape=(nj,), dtype=np.float32)


def _info(task: ReachTask, success, distance, angle, collision=None) -> dict[str, Any]:
    info = {"is_success": success, "distance": distance}
    if task.goal_kind is GoalKind.POSE:
        info["orientation_error"] = angle
    if collision is not None:
        info["collision"] = collision
    return info


class IiwaReachEnv(gym.Env):
    """Reach a goal with the end effector of a KUKA LBR iiwa 14 R820, by joint velocity commands.

    ## Description

    A kinematic 7-joint arm (no dynamics): each step integrates the commanded joint
    velocities over ``dt``, clamps the joints to their limits, computes the end effector by
    forward kinematics and checks collisions (floor, self, obstacles; ``info["collision"]``,
    see docs/envs.md). Goals are the forward kinematics of random collision-free
    configurations within the joint limits, so every goal is reachable. The observation
    follows panda-gym's goal-conditioned layout, so hindsight experience replay (HER)
    works out of the box. The step is :meth:`envs.core.ReachTask.step`, the same batched
    function that drives :class:`IiwaReachVectorEnv` and ``envs.sb3.IiwaReachVecEnv``.

    ## Action Space

    ``Box(-1, 1, (7,), float32)``: joint velocities as fractions of the datasheet's
    maximum joint speeds (85, 85, 100, 75, 130, 135, 135 deg/s). Joint ``i`` moves by
    ``a_i * v_max_i * dt`` radians, then is clamped into its limits. Values outside
    ``[-1, 1]`` are clipped; NaN/inf, a number beyond float32's range or a wrong shape raise
    ``ValueError``.

    ## Observation Space

    ``Dict`` of float32 boxes:

    - ``observation`` ``(21 + g,)``: ``cos q`` (7), ``sin q`` (7), the joint velocity of the
      last step over ``v_max`` (7, in ``[-1, 1]``; zero at reset), then the achieved goal (g);
    - ``achieved_goal`` ``(g,)``: the end-effector position (m, base frame), and for pose
      goals also the first two columns of its rotation matrix (g = 3 or 9);
    - ``desired_goal`` ``(g,)``: the goal in the same form. It appears only here, so
      relabelling goals (HER) never contradicts the ``observation``.

    ## Rewards

    ``compute_reward(achieved_goal, desired_goal, info)`` (batched, numpy or torch in, float32 numpy out):

    - dense (``IiwaReach-v0``): ``-d``, the distance in metres;
    - sparse (``IiwaReachSparse-v0``): ``0`` if successful, else ``-1``;
    - pose (``IiwaReachPose-v0``, dense): ``-(d + orientation_weight * angle)``, the angle
      (rad) of the rotation between the achieved and desired orientations.

    Success: ``d < distance_threshold`` (default 0.01 m) and, for pose goals,
    ``angle < orientation_threshold`` (default 0.1 rad). ``info`` holds ``is_success``,
    ``distance`` and, for pose goals, ``orientation_error``.

    ## Starting State

    ``start="home"`` (default): ``iiwa_torch.robots.IIWA_HOME``, ``q = (0, 30, 0, -60, 0, 30, 0)``
    degrees, zero velocity.
    ``start="random"``: uniform within the joint limits. The goal is drawn at every reset;
    with ``goal_min_distance > 0`` goals nearer than that to the start are redrawn.

    ## Episode End

    Terminated when successful (``terminate_on_success=True``, as panda-gym) or, with
    ``collision="terminate"`` (default), on a collision. Truncated
    after ``max_episode_steps`` (50 in the registered ids, through gymnasium's
    ``TimeLimit``): from home, a straight full-speed joint move reaches any configuration
    within the limits in at most 48 steps (2.4 s, joint 4's 180 deg at 75 deg/s), so every
    goal is reachable in time. With ``start="random"`` the same bound is 80 steps; use
    ``max_episode_steps=100`` there.

    ## Arguments

    ``gymnasium.make("IiwaReach-v0", render_mode=None, **options)`` where ``options`` are
    :class:`envs.core.ReachTask`'s (the task's own, with their units and ranges:
    :class:`envs.settings.ReachSettings`): ``robot`` (a preset name, ``"panda"``, a URDF path or a ``Chain``
    with velocity limits, default ``iiwa14()``; the action space then has one entry per joint),
    ``end_link``, ``capsules``, ``goal`` (``"position"``/``"pose"``), ``goal_region``
    (``"joint_limits"``/``"panda_gym"``), ``reward`` (``"dense"``/``"sparse"``),
    ``start`` (``"home"``/``"random"``), ``dt`` (0.05 s), ``distance_threshold`` (0.01 m),
    ``orientation_threshold`` (0.1 rad), ``orientation_weight`` (0.1 m/rad),
    ``goal_min_distance`` (0 m), ``floor`` (0 m; ``None``: none), ``collision``
    (``"terminate"``/``"penalize"``/``"off"``), ``collision_penalty`` (1.0), ``obstacles`` (0;
    4 in ``IiwaReachObstacles-v0``), ``max_episode_steps`` (the env's own limit, default
    ``None``: ``gymnasium.make`` adds ``TimeLimit`` instead), ``terminate_on_success``,
    ``home``, ``dtype`` (float32), ``device``. ``render_mode``: ``"rgb_array"`` (matplotlib,
    an ``(H, W, 3)`` uint8 image) or ``"human"`` (a matplotlib window).

    ## Version History

    - v0: initial version.
    """

    metadata = {"render_modes": _RENDER_MODES, "render_fps": _RENDER_FPS}

    def __init__(self, render_mode: str | None = None, **task_options: Any) -> None:
        if render_mode is not None and render_mode not in _RENDER_MODES:
            raise ValueError(f"render_mode must be one of {_RENDER_MODES} or None, got {render_mode!r}")
        self.task = ReachTask(**task_options)
        self.observation_space, self.action_space = goal_env_spaces(self.task)
        self.render_mode = render_mode
        self._state: ReachState | None = None
        self._figure = None
        self._image = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start an episode. ``reset(seed=s)``, ``s`` in ``[0, 2**64)``, makes the following episodes reproducible."""
        if options:
            raise ValueError(f"reset takes no options, got {options!r}")
        state, floats, flags = self.task.reset_one(self._state, seed, self.np_random)  # checks the seed first
        super().reset(seed=seed)
        self._state = state
        if self.render_mode == "human":
            self.render()
        obs, _, _, _, info = self._outputs(floats, flags)
        return obs, info

    def step(self, action):
        """Apply one joint-velocity command ``(7,)``; see the class docstring."""
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        self._state, floats, flags = self.task.step_one(self._state, action)
        if self.render_mode == "human":
            self.render()
        return self._outputs(floats, flags)

    def _outputs(self, floats: np.ndarray, flags: np.ndarray) -> tuple:
        """The packed rows of a step or a reset (``transport.pack``'s, as numpy) -> observation, reward,
        terminated, truncated and info."""
        d = self.task.transport.packed_size
        reward, dist, *angle = floats[d:].tolist()  # angle: one number for pose goals, none for positions
        term, trunc, success, *collision = flags.tolist()  # collision: one flag when checked, else none
        info = _info(self.task, success, dist, angle[0] if angle else None, collision[0] if collision else None)
        return self.task.transport.split(floats[:d]), reward, term, trunc, info

    @property
    def joint_angles(self) -> np.ndarray:
        """The arm's current joint angles ``(7,)``, radians (e.g. to animate an episode with
        ``iiwa_torch.viz.animate(env.unwrapped.task.robot, qs, "episode.gif")``)."""
        if self._state is None:
            raise RuntimeError("call reset() first")
        return self._state.q[:, 0].double().cpu().numpy()

    def compute_reward(self, achieved_goal, desired_goal, info=None):
        """Batched reward: goals ``(..., g)``, numpy or torch -> ``(...)`` float32 numpy; the collision
        penalty is taken from ``info`` (:meth:`envs.core.ReachTask.compute_reward`)."""
        return self.task.compute_reward(achieved_goal, desired_goal, info)

    def render(self):
        """``rgb_array``: an ``(H, W, 3)`` uint8 image of the arm, its end effector and the goal."""
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode='rgb_array' or 'human'")
            return None
        if self._state is None:
            raise RuntimeError("call reset() before render()")
        from iiwa_torch.viz import render_rgb

        image = render_rgb(self.task.robot, self._state.q[:, 0], goal=self._state.goal[:3, 0], size=(480, 480))
        if self.render_mode == "rgb_array":
            return image
        plt = require("matplotlib.pyplot", "viz")  # "human": show the same picture in a pyplot window

        if self._figure is None:
            self._figure = plt.figure("IiwaReach")
            self._image = self._figure.add_subplot().imshow(image)
            self._figure.axes[0].set_axis_off()
        else:
            self._image.set_data(image)
        plt.pause(1 / self.metadata["render_fps"])
        return None

    def close(self) -> None:
        if self._figure is not None:
            require("matplotlib.pyplot", "viz").close(self._figure)
            self._figure = None


class IiwaReachVectorEnv(VectorEnv):
    """``num_envs`` iiwa reaching tasks stepped by one batched torch call (a gymnasium ``VectorEnv``).

    Same task, spaces and options as :class:`IiwaReachEnv` (see there), with all state
    in ``(num_envs, ...)`` tensors and no Python loop over environments in a step.

    Differences from the single env:

    - ``max_episode_steps`` (default 50) is the env's own; ``gymnasium.make_vec`` passes
      the registered value.
    - Auto-reset happens in the same step (``metadata["autoreset_mode"] ==
      AutoresetMode.SAME_STEP``): when an environment terminates or truncates, the
      returned observation is the first of its next episode; reward, flags and ``info``
      (``is_success``, ``distance``) describe the finished step, and its last observation
      is ``info["final_obs"][i]`` (an object array of per-env dicts, ``None`` elsewhere,
      with the mask ``info["_final_obs"]``, as gymnasium's ``SyncVectorEnv`` does; the same
      step's info is also under ``info["final_info"]``). Gymnasium's vector wrappers
      (``RecordEpisodeStatistics``, ...) read this mode from ``metadata``.
    - ``reset(seed=s)`` seeds environment ``i`` with ``s + i`` (a list of seeds works too):
      the batch then runs exactly like single envs reset with those seeds.
    - ``step`` accepts a numpy array or a torch tensor of shape ``(num_envs, 7)``.
    - Observations are ``(num_envs, ...)`` float32 views of one array per step, stored one
      component per memory row (Fortran order), which keeps the batched step fast; each
      step returns new arrays, so earlier observations stay valid.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": _RENDER_FPS, "autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(
        self, num_envs: int = 1, max_episode_steps: int | None = 50, render_mode: str | None = None, **task_options: Any
    ) -> None:
        if not is_integer(num_envs) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive int, got {num_envs!r}")
        if render_mode is not None and render_mode != "rgb_array":
            raise ValueError(f"render_mode must be 'rgb_array' or None, got {render_mode!r}")
        self.num_envs = int(num_envs)
        self.render_mode = render_mode
        self.task = ReachTask(max_episode_steps=max_episode_steps, **task_options)
        self.single_observation_space, self.single_action_space = goal_env_spaces(self.task)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._state: ReachState | None = None

    @torch.inference_mode()
    def reset(self, *, seed: int | list[int | None] | None = None, options: dict | None = None):
        """Reset every environment; ``seed=s`` seeds environment ``i`` with ``s + i``."""
        if options:
            raise ValueError(f"reset takes no options, got {options!r}")
        if isinstance(seed, int) and not isinstance(seed, bool):
            seeds = [seed + i for i in range(self.num_envs)]
        elif seed is None or isinstance(seed, (list, tuple)):
            seeds = [None] * self.num_envs if seed is None else list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(f"seed must be an int or a list of {self.num_envs} ints/None, got {len(seeds)} seeds")
        else:
            raise ValueError(f"seed must be an int, a list of ints/None or None, got {seed!r}")
        state = self.task.reset_all(self._state, seeds, self.np_random)  # checks the seeds first
        if isinstance(seed, int):
            super().reset(seed=seed)
        self._state = state
        tr = self.task.reset_transition(self._state)
        return tr.obs, _info(self.task, tr.success, tr.distance, tr.angle, tr.collision)

    @torch.inference_mode()
    def step(self, actions):
        """Step all environments with ``(num_envs, 7)`` actions; finished ones restart in the same step."""
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        a = self.task.transport.check_action(actions, self.num_envs)
        self._state, tr = self.task.step_autoreset(self._state, a)
        info = _info(self.task, tr.success, tr.distance, tr.angle, tr.collision)
        if tr.final_index.size:
            final = np.full(self.num_envs, None, dtype=object)
            final[tr.final_index] = self.task.transport.obs_per_env(tr.final_obs)  # finished environments only
            done = tr.terminated | tr.truncated
            info["final_obs"], info["_final_obs"] = final, done
            # the finished step's info (already in ``info``), under the name SyncVectorEnv uses
            info["final_info"] = {**_info(self.task, tr.success, tr.distance, tr.angle, tr.collision),
                                  "_is_success": done}
            info["_final_info"] = done
        return tr.obs, tr.reward, tr.terminated, tr.truncated, info

    def compute_reward(self, achieved_goal, desired_goal, info=None):
        """Batched reward: goals ``(..., g)``, numpy or torch -> ``(...)`` float32 numpy; the collision
        penalty is taken from ``info`` (:meth:`envs.core.ReachTask.compute_reward`)."""
        return self.task.compute_reward(achieved_goal, desired_goal, info)

    def render(self):
        """``rgb_array``: a tuple with one image per environment (slow for large ``num_envs``)."""
        if self.render_mode is None:
            gym.logger.warn("render() called without render_mode='rgb_array'")
            return None
        if self._state is None:
            raise RuntimeError("call reset() before render()")
        from iiwa_torch.viz import render_rgb

        state = self._state
        return tuple(render_rgb(self.task.robot, q, goal=g[:3]) for q, g in zip(state.q.T, state.goal.T))

