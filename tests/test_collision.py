"""Capsule models and clearance, against coal (FCL's successor), closed forms, brute force and finite differences."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from iiwa_torch import robots, so3
from iiwa_torch.collision import (
    Capsules,
    World,
    capsule_clearance,
    clearance,
    pairwise_clearance,
    robot_capsules,
    segment_box_distance,
    segment_distance,
    self_collision_pairs,
)

coal = pytest.importorskip("coal")

HOME = {7: [math.radians(v) for v in (0.0, 30.0, 0.0, -60.0, 0.0, 30.0, 0.0)]}  # envs.core.IIWA_HOME


def _random_segments(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 4, 3): p1, q1, p2, q2 with a quarter generic, and the rest parallel, collinear,
    crossing (touching) or of zero length."""
    p1, q1 = rng.normal(size=(2, n, 3))
    p2, q2 = rng.normal(size=(2, n, 3))
    kind = np.arange(n) % 6
    d1 = q1 - p1
    shift = rng.normal(size=(n, 3)) * 0.5
    scale = rng.uniform(-2, 2, size=(n, 1))
    par = kind == 1  # parallel, offset
    p2[par], q2[par] = p1[par] + shift[par], p1[par] + shift[par] + scale[par] * d1[par]
    col = kind == 2  # collinear, overlapping or not
    start = rng.uniform(-1.5, 1.5, size=(n, 1))
    p2[col], q2[col] = p1[col] + start[col] * d1[col], p1[col] + (start[col] + scale[col]) * d1[col]
    cross = kind == 3  # the second segment passes through a point of the first
    u = rng.uniform(0, 1, size=(n, 1))
    hit = p1 + u * d1
    p2[cross], q2[cross] = hit[cross] - shift[cross], hit[cross] + 0.7 * shift[cross]
    q2[kind == 4] = p2[kind == 4]  # second is a point
    q1[kind == 5], q2[kind == 5] = p1[kind == 5], p2[kind == 5]  # both points
    return np.stack([p1, q1, p2, q2], 1)


def _coal_capsule(p, q, r):
    """A coal shape and pose for the capsule of segment p q and radius r."""
    axis = q - p
    length = np.linalg.norm(axis)
    if length < 1e-12:
        return coal.Sphere(r), coal.Transform3s(np.eye(3), p)
    z = axis / length
    x = np.cross(z, [1.0, 0, 0] if abs(z[0]) < 0.9 else [0, 1.0, 0])
    x /= np.linalg.norm(x)
    rot = np.stack([x, np.cross(z, x), z], 1)
    return coal.Capsule(r, length), coal.Transform3s(rot, (p + q) / 2)


def _coal_distance(a, b) -> float:
    return coal.distance(*a, *b, coal.DistanceRequest(), coal.DistanceResult())


def _random_rotation(rng) -> np.ndarray:
    m, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return m * np.sign(np.linalg.det(m))


def test_segment_distance_matches_coal_on_thousands_of_cases():
    rng = np.random.default_rng(0)
    seg = _random_segments(rng, 3000)
    radii = rng.uniform(0.01, 0.2, size=(3000, 2))
    ours = segment_distance(*torch.from_numpy(seg).unbind(1)).numpy() - radii.sum(1)
    ref = np.array(
        [_coal_distance(_coal_capsule(s[0], s[1], r[0]), _coal_capsule(s[2], s[3], r[1])) for s, r in zip(seg, radii)]
    )
    apart = ref > 1e-6  # coal's penetration depth is not a distance between the segments
    assert apart.sum() > 1500
    np.testing.assert_allclose(ours[apart], ref[apart], atol=1e-9)
    assert (ours[~apart] <= 1e-9).all()
    cross = np.arange(3000) % 6 == 3
    np.testing.assert_allclose(ours[cross] + radii[cross].sum(1), 0.0, atol=1e-12)


