"""pieper's numpy path for small CPU batches against its batched torch path, on the same targets:
random poses, unreachable ones, configurations at joint limits and singular ones (wrist aligned,
arm stretched, wrist centre on the shoulder cylinder), PUMA 560 and LR Mate (with a base and a
tool), float32 and float64."""

from __future__ import annotations

import pytest
import torch
from conftest import placed

from iiwa_torch import robots, so3
from iiwa_torch.collision import World
from iiwa_torch.ik import analytic
from iiwa_torch.ik.analytic import spherical6r
from iiwa_torch.so3 import pose_error

BATCH = min(64, spherical6r.PIEPER_NUMPY_BATCH)  # poses per call, all on the numpy path
F64 = torch.float64


pytestmark = pytest.mark.usefixtures("small_kernel")  # every test twice: compiled and numpy


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


CHAINS = {"puma560": robots.puma560(), "lrmate_placed": placed(robots.lrmate200ic())}


def _batched(chain, target, **kwargs):
    """The batched torch path: the numpy path switched off."""
    old = spherical6r.PIEPER_NUMPY_BATCH
    spherical6r.PIEPER_NUMPY_BATCH = 0
    try:
        return analytic.pieper(chain, target, **kwargs)
    finally:
        spherical6r.PIEPER_NUMPY_BATCH = old


FLAGS = ("valid", "reachable", "within_limits")


def _stable(chain, target, q_tol: float, ulps: float) -> torch.Tensor:
    """``(B, 8)`` bool: branches that rounding does not decide. The batched path's branch moves by at
    most ``q_tol`` and keeps its flags when the target positions are scaled by ``1 +- ulps * eps``, and
    none of its joints is within ``q_tol`` of a limit, also a turn away (a joint whose limits span more
    than ``[-pi, pi]`` is shifted by 2 pi into them when that fits, so an angle far from a limit can be
    a turn from it), or of +-pi (where the wrap into ``[-pi, pi]`` picks a side), nor does it move by
    ``q_tol`` when the target turns by ``ulps * eps`` (rad), nor is the wrist so
    near alignment that rounding moves the split of q4 and q6 by ``q_tol`` (``|sin theta5| <= 100 eps /
    q_tol``). Elsewhere the numpy path, whose sin, cos, atan2 and sqrt differ from torch's in the last
    bit or two (how much depends on the CPU's vector kernels), may decide otherwise."""
    ref = _batched(chain, target)
    q = ref.q.double()
    ok = torch.ones(q.shape[:-1], dtype=torch.bool)
    for limit in chain.limits.double():
        gap = torch.remainder(q - limit, 2 * torch.pi)  # distance to the nearest turn of the limit
        ok &= torch.minimum(gap, 2 * torch.pi - gap).amin(-1) > q_tol
    ok &= (q.abs() - torch.pi).abs().amin(-1) > q_tol
    ok &= (q[..., 4] + chain.dh[4, 3]).sin().abs() > 100 * torch.finfo(target.dtype).eps / q_tol
    eps = torch.finfo(target.dtype).eps
    turn = so3.exp(torch.tensor([1.0, -2.0, 3.0], dtype=target.dtype) * ulps * eps)  # a turn of a few ulps
    for sign in (1, -1):
        moved = target.clone()
        moved[:, :3, 3] *= 1 + sign * ulps * eps
        turned = target.clone()
        turned[:, :3, :3] = turned[:, :3, :3] @ (turn if sign > 0 else turn.T)
        for out in (_batched(chain, moved), _batched(chain, turned)):
            ok &= (out.q - ref.q).abs().amax(-1) <= q_tol
            for name in FLAGS:
                ok &= getattr(out, name) == getattr(ref, name)
    return ok


def _assert_same(fast, slow, q_tol: float, mask=None) -> None:
    """Both AnalyticSolutions of the same types, shapes and layout; q within ``q_tol`` rad and the
    same flags on the branches of ``mask`` (all by default)."""
    assert type(fast) is type(slow) and fast.clearance is None and fast.collision_free is None
    for name in ("q", *FLAGS):
        a, b = getattr(fast, name), getattr(slow, name)
        assert isinstance(a, torch.Tensor) and a.dtype == b.dtype and a.shape == b.shape, name
    assert fast.q.stride() == slow.q.stride()  # joint-major, as the batched path lays q out
    assert torch.isfinite(fast.q).all()
    mask = torch.ones(fast.valid.shape, dtype=torch.bool) if mask is None else mask
    for name in FLAGS:
        assert torch.equal(getattr(fast, name)[mask], getattr(slow, name)[mask]), name
    diff = (fast.q - slow.q).abs().amax(-1)[mask]
    assert diff.numel() == 0 or diff.max().item() <= q_tol, f"{diff.max().item():.3g} rad at {diff.argmax().item()}"


