"""iiwa_solve's numpy path for small CPU batches against its batched torch path, on the same targets:
random reachable poses, unreachable ones, poses at joint limits and singular ones, float32 and float64.
Every test runs twice: with the compiled sweep (numba; skipped without it) and the numpy one."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import placed

from iiwa_torch import robots
from iiwa_torch.collision import World
from iiwa_torch.ik import analytic
from iiwa_torch.ik.analytic import srs_sweep

BATCH = min(64, srs_sweep.SOLVE_NUMPY_BATCH)  # poses per call, all on the numpy path


pytestmark = pytest.mark.usefixtures("small_kernel")  # every test twice: compiled and numpy


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


CHAINS = {"plain": robots.iiwa14(), "placed": placed(robots.iiwa14())}  # placed: base and tool stripped from the target


def _batched(chain, target, **kwargs):
    """The batched torch path: the numpy path switched off."""
    old = srs_sweep.SOLVE_NUMPY_BATCH, srs_sweep.SOLVE_COMPILED_BATCH
    srs_sweep.SOLVE_NUMPY_BATCH = srs_sweep.SOLVE_COMPILED_BATCH = 0
    try:
        return analytic.iiwa_solve(chain, target, **kwargs)
    finally:
        srs_sweep.SOLVE_NUMPY_BATCH, srs_sweep.SOLVE_COMPILED_BATCH = old


def _stable(chain, target, kwargs: dict, q_tol: float, ulps: float) -> torch.Tensor:
    """``(B,)`` bool: the batched path's answer moves by at most ``q_tol`` (and its success stays)
    when the target positions are scaled by ``1 +- ulps * eps``. Elsewhere (a near tie between
    candidates, a near-singular split of aligned joints) rounding alone picks the answer, and the
    numpy path, whose sin, cos and atan2 differ from torch's in the last bit, may pick another
    valid one."""
    ref = _batched(chain, target, **kwargs)
    ok = torch.ones(target.shape[0], dtype=torch.bool)
    for sign in (1, -1):
        moved = target.clone()
        moved[:, :3, 3] *= 1 + sign * ulps * torch.finfo(target.dtype).eps
        out = _batched(chain, moved, **kwargs)
        ok &= ((out.q - ref.q).abs().amax(-1) <= q_tol) & (out.success == ref.success)
    return ok


def _assert_valid(chain, result, target) -> None:
    """Answers within the limits whose success is what their FK error says."""
    assert chain.within_limits(result.q).all()
    ok = (result.pos_err <= 1e-4) & (result.rot_err <= 1e-3)
    assert torch.equal(ok, result.success)


def _assert_same(fast, slow, q_tol: float, err_tol: float, q_mask=None) -> None:
    """Every field of two IKResults: q within ``q_tol`` rad and the same success (where ``q_mask``),
    errors within ``err_tol`` (where both succeed)."""
    for name in ("q", "success", "pos_err", "rot_err", "iterations"):
        a, b = getattr(fast, name), getattr(slow, name)
        assert a.dtype == b.dtype and a.shape == b.shape and a.device == b.device, name
    assert fast.clearance is None and slow.clearance is None
    assert torch.equal(fast.iterations, slow.iterations)
    mask = torch.ones(fast.q.shape[:-1], dtype=torch.bool) if q_mask is None else q_mask
    assert torch.equal(fast.success[mask], slow.success[mask])
    diff = (fast.q - slow.q).abs().amax(-1)[mask]
    assert diff.max().item() <= q_tol, f"{diff.max().item():.3g} rad at {diff.argmax().item()}"
    both = mask & fast.success & slow.success
    for a, b in ((fast.pos_err, slow.pos_err), (fast.rot_err, slow.rot_err)):
        assert torch.all((a - b)[both].abs() <= err_tol)


def _at_limits(chain, n: int, gen) -> torch.Tensor:
    """Configurations with 1-3 joints exactly at a limit (either side)."""
    q = chain.random_q(n, generator=gen)
    lo, hi = chain.limits
    for row in range(n):
        joints = torch.randperm(7, generator=gen)[: 1 + row % 3]
        side = torch.rand(len(joints), generator=gen) < 0.5
        q[row, joints] = torch.where(side, lo[joints], hi[joints])
    return q


def _singular(chain, n: int, gen) -> torch.Tensor:
    """Wrist aligned (q6 = 0), shoulder aligned (q2 = 0), arm stretched (q4 = 0), and the wrist centre
    straight above the shoulder (q2 chosen for it), in turn, the other joints random."""
    q = chain.random_q(n, generator=gen)
    d3, d5 = float(chain.dh[2, 2]), float(chain.dh[4, 2])
    for row in range(n):
        kind = row % 4
        if kind == 0:
            q[row, 5] = 0.0
        elif kind == 1:
            q[row, 1] = 0.0
        elif kind == 2:
            q[row, 3] = 0.0
        else:  # planar arm (q3 = 0): the wrist at angle q2 - atan2(d5 sin q4, d3 + d5 cos q4) off the z axis
            q[row, 2] = 0.0
            q4 = float(q[row, 3])
            q[row, 1] = math.atan2(d5 * math.sin(q4), d3 + d5 * math.cos(q4))
    return q


def _wrist_xy(chain, q: torch.Tensor) -> torch.Tensor:
    frames = chain.fk_all(q)
    return frames[..., 5, :2, 3] - frames[..., 0, :2, 3]


def test_the_vertical_shoulder_wrist_line_is_built():
    """The test's singular set really puts the wrist centre above the shoulder (every 4th pose)."""
    chain = robots.iiwa14()
    q = _singular(chain, 8, _gen(0))
    assert _wrist_xy(chain, q[3::4]).abs().max() < 1e-12
    assert q[0::4, 5].eq(0).all() and q[1::4, 1].eq(0).all() and q[2::4, 3].eq(0).all()


