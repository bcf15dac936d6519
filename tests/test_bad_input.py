"""Every public entry point, walked with the classes of bad input: wrong shapes, integer and
half-precision dtypes, NaN/inf, meta tensors, non-rigid poses, bad choice strings, zero or
negative counts and tolerances. Each must raise ``ValueError``/``TypeError`` whose message
names the argument (never a raw torch/numpy error, never a NaN result).

The table :data:`ENTRIES` is checked against the modules' ``__all__`` (and ``DHChain``'s public
methods): a new public name must get an entry here or a reason in :data:`EXEMPT`.
"""

from __future__ import annotations

import importlib
import inspect
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, fields, is_dataclass

import numpy as np
import pytest
import torch

import envs
from envs.core import ReachTask
from envs.goals import decode_pose_goal, encode_pose_goal
from envs.reach import IiwaReachEnv, IiwaReachVectorEnv, goal_env_spaces
from envs.sb3 import IiwaReachVecEnv
from iiwa_torch import Chain, DHChain, capsule_fit, collision, robots, so3, trajectory, urdf, workspace
from iiwa_torch.ik import MinimizeOptions, SolveOptions, analytic, dls_step, minimize, solve

CHAIN = robots.iiwa14()
PUMA = robots.puma560()
Q = CHAIN.random_q(3, generator=torch.Generator().manual_seed(0))  # (3, 7) float64
POSE = CHAIN.fk(Q)  # (3, 4, 4)
PUMA_POSE = PUMA.fk(PUMA.random_q(3, generator=torch.Generator().manual_seed(1)))
ROT = POSE[:, :3, :3]
URDF = urdf.to_urdf(CHAIN)
SPHERES = (  # two joints, a sphere on each link, for capsule_fit
    '<robot name="s"><link name="a"><collision><geometry><sphere radius="0.1"/></geometry></collision></link>'
    '<link name="b"><collision><geometry><sphere radius="0.1"/></geometry></collision></link><link name="c">'
    '<collision><geometry><sphere radius="0.1"/></geometry></collision></link>'
    '<joint name="j1" type="revolute"><parent link="a"/><child link="b"/><origin xyz="0 0 0.3"/>'
    '<limit lower="-1" upper="1" effort="1" velocity="1"/></joint>'
    '<joint name="j2" type="revolute"><parent link="b"/><child link="c"/>'
    '<origin xyz="0.3 0 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint></robot>'
)


@dataclass(frozen=True)
class Entry:
    """One public callable: ``call(**good())`` is valid; each name in ``tensors`` (``poses``) gets
    every bad float tensor (and every non-rigid pose); ``bad`` adds ``(argument, value)`` pairs.
    Each bad call must raise ``ValueError``/``TypeError`` whose message names the argument
    (``names`` maps an argument to the name the message uses, e.g. ``n`` -> ``shape``)."""

    call: Callable
    good: Callable[[], dict]
    tensors: tuple[str, ...] = ()
    poses: tuple[str, ...] = ()
    bad: tuple[tuple[str, object], ...] = ()
    names: tuple[tuple[str, str], ...] = ()
    converts_dtype: bool = False  # data converted to float64 (a constructor): no dtype variants


def _counts(*names: str, allow_zero=False) -> tuple:
    """Bad values of integer count arguments."""
    values = (-1, 2.5, True, "3") + (() if allow_zero else (0,))
    return tuple((n, v) for n in names for v in values)


def _bools(*names: str) -> tuple:
    """Values of boolean options whose truthiness must not stand in for True or False."""
    return tuple((n, v) for n in names for v in ("no", "False", None, 1, 0.0))


def _non_rotations(name: str) -> tuple:
    """Finite ``(3, 3)`` matrices that are not rotations: scaled, a reflection, a shear."""
    shear = torch.eye(3, dtype=torch.float64)
    shear[0, 1] = 0.5
    return tuple((name, m) for m in (2 * ROT, -ROT, shear))
# a NumPy generator, a seed and a torch generator's class are not torch generators
_GENERATORS = tuple(("generator", g) for g in (np.random.default_rng(0), 5, torch.Generator))
_TWO_WORLDS = collision.World(spheres=(torch.zeros(2, 1, 3, dtype=torch.float64),
                                       torch.ones(2, 1, dtype=torch.float64)))
_DEVICES = (("device", "meta"), ("device", "gpu0")) + (() if torch.cuda.is_available() else (("device", "cuda"),))


def _tols(*names: str) -> tuple:
    """Bad values of positive finite tolerances / sizes."""
    return tuple((n, v) for n in names for v in (0.0, -1e-3, math.nan, math.inf, "1e-3"))


def _env_step(env_cls, n: int | None):
    def run(action, **kw):
        env = env_cls(**kw) if n is None else env_cls(n, **kw)
        env.reset(seed=0)
        return env.step(action)

    return run


def _env_reset(env_cls, n: int | None):
    def run(seed, **kw):
        env = env_cls(**kw) if n is None else env_cls(n, **kw)
        return env.reset(seed=seed)

    return run


def _vec_step(action):
    vec = IiwaReachVecEnv(2, seed=0)
    vec.reset()
    vec.step_async(action)
    return vec.step_wait()


def _compute_reward(achieved_goal, desired_goal):
    return IiwaReachEnv().compute_reward(achieved_goal, desired_goal, None)


_TASK_OPTIONS = _tols("dt", "distance_threshold", "orientation_threshold") + (
    ("orientation_weight", -1.0),
    ("orientation_weight", math.nan),
    ("goal_min_distance", -0.1),
    ("goal_min_distance", math.nan),
    ("goal", "orientation"),
    ("reward", "shaped"),
    ("start", "anywhere"),
    ("max_episode_steps", 0),
    ("max_episode_steps", -3),
    ("max_episode_steps", 2.5),
    ("dtype", torch.float16),
    ("dtype", torch.int64),
    ("robot", "iiwa15"),
    ("robot", 14),
    ("end_link", "tool0"),
    ("capsules", "capsules"),
    ("goal_region", "anywhere"),
    ("home", torch.full((6,), 0.1)),
    ("home", torch.full((7,), math.nan)),
    *_bools("terminate_on_success", "observe_clearance"),
)