def test_segment_distance_against_dense_points_and_closed_forms():
    rng = np.random.default_rng(1)
    seg = torch.from_numpy(_random_segments(rng, 120))
    ours = segment_distance(*seg.unbind(1))
    u = torch.linspace(0, 1, 401, dtype=torch.float64)[:, None]
    a = seg[:, None, 0] + u * (seg[:, None, 1] - seg[:, None, 0])  # (120, 401, 3)
    b = seg[:, None, 2] + u * (seg[:, None, 3] - seg[:, None, 2])
    brute = torch.cdist(a, b).flatten(1).amin(1)
    step = ((seg[:, 1] - seg[:, 0]).norm(dim=-1) + (seg[:, 3] - seg[:, 2]).norm(dim=-1)) / 400
    assert (ours <= brute + 1e-12).all() and (brute - ours <= step + 1e-12).all()
    x = torch.tensor([1.0, 0, 0], dtype=torch.float64)
    y = torch.tensor([0, 1.0, 0], dtype=torch.float64)
    o = torch.zeros(3, dtype=torch.float64)
    assert segment_distance(o, x, 0.3 * y + 0.5 * x, 0.3 * y + 3 * x).item() == pytest.approx(0.3)  # parallel
    assert segment_distance(o, x, 3 * x, 2 * x).item() == pytest.approx(1.0)  # collinear, reversed
    assert segment_distance(o, o, 2 * y, 2 * y).item() == pytest.approx(2.0)  # two points


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_degenerate_segments_have_finite_gradients(dtype):
    x = torch.tensor([1.0, 0, 0], dtype=dtype)
    y = torch.tensor([0, 1.0, 0], dtype=dtype)
    o = torch.zeros(3, dtype=dtype)
    cases = [
        (o, x, 0.2 * y, 0.2 * y + x),  # parallel
        (o, x, 0.5 * x - y, 0.5 * x + y),  # crossing: distance 0
        (o, o, o, x),  # a point on the other segment
        (o, o, o, o),  # coincident points
        (o, x, 2 * x, 3 * x),  # collinear
    ]
    for case in cases:
        pts = [p.clone().requires_grad_() for p in case]
        d = segment_distance(*pts)
        (grads := torch.autograd.grad(d, pts))
        assert torch.isfinite(d) and all(torch.isfinite(g).all() for g in grads)


def test_gradcheck_segment_and_box_distances():
    rng = np.random.default_rng(2)
    seg = torch.from_numpy(rng.normal(size=(4, 4, 3))).requires_grad_()
    assert torch.autograd.gradcheck(lambda s: segment_distance(*s.unbind(1)), (seg,))
    pose = torch.eye(4, dtype=torch.float64).repeat(4, 1, 1)
    pose[:, :3, :3] = torch.from_numpy(np.stack([_random_rotation(rng) for _ in range(4)]))
    pose[:, :3, 3] = torch.from_numpy(rng.normal(size=(4, 3)) * 0.1)
    half = torch.from_numpy(rng.uniform(0.2, 0.5, size=(4, 3))).requires_grad_()
    centre = pose[:, :3, 3].clone().requires_grad_()

    def box(s, h, c):
        full = torch.cat([torch.cat([pose[:, :3, :3], c[..., None]], -1), pose[:, 3:]], -2)
        return segment_box_distance(s[:, 0] * 2, s[:, 1] * 2, full, h)

    assert torch.autograd.gradcheck(box, (seg, half, centre), atol=1e-6)


def test_segment_box_distance_matches_coal_outside_and_brute_force_inside():
    rng = np.random.default_rng(3)
    n = 1500
    rot = np.stack([_random_rotation(rng) for _ in range(n)])
    centre = rng.normal(size=(n, 3)) * 0.3
    half = rng.uniform(0.05, 0.5, size=(n, 3))
    seg = rng.normal(size=(n, 2, 3))
    seg[::5, 1] = seg[::5, 0]  # some points
    pose = np.tile(np.eye(4), (n, 1, 1))
    pose[:, :3, :3], pose[:, :3, 3] = rot, centre
    r = 0.05
    t = torch.from_numpy
    ours = segment_box_distance(t(seg[:, 0]), t(seg[:, 1]), t(pose), t(half)).numpy() - r
    ref = np.array(
        [
            _coal_distance(_coal_capsule(s[0], s[1], r), (coal.Box(*(2 * h)), coal.Transform3s(R, c)))
            for s, R, c, h in zip(seg, rot, centre, half)
        ]
    )
    apart = ref > 1e-4
    assert apart.sum() > 500
    np.testing.assert_allclose(ours[apart], ref[apart], atol=1e-6)
    # inside: the deepest sampled point of the segment, from the box's own signed distance
    u = np.linspace(0, 1, 2001)[:, None]
    inside = np.flatnonzero(~apart)[:100]
    for k in inside:
        local = (seg[k, 0] + u * (seg[k, 1] - seg[k, 0]) - centre[k]) @ rot[k]
        excess = np.abs(local) - half[k]
        sdf = np.linalg.norm(np.maximum(excess, 0), axis=1) + np.minimum(excess.max(1), 0)
        assert ours[k] <= sdf.min() - r + 1e-9 and sdf.min() - r - ours[k] < 1e-3


