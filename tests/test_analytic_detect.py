"""Closed forms found from the joint axes (``analytic.structure`` / ``analytic.solve``): URDF
arms (pybullet's iiwa, presets exported and read back), a hand-made chain with a base and
turned axes, the Panda refused; FK closure of every branch and the same branches as the
presets' own solvers."""

import math

import pytest
import torch

from iiwa_torch import robots, urdf
from iiwa_torch.chain import Chain
from iiwa_torch.collision import World
from iiwa_torch.ik import analytic
from iiwa_torch.so3 import pose_error

pybullet_data = pytest.importorskip("pybullet_data")

F64 = torch.float64
N = 300


def _closure(chain, sol, target):
    """Largest position (m) and rotation (rad) error of ``chain.fk`` over the reachable branches."""
    extra = sol.q.ndim - 1 - (target.ndim - 2)  # branch dims
    goal = target.reshape(*target.shape[:-2], *(1,) * extra, 4, 4).expand(*sol.q.shape[:-1], 4, 4)
    pos, rot = pose_error(chain.fk(sol.q), goal)
    ok = sol.reachable
    return pos.norm(dim=-1)[ok].max().item(), rot.norm(dim=-1)[ok].max().item()


def _assert_same_branches(q_a, ok_a, q_b, ok_b, tol):
    """Every reachable branch of one solution set is a reachable branch of the other (joint angles
    modulo 2 pi within ``tol``), per pose; both ``q (P, B, n)``, ``ok (P, B)``."""
    diff = q_a[:, :, None, :] - q_b[:, None, :, :]
    dist = (torch.remainder(diff + math.pi, 2 * math.pi) - math.pi).abs().amax(-1)  # (P, B, B)
    big = torch.tensor(math.inf, dtype=F64)
    a_in_b = torch.where(ok_b[:, None, :], dist, big).amin(-1)
    b_in_a = torch.where(ok_a[:, :, None], dist, big).amin(-2)
    assert a_in_b[ok_a].max() < tol
    assert b_in_a[ok_b].max() < tol
    assert torch.equal(ok_a.sum(-1), ok_b.sum(-1))


def _exported(preset):
    return robots.from_urdf(urdf.to_urdf(preset))


def _kuka():
    return robots.from_urdf(pybullet_data.getDataPath() + "/kuka_iiwa/model.urdf")


def _targets(chain, seed=0):
    return chain.fk(chain.random_q(N, generator=torch.Generator().manual_seed(seed)))


@pytest.mark.parametrize("make", [_kuka, lambda: _exported(robots.iiwa14()), lambda: _exported(robots.puma560()),
                                  lambda: _exported(robots.lrmate200ic()), lambda: _exported(robots.planar3r())])
def test_equivalent_dh_chain_has_the_chains_fk(make):
    chain = make()
    found = analytic.structure(chain)
    q = chain.random_q(500, generator=torch.Generator().manual_seed(3))
    assert (found.dh.fk(found.to_dh(q)) - chain.fk(q)).abs().max() < 1e-12
    assert torch.equal(found.from_dh(found.to_dh(q)), q)
    expected = {3: analytic.ClosedForm.PLANAR3R, 6: analytic.ClosedForm.PIEPER, 7: analytic.ClosedForm.SRS}
    assert found.form is expected[chain.n_joints]


def test_pybullet_iiwa_is_srs_with_the_presets_branches():
    chain = _kuka()
    found = analytic.structure(chain)
    assert found.form is analytic.ClosedForm.SRS
    # The file's pi/2 is 1.57079632679: the axes meet within ~1e-11 only, and are refused below that.
    assert 1e-13 < found.deviation < 1e-10
    with pytest.raises(ValueError, match=r"axes 1 and 2 are not perpendicular \(4.9e-12 rad off\)"):
        analytic.structure(chain, tol=1e-12)
    # The iiwa 14 preset with the file's 0.081 m flange, and the file's end frame as its tool:
    # the two arms agree (to the file's rounding) at random q, so their IK must too.
    preset = robots.iiwa14(flange=0.081)
    zero = torch.zeros(7, dtype=F64)
    preset = robots.iiwa14(flange=0.081, tool=torch.linalg.inv(preset.fk(zero)) @ chain.fk(zero))
    q = chain.random_q(N, generator=torch.Generator().manual_seed(1))
    assert (preset.fk(q) - chain.fk(q)).abs().max() < 1e-10
    target = chain.fk(q)
    psi = analytic.iiwa_arm_angle(preset, q)[:, None] + torch.tensor([0.0, 1.0, -2.5], dtype=F64)  # (N, 3)
    sol = analytic.solve(chain, target, psi)
    assert sol.q.shape == (N, 3, 8, 7)
    pos, rot = _closure(chain, sol, target)
    assert pos <= 1e-12 and rot <= 1e-12
    ref = analytic.iiwa(preset, target, psi)
    # The two arms differ by ~1e-11; near an aligned shoulder or wrist a branch moves ~1e3 times that.
    _assert_same_branches(sol.q.reshape(-1, 8, 7), sol.reachable.reshape(-1, 8),
                          ref.q.reshape(-1, 8, 7), ref.reachable.reshape(-1, 8), 1e-6)
    assert torch.equal(sol.valid, sol.reachable & chain.within_limits(sol.q))
    # The arm angle is the preset's: every branch has the asked-for one.
    dpsi = analytic.iiwa_arm_angle(preset, sol.q) - psi[..., None]
    assert (torch.remainder(dpsi + math.pi, 2 * math.pi) - math.pi).abs()[sol.reachable].max() < 1e-9


