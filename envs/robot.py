"""The robot side of the reaching task: which arm (:func:`resolve_robot`), where it starts
(:func:`default_home`) and how joint-velocity actions move it within its limits (:class:`JointVelocityArm`)."""

from __future__ import annotations

import copy
import functools
import os

import torch

from iiwa_torch import robots
from iiwa_torch.chain import Chain
from iiwa_torch.checks import check_instance, require
from iiwa_torch.collision import Capsules, World, clearance, robot_capsules
from iiwa_torch.dh import DHChain
from iiwa_torch.robots import IIWA_HOME

from .arrays import NUMPY, TORCH, ArrayOps

__all__ = ["URDF_ARMS", "resolve_robot", "default_home", "JointVelocityArm"]

Tensor = torch.Tensor

#: Arms the envs know by name, read from pybullet_data's URDF files (``pip install pybullet``):
#: name -> (file in pybullet_data, default end link). The Panda's end effector is the point
#: between the fingertips panda-gym reaches with (``panda_grasptarget``, 0.105 m past the hand).
URDF_ARMS = {"panda": ("franka_panda/panda.urdf", "panda_grasptarget")}

_IIWA_PRESETS = ("iiwa14", "iiwa7")


def resolve_robot(robot=None, end_link: str | None = None, capsules: Capsules | None = None,
                  checked: bool = True) -> tuple[Chain, Capsules | None]:
    """The envs' ``robot`` option -> its chain and capsule model (``None`` unless ``checked``,
    i.e. collisions are checked).

    ``robot``: ``None`` (``iiwa14()``), a preset name (:data:`iiwa_torch.robots.PRESETS`: its
    preset capsules), a name of :data:`URDF_ARMS`, a URDF file path (capsules fitted to its
    collision meshes, :func:`iiwa_torch.capsule_fit.urdf_capsules`, once per file and end link
    in a process) or a :class:`~iiwa_torch.chain.Chain` (a DH preset's chain has its preset
    capsules; any other needs ``capsules=``). ``end_link``: the URDF's end link (needed when the
    file branches, as the Panda's fingers do). ``capsules``: a model fitted to the chain,
    used as given. ValueError for an unknown name, a missing file, ``end_link`` with a chain or
    a preset, or a chain without capsules to check."""
    if capsules is not None:
        check_instance(capsules, Capsules, "capsules")
        if not checked:
            raise ValueError("capsules are for collision checks: use collision='terminate' or 'penalize', not 'off'")
    source = None
    if robot is None or isinstance(robot, Chain):
        chain = robots.iiwa14() if robot is None else robot
    elif isinstance(robot, (str, os.PathLike)):
        name = os.fspath(robot)
        if name in robots.PRESETS:
            chain = robots.PRESETS[name]()
        else:
            source, default_end = _urdf_file(name)
            end_link = default_end if end_link is None else end_link
            chain = robots.from_urdf(source, end_link=end_link)
    else:
        raise TypeError(f"robot must be a preset name, a URDF path or a Chain, got {type(robot).__name__}")
    if end_link is not None and source is None:
        raise ValueError(f"end_link applies to a URDF robot (a file or one of {sorted(URDF_ARMS)}), "
                         f"got robot={robot!r}")
    if not checked or capsules is not None:
        if capsules is not None and max(capsules.frames) > chain.n_joints:
            raise ValueError(f"capsules index frames up to {max(capsules.frames)}, but robot {chain.name!r} has "
                             f"{chain.n_joints + 1} (fit them to this chain)")
        return chain, capsules
    if source is not None:
        return chain, _fitted_capsules(source, os.stat(source).st_mtime_ns, chain.link_names[-1])
    if isinstance(chain, DHChain) and chain.name in robots.PRESETS:
        return chain, robot_capsules(chain)
    raise ValueError(f"robot {chain.name!r} has no capsule model to check collisions with: pass capsules= (e.g. "
                     "iiwa_torch.capsule_fit.urdf_capsules(chain, urdf_file)) or collision='off'")


def _urdf_file(name: str) -> tuple[str, str | None]:
    """A name of :data:`URDF_ARMS` or a URDF path -> the file's path and its default end link."""
    if name in URDF_ARMS:
        file, end = URDF_ARMS[name]
        data = require("pybullet_data", "franka")
        return os.path.join(data.getDataPath(), file), end
    if not os.path.isfile(name):
        raise ValueError(f"robot must be a preset name {sorted(robots.PRESETS)}, an arm of {sorted(URDF_ARMS)} or "
                         f"a URDF file, got {name!r} (no such file)")
    return os.path.abspath(name), None


@functools.lru_cache(maxsize=16)
def _fitted_capsules(source: str, mtime_ns: int, end_link: str) -> Capsules:
    """:func:`~iiwa_torch.capsule_fit.urdf_capsules` of the chain from ``source``'s root to ``end_link``
    (seconds of fitting: kept per file, its modification time and end link; the model is frozen)."""
    from iiwa_torch.capsule_fit import urdf_capsules

    with torch.inference_mode(False):  # shared: no inference tensors in it, whoever asks first
        return urdf_capsules(robots.from_urdf(source, end_link=end_link), source)


