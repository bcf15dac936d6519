"""Gradient IK with a world (ik.solve / ik.minimize with world= and margin=).

Targets are FK of random collision-free configurations with spheres placed near the arm but
clear of it, so a collision-free answer exists by construction. Every answer is verified by
chain.fk and so3.pose_error, and its clearance to the floor and spheres by brute force:
points sampled densely along each capsule's axis (an independent reference for the distance
kernels), besides collision.clearance for the self pairs.
"""

import dataclasses
import math

import pytest
import torch

from iiwa_torch import robots, so3
from iiwa_torch.collision import World, clearance, robot_capsules
from iiwa_torch.ik import IKResult, minimize, solve

F = torch.float64
ARM = robots.iiwa14()
CAPS = robot_capsules(ARM)
MARGIN = 0.01


def axis_points(q, samples=401):
    """``q (b, 7)`` -> points along every capsule's segment ``(b, K, samples, 3)`` (world frame)."""
    frames = ARM.fk_all(q)[:, list(CAPS.frames)]  # (b, K, 4, 4)
    t = torch.linspace(0, 1, samples, dtype=F)[:, None]
    local = CAPS.points[:, None, 0] + t * (CAPS.points[:, None, 1] - CAPS.points[:, None, 0])  # (K, s, 3)
    return torch.einsum("bkij,ksj->bksi", frames[..., :3, :3], local) + frames[..., None, :3, 3]


def brute_world_clearance(q, centres, radii, floor=0.0):
    """Floor and sphere clearance of the capsules by sampling their axes (within 1.3 mm of the
    exact value for these segment lengths: half a sampling step)."""
    pts = axis_points(q)  # (b, K, s, 3)
    r = CAPS.radii[None, :, None]
    floor_gap = (pts[..., 2] - r - floor)[:, CAPS.floor].flatten(1).amin(1)
    gaps = (pts[:, :, :, None] - centres[:, None, None]).norm(dim=-1) - r[..., None] - radii[:, None, None]
    return torch.minimum(floor_gap, gaps.flatten(1).amin(1))


def spheres_near(q, count, seed):
    """``count`` spheres per configuration, each beside a random point of a random capsule and
    clear of the whole arm (and above the floor) by MARGIN + 1 cm or more."""
    g = torch.Generator().manual_seed(seed)
    pts = axis_points(q, samples=11)
    b, k = pts.shape[:2]
    centres, radii = torch.zeros(b, count, 3, dtype=F), torch.zeros(b, count, dtype=F)
    for s in range(count):
        todo = torch.arange(b)
        while todo.numel():
            m = todo.numel()
            cap = torch.randint(0, k, (m,), generator=g)
            base = pts[todo, cap, torch.randint(0, 11, (m,), generator=g)]
            rad = 0.04 + 0.06 * torch.rand(m, generator=g, dtype=F)
            u = torch.randn(m, 3, generator=g, dtype=F)
            gap = MARGIN + 0.01 + 0.05 * torch.rand(m, generator=g, dtype=F)
            cand = base + u / u.norm(dim=-1, keepdim=True) * (CAPS.radii[cap] + rad + gap)[:, None]
            world = World(floor=0.0, spheres=(cand[:, None], rad[:, None]))
            ok = (clearance(ARM, q[todo], world) >= MARGIN + 0.01) & (cand[:, 2] > rad)
            centres[todo[ok], s], radii[todo[ok], s] = cand[ok], rad[ok]
            todo = todo[~ok]
    return centres, radii


def problems(count, seed):
    q = ARM.random_q(3 * count, generator=torch.Generator().manual_seed(seed))
    q = q[clearance(ARM, q) >= MARGIN + 0.02][:count]
    centres, radii = spheres_near(q, 3, seed + 1)
    return q, ARM.fk(q), centres, radii


@pytest.fixture(scope="module")
def solved():
    q, target, centres, radii = problems(200, 0)
    world = World(floor=0.0, spheres=(centres, radii))
    return q, target, centres, radii, world, solve(ARM, target, world=world, margin=MARGIN)


