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


def _contains(q_branches: torch.Tensor, q: torch.Tensor, tol: float = 1e-7, among=None) -> torch.Tensor:
    """``(..., B, n), (..., n) -> (...)``: some branch (of those ``among``, a ``(..., B)`` mask)
    equals ``q`` modulo 2 pi."""
    hit = _wrap(q_branches - q[..., None, :]).abs().amax(-1) < tol
    return (hit if among is None else hit & among).any(-1)


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
        # q is within limits, so its branch must be valid: wrapped into the limits (PUMA q3 < -pi).
        assert _contains(sol.q, q, among=sol.valid).all()
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


# ---------------------------------------------------------------- iiwa (arm angle)
def _iiwa_chains():
    base = torch.eye(4, dtype=torch.float64)
    base[:3, :3] = exp(torch.tensor([0.0, 0.3, 0.2], dtype=torch.float64))
    base[:3, 3] = torch.tensor([0.1, 0.2, 0.3])
    return {
        "iiwa14": robots.iiwa14(),
        "iiwa7": robots.iiwa7(),
        "paper-flange+tool+base": _with(robots.iiwa14(flange=0.090), base=base, tool=_tool()),
    }


IIWA = _iiwa_chains()


class TestIiwa:
    @pytest.mark.parametrize("name", list(IIWA))
    def test_round_trip_and_closure(self, name):
        chain = IIWA[name]
        q = chain.random_q(N_POSES, generator=_gen(10))
        target = chain.fk(q)
        psi = analytic.iiwa_arm_angle(chain, q)
        sol = analytic.iiwa(chain, target, psi)
        assert sol.q.shape == (N_POSES, 8, 7)
        assert sol.reachable.all() and _contains(sol.q, q, among=sol.valid).all()
        pos, rot = _closure(chain, sol.q, target)
        assert pos.max() < TOL and rot.max() < TOL
        # One arm angle is one elbow position: every branch has the arm angle asked for.
        assert _wrap(analytic.iiwa_arm_angle(chain, sol.q) - psi[:, None]).abs().max() < 1e-8
        assert (sol.valid == chain.within_limits(sol.q)).all()

    def test_eight_distinct_branches_for_several_arm_angles(self):
        chain = IIWA["iiwa14"]
        q = chain.random_q(2000, generator=_gen(11))
        target = chain.fk(q)
        psi = (2 * torch.rand(2000, 4, generator=_gen(12), dtype=torch.float64) - 1) * math.pi
        sol = analytic.iiwa(chain, target, psi)  # (..., K) arm angles: q (2000, 4, 8, 7)
        assert sol.q.shape == (2000, 4, 8, 7)
        assert sol.reachable.all() and _distinct(sol.q).all()
        pos, rot = _closure(chain, sol.q, target[:, None])
        assert pos.max() < TOL and rot.max() < TOL
        # Branch signs: k = 4 shoulder + 2 elbow + wrist, 0 for sin(q) >= 0.
        signs = torch.tensor([[(k >> 2) & 1, (k >> 1) & 1, k & 1] for k in range(8)], dtype=torch.bool)
        assert ((sol.q[..., [1, 3, 5]] < 0) == signs).all()

    def test_reference_plane_is_where_q3_is_zero(self):
        # With q3 = 0 the elbow lies in the vertical plane through shoulder and wrist:
        # arm angle 0 (elbow above the shoulder-wrist line) or pi (below it).
        chain = IIWA["iiwa14"]
        q = chain.random_q(1000, generator=_gen(13))
        q[:, 2] = 0.0
        psi = analytic.iiwa_arm_angle(chain, q)
        assert psi.sin().abs().max() < 1e-9
        frames = chain.fk_all(q)
        s, e, w = frames[:, 1, :3, 3], frames[:, 3, :3, 3], frames[:, 5, :3, 3]
        u = (w - s) / (w - s).norm(dim=-1, keepdim=True)
        off_line = (e - s) - ((e - s) * u).sum(-1, keepdim=True) * u
        up = off_line[:, 2] > 0
        assert ((psi.cos() > 0) == up).all()

    def test_seed_paper_pose(self):
        # robots.md / seed 000 with the paper's 0.090 m flange: q4 = -pi/2, q5 = pi/3 ->
        # p = (0.490, 0, 0.780), R = [[0, 0, 1], [sqrt3/2, 1/2, 0], [-1/2, sqrt3/2, 0]].
        chain = robots.iiwa14(flange=0.090)
        r3 = math.sqrt(3) / 2
        target = torch.tensor(
            [[0, 0, 1, 0.490], [r3, 0.5, 0, 0], [-0.5, r3, 0, 0.780], [0, 0, 0, 1]], dtype=torch.float64
        )
        # q2 = q6 = 0: shoulder and wrist aligned, only q1 + q3 and q5 + q7 are determined.
        def reduced(q):
            return torch.stack([q[..., 0] + q[..., 2], q[..., 1], q[..., 3], q[..., 4] + q[..., 6], q[..., 5]], -1)

        expected = torch.tensor([0, 0, -math.pi / 2, math.pi / 3, 0], dtype=torch.float64)
        both = analytic.iiwa(chain, target, torch.tensor([0.0, math.pi], dtype=torch.float64))
        locked = analytic.iiwa_q3_locked(chain, target)
        for sol in (both, locked):
            assert sol.reachable.all() and _contains(reduced(sol.q).flatten(0, -2), expected, tol=1e-9)
            pos, rot = _closure(chain, sol.q, target)
            assert pos.max() < TOL and rot.max() < TOL

    def test_stretched_arm_is_finite(self):
        chain = robots.iiwa14(flange=0.090)
        target = torch.eye(4, dtype=torch.float64)
        target[2, 3] = 1.270  # robots.md: all joints 0
        sol = analytic.iiwa(chain, target, 0.3)
        assert torch.isfinite(sol.q).all() and sol.reachable.all()
        pos, rot = _closure(chain, sol.q, target)
        assert pos.max() < 1e-6 and rot.max() < 1e-9
        assert analytic.iiwa_arm_angle(chain, torch.zeros(7, dtype=torch.float64)) == 0

    def test_out_of_reach_and_float32(self):
        chain = robots.iiwa14().float()  # Module.float() converts in place: a fresh chain
        target = _random_poses(N_POSES, _gen(14), (0.0, 0.0, 0.36), 0.9).float()
        sol = analytic.iiwa(chain, target, 0.5)
        assert sol.q.dtype == torch.float32 and torch.isfinite(sol.q).all()
        assert 0.2 < sol.reachable.float().mean() < 0.9
        pos, rot = _closure(chain, sol.q, target)
        assert pos[sol.reachable].max() < 1e-4 and rot[sol.reachable].max() < 1e-4

    def test_arm_angle_shapes_and_batched_equals_looped(self):
        chain = IIWA["iiwa14"]
        q = chain.random_q(5, generator=_gen(24))
        target = chain.fk(q)
        grid = torch.tensor([-2.0, 0.1, 1.5], dtype=torch.float64)
        per_pose = analytic.iiwa(chain, target, 0.3).q  # one float for all poses
        assert per_pose.shape == (5, 8, 7)
        assert analytic.iiwa(chain, target, grid[None]).q.shape == (5, 3, 8, 7)
        assert analytic.iiwa(chain, target[0], grid).q.shape == (3, 8, 7)
        looped = torch.stack([analytic.iiwa(chain, target[k], 0.3).q for k in range(5)])
        torch.testing.assert_close(looped, per_pose, rtol=0, atol=1e-12)
        many = analytic.iiwa(chain, target[:, None].expand(5, 3, 4, 4), grid.expand(5, 3))
        torch.testing.assert_close(many.q, analytic.iiwa(chain, target, grid[None]).q, rtol=0, atol=1e-12)

    def test_bad_input(self):
        target = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
        with pytest.raises(ValueError, match="iiwa"):
            analytic.iiwa(robots.puma560(), target, 0.0)
        with pytest.raises(ValueError, match="psi must have shape"):
            analytic.iiwa(IIWA["iiwa14"], target, torch.zeros(3, 2, 1, dtype=torch.float64))
        with pytest.raises(ValueError, match="7 joints"):
            analytic.iiwa_arm_angle(robots.puma560(), torch.zeros(6, dtype=torch.float64))