def default_home(chain: Chain, capsules: Capsules | None = None, floor: float | None = None) -> Tensor:
    """The start posture ``(nj,)`` float64 of an arm whose ``home`` is not given: ``IIWA_HOME`` for the
    iiwa presets; else zeros if within the limits and (with ``capsules``) clear of itself and the floor
    at ``floor`` (m), else the middle of the limits (0 for a continuous joint)."""
    if isinstance(chain, DHChain) and chain.name in _IIWA_PRESETS:
        return torch.tensor(IIWA_HOME, dtype=torch.float64)
    zero = torch.zeros(chain.n_joints, dtype=torch.float64, device=chain.limits.device)
    if bool(chain.within_limits(zero)) and (capsules is None or bool(clearance(chain, zero, World(floor=floor),
                                                                               capsules) > 0)):
        return zero
    return chain.geometry(torch.float64).draw_limits.mean(0)


class JointVelocityArm:
    """A chain driven by joint-velocity actions, batch last (joint angles ``(nj, n)``).

    Args:
        chain: any :class:`~iiwa_torch.chain.Chain` with ``velocity_limits``.
        dt: control period, s: an action ``a`` in ``[-1, 1]^nj`` moves joint ``i`` by
            ``a_i * velocity_limits_i * dt``.
        home: start posture ``(nj,)`` rad, within the limits (default :func:`default_home` without
            collision checks).
        dtype, device: of the state; the arm keeps a private copy of the chain in them (so FK
            converts no buffer at each call, and the caller's chain is left alone).
    """

    def __init__(self, chain: Chain, dt: float, home, dtype: torch.dtype, device: torch.device) -> None:
        check_instance(chain, Chain, "robot")
        if chain.velocity_limits is None:
            raise ValueError(
                f"robot {chain.name!r} has no velocity_limits (joint speeds, rad/s), which scale the actions; "
                f"give the chain its own, e.g. chain.velocity_limits = torch.full(({chain.n_joints},), 2.0, "
                "dtype=torch.float64), and pass the chain as robot="
            )
        same = chain.limits.device == device and chain.limits.dtype == dtype
        self.chain = chain if same else copy.deepcopy(chain).to(device=device, dtype=dtype)
        self.n_joints = n = self.chain.n_joints
        if home is None:
            home = default_home(chain)
        home = torch.as_tensor(home, dtype=dtype, device=device)
        if home.shape != (n,) or not torch.isfinite(home).all() or not bool(self.chain.within_limits(home)):
            raise ValueError(f"home must be {n} finite joint angles within the limits of {chain.name!r}, got "
                             f"{home.tolist()} (home=None takes the robot's default; the Franka* ids set the Panda's)")
        self.home = home
        self.lower, self.upper = self.chain.limits.to(dtype)
        # where random configurations are drawn: the limits, one turn for a continuous joint
        self.draw_lower, self.draw_upper = self.chain.geometry(dtype).draw_limits
        self.max_step = (self.chain.velocity_limits * dt).to(dtype)  # (nj,) rad per step at |a| = 1
        # the same as columns (nj, 1), to broadcast along the state's rows
        columns = (self.lower[:, None], self.upper[:, None], self.max_step[:, None])
        self._columns = {TORCH.name: columns}
        if self.lower.device.type == "cpu":  # the same as numpy arrays, for NUMPY
            self._columns[NUMPY.name] = tuple(c.numpy() for c in columns)
        #: bound on any end-effector coordinate, m
        self.position_bound = self.chain.reach_bound()

    def configurations(self, u: Tensor) -> Tensor:
        """Uniform numbers ``(..., nj)`` in ``[0, 1)`` -> joint angles ``(..., nj)`` within the limits
        (a continuous joint within ``[-pi, pi]``)."""
        return self.draw_lower + u * (self.draw_upper - self.draw_lower)

    def integrate(self, q, action, xp: ArrayOps = TORCH):
        """Joint angles and finite actions ``(nj, n)`` -> the new angles (the actions clipped to
        ``[-1, 1]``, the result clamped to the limits) and the motion made over the speed limits.
        Tensors, or numpy arrays with ``xp=NUMPY`` (:mod:`envs.arrays`)."""
        lower, upper, max_step = self._columns[xp.name]
        a = xp.clip(action, -1.0, 1.0)  # not in place: the action may share the caller's memory
        # in place on the new arrays: a third faster at n = 65,536 than new ones per op
        new = xp.clip_(xp.multiply_add(q, a, max_step), lower, upper)
        # this clip only removes float rounding (1e-6)
        return new, xp.clip_(xp.divide_(new - q, max_step), -1.0, 1.0)

    def steps_to_reach_bound(self) -> int:
        """Steps a full-speed straight joint move needs, in the worst case, from ``home`` to any
        configuration drawn within the limits: ``ceil(max_i max(|lo_i - h_i|, |hi_i - h_i|) / (v_i dt))``."""
        span = torch.maximum((self.draw_lower - self.home).abs(), (self.draw_upper - self.home).abs())
        return int(torch.ceil((span / self.max_step).max() - 1e-4))  # 1e-4: float32 rounding of exact ratios