def test_segment_box_distance_is_the_minimum_of_dense_samples_in_every_configuration():
    rng = np.random.default_rng(9)
    n = 4000
    rot = np.stack([_random_rotation(rng) for _ in range(n)])
    rot[::3] = np.eye(3)  # axis-aligned: the segments below become parallel to faces
    half = rng.uniform(0.05, 0.4, size=(n, 3))
    seg = rng.normal(size=(n, 2, 3)) * 0.5
    seg[::3, 1, 2] = seg[::3, 0, 2]  # parallel to a pair of faces
    seg[::6, 1, 1] = seg[::6, 0, 1]  # parallel to an edge
    seg[1::6] *= 0.2  # mostly inside
    touch = np.arange(n) % 6 == 2  # the start point on a face, the segment leaving it
    seg[touch, 0] = rng.uniform(-1, 1, size=(touch.sum(), 3)) * half[touch]
    seg[touch, 0, 0] = half[touch, 0]
    seg[touch, 1, 0] = half[touch, 0] + np.abs(seg[touch, 1, 0])
    seg[5::6, 1] = seg[5::6, 0]  # points
    local = seg.copy()
    seg = np.einsum("nij,nkj->nki", rot, local)  # world frame, box centred at the origin
    pose = np.tile(np.eye(4), (n, 1, 1))
    pose[:, :3, :3] = rot
    t = torch.from_numpy
    ours = segment_box_distance(t(seg[:, 0]), t(seg[:, 1]), t(pose), t(half)).numpy()
    u = np.linspace(0, 1, 4001)[None, :, None]
    x = local[:, :1] + u * (local[:, 1:] - local[:, :1])  # (n, 4001, 3)
    excess = np.abs(x) - half[:, None]
    sdf = np.linalg.norm(np.maximum(excess, 0), axis=-1) + np.minimum(excess.max(-1), 0)
    step = np.linalg.norm(local[:, 1] - local[:, 0], axis=-1) / 4000
    assert np.isfinite(ours).all()
    assert (ours <= sdf.min(1) + 1e-12).all() and (sdf.min(1) - ours <= step + 1e-12).all()
    assert (ours < 0).sum() > 500 and (ours > 0).sum() > 1000
    np.testing.assert_allclose(ours[touch], 0.0, atol=1e-12)


def test_segment_box_distance_gradient_matches_finite_differences():
    """Outside and inside: inside, the deepest point is where two of the lines |x_i| - h_i cross, and it
    moves with the segment (its gradient is not the sdf's at a fixed point)."""
    rng = np.random.default_rng(10)
    inside = 0
    for case in range(60):
        pose = torch.eye(4, dtype=torch.float64)
        pose[:3, :3] = torch.from_numpy(_random_rotation(rng))
        half = torch.from_numpy(rng.uniform(0.1, 0.4, 3))
        seg = torch.from_numpy(rng.normal(size=(2, 3)) * (0.15 if case % 2 else 0.6)).requires_grad_()
        d = segment_box_distance(seg[0], seg[1], pose, half)
        (grad,) = torch.autograd.grad(d, seg)
        assert torch.isfinite(grad).all()
        inside += d.item() < 0
        h = 1e-6
        fd = torch.zeros(2, 3, dtype=torch.float64)
        for i in range(2):
            for j in range(3):
                e = torch.zeros(2, 3, dtype=torch.float64)
                e[i, j] = h
                plus, minus = seg.detach() + e, seg.detach() - e
                fd[i, j] = (
                    segment_box_distance(plus[0], plus[1], pose, half)
                    - segment_box_distance(minus[0], minus[1], pose, half)
                ) / (2 * h)
        torch.testing.assert_close(grad, fd, atol=1e-5, rtol=0)
    assert 10 < inside < 50
    # a segment through a box's middle: the deepest point slides along it as p moves (was held still)
    p = torch.tensor([-0.05, 0.0, 0.0], dtype=torch.float64, requires_grad=True)
    q, half = torch.tensor([0.05, 0.1, 0.5], dtype=torch.float64), torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    d = segment_box_distance(p, q, torch.eye(4, dtype=torch.float64), half)
    # closed form: the lines -x - h_x and z - h_z cross at t = (h_z - h_x - p_x - p_z) / (q_z - p_z + q_x - p_x)
    # (y stays clear of its faces), and the distance there is z(t) - h_z
    t = (half[2] - half[0] - p[0] - p[2]) / (q[2] - p[2] + q[0] - p[0])
    closed = p[2] + t * (q[2] - p[2]) - half[2]
    torch.testing.assert_close(d, closed, atol=1e-15, rtol=0)
    torch.testing.assert_close(torch.autograd.grad(d, p)[0], torch.autograd.grad(closed, p)[0], atol=1e-12, rtol=0)


