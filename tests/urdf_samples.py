"""URDF files written for the tests, and how pinocchio (the reference) takes joint values."""

import math

# Every joint kind, axes off the coordinate axes, fixed joints inside and after the path, a branch
# off it: written by hand for this test.
ODD_URDF = """<?xml version="1.0"?>
<robot name="odd">
  <link name="root"/><link name="a"/><link name="b"/><link name="c"/><link name="d"/><link name="e"/>
  <link name="tip"/><link name="side"/>
  <joint name="j1" type="revolute"><parent link="root"/><child link="a"/>
    <origin xyz="0.1 -0.2 0.3" rpy="0.3 -0.2 0.1"/><axis xyz="0.2 -0.4 0.9"/>
    <limit lower="-2" upper="2.5" effort="1" velocity="1.5"/></joint>
  <joint name="f1" type="fixed"><parent link="a"/><child link="b"/><origin xyz="0 0.05 0.1" rpy="1.1 0 0.4"/></joint>
  <joint name="j2" type="prismatic"><parent link="b"/><child link="c"/>
    <origin xyz="0.2 0 0" rpy="0 0.7 0"/><axis xyz="1 1 0"/>
    <limit lower="-0.1" upper="0.3" effort="1" velocity="0.5"/></joint>
  <joint name="j3" type="continuous"><parent link="c"/><child link="d"/>
    <origin xyz="0 0 0.25" rpy="-0.5 0.2 0"/><axis xyz="0 -1 0"/></joint>
  <joint name="j4" type="revolute"><parent link="d"/><child link="e"/>
    <origin xyz="0.15 0.1 0" rpy="0 0 -1.3"/><axis xyz="0 0 -1"/>
    <limit lower="-1" upper="1" effort="1" velocity="2"/></joint>
  <joint name="f2" type="fixed"><parent link="e"/><child link="tip"/>
    <origin xyz="0.05 0.02 0.12" rpy="0.2 0.3 0.4"/></joint>
  <joint name="s" type="revolute"><parent link="b"/><child link="side"/>
    <axis xyz="1 0 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
</robot>
"""


def pinocchio_q(pin, model, slots, values):
    """pinocchio's configuration of ``model`` with ``values`` (rad or m) at its joints ``slots``, the
    others neutral; a continuous joint takes its (cos, sin)."""
    full = pin.neutral(model)
    for slot, value in zip(slots, values):
        if slot.nq == 2:
            full[slot.idx_q : slot.idx_q + 2] = math.cos(value), math.sin(value)
        else:
            full[slot.idx_q] = value
    return full