def test_the_construction_is_clear_and_plain_answers_often_collide(solved):
    q, target, centres, radii, world, _ = solved
    assert (brute_world_clearance(q, centres, radii) >= MARGIN).all()
    plain = solve(ARM, target)
    assert plain.clearance is None
    # without the world a large share of the answers collide: the test below can fail
    assert (brute_world_clearance(plain.q, centres, radii) < MARGIN).double().mean() > 0.1


def test_solve_with_world_verified_by_fk_and_brute_force(solved):
    _, target, centres, radii, world, result = solved
    assert result.success.double().mean() >= 0.98
    pos, rot = so3.pose_error(ARM.fk(result.q), target)
    reached = (pos.norm(dim=-1) <= 1e-4) & (rot.norm(dim=-1) <= 1e-3)
    brute = brute_world_clearance(result.q, centres, radii)
    own = clearance(ARM, result.q, World(floor=None))  # self pairs only
    ok = reached & (brute >= MARGIN) & (own >= MARGIN)
    assert torch.equal(result.success, ok)
    # the reported clearance is the minimum over self, floor and spheres
    torch.testing.assert_close(result.clearance, torch.minimum(own, clearance(ARM, result.q, world)))
    assert (result.clearance - torch.minimum(own, brute)).abs().max() < 2e-3
    assert ARM.within_limits(result.q).all()


def test_batched_world_matches_one_target_at_a_time(solved):
    _, target, centres, radii, world, result = solved
    for i in (0, 7, 42):
        alone = solve(ARM, target[i], world=World(floor=0.0, spheres=(centres[i], radii[i])), margin=MARGIN)
        # the same seed wins; float32 iterations round differently in a batch (1e-5 rad)
        torch.testing.assert_close(alone.q, result.q[i], atol=1e-5, rtol=0)


def test_float32_and_an_unbatched_world():
    centres = torch.tensor([[0.5, 0.0, 0.5], [0.0, 0.5, 0.9], [-0.3, -0.3, 0.3]], dtype=F)
    radii = torch.tensor([0.1, 0.08, 0.12], dtype=F)
    world = World(floor=0.0, spheres=(centres, radii))
    q = ARM.random_q(200, generator=torch.Generator().manual_seed(5))
    q = q[clearance(ARM, q, world) >= MARGIN + 0.02][:40]  # one world for every target, clear at q
    world32 = World(floor=0.0, spheres=(centres.float(), radii.float()))
    result = solve(ARM, ARM.fk(q).float(), world=world32, margin=MARGIN)
    assert result.q.dtype == torch.float32 and result.clearance.dtype == torch.float32
    d = brute_world_clearance(result.q.double(), centres.expand(len(q), 3, 3), radii.expand(len(q), 3))
    assert (d[result.success] >= MARGIN - 1e-5).all()
    assert result.success.double().mean() >= 0.95


def test_position_mode_with_a_world(solved):
    _, target, centres, radii, world, _ = solved
    few = slice(0, 40)
    goal = target[few, :3, 3]
    result = solve(ARM, goal, mode="position", world=world.map_batch(lambda t, _: t[few]), margin=MARGIN)
    err = (ARM.fk(result.q)[:, :3, 3] - goal).norm(dim=-1)
    ok = (err <= 1e-4) & (brute_world_clearance(result.q, centres[few], radii[few]) >= MARGIN)
    assert torch.equal(result.success, ok & (clearance(ARM, result.q, World(floor=None)) >= MARGIN))
    assert result.success.all()


def test_target_reachable_only_through_the_floor():
    # flange 3 cm above the floor: the wrist capsule (radius 0.075) ends there, so every exact
    # solution puts it into the floor
    q = ARM.random_q(4000, generator=torch.Generator().manual_seed(3))
    z = ARM.fk(q)[:, 2, 3]
    target = ARM.fk(q[(z > 0.02) & (z < 0.04)][:5])
    assert target.shape[0] == 5
    assert solve(ARM, target).success.all()  # reachable without a world
    result = solve(ARM, target, world=World(floor=0.0))
    assert not result.success.any()
    for value in (result.q, result.pos_err, result.rot_err, result.clearance):
        assert torch.isfinite(value).all()
    assert ARM.within_limits(result.q).all()


def test_world_none_is_the_plain_solve():
    target = ARM.fk(ARM.random_q(50, generator=torch.Generator().manual_seed(4)))
    a, b = solve(ARM, target), solve(ARM, target, world=None, margin=0.0)
    assert torch.equal(a.q, b.q) and a.clearance is None and b.clearance is None