def test_world_obstacles_match_coal_for_a_robot():
    chain = robots.iiwa14()
    caps = robot_capsules(chain)
    rng = np.random.default_rng(4)
    q = chain.random_q(20, generator=torch.Generator().manual_seed(4))
    n_obs = 3
    normal = rng.normal(size=(20, n_obs, 3))
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    world = World(
        floor=-0.1,
        walls=(torch.from_numpy(normal), torch.from_numpy(rng.uniform(-1.5, -0.5, (20, n_obs)))),
        spheres=(
            torch.from_numpy(rng.normal(size=(20, n_obs, 3))),
            torch.from_numpy(rng.uniform(0.05, 0.2, (20, n_obs))),
        ),
        capsules=(
            torch.from_numpy(rng.normal(size=(20, n_obs, 2, 3))),
            torch.from_numpy(rng.uniform(0.05, 0.2, (20, n_obs))),
        ),
    )
    res = pairwise_clearance(chain, q, world, caps)
    assert res.distance.shape == (20, len(res.pairs))
    frames = chain.fk_all(q)[:, list(caps.frames)].numpy()
    pts = caps.points.numpy()
    checked = 0
    for b in range(20):
        shapes = {}
        for k, name in enumerate(caps.names):
            ends = frames[b, k, :3, :3] @ pts[k].T + frames[b, k, :3, 3:]
            shapes[name] = _coal_capsule(ends[:, 0], ends[:, 1], caps.radii[k].item())
        ident = coal.Transform3s()
        for m in range(n_obs):
            shapes[f"wall{m}"] = (coal.Halfspace(normal[b, m], world.walls[1][b, m].item()), ident)
            c, r = world.spheres[0][b, m].numpy(), world.spheres[1][b, m].item()
            shapes[f"sphere{m}"] = (coal.Sphere(r), coal.Transform3s(np.eye(3), c))
            p = world.capsules[0][b, m].numpy()
            shapes[f"capsule{m}"] = _coal_capsule(p[0], p[1], world.capsules[1][b, m].item())
        shapes["floor"] = (coal.Halfspace(np.array([0, 0, 1.0]), -0.1), ident)
        for (a, o), d in zip(res.pairs, res.distance[b].tolist()):
            ref = _coal_distance(shapes[a], shapes[o])
            if ref > 1e-6 or o == "floor" or o.startswith("wall"):  # half-spaces: exact depth too
                assert d == pytest.approx(ref, abs=1e-9), (a, o)
                checked += 1
    assert checked > 20 * len(res.pairs) // 2


def test_presets_home_is_clear_and_a_link_below_the_floor_is_not():
    for make in robots.PRESETS.values():
        chain = make()
        caps = robot_capsules(chain)
        q = torch.tensor(HOME.get(chain.n_joints, [0.0] * chain.n_joints), dtype=torch.float64)
        assert clearance(chain, q).item() > 0.05, chain.name
        if caps.floor_height is not None:
            assert clearance(chain, q, World(floor=1.5)).item() < 0, chain.name
    iiwa = robots.iiwa14()
    down = torch.tensor([0.0, math.radians(110), 0, 0, 0, 0, 0], dtype=torch.float64)  # arm folded towards the floor
    res = pairwise_clearance(iiwa, down)
    by_pair = dict(zip(res.pairs, res.distance.tolist()))
    # the wrist tip sits at z = 0.36 + 0.946 cos(110 deg) = 0.036 m, inside its 0.075 m radius
    assert by_pair[("wrist", "floor")] == pytest.approx(0.36 + 0.946 * math.cos(math.radians(110)) - 0.075)
    assert clearance(iiwa, down).item() < 0


def test_iiwa_model_covers_the_datasheet_and_pairs_are_as_documented():
    chain = robots.iiwa14()
    caps = robot_capsules(chain)
    assert caps.names == ("base", "upper_arm", "forearm", "wrist")
    assert caps.pairs == ((0, 2), (0, 3), (1, 3))  # neighbours excluded; no pair always touches
    frames = chain.fk_all(torch.zeros(7, dtype=torch.float64))
    top = (frames[caps.frames[-1], :3, :3] @ caps.points[-1, 1] + frames[caps.frames[-1], :3, 3])[2]
    assert top.item() == pytest.approx(1.306)  # KUKA's dimension A: the flange at home
    assert not caps.floor[0] and caps.floor[1:].all() and caps.world.all()


def test_batched_shapes_dtypes_and_per_environment_worlds():
    chain = robots.iiwa14()
    q64 = chain.random_q(3, 5, generator=torch.Generator().manual_seed(5))
    centre = torch.zeros(5, 1, 3, dtype=torch.float64)
    centre[:, 0, 2] = torch.linspace(0.2, 2.0, 5)
    world = World(spheres=(centre, torch.full((5, 1), 0.1, dtype=torch.float64)))
    d = clearance(chain, q64, world)
    assert d.shape == (3, 5)
    looped = torch.stack(
        [
            torch.stack(
                [
                    clearance(chain, q64[i, j], World(spheres=(centre[j], torch.full((1,), 0.1, dtype=torch.float64))))
                    for j in range(5)
                ]
            )
            for i in range(3)
        ]
    )
    torch.testing.assert_close(d, looped)
    w32 = World(spheres=(centre.float(), torch.full((5, 1), 0.1)))
    torch.testing.assert_close(clearance(chain, q64.float(), w32), d.float(), atol=1e-5, rtol=0)