class TestIiwaQ3Locked:
    @pytest.mark.parametrize("name", list(IIWA))
    def test_round_trip_and_closure(self, name):
        chain = IIWA[name]
        q = chain.random_q(N_POSES, generator=_gen(15))
        q3 = q[:, 2].clone()  # a different locked angle per pose
        target = chain.fk(q)
        sol = analytic.iiwa_q3_locked(chain, target, q3)
        assert sol.reachable.all() and _contains(sol.q, q, among=sol.valid).all() and _distinct(sol.q).all()
        assert (sol.q[..., 2] - q3[:, None]).abs().max() < 1e-12
        pos, rot = _closure(chain, sol.q, target)
        assert pos.max() < TOL and rot.max() < TOL

    def test_default_locks_q3_at_zero_and_unreachable(self):
        chain = IIWA["iiwa14"]
        target = _random_poses(N_POSES, _gen(16), (0.0, 0.0, 0.36), 0.9)
        sol = analytic.iiwa_q3_locked(chain, target)
        assert sol.q[..., 2].abs().max() < 1e-12 and torch.isfinite(sol.q).all()
        assert 0.1 < sol.reachable.float().mean() < 0.9
        pos, rot = _closure(chain, sol.q, target)
        assert pos[sol.reachable].max() < TOL and rot[sol.reachable].max() < TOL


