"""Trajectories: jtraj against its boundary conditions, finite differences and roboticstoolbox;
ctraj against geometry and spatialmath's interpolation; tracking error and continuity; time scaling."""

import math

import numpy as np
import pytest
import torch

from iiwa_torch import Chain, compiled, robots, so3
from iiwa_torch.ik import solve
from iiwa_torch.trajectory import ctraj, jtraj, sampled_duration, shortest_duration, track

F64 = torch.float64


@pytest.fixture(scope="module")
def arm():
    return robots.iiwa14()


def _pair(n=7, batch=(), seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(*batch, n, generator=g, dtype=F64), torch.randn(*batch, n, generator=g, dtype=F64)


# ------------------------------------------------------------------ jtraj
def test_jtraj_boundary_conditions_with_time_vector_and_given_velocities():
    q0, q1 = _pair()
    qd0, qd1 = _pair(seed=1)
    t = torch.linspace(0.5, 3.0, 41, dtype=F64)  # a move that starts at 0.5 s and lasts 2.5 s
    tr = jtraj(q0, q1, t, qd0, qd1)
    assert tr.q.shape == tr.qd.shape == tr.qdd.shape == (41, 7)
    torch.testing.assert_close(tr.q[0], q0, rtol=0, atol=1e-12)
    torch.testing.assert_close(tr.q[-1], q1, rtol=0, atol=1e-12)
    torch.testing.assert_close(tr.qd[0], qd0, rtol=0, atol=1e-12)
    torch.testing.assert_close(tr.qd[-1], qd1, rtol=0, atol=1e-12)
    torch.testing.assert_close(tr.qdd[[0, -1]], torch.zeros(2, 7, dtype=F64), rtol=0, atol=1e-12)


def test_jtraj_rest_to_rest_closed_form():
    """Zero boundary velocities: symmetric about the midpoint, peak speed 15/8 |dq| / T there."""
    q0, q1 = _pair()
    duration = 2.0
    tr = jtraj(q0, q1, torch.linspace(0, duration, 21, dtype=F64))
    torch.testing.assert_close(tr.q[10], (q0 + q1) / 2, rtol=0, atol=1e-12)
    torch.testing.assert_close(tr.qd[10], 15 / 8 * (q1 - q0) / duration, rtol=0, atol=1e-12)
    torch.testing.assert_close(tr.qd.abs().amax(0), 15 / 8 * (q1 - q0).abs() / duration, rtol=0, atol=1e-12)


def test_jtraj_velocity_and_acceleration_match_finite_differences():
    q0, q1 = _pair()
    qd0, qd1 = _pair(seed=2)
    t = torch.linspace(0, 1.5, 3001, dtype=F64)
    tr = jtraj(q0, q1, t, qd0, qd1)
    h = float(t[1] - t[0])
    torch.testing.assert_close((tr.q[2:] - tr.q[:-2]) / (2 * h), tr.qd[1:-1], rtol=0, atol=1e-5)
    torch.testing.assert_close((tr.qd[2:] - tr.qd[:-2]) / (2 * h), tr.qdd[1:-1], rtol=0, atol=1e-4)


def test_jtraj_matches_roboticstoolbox():
    rtb = pytest.importorskip("roboticstoolbox")
    q0, q1 = _pair(6)
    qd0, qd1 = _pair(6, seed=3)
    t = np.linspace(0, 2.0, 25)
    ref = rtb.jtraj(q0.numpy(), q1.numpy(), t, qd0.numpy(), qd1.numpy())
    ours = jtraj(q0, q1, torch.from_numpy(t), qd0, qd1)
    for mine, theirs in ((ours.q, ref.q), (ours.qd, ref.qd), (ours.qdd, ref.qdd)):
        np.testing.assert_allclose(mine.numpy(), theirs, atol=1e-10)
    steps = jtraj(q0, q1, 25)  # step count: unit duration, as roboticstoolbox's integer form
    np.testing.assert_allclose(steps.q.numpy(), rtb.jtraj(q0.numpy(), q1.numpy(), 25).q, atol=1e-12)


def test_jtraj_batched_equals_looped_and_per_pair_durations():
    q0, q1 = _pair(batch=(3, 2))
    t = torch.linspace(0, 1, 11, dtype=F64) * torch.tensor([1.0, 2.0], dtype=F64)[:, None]  # (2, 11)
    batched = jtraj(q0, q1, t)
    assert batched.q.shape == (3, 2, 11, 7)
    for i in range(3):
        for j in range(2):
            single = jtraj(q0[i, j], q1[i, j], t[j])
            torch.testing.assert_close(batched.q[i, j], single.q, rtol=0, atol=1e-14)
            torch.testing.assert_close(batched.qd[i, j], single.qd, rtol=0, atol=1e-14)


def test_jtraj_one_pair_many_durations_with_velocities():
    q0, q1 = _pair()
    qd0 = torch.full((7,), 0.3, dtype=F64)
    t = torch.linspace(0, 1, 9, dtype=F64) * torch.tensor([1.0, 3.0], dtype=F64)[:, None]  # (2, 9)
    tr = jtraj(q0, q1, t, qd0=qd0)
    assert tr.q.shape == (2, 9, 7)
    torch.testing.assert_close(tr.qd[:, 0], qd0.expand(2, 7), rtol=0, atol=1e-12)
    torch.testing.assert_close(tr.q[1], jtraj(q0, q1, t[1], qd0=qd0).q, rtol=0, atol=1e-14)


def test_jtraj_gradients():
    q0, q1 = (x.requires_grad_() for x in _pair(3))
    assert torch.autograd.gradcheck(lambda a, b: jtraj(a, b, 7).q, (q0, q1))


@pytest.mark.parametrize(
    ("t", "error", "match"),
    [(1, ValueError, "at least 2"), (True, TypeError, "bool"), ([0.0, 1.0, 0.5], ValueError, "increasing")],
)
def test_jtraj_rejects_bad_times(t, error, match):
    q0, q1 = _pair()
    with pytest.raises(error, match=match):
        jtraj(q0, q1, t)


def test_jtraj_rejects_mismatched_joints():
    with pytest.raises(ValueError, match="broadcast together"):
        jtraj(torch.zeros(7, dtype=F64), torch.zeros(6, dtype=F64), 5)
    with pytest.raises(TypeError, match="q0 must be a float32 or float64 tensor"):
        jtraj(torch.zeros(7, dtype=torch.int64), torch.zeros(7, dtype=F64), 5)


# ------------------------------------------------------------------ ctraj
def _poses(arm, seed=0, batch=()):
    q = arm.random_q(*batch, 2, generator=torch.Generator().manual_seed(seed))
    pose = arm.fk(q)
    return pose[..., 0, :, :], pose[..., 1, :, :]


def test_ctraj_endpoints_straight_line_and_constant_speed(arm):
    T0, T1 = _poses(arm)
    path = ctraj(T0, T1, 31)
    assert path.shape == (31, 4, 4)
    torch.testing.assert_close(path[0], T0, rtol=0, atol=1e-12)
    torch.testing.assert_close(path[-1], T1, rtol=0, atol=1e-12)
    p = path[:, :3, 3]
    direction = (T1[:3, 3] - T0[:3, 3]) / (T1[:3, 3] - T0[:3, 3]).norm()
    off_line = (p - T0[:3, 3]) - ((p - T0[:3, 3]) @ direction)[:, None] * direction
    assert off_line.norm(dim=-1).max() < 1e-12
    step = p.diff(dim=0).norm(dim=-1)
    torch.testing.assert_close(step, torch.full_like(step, float(step.mean())), rtol=0, atol=1e-12)
    # constant angular rate about one fixed axis
    rel = so3.log(path[:-1, :3, :3].transpose(-1, -2) @ path[1:, :3, :3])  # body-frame increments
    torch.testing.assert_close(rel, rel[:1].expand_as(rel), rtol=0, atol=1e-10)
    # every pose is a proper transform
    rot = path[:, :3, :3]
    torch.testing.assert_close(
        rot @ rot.transpose(-1, -2), torch.eye(3, dtype=F64).expand(31, 3, 3), rtol=0, atol=1e-12
    )


def test_ctraj_matches_spatialmath_interp(arm):
    sm = pytest.importorskip("spatialmath")
    T0, T1 = _poses(arm, seed=4)
    s = np.linspace(0, 1, 9)
    ref = sm.SE3(T0.numpy(), check=False).interp(sm.SE3(T1.numpy(), check=False), s)
    np.testing.assert_allclose(ctraj(T0, T1, 9).numpy(), np.stack(ref.A), atol=1e-9)


def test_ctraj_quintic_profile_starts_and_stops_at_rest(arm):
    T0, T1 = _poses(arm, seed=5)
    path = ctraj(T0, T1, torch.linspace(0, 2, 201, dtype=F64), profile="quintic")
    p = path[:, :3, 3]
    step = p.diff(dim=0).norm(dim=-1)
    assert step[0] < 1e-3 * step.max() and step[-1] < 1e-3 * step.max()
    torch.testing.assert_close(p[100], (T0[:3, 3] + T1[:3, 3]) / 2, rtol=0, atol=1e-12)  # symmetric


def test_ctraj_batched(arm):
    T0, T1 = _poses(arm, seed=6, batch=(4,))
    path = ctraj(T0, T1, 5)
    assert path.shape == (4, 5, 4, 4)
    torch.testing.assert_close(path[2], ctraj(T0[2], T1[2], 5), rtol=0, atol=1e-14)


def test_ctraj_rejects_bad_profile(arm):
    T0, T1 = _poses(arm)
    with pytest.raises(ValueError, match="profile must be one of"):
        ctraj(T0, T1, 5, profile="trapezoid")


def test_ctraj_time_vectors_must_match_the_poses(arm):
    T0 = arm.fk(arm.random_q(3, generator=torch.Generator().manual_seed(0)))
    t = torch.tensor([[0.0, 1.0], [0.0, 2.0]], dtype=F64)  # 2 time vectors for 3 paths
    with pytest.raises(ValueError, match=r"the batch of t .* \(2,\), of T0 .* \(3,\)"):
        ctraj(T0, T0.flip(0), t)
    assert ctraj(T0, T0.flip(0), t[:1]).shape == (3, 2, 4, 4)


# ------------------------------------------------------------------ tracking
def _line(arm, q0, offset, steps):
    T0 = arm.fk(q0)
    T1 = T0.clone()
    T1[..., :3, 3] += torch.tensor(offset, dtype=F64)
    return ctraj(T0, T1, steps)


Q_START = torch.tensor([0.1, 0.5, 0.1, -1.2, 0.2, 0.8, 0.3], dtype=F64)


@pytest.mark.parametrize("method", ["gradient", "analytic"])
def test_track_reachable_line_accurate_and_continuous(arm, method):
    path = _line(arm, Q_START, [0.0, 0.3, -0.2], 40)  # 0.36 m line
    res = track(arm, path, Q_START, method=method)
    assert res.q.shape == (40, 7)
    assert res.pos_err.max() <= 1e-6
    assert res.rot_err.max() <= 1e-6
    assert bool(res.success.all())
    assert bool(arm.within_limits(res.q).all())
    # 40 steps of 9 mm: a continuous joint path moves a few hundredths of a rad per step
    assert res.max_step < 0.05
    torch.testing.assert_close(res.max_step, res.q.diff(dim=0).abs().max(), rtol=0, atol=0)
    # the errors reported are those of fk(q), recomputed here
    pos, _ = so3.pose_error(arm.fk(res.q), path)
    torch.testing.assert_close(res.pos_err, pos.norm(dim=-1), rtol=0, atol=1e-15)


@pytest.mark.parametrize("method", ["gradient", "analytic"])
def test_track_through_a_shoulder_alignment_stays_continuous(arm, method):
    """q2 passes through 0 (joints 1 and 3 aligned) on this line: only q1 + q3 is fixed there,
    and holding the arm angle would swing q1 and q3 by ~1.4 rad; the smallest step is 0.016 rad."""
    q0 = torch.tensor([0.341, 0.07, -0.014, -1.315, 0.048, 0.819, 0.405], dtype=F64)
    res = track(arm, _line(arm, q0, [-0.006, -0.092, -0.082], 30), q0, method=method)
    assert res.pos_err.max() <= 1e-6 and bool(res.success.all())
    assert res.max_step < 0.03
    assert res.q[:, 1].min() < 0 < res.q[:, 1].max()  # it really crosses q2 = 0


def test_track_analytic_and_gradient_agree_away_from_singularities(arm):
    path = _line(arm, Q_START, [0.0, 0.3, -0.2], 40)
    a, g = (track(arm, path, Q_START, method=m) for m in ("analytic", "gradient"))
    # both take (close to) the smallest joint step at each pose, so the paths nearly coincide
    assert (a.q - g.q).abs().max() < 0.02


def test_track_batched_paths(arm):
    q0 = Q_START + 0.3 * torch.randn(3, 7, generator=torch.Generator().manual_seed(2), dtype=F64)
    path = _line(arm, q0, [0.0, 0.0, -0.05], 10)
    res = track(arm, path, q0, method="gradient")
    assert res.q.shape == (3, 10, 7) and res.max_step.shape == (3,) and res.pos_err.shape == (3, 10)
    assert res.pos_err.max() <= 1e-6 and res.max_step.max() < 0.05
    for i in range(3):
        single = track(arm, path[i], q0[i], method="gradient")
        torch.testing.assert_close(single.q, res.q[i], rtol=0, atol=1e-9)


@pytest.mark.parametrize("method", ["gradient", "analytic"])
def test_track_one_path_from_several_starts(arm, method):
    """q0 (3, n) with one path (T, 4, 4): three tracks of the same path, as the batch shapes broadcast."""
    q0 = Q_START + 0.01 * torch.randn(3, 7, generator=torch.Generator().manual_seed(4), dtype=F64)
    path = _line(arm, Q_START, [0.0, 0.0, -0.05], 6)
    res = track(arm, path, q0, method=method)
    assert res.q.shape == (3, 6, 7) and res.success.all()
    torch.testing.assert_close(res.q[1], track(arm, path, q0[1], method=method).q, rtol=0, atol=1e-9)


def _solve_per_pose(arm, path, q0, pos_tol=1e-7, rot_tol=1e-6, rest_gain=0.0):
    """The gradient method as one ik.solve per pose, each from the last answer (q0 first)."""
    q, out = q0.to(path.dtype), []
    for k in range(path.shape[-3]):
        q = solve(arm, path[..., k, :, :], q, pos_tol=pos_tol, rot_tol=rot_tol, seeds=1, iterations=50,
                  rest=q0.to(path.dtype) if rest_gain else None, rest_gain=rest_gain).q
        out.append(q)
    return torch.stack(out, -2)


@pytest.mark.parametrize("compiled_on", [True, False])
@pytest.mark.parametrize(
    "case",
    ["one line", "three lines", "rest gain", "float32", "loose tolerances", "q0 outside the limits"],
)
def test_track_small_path_equals_one_solve_per_pose(arm, monkeypatch, case, compiled_on):
    """A few CPU paths take the whole loop in one call (ik.lm_compiled.track_compiled): the answers of one
    ik.solve per pose (the loop it replaces), bit for bit, and of the batched torch loop that a
    q0 requiring grad takes, to rounding."""
    if not compiled_on:
        monkeypatch.setattr(compiled, "ENABLED", False)
    gen = torch.Generator().manual_seed(5)
    batch = (3,) if case == "three lines" else ()
    q0 = Q_START + 0.2 * torch.randn(*batch, 7, generator=gen, dtype=F64)
    if case == "q0 outside the limits":
        q0[6] = 3.1  # beyond joint 7's 175 deg: solve shifts or clamps it into the limits
    path = _line(arm, q0, [0.05, -0.08, 0.06], 25)
    options = {"rest gain": {"rest_gain": 0.3}, "loose tolerances": {"pos_tol": 1e-4, "rot_tol": 1e-3}}.get(case, {})
    if case == "float32":
        path, q0 = path.float(), q0.float()
    res = track(arm, path, q0, **options)
    expected = _solve_per_pose(arm, path, q0, **options)
    assert res.q.dtype == path.dtype and res.q.shape == (*batch, 25, 7)
    torch.testing.assert_close(res.q, expected, rtol=0, atol=0)
    torch_loop = track(arm, path, q0.clone().requires_grad_(True), **options)
    torch.testing.assert_close(res.q, torch_loop.q, rtol=0, atol=1e-5 if case in ("float32", "loose tolerances")
                               else 1e-9)  # fmt: skip
    torch.testing.assert_close(res.pos_err, torch_loop.pos_err, rtol=0, atol=1e-5)


@pytest.mark.parametrize("method", ["gradient", "analytic"])
def test_track_reports_the_jump_near_a_wrist_singularity(arm, method):
    """q6 = 0.054 rad: 5 mm of motion needs 0.7 rad of joints 5 and 7; max_step must say so."""
    q0 = torch.tensor([1.2389, -0.8442, 0.6194, 0.0843, 1.2262, 0.0539, -1.1594], dtype=F64)
    res = track(arm, _line(arm, q0, [0.0, 0.0, -0.05], 10), q0, method=method)
    assert res.pos_err.max() <= 1e-6
    assert res.max_step > 0.5


def test_track_analytic_6r_arm():
    puma = robots.puma560()
    q0 = torch.tensor([0.2, 0.6, -0.4, 0.3, 0.7, 0.1], dtype=F64)
    res = track(puma, _line(puma, q0, [0.05, -0.1, 0.05], 20), q0, method="analytic")
    assert res.pos_err.max() <= 1e-9 and res.max_step < 0.05
    torch.testing.assert_close(res.q[0], q0, rtol=0, atol=1e-9)  # the branch of q0 is kept


@pytest.mark.parametrize("name", ["puma560", "lrmate200ic"])
def test_track_analytic_follows_a_wrist_across_half_a_turn(name):
    """q6 from 170 to 190 degrees (inside both arms' limits) one degree a step: the configurations
    themselves are the smooth answer, which the closed forms give as angles in [-pi, pi]."""
    arm = getattr(robots, name)()
    q = torch.tensor([0.3, 0.6, -0.8, 0.4, 0.7, 0.0], dtype=F64).repeat(21, 1)
    q[:, 5] = torch.linspace(math.radians(170), math.radians(190), 21, dtype=F64)
    assert arm.within_limits(q).all()
    res = track(arm, arm.fk(q), q[0], method="analytic")
    torch.testing.assert_close(res.q, q, rtol=0, atol=1e-9)


def test_track_rejects_bad_method_and_shapes(arm):
    path = _line(arm, Q_START, [0.0, 0.0, 0.1], 3)
    with pytest.raises(ValueError, match="method must be one of"):
        track(arm, path, Q_START, method="newton")
    with pytest.raises(ValueError, match=r"\(\.\.\., T, 4, 4\)"):
        track(arm, path[0], Q_START)
    with pytest.raises(ValueError, match="do not broadcast"):
        track(arm, path.expand(2, 3, 4, 4), Q_START.expand(3, 7))
    with pytest.raises(ValueError, match="'planar3r' is a DHChain of 3 joints \\(use method='gradient'\\)"):
        track(robots.planar3r(), path, torch.zeros(3, dtype=F64), method="analytic")
    urdf_arm = Chain(torch.eye(4, dtype=F64).repeat(7, 1, 1), [[0, 0, 1]] * 7)  # as from_urdf builds
    with pytest.raises(ValueError, match="is a Chain of 7 joints \\(use method='gradient'\\)"):
        track(urdf_arm, path, Q_START, method="analytic")


# ------------------------------------------------------------------ time scaling
def test_shortest_duration_respects_and_reaches_speed_limits(arm):
    q0, q1 = arm.random_q(2, 5, generator=torch.Generator().manual_seed(7))
    duration = shortest_duration(arm, q0, q1)  # (5,)
    assert duration.shape == (5,)
    t = torch.linspace(0, 1, 101, dtype=F64) * duration[:, None]  # odd count: the midpoint is sampled
    speed_ratio = (jtraj(q0, q1, t).qd.abs() / arm.velocity_limits).amax((-2, -1))
    assert (speed_ratio <= 1 + 1e-12).all()
    torch.testing.assert_close(speed_ratio, torch.ones(5, dtype=F64), rtol=0, atol=1e-12)  # and no slower
    # datasheet check by hand: A1 moving 85 deg at 85 deg/s alone takes 15/8 s
    q_a1 = torch.zeros(7, dtype=F64)
    q_a1[0] = math.radians(85)
    assert float(shortest_duration(arm, torch.zeros(7, dtype=F64), q_a1)) == pytest.approx(15 / 8, abs=1e-12)
    half = shortest_duration(arm, torch.zeros(7, dtype=F64), q_a1, speed_scale=0.5)
    assert float(half) == pytest.approx(15 / 4, abs=1e-12)


def test_sampled_duration_respects_speed_limits(arm):
    res = track(arm, _line(arm, Q_START, [0.0, 0.3, -0.2], 20), Q_START, method="analytic")
    duration = sampled_duration(arm, res.q)
    dt = duration / 19
    ratio = (res.q.diff(dim=0).abs() / dt / arm.velocity_limits).max()
    assert float(ratio) == pytest.approx(1.0, abs=1e-12)


def test_time_scaling_needs_speed_limits():
    with pytest.raises(ValueError, match="no velocity_limits"):
        shortest_duration(robots.puma560(), torch.zeros(6, dtype=F64), torch.ones(6, dtype=F64))


@pytest.mark.parametrize("name", ["q0", "q1", "qd0", "qd1"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_jtraj_rejects_non_finite_inputs_like_ctraj(name, bad):
    args = {key: torch.zeros(3, 7, dtype=torch.float64) for key in ("q0", "q1", "qd0", "qd1")}
    args[name][1, 4] = bad
    with pytest.raises(ValueError, match=rf"{name} contains NaN or inf \(first at index \(1, 4\)\)"):
        jtraj(args["q0"], args["q1"], 10, args["qd0"], args["qd1"])
    T = torch.eye(4, dtype=torch.float64).expand(3, 4, 4).clone()
    T[1, 0, 3] = bad
    with pytest.raises(ValueError, match="T1 contains NaN or inf"):
        ctraj(torch.eye(4, dtype=torch.float64), T, 10)
