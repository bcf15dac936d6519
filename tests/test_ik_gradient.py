"""Gradient-based IK (iiwa_torch.ik.solve / minimize).

Expected values come from the chain's own FK of random configurations (reachable targets by
construction), from chain.jacobian / so3.pose_error (independent code paths for the solver's
batch-last kernel), and from closed-form facts (reach of the arm, planar z).
"""

import math

import numpy as np
import pytest
import torch

from iiwa_torch import robots, so3
from iiwa_torch.dh import DHChain
from iiwa_torch.ik import IKResult, MinimizeOptions, SolveOptions, lm_compiled, lm_setup, minimize, solve
from iiwa_torch.ik.dls import cholesky_solve_batch_last, dls_step, dls_step_numpy

DTYPES = [torch.float64, torch.float32]


def reachable(chain, count, seed, dtype=torch.float64):
    """Targets: FK of random configurations within the limits (seeded)."""
    q = chain.random_q(count, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return chain.fk(q).to(dtype), q.to(dtype)


def within_limits(chain, q):
    """Every joint within the chain's float64 limits (a float32 answer is compared exactly)."""
    return chain.within_limits(q.double()).all()


def first_step(chain, q0, target, weight, damping=1e-2):
    """The first LM step from ``q0`` by hand, from the public Jacobian, pose error and DLS step:
    rotation rows weighted by ``weight``, damping 1% of the squared weighted error (at most ``damping``)."""
    e_pos, e_rot = so3.pose_error(chain.fk(q0), target)
    scale = torch.tensor([1, 1, 1, weight, weight, weight], dtype=q0.dtype)
    e = torch.cat([e_pos, e_rot], -1) * scale
    lam = (0.01 * e.square().sum(-1)).clamp(1e-12, damping)
    return q0 + dls_step(chain.jacobian(q0) * scale[:, None], e, lam)


def one_step(chain, target, q0, weight):
    return solve(chain, target, q0, seeds=1, iterations=1, rot_weight=weight, precision="input").q


def near(chain, q0, seed, size=0.02):
    """Targets a little away from ``chain.fk(q0)`` (so one step is a clear improvement)."""
    gen = torch.Generator().manual_seed(seed)
    return chain.fk(q0 + size * torch.randn(q0.shape, generator=gen, dtype=q0.dtype))


def mid_q(chain, count, seed):
    """Configurations in the middle half of the limits (one small step stays inside them)."""
    lo, hi = chain.limits
    u = torch.rand(count, chain.n_joints, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return (lo + hi) / 2 + (u - 0.5) * (hi - lo) / 2


# ---------------------------------------------------------------- the solver's kernel, through one step
@pytest.mark.parametrize("name", list(robots.PRESETS))
def test_first_step_is_the_dls_step_of_chain_jacobian_and_pose_error(name):
    chain = robots.PRESETS[name]()
    q0 = mid_q(chain, 64, 0)
    target = near(chain, q0, 1)
    torch.testing.assert_close(one_step(chain, target, q0, 0.5), first_step(chain, q0, target, 0.5), atol=1e-9, rtol=0)


@pytest.mark.parametrize("compiled_rounds", [True, False])
def test_first_step_follows_the_damping_setting(monkeypatch, compiled_rounds):
    """``damping`` caps the initial damping on both paths: a far target (1% of its squared error
    above the cap) takes the hand-computed step with the smaller cap."""
    if not compiled_rounds:
        monkeypatch.setattr(lm_compiled, "COMPILED_BATCH", 0)
    chain = robots.iiwa14()
    q0 = mid_q(chain, 16, 4)
    target = near(chain, q0, 5, size=0.05)
    options = SolveOptions(seeds=1, iterations=1, precision="input", damping=1e-6)
    expected = first_step(chain, q0, target, 1.0, damping=1e-6)
    torch.testing.assert_close(solve(chain, target, q0, options=options).q, expected, atol=1e-9, rtol=0)
    assert (first_step(chain, q0, target, 1.0) - expected).abs().max() > 1e-4  # the cap mattered


def test_options_object_and_keywords_are_one_setting():
    """``options=SolveOptions(...)`` solves as the same keywords do; keywords beside it replace
    its fields; the defaults are the dataclass's; the object is frozen and hashable."""
    chain = robots.iiwa14()
    target, _ = reachable(chain, 20, 11)
    opts = SolveOptions(seeds=4, iterations=10, pos_tol=1e-6, rot_tol=1e-6)
    by_object = solve(chain, target, options=opts)
    by_keywords = solve(chain, target, seeds=4, iterations=10, pos_tol=1e-6, rot_tol=1e-6)
    for field in ("q", "success", "iterations"):
        assert torch.equal(getattr(by_object, field), getattr(by_keywords, field))
    mixed = solve(chain, target, options=SolveOptions(seeds=4, iterations=3), iterations=10, pos_tol=1e-6,
                  rot_tol=1e-6)
    assert torch.equal(mixed.q, by_object.q)
    assert torch.equal(solve(chain, target, options=SolveOptions()).q, solve(chain, target).q)
    with pytest.raises(AttributeError):
        opts.seeds = 8
    assert hash(opts) == hash(SolveOptions(seeds=4, iterations=10, pos_tol=1e-6, rot_tol=1e-6))
    assert opts.unconstrained_steps == 4 and SolveOptions(iterations=5).unconstrained_steps == 2


def test_minimize_options_object_and_keywords_are_one_setting():
    chain = robots.iiwa14()
    target, q = reachable(chain, 3, 12)
    q0 = q + 0.05

    def loss(q, pose):
        return (pose[..., :3, 3] - target[..., :3, 3]).square().sum(-1)

    by_object = minimize(chain, loss, q0, target=target[..., :3, 3],
                         options=MinimizeOptions(mode="position", optimizer="lbfgs", steps=20))
    by_keywords = minimize(chain, loss, q0, target=target[..., :3, 3], mode="position", optimizer="lbfgs", steps=20)
    assert torch.equal(by_object.q, by_keywords.q) and bool(by_object.success.all())


def test_first_step_with_modified_dh_base_and_tool():
    tool = torch.eye(4, dtype=torch.float64)
    tool[:3, :3] = so3.exp(torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64))
    tool[:3, 3] = torch.tensor([0.01, 0.02, 0.1])
    base = torch.eye(4, dtype=torch.float64)
    base[:3, :3] = so3.exp(torch.tensor([0.0, 0.0, 0.7], dtype=torch.float64))
    base[:3, 3] = torch.tensor([0.5, -0.2, 0.1])
    table = [(0, 0, 0.3, 0), (0.1, -math.pi / 2, 0, 0.2), (0.4, 0.3, 0.05, 0), (0.02, math.pi / 2, 0.35, 0)]
    chain = DHChain(table, convention="modified", base=base, tool=tool)
    q0 = mid_q(chain, 32, 2)
    target = near(chain, q0, 3, size=0.005)  # 4 joints cannot follow a pose: a short way only
    torch.testing.assert_close(one_step(chain, target, q0, 1.0), first_step(chain, q0, target, 1.0), atol=1e-9, rtol=0)


def test_first_step_near_a_half_turn_is_finite():
    # Targets turned by pi - d about an axis from the current pose: the step is finite, and away
    # from exactly pi it is the DLS step of so3.pose_error's rotation vector.
    chain = robots.iiwa14()
    q0 = mid_q(chain, 5, 4)
    pose = chain.fk(q0)
    angles = torch.tensor([math.pi, math.pi - 1e-4, 3.0, 1e-8, 0.0], dtype=torch.float64)
    axis = torch.nn.functional.normalize(torch.tensor([[0.3, -0.5, 0.8]], dtype=torch.float64), dim=-1)
    target = pose.clone()
    target[:, :3, :3] = so3.exp(axis * angles[:, None]) @ pose[:, :3, :3]
    q1 = one_step(chain, target, q0, 1.0)
    assert torch.isfinite(q1).all()
    expected = first_step(chain, q0, target, 1.0)
    inside = chain.within_limits(expected)  # (the solver projects a step that leaves the limits)
    assert inside[1:].sum() >= 2
    torch.testing.assert_close(q1[1:][inside[1:]], expected[1:][inside[1:]], atol=1e-9, rtol=0)


# ---------------------------------------------------------------- success on reachable targets
def test_an_arm_far_from_the_origin_is_solved_to_tight_tolerances():
    """Float32 spaces numbers 3e-5 m apart at 300 m: the default precision must not iterate there at 1e-5 m."""
    near, far = robots.iiwa14(), robots.iiwa14()
    far.base[0, 3] = 300.0
    target, _ = reachable(near, 2000, 3, torch.float64)
    options = SolveOptions(pos_tol=1e-5, rot_tol=1e-5)
    assert lm_setup.work_dtype(target, options) == torch.float32  # the fast path where float32 suffices
    shifted = far.base @ target
    assert lm_setup.work_dtype(shifted, options) == torch.float64
    assert solve(far, shifted, options=options).success.all()


@pytest.mark.parametrize(
    "dtype, precision", [(torch.float64, "auto"), (torch.float64, "input"), (torch.float32, "auto")]
)
def test_iiwa_pose_success_rate(dtype, precision):
    # 2,000 seeded reachable poses. The bar is >= 99.9 % success: we allow 2 failures
    # (99.9 %); the benchmark measures the rate on 10,000.
    chain = robots.iiwa14()
    target, _ = reachable(chain, 2000, 10, dtype)
    result = solve(chain, target, precision=precision)
    assert isinstance(result, IKResult)
    assert result.q.dtype == dtype and result.q.shape == (2000, 7)
    assert int((~result.success).sum()) <= 2
    assert within_limits(chain, result.q)
    # success is what FK of the returned q says, at 0.1 mm / 1 mrad
    pos, rot = so3.pose_error(chain.fk(result.q), target)
    assert torch.equal(result.success, (pos.norm(dim=-1) <= 1e-4) & (rot.norm(dim=-1) <= 1e-3))
    assert (result.iterations > 0).all()


@pytest.mark.parametrize("name", list(robots.PRESETS))
@pytest.mark.parametrize("dtype", DTYPES)
def test_position_only_always_succeeds(name, dtype):
    chain = robots.PRESETS[name]()
    target, _ = reachable(chain, 300, 11, dtype)
    result = solve(chain, target[:, :3, 3], mode="position")
    assert result.success.all()
    assert within_limits(chain, result.q)
    assert (result.rot_err == 0).all()


@pytest.mark.parametrize("name", ["puma560", "lrmate200ic", "iiwa7"])
def test_other_arms_full_pose(name):
    # 6-DOF arms have at most 8 branches and the joint limits cut some: they get 32 seeds by
    # default (measured on 3,000 poses: 96.7 % with 8 seeds on the LR Mate, 99.8 % with 32).
    chain = robots.PRESETS[name]()
    target, _ = reachable(chain, 300, 12)
    result = solve(chain, target)
    assert result.success.double().mean() >= 0.99
    assert within_limits(chain, result.q)


def test_planar3r_position_targets_in_its_plane():
    chain = robots.planar3r()
    target, _ = reachable(chain, 200, 13)
    assert torch.all(target[:, 2, 3] == 0)  # the arm moves in z = 0
    result = solve(chain, target[:, :3, 3], mode="position")
    assert result.success.all()
    # a target off the plane cannot be reached: best effort, no NaN
    off = target[:, :3, 3] + torch.tensor([0.0, 0.0, 0.2], dtype=torch.float64)
    result = solve(chain, off, mode="position", seeds=2)
    assert not result.success.any()
    assert torch.isfinite(result.q).all()
    torch.testing.assert_close(result.pos_err.min(), torch.tensor(0.2, dtype=torch.float64), atol=1e-6, rtol=0)


# ---------------------------------------------------------------- unreachable and singular
@pytest.mark.parametrize("dtype", DTYPES)
def test_unreachable_targets_give_finite_best_effort(dtype):
    chain = robots.iiwa14()
    target, _ = reachable(chain, 64, 14, dtype)
    far = target.clone()
    far[:, :3, 3] *= 5 / far[:, :3, 3].norm(dim=-1, keepdim=True)  # 5 m away: reach is 1.306 m
    result = solve(chain, far, seeds=3, iterations=8)
    assert not result.success.any()
    for value in (result.q, result.pos_err, result.rot_err):
        assert torch.isfinite(value).all()
    assert within_limits(chain, result.q)
    assert (result.pos_err >= 5 - 1.306).all()  # the flange is at most 1.306 m from the base
    # Position only, the best effort is the arm stretched toward the target: the miss is the
    # target's distance from the shoulder (0, 0, 0.36) minus the arm's length 0.946 m, unless
    # the joint limits forbid pointing straight at it.
    result = solve(chain, far[:, :3, 3], mode="position", seeds=2, iterations=40, precision="input")
    shoulder = torch.tensor([0.0, 0.0, 0.36], dtype=dtype)
    bound = (far[:, :3, 3] - shoulder).norm(dim=-1) - 0.946
    tol, close = (1e-9, 1e-4) if dtype == torch.float64 else (1e-5, 1e-3)  # float32 converges less far
    assert (result.pos_err >= bound - tol).all()
    assert ((result.pos_err - bound) < close).double().mean() >= 0.9


def test_unreachable_orientation():
    # A position at full reach straight up, but the flange pointing down: impossible.
    chain = robots.iiwa14()
    pose = torch.eye(4, dtype=torch.float64)
    pose[2, 3] = 1.306
    pose[:3, :3] = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    result = solve(chain, pose[None], seeds=4)
    assert not result.success.any()
    assert torch.isfinite(result.q).all() and torch.isfinite(result.rot_err).all()


@pytest.mark.parametrize("dtype", DTYPES)
def test_singular_seeds_and_targets(dtype):
    chain = robots.iiwa14()
    q = chain.random_q(200, generator=torch.Generator().manual_seed(15), dtype=dtype)
    q[:100, 3] = 0  # stretched elbow
    q[100:, 5] = 0  # aligned wrist
    target = chain.fk(q)
    # start every problem at the fully singular zero posture (q4 = q6 = 0, arm straight up)
    result = solve(chain, target, torch.zeros(7, dtype=dtype), seeds=6)
    assert torch.isfinite(result.q).all()
    assert result.success.double().mean() >= 0.99
    # the straight-up pose itself, from a singular seed
    up = chain.fk(torch.zeros(1, 7, dtype=dtype))
    result = solve(chain, up, torch.zeros(7, dtype=dtype), seeds=1)
    assert result.success.all() and torch.isfinite(result.q).all()


def test_minimize_gradients_finite_at_singularity():
    chain = robots.iiwa14()
    goal = chain.fk(chain.random_q(4, generator=torch.Generator().manual_seed(16)))

    loss = pose_loss(goal)
    q0 = torch.zeros(4, 7, dtype=torch.float64, requires_grad=True)
    value = loss(q0, chain.fk(q0)).sum()
    (grad,) = torch.autograd.grad(value, q0)
    assert torch.isfinite(grad).all()
    result = minimize(chain, loss, torch.zeros(4, 7, dtype=torch.float64), target=goal, steps=50)
    assert torch.isfinite(result.q).all()


# ---------------------------------------------------------------- batching, seeds, null space
@pytest.mark.parametrize("precision, atol", [("input", 1e-9), ("auto", 1e-3)])
def test_batched_equals_looped(precision, atol):
    # "auto" iterates these float64 targets in float32, whose rounding differs between the
    # batch sizes' Cholesky paths (LAPACK for a few problems, unrolled for many): the same
    # solution, up to where within the tolerance each run stopped.
    chain = robots.iiwa14()
    target, _ = reachable(chain, 1200, 17)
    batched = solve(chain, target, precision=precision)
    for i in range(0, 1200, 100):
        single = solve(chain, target[i : i + 1], precision=precision)
        torch.testing.assert_close(single.q[0], batched.q[i], atol=atol, rtol=0)
        assert bool(single.success[0]) == bool(batched.success[i])


def test_float64_precision_choices():
    # Both ways reach the default tolerance on float64 targets; tolerances below 1e-5 switch
    # "auto" to float64 iterations, which reach 1e-9.
    chain = robots.iiwa14()
    target, _ = reachable(chain, 300, 25)
    auto = solve(chain, target)
    full = solve(chain, target, precision="input")
    tight = solve(chain, target, pos_tol=1e-9, rot_tol=1e-9)  # below 1e-5: float64 iterations
    for result in (auto, full, tight):
        assert result.q.dtype == torch.float64 and result.success.all()
    assert tight.pos_err.max() <= 1e-9 and tight.rot_err.max() <= 1e-9
    with pytest.raises(ValueError, match="precision"):
        solve(chain, target, precision="half")


def test_cholesky_paths_match_linalg_solve():
    gen = torch.Generator().manual_seed(26)
    for batch in (50, 2000):  # LAPACK and unrolled paths
        M = torch.randn(6, 9, batch, generator=gen, dtype=torch.float64)
        A = (M[:, None] * M[None]).sum(2) + 1e-3 * torch.eye(6, dtype=torch.float64)[..., None]
        rhs = torch.randn(6, 2, batch, generator=gen, dtype=torch.float64)
        x = cholesky_solve_batch_last(A, rhs, 1e-12)
        expected = torch.linalg.solve(A.permute(2, 0, 1), rhs.permute(2, 0, 1)).permute(1, 2, 0)
        torch.testing.assert_close(x, expected, atol=1e-9, rtol=1e-9)
        # a singular matrix (zero Jacobian) gives a finite answer, not NaN
        zero = cholesky_solve_batch_last(torch.zeros_like(A), rhs, 1e-12)
        assert torch.isfinite(zero).all()


@pytest.mark.parametrize("rows", [6, 3])
def test_dls_step_is_damped_least_squares(rows):
    """dq minimises |J dq - e|^2 + lam |dq|^2: least squares on [J; sqrt(lam) I] dq = [e; 0]."""
    gen = torch.Generator().manual_seed(27)
    J = torch.randn(2, 5, rows, 7, generator=gen, dtype=torch.float64)
    J[0, 0, 0] = 0.0  # a rank-deficient Jacobian: only the damping keeps the step finite
    e = torch.randn(2, 5, rows, generator=gen, dtype=torch.float64)
    lam = torch.tensor([1e-2, 1e-4], dtype=torch.float64)[:, None]  # (2, 1): broadcasts over the batch
    stacked = torch.cat([J, lam[..., None, None].sqrt() * torch.eye(7, dtype=torch.float64).expand(2, 5, 7, 7)], -2)
    rhs = torch.cat([e, torch.zeros(2, 5, 7, dtype=torch.float64)], -1)
    expected = torch.linalg.lstsq(stacked, rhs[..., None]).solution[..., 0]
    torch.testing.assert_close(dls_step(J, e, lam), expected, atol=1e-10, rtol=1e-10)
    # a float damping, broadcast Jacobian; and differentiable
    broadcast = dls_step(J[0, 0].expand(5, rows, 7), e[0], torch.full((5,), 1e-2, dtype=torch.float64))
    torch.testing.assert_close(dls_step(J[0, 0], e[0], 1e-2), broadcast)
    args = (J[1, :2].clone().requires_grad_(), e[1, :2].clone().requires_grad_())
    assert torch.autograd.gradcheck(lambda j, v: dls_step(j, v, 1e-2), args)


@pytest.mark.parametrize("rows", [6, 3])
def test_dls_step_numpy_is_damped_least_squares_with_held_joints(rows):
    """The numpy step against least squares on [J diag(free); sqrt(lam) I] dq = [e; 0], the held
    joints' columns zeroed (their step 0), damping broadcast over a batch."""
    gen = np.random.default_rng(28)
    J, e = gen.normal(size=(4, 3, rows, 7)), gen.normal(size=(4, 3, rows))
    lam = np.array([1e-2, 1e-3, 1e-4])  # (3,): one per column of the batch
    free = (gen.random((4, 3, 7)) > 0.3).astype(np.float64)
    for held in (None, free):
        f = np.ones_like(free) if held is None else held
        stacked = np.concatenate([J * f[..., None, :], np.sqrt(lam)[:, None, None] * np.eye(7)[None]
                                  .repeat(4 * 3, 0).reshape(4, 3, 7, 7)], -2)
        rhs = np.concatenate([e, np.zeros((4, 3, 7))], -1)
        expected = np.stack([np.linalg.lstsq(a, b, rcond=None)[0] for a, b in
                             zip(stacked.reshape(-1, rows + 7, 7), rhs.reshape(-1, rows + 7))]).reshape(4, 3, 7) * f
        np.testing.assert_allclose(dls_step_numpy(J, e, lam, held), expected, atol=1e-10, rtol=1e-10)


def test_dls_step_gradient_same_on_both_cholesky_paths():
    gen = torch.Generator().manual_seed(28)
    J = torch.randn(600, 6, 7, generator=gen, dtype=torch.float64, requires_grad=True)  # > 384: unrolled
    e = torch.randn(600, 6, generator=gen, dtype=torch.float64)
    weights = torch.randn(600, 7, generator=gen, dtype=torch.float64)
    (grad_all,) = torch.autograd.grad((dls_step(J, e, 1e-2) * weights).sum(), J)
    (grad_few,) = torch.autograd.grad((dls_step(J[:10], e[:10], 1e-2) * weights[:10]).sum(), J)  # LAPACK
    torch.testing.assert_close(grad_all[:10], grad_few[:10], atol=1e-10, rtol=1e-10)


def test_dls_step_rejects_bad_input():
    J, e = torch.zeros(4, 6, 7), torch.zeros(4, 6)
    with pytest.raises(ValueError, match="error must have shape"):
        dls_step(J, e[:, :3], 0.1)
    with pytest.raises(ValueError, match="damping must be a positive number"):
        dls_step(J, e, 0.0)
    with pytest.raises(TypeError, match="jacobian must be a torch.Tensor"):
        dls_step(J.numpy(), e, 0.1)


def test_batch_shape_and_q0_broadcast():
    chain = robots.iiwa14()
    target, _ = reachable(chain, 12, 18)
    result = solve(chain, target.reshape(3, 4, 4, 4), torch.zeros(7, dtype=torch.float64))
    assert result.q.shape == (3, 4, 7) and result.success.shape == (3, 4)
    assert result.pos_err.shape == (3, 4) and result.iterations.shape == (3, 4)


def test_q0_near_solution_is_kept():
    # Tracking: a seed next to a solution converges to that solution, not another branch.
    chain = robots.iiwa14()
    target, q_true = reachable(chain, 300, 19)
    q0 = chain.clamp(q_true + 0.01)
    result = solve(chain, target, q0)
    assert result.success.all()
    assert (result.q - q_true).abs().max() < 0.05


def test_rest_posture_pull_uses_the_null_space():
    # Another solution of the same poses: move along the Jacobian's null space (SVD) and
    # project back. Pulled toward it, the solver must land near it instead of near q0.
    chain = robots.iiwa14()
    target, q_true = reachable(chain, 300, 20)
    null = torch.linalg.svd(chain.jacobian(q_true)).Vh[:, -1]  # (300, 7) self-motion direction
    other = solve(chain, target, chain.clamp(q_true + 0.4 * null), seeds=1)
    ok = other.success  # (a few starts are cut by the joint limits)
    assert ok.sum() >= 280
    target, q0, rest = target[ok], chain.clamp(q_true[ok] + 0.02), other.q[ok]
    plain = solve(chain, target, q0)
    pulled = solve(chain, target, q0, rest=rest, rest_gain=0.5)
    assert plain.success.all() and pulled.success.all()
    dist_plain = (plain.q - rest).norm(dim=-1).mean()
    dist_pulled = (pulled.q - rest).norm(dim=-1).mean()
    assert dist_plain > 0.3 and dist_pulled < 0.2 * dist_plain


def test_generator_makes_seeds_reproducible():
    chain = robots.iiwa14()
    target, _ = reachable(chain, 200, 21)
    a = solve(chain, target, generator=torch.Generator().manual_seed(3))
    b = solve(chain, target, generator=torch.Generator().manual_seed(3))
    assert torch.equal(a.q, b.q)


# ---------------------------------------------------------------- minimize
def test_minimize_reaches_point_and_keeps_elbow_high():
    chain = robots.iiwa14()
    goal = torch.tensor([[0.5, 0.1, 0.4], [0.3, -0.4, 0.6], [-0.4, 0.3, 0.3], [0.6, 0.0, 0.8]], dtype=torch.float64)
    start = solve(chain, goal, mode="position").q  # reaches, elbow anywhere

    def elbow_height(q):
        return chain.fk_all(q)[..., 4, 2, 3]  # frame 4: the elbow (wrist-side of joint 4)

    def loss(q, pose):
        return (pose[..., :3, 3] - goal).square().sum(-1) + torch.relu(0.7 - elbow_height(q)).square()

    result = minimize(
        chain, loss, start, target=goal, mode="position", success_fn=lambda q, pose: elbow_height(q) >= 0.7 - 1e-3
    )
    assert result.success.all()
    assert result.success.all()  # reached within 0.1 mm, elbow above 0.7 m
    # the custom term went down: solve's answer had one elbow at 0.18 m
    assert elbow_height(start).min() < 0.5
    assert (elbow_height(result.q) > torch.minimum(elbow_height(start), torch.tensor(0.699))).all()
    assert within_limits(chain, result.q)


def pose_loss(goal, rot_weight=0.1):
    def loss(q, pose):
        pos, rot = so3.pose_error(pose, goal)
        return pos.square().sum(-1) + rot_weight * rot.square().sum(-1)

    return loss


def test_minimize_batched_equals_looped_with_adam():
    chain = robots.iiwa14()
    target, q_true = reachable(chain, 6, 22)
    q0 = chain.clamp(q_true + 0.2)
    batched = minimize(chain, pose_loss(target), q0, target=target, steps=60)
    for i in range(6):
        goal = target[i : i + 1]
        single = minimize(chain, pose_loss(goal), q0[i : i + 1], target=goal, steps=60)
        torch.testing.assert_close(single.q[0], batched.q[i], atol=1e-9, rtol=0)


def test_minimize_lbfgs_reaches_a_pose():
    chain = robots.iiwa14()
    target, q_true = reachable(chain, 1, 23)

    result = minimize(
        chain, pose_loss(target, 1.0), chain.clamp(q_true + 0.3), target=target, optimizer="lbfgs", steps=100
    )
    assert result.success.all()


# ---------------------------------------------------------------- input errors
def test_input_errors():
    chain = robots.iiwa14()
    target, _ = reachable(chain, 2, 24)
    with pytest.raises(ValueError, match="mode"):
        solve(chain, target, mode="orientation")
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        solve(chain, target, mode="position")
    with pytest.raises(ValueError, match=r"\(\.\.\., 4, 4\)"):
        solve(chain, target[:, :3])
    with pytest.raises(ValueError, match=r'got \(3,\); for positions \(\.\.\., 3\) pass mode="position"'):
        solve(chain, target[0, :3, 3])  # a point without mode=: the error says how to ask for it
    with pytest.raises(TypeError, match=r"target must be a float32 or float64 tensor, got torch\.int64"):
        solve(chain, torch.tensor([1, 0, 1]), mode="position")
    with pytest.raises(ValueError, match="NaN"):
        solve(chain, target * float("nan"))
    with pytest.raises(ValueError, match="q0"):
        solve(chain, target, torch.zeros(3, 7, dtype=torch.float64))
    with pytest.raises(ValueError, match="seeds"):
        solve(chain, target, seeds=0)
    with pytest.raises(ValueError, match="pos_tol"):
        solve(chain, target, pos_tol=-1.0)
    with pytest.raises(ValueError, match="rest_gain"):
        solve(chain, target, rest=torch.zeros(7, dtype=torch.float64), rest_gain=2.0)
    with pytest.raises(ValueError, match="optimizer"):
        minimize(chain, lambda q, p: q.sum(-1), torch.zeros(2, 7, dtype=torch.float64), target=target, optimizer="sgd")
    with pytest.raises(ValueError, match="one value per problem"):
        minimize(chain, lambda q, p: q.sum(), torch.zeros(2, 7, dtype=torch.float64), target=target, steps=2)


@pytest.mark.parametrize("mode", ["pose", "position"])
def test_no_targets_give_an_empty_answer(mode):
    """A batch of 0 targets (e.g. none left to solve) ranks an empty pool product and returns (0, n)."""
    chain = robots.iiwa14()
    target = torch.empty((0, 4, 4) if mode == "pose" else (0, 3), dtype=torch.float64)
    result = solve(chain, target, mode=mode)
    assert result.q.shape == (0, 7) and result.success.shape == (0,)