ENTRIES: dict[str, Entry] = {
    # ------------------------------------------------------------------ the chain
    "iiwa_torch.robots:from_urdf": Entry(
        robots.from_urdf,
        lambda: {"source": URDF},
        bad=(
            ("source", "<robot"),
            ("source", "/no/such.urdf"),
            ("source", 3),
            ("end_link", "nope"),
            ("end_link", 5),
            ("base_link", "x"),
        ),
    ),
    "iiwa_torch.capsule_fit:urdf_capsules": Entry(
        capsule_fit.urdf_capsules,
        lambda: {"chain": robots.from_urdf(SPHERES), "source": SPHERES, "samples": 64},
        bad=(
            ("chain", "panda"),
            ("chain", CHAIN),
            ("source", "<robot"),
            ("source", 3),
            ("base_link", "nope"),
            ("pairs", [("a", "x")]),
            ("pairs", [("a", "a")]),
            *_counts("samples"),
            *_counts("seed", allow_zero=True),
        ),
    ),
    "iiwa_torch:Chain": Entry(
        Chain,
        lambda: {"origins": POSE[:2], "axes": torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]]),
                 "limits": CHAIN.limits[:, :2], "base": torch.eye(4), "tool": POSE[0]},
        poses=("base", "tool"),
        converts_dtype=True,
        bad=(
            ("origins", POSE[:2, :3]),
            ("origins", POSE[:2] * 2),
            ("axes", torch.zeros(2, 3)),
            ("axes", torch.ones(3, 3)),
            ("axes", torch.full((2, 3), math.nan)),
            ("limits", CHAIN.limits[:, :1]),
            ("limits", CHAIN.limits[:, :2].flip(0)),
            ("limits", CHAIN.limits[:, :2].clone().fill_(math.inf)),
            ("kinds", ["revolute", "spherical"]),
            ("kinds", ["revolute"]),
            ("velocity_limits", torch.full((2,), -1.0)),
            ("name", 3),
        ),
    ),
    "iiwa_torch:DHChain": Entry(
        DHChain,
        lambda: {"table": CHAIN.dh, "limits": CHAIN.limits, "base": torch.eye(4), "tool": POSE[0]},
        poses=("base", "tool"),
        converts_dtype=True,
        bad=(
            ("table", CHAIN.dh[:, :3]),
            ("table", CHAIN.dh.clone().fill_(math.nan)),
            ("table", CHAIN.dh.to("meta")),
            ("limits", CHAIN.limits[:, :6]),
            ("limits", CHAIN.limits.flip(0)),
            ("limits", CHAIN.limits.clone().fill_(math.inf)),
            ("convention", "craig"),
            ("velocity_limits", torch.full((7,), -1.0)),
            ("velocity_limits", torch.full((7,), math.nan)),
            ("name", 3),
        ),
    ),
    "DHChain.fk": Entry(CHAIN.fk, lambda: {"q": Q}, tensors=("q",)),
    "DHChain.fk_all": Entry(CHAIN.fk_all, lambda: {"q": Q}, tensors=("q",)),
    "DHChain.position": Entry(CHAIN.position, lambda: {"q": Q}, tensors=("q",)),
    "DHChain.jacobian": Entry(CHAIN.jacobian, lambda: {"q": Q}, tensors=("q",)),
    "DHChain.clamp": Entry(CHAIN.clamp, lambda: {"q": Q}, tensors=("q",)),
    "DHChain.within_limits": Entry(CHAIN.within_limits, lambda: {"q": Q}, tensors=("q",)),
    "DHChain.check_q": Entry(CHAIN.check_q, lambda: {"q": Q}, tensors=("q",)),
    "DHChain.random_q": Entry(
        lambda n, **kw: CHAIN.random_q(n, **kw),
        lambda: {"n": 3},
        bad=_counts("n", allow_zero=True) + (("dtype", torch.float16), ("dtype", torch.int32)) + _GENERATORS,
        names=(("n", "shape"),),
    ),
    "DHChain.reach_bound": Entry(
        CHAIN.reach_bound, lambda: {"point": torch.zeros(3, dtype=torch.float64)}, bad=(("point", [1.0, math.nan]),)
    ),
    "iiwa_torch.robots:iiwa14": Entry(robots.iiwa14, lambda: {}, bad=_tols("flange")[1:] + (("tool", torch.eye(3)),)),
    "iiwa_torch.robots:iiwa7": Entry(robots.iiwa7, lambda: {}, bad=_tols("flange")[1:] + (("tool", torch.eye(3)),)),
    "iiwa_torch.robots:planar3r": Entry(robots.planar3r, lambda: {}, bad=_tols("l1", "l2", "l3")),
    # ------------------------------------------------------------------ so3
    "iiwa_torch.so3:skew": Entry(so3.skew, lambda: {"v": Q[:, :3]}, tensors=("v",)),
    "iiwa_torch.so3:exp": Entry(
        so3.exp, lambda: {"rotvec": Q[:, :3]}, tensors=("rotvec",),
        bad=(("rotvec", torch.full((3,), 1e300, dtype=torch.float64)), ("rotvec", torch.full((3,), 2e19))),
    ),  # fmt: skip
    "iiwa_torch.so3:log": Entry(so3.log, lambda: {"rot": ROT}, tensors=("rot",), bad=_non_rotations("rot")),
    "iiwa_torch.so3:check_rotation": Entry(
        so3.check_rotation, lambda: {"rot": ROT}, tensors=("rot",), bad=_non_rotations("rot")
    ),
    "iiwa_torch.so3:matrix_to_quaternion": Entry(so3.matrix_to_quaternion, lambda: {"rot": ROT}, tensors=("rot",)),
    "iiwa_torch.so3:quaternion_to_matrix": Entry(
        so3.quaternion_to_matrix, lambda: {"quat": Q[:, :4]}, tensors=("quat",), bad=(("quat", torch.zeros(4)),)
    ),
    "iiwa_torch.so3:matrix_to_rpy": Entry(so3.matrix_to_rpy, lambda: {"rot": ROT}, tensors=("rot",)),
    "iiwa_torch.so3:rpy_to_matrix": Entry(so3.rpy_to_matrix, lambda: {"rpy": Q[:, :3]}, tensors=("rpy",)),
    "iiwa_torch.so3:pose_error": Entry(
        so3.pose_error, lambda: {"pose": POSE, "target": POSE.flip(0)}, poses=("pose", "target")
    ),
    "iiwa_torch.so3:check_pose": Entry(so3.check_pose, lambda: {"pose": POSE}, tensors=("pose",)),
    "iiwa_torch.so3:check_rigid": Entry(so3.check_rigid, lambda: {"pose": POSE}, poses=("pose",)),
    # ------------------------------------------------------------------ inverse kinematics
    "iiwa_torch.ik:solve": Entry(
        solve,
        lambda: {"chain": CHAIN, "target": POSE, "q0": Q, "iterations": 2, "rest": Q, "rest_gain": 0.1},
        tensors=("q0", "rest"),
        poses=("target",),
        bad=(("mode", "orientation"), ("precision", "half"), ("rest_gain", 2.0), ("world", _TWO_WORLDS),
             ("options", {"seeds": 2}), ("options", MinimizeOptions()), ("damping_up", 0.9), ("colour", 1))
        + _GENERATORS
        + _counts("seeds", "iterations", "check_every")
        + _tols("pos_tol", "rot_tol", "rot_weight"),
    ),
    "iiwa_torch.ik:minimize": Entry(
        minimize,
        lambda: {"chain": CHAIN, "loss": lambda q, p: q.square().sum(-1), "q0": Q, "target": POSE, "steps": 2},
        tensors=("q0",),
        poses=("target",),
        bad=(("mode", "orientation"), ("optimizer", "sgd"), ("loss", None), ("world", _TWO_WORLDS),
             ("loss", lambda q, p: torch.ones(q.shape[:-1], dtype=q.dtype)),  # does not depend on q
             ("loss", lambda q, p: p.detach()[..., 2, 3]), ("options", SolveOptions()), ("seeds", 2))
        + _counts("steps")
        + _tols("pos_tol", "rot_tol", "lr"),
    ),
    "iiwa_torch.ik:SolveOptions": Entry(
        SolveOptions,
        lambda: {"pos_tol": 1e-5, "free_steps": 0},
        bad=(("mode", "orientation"), ("precision", "half"), ("rest_gain", 2.0), ("rest_gain", -0.1),
             ("damping_down", 1.0), ("damping_down", 0.0), ("damping_up", 1.0), ("damping_up", math.inf))
        + _counts("seeds", "iterations", "check_every")
        + _counts("free_steps", allow_zero=True)
        + _tols("pos_tol", "rot_tol", "rot_weight", "damping"),
    ),
    "iiwa_torch.ik:MinimizeOptions": Entry(
        MinimizeOptions,
        lambda: {"optimizer": "lbfgs"},
        bad=(("mode", "orientation"), ("optimizer", "sgd")) + _counts("steps")
        + _tols("pos_tol", "rot_tol", "lr", "clearance_weight"),
    ),
    "iiwa_torch.ik:dls_step": Entry(
        dls_step,
        lambda: {"jacobian": CHAIN.jacobian(Q), "error": torch.ones(3, 6, dtype=torch.float64), "damping": 1e-2},
        tensors=("error",),
        bad=(
            ("jacobian", torch.ones(6)),
            ("jacobian", torch.ones(3, 6, 7, dtype=torch.float16)),
            ("jacobian", torch.full((3, 6, 7), math.nan, dtype=torch.float64)),
            ("jacobian", torch.ones(3, 6, 7, dtype=torch.float64, device="meta")),
        )
        + _tols("damping")[1:],
    ),
    "iiwa_torch.ik.analytic:iiwa": Entry(
        analytic.iiwa,
        lambda: {"chain": CHAIN, "target": POSE, "psi": torch.zeros(3, dtype=torch.float64)},
        tensors=("psi",),
        poses=("target",),
        bad=(("chain", PUMA), ("psi", "0")),
    ),
    "iiwa_torch.ik.analytic:iiwa_arm_angle": Entry(
        analytic.iiwa_arm_angle, lambda: {"chain": CHAIN, "q": Q}, tensors=("q",), bad=(("chain", PUMA),)
    ),
    "iiwa_torch.ik.analytic:iiwa_q3_locked": Entry(
        analytic.iiwa_q3_locked,
        lambda: {"chain": CHAIN, "target": POSE, "q3": torch.zeros(3, dtype=torch.float64)},
        tensors=("q3",),
        poses=("target",),
        bad=(("chain", PUMA),),
    ),
    "iiwa_torch.ik.analytic:iiwa_solve": Entry(
        analytic.iiwa_solve,
        lambda: {"chain": CHAIN, "target": POSE, "q0": Q, "num_psi": 2},
        tensors=("q0",),
        poses=("target",),
        bad=_counts("num_psi") + _tols("pos_tol", "rot_tol"),
    ),
    "iiwa_torch.ik.analytic:structure": Entry(
        analytic.structure, lambda: {"chain": PUMA}, bad=(("chain", "puma"), ("tol", -1.0), ("tol", math.nan))
    ),
    "iiwa_torch.ik.analytic:solve": Entry(
        analytic.solve, lambda: {"chain": PUMA, "target": PUMA_POSE}, poses=("target",),
        bad=(("chain", "puma"), ("psi", 0.5)),
    ),
    "iiwa_torch.ik.analytic:pieper": Entry(
        analytic.pieper, lambda: {"chain": PUMA, "target": PUMA_POSE}, poses=("target",), bad=(("chain", CHAIN),)
    ),
    "iiwa_torch.ik.analytic:planar3r": Entry(
        analytic.planar3r,
        lambda: {
            "chain": robots.planar3r(),
            "x": torch.tensor([1.0, 0.5], dtype=torch.float64),
            "y": torch.tensor([0.5, 1.0], dtype=torch.float64),
            "phi": torch.tensor([0.1, 0.2], dtype=torch.float64),
        },
        tensors=("x", "y", "phi"),
        bad=(("chain", CHAIN),),
    ),
    # ------------------------------------------------------------------ trajectories
    "iiwa_torch.trajectory:jtraj": Entry(
        trajectory.jtraj,
        lambda: {"q0": Q, "q1": Q.flip(0), "t": 5, "qd0": torch.zeros_like(Q)},
        tensors=("q0", "q1", "qd0"),
        bad=(("t", 1), ("t", 0), ("t", -3), ("t", 2.5), ("t", torch.tensor([0.0, 1.0, 0.5], dtype=torch.float64)),
             ("t", torch.tensor([0.0, 1e-200], dtype=torch.float64)),  # accelerations overflow
             ("t", "10"), ("t", None), ("q1", Q.float()), ("qd0", torch.zeros_like(Q).float())),
    ),
    "iiwa_torch.trajectory:ctraj": Entry(
        trajectory.ctraj,
        lambda: {"T0": POSE, "T1": POSE.flip(0), "t": 4},
        poses=("T0", "T1"),
        bad=(("t", 1), ("t", -2), ("t", "4"), ("profile", "cubic"), ("T1", POSE.float())),
    ),
    "iiwa_torch.trajectory:track": Entry(
        trajectory.track,
        lambda: {"chain": CHAIN, "poses": POSE[None], "q0": Q[0]},
        tensors=("q0",),
        poses=("poses",),
        bad=(("method", "rrt"), ("rest_gain", math.nan), ("rest_gain", -1.0), ("poses", POSE[:0]))
        + _tols("pos_tol", "rot_tol"),
    ),
    "iiwa_torch.trajectory:path_clearance": Entry(
        trajectory.path_clearance,
        lambda: {"chain": CHAIN, "q": Q[None], "world": collision.World()},
        tensors=("q",),
        bad=(("capsules", "capsules"),),
    ),
    "iiwa_torch.trajectory:shortest_duration": Entry(
        trajectory.shortest_duration,
        lambda: {"chain": CHAIN, "q0": Q, "q1": Q.flip(0)},
        tensors=("q0", "q1"),
        bad=(("speed_scale", 1.5),) + _tols("speed_scale"),
    ),
    "iiwa_torch.trajectory:sampled_duration": Entry(
        trajectory.sampled_duration,
        lambda: {"chain": CHAIN, "q": Q},
        tensors=("q",),
        bad=(("speed_scale", 1.5),) + _tols("speed_scale"),
    ),
    # ------------------------------------------------------------------ collision
    "iiwa_torch.collision:World": Entry(
        collision.World,
        lambda: {
            "floor": 0.0,
            "walls": (torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64), torch.tensor([-1.0], dtype=torch.float64)),
            "boxes": (POSE[:1], torch.full((1, 3), 0.1, dtype=torch.float64)),
        },
        bad=(
            ("floor", math.nan),
            ("floor", "0"),
            ("floor", True),
            ("floor", -1e200),  # beyond collision.MAX_EXTENT: squared distances would overflow
            ("spheres", (torch.tensor([[1e200, 0.0, 0.0]], dtype=torch.float64), torch.ones(1, dtype=torch.float64))),
            ("spheres", (torch.tensor([[0.0, 0.0, 3e19]]), torch.tensor([0.1]))),
            ("capsules", (torch.zeros(1, 2, 3, dtype=torch.float64), torch.tensor([1e160], dtype=torch.float64))),
            ("walls", torch.zeros(1, 3)),
            ("walls", (torch.zeros(1, 3, dtype=torch.float64), torch.zeros(1, dtype=torch.float64))),
            ("walls", (torch.tensor([[1.0, 0, 0]]), torch.tensor([math.nan]))),
            ("spheres", (torch.zeros(1, 3, dtype=torch.float64), torch.full((1,), -0.1, dtype=torch.float64))),
            ("spheres", (torch.zeros(1, 3, dtype=torch.float16), torch.full((1,), 0.1, dtype=torch.float16))),
            ("boxes", (2 * POSE[:1], torch.full((1, 3), 0.1, dtype=torch.float64))),
            ("capsules", (torch.zeros(1, 3, 3, dtype=torch.float64), torch.ones(1, dtype=torch.float64))),
        ),
    ),
    "iiwa_torch.collision:check_world": Entry(
        collision.check_world,
        lambda: {"world": collision.World(), "margin": 0.01},
        bad=(("margin", "1 cm"), ("capsules", "capsules")),
    ),
    "iiwa_torch.collision:clearance": Entry(
        collision.clearance,
        lambda: {"chain": CHAIN, "q": Q, "world": collision.World()},
        tensors=("q",),
        bad=(("world", 0.0), ("capsules", "capsules"), ("world", _TWO_WORLDS)),
    ),
    "iiwa_torch.collision:capsule_clearance": Entry(
        collision.capsule_clearance,
        lambda: {"chain": CHAIN, "q": Q, "world": collision.World()},
        tensors=("q",),
        bad=(("world", 0.0), ("capsules", "capsules")),
    ),
    "iiwa_torch.collision:pairwise_clearance": Entry(
        collision.pairwise_clearance,
        lambda: {"chain": CHAIN, "q": Q, "world": collision.World()},
        tensors=("q",),
        bad=(("world", 0.0), ("capsules", "capsules")),
    ),
    "iiwa_torch.collision:robot_capsules": Entry(collision.robot_capsules, lambda: {"chain": CHAIN}),
    "iiwa_torch.collision:self_collision_pairs": Entry(
        collision.self_collision_pairs,
        lambda: {"chain": CHAIN, "capsules": collision.robot_capsules(CHAIN), "samples": 64},
        bad=_counts("samples") + (("seed", -1), ("seed", 1.5), ("capsules", None)),
    ),
    "iiwa_torch.collision:segment_distance": Entry(
        collision.segment_distance,
        lambda: {"p1": Q[:, :3], "q1": Q[:, 1:4], "p2": Q[:, 2:5], "q2": Q[:, 3:6]},
        tensors=("p1", "q1", "p2", "q2"),
    ),
    "iiwa_torch.collision:segment_box_distance": Entry(
        collision.segment_box_distance,
        lambda: {"p": Q[:, :3], "q": Q[:, 1:4], "pose": POSE, "half": torch.full((3, 3), 0.1, dtype=torch.float64)},
        tensors=("p", "q", "half"),
        poses=("pose",),
    ),
    # ------------------------------------------------------------------ workspace
    "iiwa_torch.workspace:frame_point": Entry(
        workspace.frame_point,
        lambda: {"chain": CHAIN, "frame": 6, "trials": 4},
        bad=(("frame", -1), ("frame", 9), ("frame", 2.0)) + _counts("trials") + _tols("tol"),
    ),
    "iiwa_torch.workspace:sample_points": Entry(
        workspace.sample_points,
        lambda: {"chain": CHAIN, "n": 8},
        bad=_counts("n") + _GENERATORS
        + (("point", [0.0, math.nan, 0.0]), ("point", [0.0, 1.0]), ("dtype", torch.float16)),
    ),
    "iiwa_torch.workspace:occupancy": Entry(
        workspace.occupancy,
        lambda: {"chain": CHAIN, "n_samples": 256, "h": 0.2},
        bad=_counts("n_samples", "block") + _tols("h") + _GENERATORS
        + (("section", "xz"), ("point", [math.inf, 0.0, 0.0]), ("counts", 5), ("counts", np.zeros((3, 3)))),
    ),
    "iiwa_torch.workspace:volume": Entry(
        workspace.volume,
        lambda: {"chain": CHAIN, "h": 0.2, "n_start": 256, "max_samples": 1024, "tol": 0.5},
        bad=_counts("n_start", "max_samples") + _tols("h", "tol") + (("section", "xz"), ("h", 1e-320), ("h", 1e-9)),
    ),
    "iiwa_torch.workspace:extent": Entry(
        workspace.extent,
        lambda: {"chain": CHAIN, "n_samples": 64},
        bad=_counts("n_samples", "block") + (("point", "origin"),),
    ),
    "iiwa_torch.workspace:envelopes": Entry(
        workspace.envelopes,
        lambda: {"occ": workspace.occupancy(CHAIN, 256, 0.2, section="rz")},
        bad=(("occ", None), ("axis_gap", -1), ("axis_gap", 1.5)),
    ),
    "iiwa_torch.workspace:dexterity": Entry(workspace.dexterity, lambda: {"chain": CHAIN, "q": Q}, tensors=("q",)),
    "iiwa_torch.workspace:dexterity_map": Entry(
        workspace.dexterity_map,
        lambda: {"chain": CHAIN, "n_samples": 64, "h": 0.2},
        bad=_counts("n_samples", "block") + _tols("h") + _GENERATORS,
    ),
    # ------------------------------------------------------------------ environments
    "envs:make_task": Entry(
        envs.make_task,
        lambda: {"env_id": "IiwaReach-v0"},
        bad=(("env_id", "IiwaReach-v9"), ("env_id", 3)),
    ),
    "envs:registered_options": Entry(
        envs.registered_options,
        lambda: {"env_id": "IiwaReachObstacles-v0"},
        bad=(("env_id", "IiwaReach-v9"), ("env_id", 3)),
    ),
    "envs.core:ReachTask": Entry(ReachTask, lambda: {}, bad=_TASK_OPTIONS + _DEVICES),
    "envs.reach:IiwaReachEnv": Entry(IiwaReachEnv, lambda: {}, bad=_TASK_OPTIONS + (("render_mode", "video"),)),
    "IiwaReachEnv.step": Entry(
        _env_step(IiwaReachEnv, None),
        lambda: {"action": np.zeros(7, dtype=np.float32)},
        bad=(
            ("action", np.zeros(6, dtype=np.float32)),
            ("action", np.full(7, np.nan, dtype=np.float32)),
            ("action", np.full(7, 1e39)),
            ("action", "forward"),
        ),
    ),
    "IiwaReachEnv.reset": Entry(
        _env_reset(IiwaReachEnv, None), lambda: {"seed": 3}, bad=(("seed", -1), ("seed", 2**64), ("seed", 1.5))
    ),
    "IiwaReachEnv.compute_reward": Entry(
        _compute_reward,
        lambda: {"achieved_goal": np.zeros((2, 3)), "desired_goal": np.ones((2, 3))},
        bad=(
            ("achieved_goal", np.zeros((2, 4))),
            ("desired_goal", np.zeros((3, 3))),
            ("achieved_goal", np.full((2, 3), np.nan)),
            ("desired_goal", "goal"),
        ),
    ),
    "envs.reach:IiwaReachVectorEnv": Entry(
        IiwaReachVectorEnv,
        lambda: {"num_envs": 2},
        bad=_counts("num_envs") + (("max_episode_steps", 0),) + _TASK_OPTIONS[:6] + (("render_mode", "video"),),
    ),
    "IiwaReachVectorEnv.step": Entry(
        _env_step(IiwaReachVectorEnv, 2),
        lambda: {"action": np.zeros((2, 7), dtype=np.float32)},
        bad=(("action", np.zeros((3, 7), dtype=np.float32)), ("action", np.full((2, 7), np.inf, dtype=np.float32))),
    ),
    "IiwaReachVectorEnv.reset": Entry(
        _env_reset(IiwaReachVectorEnv, 2), lambda: {"seed": 3}, bad=(("seed", -1), ("seed", [1, 2, 3]), ("seed", 0.5))
    ),
    "envs.reach:goal_env_spaces": Entry(goal_env_spaces, lambda: {"task": ReachTask()}),
    "envs.sb3:IiwaReachVecEnv": Entry(
        IiwaReachVecEnv,
        lambda: {"num_envs": 2},
        bad=_counts("num_envs") + (("env_id", "CartPole-v1"), ("seed", -1), ("max_episode_steps", 0)),
    ),
    "IiwaReachVecEnv.step": Entry(
        _vec_step,
        lambda: {"action": np.zeros((2, 7), dtype=np.float32)},
        bad=(("action", np.zeros((2, 6), dtype=np.float32)), ("action", np.full((2, 7), np.nan, dtype=np.float32))),
    ),
    "envs.goals:decode_pose_goal": Entry(
        decode_pose_goal, lambda: {"goal": encode_pose_goal(POSE)}, tensors=("goal",), converts_dtype=True,
        bad=(("goal", torch.zeros(9)), ("goal", torch.tensor([0.5, 0, 0.5, 1, 0, 0, 0, 0, 0])),
             ("goal", torch.tensor([0.5, 0, 0.5, 1, 0, 0, 2, 0, 0]))),  # no y column; y along x
    ),  # fmt: skip
    "envs.goals:encode_pose_goal": Entry(encode_pose_goal, lambda: {"pose": POSE}, poses=("pose",)),
}

