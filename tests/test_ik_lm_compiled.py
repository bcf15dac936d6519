"""The compiled path of ik.solve (iiwa_torch.ik.lm_compiled) against the batched torch loop.

Both run on the same targets (FK of random configurations within the limits, so reachable),
the batched loop forced by setting the threshold to 0; every answer is verified by its own
chain.fk and so3.pose_error, and its joints against the chain's float64 limits. Without numba
only the torch loop's tests run.
"""

import warnings

import numpy as np
import pytest
import torch

from iiwa_torch import compiled, robots, so3
from iiwa_torch.collision import World
from iiwa_torch.ik import lm, lm_compiled, lm_setup, solve

needs_numba = pytest.mark.skipif(not compiled.ENABLED, reason="numba not installed or IIWA_TORCH_NUMBA=0")

CHAINS = {"iiwa14": robots.iiwa14(), "puma560": robots.puma560(), "planar3r": robots.planar3r()}


def targets(chain, count, seed, dtype, mode):
    q = chain.random_q(count, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    pose = chain.fk(q).to(dtype)
    return (pose if mode == "pose" else pose[:, :3, 3]), q.to(dtype)


def in_chunks(chain, target, q0=None, **options):
    """solve on ``target`` in calls of at most lm_compiled.COMPILED_BATCH targets, concatenated."""
    size, rest = lm_compiled.COMPILED_BATCH, options.pop("rest", None)
    parts = [
        solve(chain, target[i : i + size], *(None if x is None else x[i : i + size] for x in (q0,)), **options,
              rest=None if rest is None else rest[i : i + size])
        for i in range(0, target.shape[0], size)
    ]  # fmt: skip
    return {k: torch.cat([getattr(p, k) for p in parts]) for k in ("q", "success", "pos_err", "rot_err")}


def batched(monkeypatch, chain, target, q0=None, **options):
    with monkeypatch.context() as m:
        m.setattr(lm_compiled, "COMPILED_BATCH", 0)
        return solve(chain, target, q0, **options)


def check_answers(chain, target, out, mode, pos_tol=1e-4, rot_tol=1e-3):
    """Errors recomputed from chain.fk(q) match the result's; success means both within tolerance."""
    pose = chain.fk(out["q"].double())
    if mode == "pose":
        pos_vec, rot_vec = so3.pose_error(pose, target.double())
    else:
        pos_vec, rot_vec = target.double() - pose[:, :3, 3], None
    pos_err = pos_vec.norm(dim=-1)
    rot_err = torch.zeros_like(pos_err) if rot_vec is None else rot_vec.norm(dim=-1)
    slack = 1e-5 if target.dtype == torch.float32 else 1e-9
    assert torch.allclose(out["pos_err"].double(), pos_err, atol=slack)
    assert torch.allclose(out["rot_err"].double(), rot_err, atol=10 * slack)
    ok = out["success"]
    assert bool((pos_err[ok] <= pos_tol + slack).all() and (rot_err[ok] <= rot_tol + 10 * slack).all())
    assert bool(chain.within_limits(out["q"].double()).all())


def agree(fast, slow, count):
    """The same success set, up to 0.5% of the targets (borderline cases of rounding)."""
    differ = int((fast["success"] != slow.success).sum())
    assert differ <= max(1, count // 200), f"{differ} of {count} targets differ in success"
    assert abs(int(fast["success"].sum()) - int(slow.success.sum())) <= max(1, count // 200)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("mode", ["pose", "position"])
@pytest.mark.parametrize("name", list(CHAINS))
def test_same_answers_as_the_batched_loop(monkeypatch, name, mode, dtype):
    chain = CHAINS[name]
    count = 128
    target, _ = targets(chain, count, 1, dtype, mode)
    fast = in_chunks(chain, target, mode=mode)
    slow = batched(monkeypatch, chain, target, mode=mode)
    check_answers(chain, target, fast, mode)
    agree(fast, slow, count)
    assert fast["success"].float().mean() > (0.95 if mode == "pose" else 0.99)
    both = fast["success"] & slow.success
    # the same seed converges in both (the same method): answers near each other
    assert (fast["q"][both] - slow.q[both]).abs().max() < 1e-2


def test_one_thousand_iiwa_poses(monkeypatch):
    chain = CHAINS["iiwa14"]
    target, _ = targets(chain, 1000, 2, torch.float64, "pose")
    fast = in_chunks(chain, target)
    slow = batched(monkeypatch, chain, target)
    check_answers(chain, target, fast, "pose")
    agree(fast, slow, 1000)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_q0_rest_and_options(monkeypatch, dtype):
    """A first seed (some angles a turn outside the limits), a rest posture, a rotation weight,
    fewer iterations and seeds; another damping schedule; tight tolerances iterated in the target's dtype."""
    chain = CHAINS["iiwa14"]
    target, q = targets(chain, 40, 3, dtype, "pose")
    gen = torch.Generator().manual_seed(4)
    q0 = q + 0.1 * torch.randn(q.shape, generator=gen, dtype=dtype)
    q0[::3, 0] += 2 * torch.pi
    options = dict(rest=q, rest_gain=0.1, rot_weight=0.5, seeds=3, iterations=12, check_every=3)
    # tolerances near float32's resolution only in float64: there the rounding of a float64
    # answer to float32 decides some borderline targets
    tight = {"pos_tol": 1e-6, "rot_tol": 1e-5, "precision": "input"}
    schedule = {"damping": 1e-3, "damping_down": 0.5, "damping_up": 4.0, "free_steps": 2}
    for extra in ({}, schedule, tight) if dtype == torch.float64 else ({}, schedule):
        fast = in_chunks(chain, target, q0, **options, **extra)
        slow = batched(monkeypatch, chain, target, q0, **options, **extra)
        check_answers(chain, target, fast, "pose", extra.get("pos_tol", 1e-4), extra.get("rot_tol", 1e-3))
        agree(fast, slow, 40)
        assert fast["success"].float().mean() > 0.75  # few seeds and iterations, a rest pull
    only_q0 = solve(chain, target[:5], q0[:5], seeds=1)  # no pool at all
    assert bool(only_q0.success.all())


@pytest.mark.parametrize("with_q0", [False, True])
def test_round_width_changes_no_answer(monkeypatch, with_q0):
    """The torch rounds with seeds side by side or one seed per round (as the compiled kernels
    run them; test_backends.py holds those to this): the same answers, as a problem's
    answer is its lowest-numbered converged seed; one seed per round spends fewer iterations.
    Out-of-reach targets and few iterations make later seeds run."""
    monkeypatch.setattr(compiled, "ENABLED", False)
    chain = CHAINS["iiwa14"]
    target, q = targets(chain, 30, 13, torch.float64, "pose")
    target[:3, :3, 3] *= 3.0
    q0 = q + 0.3 if with_q0 else None
    options = dict(iterations=6, seeds=5, precision="input")
    wide = solve(chain, target, q0, **options)
    with monkeypatch.context() as m:
        m.setattr(lm, "round_width", lambda *args: 1)
        narrow = solve(chain, target, q0, **options)
    # not bit for bit in torch: its vectorised sine and cosine round differently from the scalar tail
    assert (wide.q - narrow.q).abs().max() < 1e-9 and torch.equal(wide.success, narrow.success)
    assert bool((narrow.iterations <= wide.iterations).all()) and (narrow.iterations < wide.iterations).any()
    assert not wide.success[:3].any() and int(wide.success.sum()) > 20


@needs_numba
def test_shapes_and_iterations(monkeypatch):
    chain = CHAINS["iiwa14"]
    target, _ = targets(chain, 6, 5, torch.float64, "pose")
    fast = solve(chain, target.reshape(2, 3, 4, 4))
    slow = batched(monkeypatch, chain, target.reshape(2, 3, 4, 4))
    for field in ("q", "success", "pos_err", "rot_err", "iterations"):
        a, b = getattr(fast, field), getattr(slow, field)
        assert a.shape == b.shape and a.dtype == b.dtype, field
    assert bool((fast.iterations > 0).all())
    one = solve(chain, target[0])  # no batch dimension
    assert one.q.shape == (7,) and one.success.shape == ()


@pytest.fixture
def calls(monkeypatch):
    """How many times solve took the compiled path."""
    seen = []
    original = lm_compiled.solve_compiled

    def spy(*args, **kwargs):
        seen.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(lm_compiled, "solve_compiled", spy)
    return seen


@needs_numba
def test_which_path(calls):
    chain = CHAINS["iiwa14"]
    target, q = targets(chain, lm_compiled.COMPILED_BATCH + 1, 6, torch.float64, "pose")
    solve(chain, target[:3])
    assert len(calls) == 1
    solve(chain, target)  # above the threshold
    solve(chain, target[:3], world=World(floor=-1.0))  # a world
    solve(chain, target[:3].clone().requires_grad_(True))  # something to differentiate
    solve(chain, target[:3], q[:3].clone().requires_grad_(True))
    assert len(calls) == 1
    with torch.no_grad():  # requires_grad without grad mode: nothing to differentiate
        solve(chain, target[:3].clone().requires_grad_(True))
    assert len(calls) == 2


def test_exact_answer_is_finite():
    """q0 already at the target: zero errors, no 0/0 in the rotation angle. In float64 throughout
    (``precision="input"``: the torch path, without numba, otherwise iterates in float32)."""
    chain = CHAINS["iiwa14"]
    target, q = targets(chain, 2, 7, torch.float64, "pose")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        result = solve(chain, target, q, seeds=1, precision="input")
    assert bool(result.success.all()) and bool((result.rot_err < 1e-7).all())
    # a step may be kept on rounding alone (the compiled kernels' FK differs from chain.fk's in the last bits)
    assert (result.q - q).abs().max() < 1e-12


def test_bad_q0_and_rest_raise_as_before():
    chain = CHAINS["iiwa14"]
    target, q = targets(chain, 2, 8, torch.float64, "pose")
    with pytest.raises(TypeError, match="q0"):
        solve(chain, target, q.tolist())
    with pytest.raises(TypeError, match="rest"):
        solve(chain, target, rest=q.tolist(), rest_gain=0.1)
    with pytest.raises(ValueError, match="rest has no effect with rest_gain=0"):
        solve(chain, target, rest=q)


def test_default_pool_is_cached_per_geometry():
    """No generator: the pool of a fresh generator seeded with 0, computed once per chain geometry;
    an explicit such generator (never cached) gives the same answers, also after the limits change."""
    chain = robots.iiwa14()
    target, _ = targets(chain, 5, 12, torch.float64, "pose")
    for _ in range(2):
        cached = solve(chain, target)
        fresh = solve(chain, target, generator=torch.Generator().manual_seed(0))
        assert torch.equal(cached.q, fresh.q) and torch.equal(cached.iterations, fresh.iterations)
        with torch.no_grad():
            chain.limits.mul_(0.9)  # a new geometry: the pool is drawn again within the new limits
    assert bool(chain.within_limits(solve(chain, target).q).all())


@pytest.mark.parametrize("mode", ["pose", "position"])
def test_seed_ranks_in_numpy_as_in_torch(mode):
    """The pool's distances to the targets and their ranks by the numpy path's arrays (the small
    path's) and by torch tensors (the batched loop's): the same formula, the same ranks."""
    chain = CHAINS["iiwa14"]
    pool = chain.random_q(64, generator=torch.Generator().manual_seed(14), dtype=torch.float32)
    features = lm_setup.pool_features(chain, pool, mode)
    target, _ = targets(chain, 20, 15, torch.float32, mode)
    by_torch = lm_setup.pool_distance(chain, pool, target, mode, features)
    by_numpy = lm_setup.pool_distance(chain, pool, target.numpy(), mode, tuple(x.numpy() for x in features))
    assert isinstance(by_numpy, np.ndarray) and np.allclose(by_numpy, by_torch.numpy(), atol=1e-5, rtol=0)
    for count in (1, 5):
        assert np.array_equal(lm_setup.seed_ranks(by_numpy, count), lm_setup.seed_ranks(by_torch, count).numpy())
    # the definition: squared position distance plus 0.3^2 times the squared Frobenius rotation distance
    pose = chain.fk(pool).double()
    if mode == "pose":
        t = target.double()
        full = ((pose[:, None, :3, 3] - t[None, :, :3, 3]).square().sum(-1)
                + 0.09 * (pose[:, None, :3, :3] - t[None, :, :3, :3]).square().sum((-2, -1)))
    else:
        full = (pose[:, None, :3, 3] - target.double()[None]).square().sum(-1)
    assert np.array_equal(lm_setup.seed_ranks(by_numpy, 5), lm_setup.seed_ranks(full, 5).numpy())