@pytest.mark.parametrize("preset", [robots.puma560(), robots.lrmate200ic()], ids=["puma560", "lrmate200ic"])
def test_exported_pieper_arms_are_recognised(preset):
    chain = _exported(preset)
    assert type(chain) is Chain
    assert analytic.structure(chain).form is analytic.ClosedForm.PIEPER
    target = _targets(chain)
    sol = analytic.solve(chain, target)
    assert sol.q.shape == (N, 8, 6)
    pos, rot = _closure(chain, sol, target)
    assert pos <= 1e-12 and rot <= 1e-12
    ref = analytic.pieper(preset, target)
    _assert_same_branches(sol.q, sol.reachable, ref.q, ref.reachable, 1e-9)
    assert torch.equal(sol.valid.sum(-1), ref.valid.sum(-1))


@pytest.mark.parametrize("written", ["1.570796", "1.5708"])
def test_a_file_with_pi_over_2_rounded(written):
    """pi/2 written with 7 digits: every reachable branch closes after the Gauss-Newton steps; with 5 digits
    (3.7e-6 rad off, beyond what the closed form takes) ``solve`` refuses what ``structure`` accepted."""
    chain = robots.from_urdf(urdf.to_urdf(robots.puma560()).replace(repr(math.pi / 2), written))
    assert analytic.structure(chain, tol=1e-4).form is analytic.ClosedForm.PIEPER
    target = _targets(chain)
    if written == "1.5708":
        with pytest.raises(ValueError, match=r"3.7e-06 \(m or rad\) from an ideal pieper arm.*only within 1e-06"):
            analytic.solve(chain, target, tol=1e-4)
        return
    sol = analytic.solve(chain, target, tol=1e-4)
    pos, rot = pose_error(chain.fk(sol.q), target[:, None].expand(N, 8, 4, 4))
    closure = torch.maximum(pos.norm(dim=-1), rot.norm(dim=-1))
    assert closure[sol.reachable].max() <= 1e-9 and sol.valid.any(-1).all()


def test_exported_planar3r_is_recognised_and_off_plane_targets_are_unreachable():
    preset = robots.planar3r(1.0, 0.7, 0.4)
    chain = _exported(preset)
    target = _targets(chain)
    sol = analytic.solve(chain, target)
    assert sol.q.shape == (N, 2, 3)
    assert sol.reachable.all()
    pos, rot = _closure(chain, sol, target)
    assert pos <= 1e-12 and rot <= 1e-12
    heading = torch.atan2(target[:, 1, 0], target[:, 0, 0])
    ref = analytic.planar3r(preset, target[:, 0, 3], target[:, 1, 3], heading)
    _assert_same_branches(sol.q, sol.reachable, ref.q, ref.reachable, 1e-9)
    lifted = target.clone()
    lifted[:, 2, 3] += 1e-6
    assert not analytic.solve(chain, lifted).reachable.any()


@pytest.mark.parametrize("name", ["puma560", "iiwa14"])
def test_hand_made_chain_with_a_base_and_turned_axes(name):
    """A preset's joints as a plain Chain, placed by a base transform, with some axes reversed
    (so its joint values are the preset's with those signs turned): same branches, signed."""
    preset = robots.PRESETS[name]()
    # PUMA: axes 2 and 3 made antiparallel; iiwa: axes 3 and 5 against the arm (negative d3, d5 as given).
    turned = {"puma560": [1.0, -1.0, 1.0, -1.0, 1.0, -1.0], "iiwa14": [1.0, -1.0, -1.0, 1.0, -1.0, 1.0, -1.0]}
    flip = torch.tensor(turned[name], dtype=F64)
    turn = torch.tensor([[0.0, -1.0, 0.0], [0.6, 0.0, -0.8], [0.8, 0.0, 0.6]], dtype=F64)
    base = torch.eye(4, dtype=F64)
    base[:3, :3], base[:3, 3] = turn, torch.tensor([0.3, -1.2, 0.5], dtype=F64)
    lo, hi = preset.limits
    exported = _exported(preset)
    chain = Chain(exported.origins, exported.axes * flip[:, None], base=base, tool=exported.tool,
                  limits=torch.stack([torch.where(flip > 0, lo, -hi), torch.where(flip > 0, hi, -lo)]))
    placed = robots.PRESETS[name]()
    placed.base.copy_(base)
    q = chain.random_q(N, generator=torch.Generator().manual_seed(2))
    assert (chain.fk(q) - placed.fk(q * flip)).abs().max() < 1e-12  # the chain is what it says
    target = chain.fk(q)
    if name == "iiwa14":
        psi = analytic.iiwa_arm_angle(placed, q * flip)
        sol, ref = analytic.solve(chain, target, psi), analytic.iiwa(placed, target, psi)
    else:
        sol, ref = analytic.solve(chain, target), analytic.pieper(placed, target)
    pos, rot = _closure(chain, sol, target)
    assert pos <= 1e-12 and rot <= 1e-12
    _assert_same_branches(sol.q * flip, sol.reachable, ref.q, ref.reachable, 1e-9)
    assert torch.equal(sol.valid.sum(-1), ref.valid.sum(-1))
    # Every target comes from an in-limit q: some branch is valid and is that q.
    dist = (torch.remainder(sol.q - q[:, None] + math.pi, 2 * math.pi) - math.pi).abs().amax(-1)
    if name == "puma560":
        assert (torch.where(sol.valid, dist, math.inf).amin(-1) < 1e-7).all()