@pytest.mark.parametrize("n", [3, 100])  # the numpy path for a few configurations, torch beyond
def test_a_kind_with_no_obstacle_adds_nothing(n):
    """Spheres and boxes given with M = 0 (e.g. an env whose obstacles are all of the other kind) are no
    obstacles: the same clearance as the floor alone, and no pair columns for them."""
    chain = robots.iiwa14()
    q = chain.random_q(n, generator=torch.Generator().manual_seed(2))
    empty = World(spheres=(torch.zeros(0, 3, dtype=torch.float64), torch.zeros(0, dtype=torch.float64)),
                  boxes=(torch.zeros(0, 4, 4, dtype=torch.float64), torch.zeros(0, 3, dtype=torch.float64)))
    torch.testing.assert_close(clearance(chain, q, empty), clearance(chain, q, World()), rtol=0, atol=1e-12)
    assert pairwise_clearance(chain, q, empty).pairs == pairwise_clearance(chain, q, World()).pairs
    box = (torch.eye(4, dtype=torch.float64)[None].clone(), torch.full((1, 3), 0.05, dtype=torch.float64))
    box[0][0, :3, 3] = torch.tensor([0.5, 0.0, 0.5])
    only_boxes = World(spheres=empty.spheres, boxes=box)
    torch.testing.assert_close(clearance(chain, q, only_boxes), clearance(chain, q, World(boxes=box)))


def test_clearance_gradient_in_q_and_obstacles():
    chain = robots.iiwa14()
    q = chain.random_q(3, generator=torch.Generator().manual_seed(6)).requires_grad_()
    pose = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
    pose[:, :3, 3] = torch.tensor([0.5, 0.0, 0.5], dtype=torch.float64)
    half = torch.full((3, 1, 3), 0.1, dtype=torch.float64, requires_grad=True)
    centre = torch.tensor([[[0.0, 0.5, 0.8]]], dtype=torch.float64).repeat(3, 1, 1).requires_grad_()

    def all_distances(q, half, centre):
        world = World(boxes=(pose[:, None], half), spheres=(centre, torch.full((3, 1), 0.1, dtype=torch.float64)))
        return pairwise_clearance(chain, q, world).distance

    assert torch.autograd.gradcheck(all_distances, (q, half, centre), atol=1e-6)


def test_bad_input_is_rejected_with_a_clear_message():
    chain = robots.iiwa14()
    q = torch.zeros(7, dtype=torch.float64)
    one = torch.ones(1, dtype=torch.float64)
    with pytest.raises(ValueError, match="radii must be positive"):
        World(spheres=(torch.zeros(1, 3, dtype=torch.float64), -one))
    with pytest.raises(ValueError, match="radii must be positive"):
        World(capsules=(torch.zeros(1, 2, 3, dtype=torch.float64), 0 * one))
    with pytest.raises(ValueError, match="NaN"):
        World(spheres=(torch.zeros(1, 3, dtype=torch.float64), one * math.nan))
    skew = torch.eye(4, dtype=torch.float64)[None].clone()
    skew[0, 0, 1] = 0.3
    with pytest.raises(ValueError, match="orthonormal"):
        World(boxes=(skew, torch.ones(1, 3, dtype=torch.float64)))
    with pytest.raises(ValueError, match="shape"):
        World(spheres=(torch.zeros(1, 2, dtype=torch.float64), one))
    with pytest.raises(ValueError, match="unit"):
        World(walls=(torch.ones(1, 3, dtype=torch.float64), one))
    with pytest.raises(TypeError, match="float64"):
        World(spheres=(torch.zeros(1, 3, dtype=torch.float64), torch.ones(1)))
    with pytest.raises(TypeError, match="q is torch.float32"):
        clearance(chain, q.float(), World(spheres=(torch.zeros(1, 3, dtype=torch.float64), one)))
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 7\)"):
        clearance(chain, torch.zeros(6, dtype=torch.float64))
    with pytest.raises(ValueError, match="radii must be positive"):
        Capsules.build(chain, ["a"], [0], [[[0, 0, 0], [0, 0, 1]]], [0.0])
    with pytest.raises(ValueError, match="NaN"):
        Capsules.build(chain, ["a"], [0], [[[0, 0, 0], [0, 0, 1]]], [math.nan])
    with pytest.raises(ValueError, match="frames must index"):
        Capsules.build(chain, ["a"], [8], [[[0, 0, 0], [0, 0, 1]]], [0.1])
    with pytest.raises(ValueError, match=r"points must be a float64 tensor of shape \(1, 2, 3\)"):
        Capsules.build(chain, ["a"], [0], [[0, 0, 0]], [0.1])
    with pytest.raises(ValueError, match="no capsule model"):
        robot_capsules(robots.planar3r().__class__([(1.0, 0, 0, 0)], name="custom"))


def test_custom_chain_capsules():
    chain = robots.planar3r().__class__([(1.0, 0, 0, 0), (1.0, 0, 0, 0), (1.0, 0, 0, 0)], name="custom")
    caps = Capsules.build(
        chain,
        ["l1", "l2", "l3"],
        [1, 2, 3],
        [[[-1.0, 0, 0], [0, 0, 0]]] * 3,
        [0.1] * 3,
        floor_height=None,
    )
    assert caps.pairs == ((0, 2),)
    folded = torch.tensor([0.0, math.pi * 0.95, math.pi * 0.95], dtype=torch.float64)
    # link 3 folds back onto link 1: their segments cross near the origin
    assert clearance(chain, folded, capsules=caps).item() < 0
    assert clearance(chain, torch.zeros(3, dtype=torch.float64), capsules=caps).item() == pytest.approx(1.0 - 0.2)


