"""Closed-form IK and trajectories in a world of obstacles: clearances against coal (FCL's
successor), FK of every answer, poses reachable only through a collision (by geometry),
world=None unchanged, bad input."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from iiwa_torch import robots, so3
from iiwa_torch.collision import World, clearance, robot_capsules
from iiwa_torch.ik import analytic
from iiwa_torch.trajectory import ctraj, jtraj, path_clearance, track

coal = pytest.importorskip("coal")

F64 = torch.float64
ARM = robots.iiwa14()
CENTRES = torch.tensor([[0.45, 0.2, 0.55], [0.35, -0.35, 0.35], [-0.2, 0.4, 0.75]], dtype=F64)
RADII = torch.tensor([0.1, 0.12, 0.08], dtype=F64)
WORLD = World(floor=0.0, spheres=(CENTRES, RADII))


def _coal_capsule(p, q, r):
    axis = q - p
    length = np.linalg.norm(axis)
    z = axis / length
    x = np.cross(z, [1.0, 0, 0] if abs(z[0]) < 0.9 else [0, 1.0, 0])
    x /= np.linalg.norm(x)
    return coal.Capsule(r, length), coal.Transform3s(np.stack([x, np.cross(z, x), z], 1), (p + q) / 2)


def _coal_clearance(chain, q, centres, radii, floor=0.0) -> float:
    """Smallest coal distance over the capsule model's self pairs, its floor and obstacle
    capsules against the floor and the spheres, for one configuration ``q (n,)``."""
    caps = robot_capsules(chain)
    frames = chain.fk_all(q).numpy()
    shapes = []
    for k, f in enumerate(caps.frames):
        ends = frames[f, :3, :3] @ caps.points[k].numpy().T + frames[f, :3, 3:4]
        shapes.append(_coal_capsule(ends[:, 0], ends[:, 1], caps.radii[k].item()))

    def dist(a, b):
        return coal.distance(*a, *b, coal.DistanceRequest(), coal.DistanceResult())

    out = [dist(shapes[i], shapes[j]) for i, j in caps.pairs]
    ground = (coal.Halfspace(np.array([0.0, 0.0, 1.0]), floor), coal.Transform3s())
    out += [dist(shapes[k], ground) for k in range(len(shapes)) if caps.floor[k]]
    for c, r in zip(centres.tolist(), radii.tolist()):
        ball = (coal.Sphere(r), coal.Transform3s(np.eye(3), np.array(c)))
        out += [dist(shapes[k], ball) for k in range(len(shapes)) if caps.world[k]]
    return min(out)


def _free_targets(n, margin, seed=0):
    """FK poses of random in-limit configurations that clear WORLD by more than ``margin``."""
    q = ARM.random_q(4 * n, generator=torch.Generator().manual_seed(seed))
    q = q[clearance(ARM, q, WORLD) > margin][:n]
    assert q.shape[0] == n
    return q, ARM.fk(q)


def _pose_errors(chain, q, target):
    pos, rot = so3.pose_error(chain.fk(q), target)
    return pos.norm(dim=-1), rot.norm(dim=-1)


# ------------------------------------------------------------------ branches
def test_every_branch_carries_its_clearance_against_coal():
    q, target = _free_targets(6, 0.0, seed=1)
    psi = torch.tensor([-2.0, 0.5, 2.5], dtype=F64).expand(6, 3)
    sol = analytic.iiwa(ARM, target, psi, world=WORLD, margin=0.03)
    assert sol.clearance.shape == sol.valid.shape == (6, 3, 8)
    ref = np.array([_coal_clearance(ARM, x, CENTRES, RADII) for x in sol.q.reshape(-1, 7)]).reshape(6, 3, 8)
    ours = sol.clearance.numpy()
    apart = ref > 1e-6  # where coal reports contact it gives a penetration depth, not our distance
    assert 20 < apart.sum() < ref.size
    np.testing.assert_allclose(ours[apart], ref[apart], atol=1e-9)
    assert (ours[~apart] <= 1e-9).all()
    torch.testing.assert_close(sol.collision_free, sol.clearance >= 0.03)
    torch.testing.assert_close(sol.valid, sol.reachable & sol.within_limits & sol.collision_free)
    assert (sol.valid != (sol.reachable & sol.within_limits)).any()  # the world removed some branches


def test_pieper_planar_and_q3_locked_branches_with_a_world():
    puma = robots.puma560()
    target = puma.fk(puma.random_q(5, generator=torch.Generator().manual_seed(2)))
    sol = analytic.pieper(puma, target, world=WORLD)
    ref = np.array([_coal_clearance(puma, x, CENTRES, RADII) for x in sol.q.reshape(-1, 6)]).reshape(5, 8)
    apart = ref > 1e-6
    np.testing.assert_allclose(sol.clearance.numpy()[apart], ref[apart], atol=1e-9)
    locked = analytic.iiwa_q3_locked(ARM, ARM.fk(_free_targets(4, 0.0)[0]), 0.0, world=WORLD)
    torch.testing.assert_close(locked.clearance, clearance(ARM, locked.q, WORLD))
    planar = robots.planar3r()
    # a wall x >= -0.45 m: branch by branch, the capsules' lowest x from the closed-form joint positions
    wall = World(floor=None, walls=(torch.tensor([[1.0, 0.0, 0.0]], dtype=F64), torch.tensor([-0.45], dtype=F64)))
    sol = analytic.planar3r(planar, 1.0, 1.2, 0.5, world=wall)
    th = sol.q.cumsum(-1)
    x = torch.stack([torch.zeros(2, dtype=F64), torch.cos(th[:, 0]), torch.cos(th[:, 0]) + torch.cos(th[:, 1])], -1)
    x = torch.cat([x, (x[:, 2] + 0.5 * torch.cos(th[:, 2]))[:, None]], -1)  # base, elbow, wrist, tip
    expected = torch.minimum((x + 0.45).amin(-1) - 0.05, clearance(planar, sol.q, World(floor=None)))
    torch.testing.assert_close(sol.clearance, expected)
    assert sol.collision_free.tolist() == [True, False]  # the elbow-up branch reaches behind the wall


def test_branch_world_batch_is_one_set_per_pose():
    _, target = _free_targets(3, 0.0, seed=3)
    shifted = CENTRES + torch.tensor([[[0.0, 0.0, 0.0]], [[0.05, 0.0, 0.0]], [[0.0, -0.1, 0.2]]], dtype=F64)
    batched = World(floor=0.0, spheres=(shifted, RADII.expand(3, 3)))
    psi = torch.zeros(3, 2, dtype=F64)
    sol = analytic.iiwa(ARM, target, psi, world=batched)
    for i in range(3):
        single = analytic.iiwa(ARM, target[i], psi[i], world=World(floor=0.0, spheres=(shifted[i], RADII)))
        torch.testing.assert_close(sol.clearance[i], single.clearance)


# ------------------------------------------------------------------ iiwa_solve
def test_iiwa_solve_finds_collision_free_solutions_checked_by_fk_and_coal():
    margin = 0.02
    _, target = _free_targets(300, margin)
    res = analytic.iiwa_solve(ARM, target, world=WORLD, margin=margin)
    assert res.success.float().mean() >= 0.99
    pos, rot = _pose_errors(ARM, res.q, target)
    assert pos[res.success].max() < 1e-9 and rot[res.success].max() < 1e-9
    assert ((res.q >= ARM.limits[0]) & (res.q <= ARM.limits[1])).all()
    torch.testing.assert_close(res.clearance, clearance(ARM, res.q, WORLD))
    checked = res.success.nonzero().squeeze(-1)[:40]
    ref = np.array([_coal_clearance(ARM, res.q[i], CENTRES, RADII) for i in checked])
    assert (ref >= margin - 1e-9).all()
    np.testing.assert_allclose(res.clearance[checked].numpy(), ref, atol=1e-9)


def test_iiwa_solve_near_q0_and_the_world_none_answer_when_it_is_clear():
    q, target = _free_targets(200, 0.0, seed=4)
    plain = analytic.iiwa_solve(ARM, target, q0=q)
    assert plain.clearance is None
    res = analytic.iiwa_solve(ARM, target, q0=q, world=WORLD)
    assert res.success.all()
    # q itself is a collision-free solution: the answer is at least as near (to the sampling)
    assert ((res.q - q).norm(dim=-1) <= (plain.q - q).norm(dim=-1) + 0.05).float().mean() > 0.97
    # where the plain answer is well clear, the search picks it: the same rule among valid ones
    clear = clearance(ARM, plain.q, WORLD) > 0.05
    assert clear.sum() > 150
    same = (res.q[clear] - plain.q[clear]).abs().amax(-1) < 1e-12
    assert same.float().mean() > 0.97


def test_a_pose_reachable_only_through_a_collision_fails_with_a_finite_best_effort():
    # A sphere centred on the flange of every solution: the wrist capsule ends there, so each
    # solution's clearance is at most -(0.04 + 0.075) m.
    q = torch.tensor([[0.3, 0.7, -0.2, -1.2, 0.3, 0.9, 0.1], [-1.0, 0.4, 0.5, -1.6, -0.4, 1.1, 0.0]], dtype=F64)
    target = ARM.fk(q)
    world = World(floor=0.0, spheres=(target[:, None, :3, 3], torch.full((2, 1), 0.04, dtype=F64)))
    res = analytic.iiwa_solve(ARM, target, world=world)
    assert not res.success.any()
    assert torch.isfinite(res.q).all() and torch.isfinite(res.clearance).all()
    assert (res.clearance <= -0.115 + 1e-9).all()
    pos, rot = _pose_errors(ARM, res.q, target)
    assert pos.max() < 1e-9 and rot.max() < 1e-9  # the pose is still met: only the clearance fails
    plain = analytic.iiwa_solve(ARM, target)
    assert plain.success.all()
    # best effort: the largest clearance found is no worse than the plain answer's
    assert (res.clearance >= clearance(ARM, plain.q, world) - 1e-12).all()
    below = ARM.fk(q[:1]).clone()
    below[0, 2, 3] = -0.05  # under the floor: every solution's wrist is below it
    assert not analytic.iiwa_solve(ARM, below, world=World()).success.any()


def test_iiwa_solve_per_pose_worlds_equal_one_at_a_time():
    _, target = _free_targets(4, 0.05, seed=5)
    shifted = CENTRES + 0.05 * torch.randn(4, 3, 3, generator=torch.Generator().manual_seed(0), dtype=F64)
    world = World(floor=0.0, spheres=(shifted, RADII.expand(4, 3)))
    res = analytic.iiwa_solve(
        ARM,
        target.reshape(2, 2, 4, 4),
        world=World(floor=0.0, spheres=(shifted.reshape(2, 2, 3, 3), RADII.expand(2, 2, 3))),
    )
    assert res.q.shape == (2, 2, 7) and res.clearance.shape == (2, 2)
    for i in range(4):
        one = analytic.iiwa_solve(ARM, target[i], world=World(floor=0.0, spheres=(shifted[i], RADII)))
        torch.testing.assert_close(res.q.reshape(4, 7)[i], one.q)
    assert world.batch_shape == (4,)


def test_world_none_is_unchanged_and_bad_world_arguments_are_named():
    _, target = _free_targets(5, 0.0, seed=6)
    sol = analytic.iiwa(ARM, target, 0.3)
    assert sol.clearance is None and sol.collision_free is None
    with pytest.raises(ValueError, match="margin"):
        analytic.iiwa_solve(ARM, target, margin=-0.01, world=WORLD)
    with pytest.raises(ValueError, match="margin"):
        analytic.iiwa_solve(ARM, target, margin=float("nan"), world=WORLD)
    with pytest.raises(ValueError, match="margin and capsules apply to a world"):
        analytic.iiwa_solve(ARM, target, margin=0.02)
    with pytest.raises(TypeError, match="World"):
        analytic.iiwa_solve(ARM, target, world=[CENTRES])
    with pytest.raises(TypeError, match="float64"):
        analytic.iiwa_solve(ARM, target, world=World(spheres=(CENTRES.float(), RADII.float())))
    with pytest.raises(ValueError, match="batch shape"):
        analytic.iiwa_solve(ARM, target, world=World(spheres=(CENTRES.expand(4, 3, 3), RADII.expand(4, 3))))
    with pytest.raises(TypeError, match="capsules"):
        analytic.pieper(robots.puma560(), robots.puma560().fk(torch.zeros(6, dtype=F64)), world=WORLD, capsules=1)
    with pytest.raises(ValueError, match="chain= and world="):
        jtraj(torch.zeros(7, dtype=F64), torch.ones(7, dtype=F64), 5, world=WORLD)


# ------------------------------------------------------------------ trajectories
@pytest.fixture(scope="module")
def line():
    q0 = torch.tensor([0, 30, 0, -80, 0, 70, 0], dtype=F64).deg2rad()
    goal = ARM.fk(q0).clone()
    goal[:3, 3] += torch.tensor([0.0, 0.35, -0.15], dtype=F64)
    return q0, ctraj(ARM.fk(q0), goal, 30, profile="quintic")


def test_track_keeps_the_analytic_path_clear_where_the_arm_angle_allows(line):
    q0, path = line
    plain = track(ARM, path, q0, method="analytic")
    assert plain.clearance is None and plain.min_clearance is None
    # a sphere where the plain path's elbow passes half way
    centre = ARM.fk_all(plain.q[15])[3, :3, 3]
    world = World(floor=0.0, spheres=(centre[None], torch.tensor([0.05], dtype=F64)))
    res = track(ARM, path, q0, method="analytic", world=world, margin=0.01)
    ref = np.array([_coal_clearance(ARM, x, centre[None], torch.tensor([0.05], dtype=F64)) for x in res.q])
    before = np.array([_coal_clearance(ARM, x, centre[None], torch.tensor([0.05], dtype=F64)) for x in plain.q])
    assert before.min() < -0.1  # the plain path goes through it
    assert ref.min() >= 0.01 - 1e-9 and res.collision_free.all() and res.success.all()
    np.testing.assert_allclose(res.clearance.numpy(), ref, atol=1e-9)
    assert res.min_clearance.item() == pytest.approx(ref.min(), abs=1e-9)
    pos, rot = _pose_errors(ARM, res.q, path)
    assert pos.max() < 1e-9 and rot.max() < 1e-9
    assert res.max_step < 0.15  # the elbow swings round the sphere without a jump


def test_track_says_where_no_arm_angle_clears(line):
    q0, path = line
    centre = path[12, :3, 3]  # the flange passes through this sphere
    world = World(floor=0.0, spheres=(centre[None], torch.tensor([0.03], dtype=F64)))
    res = track(ARM, path, q0, method="analytic", world=world)
    dist = (path[:, :3, 3] - centre).norm(dim=-1)
    must_collide = dist < 0.03 + 0.075  # the wrist capsule (radius 0.075) ends at the flange
    assert must_collide.sum() >= 3
    assert not res.collision_free[must_collide].any() and not res.success[must_collide].any()
    assert res.collision_free[dist > 0.3].all()
    pos, _ = _pose_errors(ARM, res.q, path)
    assert pos.max() < 1e-9  # colliding steps still meet the pose
    six = robots.puma560()
    q6 = torch.tensor([0.2, -0.6, 0.3, 0.1, 0.5, 0.0], dtype=F64)
    p6 = ctraj(six.fk(q6), six.fk(q6 + 0.1), 5)
    r6 = track(six, p6, q6, method="analytic", world=World())
    torch.testing.assert_close(r6.clearance, clearance(six, r6.q, World()))


def test_track_gradient_steers_round_a_sphere_on_the_elbow_path(line):
    """A sphere where the obstacle-free path's elbow passes: the gradient tracker with the world keeps
    every step 1 cm clear (distances recomputed with coal) and still meets each pose."""
    q0, path = line
    free = track(ARM, path, q0, method="analytic")
    elbow = ARM.fk_all(free.q[path.shape[0] // 2])[3, :3, 3]
    centres, radii = elbow[None], torch.tensor([0.05], dtype=F64)
    res = track(ARM, path, q0, method="gradient", world=World(floor=0.0, spheres=(centres, radii)), margin=0.01)
    ref = np.array([_coal_clearance(ARM, x, centres, radii) for x in res.q])
    assert ref.min() >= 0.01 - 1e-9
    assert bool(res.success.all()) and float(res.pos_err.max()) < 1e-7
    # a fatter capsule model of one's own: 1 cm fatter capsules clear by 1 cm, so the preset's clear by 2 cm
    fat = dataclasses.replace(robot_capsules(ARM), radii=robot_capsules(ARM).radii + 0.01)
    res = track(ARM, path, q0, method="gradient", world=World(floor=0.0, spheres=(centres, radii)), margin=0.01,
                capsules=fat)  # fmt: skip
    ref = np.array([_coal_clearance(ARM, x, centres, radii) for x in res.q])
    assert ref.min() >= 0.02 - 1e-9 and bool(res.success.all())


def test_track_gradient_and_jtraj_report_the_clearance_along_the_path(line):
    q0, path = line
    world = World(floor=0.0, spheres=(CENTRES, RADII))
    res = track(ARM, path[:6], q0, method="gradient", world=world)
    ref = np.array([_coal_clearance(ARM, x, CENTRES, RADII) for x in res.q])
    np.testing.assert_allclose(res.clearance.numpy(), ref, atol=1e-9)
    torch.testing.assert_close(res.collision_free, res.clearance >= 0)
    q1 = torch.tensor([1.2, 60, 0, -40, 0, 30, 0], dtype=F64).deg2rad()
    traj = jtraj(q0, q1, 15, chain=ARM, world=world)
    ref = min(_coal_clearance(ARM, x, CENTRES, RADII) for x in traj.q)
    assert traj.min_clearance.item() == pytest.approx(ref, abs=1e-9)
    assert jtraj(q0, q1, 15).min_clearance is None
    batch = jtraj(
        q0.expand(2, 7), q1, 15, chain=ARM, world=World(spheres=(CENTRES.expand(2, 3, 3), RADII.expand(2, 3)))
    )
    assert batch.min_clearance.shape == (2,)
    torch.testing.assert_close(batch.min_clearance, path_clearance(ARM, batch.q, WORLD).amin(-1))
    assert math.isfinite(res.min_clearance.item())