@pytest.mark.parametrize("name", ["puma560", "iiwa14"])
def test_first_axis_along_the_world_x_axis(name):
    """A preset mounted on a wall (base turned so joint 1's axis is the world x axis, where frame 0's
    x axis cannot follow the world's): still recognised, with the preset's branches."""
    placed = robots.PRESETS[name]()
    placed.base[:3, :3] = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]], dtype=F64)
    q = placed.random_q(N, generator=torch.Generator().manual_seed(5))
    target = placed.fk(q)
    exported = _exported(robots.PRESETS[name]())
    chain = Chain(exported.origins, exported.axes, base=placed.base, tool=exported.tool, limits=placed.limits)
    assert (chain.fk(q) - target).abs().max() < 1e-12
    if name == "iiwa14":
        psi = analytic.iiwa_arm_angle(placed, q)
        sol, ref = analytic.solve(chain, target, psi), analytic.iiwa(placed, target, psi)
    else:
        sol, ref = analytic.solve(chain, target), analytic.pieper(placed, target)
    pos, rot = _closure(chain, sol, target)
    assert pos <= 1e-12 and rot <= 1e-12
    _assert_same_branches(sol.q, sol.reachable, ref.q, ref.reachable, 1e-9)


def test_panda_is_refused_naming_the_failed_conditions():
    panda = robots.from_urdf(pybullet_data.getDataPath() + "/franka_panda/panda.urdf", end_link="panda_hand")
    with pytest.raises(ValueError) as info:
        analytic.structure(panda)
    text = str(info.value)
    assert "not a 7R S-R-S arm" in text
    assert "axes 6 and 7 do not meet (closest approach 0.088 m)" in text
    assert "axes 3 and 4 do not meet (closest approach 0.0825 m)" in text
    assert "ik.solve" in text
    with pytest.raises(ValueError, match="axes 6 and 7 do not meet"):
        analytic.solve(panda, panda.fk(torch.zeros(7, dtype=F64)), 0.0)


def test_world_clearances_as_for_the_preset():
    arm = robots.puma560()
    arm.base.copy_(torch.tensor([[1.0, 0, 0, 0.1], [0, 1, 0, 0], [0, 0, 1, 0.2], [0, 0, 0, 1]], dtype=F64))
    target = _targets(arm, seed=4)[:50]
    world = World(floor=0.0, spheres=(torch.tensor([[0.4, 0.2, 0.7]], dtype=F64), torch.tensor([0.15], dtype=F64)))
    sol = analytic.solve(arm, target, world=world, margin=0.01)
    ref = analytic.pieper(arm, target, world=world, margin=0.01)
    _assert_same_branches(sol.q, sol.valid, ref.q, ref.valid, 1e-9)
    assert sol.clearance is not None and 0 < sol.collision_free.sum() < sol.collision_free.numel()
    assert torch.equal(sol.valid, sol.reachable & sol.within_limits & sol.collision_free)


def test_bad_input():
    with pytest.raises(ValueError, match="needs the arm angles psi"):
        analytic.solve(robots.iiwa14(), _targets(robots.iiwa14())[:2])
    with pytest.raises(ValueError, match="takes no psi"):
        analytic.solve(robots.puma560(), _targets(robots.puma560())[:2], 0.0)
    with pytest.raises(ValueError, match="has 2 joints: the closed forms solve 3"):
        analytic.structure(Chain(torch.eye(4, dtype=F64).repeat(2, 1, 1), [[0, 0, 1.0]] * 2))
    with pytest.raises(ValueError, match="axes 1 and 2 coincide"):
        analytic.structure(Chain(torch.eye(4, dtype=F64).repeat(3, 1, 1), [[0, 0, 1.0]] * 3))
    with pytest.raises(ValueError, match="prismatic"):
        analytic.structure(Chain(torch.eye(4, dtype=F64).repeat(3, 1, 1), [[0, 0, 1.0]] * 3,
                                 kinds=["revolute", "prismatic", "revolute"], limits=[[-1.0] * 3, [1.0] * 3]))
    with pytest.raises(ValueError, match="tol"):
        analytic.structure(robots.puma560(), tol=0.0)
    with pytest.raises(TypeError, match="chain must be a Chain"):
        analytic.structure("puma560")