def test_pairs_that_always_overlap_are_left_out():
    chain = robots.planar3r().__class__([(1.0, 0, 0, 0), (1.0, 0, 0, 0), (1.0, 0, 0, 0)], name="custom")
    link = [[-1.0, 0, 0], [0, 0, 0]]
    caps = Capsules.build(
        chain, ["hub", "l1", "l2", "l3"], [0, 1, 2, 3], [[[0, 0, 0], [0, 0, 0]], link, link, link], [1.2, 0.1, 0.1, 0.1]
    )
    # l2 starts 1 m from the origin, inside the hub's 1.2 m: (hub, l2) touches in every posture
    assert caps.pairs == ((0, 3), (1, 3))


def test_nearly_parallel_segments_in_both_dtypes():
    gen = torch.Generator().manual_seed(7)
    n = 400
    p1, d, kick, p2 = torch.randn(4, n, 3, generator=gen, dtype=torch.float64)
    perp = torch.linalg.cross(d, kick)
    perp *= d.norm(dim=-1, keepdim=True) / perp.norm(dim=-1, keepdim=True)
    angle = torch.logspace(-9, -1, n, dtype=torch.float64)[:, None]
    p2 = p1 + 0.3 * p2
    q1, q2 = p1 + d, p2 + d + angle * perp
    ours = segment_distance(p1, q1, p2, q2)
    # reference: 20,001 points on the first segment, each projected exactly onto the second
    s = torch.linspace(0, 1, 20001, dtype=torch.float64)[:, None]
    u = q2 - p2
    x = p1[:, None] + s * d[:, None] - p2[:, None]  # (n, 20001, 3)
    t = ((x * u[:, None]).sum(-1) / (u * u).sum(-1, keepdim=True)).clamp(0, 1)
    ref = (x - t[..., None] * u[:, None]).norm(dim=-1).amin(1)
    assert (ours <= ref + 5e-8).all() and (ref - ours <= 1e-4).all()
    rounded = [v.float() for v in (p1, q1, p2, q2)]
    torch.testing.assert_close(
        segment_distance(*rounded).double(), segment_distance(*(v.double() for v in rounded)), atol=1e-6, rtol=0
    )


def test_preset_pairs_are_what_sampling_finds():
    for make in robots.PRESETS.values():
        chain = make()
        caps = robot_capsules(chain)
        assert self_collision_pairs(chain, caps, samples=2048, seed=1) == caps.pairs, chain.name


def test_capsule_distance_matches_pybullet():
    pb = pytest.importorskip("pybullet")
    rng = np.random.default_rng(8)
    seg = _random_segments(rng, 300)
    seg = seg[np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1) > 1e-3]
    seg = seg[np.linalg.norm(seg[:, 3] - seg[:, 2], axis=1) > 1e-3]
    radii = rng.uniform(0.01, 0.2, size=(len(seg), 2))
    ours = segment_distance(*torch.from_numpy(seg).unbind(1)).numpy() - radii.sum(1)
    client = pb.connect(pb.DIRECT)
    try:
        ref = []
        for s, r in zip(seg, radii):
            bodies = []
            for (p, q), radius in zip((s[:2], s[2:]), r):
                length = float(np.linalg.norm(q - p))
                u = (q - p) / length
                u = -u if u[2] < 0 else u  # a capsule is symmetric: keep the axis in z >= 0
                quat = np.array([-u[1], u[0], 0.0, 1.0 + u[2]])  # the shortest turn taking z to u
                quat /= np.linalg.norm(quat)
                col = pb.createCollisionShape(pb.GEOM_CAPSULE, radius=radius, height=length, physicsClientId=client)
                bodies.append(
                    pb.createMultiBody(
                        0, col, basePosition=(p + q) / 2, baseOrientation=quat.tolist(), physicsClientId=client
                    )
                )
            ref.append(min(h[8] for h in pb.getClosestPoints(*bodies, 100.0, physicsClientId=client)))
            for body in bodies:
                pb.removeBody(body, physicsClientId=client)
    finally:
        pb.disconnect(client)
    ref = np.array(ref)
    apart = ref > 1e-4
    assert apart.sum() > 100
    np.testing.assert_allclose(ours[apart], ref[apart], atol=1e-6)


def test_gradient_is_finite_when_an_obstacle_sits_on_a_capsule_axis():
    chain = robots.iiwa14()
    q = torch.zeros(7, dtype=torch.float64, requires_grad=True)
    centre = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64, requires_grad=True)  # on the forearm's axis
    points = torch.tensor([[[0.0, 0.0, 0.9], [0.0, 0.0, 1.1]]], dtype=torch.float64, requires_grad=True)  # along it
    world = World(
        spheres=(centre, torch.tensor([0.05], dtype=torch.float64)),
        capsules=(points, torch.tensor([0.05], dtype=torch.float64)),
    )
    d = clearance(chain, q, world)
    assert d.item() == pytest.approx(-0.13)  # forearm radius 0.08 + 0.05, centre distance 0
    grads = torch.autograd.grad(d, (q, centre, points))
    assert all(torch.isfinite(g).all() for g in grads)


