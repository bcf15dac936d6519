"""The joint-space features of ``train.features.JointGoalExtractor``, against independent values.

The damped-least-squares step is checked against numpy's least squares on the stacked
system ``[J_p; lambda I] dq = [e; 0]`` (the same minimiser, solved another way), with
``J_p`` from central finite differences of the forward kinematics, not from the Jacobian.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from gymnasium import spaces

from iiwa_torch.robots import iiwa14
from train.features import GoalDeltaExtractor, JointGoalExtractor

MAX_STEP = [0.0742, 0.0742, 0.0873, 0.0654, 0.1134, 0.1178, 0.1178]  # rad per step (iiwa speeds x 0.05 s)


def _space(obs_dim: int = 24, goal_dim: int = 3) -> spaces.Dict:
    box = lambda n: spaces.Box(-10, 10, (n,))
    return spaces.Dict({"observation": box(obs_dim), "achieved_goal": box(goal_dim), "desired_goal": box(goal_dim)})


def _fd_position_jacobian(q: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """``(nj,)`` rad -> ``(3, nj)`` m/rad by central differences of the end-effector position."""
    chain = iiwa14()
    cols = []
    for i in range(q.size):
        dq = np.zeros_like(q)
        dq[i] = h
        plus = chain.fk(torch.from_numpy(q + dq))[:3, 3].numpy()
        minus = chain.fk(torch.from_numpy(q - dq))[:3, 3].numpy()
        cols.append((plus - minus) / (2 * h))
    return np.stack(cols, axis=1)


def test_joint_features_match_least_squares_on_finite_difference_jacobians():
    chain = iiwa14()
    g = torch.Generator().manual_seed(3)
    q = chain.random_q(5, generator=g)  # (5, 7) float64
    q[0] = 0.0  # the stretched arm: J_p has rank 2, only the damping keeps the step finite
    error = (torch.rand(5, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([[0.2], [0.02], [0.002],
                                                                                      [1.0], [0.005]])
    dampings = (0.1, 0.01)
    ext = JointGoalExtractor(_space(), "iiwa14", MAX_STEP, dampings=dampings)
    achieved = chain.fk(q)[:, :3, 3]
    obs = {"observation": torch.cat([q.cos(), q.sin(), torch.zeros(5, 7), achieved], -1).float(),
           "achieved_goal": achieved.float(), "desired_goal": (achieved + error).float()}
    out = ext(obs).double()
    base = GoalDeltaExtractor(_space())(obs)
    assert out.shape == (5, ext.features_dim) == (5, base.shape[1] + 4 * 7 + 1)
    assert torch.equal(out[:, : base.shape[1]].float(), base)
    joint = out[:, base.shape[1]:].numpy()
    e = (obs["desired_goal"] - obs["achieved_goal"]).double().numpy()  # the error the network sees (float32)
    for b in range(5):
        jp = _fd_position_jacobian(q[b].numpy())
        for k, lam in enumerate(dampings):
            stacked = np.vstack([jp, lam * np.eye(7)])
            dq = np.linalg.lstsq(stacked, np.concatenate([e[b], np.zeros(7)]), rcond=None)[0]
            u = dq / np.array(MAX_STEP)
            u = u / max(1.0, np.abs(u).max())
            np.testing.assert_allclose(joint[b, 7 * k : 7 * k + 7], u, atol=2e-5, err_msg=f"goal {b} lambda {lam}")
        np.testing.assert_allclose(joint[b, 14:21], jp.T @ e[b] / np.linalg.norm(e[b]), atol=2e-5)
        lower, upper = chain.limits.numpy()
        np.testing.assert_allclose(joint[b, 21:28], 2 * (q[b].numpy() - lower) / (upper - lower) - 1, atol=1e-6)
        np.testing.assert_allclose(joint[b, 28], np.linalg.norm(e[b]), rtol=1e-6)
    assert np.all(np.abs(joint[:, :14]) <= 1.0 + 1e-9)


def test_error_damping_grows_each_damping_with_the_error():
    """``error_damping = c``: the step is the least-squares one with ``lambda + c |e|`` (numpy's lstsq on
    ``[J_p; lambda I] dq = [e; 0]``, J_p by finite differences); a large error is damped far more."""
    chain = iiwa14()
    g = torch.Generator().manual_seed(4)
    q = chain.random_q(4, generator=g)
    error = (torch.rand(4, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([[0.8], [0.1], [0.01], [0.001]])
    dampings, c = (0.01, 0.03), 1.5
    ext = JointGoalExtractor(_space(), "iiwa14", MAX_STEP, dampings=dampings, error_damping=c)
    achieved = chain.fk(q)[:, :3, 3]
    obs = {"observation": torch.cat([q.cos(), q.sin(), torch.zeros(4, 7), achieved], -1).float(),
           "achieved_goal": achieved.float(), "desired_goal": (achieved + error).float()}
    joint = ext(obs).double()[:, -(4 * 7 + 1):].numpy()
    e = (obs["desired_goal"] - obs["achieved_goal"]).double().numpy()
    for b in range(4):
        jp = _fd_position_jacobian(q[b].numpy())
        for k, lam in enumerate(dampings):
            lam = lam + c * np.linalg.norm(e[b])
            dq = np.linalg.lstsq(np.vstack([jp, lam * np.eye(7)]), np.concatenate([e[b], np.zeros(7)]), rcond=None)[0]
            u = dq / np.array(MAX_STEP)
            np.testing.assert_allclose(joint[b, 7 * k : 7 * k + 7], u / max(1.0, np.abs(u).max()), atol=2e-5)


def test_step_bound_clip_clips_each_joint_where_shrink_keeps_the_direction():
    """A far goal: the DLS step exceeds full speed. ``shrink`` divides it by its largest entry (numpy's
    lstsq step, divided by hand); ``clip`` clips each joint to +-1 and leaves the unsaturated ones as
    they are."""
    chain = iiwa14()
    q = chain.random_q(1, generator=torch.Generator().manual_seed(8))
    achieved = chain.fk(q)[:, :3, 3]
    error = torch.tensor([[0.03, -0.02, 0.01]], dtype=torch.float64)
    obs = {"observation": torch.cat([q.cos(), q.sin(), torch.zeros(1, 7), achieved], -1).float(),
           "achieved_goal": achieved.float(), "desired_goal": (achieved + error).float()}
    e = (obs["desired_goal"] - obs["achieved_goal"]).double().numpy()[0]
    jp = _fd_position_jacobian(q[0].numpy())
    u = np.linalg.lstsq(np.vstack([jp, 0.1 * np.eye(7)]), np.concatenate([e, np.zeros(7)]), rcond=None)[0] / MAX_STEP
    assert np.abs(u).max() > 1 and np.sum(np.abs(u) < 1) >= 2  # some joints saturate, some do not
    for bound, expected in (("shrink", u / np.abs(u).max()), ("clip", np.clip(u, -1, 1))):
        ext = JointGoalExtractor(_space(), "iiwa14", MAX_STEP, dampings=(0.1,), step_bound=bound)
        np.testing.assert_allclose(ext(obs).double()[0, -(3 * 7 + 1):][:7].numpy(), expected, atol=2e-5)
    with pytest.raises(ValueError, match="step_bound must be one of"):
        JointGoalExtractor(_space(), max_step=MAX_STEP, step_bound="scale")


@pytest.mark.parametrize("value", [-0.1, float("nan"), float("inf"), True, "1"])
def test_error_damping_must_be_a_non_negative_number(value):
    with pytest.raises(ValueError, match="error_damping must be a finite number >= 0"):
        JointGoalExtractor(_space(), max_step=MAX_STEP, error_damping=value)


def test_joint_features_at_the_limits_and_on_target_by_hand():
    """At q = upper limits the place features are +1; with a zero error every step feature is zero."""
    chain = iiwa14()
    q = chain.limits[1].unsqueeze(0)
    achieved = chain.fk(q)[:, :3, 3].float()
    obs = {"observation": torch.cat([q.cos(), q.sin(), torch.zeros(1, 7)], -1).float(),
           "achieved_goal": achieved, "desired_goal": achieved.clone()}
    ext = JointGoalExtractor(_space(21), "iiwa14", MAX_STEP)
    joint = ext(obs)[0, -29:]
    assert torch.allclose(joint[21:28], torch.ones(7), atol=1e-5)
    assert torch.equal(joint[:21], torch.zeros(21)) and joint[28] == 0


@pytest.mark.parametrize("kwargs, message", [
    ({"robot": "nope", "max_step": MAX_STEP}, "robot must be one of"),
    ({"robot": "iiwa14", "max_step": MAX_STEP[:3]}, "max_step must be 7 positive"),
    ({"robot": "iiwa14", "max_step": MAX_STEP, "dampings": [0.0]}, "dampings"),
])
def test_joint_extractor_bad_options(kwargs, message):
    with pytest.raises(ValueError, match=message):
        JointGoalExtractor(_space(), **kwargs)


def test_joint_extractor_needs_cos_sin_in_the_observation():
    with pytest.raises(ValueError, match="needs >= 14"):
        JointGoalExtractor(_space(obs_dim=10), "iiwa14", MAX_STEP)


def _fd_weighted_jacobian(q: np.ndarray, w: float, h: float = 1e-6) -> np.ndarray:
    """``(nj,)`` rad -> ``(6, nj)``: position rows (m/rad), then ``w`` times the angular-velocity rows,
    each column ``log(R(q + h) R(q - h)^T) / 2h`` (scipy's rotation vector): central differences."""
    from scipy.spatial.transform import Rotation

    chain = iiwa14()
    cols = []
    for i in range(q.size):
        dq = np.zeros_like(q)
        dq[i] = h
        plus, minus = chain.fk(torch.from_numpy(q + dq)).numpy(), chain.fk(torch.from_numpy(q - dq)).numpy()
        omega = Rotation.from_matrix(plus[:3, :3] @ minus[:3, :3].T).as_rotvec() / (2 * h)
        cols.append(np.concatenate([(plus[:3, 3] - minus[:3, 3]) / (2 * h), w * omega]))
    return np.stack(cols, axis=1)


def test_pose_goal_features_match_least_squares_with_scipy_rotation_errors():
    """Pose goals (position, first two rotation columns): e = [e_p; w log(R_d R_a^T)], J = [J_p; w J_r]."""
    from scipy.spatial.transform import Rotation

    chain = iiwa14()
    g = torch.Generator().manual_seed(5)
    q = chain.random_q(4, generator=g)
    target = chain.random_q(4, generator=g) * torch.tensor([[0.02], [0.2], [1.0], [0.0]], dtype=torch.float64) + q
    w = 0.5
    pose_a, pose_d = chain.fk(q), chain.fk(target)
    goal = lambda p: torch.cat([p[:, :3, 3], p[:, :3, 0], p[:, :3, 1]], -1).float()  # the env's pose-goal layout
    obs = {"observation": torch.cat([q.cos(), q.sin(), torch.zeros(4, 7), goal(pose_a)], -1).float(),
           "achieved_goal": goal(pose_a), "desired_goal": goal(pose_d)}
    ext = JointGoalExtractor(_space(30, 9), "iiwa14", MAX_STEP, dampings=(0.1,), orientation_weight=w)
    joint = ext(obs)[:, -(3 * 7 + 1):].double().numpy()
    for b in range(3):  # goal 3 is the achieved pose itself (checked below)
        ra, rd = pose_a[b, :3, :3].numpy(), pose_d[b, :3, :3].numpy()
        e = np.concatenate([(pose_d[b, :3, 3] - pose_a[b, :3, 3]).numpy(),
                            w * Rotation.from_matrix(rd @ ra.T).as_rotvec()])
        jw = _fd_weighted_jacobian(q[b].numpy(), w)
        dq = np.linalg.lstsq(np.vstack([jw, 0.1 * np.eye(7)]), np.concatenate([e, np.zeros(7)]), rcond=None)[0]
        u = dq / np.array(MAX_STEP)
        np.testing.assert_allclose(joint[b, :7], u / max(1.0, np.abs(u).max()), atol=1e-4, err_msg=f"goal {b}")
        np.testing.assert_allclose(joint[b, 7:14], jw.T @ e / np.linalg.norm(e), atol=1e-4)
        np.testing.assert_allclose(joint[b, 21], np.linalg.norm(e), rtol=1e-4, atol=1e-6)
    assert joint[3, 21] < 1e-6 and np.abs(joint[3, :7]).max() < 1e-3  # float32 goals: not exactly zero


def test_velocity_damper_is_the_qp_solution():
    """Against scipy's SLSQP on ``min (x - x0)^T H (x - x0)`` subject to the damper's constraints."""
    from scipy.optimize import minimize

    from train.features import velocity_damper

    rng = np.random.default_rng(2)
    chain = iiwa14()
    lo, hi = chain.limits.numpy()
    b, k, n = 6, 3, 7
    q = torch.as_tensor(rng.uniform(lo, hi, (b, n)))
    jac = chain.jacobian(q)[:, :3]
    damping = torch.tensor([0.01], dtype=torch.float64)
    dq0 = torch.as_tensor(rng.normal(scale=0.05, size=(b, 1, n)))
    distance = torch.as_tensor(rng.uniform(0.0, 0.2, (b, k)))
    gradient = torch.as_tensor(rng.normal(scale=0.5, size=(b, k, n)))
    xi, safe, influence = 0.3, 0.02, 0.15
    out = velocity_damper(dq0, jac, damping, distance, gradient, xi, safe, influence, sweeps=300)
    for i in range(b):
        H = (jac[i].T @ jac[i] + 0.01 * torch.eye(n)).numpy()
        x0 = dq0[i, 0].numpy()
        active = distance[i].numpy() < influence
        cons = [{"type": "ineq", "fun": lambda x, g=g, d=d: g @ x + xi * (d - safe)}
                for g, d, a in zip(gradient[i].numpy(), distance[i].numpy(), active) if a]
        ref = minimize(lambda x, H=H, x0=x0: (x - x0) @ H @ (x - x0), x0,
                       jac=lambda x, H=H, x0=x0: 2 * H @ (x - x0), constraints=cons,
                       method="SLSQP", options={"ftol": 1e-14, "maxiter": 500}).x
        np.testing.assert_allclose(out[i, 0].numpy(), ref, atol=1e-6)
    # nothing within reach: unchanged
    far = velocity_damper(dq0, jac, damping, distance + influence, gradient, xi, safe, influence)
    torch.testing.assert_close(far, dq0)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_hildreth_numpy_path_equals_the_torch_path(dtype):
    """A few rows without autograd iterate in numpy; with requires_grad (or more rows) in torch: the
    same answers to the rounding of the sums, and the torch path's gradients still flow."""
    from train.features import NUMPY_ROWS, hildreth

    rng = np.random.default_rng(7)
    for rows in (1, 2, NUMPY_ROWS):
        x, normal, scaled = (torch.as_tensor(rng.normal(size=shape), dtype=dtype)
                             for shape in ((rows, 7), (rows, 4, 7), (rows, 4, 7)))
        scaled = normal + 0.1 * scaled  # a metric near the Euclidean one
        bound = torch.as_tensor(rng.normal(size=(rows, 4)), dtype=dtype)
        fast = hildreth(x, normal, scaled, bound)
        leaf = x.clone().requires_grad_(True)
        slow = hildreth(leaf, normal, scaled, bound)
        assert slow.requires_grad and not fast.requires_grad and fast.dtype == dtype
        torch.testing.assert_close(fast, slow.detach(), rtol=0, atol=1e-12 if dtype == torch.float64 else 1e-5)


def test_avoidance_needs_the_clearance_rows():
    with pytest.raises(ValueError, match="observe_clearance=True"):
        JointGoalExtractor(_space(), max_step=MAX_STEP, avoidance={"xi": 0.3, "safe": 0.02, "influence": 0.15})
    with pytest.raises(ValueError, match="avoidance must be"):
        JointGoalExtractor(_space(60), max_step=MAX_STEP, clearance_rows=[21, 4],
                           avoidance={"xi": 2.0, "safe": 0.02, "influence": 0.15})


def _arms_at_an_upper_limit(count: int = 30):
    """Random arms (seed 5), each 1 mrad inside a random joint ``i``'s upper limit, with a 5 cm position
    error along that joint's own motion (it pushes the joint out) -> ``(q, i, J_p, error)``; joints that
    hardly move the point (joint 7 never does) are skipped. ``J_p`` by finite differences."""
    rng = np.random.default_rng(5)
    lower, upper = iiwa14().limits.numpy()
    for _ in range(count):
        q = rng.uniform(lower, upper)
        i = rng.integers(7)
        q[i] = upper[i] - 1e-3
        jp = _fd_position_jacobian(q)
        if np.linalg.norm(jp[:, i]) >= 1e-2:
            yield q, i, jp, jp[:, i] * 0.05 / np.linalg.norm(jp[:, i])


def test_limit_rounds_hold_the_joints_a_step_would_push_past_a_limit():
    """Each arm starts 1 mrad inside a random joint's upper limit, with an error whose plain DLS step
    pushes that joint out; with ``limit_rounds`` the step keeps every joint within its limits and is the
    damped least-squares step (numpy's ``lstsq``, finite-difference Jacobian) over the other joints."""
    lower, upper = iiwa14().limits.numpy()
    ext = JointGoalExtractor(_space(), "iiwa14", MAX_STEP, dampings=(0.1,), limit_rounds=3)
    plain = JointGoalExtractor(_space(), "iiwa14", MAX_STEP, dampings=(0.1,))
    checked = 0
    for q, i, jp, error in _arms_at_an_upper_limit():
        qt, et, jt = torch.as_tensor(q)[None], torch.as_tensor(error)[None], torch.as_tensor(jp)[None]
        before = plain.bounded_step(qt, jt, et)[0, 0].numpy() * MAX_STEP
        if not q[i] + before[i] > upper[i]:
            continue
        checked += 1
        step = ext.bounded_step(qt, jt, et)[0, 0].numpy() * MAX_STEP
        assert np.all(q + step <= upper + 1e-12) and np.all(q + step >= lower - 1e-12)
        free = np.abs(step) > 0
        assert not free[i]
        stacked = np.vstack([jp[:, free], 0.1 * np.eye(free.sum())])
        dq = np.linalg.lstsq(stacked, np.concatenate([error, np.zeros(free.sum())]), rcond=None)[0]
        expected = np.zeros(7)
        expected[free] = dq
        expected /= max(1.0, np.abs(expected / MAX_STEP).max())
        np.testing.assert_allclose(step, expected, atol=1e-9)
    assert checked >= 10


def test_limit_hold_limit_moves_a_held_joint_onto_its_limit():
    """As above, each arm 1 mrad inside a joint's upper limit with an error pushing it out: with
    ``limit_hold = "limit"`` that joint steps onto its limit (1 mrad) and the others take the damped
    least-squares step (numpy's ``lstsq``) for the rest of the error, ``e - J_i 1e-3``."""
    lower, upper = iiwa14().limits.numpy()
    ext = JointGoalExtractor(_space(), "iiwa14", MAX_STEP, dampings=(0.1,), limit_rounds=3, step_bound="clip",
                             limit_hold="limit")
    checked = 0
    for q, i, jp, error in _arms_at_an_upper_limit():
        free = np.arange(7) != i
        stacked = np.vstack([jp[:, free], 0.1 * np.eye(6)])
        dq = np.linalg.lstsq(stacked, np.concatenate([error - jp[:, i] * 1e-3, np.zeros(6)]), rcond=None)[0]
        expected = np.zeros(7)
        expected[free], expected[i] = dq, 1e-3
        expected = np.clip(expected / MAX_STEP, -1, 1) * MAX_STEP
        if np.any(q + expected > upper) or np.any(q + expected < lower):  # another joint would be held too
            continue
        qt, et, jt = torch.as_tensor(q)[None], torch.as_tensor(error)[None], torch.as_tensor(jp)[None]
        step = ext.bounded_step(qt, jt, et)[0, 0].numpy() * MAX_STEP
        if step[i] == 0 and np.all(q + step <= upper):  # the first round held nothing (i not pushed out)
            continue
        checked += 1
        assert np.all(q + step <= upper + 1e-12) and np.all(q + step >= lower - 1e-12)
        np.testing.assert_allclose(step, expected, atol=1e-9)
    assert checked >= 10


def test_clip_guard_keeps_a_descent_direction():
    """DLS steps beyond full speed on random arms (6-row Jacobians): ``clip_guard = c`` gives the clipped
    step when its first-order progress ``e . J dq`` is at least ``c`` times the shrunk step's, else the
    shrunk one, so the step always descends (a clipped step alone sometimes does not)."""
    chain = iiwa14()
    rng = np.random.default_rng(9)
    q = torch.as_tensor(rng.uniform(*chain.limits.numpy(), (400, 7)))
    jac = chain.jacobian(q)
    error = torch.as_tensor(rng.normal(size=(400, 6)) * 0.05)
    guarded = JointGoalExtractor(_space(goal_dim=9), "iiwa14", MAX_STEP, dampings=(0.01, 0.03), step_bound="clip",
                                 clip_guard=0.5)
    clipped = JointGoalExtractor(_space(goal_dim=9), "iiwa14", MAX_STEP, dampings=(0.01, 0.03), step_bound="clip")
    shrunk = JointGoalExtractor(_space(goal_dim=9), "iiwa14", MAX_STEP, dampings=(0.01, 0.03))
    u, a, b = (ext.bounded_step(q, jac, error) for ext in (guarded, clipped, shrunk))
    progress = lambda v: ((jac @ (v * torch.as_tensor(MAX_STEP)).mT).mT * error[:, None]).sum(-1)  # (B, L)
    use_shrunk = progress(a) < 0.5 * progress(b)
    assert torch.equal(u, torch.where(use_shrunk[..., None], b, a))
    assert bool((progress(b) > 0).all()) and bool((progress(u) >= 0.5 * progress(b) - 1e-12).all())
    assert 0 < int(use_shrunk.sum()) < use_shrunk.numel() and bool((progress(a) < 0).any())
    assert float(u.abs().max()) <= 1.0


@pytest.mark.parametrize("kwargs, message", [
    ({"limit_hold": "edge"}, "limit_hold must be one of"),
    ({"step_bound": "clip", "clip_guard": 1.5}, "clip_guard must be a number in"),
    ({"step_bound": "clip", "clip_guard": True}, "clip_guard must be a number in"),
    ({"clip_guard": 0.3}, "clip_guard needs step_bound: clip")])
def test_limit_hold_and_clip_guard_bad_options(kwargs, message):
    with pytest.raises(ValueError, match=message):
        JointGoalExtractor(_space(), max_step=MAX_STEP, **kwargs)


def test_null_space_centering_is_the_damped_least_squares_step_towards_the_centering_step():
    """``null_space_centering = k``: the step minimises ``|J_p dq - e|^2 + lambda^2 |dq - dq0|^2`` with
    ``dq0 = -k p |p| max_step`` (numpy's lstsq on ``[J_p; lambda I] dq = [e; lambda dq0]``, J_p by finite
    differences, p each joint's place within its limits), and a small step comes out unbounded."""
    chain = iiwa14()
    rng = np.random.default_rng(6)
    lower, upper = chain.limits.numpy()
    lam, k = 0.1, 0.5
    ext = JointGoalExtractor(_space(), "iiwa14", MAX_STEP, dampings=(lam,), null_space_centering=k)
    for _ in range(5):
        q = rng.uniform(lower, upper)
        jp = _fd_position_jacobian(q)
        error = rng.normal(size=3) * 0.003
        place = 2 * (q - lower) / (upper - lower) - 1
        dq0 = -k * place * np.abs(place) * np.array(MAX_STEP)
        step = ext.bounded_step(*(torch.as_tensor(x)[None] for x in (q, jp, error)))[0, 0].numpy() * MAX_STEP
        expected = np.linalg.lstsq(np.vstack([jp, lam * np.eye(7)]), np.concatenate([error, lam * dq0]),
                                   rcond=None)[0]
        assert np.abs(expected / MAX_STEP).max() < 1  # not bounded: the minimiser itself
        np.testing.assert_allclose(step, expected, atol=1e-9)
        np.testing.assert_allclose(ext.centering_step(torch.as_tensor(q)[None])[0].numpy(), dq0, atol=1e-15)


def test_null_space_centering_moves_a_joint_away_from_its_limit_without_moving_the_hand():
    """At the goal (``e = 0``) and a small damping, the pose step is the centering step projected onto the
    Jacobian's null space: it changes neither the position nor the orientation to first order
    (``|J dq| <= 1e-3 |J| |dq0|``), and, with the other joints near mid-range, it moves a
    joint at its upper or lower limit back inside (each joint the 1-D self-motion moves at all)."""
    chain = iiwa14()
    rng = np.random.default_rng(7)
    lower, upper = chain.limits.numpy()
    w = 0.2
    ext = JointGoalExtractor(_space(goal_dim=9), "iiwa14", MAX_STEP, dampings=(1e-4,), orientation_weight=w,
                             null_space_centering=1.0, step_bound="clip")
    checked = 0
    for i in range(7):
        for side in (lower, upper):
            q = rng.uniform(-0.3, 0.3, 7)
            q[3] = -0.6  # the elbow bent: away from the stretched arm's singularity
            q[i] = side[i] - np.sign(side[i]) * 1e-3
            qt = torch.as_tensor(q)[None]
            jac = chain.jacobian(qt)
            jw = torch.cat([jac[:, :3], w * jac[:, 3:]], 1)  # (1, 6, 7)
            null = torch.linalg.svd(jw[0]).Vh[-1].numpy()
            step = ext.bounded_step(qt, jw, torch.zeros(1, 6, dtype=torch.float64))[0, 0].numpy() * MAX_STEP
            push = np.linalg.norm(ext.centering_step(qt)[0].numpy())  # |dq0|
            assert np.linalg.norm(jw[0].numpy() @ step) <= 1e-3 * np.linalg.norm(jw[0].numpy(), 2) * push
            assert np.linalg.norm(step - null * (null @ step)) <= 1e-3 * push  # along the null space
            if abs(null[i]) < 0.1:  # a joint the self-motion hardly moves here (joint 4 never moves in it)
                continue
            checked += 1
            assert -np.sign(side[i]) * step[i] > 0.01 * MAX_STEP[i], (i, step)
    assert checked >= 5


def test_last_joint_twist_is_the_turn_about_the_last_joints_axis():
    """A rotation error ``Rot(s, beta) Rot(z, alpha)`` with ``s`` perpendicular to the last joint's axis ``z``
    (a swing after a twist) has the twist ``alpha``, whatever the swing; the centering step then centres the
    last joint on ``q_n + alpha`` and leaves the others as they are."""
    from iiwa_torch import so3

    chain = iiwa14()
    rng = np.random.default_rng(8)
    w = 0.2
    ext = JointGoalExtractor(_space(goal_dim=9), "iiwa14", MAX_STEP, orientation_weight=w, null_space_centering=2.0,
                             centering_twist=True)
    lower, upper = chain.limits.numpy()
    q = torch.as_tensor(rng.uniform(lower, upper, (6, 7)))
    jac = chain.jacobian(q)
    z = jac[:, 3:, -1].numpy()
    s = np.cross(z, rng.normal(size=(6, 3)))
    s /= np.linalg.norm(s, axis=1, keepdims=True)
    alpha = np.array([0.0, 0.3, -1.2, 2.5, -3.0, 3.1])
    beta = np.array([0.0, 0.0, 0.4, -1.0, 2.0, 0.1])
    turn = so3.exp(torch.as_tensor(s * beta[:, None])) @ so3.exp(torch.as_tensor(z * alpha[:, None]))
    error = torch.cat([torch.zeros(6, 3, dtype=torch.float64), w * so3.log(turn)], 1)
    jw = torch.cat([jac[:, :3], w * jac[:, 3:]], 1)
    for xp_in in (lambda t: t, lambda t: t.numpy()):
        phi = ext.last_joint_twist(xp_in(jw), xp_in(error))
        np.testing.assert_allclose(np.asarray(phi), alpha, atol=1e-9)
    shifted = q.clone()
    shifted[:, -1] += torch.as_tensor(alpha)
    torch.testing.assert_close(ext.centering_step(q, torch.as_tensor(alpha)), ext.centering_step(shifted))
    torch.testing.assert_close(ext.centering_step(q, torch.as_tensor(alpha))[:, :-1], ext.centering_step(q)[:, :-1])


def test_centering_twist_needs_pose_goals_and_centering():
    with pytest.raises(ValueError, match="centering_twist needs pose goals"):
        JointGoalExtractor(_space(), max_step=MAX_STEP, null_space_centering=1.0, centering_twist=True)
    with pytest.raises(ValueError, match="centering_twist needs pose goals"):
        JointGoalExtractor(_space(goal_dim=9), max_step=MAX_STEP, centering_twist=True)
    with pytest.raises(TypeError, match="centering_twist must be True or False"):
        JointGoalExtractor(_space(goal_dim=9), max_step=MAX_STEP, null_space_centering=1.0, centering_twist=1)


@pytest.mark.parametrize("value", [-0.1, math.inf, math.nan, True, "1"])
def test_null_space_centering_must_be_a_non_negative_number(value):
    with pytest.raises(ValueError, match="null_space_centering must be a finite number >= 0"):
        JointGoalExtractor(_space(), max_step=MAX_STEP, null_space_centering=value)


def test_limit_rounds_must_be_a_count():
    with pytest.raises(ValueError, match="limit_rounds must be an int >= 0"):
        JointGoalExtractor(_space(), max_step=MAX_STEP, limit_rounds=-1)


def _observations(rows: int, goal_dim: int, dtype, rng) -> dict[str, torch.Tensor]:
    """Random observations of the clearance env's layout (``cos q, sin q``, velocities, then 4
    capsules' clearances and gradients from column 21): joints anywhere within their limits, row 0
    at the lower limits, row 1 at the upper ones, row 2 stretched out (q = 0); goal errors from
    1 m down to zero (the last row); pose goals turned by 0 to 3.1 rad; some capsules within reach."""
    from envs.goals import encode_pose_goal
    from iiwa_torch import so3

    chain = iiwa14()
    lower, upper = chain.limits.numpy()
    q = rng.uniform(lower, upper, (rows, 7))
    q[:3] = [lower, upper, np.zeros(7)][: rows]
    q[3::2, rng.integers(7)] = upper[0]  # one joint at a limit (the first joint's range is the widest)
    q = torch.as_tensor(q)
    pose = chain.fk(q)
    error = rng.normal(size=(rows, 3)) * np.geomspace(1.0, 1e-4, rows)[:, None]
    error[-1] = 0.0
    desired = pose.clone()
    desired[:, :3, 3] += torch.as_tensor(error)
    angles = np.resize([0.0, 1e-7, 1e-3, 0.5, 2.0, 3.1], rows)
    axes = rng.normal(size=(rows, 3))
    turn = so3.exp(torch.as_tensor(axes / np.linalg.norm(axes, axis=1, keepdims=True) * angles[:, None]))
    desired[:, :3, :3] = turn @ pose[:, :3, :3]
    if rows > 1:
        desired[-1] = pose[-1]
    goal = (lambda p: p[:, :3, 3]) if goal_dim == 3 else encode_pose_goal
    clearance = np.concatenate([rng.uniform(-0.02, 0.4, (rows, 4)), rng.normal(size=(rows, 28)) * 0.3], 1)
    obs = torch.cat([q.cos(), q.sin(), torch.as_tensor(rng.uniform(-1, 1, (rows, 7))), torch.as_tensor(clearance)], 1)
    return {"observation": obs.to(dtype), "achieved_goal": goal(pose).to(dtype),
            "desired_goal": goal(desired).to(dtype)}


@pytest.mark.parametrize("goal_dim, avoidance, limit_rounds, error_damping, step_bound, centering, extra", [
    (3, False, 0, 0.0, "shrink", 0.0, {}), (3, True, 0, 0.0, "shrink", 0.0, {}), (3, True, 3, 0.0, "shrink", 0.0, {}),
    (9, False, 3, 0.0, "shrink", 0.0, {}), (9, True, 3, 0.0, "shrink", 0.0, {}), (9, True, 3, 1.0, "clip", 0.0, {}),
    (3, False, 0, 0.0, "shrink", 1.0, {}), (9, True, 3, 1.0, "clip", 3.0, {}), (9, True, 3, 1.0, "clip", "twist", {}),
    (3, False, 3, 0.0, "shrink", 0.0, {"limit_hold": "limit"}), (3, True, 0, 0.0, "clip", 0.0, {"clip_guard": 0.3}),
    (9, True, 3, 1.0, "clip", "twist", {"limit_hold": "limit", "clip_guard": 0.3})])
def test_numpy_path_equals_the_torch_path(goal_dim, avoidance, limit_rounds, error_damping, step_bound, centering,
                                          extra, monkeypatch, small_kernel):
    """Up to NUMPY_ROWS rows without autograd the extractor runs in numpy (with numba, by one compiled
    kernel where it restates the options: ``small_kernel``); with NUMPY_ROWS = 0 the same observations
    take the torch path. Float64 observations: every feature agrees to 1e-12 (the DLS and damper solves
    by LU or by unrolled Cholesky instead of LAPACK's, the Jacobian and the pose goals' rotation error
    computed another way); float32 ones (the env's): to the last bit of float32."""
    import train.features
    from train.features import NUMPY_ROWS

    rng = np.random.default_rng(11)
    kwargs = {"avoidance": {"xi": 0.3, "safe": 0.005, "influence": 0.1}} if avoidance else {}
    kwargs.update(extra)
    ext = JointGoalExtractor(_space(21 + 4 * 8, goal_dim), "iiwa14", MAX_STEP, dampings=(0.1, 0.03),
                             orientation_weight=0.2, clearance_rows=(21, 4), limit_rounds=limit_rounds,
                             error_damping=error_damping, step_bound=step_bound,
                             null_space_centering=2.0 if centering == "twist" else centering,
                             centering_twist=centering == "twist", **kwargs)
    cases = [(rows, dtype) for rows in (1, 2, 7, NUMPY_ROWS) for dtype in (torch.float64, torch.float32)] * 3
    held = 0
    for rows, dtype in cases:
        obs = _observations(rows, goal_dim, dtype, rng)
        with monkeypatch.context() as patch:  # the numpy path takes no torch Jacobian; the kernel, no numpy path
            patch.setattr(ext.chain, "jacobian", None)
            if small_kernel == "compiled":
                patch.setattr(ext, "joint_features", None)
            fast = ext(obs)
        with monkeypatch.context() as patch:
            patch.setattr(train.features, "NUMPY_ROWS", 0)
            slow = ext(obs)
        assert fast.dtype == slow.dtype == dtype and fast.shape == slow.shape == (rows, ext.features_dim)
        if dtype == torch.float64:
            torch.testing.assert_close(fast, slow, rtol=0, atol=1e-12)
        else:
            torch.testing.assert_close(fast, slow, rtol=2.0 ** -23, atol=1e-12)
        if limit_rounds and extra.get("limit_hold", "still") == "still":
            steps = slow[:, ext.step_columns[0] : ext.step_columns[1]].double() * torch.as_tensor(MAX_STEP)
            q = torch.atan2(obs["observation"][:, 7:14], obs["observation"][:, :7]).double()
            at_limit = q[:-1] >= iiwa14().limits[1] - 1e-6  # the last row's error is zero: no step at all
            held += int((steps[:-1][at_limit] == 0).sum())
    if limit_rounds and extra.get("limit_hold", "still") == "still":
        assert held > 0  # some joints at their limits were held by the limit rounds


def test_the_options_are_one_checked_settings_object():
    """Keywords (a config's features_extractor_kwargs) and a JointSettings build the same frozen settings;
    the avoidance mapping becomes its named gains; every shipped joint-feature config still constructs."""
    import dataclasses
    from pathlib import Path

    import yaml

    from train.features import Avoidance, JointSettings

    gains = {"xi": 0.3, "safe": 0.02, "influence": 0.15}
    by_keywords = JointGoalExtractor(_space(60), "iiwa14", MAX_STEP, dampings=(0.1,), clearance_rows=[21, 4],
                                     avoidance=gains)
    settings = JointSettings(dampings=(0.1,), clearance_rows=(21, 4), avoidance=Avoidance(**gains))
    assert JointGoalExtractor(_space(60), "iiwa14", MAX_STEP, settings=settings).settings == by_keywords.settings
    assert by_keywords.settings.avoidance == Avoidance(0.3, 0.02, 0.15)
    with pytest.raises(dataclasses.FrozenInstanceError):
        settings.limit_rounds = 3
    policies = Path(__file__).resolve().parents[1] / "train" / "policies"
    configs = [yaml.safe_load(p.read_text()) for p in sorted(policies.glob("*/config.yaml"))]
    joint = [c["hyperparams"]["features_extractor_kwargs"] for c in configs
             if c["hyperparams"].get("features_extractor") == "joint"]
    assert len(joint) >= 3
    for kwargs in joint:
        options = {k: v for k, v in kwargs.items() if k not in ("robot", "max_step", "scales")}
        assert JointSettings(**options).dampings == tuple(kwargs["dampings"])
