"""Every kinematics backend held to the torch path, for DH presets and URDF chains (every joint
kind): the elementwise and 4x4-product torch kernels, Horner's position, the numpy products,
the Python-float recursion and the compiled (numba) kernels give the same end poses, frames,
joint axes and Jacobians. The torch path itself is held to the DH reference (test_dh.py) and
to pinocchio (test_chain.py)."""

import importlib.util

import numpy as np
import pytest
import torch
from urdf_samples import ODD_URDF

from iiwa_torch import compiled, robots
from iiwa_torch import kinematics as kin

F64 = torch.float64


def _chains():
    chains = {name: robots.PRESETS[name]() for name in ("iiwa14", "puma560", "lrmate200ic")}
    chains["odd"] = robots.from_urdf(ODD_URDF, end_link="tip")  # tilted axes, prismatic, continuous
    if importlib.util.find_spec("pybullet_data"):
        import pybullet_data

        chains["panda"] = robots.from_urdf(f"{pybullet_data.getDataPath()}/franka_panda/panda.urdf",
                                           end_link="panda_hand")
    return chains


CHAINS = _chains()


def _torch_path(chain, q):
    """End poses, link frames and Jacobians by the torch 4x4 products (autograd on, so no shortcut)."""
    g = chain.geometry(q.dtype)
    x = q.clone().requires_grad_()
    with torch.enable_grad():
        return (kin.end_pose_matmul(g, x).detach(), kin.all_poses(g, x).detach(), kin.jacobian(g, x).detach())


def _elementwise(chain, q):
    g = chain.geometry(q.dtype)
    frames, axes = kin.frames_batch_last(g, q.T.contiguous().requires_grad_())
    end = kin.tool_frame_batch_last(g, frames[-1])
    stack = torch.stack([torch.stack(f, 1) for f in frames]).detach()  # (F, 3, 4, b)
    return torch.stack(end, 1).detach().permute(2, 0, 1), stack.permute(3, 0, 1, 2), axes


@pytest.mark.parametrize("name", list(CHAINS))
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_every_backend_gives_the_torch_paths_numbers(name, dtype, monkeypatch):
    chain = CHAINS[name]
    q = chain.random_q(40, generator=torch.Generator().manual_seed(0), dtype=dtype)
    tol = 1e-12 if dtype == F64 else 3e-6
    pose, frames, jac = _torch_path(chain, q)
    g = chain.geometry(dtype)
    # elementwise torch kernel: frames, end pose and joint axes (the Jacobian's columns)
    end, every, axes = _elementwise(chain, q)
    torch.testing.assert_close(end, pose[:, :3], atol=tol, rtol=0)
    torch.testing.assert_close(every, frames[:, :, :3], atol=tol, rtol=0)
    torch.testing.assert_close(kin.jacobian(g, q.repeat(5, 1)), jac.repeat(5, 1, 1), atol=tol, rtol=0)  # > 128
    z = torch.stack([a[0] for a in axes]).detach().permute(2, 1, 0)  # (b, 3, n)
    slides = g.prismatic[:, 0]  # a prismatic joint's axis is its linear column, a revolute one's its angular
    torch.testing.assert_close(z, torch.where(slides, jac[:, :3], jac[:, 3:]), atol=tol, rtol=0)
    # Horner's position
    torch.testing.assert_close(kin.position_horner(g, q.T.contiguous()).T, pose[:, :3, 3], atol=tol, rtol=0)
    # numpy products
    torch.testing.assert_close(torch.from_numpy(kin.end_pose_numpy(g, q)), pose, atol=tol, rtol=0)
    torch.testing.assert_close(torch.from_numpy(kin.frames_numpy(g, q.numpy())).transpose(0, 1), frames,
                               atol=tol, rtol=0)
    numpy_pose, numpy_jac = kin.pose_jacobian_numpy(g, q.numpy())
    torch.testing.assert_close(torch.from_numpy(numpy_jac), jac, atol=tol, rtol=0)
    # Python floats, one configuration (the compiled kernels off)
    monkeypatch.setattr(compiled, "ENABLED", False)
    for i in (0, 17):
        torch.testing.assert_close(kin.end_pose_floats(g, q[i]), pose[i], atol=tol, rtol=0)
        torch.testing.assert_close(kin.jacobian_floats(g, q[i]), jac[i], atol=tol, rtol=0)
        rows = [torch.tensor([*x, *y, *z, *p], dtype=F64).reshape(4, 3).T for x, y, z, p in kin.frames_floats(g, q[i])]
        torch.testing.assert_close(torch.stack(rows).to(dtype), frames[i, :, :3], atol=tol, rtol=0)
        torch.testing.assert_close(kin.position_batch_last(g, q[i : i + 1].T)[:, 0], pose[i, :3, 3], atol=tol, rtol=0)


@pytest.mark.skipif(not compiled.ENABLED, reason="numba (the fast extra) is not installed")
@pytest.mark.parametrize("name", list(CHAINS))
def test_the_compiled_kernels_give_the_float_paths_bits(name, monkeypatch):
    """numba restates the Python-float recursion, term for term: the same bits."""
    chain = CHAINS[name]
    g = chain.geometry(F64)
    q = chain.random_q(30, generator=torch.Generator().manual_seed(1))
    kernels = compiled.kernels()
    poses, jacs = kernels.end_poses(*g.float_arrays, q.numpy()), kernels.jacobians(*g.float_arrays, q.numpy())
    monkeypatch.setattr(compiled, "ENABLED", False)
    for i in range(30):
        np.testing.assert_array_equal(poses[i], kin.end_pose_floats(g, q[i]).numpy())
        np.testing.assert_array_equal(jacs[i], kin.jacobian_floats(g, q[i]).numpy())
    assert np.abs(poses - _torch_path(chain, q)[0].numpy()).max() < 1e-12
