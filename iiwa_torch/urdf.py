"""Export a :class:`~iiwa_torch.dh.DHChain` to URDF, so other tools load the same robot.

Links are ``base_link``, ``link1`` ... ``linkN`` (link i carries DH frame i) and
``tool0`` (the end effector). Revolute joint i sits where DH rotates about z:

- standard DH: its origin is the previous link's constant part ``Tz(d) Tx(a) Rx(alpha)``
  (the base transform for joint 1) times ``Rz(offset)``;
- modified DH: its origin is ``Tz(d_prev) Rx(alpha) Tx(a) Rz(offset)``.

A fixed joint ``tool_joint`` carries the last constant part and the tool transform. Links
have no visuals and a token inertia (kinematics only).
"""

from __future__ import annotations

from xml.sax.saxutils import quoteattr

import torch

from .dh import Convention, DHChain
from .kinematics import elementary_transform
from .so3 import matrix_to_rpy

__all__ = ["to_urdf"]


def _origin(matrix: torch.Tensor) -> str:
    xyz = " ".join(f"{v:.12g}" for v in matrix[:3, 3].tolist())
    rpy = " ".join(f"{v:.12g}" for v in matrix_to_rpy(matrix[:3, :3]).tolist())
    return f'<origin xyz="{xyz}" rpy="{rpy}"/>'


def _link(name: str) -> str:
    inertia = '<inertia ixx="1e-4" ixy="0" ixz="0" iyy="1e-4" iyz="0" izz="1e-4"/>'
    return f'  <link name="{name}"><inertial><mass value="0.1"/>{inertia}</inertial></link>'


def to_urdf(chain: DHChain, name: str | None = None) -> str:
    """The chain as a URDF document (a string), joint limits and speeds included."""
    robot = name or chain.name
    dh = chain.dh.detach().cpu().to(torch.float64)
    lower, upper = chain.limits.detach().cpu().tolist()
    speeds = chain.velocity_limits.tolist() if chain.velocity_limits is not None else [10.0] * chain.n_joints
    links = ["base_link"] + [f"link{i + 1}" for i in range(chain.n_joints)] + ["tool0"]
    lines = ['<?xml version="1.0"?>', f"<robot name={quoteattr(robot)}>"]
    lines += [_link(link) for link in links]
    carry = chain.base.detach().cpu().to(torch.float64)  # constant transform waiting to be placed
    for i, ((a, alpha, d, offset), joint) in enumerate(zip(dh.tolist(), chain.joint_names)):
        if chain.convention is Convention.STANDARD:
            origin = carry @ elementary_transform("z", offset)
            carry = elementary_transform("z", 0.0, (0.0, 0.0, d)) @ elementary_transform("x", alpha, (a, 0.0, 0.0))
        else:
            origin = carry @ elementary_transform("x", alpha, (a, 0.0, 0.0)) @ elementary_transform("z", offset)
            carry = elementary_transform("z", 0.0, (0.0, 0.0, d))
        lines.append(
            f'  <joint name={quoteattr(joint)} type="revolute">'
            f'<parent link="{links[i]}"/><child link="{links[i + 1]}"/>{_origin(origin)}'
            f'<axis xyz="0 0 1"/><limit lower="{lower[i]:.12g}" upper="{upper[i]:.12g}" '
            f'effort="100" velocity="{speeds[i]:.12g}"/></joint>'
        )
    tool = carry @ chain.tool.detach().cpu().to(torch.float64)
    lines.append(
        f'  <joint name="tool_joint" type="fixed"><parent link="{links[-2]}"/>'
        f'<child link="tool0"/>{_origin(tool)}</joint>'
    )
    lines.append("</robot>")
    return "\n".join(lines) + "\n"