#: Public names that are not entry points a user feeds data to, with the reason.
EXEMPT = {
    "iiwa_torch:Convention": "an Enum of choice strings (checked where taken)",
    "iiwa_torch:JointKind": "an Enum of choice strings (checked where taken)",
    "iiwa_torch:collision": "a module",
    "iiwa_torch:robots": "a module",
    "iiwa_torch:so3": "a module",
    "iiwa_torch.so3:RIGID_TOL": "a constant",
    "iiwa_torch.robots:PRESETS": "a constant",
    "iiwa_torch.robots:IIWA_HOME": "a constant",
    "iiwa_torch.robots:puma560": "no arguments",
    "iiwa_torch.robots:lrmate200ic": "no arguments",
    "iiwa_torch.ik:IKResult": "a result type",
    "iiwa_torch.ik.analytic:ClosedForm": "an Enum of the closed forms (a result's field)",
    "iiwa_torch.ik.analytic:Structure": "a result type",
    "iiwa_torch.ik.analytic:AnalyticSolutions": "a result type",
    "iiwa_torch.trajectory:JointTrajectory": "a result type",
    "iiwa_torch.trajectory:TrackResult": "a result type",
    "iiwa_torch.trajectory:Method": "a Literal of choice strings (checked where taken)",
    "iiwa_torch.trajectory:Profile": "a Literal of choice strings (checked where taken)",
    "envs.core:CollisionKind": "a Literal of choice strings (checked where taken)",
    "iiwa_torch.collision:Capsules": "a model type, built by robot_capsules",
    "iiwa_torch.collision:Clearances": "a result type",
    "iiwa_torch.collision:CLEARANCE_NUMPY_BATCH": "a constant",
    "iiwa_torch.collision:MAX_EXTENT": "a constant",
    "iiwa_torch.collision:clearance_of_one": "documented unchecked kernel of one configuration (the single env's "
    "step); clearance is the checked entry and runs the same functions",
    "iiwa_torch.collision:capsule_clearance_of_one": "documented unchecked kernel of one configuration (the single "
    "env's clearance rows); capsule_clearance is the checked entry and runs it",
    "iiwa_torch.collision:obstacle_clearance_of_one": "documented unchecked kernel of one configuration (the "
    "single env's obstacle draws); pairwise_clearance is the checked entry",
    "iiwa_torch.collision:own_clearance_of_one": "documented unchecked kernel of one configuration (the single "
    "env's collision flag); clearance is the checked entry",
    "iiwa_torch.collision:solids_numpy": "converts an already validated World",
    "iiwa_torch.workspace:Section": "an Enum of choice strings (checked where taken)",
    "iiwa_torch.workspace:Occupancy": "a result type",
    "iiwa_torch.workspace:Volume": "a result type",
    "iiwa_torch.workspace:Extent": "a result type",
    "iiwa_torch.workspace:Dexterity": "a result type",
    "iiwa_torch.workspace:DexterityMap": "a result type",
    "iiwa_torch.workspace:DATASHEET": "a constant",
    "iiwa_torch.workspace:plot_workspace": "occupancy and dexterity_map with a file path (its own: test_workspace)",
    "DHChain.frames_batch_last": "documented unchecked batch-last kernel (docs/kinematics.md)",
    "DHChain.tool_frame_batch_last": "documented unchecked batch-last kernel (docs/kinematics.md)",
    "DHChain.position_batch_last": "documented unchecked batch-last kernel (docs/kinematics.md)",
    "DHChain.geometry": "the kernels' constants for a dtype (checked: float32/float64)",
    "envs:ENV_IDS": "a constant",
    "envs:MAX_EPISODE_STEPS": "a constant",
    "envs:PANDA_HOME": "a constant",
    "envs:register_envs": "no arguments",
    "envs.core:StartKind": "an Enum of choice strings (checked where taken)",
    "envs.core:ReachState": "the batched state, built by ReachTask",
    "envs.core:StepResult": "a result type",
    "envs.goals:GoalKind": "an Enum of choice strings (checked where taken)",
    "envs.goals:RewardKind": "an Enum of choice strings (checked where taken)",
    "envs.goals:GoalRegion": "an Enum of choice strings (checked where taken)",
    "envs.goals:PANDA_GYM_BOX": "a constant",
    "envs.goals:ReachGoals": "built by ReachTask from its checked options",
    "envs.goals:enum_option": "the choice check itself",
}

