"""Facts of the Reacher family (ReacherVertical, ReacherTurn, ReacherPush) that the generic
environment tests do not cover: reward formulas, observation layouts, starting states and the
physics of the shared arm and of each task's object."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
import pytest

import ede_envs  # noqa: F401  (registers the ede/ ids)
from ede_envs.reacher import ReacherFamilyEnv
from tests.support import unwrapped

VERTICAL, TURN, PUSH = "ede/ReacherVertical-v0", "ede/ReacherTurn-v0", "ede/ReacherPush-v0"
REACHER_IDS = (VERTICAL, TURN, PUSH)

ARM_BASE_XZ = np.array([0.0, 0.25])
LINK_LENGTH = 0.2
FINGERTIP_OFFSET = 0.21  # along the second link
SPINNER_HINGE_XZ = np.array([0.35, 0.25])
SPINNER_TIP_RADIUS = 0.14
SPINNER_TARGET_RADIUS = 0.15
N_RESETS = 300


def _spec_reward(env_id: str, info: dict[str, Any]) -> float:
    """The reward as the spec writes it, from the raw quantities in ``info``."""
    ctrl = info["action_norm_sq"]
    if env_id == VERTICAL:
        return -np.linalg.norm(info["fingertip_xz"] - info["target_xz"]) - ctrl
    if env_id == TURN:
        return -10 * np.linalg.norm(info["tip_xz"] - info["target_xz"]) - 0.5 * ctrl
    return (
        -10 * np.linalg.norm(info["box_xz"] - info["target_xz"])
        - 0.5 * np.linalg.norm(info["fingertip_xz"] - info["box_xz"])
        - ctrl
    )


@pytest.fixture
def make_env() -> Iterator[Callable[[str], ReacherFamilyEnv]]:
    """Make unwrapped Reacher envs, closing them after the test."""
    envs: list[gym.Env] = []

    def make(env_id: str) -> ReacherFamilyEnv:
        env = gym.make(env_id)
        envs.append(env)
        return unwrapped(env, ReacherFamilyEnv)

    yield make
    for env in envs:
        env.close()


def _rollout(
    env: ReacherFamilyEnv, seed: int, n_steps: int
) -> Iterator[tuple[np.ndarray, np.ndarray, float, bool, bool, dict[str, Any]]]:
    """Random actions (from their own seeded generator) after ``reset(seed=seed)``."""
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    for _ in range(n_steps):
        action = rng.uniform(-1, 1, size=2).astype(np.float32)
        observation, reward, terminated, truncated, info = env.step(action)
        yield action, observation, reward, terminated, truncated, info


def _resets(env: ReacherFamilyEnv, n: int) -> Iterator[np.ndarray]:
    for seed in range(n):
        observation, _ = env.reset(seed=seed)
        yield observation


# Rewards


@pytest.mark.parametrize("env_id", REACHER_IDS)
def test_reward_matches_spec_formula(env_id: str, make_env) -> None:
    env = make_env(env_id)
    for seed in range(3):
        for action, _, reward, terminated, truncated, info in _rollout(env, seed, 40):
            assert reward == pytest.approx(_spec_reward(env_id, info), rel=1e-12, abs=1e-12)
            assert info["action_norm_sq"] == pytest.approx(float(np.sum(np.square(action))))
            assert not terminated and not truncated


@pytest.mark.parametrize("env_id", REACHER_IDS)
def test_info_positions_are_the_simulated_ones(env_id: str, make_env) -> None:
    env = make_env(env_id)
    for *_, info in _rollout(env, seed=0, n_steps=20):
        np.testing.assert_array_equal(info["target_xz"], env.data.body("target").xpos[[0, 2]])
        if env_id == TURN:
            np.testing.assert_array_equal(info["tip_xz"], env.data.site("spinner_tip").xpos[[0, 2]])
        else:
            fingertip = env.data.body("fingertip").xpos[[0, 2]]
            np.testing.assert_array_equal(info["fingertip_xz"], fingertip)
        if env_id == PUSH:
            np.testing.assert_array_equal(info["box_xz"], env.data.body("box").xpos[[0, 2]])


@pytest.mark.parametrize(
    ("env_id", "terms"),
    [
        (VERTICAL, {"reward_dist", "reward_ctrl"}),
        (TURN, {"reward_dist", "reward_ctrl"}),
        (PUSH, {"reward_dist", "reward_near", "reward_ctrl"}),
    ],
)
def test_reward_terms_sum_to_reward(env_id: str, terms: set[str], make_env) -> None:
    env = make_env(env_id)
    for *_, reward, _, _, info in _rollout(env, seed=1, n_steps=40):
        assert {key for key in info if key.startswith("reward_")} == terms
        assert sum(info[key] for key in terms) == pytest.approx(reward, rel=1e-12, abs=1e-12)


def test_info_keeps_its_arrays_after_later_steps(make_env) -> None:
    env = make_env(VERTICAL)
    steps = list(_rollout(env, seed=0, n_steps=5))
    first_info = steps[0][-1]
    assert not np.array_equal(first_info["fingertip_xz"], env.fingertip_xz)


def test_episode_is_truncated_at_100_steps_and_never_terminated() -> None:
    env = gym.make(VERTICAL)
    env.reset(seed=0)
    for step in range(1, 101):
        *_, terminated, truncated, _ = env.step(env.action_space.sample())
        assert not terminated
        assert truncated == (step == 100)
    env.close()


# Observations


@pytest.mark.parametrize(("env_id", "size"), [(VERTICAL, 10), (TURN, 11), (PUSH, 14)])
def test_observation_layout(env_id: str, size: int, make_env) -> None:
    env = make_env(env_id)
    assert env.observation_space.shape == (size,)
    for _, observation, *_ in _rollout(env, seed=2, n_steps=30):
        qpos, qvel = env.data.qpos, env.data.qvel
        target_xz = env.data.body("target").xpos[[0, 2]]
        np.testing.assert_allclose(observation[0:2], np.cos(qpos[:2]))
        np.testing.assert_allclose(observation[2:4], np.sin(qpos[:2]))
        if env_id == VERTICAL:
            np.testing.assert_allclose(observation[4:6], target_xz)
            np.testing.assert_allclose(observation[6:8], qvel)
            fingertip_xz = env.data.body("fingertip").xpos[[0, 2]]
            np.testing.assert_allclose(observation[8:10], fingertip_xz - target_xz)
        elif env_id == TURN:
            np.testing.assert_allclose(observation[4:6], target_xz)
            np.testing.assert_allclose(observation[6:9], qvel)
            np.testing.assert_allclose(observation[9:11], env.data.site("spinner_tip").xpos[[0, 2]])
        else:
            box = env.data.body("box")
            np.testing.assert_allclose(observation[4:6], box.xpos[[0, 2]])  # box_x, box_z
            np.testing.assert_allclose(observation[6], qpos[4])  # box_angle
            np.testing.assert_allclose(observation[7:9], target_xz)
            np.testing.assert_allclose(observation[9:14], qvel)


def test_turn_observation_stays_bounded_while_the_spinner_winds_up(make_env) -> None:
    env = make_env(TURN)
    env.reset(seed=0)
    qpos = env.data.qpos.copy()
    qpos[2] = 40 * np.pi  # twenty turns
    env.set_state(qpos, env.data.qvel.copy())
    observation, *_ = env.step(np.zeros(2, dtype=np.float32))
    assert np.all(np.abs(observation[:6]) <= 1) and np.all(np.abs(observation[9:]) <= 1)


# Starting states


@pytest.mark.parametrize("env_id", REACHER_IDS)
def test_reset_arm_is_spread_contact_free_and_nearly_at_rest(env_id: str, make_env) -> None:
    env = make_env(env_id)
    positions, velocities = [], []
    for _ in _resets(env, N_RESETS):
        assert env.data.ncon == 0
        positions.append(env.data.qpos[:2].copy())
        velocities.append(env.data.qvel[:2].copy())
    arm_qpos, arm_qvel = np.array(positions), np.array(velocities)
    assert np.all(np.abs(arm_qpos[:, 0]) <= np.pi)
    assert np.all(np.abs(arm_qpos[:, 1]) <= 3.0)  # joint1 starts within its limit
    assert arm_qpos.min(axis=0) == pytest.approx([-np.pi, -3.0], abs=0.3)
    assert arm_qpos.max(axis=0) == pytest.approx([np.pi, 3.0], abs=0.3)
    assert np.all(np.abs(arm_qvel) <= 0.005) and np.any(arm_qvel != 0)


def test_reset_vertical_target_fills_its_square(make_env) -> None:
    env = make_env(VERTICAL)
    targets = np.array([obs[4:6] for obs in _resets(env, N_RESETS)])
    offsets = targets - ARM_BASE_XZ
    assert np.all(np.abs(offsets) <= 0.2)
    assert offsets.min(axis=0) == pytest.approx([-0.2, -0.2], abs=0.03)
    assert offsets.max(axis=0) == pytest.approx([0.2, 0.2], abs=0.03)


def test_reset_turn_target_on_its_circle_and_spinner_at_rest(make_env) -> None:
    env = make_env(TURN)
    targets, spinner_angles = [], []
    for obs in _resets(env, N_RESETS):
        targets.append(obs[4:6])
        spinner_angles.append(env.data.qpos[2])
        assert env.data.qvel[2] == 0
        tip_radius = np.linalg.norm(obs[9:11] - SPINNER_HINGE_XZ)
        assert tip_radius == pytest.approx(SPINNER_TIP_RADIUS)
    radii = np.linalg.norm(np.array(targets) - SPINNER_HINGE_XZ, axis=1)
    np.testing.assert_allclose(radii, SPINNER_TARGET_RADIUS)
    offsets = np.array(targets) - SPINNER_HINGE_XZ
    angles = np.arctan2(offsets[:, 1], offsets[:, 0])
    assert np.histogram(angles, bins=4, range=(-np.pi, np.pi))[0].min() > N_RESETS / 8
    assert np.ptp(spinner_angles) > 5.0


def test_reset_push_box_and_target_in_their_ranges(make_env) -> None:
    env = make_env(PUSH)
    box_rows, target_rows = [], []
    for obs in _resets(env, N_RESETS):
        box_rows.append(obs[4:6])
        target_rows.append(obs[7:9])
        np.testing.assert_array_equal(env.data.qvel[2:], 0.0)  # the box starts at rest
    boxes, targets = np.array(box_rows), np.array(target_rows)
    assert np.all(np.abs(boxes[:, 0]) <= 0.2) and np.ptp(boxes[:, 0]) > 0.35
    assert np.all((boxes[:, 1] >= 0.03) & (boxes[:, 1] <= 0.05))
    assert np.all(np.abs(targets[:, 0]) <= 0.2) and np.ptp(targets[:, 0]) > 0.35
    np.testing.assert_allclose(targets[:, 1], 0.03)


def test_reset_raises_when_no_state_is_contact_free(make_env) -> None:
    env = make_env(VERTICAL)
    env.model.geom_margin[env.model.geom("floor").id] = 10.0  # everything now touches the floor
    with pytest.raises(RuntimeError, match="contact-free"):
        env.reset(seed=0)


# Physics of the shared arm


@pytest.mark.parametrize("env_id", REACHER_IDS)
def test_fingertip_follows_the_arm_kinematics(env_id: str, make_env) -> None:
    env = make_env(env_id)
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(10):
        qpos = env.data.qpos.copy()
        qpos[:2] = rng.uniform(-3, 3, size=2)
        env.set_state(qpos, env.data.qvel.copy())
        q0, q01 = qpos[0], qpos[0] + qpos[1]
        expected = (
            ARM_BASE_XZ
            + LINK_LENGTH * np.array([np.cos(q0), np.sin(q0)])
            + FINGERTIP_OFFSET * np.array([np.cos(q01), np.sin(q01)])
        )
        np.testing.assert_allclose(env.fingertip_xz, expected, atol=1e-12)


@pytest.mark.parametrize("env_id", REACHER_IDS)
def test_gravity_pulls_an_unpowered_horizontal_arm_down(env_id: str, make_env) -> None:
    env = make_env(env_id)
    env.reset(seed=0)
    qpos, qvel = env.data.qpos.copy(), np.zeros(env.model.nv)
    qpos[:2] = (np.pi, 0.0)  # straight out to the left, clear of the spinner and the box
    env.set_state(qpos, qvel)
    start_z = env.fingertip_xz[1]
    for _ in range(30):
        env.step(np.zeros(2, dtype=np.float32))
    assert env.fingertip_xz[1] < start_z - 0.05


@pytest.mark.parametrize("direction", [1.0, -1.0])
def test_elbow_stops_at_its_limit(direction: float, make_env) -> None:
    env = make_env(VERTICAL)
    env.reset(seed=0)
    # Without contacts only the limit can stop the elbow; full torque pushes it hard into it.
    env.model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    env.set_state(np.zeros(2), np.zeros(2))
    elbow = []
    for _ in range(50):
        env.step(np.array([0.0, direction], dtype=np.float32))
        elbow.append(direction * env.data.qpos[1])
    assert max(elbow) > 2.9  # it got there
    assert max(elbow) < 3.3  # and a soft limit lets it overshoot only a little
    assert elbow[-1] < 3.1


def test_actions_move_the_arm_the_way_their_sign_says(make_env) -> None:
    env = make_env(VERTICAL)
    env.reset(seed=0)
    env.model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_GRAVITY
    env.set_state(np.zeros(2), np.zeros(2))
    env.step(np.array([1.0, -1.0], dtype=np.float32))
    assert env.data.qvel[0] > 0 and env.data.qvel[1] < 0


# Physics of the tasks' objects


def test_arm_sweeping_along_the_floor_pushes_the_box(make_env) -> None:
    env = make_env(PUSH)
    env.reset(seed=0)
    # Arm out to the left with the elbow bent, box resting on the floor to the right: turning
    # the base counterclockwise sweeps the fingertip down and then along +x through the box.
    env.set_state(np.array([np.pi, -1.2, 0.1, 0.04, 0.0]), np.zeros(5))
    for _ in range(30):
        env.step(np.array([0.3, 0.0], dtype=np.float32))
    assert env.data.qpos[2] > 0.1 + 0.05


def test_arm_knocks_the_spinner_round_and_only_the_arm_does(make_env) -> None:
    env = make_env(TURN)
    env.reset(seed=0)
    upright = np.array([np.pi / 2, 0.0, 0.0])
    for base_torque, spinner_turns in [(-0.3, True), (0.3, False)]:
        # Clockwise from upright the arm comes down onto the spinner; counterclockwise it
        # swings away on the left and the spinner, balanced on its hinge, stays put.
        env.set_state(upright, np.zeros(3))
        for _ in range(30):
            env.step(np.array([base_torque, 0.0], dtype=np.float32))
        assert (abs(env.data.qpos[2]) > 0.05) == spinner_turns