def test_one_configuration_equals_its_row_of_a_large_batch():
    chain = robots.iiwa14()
    q = chain.random_q(200, generator=torch.Generator().manual_seed(11))  # above the 4x4 kernel's batch sizes
    pose = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    pose[:, :3, 3] = torch.tensor([[0.5, 0.0, 0.5], [0.0, -0.4, 0.8]], dtype=torch.float64)
    world = World(
        floor=0.0,
        spheres=(torch.tensor([[0.3, 0.3, 0.9]], dtype=torch.float64), torch.tensor([0.1], dtype=torch.float64)),
        boxes=(pose, torch.full((2, 3), 0.1, dtype=torch.float64)),
    )
    batch = pairwise_clearance(chain, q, world).distance
    single = torch.stack([pairwise_clearance(chain, row, world).distance for row in q[:40]])
    torch.testing.assert_close(single, batch[:40], atol=1e-12, rtol=0)
    torch.testing.assert_close(clearance(chain, q, world), batch.amin(-1), atol=0, rtol=0)


def test_large_batches_give_the_same_answer_on_any_thread_count_and_leave_it_as_it_was():
    chain = robots.iiwa14()
    q = chain.random_q(10_000, generator=torch.Generator().manual_seed(12)).float()  # several blocks
    world = World(floor=0.0, spheres=(torch.tensor([[0.4, 0.0, 0.6]]), torch.tensor([0.15])))
    before = torch.get_num_threads()
    try:
        answers = []
        for threads in (1, 2):
            torch.set_num_threads(threads)
            x = q.clone().requires_grad_(True)
            d = clearance(chain, x, world)
            assert torch.get_num_threads() == threads
            answers.append((d.detach(), torch.autograd.grad(d.sum(), x)[0]))
    finally:
        torch.set_num_threads(before)
    for a, b in zip(*answers):
        torch.testing.assert_close(b, a, atol=0, rtol=0)
    torch.testing.assert_close(answers[0][0], pairwise_clearance(chain, q, world).distance.amin(-1), atol=0, rtol=0)


@pytest.mark.parametrize("world_batch", [(), (60,)])
def test_clearance_skips_far_boxes_without_changing_the_minimum_or_its_gradient(world_batch):
    # clearance runs the exact segment-box search only on pairs that can be the minimum; the
    # reference is every pair's exact distance (pairwise_clearance, checked against coal above)
    chain = robots.iiwa14()
    rng = np.random.default_rng(11)
    q = chain.random_q(60, generator=torch.Generator().manual_seed(11)).requires_grad_()
    m = 5
    rot = torch.from_numpy(np.stack([_random_rotation(rng) for _ in range(int(np.prod(world_batch, dtype=int)) * m)]))
    pose = torch.eye(4, dtype=torch.float64).repeat(rot.shape[0], 1, 1)
    pose[:, :3, :3] = rot
    # centres from touching the arm's workspace to far outside it (and one parked 100 m up)
    radius = rng.uniform(0.5, 3.0, rot.shape[0])
    direction = rng.normal(size=(rot.shape[0], 3))
    pose[:, :3, 3] = torch.from_numpy(direction / np.linalg.norm(direction, axis=-1, keepdims=True) * radius[:, None])
    pose[0, :3, 3] = torch.tensor([0.0, 0.0, 100.0])
    pose = pose.reshape(*world_batch, m, 4, 4).requires_grad_()
    half = torch.from_numpy(rng.uniform(0.02, 0.3, (*world_batch, m, 3)))
    world = World(floor=-0.2, boxes=(pose, half))
    got = clearance(chain, q, world)
    ref = pairwise_clearance(chain, q, world).distance.amin(-1)
    assert torch.equal(got, ref)
    assert (got < 0).any() and (got > 0).any()
    g_got = torch.autograd.grad(got.sum(), (q, pose))
    g_ref = torch.autograd.grad(ref.sum(), (q, pose))
    for a, b in zip(g_got, g_ref):
        assert torch.allclose(a, b, atol=1e-12)