def _assert_closure(chain, sol, target, tol: float) -> None:
    """Every reachable branch reproduces its target (FK of q), and valid means within the limits."""
    pos, rot = pose_error(chain.fk(sol.q.double()), target.double()[..., None, :, :].expand(*sol.q.shape[:-1], 4, 4))
    err = torch.maximum(pos.norm(dim=-1), rot.norm(dim=-1))[sol.reachable]
    assert err.numel() == 0 or err.max() < tol
    assert torch.equal(sol.valid, sol.reachable & chain.within_limits(sol.q))


def _at_limits(chain, gen) -> torch.Tensor:
    """Configurations with 1-3 joints exactly at a limit (either side)."""
    q = chain.random_q(BATCH, generator=gen)
    lo, hi = chain.limits
    for row in range(BATCH):
        joints = torch.randperm(6, generator=gen)[: 1 + row % 3]
        side = torch.rand(len(joints), generator=gen) < 0.5
        q[row, joints] = torch.where(side, lo[joints], hi[joints])
    return q


def _singular(chain, gen) -> torch.Tensor:
    """Targets of configurations with the wrist aligned (theta5 = 0) and of the arm stretched or
    folded (theta3 = -gamma or pi - gamma), then FK poses whose wrist centre is moved onto the cylinder
    of radius |d2 + d3| about the waist axis, in turn."""
    q = chain.random_q(BATCH, generator=gen)
    dh = chain.dh
    gamma = torch.atan2(-torch.sin(dh[2, 1]) * dh[3, 2], dh[2, 0])
    for row in range(BATCH):
        if row % 3 == 0:
            q[row, 4] = -dh[4, 3]
        elif row % 3 == 1:
            q[row, 2] = -gamma - dh[2, 3] + (torch.pi if row % 2 else 0.0)
    target = chain.fk(q)
    # the wrist centre in frame 0, and the shift of the target that puts it on the cylinder
    frames = chain.fk_all(q)
    base = chain.base
    wrist = (frames[:, 5, :3, 3] - base[:3, 3]) @ base[:3, :3]
    lateral = float(dh[1, 2] + dh[2, 2])
    r = wrist[:, :2].norm(dim=-1, keepdim=True)
    moved = wrist.clone()
    moved[:, :2] *= abs(lateral) / r if lateral else 0.0
    rows = torch.arange(BATCH) % 3 == 2
    target[rows, :3, 3] += ((moved - wrist) @ base[:3, :3].T)[rows]
    return target


def _targets(chain, case: str, seed: int) -> torch.Tensor:
    gen = _gen(seed)
    if case == "random":
        return chain.fk(chain.random_q(BATCH, generator=gen))
    if case == "limits":
        return chain.fk(_at_limits(chain, gen))
    if case == "singular":
        return _singular(chain, gen)
    target = chain.fk(chain.random_q(BATCH, generator=gen))  # unreachable: 2-3 m out from the shoulder
    shoulder = chain.fk_all(torch.zeros(6, dtype=F64))[1, :3, 3]
    offset = target[:, :3, 3] - shoulder
    reach = 2.0 + torch.rand(BATCH, 1, generator=gen, dtype=F64)
    target[:, :3, 3] = shoulder + reach * offset / offset.norm(dim=-1, keepdim=True)
    return target


CASES = ["random", "unreachable", "limits", "singular"]
MIN_STABLE = {"limits": 0.45, "singular": 0.2}  # share of branches not decided by rounding (seen: >= 0.51, 0.23)


def test_the_singular_set_is_singular():
    """The wrist-aligned, stretched and on-the-cylinder targets really are (an independent check
    on the wrist centre of the batched path's branches)."""
    chain = CHAINS["puma560"]
    target = _singular(chain, _gen(0))
    sol = _batched(chain, target)
    theta = sol.q + chain.dh[:, 3]
    assert theta[0::3, :, 4].sin().abs().amin(-1).max() < 1e-7  # some branch has the wrist aligned
    wrist = chain.fk_all(sol.q[2::3])[..., 5, :3, 3]
    assert (wrist[..., :2].norm(dim=-1) - (chain.dh[1, 2] + chain.dh[2, 2])).abs().max() < 1e-9