MODULES = (
    "iiwa_torch",
    "iiwa_torch.so3",
    "iiwa_torch.robots",
    "iiwa_torch.ik",
    "iiwa_torch.ik.analytic",
    "iiwa_torch.trajectory",
    "iiwa_torch.collision",
    "iiwa_torch.capsule_fit",
    "iiwa_torch.workspace",
    "envs",
    "envs.core",
    "envs.goals",
    "envs.reach",
    "envs.sb3",
)


def _public_names() -> set[str]:
    names = set()
    for module in MODULES:
        mod = importlib.import_module(module)
        names |= {f"{module}:{n}" for n in mod.__all__}
    module_methods = set(dir(torch.nn.Module))
    names |= {f"DHChain.{n}" for n in dir(DHChain) if not n.startswith("_") and n not in module_methods}
    names -= {"DHChain.n_joints"}  # a property
    return names


def test_every_public_entry_point_is_walked():
    public = _public_names()
    missing = sorted(n for n in public if n not in ENTRIES and n not in EXEMPT)
    assert not missing, f"public names without a bad-input entry (add one to ENTRIES or a reason to EXEMPT): {missing}"
    listed = ENTRIES.keys() | EXEMPT.keys()
    stale = sorted(n for n in listed if (":" in n or n.startswith("DHChain.")) and n not in public)
    assert not stale, f"entries for names that are not public: {stale}"


