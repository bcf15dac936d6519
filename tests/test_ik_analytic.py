"""Closed-form IK: FK closure of every branch, round trips, branch counts, peers, gradients."""

from __future__ import annotations

import math

import pytest
import torch

from iiwa_torch import robots
from iiwa_torch.dh import DHChain
from iiwa_torch.ik import analytic
from iiwa_torch.so3 import exp, pose_error

N_POSES = 10_000
TOL = 1e-9


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _wrap(angle: torch.Tensor) -> torch.Tensor:
    return torch.remainder(angle + math.pi, 2 * math.pi) - math.pi


def _closure(chain: DHChain, q: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Position and rotation error norms of ``fk(q) (..., B, n)`` against ``target (..., 4, 4)``."""
    pos, rot = pose_error(chain.fk(q), target[..., None, :, :])
    return pos.norm(dim=-1), rot.norm(dim=-1)


def _contains(q_branches: torch.Tensor, q: torch.Tensor, tol: float = 1e-7) -> torch.Tensor:
    """``(..., B, n), (..., n) -> (...)``: some branch equals ``q`` modulo 2 pi."""
    return (_wrap(q_branches - q[..., None, :]).abs().amax(-1) < tol).any(-1)


def _distinct(q_branches: torch.Tensor, tol: float = 1e-6) -> torch.Tensor:
    """``(..., B, n) -> (...)``: all B branches differ pairwise (modulo 2 pi)."""
    diff = _wrap(q_branches[..., :, None, :] - q_branches[..., None, :, :]).abs().amax(-1)  # (..., B, B)
    eye = torch.eye(q_branches.shape[-2], dtype=torch.bool)
    return ((diff > tol) | eye).all(-1).all(-1)


def _random_poses(n: int, gen: torch.Generator, centre, radius: float) -> torch.Tensor:
    """Random rotations and positions in a ball: ``(n, 4, 4)``, float64."""
    pose = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    pose[:, :3, :3] = exp(math.pi * (2 * torch.rand(n, 3, generator=gen, dtype=torch.float64) - 1))
    offset = 2 * torch.rand(n, 3, generator=gen, dtype=torch.float64) - 1
    pose[:, :3, 3] = torch.as_tensor(centre, dtype=torch.float64) + radius * offset
    return pose


def _tool() -> torch.Tensor:
    tool = torch.eye(4, dtype=torch.float64)
    tool[:3, :3] = exp(torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64))
    tool[:3, 3] = torch.tensor([0.02, -0.01, 0.1])
    return tool


def _with(chain: DHChain, base=None, tool=None, table=None) -> DHChain:
    return DHChain(
        chain.dh if table is None else table,
        limits=chain.limits,
        base=base if base is not None else chain.base,
        tool=tool if tool is not None else chain.tool,
        name=chain.name,
    )


# ---------------------------------------------------------------- planar 3R
class TestPlanar:
    def _solve(self, chain, target):
        phi = torch.atan2(target[..., 1, 0], target[..., 0, 0])
        return analytic.planar3r(chain, target[..., 0, 3], target[..., 1, 3], phi)

    @pytest.mark.parametrize("chain", [robots.planar3r(), robots.planar3r(0.7, 0.4, 0.2)])
    def test_closure_and_round_trip(self, chain):
        q = chain.random_q(N_POSES, generator=_gen(0))
        target = chain.fk(q)
        sol = self._solve(chain, target)
        assert sol.q.shape == (N_POSES, 2, 3)
        assert sol.reachable.all() and _contains(sol.q, q).all() and _distinct(sol.q).all()
        pos, rot = _closure(chain, sol.q, target)
        assert pos.max() < TOL and rot.max() < TOL

    def test_textbook_values(self):
        # L1 = L2 = 1, L3 = 0.5: wrist at (1, 1) means elbow angles +-90 deg (c2 = 0), heading 90 deg.
        chain = robots.planar3r()
        sol = analytic.planar3r(chain, 1.0, 1.5, math.pi / 2)
        half = math.pi / 2
        expected = torch.tensor([[0.0, half, 0.0], [half, -half, half]], dtype=torch.float64)
        torch.testing.assert_close(sol.q, expected, atol=1e-12, rtol=0)

    def test_base_tool_and_offsets(self):
        base = torch.eye(4, dtype=torch.float64)
        base[:2, :2] = torch.tensor([[0.0, -1.0], [1.0, 0.0]])
        base[:3, 3] = torch.tensor([0.3, -0.2, 0.1])
        tool = torch.eye(4, dtype=torch.float64)
        tool[:2, :2] = torch.tensor([[math.cos(0.4), -math.sin(0.4)], [math.sin(0.4), math.cos(0.4)]])
        tool[:3, 3] = torch.tensor([0.1, 0.05, 0.0])
        table = torch.tensor([[1.0, 0, 0.1, 0.2], [0.8, 0, 0, -0.3], [0.3, 0, 0, 0.1]], dtype=torch.float64)
        chain = DHChain(table, base=base, tool=tool)
        q = chain.random_q(500, generator=_gen(1))
        target = chain.fk(q)
        sol = self._solve(chain, target)
        assert _contains(sol.q, q).all()
        pos, rot = _closure(chain, sol.q, target)
        assert pos.max() < TOL and rot.max() < TOL

    def test_out_of_reach_is_invalid_and_finite(self):
        sol = analytic.planar3r(robots.planar3r(), torch.tensor([5.0, 0.0]), torch.tensor([0.0, 0.0]), 0.0)
        assert sol.reachable.tolist() == [[False, False], [True, True]]
        assert torch.isfinite(sol.q).all()

    def test_rejects_other_arms(self):
        with pytest.raises(ValueError, match="planar 3R"):
            analytic.planar3r(robots.puma560(), 1.0, 0.0, 0.0)


# ---------------------------------------------------------------- 6R spherical wrist
PIEPER_ARMS = [robots.puma560, robots.lrmate200ic]


class TestPieper:
    @pytest.mark.parametrize("make", PIEPER_ARMS)
    def test_closure_and_round_trip(self, make):
        chain = make()
        q = chain.random_q(N_POSES, generator=_gen(2))
        target = chain.fk(q)
        sol = analytic.pieper(chain, target)
        assert sol.q.shape == (N_POSES, 8, 6)
        assert _contains(sol.q, q).all()
        pos, rot = _closure(chain, sol.q, target)
        pos, rot = pos[sol.reachable], rot[sol.reachable]
        assert pos.max() < TOL and rot.max() < TOL
        assert (sol.valid == (sol.reachable & chain.within_limits(sol.q))).all()

    def test_closure_on_random_poses_with_base_and_tool(self):
        base = torch.eye(4, dtype=torch.float64)
        base[:3, :3] = exp(torch.tensor([0.1, 0.2, -0.3], dtype=torch.float64))
        base[:3, 3] = torch.tensor([0.5, -0.1, 0.2])
        chain = _with(robots.lrmate200ic(), base=base, tool=_tool())
        target = _random_poses(N_POSES, _gen(3), base[:3, 3] + torch.tensor([0.0, 0.0, 0.35]), 0.6)
        sol = analytic.pieper(chain, target)
        assert 0.2 < sol.reachable.float().mean() < 0.95  # the ball holds both kinds of target
        pos, rot = _closure(chain, sol.q, target)
        assert pos[sol.reachable].max() < TOL and rot[sol.reachable].max() < TOL
        assert torch.isfinite(sol.q).all()

    def test_puma_has_eight_distinct_branches(self):
        chain = robots.puma560()
        q = chain.random_q(2000, generator=_gen(4))
        sol = analytic.pieper(chain, chain.fk(q))
        assert sol.reachable.all() and _distinct(sol.q).all()

    def test_lrmate_branch_count_follows_geometry(self):
        # With the shoulder offset a1, joint 2 sits a1 in front of the waist axis: the 4 branches
        # with the wrist centre in front (behind) exist iff its distance to joint 2 lies in
        # [|a2 - L3|, a2 + L3], L3 the forearm.
        chain = robots.lrmate200ic()
        q = chain.random_q(2000, generator=_gen(5))
        sol = analytic.pieper(chain, chain.fk(q))
        wrist = chain.fk_all(q)[:, 5, :3, 3]
        r = wrist[:, :2].norm(dim=-1)
        a1, d1, a2, a3, d4 = 0.075, 0.330, 0.300, 0.075, 0.320
        lo, hi = abs(a2 - math.hypot(a3, d4)), a2 + math.hypot(a3, d4)
        for side, offset in ((slice(0, 4), -a1), (slice(4, 8), a1)):
            dist = torch.hypot(r + offset, wrist[:, 2] - d1)
            ok = (dist >= lo) & (dist <= hi)
            assert (sol.reachable[:, side] == ok[:, None]).all()
        both = sol.reachable.all(-1)
        assert both.float().mean() > 0.5 and _distinct(sol.q[both]).all()

    def test_home_pose_of_the_lrmate(self):
        # robots.md: all joints 0 -> flange at (0.475, 0, 0.705).
        chain = robots.lrmate200ic()
        target = torch.eye(4, dtype=torch.float64)
        target[:3, :3] = chain.fk(torch.zeros(6, dtype=torch.float64))[:3, :3]
        target[:3, 3] = torch.tensor([0.475, 0.0, 0.705], dtype=torch.float64)
        sol = analytic.pieper(chain, target)
        assert _contains(sol.q, torch.zeros(6, dtype=torch.float64), tol=1e-9)

    def test_agrees_with_roboticstoolbox_ikine_a(self):
        rtb = pytest.importorskip("roboticstoolbox")
        puma = rtb.models.DH.Puma560()
        table = torch.tensor([[link.a, link.alpha, link.d, link.offset] for link in puma.links], dtype=torch.float64)
        ours = robots.puma560()
        # Same structure as robots.md; rtb's d1 is 0.67183, so build the chain from rtb's table.
        torch.testing.assert_close(table[1:], ours.dh[1:])
        chain = _with(ours, table=table)
        q = chain.random_q(40, generator=_gen(6))
        target = chain.fk(q)
        sol = analytic.pieper(chain, target)
        matched = 0
        for k in range(q.shape[0]):
            for config in ("lun", "luf", "ldn", "ldf", "run", "ruf", "rdn", "rdf"):
                theirs = puma.ikine_a(target[k].numpy(), config=config)
                if not theirs.success:
                    continue
                assert _contains(sol.q[k], torch.as_tensor(theirs.q), tol=1e-8), (k, config)
                matched += 1
        assert matched >= 8 * 40 * 0.9

    def test_out_of_reach_is_invalid_and_finite(self):
        target = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
        target[:, :3, 3] = torch.tensor([[3.0, 0, 0], [0, 0, 0.5], [0.0, 0.0, 0.6718]])
        sol = analytic.pieper(robots.puma560(), target)
        assert not sol.reachable[0].any() and not sol.valid[0].any()
        assert torch.isfinite(sol.q).all()

    def test_rejects_other_arms(self):
        target = torch.eye(4, dtype=torch.float64)
        with pytest.raises(ValueError, match="Pieper"):
            analytic.pieper(robots.iiwa14(), target)
        table = robots.puma560().dh.clone()
        table[1, 1] = 0.1  # shoulder and elbow axes no longer parallel
        with pytest.raises(ValueError, match="row 2 needs alpha = 0"):
            analytic.pieper(_with(robots.puma560(), table=table), target)


# ---------------------------------------------------------------- gradients
def test_gradients_are_finite_and_match_finite_differences():
    chain = robots.puma560()
    q = chain.random_q(3, generator=_gen(7))
    target = chain.fk(q)
    far = target.clone()
    far[0, :3, 3] = torch.tensor([3.0, 0.0, 0.0])  # one unreachable target in the batch
    target = torch.cat([target, far[:1]]).requires_grad_(True)

    sol = analytic.pieper(chain, target)
    (sol.q * sol.valid[..., None]).sum().backward()
    assert torch.isfinite(target.grad).all()

    def first_branch_angles(pose):
        return analytic.pieper(chain, pose).q[..., 0, :]

    torch.autograd.gradcheck(first_branch_angles, (target[:3].detach().clone().requires_grad_(True),))