class TestIiwaSolve:
    def test_finds_a_solution_for_reachable_poses(self):
        chain = IIWA["iiwa14"]
        q = chain.random_q(3000, generator=_gen(17))
        target = chain.fk(q)
        res = analytic.iiwa_solve(chain, target)
        assert res.success.float().mean() >= 0.999
        assert chain.within_limits(res.q).all() and (res.iterations == 0).all()
        assert res.pos_err.max() < TOL and res.rot_err.max() < TOL

    def test_nearest_to_reference(self):
        chain = IIWA["iiwa14"]
        q = chain.random_q(500, generator=_gen(18))
        target = chain.fk(q)
        res = analytic.iiwa_solve(chain, target, q0=q)
        assert res.success.all() and _wrap(res.q - q).abs().max() < 1e-8
        # A reference near q: the answer is about as close to it as q is (the pick is over
        # sampled arm angles; near q2 = 0 or q6 = 0 the joints swing fast with psi).
        ref = chain.clamp(q + 0.05 * torch.randn(500, 7, generator=_gen(19), dtype=torch.float64))
        near = analytic.iiwa_solve(chain, target, q0=ref)
        assert near.success.all()
        excess = _wrap(near.q - ref).norm(dim=-1) - _wrap(q - ref).norm(dim=-1)
        assert (excess <= 0.05).float().mean() >= 0.97 and excess.median() < 0.01

    def test_batch_shapes_and_unreachable(self):
        chain = IIWA["iiwa14"]
        q = chain.random_q(2, 3, generator=_gen(25))
        target = chain.fk(q)
        assert analytic.iiwa_solve(chain, target[:0]).q.shape == (0, 3, 7)
        res = analytic.iiwa_solve(chain, target, q0=q[0, 0])  # q0 broadcast over the batch
        assert res.q.shape == (2, 3, 7) and res.success.all()
        far = target.clone()
        far[..., 0, 3] = 5.0
        res = analytic.iiwa_solve(chain, far)
        assert not res.success.any() and chain.within_limits(res.q).all() and torch.isfinite(res.q).all()
        assert (res.pos_err > 3).all()

    def test_agrees_with_the_gradient_solver(self):
        ik = pytest.importorskip("iiwa_torch.ik")
        if not hasattr(ik, "solve"):
            pytest.skip("the gradient solver iiwa_torch.ik.solve is not there yet")
        chain = IIWA["iiwa14"]
        q = chain.random_q(200, generator=_gen(20))
        target = chain.fk(q)
        ours = analytic.iiwa_solve(chain, target)
        theirs = ik.solve(chain, target, seeds=16, generator=_gen(21))
        both = ours.success & theirs.success
        assert ours.success.all() and both.float().mean() > 0.95
        # Same pose reached (the arm is redundant: the joint angles may differ).
        pose_a, pose_b = chain.fk(ours.q[both]), chain.fk(theirs.q[both])
        pos, rot = pose_error(pose_a, pose_b)
        assert pos.norm(dim=-1).max() < 2e-4 and rot.norm(dim=-1).max() < 2e-3


SINGULAR = {  # joint index -> value: wrist or shoulder aligned, arm stretched
    "iiwa14": [{5: 0.0}, {1: 0.0}, {3: 0.0}, {1: 0.0, 3: 0.0}, {1: 0.0, 3: 0.0, 5: 0.0}],
    "puma560": [{4: 0.0}, {2: -math.pi / 2 + math.atan2(0.0203, 0.4318)}],
    "lrmate200ic": [{4: 0.0}],
}


@pytest.mark.parametrize("name", list(SINGULAR))
def test_singular_configurations_are_finite_and_exact(name):
    # At singular configurations the branches stay finite, and every reachable one still
    # reproduces the pose (only the sum/difference of the aligned joints is determined).
    chain = robots.PRESETS[name]()
    for pins in SINGULAR[name]:
        q = chain.random_q(500, generator=_gen(40))
        for joint, value in pins.items():
            q[:, joint] = value
        target = chain.fk(q)
        if name == "iiwa14":
            sol = analytic.iiwa(chain, target, analytic.iiwa_arm_angle(chain, q))
        else:
            sol = analytic.pieper(chain, target)
        assert torch.isfinite(sol.q).all() and sol.reachable.any(-1).all(), pins
        pos, rot = _closure(chain, sol.q, target)
        assert pos[sol.reachable].max() < TOL and rot[sol.reachable].max() < TOL, pins