def _bad_tensors(good: torch.Tensor) -> dict[str, object]:
    """Bad versions of a valid float tensor argument."""
    nan, inf = good.clone(), good.clone()
    nan.view(-1)[-1] = math.nan
    inf.view(-1)[0] = -math.inf
    return {
        "wrong shape": torch.cat([good, good], -1),  # broadcasts with nothing of the good shape
        "int64": good.round().long(),
        "float16": good.half(),
        "bfloat16": good.bfloat16(),
        "NaN": nan,
        "inf": inf,
        "meta": good.to("meta"),
    }


def _non_rigid(good: torch.Tensor) -> dict[str, torch.Tensor]:
    scaled, bottom, mirror = good.clone(), good.clone(), good.clone()
    scaled[..., :3, :3] *= 2
    bottom[..., 3, 0] = 0.5
    mirror[..., :3, 2] *= -1
    return {"scaled rotation": scaled, "bottom row": bottom, "reflection": mirror, **_bad_tensors(good)}


def _cases():
    for key, entry in ENTRIES.items():
        good = entry.good()
        skip = ("int64", "float16", "bfloat16") if entry.converts_dtype else ()
        for arg in entry.tensors + entry.poses:
            variants = _non_rigid(good[arg]) if arg in entry.poses else _bad_tensors(good[arg])
            for label, value in variants.items():
                if label not in skip:
                    yield pytest.param(key, arg, value, id=f"{key}-{arg}-{label}")
        wrong_types = (("chain", "iiwa14"),) if isinstance(good.get("chain"), DHChain) else ()
        try:
            params = inspect.signature(entry.call).parameters
        except (TypeError, ValueError):
            params = {}
        if "world" in params and key != "iiwa_torch.collision:World":
            wrong_types += (("world", 0.0),)
        if "margin" in params:
            wrong_types += (("margin", -1.0), ("margin", math.nan))
        for arg, value in entry.bad + wrong_types:
            shown = re.sub(r" at 0x[0-9a-fA-F]+", "", repr(value))  # ids equal in every xdist worker
            yield pytest.param(key, arg, value, id=f"{key}-{arg}={shown:.30}")