def _unreachable(chain, n: int, gen) -> torch.Tensor:
    """FK poses moved out of reach: the position 1.2-1.8 m from the shoulder, in its direction
    (the wrist centre reaches 0.82 m, the flange 0.126 m beyond, the test tool 0.1 m more)."""
    target = chain.fk(chain.random_q(n, generator=gen))
    shoulder = chain.fk_all(torch.zeros(7, dtype=torch.float64))[1, :3, 3]
    offset = target[:, :3, 3] - shoulder
    reach = 1.2 + 0.6 * torch.rand(n, 1, generator=gen, dtype=torch.float64)
    target[:, :3, 3] = shoulder + reach * offset / offset.norm(dim=-1, keepdim=True)
    return target


CASES = ["random", "unreachable", "limits", "singular"]


def _targets(chain, case: str, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(target (BATCH, 4, 4), q (BATCH, 7))`` float64: a pose set and configurations near it (q0)."""
    gen = _gen(seed)
    if case == "unreachable":
        target = _unreachable(chain, BATCH, gen)
        return target, chain.random_q(BATCH, generator=gen)
    q = {"random": chain.random_q, "limits": _at_limits, "singular": _singular}[case]
    q = q(BATCH, generator=gen) if case == "random" else q(chain, BATCH, gen)
    noise = 0.05 * (2 * torch.rand(BATCH, 7, generator=gen, dtype=torch.float64) - 1)
    return chain.fk(q), chain.clamp(q + noise)


@pytest.mark.parametrize("chain_name", list(CHAINS))
@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("with_q0", [False, True])
def test_numpy_path_matches_the_batched_path_float64(chain_name, case, with_q0):
    """q within 1e-9 rad and the same success everywhere on random and unreachable poses; on poses at
    limits and singular ones, the same success everywhere and q within 1e-9 rad wherever the batched
    path's own answer is stable under a 2-ulp change of the target (most poses), a valid answer elsewhere."""
    chain = CHAINS[chain_name]
    stable_count = 0
    for seed in range(3):
        target, q0 = _targets(chain, case, 100 * seed + CASES.index(case))
        kwargs = {"q0": q0} if with_q0 else {}
        fast, slow = analytic.iiwa_solve(chain, target, **kwargs), _batched(chain, target, **kwargs)
        mask = None if case in ("random", "unreachable") else _stable(chain, target, kwargs, 1e-9, 2)
        _assert_same(fast, slow, q_tol=1e-9, err_tol=1e-12, q_mask=mask)
        _assert_valid(chain, fast, target)
        stable_count += BATCH if mask is None else int(mask.sum())
        if case == "unreachable":
            assert not fast.success.any()
        elif case != "limits":  # at a limit, the feasible arm angles may be too few for the grid
            assert fast.success.all()
    assert stable_count >= 0.7 * 3 * BATCH


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("with_q0", [False, True])
def test_numpy_path_matches_the_batched_path_float32(case, with_q0):
    """float32 targets: the numpy path computes in float64 and returns float32, the batched path
    computes in float32. The same success and the same answer up to float32 rounding (random poses,
    poses at limits) where the batched path's answer is stable (judged as for float64, with 2 float32
    ulps), and valid answers everywhere."""
    chain = CHAINS["plain"]
    for seed in range(3):
        target, q0 = _targets(chain, case, 100 * seed + CASES.index(case) + 7)
        target, q0 = target.float(), q0.float()
        kwargs = {"q0": q0} if with_q0 else {}
        fast, slow = analytic.iiwa_solve(chain, target, **kwargs), _batched(chain, target, **kwargs)
        mask = _stable(chain, target, kwargs, 1e-3, 2)
        # out of reach and at singular poses a float32 ranking of candidates is decided by its rounding
        q_tol = 1e-3 if case in ("random", "limits") else 2 * math.pi
        _assert_same(fast, slow, q_tol=q_tol, err_tol=2e-5, q_mask=mask)
        _assert_valid(chain, fast, target)
        if case == "random":
            assert mask.float().mean() >= 0.9 and fast.success.all()


def test_numpy_path_matches_on_stretched_targets():
    """Targets a rounding error beyond full stretch (scaled by 1 + 1e-12) and well beyond (1 + 1e-3)."""
    chain = CHAINS["plain"]
    q = chain.random_q(BATCH, generator=_gen(5))
    q[:, 3] = 0.0
    target = chain.fk(q)
    shoulder = chain.fk_all(torch.zeros(7, dtype=torch.float64))[1, :3, 3]
    for scale in (1 + 1e-12, 1 + 1e-3):
        stretched = target.clone()
        stretched[:, :3, 3] = shoulder + scale * (target[:, :3, 3] - shoulder)
        fast, slow = analytic.iiwa_solve(chain, stretched), _batched(chain, stretched)
        _assert_same(fast, slow, q_tol=1e-9, err_tol=1e-12)


def test_numpy_path_keeps_leading_shapes_and_broadcast_q0():
    chain = CHAINS["plain"]
    q = chain.random_q(2, 3, generator=_gen(6))
    target = chain.fk(q)
    for q0 in (None, q[0, 0], q):
        fast, slow = analytic.iiwa_solve(chain, target, q0=q0), _batched(chain, target, q0=q0)
        assert fast.q.shape == (2, 3, 7) and fast.success.shape == (2, 3)
        _assert_same(fast, slow, q_tol=1e-9, err_tol=1e-12)
    one = analytic.iiwa_solve(chain, target[0, 0])  # a single (4, 4) pose
    assert one.q.shape == (7,) and one.success.shape == ()
    _assert_same(one, _batched(chain, target[0, 0]), q_tol=1e-9, err_tol=1e-12)


def test_numpy_path_with_few_arm_angles_and_the_fine_retry():
    """num_psi = 1: most poses find no valid candidate on the first sweep and take the retry."""
    chain = CHAINS["plain"]
    target, q0 = _targets(chain, "random", 11)
    for kwargs in ({}, {"q0": q0}):
        fast = analytic.iiwa_solve(chain, target, num_psi=1, **kwargs)
        slow = _batched(chain, target, num_psi=1, **kwargs)
        _assert_same(fast, slow, q_tol=1e-9, err_tol=1e-12)


def test_gradients_still_flow_where_asked():
    """A target or q0 that requires grad takes the batched path: q is differentiable as before."""
    chain = CHAINS["plain"]
    q = chain.random_q(3, generator=_gen(7))
    target = chain.fk(q).requires_grad_()
    out = analytic.iiwa_solve(chain, target)
    assert out.q.requires_grad
    (grad,) = torch.autograd.grad(out.q.sum(), target)
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0
    q0 = q.clone().requires_grad_()
    assert analytic.iiwa_solve(chain, chain.fk(q), q0=q0).q.requires_grad
    with torch.no_grad():  # nothing to differentiate: the numpy path, same answer
        fast = analytic.iiwa_solve(chain, target)
    assert not fast.q.requires_grad
    _assert_same(fast, _batched(chain, target.detach()), q_tol=1e-9, err_tol=1e-12)


def test_a_world_takes_the_batched_path_with_the_same_answers():
    chain = CHAINS["plain"]
    q = chain.random_q(4, generator=_gen(8))
    world = World(floor=0.0)
    out = analytic.iiwa_solve(chain, chain.fk(q), world=world, margin=0.01)
    ref = _batched(chain, chain.fk(q), world=world, margin=0.01)
    assert out.clearance is not None and torch.equal(out.q, ref.q) and torch.equal(out.success, ref.success)


def test_input_checks_are_unchanged_on_small_batches():
    chain = CHAINS["plain"]
    target = chain.fk(chain.random_q(2, generator=_gen(9)))
    bad = target.clone()
    bad[0, :3, :3] *= 2.0
    with pytest.raises(ValueError, match="rigid"):
        analytic.iiwa_solve(chain, bad)
    with pytest.raises(ValueError, match="broadcast"):
        analytic.iiwa_solve(chain, target, q0=torch.zeros(3, 7, dtype=torch.float64))
    with pytest.raises(ValueError, match="num_psi"):
        analytic.iiwa_solve(chain, target, num_psi=0)
    with pytest.raises(ValueError, match="iiwa"):
        analytic.iiwa_solve(robots.puma560(), target[:, :, :])
    empty = analytic.iiwa_solve(chain, target[:0])
    assert empty.q.shape == (0, 7) and empty.success.shape == (0,)