@pytest.mark.parametrize("name", ["planar3r", "puma560", "lrmate200ic", "iiwa14", "iiwa14-q3"])
def test_float32_closure(name):
    chain = robots.PRESETS[name.split("-")[0]]()
    target = chain.fk(chain.random_q(N_POSES, generator=_gen(30))).float()
    chain = chain.float()
    if name == "planar3r":
        sol = analytic.planar3r(chain, target[:, 0, 3], target[:, 1, 3], torch.atan2(target[:, 1, 0], target[:, 0, 0]))
    elif name == "iiwa14":
        sol = analytic.iiwa(chain, target, torch.linspace(-3, 3, 3)[None])
        target = target[:, None]
    elif name == "iiwa14-q3":
        sol = analytic.iiwa_q3_locked(chain, target)
    else:
        sol = analytic.pieper(chain, target)
    assert sol.q.dtype == torch.float32
    pos, rot = _closure(chain, sol.q, target)
    assert pos[sol.reachable].max() < 1e-4 and rot[sol.reachable].max() < 1e-4


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

    def first_branch_angles(xi):
        return analytic.pieper(chain, _moved(target[:3].detach(), xi)).q[..., 0, :]

    torch.autograd.gradcheck(first_branch_angles, (torch.zeros(3, 6, dtype=torch.float64, requires_grad=True),))


def _moved(pose, xi):
    """``pose (..., 4, 4)`` moved by ``xi (..., 6)`` (translation m, body rotation vector rad): a
    rigid pose for every ``xi``, so finite differences in ``xi`` stay on rigid poses."""
    top = torch.cat([pose[..., :3, :3] @ exp(xi[..., 3:]), (pose[..., :3, 3] + xi[..., :3])[..., None]], -1)
    return torch.cat([top, pose[..., 3:, :]], -2)


def test_iiwa_gradients_w_r_t_target_and_arm_angle():
    chain = robots.iiwa14()
    q = chain.random_q(3, generator=_gen(22))
    target = chain.fk(q)
    xi = torch.zeros(3, 6, dtype=torch.float64, requires_grad=True)
    psi = analytic.iiwa_arm_angle(chain, q).requires_grad_(True)
    torch.autograd.gradcheck(lambda x, p: analytic.iiwa(chain, _moved(target, x), p).q[..., 2, :], (xi, psi))
    torch.autograd.gradcheck(lambda x: analytic.iiwa_q3_locked(chain, _moved(target, x), 0.2).q[..., 5, :], (xi,))
    far = _random_poses(64, _gen(23), (0.0, 0.0, 0.36), 1.4).requires_grad_(True)  # many out of reach
    for solve in (lambda t: analytic.iiwa(chain, t, 0.4), lambda t: analytic.iiwa_q3_locked(chain, t)):
        sol = solve(far)
        assert (~sol.reachable).any()
        (sol.q * sol.valid[..., None]).sum().backward()
        assert torch.isfinite(far.grad).all()
        far.grad = None


def test_planar_gradients():
    chain = robots.planar3r()
    xyphi = torch.tensor([[1.2, 0.4, 0.3], [0.2, -1.1, 2.0]], dtype=torch.float64, requires_grad=True)
    torch.autograd.gradcheck(lambda v: analytic.planar3r(chain, v[:, 0], v[:, 1], v[:, 2]).q, (xyphi,))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_iiwa_solve_succeeds_on_every_pose_of_float32_angles(dtype):
    """FK of angles within the limits is reachable: success must follow the FK error, also where
    rounding puts the elbow cosine a hair past 1 or a joint a hair past its limit."""
    chain = robots.iiwa14().to(dtype)
    q = chain.random_q(20_000, generator=_gen(41), dtype=torch.float32).to(dtype)
    result = analytic.iiwa_solve(chain, chain.fk(q))
    assert result.success.all(), (result.pos_err[~result.success], result.rot_err[~result.success])
    assert chain.within_limits(result.q).all()


def test_iiwa_solve_succeeds_a_rounding_error_beyond_reach():
    chain = robots.iiwa14()
    q = chain.random_q(200, generator=_gen(42))
    q[:, 3] = 0.0  # stretched elbow: the wrist centre at full reach d3 + d5 from the shoulder
    T = chain.fk(q)
    shoulder = torch.tensor([0.0, 0.0, float(chain.dh[0, 2])], dtype=torch.float64)
    T[:, :3, 3] = shoulder + (T[:, :3, 3] - shoulder) * (1 + 1e-12)  # ~1e-12 m beyond reach
    result = analytic.iiwa_solve(chain, T)
    assert result.success.all()
    assert result.pos_err.max() < 1e-11 and result.rot_err.max() < 1e-11
    far = T.clone()
    far[:, :3, 3] = shoulder + (T[:, :3, 3] - shoulder) * 1.01  # 1 cm out: a failure, by the FK error
    result = analytic.iiwa_solve(chain, far)
    assert not result.success.any() and (result.pos_err > 1e-4).all()
    assert chain.within_limits(result.q).all()