@pytest.mark.parametrize(("key", "arg", "value"), list(_cases()))
def test_bad_input_raises_naming_the_argument(key, arg, value):
    entry = ENTRIES[key]
    name = dict(entry.names).get(arg, arg)
    with pytest.raises((ValueError, TypeError)) as info:
        entry.call(**{**entry.good(), arg: value})
    message = str(info.value)
    assert re.search(rf"(?<![\w.]){re.escape(name)}(?!\w)", message), f"{name!r} not named in: {message}"
    # a raw torch/numpy error is not a message for a user
    assert not re.search(r"Expected all tensors|not implemented for|mat1 and mat2|size of tensor a", message), message


def _finite(value) -> bool:
    if isinstance(value, torch.Tensor):
        return value.dtype == torch.bool or not value.is_floating_point() or bool(torch.isfinite(value).all())
    if isinstance(value, np.ndarray):
        return value.dtype.kind not in "fc" or bool(np.isfinite(value).all())
    if is_dataclass(value) and not inspect.isclass(value):
        return all(_finite(getattr(value, f.name)) for f in fields(value))
    if isinstance(value, (tuple, list)):
        return all(_finite(v) for v in value)
    return True


@pytest.mark.parametrize("key", list(ENTRIES))
def test_good_input_runs_and_is_finite(key):
    entry = ENTRIES[key]
    assert _finite(entry.call(**entry.good()))


