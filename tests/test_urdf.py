"""URDF export: pinocchio and pytorch_kinematics load it and reproduce our FK."""

import numpy as np
import pytest
import torch

from iiwa_torch import Chain, DHChain, robots
from iiwa_torch.urdf import to_urdf


def _chains():
    base = robots.iiwa14().fk(torch.full((7,), 0.2, dtype=torch.float64))
    tool = robots.puma560().fk(torch.full((6,), -0.4, dtype=torch.float64))
    yield from (robots.iiwa14(), robots.iiwa7(), robots.puma560(), robots.lrmate200ic(), robots.planar3r())
    yield DHChain(robots.lrmate200ic().dh, convention="modified", base=base, tool=tool, name="mdh")


@pytest.mark.parametrize("chain", list(_chains()), ids=lambda c: c.name)
def test_pinocchio_reproduces_fk(chain):
    pin = pytest.importorskip("pinocchio")
    model = pin.buildModelFromXML(to_urdf(chain))
    data = model.createData()
    frame = model.getFrameId("tool0")
    q = chain.random_q(100, generator=torch.Generator().manual_seed(0))
    got = []
    for qi in q.numpy():
        pin.framesForwardKinematics(model, data, qi)
        got.append(data.oMf[frame].homogeneous.copy())
    # the file's numbers round-trip float64 exactly
    np.testing.assert_allclose(np.stack(got), chain.fk(q).numpy(), atol=1e-12)
    np.testing.assert_array_equal(model.lowerPositionLimit, chain.limits[0].numpy())
    np.testing.assert_array_equal(model.upperPositionLimit, chain.limits[1].numpy())


def test_joint_names_and_speeds_exported():
    text = to_urdf(robots.iiwa14())
    assert text.count('type="revolute"') == 7 and 'name="A7"' in text
    assert 'velocity="1.48352986' in text  # 85 deg/s


def test_names_are_escaped_and_kept_apart_from_the_exporters_own():
    """Link names that need XML escaping, or that are the names the export adds, read back as they were."""
    pytest.importorskip("pytorch_kinematics")
    origins = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
    origins[:, 0, 3] = 0.3
    chain = Chain(origins, [[0, 0, 1], [0, 1, 0], [1, 0, 0]], link_names=["base_link", 'arm & "wrist"', "tool0"],
                  joint_names=["tool_joint", "j<2>", "j3"])
    again = robots.from_urdf(to_urdf(chain))
    assert again.link_names == chain.link_names and again.joint_names == chain.joint_names
    q = chain.random_q(20, generator=torch.Generator().manual_seed(0))
    np.testing.assert_allclose(again.fk(q).numpy(), chain.fk(q).numpy(), atol=1e-15)
