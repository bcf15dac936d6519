"""Every public entry point that takes a pose rejects a non-rigid one (so3.check_rigid)."""

import pytest
import torch

from iiwa_torch import robots, so3, trajectory
from iiwa_torch.ik import analytic, minimize, solve


def _bad(kind: str, pose: torch.Tensor) -> torch.Tensor:
    """``pose (4, 4)`` made non-rigid in one way."""
    bad = pose.clone()
    if kind == "zero rotation":
        bad[:3, :3] = 0.0
    elif kind == "scaled by 2":
        bad[:3, :3] *= 2.0
    elif kind == "sheared":
        bad[:3, 1] += 0.1 * bad[:3, 0]
    elif kind == "reflection":
        bad[:3, 2] *= -1.0  # orthonormal, det -1
    elif kind == "bottom row":
        bad[3, 0] = 0.5
    elif kind == "slightly off":
        bad[:3, :3] *= 1 + 1e-5  # 2e-5 off in R^T R: beyond RIGID_TOL[float64] = 1e-6
    else:
        bad[1, 1] = float("nan")
    return bad


KINDS = ["zero rotation", "scaled by 2", "sheared", "reflection", "bottom row", "slightly off", "nan"]


def _iiwa_poses():
    chain = robots.iiwa14()
    q = chain.random_q(4, generator=torch.Generator().manual_seed(3))
    return chain, q, chain.fk(q)


ENTRY_POINTS = {
    "ik.solve": lambda chain, q, T: solve(chain, T, iterations=2),
    "ik.minimize": lambda chain, q, T: minimize(chain, lambda q, p: q.sum(-1), q, target=T, steps=1),
    "analytic.iiwa": lambda chain, q, T: analytic.iiwa(chain, T, 0.0),
    "analytic.iiwa_q3_locked": lambda chain, q, T: analytic.iiwa_q3_locked(chain, T),
    "analytic.iiwa_solve": lambda chain, q, T: analytic.iiwa_solve(chain, T),
    "analytic.pieper": lambda chain, q, T: analytic.pieper(robots.puma560(), T),
    "trajectory.ctraj T0": lambda chain, q, T: trajectory.ctraj(T, T[:1].expand(4, 4, 4), 5),
    "trajectory.ctraj T1": lambda chain, q, T: trajectory.ctraj(T[:1].expand(4, 4, 4), T, 5),
    "trajectory.track": lambda chain, q, T: trajectory.track(chain, T[None], q[0]),
}


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("entry", list(ENTRY_POINTS))
def test_non_rigid_pose_is_rejected(entry, kind):
    chain, q, T = _iiwa_poses()
    T = T.clone()
    T[2] = _bad(kind, T[2])  # one bad pose in a batch of good ones
    match = "NaN" if kind == "nan" else r"rigid transforms.*\[\(.*2,?\)\]"
    with pytest.raises(ValueError, match=match):
        ENTRY_POINTS[entry](chain, q, T)


@pytest.mark.parametrize("entry", list(ENTRY_POINTS))
def test_rigid_poses_pass(entry):
    chain, q, T = _iiwa_poses()
    ENTRY_POINTS[entry](chain, q, T)


def test_check_rigid_tolerance_per_dtype():
    chain = robots.iiwa14()
    q = chain.random_q(1000, generator=torch.Generator().manual_seed(4), dtype=torch.float32)
    so3.check_rigid(robots.iiwa14().to(torch.float32).fk(q), "fk32")  # float32 FK rounding passes
    T = chain.fk(q.double())
    so3.check_rigid(T * torch.tensor([1 + 4e-7, 1, 1, 1], dtype=torch.float64))  # column 0 scaled: 8e-7 < 1e-6
    with pytest.raises(ValueError, match=r"within 1e-06"):
        so3.check_rigid(T * torch.tensor([1 + 1e-6, 1, 1, 1], dtype=torch.float64))  # 2e-6
    with pytest.raises(TypeError):
        so3.check_rigid(T.numpy())
    so3.check_rigid(torch.empty(0, 4, 4))


@pytest.mark.parametrize("count", [1, 4, 300])  # one pose in Python floats, a few in numpy, > 256 in torch
@pytest.mark.parametrize("kind", KINDS)
def test_check_rigid_at_every_batch_size(kind, count):
    chain = robots.iiwa14()
    T = chain.fk(chain.random_q(count, generator=torch.Generator().manual_seed(5)))
    so3.check_rigid(T)
    so3.check_rigid(T * torch.tensor([1 + 4e-7, 1, 1, 1], dtype=torch.float64))  # 8e-7 < 1e-6
    with pytest.raises(ValueError, match=r"within 1e-06"):
        so3.check_rigid(T * torch.tensor([1 + 1e-6, 1, 1, 1], dtype=torch.float64))  # 2e-6
    T[count // 2] = _bad(kind, T[count // 2])
    with pytest.raises(ValueError, match="NaN" if kind == "nan" else "rigid"):
        so3.check_rigid(T)


@pytest.mark.parametrize("entry", [(0, 3), (2, 3), (3, 0), (3, 3)])
@pytest.mark.parametrize("value", [float("nan"), float("inf")])
@pytest.mark.parametrize("batch", [1, 5])
def test_non_finite_translation_or_bottom_row_is_named(entry, value, batch):
    """The fast check of small CPU batches reads every entry, not only the rotation's."""
    pose = torch.eye(4, dtype=torch.float64).repeat(batch, 1, 1)
    pose[-1][entry] = value
    with pytest.raises(ValueError, match="NaN or inf"):
        so3.check_rigid(pose, "target")
    with pytest.raises(ValueError, match="NaN or inf"):
        so3.check_rigid(pose[-1], "target")