@pytest.mark.parametrize(
    ("fn", "arg"),
    [(so3.log, ROT), (so3.exp, Q[:, :3]), (CHAIN.fk, Q), (lambda p: collision.segment_distance(p, p, p, p), Q[:, :3])],
)
def test_vmap_gets_a_clear_error(fn, arg):
    with pytest.raises(TypeError, match=r"batched by torch.func.vmap.*leading dimensions"):
        torch.func.vmap(fn)(arg)


@pytest.mark.parametrize("value", ["no", "True", None, 0, 1, 1.0, np.array(True), torch.tensor(True)])
def test_check_bool_refuses_what_only_has_a_truthiness(value):
    from iiwa_torch.checks import check_bool

    check_bool(True, "flag")
    check_bool(np.False_, "flag")
    with pytest.raises(TypeError, match="flag must be True or False"):
        check_bool(value, "flag")


@pytest.mark.parametrize("shape", [(), (7,), (1, 7), (2, 1, 3), (8, 8), (65,)])
def test_all_finite_finds_every_non_finite_element(shape):
    """checks.all_finite, which every input check reads, against numpy's isfinite: one NaN or inf
    at each position of tensors and arrays of every rank (small ones are read in Python)."""
    from iiwa_torch.checks import all_finite

    n = math.prod(shape)
    for index in range(n):
        for bad in (math.nan, math.inf, -math.inf):
            x = np.arange(n, dtype=np.float64)
            x[index] = bad
            x = x.reshape(shape)
            assert all_finite(x) is bool(np.isfinite(x).all()) is False
            assert all_finite(torch.from_numpy(x)) is False
    clean = np.ones(shape)
    assert all_finite(clean) and all_finite(torch.from_numpy(clean)) and all_finite(torch.from_numpy(clean).float())