def test_result_field():
    last = dataclasses.fields(IKResult)[-1]
    assert last.name == "clearance" and last.default is None


def test_minimize_with_a_clearance_term():
    # a sphere sits where the plain answer's arm is; reaching the same point must go around it
    q, target, centres, radii = problems(60, 7)
    goal = target[:, :3, 3]
    start = solve(ARM, goal, mode="position")
    d0 = brute_world_clearance(start.q, centres, radii)
    hit = (d0 < 0).nonzero().squeeze(1)[:3]
    assert hit.numel() >= 3
    world = World(floor=0.0, spheres=(centres[hit], radii[hit]))

    def reach(q, pose):
        return (pose[..., :3, 3] - goal[hit]).square().sum(-1)

    result = minimize(ARM, reach, start.q[hit], target=goal[hit], mode="position", world=world, margin=MARGIN,
                      clearance_weight=10.0, steps=50, optimizer="lbfgs")  # fmt: skip
    d = brute_world_clearance(result.q, centres[hit], radii[hit])
    err = (ARM.fk(result.q)[:, :3, 3] - goal[hit]).norm(dim=-1)
    assert torch.equal(result.success, (err <= 1e-4) & (d >= MARGIN) & (result.clearance >= MARGIN))
    assert result.success.all()


@pytest.mark.parametrize(
    "kwargs, error, words",
    [
        ({"world": "floor"}, TypeError, "World"),
        ({"world": World(), "margin": -0.01}, ValueError, "margin"),
        ({"world": World(), "margin": math.nan}, ValueError, "margin"),
        ({"world": World(), "margin": math.inf}, ValueError, "margin"),
        ({"world": World(), "margin": True}, ValueError, "margin"),
        ({"margin": 0.01}, ValueError, "apply to a world"),
        ({"world": World(spheres=(torch.zeros(1, 3), torch.ones(1)))}, TypeError, "float32"),
        ({"world": World(spheres=(torch.zeros(3, 1, 3, dtype=F), torch.ones(3, 1, dtype=F)))}, ValueError, "batch"),
    ],
)
def test_bad_world_or_margin(kwargs, error, words):
    target = ARM.fk(ARM.random_q(5, generator=torch.Generator().manual_seed(0)))
    with pytest.raises(error, match=words):
        solve(ARM, target, **kwargs)
    q0 = ARM.random_q(5, generator=torch.Generator().manual_seed(1))
    with pytest.raises(error, match=words):
        minimize(ARM, lambda q, pose: q.square().sum(-1), q0, target=target, **kwargs)


def test_a_capsule_model_of_ones_own_is_used_by_solve_and_minimize():
    # capsules 3 cm fatter than the preset's: every successful answer clears the floor and the
    # spheres by 3 cm with the preset's capsules (brute force), which the default model does not ensure
    fat = dataclasses.replace(CAPS, radii=CAPS.radii + 0.03)
    q, target, centres, radii = problems(60, 7)
    world = World(floor=0.0, spheres=(centres, radii))
    res = solve(ARM, target, world=world, capsules=fat)
    # the fat model also brings self pairs 6 cm closer, so fewer targets can be met at all
    assert res.success.double().mean() >= 0.3
    brute = brute_world_clearance(res.q, centres, radii)
    assert (brute[res.success] >= 0.03 - 1.5e-3).all()
    torch.testing.assert_close(res.clearance, clearance(ARM, res.q, world, fat))
    plain = solve(ARM, target, world=world)
    assert (brute_world_clearance(plain.q, centres, radii)[plain.success] < 0.03 - 1.5e-3).any()
    # minimize: the clearance term and the reported clearance use the given model
    def reach(x, pose):
        return (pose[..., :3, 3] - target[:5, :3, 3]).square().sum(-1)

    out = minimize(ARM, reach, res.q[:5], target=target[:5, :3, 3], mode="position", world=World(floor=0.0),
                   capsules=fat, steps=5)  # fmt: skip
    torch.testing.assert_close(out.clearance, clearance(ARM, out.q, World(floor=0.0), fat))
    with pytest.raises(ValueError, match="margin and capsules apply to a world"):
        solve(ARM, target, capsules=fat)
