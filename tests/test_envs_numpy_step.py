"""One environment's step (numpy, :data:`envs.arrays.NUMPY`, and the float clearance) against the
batched torch step of the same states: 140 environments, above every small-batch threshold
(clearance's numpy path, the 4x4-product FK kernels), so the batch runs the torch kernels."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import envs
from envs import arrays
from envs.core import ReachState
from iiwa_torch import compiled

N = 140  # > SMALL_BATCH (128) and > CLEARANCE_NUMPY_BATCH (32): the batch takes torch's kernels
STEPS = 20
needs_numba = pytest.mark.skipif(not compiled.ENABLED, reason="numba not installed or IIWA_TORCH_NUMBA=0")


def _column(state: ReachState, i: int) -> ReachState:
    return ReachState(*(x[..., i : i + 1].contiguous() for x in state))


@pytest.fixture
def numpy_ops(monkeypatch):
    """Counts NUMPY.clip calls (one per single-env step), to show the path taken."""
    calls = []
    real = arrays.NUMPY.clip

    def spy(x, low, high):
        calls.append(x.shape)
        return real(x, low, high)

    monkeypatch.setattr(arrays.NUMPY, "clip", spy)
    return calls


@pytest.mark.parametrize(("env_id", "collision"), [("IiwaReach-v0", "terminate"), ("IiwaReachPose-v0", "penalize"),
                                                   ("IiwaReachObstacles-v0", "terminate"),
                                                   ("FrankaReach-v0", "terminate"), ("FrankaReachPose-v0", "penalize")])
def test_single_env_step_equals_the_batched_torch_step(env_id, collision, numpy_ops):
    floor = 0.1 if env_id.startswith("Franka") else 0.2  # raised: more collisions (the Panda's home is above 0.1 m)
    task = envs.make_task(env_id, collision=collision, start="random", max_episode_steps=10, floor=floor)
    rng = np.random.default_rng(3)
    with torch.inference_mode():
        state = task.reset_all(None, list(range(N)), rng)
        hits = restarts = 0
        for _ in range(STEPS):
            action = rng.uniform(-1.3, 1.3, size=(N, 7)).astype(np.float32)
            action[: N // 4, 1] = 1.0  # a quarter swing the shoulder down: into the floor or an obstacle
            a = task.transport.check_action(action, N)
            want_state, want = task.step(state, a)
            assert not numpy_ops  # the batch: torch
            clear = task.world.clearance(want_state.q.T, state.obstacles if task.world.slots else None)
            for i in range(N):
                got_state, got = task.step(_column(state, i), a[:, i : i + 1].contiguous())
                # integration, trigonometry, step count: the same ops, bit for bit
                for name in ("q", "cos_q", "sin_q", "velocity", "t"):
                    assert torch.equal(getattr(got_state, name)[..., 0], getattr(want_state, name)[..., i]), name
                # FK by another kernel (float recursion against Horner's): float32 rounding
                torch.testing.assert_close(got_state.achieved[:, 0], want_state.achieved[:, i], rtol=0, atol=2e-6)
                torch.testing.assert_close(got.distance[0], want.distance[i], rtol=0, atol=3e-6)
                if want.angle is None:
                    torch.testing.assert_close(got.reward[0], want.reward[i], rtol=0, atol=3e-6)
                else:  # near a half turn the arcsine amplifies the goals' rounding (1e-4 rad at 3.1 rad):
                    # compare the chord 8 sin^2(angle / 2) it comes from, and the reward without its angle term
                    w = task.goals.orientation_weight
                    torch.testing.assert_close(8 * torch.sin(got.angle[0] / 2) ** 2,
                                               8 * torch.sin(want.angle[i] / 2) ** 2, rtol=0, atol=3e-5)
                    torch.testing.assert_close(got.reward[0] + w * got.angle[0], want.reward[i] + w * want.angle[i],
                                               rtol=0, atol=3e-6)
                near = abs(float(clear[i])) < 1e-5  # a collision flag on the boundary may go either way
                if not near:
                    assert bool(got.collision[0]) == bool(want.collision[i])
                    assert bool(got.terminated[0]) == bool(want.terminated[i]) or bool(want.success[i])
                assert bool(got.truncated[0]) == bool(want.truncated[i])
            assert len(numpy_ops) == N and numpy_ops[0] == (7, 1)
            numpy_ops.clear()
            hits += int(want.collision.sum())
            done = want.terminated | want.truncated
            restarts += int(done.sum())
            state, _ = task.step_autoreset(state, a)  # new episodes (goals, obstacles) where done
    assert hits > 20 and restarts > N  # collisions, and many new episodes


def test_single_env_reward_is_compute_reward_bit_for_bit():
    """Through gymnasium.make (the numpy step): the step's reward is compute_reward's (torch) exactly."""
    import gymnasium as gym

    rng = np.random.default_rng(0)
    for env_id in ("IiwaReach-v0", "IiwaReachPose-v0", "IiwaReachObstacles-v0", "IiwaReachSparse-v0"):
        env = gym.make(env_id, collision="penalize").unwrapped
        env.reset(seed=1)
        collided = 0
        for _ in range(300):
            action = rng.uniform(-1, 1, 7).astype(np.float32)
            action[1] = 1.0
            obs, reward, terminated, truncated, info = env.step(action)
            assert reward == env.compute_reward(obs["achieved_goal"], obs["desired_goal"], info)
            collided += info["collision"]
            if terminated or truncated:
                env.reset()
        assert collided > 10


@needs_numba
@pytest.mark.parametrize("options", [
    {"env_id": "IiwaReach-v0", "floor": 0.2},
    {"env_id": "IiwaReachSparse-v0", "collision": "penalize", "terminate_on_success": False, "floor": 0.2},
    {"env_id": "IiwaReach-v0", "collision": "off", "max_episode_steps": None},
    {"env_id": "IiwaReach-v0", "floor": None},
    {"env_id": "FrankaReach-v0", "floor": 0.1, "goal_region": "panda_gym"},
])
def test_compiled_single_env_step_equals_the_numpy_step(options):
    """envs.compiled_step's one-call step against the step's numpy formulas (task.step, then pack) from
    the same states: every result bit for bit, but the cosines and sines of q within one unit in the
    last place (the kernel's are correctly rounded, torch's not always); collisions, successes,
    truncations and the sparse reward all occur."""
    options = dict(options)
    # a wide success radius: successes among random actions
    options.setdefault("max_episode_steps", 10)
    task = envs.make_task(options.pop("env_id"), start="random", distance_threshold=0.3, **options)
    assert task._step_constants is not None  # the compiled path applies to these tasks
    rng = np.random.default_rng(5)
    nj, seen = task.arm.n_joints, np.zeros(4, dtype=np.int64)
    with torch.inference_mode():
        states = task.reset_all(None, list(range(40)), rng)
    for i in range(40):
        state = _column(states, i)
        for _ in range(12):
            action = rng.uniform(-1.3, 1.3, size=nj).astype(np.float32)
            action[1] = 1.0  # the shoulder down: into the floor
            got_state, got_floats, got_flags = task.step_one(state, action)
            with torch.inference_mode():
                want_state, res = task.step(state, task.transport.check_action(action, 1))
                want_floats, want_flags = (p.numpy()[:, 0] for p in task.transport.pack(want_state, res))
            np.testing.assert_array_max_ulp(got_floats[: 2 * nj], want_floats[: 2 * nj], maxulp=1)
            np.testing.assert_array_equal(got_floats[2 * nj :], want_floats[2 * nj :])
            np.testing.assert_array_equal(got_flags, want_flags)
            for name in ("q", "velocity", "goal", "achieved", "t", "key", "episode"):
                assert torch.equal(getattr(got_state, name), getattr(want_state, name)), name
            seen[: len(got_flags)] += got_flags
            state = got_state
    terminated, truncated, success, collision = seen
    assert success and (collision or task.world is None or task.world.floor is None)
    assert terminated or not (task.terminate_on_success or task.collision == "terminate")
    assert truncated or task.max_episode_steps is None


@pytest.mark.parametrize("options", [{"env_id": "IiwaReachPose-v0"}, {"env_id": "IiwaReachObstacles-v0"},
                                     {"env_id": "IiwaReach-v0", "dtype": torch.float64},
                                     {"env_id": "IiwaReach-v0", "observe_clearance": True}])
def test_single_env_tasks_the_kernel_does_not_cover_take_the_numpy_step(options):
    options = dict(options)
    task = envs.make_task(options.pop("env_id"), **options)
    assert task._step_constants is None
    with torch.inference_mode():
        state = task.reset_all(None, [0], np.random.default_rng(0))
    _, floats, flags = task.step_one(state, np.zeros(7, dtype=np.float32))
    assert floats.shape == (task.transport.packed_size + 2 + (task.goal_kind.value == "pose"),)


@needs_numba
@pytest.mark.parametrize("options", [
    {"env_id": "IiwaReach-v0", "floor": 0.2},  # a raised floor: both candidates collide at times, later rounds draw
    {"env_id": "IiwaReachSparse-v0", "floor": None},
    {"env_id": "IiwaReach-v0", "collision": "off"},
    {"env_id": "FrankaReach-v0", "floor": 0.1},
    {"env_id": "FrankaReachPandaGym-v0"},
])
def test_compiled_resets_equal_the_torch_reset(options):
    """envs.compiled_step's resets against the torch formulas' (a task whose compiled paths are off), over
    20 keys of 20 episodes: one env's (reset_one; state and packed rows bit for bit, cos and sin of home
    within one unit in the last place), and a batch's goals (reset_all of 400 envs, draw_goals): each
    env's as one env's, bit for bit, and the torch batch's to its float32 FK's rounding."""
    options = dict(options)
    env_id = options.pop("env_id")
    task, reference = envs.make_task(env_id, **options), envs.make_task(env_id, **options)
    assert task._reset_constants is not None
    reference._step_constants = reference._reset_constants = None  # the torch formulas
    nj, rng, first_goals = task.arm.n_joints, np.random.default_rng(0), []
    for seed in range(20):
        state = None
        for episode in range(20):
            got_state, got_floats, got_flags = task.reset_one(state, seed if episode == 0 else None, rng)
            if episode == 0:
                first_goals.append(got_state.goal[:, 0])
            want_state, want_floats, want_flags = reference.reset_one(state, seed if episode == 0 else None, rng)
            np.testing.assert_array_max_ulp(got_floats[: 2 * nj], want_floats[: 2 * nj], maxulp=1)
            np.testing.assert_array_equal(got_floats[2 * nj :], want_floats[2 * nj :])
            np.testing.assert_array_equal(got_flags, want_flags)
            for name in ("q", "velocity", "goal", "achieved", "t", "key", "episode", "obstacles", "clearance"):
                assert torch.equal(getattr(got_state, name), getattr(want_state, name)), name
            state = got_state
    with torch.inference_mode():  # a batch draws each env's goal as one env does; torch's batch FK rounds in float32
        batch = task.reset_all(None, list(range(400)), rng)
        assert torch.equal(batch.goal[:, :20], torch.stack(first_goals, 1))
        torch.testing.assert_close(batch.goal, reference.reset_all(None, list(range(400)), rng).goal, rtol=0, atol=2e-6)
        later = task.reset_all(batch, [None] * 400, rng)  # the next episodes
        torch.testing.assert_close(later.goal, reference.reset_all(batch, [None] * 400, rng).goal, rtol=0, atol=2e-6)


@needs_numba
def test_compiled_goal_draws_split_over_threads_without_changing_them(monkeypatch):
    """From GOAL_THREADS_BATCH envs a reset's compiled goal draws run one part per torch thread (the
    kernel releases the GIL): the same goals as one call, with parts of unequal size."""
    import envs.core

    task = envs.make_task("FrankaReach-v0", floor=0.1)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        with torch.inference_mode():
            one = task.reset_all(None, list(range(301)), np.random.default_rng(0)).goal
        monkeypatch.setattr(envs.core, "GOAL_THREADS_BATCH", 1)
        torch.set_num_threads(3)
        with torch.inference_mode():
            split = task.reset_all(None, list(range(301)), np.random.default_rng(0)).goal
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(split, one)


@needs_numba
@pytest.mark.parametrize("robot", ["lrmate200ic", "odd"])
def test_compiled_step_takes_offsets_prismatic_and_far_turned_continuous_joints(robot):
    """The compiled step's other branches against the numpy step: a joint offset (the LR Mate's
    joint 2: the observation's angles are not the frames'), a prismatic joint and a continuous one
    turned beyond sin_cos's range (libm's instead; the hand-written URDF of tests/urdf_samples.py)."""
    from urdf_samples import ODD_URDF

    from iiwa_torch import robots
    from iiwa_torch.compiled.clearance_kernels import SIN_COS_RANGE

    chain = robots.lrmate200ic() if robot == "lrmate200ic" else robots.from_urdf(ODD_URDF, end_link="tip")
    chain.velocity_limits = torch.full((chain.n_joints,), 1.5, dtype=torch.float64)
    task, reference = (envs.core.ReachTask(chain, collision="off", start="random") for _ in range(2))
    reference._step_constants = None  # the numpy formulas
    assert task._step_constants is not None
    nj, rng = chain.n_joints, np.random.default_rng(7)
    with torch.inference_mode():
        states = task.reset_all(None, list(range(20)), rng)
    for i in range(20):
        state = _column(states, i)
        if robot == "odd" and i % 2:  # the continuous joint turned so far (1e15 rad) that sin_cos would be wrong
            state = state._replace(q=state.q + torch.tensor([[0.0], [0.0], [1e10 * SIN_COS_RANGE], [0.0]]))
        for _ in range(5):
            action = rng.uniform(-1.2, 1.2, size=nj).astype(np.float32)
            got_state, got, got_flags = task.step_one(state, action)
            _, want, want_flags = reference.step_one(state, action)
            np.testing.assert_array_max_ulp(got[: 2 * nj], want[: 2 * nj], maxulp=1)  # cos q, sin q
            np.testing.assert_array_equal(got[2 * nj : 3 * nj], want[2 * nj : 3 * nj])  # the motion
            np.testing.assert_allclose(got[3 * nj :], want[3 * nj :], rtol=0, atol=1e-6)  # goals, reward, distance
            np.testing.assert_array_equal(got_flags, want_flags)
            state = got_state