@pytest.mark.parametrize("n", [3, 40])  # the NumPy path (up to 32 configurations) and the torch one
def test_a_world_batch_that_does_not_fit_q_is_named(n):
    world = collision.World(spheres=(torch.zeros(n, 1, 3, dtype=torch.float64), torch.ones(n, 1, dtype=torch.float64)))
    q = CHAIN.random_q(n + 10, generator=torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match=rf"world's batch shape \({n},\) does not broadcast with q's \({n + 10},\)"):
        collision.clearance(CHAIN, q, world)
    assert collision.clearance(CHAIN, q[:n], world).shape == (n,)  # one world per configuration fits


def test_batches_that_do_not_broadcast_are_named():
    two, three = CHAIN.fk(Q[:2]), CHAIN.fk(Q[:3])
    cases = [
        (lambda: trajectory.ctraj(two, three, 5), r"T0, T1 must broadcast together, got T0 \(2, 4, 4\), T1 \(3,"),
        (lambda: so3.pose_error(two, three), r"pose, target must broadcast together"),
        (lambda: trajectory.jtraj(Q, Q.flip(0), torch.linspace(0, 1, 20, dtype=torch.float64).reshape(4, 5)),
         r"the batch of t \(\.\.\., T\), of q0 \(\.\.\., n\) must broadcast together, got .* \(4,\), .* \(3,\)"),
        (lambda: dls_step(torch.ones(5, 6, 7, dtype=torch.float64), torch.ones(3, 6, dtype=torch.float64), 1e-3),
         r"jacobian's batch, error's, damping's must broadcast together, got jacobian's batch \(5,\), error's \(3,\)"),
    ]
    for call, message in cases:
        with pytest.raises(ValueError, match=message):
            call()


def test_wrong_types_and_rotation_messages():
    with pytest.raises(TypeError, match=r"q0 must be a torch.Tensor of shape \(\.\.\., 7\), got list"):
        trajectory.shortest_duration(CHAIN, [0.0] * 7, Q[0])
    with pytest.raises(TypeError, match="chain must be a Chain, got str"):
        urdf.to_urdf("iiwa14")
    with pytest.raises(ValueError, match=r"rot must be a rotation \(orthonormal with det \+1, within 1e-06\); rot has"):
        so3.log(2 * torch.eye(3, dtype=torch.float64))


def test_numpy_scalars_are_numbers():
    """Counts and sizes of any numeric type give what the Python numbers give; bools stay refused."""
    seed = lambda: torch.Generator().manual_seed(3)  # noqa: E731
    assert torch.equal(workspace.sample_points(CHAIN, np.int64(8), generator=seed()),
                       workspace.sample_points(CHAIN, 8, generator=seed()))
    occ = workspace.occupancy(CHAIN, np.int32(256), np.float64(0.2), generator=seed())
    assert np.array_equal(occ.counts, workspace.occupancy(CHAIN, 256, 0.2, generator=seed()).counts)
    q0, q1 = Q[0], Q[1]
    assert torch.equal(trajectory.jtraj(q0, q1, np.int64(6)).q, trajectory.jtraj(q0, q1, 6).q)  # a count, not times
    assert collision.World(floor=np.float32(0.5)).floor == 0.5
    assert ReachTask(floor=np.float64(0.1), obstacles=np.int64(0), max_episode_steps=np.int16(9)).max_episode_steps == 9
    assert IiwaReachVecEnv(np.int64(2), "IiwaReach-v0").num_envs == 2
    assert torch.equal(CHAIN.random_q(np.int64(3), generator=seed()), CHAIN.random_q(3, generator=seed()))
    for value in (True, np.bool_(True)):
        with pytest.raises(ValueError, match="n must be a positive integer"):
            workspace.sample_points(CHAIN, value)


def test_a_trajectory_too_large_for_memory_is_refused_with_its_size(monkeypatch):
    from iiwa_torch import checks

    monkeypatch.setattr(checks, "available_memory", lambda: 10**9)
    q0, q1 = Q[0], Q[1]
    with pytest.raises(ValueError, match="jtraj with 10000000 steps needs about") as info:
        trajectory.jtraj(q0, q1, 10**7)
    needed = float(re.search(r"about ([\d.]+) GB", str(info.value)).group(1))
    assert needed >= 3 * 10**7 * 7 * 8 / 1e9  # at least q, qd and qdd in float64
    assert "1 GB available" in str(info.value)
    assert trajectory.jtraj(q0, q1, 1000).q.shape == (1000, 7)  # small ones still run


def test_available_memory_is_what_the_kernel_reports():
    from iiwa_torch.checks import available_memory

    text = open("/proc/meminfo").read()
    total = int(re.search(r"MemTotal:\s+(\d+) kB", text).group(1)) * 1024
    assert 0 < available_memory() <= total