@pytest.mark.parametrize("chain_name", list(CHAINS))
@pytest.mark.parametrize("case", CASES)
def test_numpy_path_matches_the_batched_path_float64(chain_name, case):
    """q within 1e-9 rad and the same flags on every branch of random and unreachable poses; at limits
    and singular poses on every branch that rounding does not decide (:func:`_stable`), and a closed,
    finite answer everywhere."""
    chain = CHAINS[chain_name]
    stable = 0
    for seed in range(3):
        target = _targets(chain, case, 100 * seed + CASES.index(case))
        fast, slow = analytic.pieper(chain, target), _batched(chain, target)
        mask = None if case in ("random", "unreachable") else _stable(chain, target, 1e-9, 2)
        _assert_same(fast, slow, q_tol=1e-9, mask=mask)
        _assert_closure(chain, fast, target, 1e-9)
        stable += 0 if mask is None else int(mask.sum())
        if case == "unreachable":
            assert not fast.reachable.any()
        else:
            assert fast.reachable.any(-1).all() and fast.valid.any()
    assert stable >= MIN_STABLE.get(case, 0) * 3 * BATCH * 8


@pytest.mark.parametrize("chain_name", list(CHAINS))
@pytest.mark.parametrize("case", CASES)
def test_numpy_path_matches_the_batched_path_float32(chain_name, case):
    """float32 targets: both paths compute in float32. The same flags and q within 1e-4 rad on the
    branches that rounding does not decide (:func:`_stable` with 2 float32 ulps and 1e-4 rad),
    closed answers everywhere."""
    chain = CHAINS[chain_name]
    for seed in range(3):
        target = _targets(chain, case, 100 * seed + CASES.index(case) + 7).float()
        fast, slow = analytic.pieper(chain, target), _batched(chain, target)
        mask = _stable(chain, target, 1e-4, 2)
        _assert_same(fast, slow, q_tol=1e-4, mask=mask)
        _assert_closure(chain, fast, target, 2e-3)
        if case == "random":
            assert mask.float().mean() >= 0.9


def test_leading_shapes_a_single_pose_and_no_poses():
    chain = CHAINS["puma560"]
    target = chain.fk(chain.random_q(2, 3, generator=_gen(6)))
    for t in (target, target[0, 0], target[:0]):
        _assert_same(analytic.pieper(chain, t), _batched(chain, t), q_tol=1e-9)
    assert analytic.pieper(chain, target[0, 0]).q.shape == (8, 6)


def test_gradients_still_flow_where_asked():
    """A target that requires grad takes the batched path: q is differentiable as before."""
    chain = CHAINS["puma560"]
    target = chain.fk(chain.random_q(3, generator=_gen(7))).requires_grad_()
    out = analytic.pieper(chain, target)
    assert out.q.requires_grad
    (grad,) = torch.autograd.grad(out.q[out.valid].sum(), target)
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0
    with torch.no_grad():  # nothing to differentiate: the numpy path, same answer
        fast = analytic.pieper(chain, target)
    assert not fast.q.requires_grad
    _assert_same(fast, _batched(chain, target.detach()), q_tol=1e-9)


def test_a_world_takes_the_batched_path_with_the_same_answers():
    chain = CHAINS["puma560"]
    target = chain.fk(chain.random_q(4, generator=_gen(8)))
    world = World(floor=-0.1)
    out, ref = analytic.pieper(chain, target, world=world), _batched(chain, target, world=world)
    assert out.clearance is not None and torch.equal(out.q, ref.q) and torch.equal(out.valid, ref.valid)


def test_a_changed_chain_is_seen():
    """The numpy path caches the chain's stripped transforms: a new tool must take effect."""
    chain = robots.puma560()
    target = chain.fk(chain.random_q(5, generator=_gen(9)))
    analytic.pieper(chain, target)
    chain.tool.copy_(placed(robots.puma560()).tool)
    fast = analytic.pieper(chain, target)
    _assert_same(fast, _batched(chain, target), q_tol=1e-9)
    _assert_closure(chain, fast, target, 1e-9)


def test_input_checks_are_unchanged_on_small_batches():
    chain = CHAINS["puma560"]
    target = chain.fk(chain.random_q(2, generator=_gen(10)))
    bad = target.clone()
    bad[0, :3, :3] *= 2.0
    with pytest.raises(ValueError, match="rigid"):
        analytic.pieper(chain, bad)
    with pytest.raises(ValueError, match="Pieper"):
        analytic.pieper(robots.iiwa14(), target)
    with pytest.raises(ValueError, match="margin"):
        analytic.pieper(chain, target, margin=-1.0)
