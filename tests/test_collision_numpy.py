"""The paths clearance takes without autograd on the CPU against its torch path (itself tested
against coal in test_collision.py), which runs whenever something requires grad: for small batches
the own distances compiled (numba; without it torch's) and the spheres and boxes in numpy, for
larger ones the compiled kernel against the floor alone, both with numba on and off
(``small_kernel``: off, the larger batches take the torch path)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from iiwa_torch import collision, compiled, robots, runtime
from iiwa_torch.collision import CLEARANCE_NUMPY_BATCH, World, clearance, robot_capsules
from iiwa_torch.dh import DHChain

PRESETS = sorted(robots.PRESETS)


@pytest.fixture
def numpy_calls(monkeypatch):
    """Counts the calls of the small-batch path (each call's number of configurations), to tell
    which path a query took."""
    calls = []
    real = collision.cpu_paths._clearance_small

    def spy(chain, q, world, capsules):
        calls.append(q.numel() // chain.n_joints)
        return real(chain, q, world, capsules)

    monkeypatch.setattr(collision.cpu_paths, "_clearance_small", spy)
    return calls


def _torch_path(chain, q, world=None, capsules=None):
    return clearance(chain, q.clone().requires_grad_(), world, capsules).detach()


def _configurations(chain, n: int, rng: np.random.Generator) -> torch.Tensor:
    """n random configurations within the limits, a tenth of them at zero or multiples of
    pi/2 (straight arms: parallel and collinear capsules)."""
    low, high = chain.limits.double().numpy()
    q = rng.uniform(low, high, size=(n, chain.n_joints))
    straight = rng.random(n) < 0.1
    q[straight] = np.clip(rng.integers(-1, 2, size=(straight.sum(), chain.n_joints)) * math.pi / 2, low, high)
    return torch.from_numpy(q)


def _spheres_touching(chain, q: torch.Tensor) -> World:
    """Spheres per configuration: one centred on the wrist capsule's start, one tangent to the
    floor, one far away (a degenerate point-on-segment case, a touching one and a generic one)."""
    caps = robot_capsules(chain)
    frame = chain.fk_all(q)[:, caps.frames[-1]]  # (B, 4, 4)
    on_axis = frame[:, :3, 3] + frame[:, :3, :3] @ caps.points[-1, 0]
    b = q.shape[0]
    centres = torch.stack(
        [
            on_axis,
            torch.tensor([0.5, 0.2, 0.1], dtype=q.dtype).expand(b, 3),
            q.new_tensor([2.0, 2.0, 2.0]).expand(b, 3),
        ],
        1,
    )
    radii = q.new_tensor([0.05, 0.1, 0.3]).expand(b, 3)
    return World(floor=0.0, spheres=(centres, radii))


@pytest.mark.parametrize("name", PRESETS)
def test_numpy_path_equals_torch_path_floor_and_spheres(name, small_kernel, numpy_calls):
    chain = robots.PRESETS[name]()
    rng = np.random.default_rng(7)
    q = _configurations(chain, 3000, rng)
    shared = World(
        floor=-0.05,
        spheres=(torch.from_numpy(rng.uniform(-0.8, 0.8, (4, 3))), torch.from_numpy(rng.uniform(0.05, 0.2, 4))),
    )
    for world in (None, World(floor=0.4), shared, _spheres_touching(chain, q)):
        want = _torch_path(chain, q, world)
        assert not numpy_calls
        got = []
        for start in range(0, len(q), CLEARANCE_NUMPY_BATCH):
            rows = slice(start, start + CLEARANCE_NUMPY_BATCH)
            sub = world.map_batch(lambda t, k, rows=rows: t[rows]) if world is not None and world.batch_shape else world
            got.append(clearance(chain, q[rows], sub))
        got = torch.cat(got)
        assert len(numpy_calls) == len(got) // CLEARANCE_NUMPY_BATCH + (len(got) % CLEARANCE_NUMPY_BATCH > 0)
        numpy_calls.clear()
        assert got.dtype == torch.float64 and got.shape == want.shape
        assert torch.allclose(got, want, rtol=0, atol=1e-12), (got - want).abs().max()
    # one configuration, and a batch shape: the shape of the torch path
    for qq in (q[0], q[:6].reshape(2, 3, -1)):
        assert torch.allclose(clearance(chain, qq, shared), _torch_path(chain, qq, shared), rtol=0, atol=1e-12)
    assert clearance(chain, q[0], shared).shape == ()


def test_world_batch_broadcasts_like_the_torch_path(numpy_calls):
    chain = robots.iiwa14()
    q = _configurations(chain, 8, np.random.default_rng(1)).reshape(1, 8, 7)
    world = World(
        spheres=(torch.rand(3, 1, 2, 3, dtype=torch.float64), torch.full((3, 1, 2), 0.1, dtype=torch.float64))
    )
    got = clearance(chain, q, world)
    assert numpy_calls and got.shape == (3, 8)
    assert torch.allclose(got, _torch_path(chain, q, world), rtol=0, atol=1e-12)


def test_float32_query_returns_float32_close_to_float64(numpy_calls):
    chain = robots.iiwa14().float()
    q = _configurations(chain, 32, np.random.default_rng(2))
    world = World(spheres=(torch.tensor([[0.5, 0.0, 0.6]]), torch.tensor([0.1])))
    got = clearance(chain, q.float(), world)
    assert numpy_calls and got.dtype == torch.float32
    reference = _torch_path(robots.iiwa14(), q, World(spheres=tuple(t.double() for t in world.spheres)))
    assert torch.allclose(got.double(), reference, rtol=0, atol=1e-6)
    assert torch.allclose(got, _torch_path(chain, q.float(), world), rtol=0, atol=1e-4)


def test_the_torch_path_keeps_what_the_numpy_path_does_not_cover(numpy_calls):
    chain = robots.iiwa14()
    q = _configurations(chain, CLEARANCE_NUMPY_BATCH + 1, np.random.default_rng(3))
    clearance(chain, q)  # above the threshold
    wall = World(
        walls=(torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64), torch.tensor([-1.0], dtype=torch.float64))
    )
    pipe = World(capsules=(torch.tensor([[[0.5, 0.0, 0.0], [0.5, 0.0, 1.0]]], dtype=torch.float64),
                           torch.tensor([0.05], dtype=torch.float64)))
    for world in (wall, pipe):
        clearance(chain, q[:4], world)
        clearance(chain, q[0], world)
    with torch.no_grad():  # grad mode off: nothing to differentiate, numpy
        clearance(chain, q[:4].clone().requires_grad_())
        clearance(chain, q[0].clone().requires_grad_())
    assert numpy_calls == [4, 1]


def _boxes_around(chain, q: torch.Tensor, rng: np.random.Generator) -> World:
    """Per configuration, three yawed and tilted boxes: one centred on the elbow capsule's start
    (the segment inside: the penetration case) in a quarter of them, else 0.3 m off it in a
    random direction; one beside the wrist; one far away."""
    caps = robot_capsules(chain)
    b = q.shape[0]
    frames = chain.fk_all(q)[:, list(caps.frames)]  # (B, K, 4, 4)
    on_axis = frames[:, 2, :3, 3] + frames[:, 2, :3, :3] @ caps.points[2, 0]
    off = torch.from_numpy(rng.normal(size=(b, 3)))
    off = 0.3 * off / off.norm(dim=-1, keepdim=True) * torch.from_numpy(rng.random((b, 1)) > 0.25)
    on_axis = on_axis + off
    beside = frames[:, 3, :3, 3] + q.new_tensor([0.22, 0.0, 0.0])
    centres = torch.stack([on_axis, beside, q.new_tensor([1.5, -1.5, 0.5]).expand(b, 3)], 1)  # (B, 3, 3)
    yaw = torch.from_numpy(rng.uniform(-math.pi, math.pi, (b, 3)))
    tilt = torch.from_numpy(rng.uniform(-0.5, 0.5, (b, 3)))
    rz, rx = torch.zeros(b, 3, 3, 3, dtype=q.dtype), torch.zeros(b, 3, 3, 3, dtype=q.dtype)
    rz[..., 0, 0], rz[..., 0, 1], rz[..., 1, 0], rz[..., 1, 1], rz[..., 2, 2] = yaw.cos(), -yaw.sin(), yaw.sin(), \
        yaw.cos(), 1.0
    rx[..., 0, 0], rx[..., 1, 1], rx[..., 1, 2], rx[..., 2, 1], rx[..., 2, 2] = 1.0, tilt.cos(), -tilt.sin(), \
        tilt.sin(), tilt.cos()
    pose = torch.zeros(b, 3, 4, 4, dtype=q.dtype)
    pose[..., :3, :3], pose[..., :3, 3], pose[..., 3, 3] = rz @ rx, centres, 1.0
    half = torch.from_numpy(rng.uniform(0.02, 0.12, (b, 3, 3)))
    return World(floor=0.0, boxes=(pose, half), spheres=(centres[:, 1:] + 0.1, q.new_full((b, 2), 0.05)))


@pytest.mark.parametrize("name", ["iiwa14", "puma560"])
def test_numpy_path_equals_torch_path_with_boxes(name, small_kernel, numpy_calls):
    """Boxes (with spheres and the floor) per configuration, in batches and one by one: the torch
    path's values to 1e-12 m."""
    chain = robots.PRESETS[name]()
    rng = np.random.default_rng(5)
    q = _configurations(chain, 640, rng)
    world = _boxes_around(chain, q, rng)
    want = _torch_path(chain, q, world)
    assert not numpy_calls and (want < 0).any() and (want > 0).any()
    got = torch.cat([clearance(chain, q[i : i + CLEARANCE_NUMPY_BATCH], world.map_batch(
        lambda t, k, i=i: t[i : i + CLEARANCE_NUMPY_BATCH])) for i in range(0, len(q), CLEARANCE_NUMPY_BATCH)])
    one = torch.stack([clearance(chain, q[i], world.map_batch(lambda t, k, i=i: t[i])) for i in range(len(q))])
    assert numpy_calls == [CLEARANCE_NUMPY_BATCH] * (len(q) // CLEARANCE_NUMPY_BATCH) + [1] * len(q)
    for values in (got, one):
        assert values.dtype == torch.float64 and values.shape == want.shape
        assert torch.allclose(values, want, rtol=0, atol=1e-12), (values - want).abs().max()


def test_gradients_take_the_torch_path():
    chain = robots.iiwa14()
    q = torch.tensor([0.1, 0.9, -0.2, -1.2, 0.3, 0.4, 0.0], dtype=torch.float64, requires_grad=True)
    centre = torch.tensor([[0.45, 0.05, 0.55]], dtype=torch.float64, requires_grad=True)
    radius = torch.tensor([0.1], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda x: clearance(chain, x), (q,))
    assert torch.autograd.gradcheck(lambda c: clearance(chain, q.detach(), World(spheres=(c, radius))), (centre,))
    d = clearance(chain, q.detach(), World(spheres=(centre, radius)))
    assert d.requires_grad  # only the world's tensor requires grad


def test_the_shared_model_first_used_in_inference_mode_still_differentiates(monkeypatch):
    """robot_capsules returns one shared model per chain: tables it first builds under
    torch.inference_mode (as the envs' steps do) must not leak inference tensors into autograd."""
    monkeypatch.setattr(compiled, "ENABLED", False)  # the torch path builds the float32 tables
    chain = robots.puma560().float()
    q = _configurations(chain, 40, np.random.default_rng(4)).float()
    with torch.inference_mode():
        caps = robot_capsules(chain)
        first = clearance(chain, q, World(), caps)  # builds the float32 tables (torch path: 40 > 32)
    other = robots.puma560().float()  # another chain object (its own FK caches), the same model
    assert robot_capsules(other) is caps
    x = q.clone().requires_grad_()
    d = clearance(other, x, World(), robot_capsules(other))
    d.sum().backward()
    assert torch.isfinite(x.grad).all() and torch.allclose(d.detach(), first)


@pytest.fixture
def compiled_calls(monkeypatch):
    """The batch sizes the compiled path of clearance ran, to tell which path a query took."""
    calls = []
    real = collision.cpu_paths._clearance_compiled

    def spy(chain, q, world, capsules):
        calls.append(q.numel() // chain.n_joints)
        return real(chain, q, world, capsules)

    monkeypatch.setattr(collision.cpu_paths, "_clearance_compiled", spy)
    return calls


def _modified_with_base() -> tuple[DHChain, collision.Capsules]:
    """The LR Mate in the modified convention on a turned, raised base, with its preset's capsules
    (sized from the same DH table, so they sit elsewhere on the arm: any segments do)."""
    lr = robots.lrmate200ic()
    base = torch.eye(4, dtype=torch.float64)
    base[:2, :2] = torch.tensor([[math.cos(0.7), -math.sin(0.7)], [math.sin(0.7), math.cos(0.7)]])
    base[:3, 3] = torch.tensor([0.1, -0.2, 0.3])
    chain = DHChain(lr.dh, convention="modified", base=base, limits=lr.limits)
    return chain, robot_capsules(lr)


@pytest.mark.parametrize("name", [*PRESETS, "modified_with_base"])
def test_large_batches_equal_the_torch_path(name, small_kernel, compiled_calls):
    """3,000 configurations (a tenth with straight arms: parallel and collinear capsules) against
    the floor at 0 (some colliding) and at 0.4 m (deep), and self pairs alone, in float64 to 1e-12 m
    and float32 to 1e-5 m; compiled when numba is on, else the torch path."""
    chain, caps = _modified_with_base() if name == "modified_with_base" else (robots.PRESETS[name](), None)
    caps = caps or robot_capsules(chain)
    q = _configurations(chain, 3000, np.random.default_rng(11))
    worlds = [World(floor=0.0), World(floor=0.4), World(floor=None)]
    want = torch.stack([_torch_path(chain, q, world, caps) for world in worlds])
    assert (want < 0).any(0).any() and (want > 0).any(0).any()
    for world in worlds:
        for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 1e-5)):
            got = clearance(chain, q.to(dtype), world, caps)
            reference = _torch_path(chain, q.to(dtype), world, caps)
            assert got.dtype == dtype and got.shape == (3000,)
            assert torch.allclose(got, reference, rtol=0, atol=tol), (dtype, (got - reference).abs().max())
    assert compiled_calls == ([3000] * 2 * len(worlds) if small_kernel == "compiled" else [])


def test_large_batches_take_any_layout_and_angle(small_kernel, compiled_calls):
    """Leading batch dims, a transposed (batch-last) view, angles far outside the limits (the
    kernel's own sine and cosine below 1e5 rad, libm's above) and a ``requires_grad`` tensor under
    ``no_grad``: the torch path's values; obstacles besides the floor: the torch path."""
    chain = robots.iiwa14()
    q = _configurations(chain, 1000, np.random.default_rng(12))
    turns = torch.from_numpy(np.random.default_rng(13).integers(-3000, 3000, q.shape)) * (2 * math.pi)
    for x in (q.reshape(10, 100, 7), q.T.contiguous().T, q + turns, q + 1e3 * turns):
        assert torch.allclose(clearance(chain, x), _torch_path(chain, x), rtol=0, atol=1e-12)
    assert clearance(chain, q.reshape(10, 100, 7)).shape == (10, 100)
    want = _torch_path(chain, q)
    with torch.no_grad():
        assert torch.allclose(clearance(chain, q.clone().requires_grad_()), want, rtol=0, atol=1e-12)
    assert compiled_calls == ([1000] * 6 if small_kernel == "compiled" else [])
    compiled_calls.clear()
    spheres = World(spheres=(torch.tensor([[0.5, 0.0, 0.5]], dtype=torch.float64), torch.tensor([0.1]).double()))
    clearance(chain, q, spheres)
    clearance(chain, q.clone().requires_grad_())
    assert not compiled_calls


def _many_pairs() -> tuple[DHChain, collision.Capsules]:
    """The iiwa 14 with its preset capsules and a point (a zero-length capsule) on each of links 3 to
    7: many self pairs, some of them point-point and point-segment, whose bounds are exact."""
    chain = robots.iiwa14()
    caps = robot_capsules(chain)
    points = torch.cat([caps.points, torch.tensor([[[0.0, 0.05, 0.0]] * 2] * 5, dtype=torch.float64)])
    frames = (*caps.frames, 3, 4, 5, 6, 7)
    names = (*caps.names, "dot3", "dot4", "dot5", "dot6", "dot7")
    radii = torch.cat([caps.radii, torch.full((5,), 0.04, dtype=torch.float64)])
    floor = torch.cat([caps.floor, torch.zeros(5, dtype=torch.bool)])  # the preset's floor checks
    return chain, collision.Capsules.build(chain, names, frames, points, radii, floor=floor)


def test_large_batches_with_many_pairs_equal_the_torch_path(small_kernel, compiled_calls):
    """The compiled kernel computes a pair's exact distance only where its mid-point bounds let it be
    the minimum (clearance_kernels.own_clearance): with many pairs, points among them, the minimum of
    every pair all the same (the torch path computes each), in blocks of any fill."""
    chain, caps = _many_pairs()
    assert len(caps.pairs) > 15
    q = _configurations(chain, 3000 + 37, np.random.default_rng(14))
    for world in (World(floor=0.0), World(floor=None)):
        got, want = clearance(chain, q, world, caps), _torch_path(chain, q, world, caps)
        assert (want < 0).any() and (want > 0).any()
        assert torch.allclose(got, want, rtol=0, atol=1e-12), (got - want).abs().max()


@pytest.mark.parametrize("world", [World(floor=0.0), None])
def test_an_empty_batch_has_an_empty_clearance(small_kernel, world):
    """Zero configurations (a filter that kept none): an empty answer on every path, as torch's."""
    chain = robots.iiwa14().double()
    q = torch.zeros(0, chain.n_joints, dtype=torch.float64)
    assert clearance(chain, q, world).shape == (0,)
    assert _torch_path(chain, q, world).shape == (0,)


@pytest.mark.skipif(not compiled.ENABLED, reason="the compiled kernels are off (no numba, or IIWA_TORCH_NUMBA=0)")
@pytest.mark.parametrize("size", [8, 3000 + 37])
def test_threads_split_a_large_batch_without_changing_it(monkeypatch, size):
    """From ``CLEARANCE_THREADS_BATCH`` configurations the compiled self + floor clearance runs one
    part of the batch per torch thread (the kernel releases the GIL): bit for bit the answer of one
    call, with parts of unequal size, and the threads were used."""
    chain, caps = _many_pairs()
    q = _configurations(chain, size, np.random.default_rng(15))
    world = World(floor=0.0)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = clearance(chain, q, world, caps)
        monkeypatch.setattr(collision.cpu_paths, "CLEARANCE_THREADS_BATCH", 1)
        pool_sizes = []
        real = runtime.thread_pool

        def spy(n, pid):
            pool_sizes.append(n)
            return real(n, pid)

        monkeypatch.setattr(runtime, "thread_pool", spy)
        torch.set_num_threads(3)
        split = clearance(chain, q, world, caps)
    finally:
        torch.set_num_threads(threads)
    assert pool_sizes == [3] and torch.equal(split, one)


@pytest.mark.skipif(not compiled.ENABLED, reason="the compiled kernels are off (no numba, or IIWA_TORCH_NUMBA=0)")
def test_a_forked_process_splits_with_threads_of_its_own(monkeypatch):
    """A process forked after the split has run (its thread pool built) has none of those threads:
    it builds its own pool and returns the same answer instead of waiting forever."""
    import multiprocessing

    chain, caps = _many_pairs()
    q = _configurations(chain, 64, np.random.default_rng(16))
    monkeypatch.setattr(collision.cpu_paths, "CLEARANCE_THREADS_BATCH", 1)
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        want = clearance(chain, q, World(floor=0.0), caps)  # builds this process's pool
        _FORKED.update(chain=chain, caps=caps, q=q)  # the child inherits them: nothing to pickle
        with multiprocessing.get_context("fork").Pool(1) as pool:
            got = pool.apply_async(_clearance_in_child).get(timeout=120)
    finally:
        torch.set_num_threads(threads)
        _FORKED.clear()
    assert np.array_equal(got, want.numpy())


_FORKED: dict = {}


def _clearance_in_child():
    torch.set_num_threads(2)
    return clearance(_FORKED["chain"], _FORKED["q"], World(floor=0.0), _FORKED["caps"]).numpy()