def test_capsule_clearance_minimum_is_clearance_and_gradient_matches_finite_differences():
    chain = robots.iiwa14()
    rng = np.random.default_rng(4)
    lo, hi = chain.limits.numpy()
    q = torch.as_tensor(rng.uniform(lo, hi, (2, 3, 7)))
    world = World(floor=0.0, spheres=(torch.tensor([[0.4, 0.1, 0.6]], dtype=torch.float64),
                                      torch.tensor([0.1], dtype=torch.float64)),
                  boxes=(torch.tensor([[[1.0, 0, 0, -0.3], [0, 1, 0, 0.2], [0, 0, 1, 0.7], [0, 0, 0, 1]]],
                                      dtype=torch.float64), torch.tensor([[0.1, 0.05, 0.2]], dtype=torch.float64)))
    distance, gradient = capsule_clearance(chain, q, world)
    k = len(robot_capsules(chain).names)
    assert distance.shape == (2, 3, k) and gradient.shape == (2, 3, k, 7)
    torch.testing.assert_close(distance.amin(-1), clearance(chain, q, world))
    h = 1e-6
    for i in range(7):
        step = torch.zeros(7, dtype=torch.float64)
        step[i] = h
        fd = (capsule_clearance(chain, q + step, world)[0] - capsule_clearance(chain, q - step, world)[0]) / (2 * h)
        # where a capsule is clear (inside a box the signed distance has kinks where faces meet)
        clear = distance > 0
        torch.testing.assert_close(gradient[..., i][clear], fd[clear], atol=1e-6, rtol=0)
    assert clear.sum() >= 18


def test_a_capsule_in_no_pair_reads_inf_with_a_zero_gradient():
    chain = robots.planar3r().__class__([(1.0, 0, 0, 0), (1.0, 0, 0, 0), (1.0, 0, 0, 0)], name="custom")
    caps = Capsules.build(chain, ["l1", "l2", "l3"], [1, 2, 3], [[[-1.0, 0, 0], [0, 0, 0]]] * 3, [0.1] * 3,
                          floor_height=None)
    q = torch.tensor([0.0, 0.3, -0.2], dtype=torch.float64)
    no_floor = World(floor=None)
    distance, gradient = capsule_clearance(chain, q, no_floor, caps)
    assert math.isinf(distance[1]) and not gradient[1].any()
    assert distance[0] == distance[2] == clearance(chain, q, no_floor, caps)


def _modified_arm():
    """A modified-DH arm (the lrmate's table) on a tilted base, with capsules of its own."""
    base = torch.eye(4, dtype=torch.float64)
    base[:3, :3] = so3.exp(torch.tensor([0.2, -0.1, 0.4], dtype=torch.float64))
    base[:3, 3] = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    chain = robots.lrmate200ic().__class__(robots.lrmate200ic().dh, convention="modified", base=base, name="mod")
    caps = Capsules.build(chain, ["base", "upper", "fore", "wrist"], [0, 2, 3, 6],
                          [[[0, 0, 0], [0, 0, 0.3]], [[0.3, 0, 0], [0, 0, 0]], [[0, 0, 0], [0.2, 0, 0.4]],
                           [[0, 0, -0.1], [0, 0, 0.05]]], [0.1, 0.07, 0.06, 0.05],
                          pairs=((0, 2), (0, 3), (1, 3)), floor=[False, True, True, True], floor_height=0.0)
    return chain, caps


@pytest.mark.parametrize("arm", ["iiwa14", "puma560", "lrmate200ic", "modified"])
def test_capsule_clearance_of_one_configuration_matches_the_batched_autograd(arm):
    """One CPU configuration against the floor and itself takes the closed-form gradient in Python
    floats: equal to the batched call's autograd (two configurations per call) to rounding, and to
    central finite differences of its own distances; float32 too. Configurations where two capsule
    axes cross (a zero segment gap: no gradient there, either path's direction is rounding) are left out."""
    if arm == "modified":
        chain, caps = _modified_arm()
    else:
        chain = getattr(robots, arm)()
        caps = robot_capsules(chain)
    q = chain.random_q(40, generator=torch.Generator().manual_seed(3))
    d_batch, g_batch = capsule_clearance(chain, q.view(20, 2, -1), capsules=caps)
    d_batch, g_batch = d_batch.reshape(40, -1), g_batch.reshape(40, -1, chain.n_joints)
    radii = caps.radii.tolist()
    gaps = pairwise_clearance(chain, q, World(floor=None), caps).distance  # the self pairs
    gaps = gaps + torch.tensor([radii[a] + radii[b] for a, b in caps.pairs], dtype=torch.float64)
    generic = (gaps > 1e-6).all(-1).nonzero().squeeze(-1).tolist()
    assert len(generic) >= 30
    h = 1e-6
    for i in generic:
        distance, gradient = capsule_clearance(chain, q[i], capsules=caps)
        torch.testing.assert_close(distance, d_batch[i], rtol=0, atol=1e-14)
        torch.testing.assert_close(gradient, g_batch[i], rtol=0, atol=1e-13)
        step = h * torch.eye(chain.n_joints, dtype=torch.float64)
        fd = (capsule_clearance(chain, q[i] + step, capsules=caps)[0]
              - capsule_clearance(chain, q[i] - step, capsules=caps)[0]) / (2 * h)  # (n, K) from the batched path
        torch.testing.assert_close(gradient, fd.T, rtol=0, atol=1e-6)
        d32, g32 = capsule_clearance(chain, q[i : i + 1].float(), capsules=caps)
        assert d32.dtype == g32.dtype == torch.float32 and d32.shape == (1, len(caps.names))
        torch.testing.assert_close(g32[0].double(), gradient, rtol=0, atol=1e-5)
