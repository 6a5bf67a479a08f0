"""Facts of ``ede/Striker-v0``: Pusher-v5's arm and motors, Striker-v2's reward, goal and layout."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
import pytest

import ede_envs  # noqa: F401  (registers the ede/ tasks)
from ede.tasks import simulator
from ede_envs.striker import (
    ARM_VELOCITY_NOISE,
    BALL_START,
    GOAL_HIGH,
    GOAL_LOW,
    MIN_GOAL_BALL_DISTANCE,
    NUM_ARM_JOINTS,
    STRIKE_THRESHOLD,
    StrikerEnv,
)
from tests.support import unwrapped

W_DIST, W_CTRL, W_NEAR = 3.0, 0.1, 0.5  # the spec's weights, written independently of the env


@pytest.fixture(scope="module")
def pusher_model() -> Iterator[mujoco.MjModel]:
    env = gym.make("Pusher-v5")
    yield simulator(env).model
    env.close()


@pytest.fixture
def striker() -> Iterator[StrikerEnv]:
    env = gym.make("ede/Striker-v0")
    yield unwrapped(env, StrikerEnv)
    env.close()


def _arm_joints(model: mujoco.MjModel) -> list[int]:
    """Ids of the joints the motors drive, in actuator order."""
    return [int(model.actuator_trnid[i, 0]) for i in range(model.nu)]


def test_arm_joints_match_pusher(striker: StrikerEnv, pusher_model: mujoco.MjModel) -> None:
    ours, theirs = striker.model, pusher_model
    assert ours.nu == theirs.nu == NUM_ARM_JOINTS
    for j_ours, j_theirs in zip(_arm_joints(ours), _arm_joints(theirs), strict=True):
        name = theirs.joint(j_theirs).name
        assert ours.joint(j_ours).name == name
        assert j_ours == j_theirs  # same order, so qpos[:7] means the same in both
        assert ours.jnt_type[j_ours] == theirs.jnt_type[j_theirs], name
        for field in ("jnt_axis", "jnt_pos", "jnt_range"):
            np.testing.assert_array_equal(
                getattr(ours, field)[j_ours], getattr(theirs, field)[j_theirs], f"{name} {field}"
            )
        assert ours.jnt_limited[j_ours] == theirs.jnt_limited[j_theirs], name
        d_ours, d_theirs = ours.jnt_dofadr[j_ours], theirs.jnt_dofadr[j_theirs]
        assert ours.dof_damping[d_ours] == theirs.dof_damping[d_theirs], name
        assert ours.dof_armature[d_ours] == theirs.dof_armature[d_theirs], name
        assert ours.dof_frictionloss[d_ours] == theirs.dof_frictionloss[d_theirs], name


def test_arm_links_match_pusher_up_to_the_end_effector(
    striker: StrikerEnv, pusher_model: mujoco.MjModel
) -> None:
    ours, theirs = striker.model, pusher_model
    # Every link but the wrist roll link (which carries the end effector) and the tip body.
    for j in _arm_joints(theirs)[:-1]:
        body = theirs.joint(j).bodyid[0]
        name = theirs.body(body).name
        b_ours = ours.body(name).id
        assert ours.body_mass[b_ours] == pytest.approx(theirs.body_mass[body], rel=1e-12), name
        np.testing.assert_allclose(ours.body_inertia[b_ours], theirs.body_inertia[body], rtol=1e-12)
        np.testing.assert_array_equal(ours.body_pos[b_ours], theirs.body_pos[body], err_msg=name)
    for field in ("timestep", "gravity", "integrator", "iterations"):
        np.testing.assert_array_equal(getattr(ours.opt, field), getattr(theirs.opt, field), field)


def test_motors_match_pusher(striker: StrikerEnv, pusher_model: mujoco.MjModel) -> None:
    ours, theirs = striker.model, pusher_model
    np.testing.assert_array_equal(ours.actuator_ctrlrange, theirs.actuator_ctrlrange)
    np.testing.assert_array_equal(ours.actuator_ctrllimited, theirs.actuator_ctrllimited)
    np.testing.assert_array_equal(ours.actuator_gear, theirs.actuator_gear)
    np.testing.assert_array_equal(ours.actuator_gainprm, theirs.actuator_gainprm)
    np.testing.assert_array_equal(ours.actuator_biasprm, theirs.actuator_biasprm)
    np.testing.assert_array_equal(ours.actuator_trntype, theirs.actuator_trntype)


def test_action_space_equals_pusher() -> None:
    striker, pusher = gym.make("ede/Striker-v0"), gym.make("Pusher-v5")
    assert striker.action_space == pusher.action_space
    assert striker.action_space == gym.spaces.Box(-2.0, 2.0, (7,), np.float32)
    assert striker.spec is not None and striker.spec.max_episode_steps == 100
    assert unwrapped(striker, StrikerEnv).frame_skip == 5


def _check_reward(reward: float, action: np.ndarray, info: dict[str, Any]) -> None:
    """The spec's formula, recomputed from the raw quantities in ``info``."""
    ball, goal, tip = info["ball_position"], info["goal_position"], info["tip_position"]
    assert info["distance_ball_goal"] == pytest.approx(np.linalg.norm(ball - goal))
    assert info["distance_tip_ball"] == pytest.approx(np.linalg.norm(ball - tip))
    assert info["action_norm_sq"] == pytest.approx(float(np.sum(np.square(action))))
    expected = (
        -W_DIST * info["closest_distance_ball_goal"]
        - W_CTRL * info["action_norm_sq"]
        - W_NEAR * np.linalg.norm(ball - info["near_reference"])
    )
    assert reward == pytest.approx(expected, abs=1e-12)
    terms = [value for key, value in info.items() if key.startswith("reward_")]
    assert sorted(k for k in info if k.startswith("reward_")) == [
        "reward_ctrl",
        "reward_dist",
        "reward_near",
    ]
    assert sum(terms) == pytest.approx(reward, abs=1e-12)


def _check_episode(infos: list[dict[str, Any]]) -> None:
    """Closest distance is the running minimum; the near reference follows the strike rule."""
    distances = np.array([info["distance_ball_goal"] for info in infos])
    closest = np.array([info["closest_distance_ball_goal"] for info in infos])
    np.testing.assert_allclose(closest, np.minimum.accumulate(distances))
    assert np.all(np.diff(closest) <= 0.0)
    strike_step = None
    for t, info in enumerate(infos):
        should_be_struck = strike_step is not None or info["distance_tip_ball"] < STRIKE_THRESHOLD
        assert info["struck"] == should_be_struck, t
        if should_be_struck and strike_step is None:
            strike_step = t
        if strike_step is None or t == strike_step:
            np.testing.assert_array_equal(info["near_reference"], info["tip_position"])
        else:
            np.testing.assert_array_equal(
                info["near_reference"], infos[strike_step]["tip_position"]
            )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_reward_formula_on_random_rollouts(seed: int) -> None:
    env = gym.make("ede/Striker-v0")
    env.reset(seed=seed)
    env.action_space.seed(seed)
    infos = []
    for _ in range(100):
        action = env.action_space.sample()
        _, reward, terminated, truncated, info = env.step(action)
        assert not terminated
        _check_reward(float(reward), action, info)
        infos.append(info)
    assert truncated  # TimeLimit at 100 steps
    _check_episode(infos)


def _place_ball_against_paddle(env: StrikerEnv, ball_velocity: tuple[float, float]) -> None:
    """Lower the arm so the paddle is at ball height and put the ball just in front of it."""
    qpos, qvel = env.data.qpos.copy(), np.zeros(env.model.nv)
    qpos[:NUM_ARM_JOINTS] = 0.0
    qpos[env.model.joint("r_shoulder_lift_joint").qposadr[0]] = 0.38
    env.set_state(qpos, qvel)
    tip = env.get_body_com("tips_arm").copy()
    qpos[NUM_ARM_JOINTS : NUM_ARM_JOINTS + 2] = tip[:2] + np.array([0.07, 0.0])
    qvel[NUM_ARM_JOINTS : NUM_ARM_JOINTS + 2] = ball_velocity
    env.set_state(qpos, qvel)
    assert np.linalg.norm(env.get_body_com("object") - tip) < STRIKE_THRESHOLD


def test_strike_fixes_the_near_reference_and_reset_clears_it() -> None:
    gym_env = gym.make("ede/Striker-v0")
    gym_env.reset(seed=3)
    env = unwrapped(gym_env, StrikerEnv)
    _place_ball_against_paddle(env, ball_velocity=(0.0, 0.0))
    rng = np.random.default_rng(3)
    infos = []
    for _ in range(15):
        action = rng.uniform(-2.0, 2.0, size=7).astype(np.float32)
        _, reward, _, _, info = gym_env.step(action)
        _check_reward(float(reward), action, info)
        infos.append(info)
    assert infos[0]["struck"]
    assert infos[-1]["distance_tip_ball"] != pytest.approx(
        np.linalg.norm(infos[-1]["ball_position"] - infos[-1]["near_reference"])
    )  # after the strike, r_near no longer follows the tip
    _check_episode(infos)

    gym_env.reset(seed=3)
    _, _, _, _, info = gym_env.step(np.zeros(7, dtype=np.float32))
    assert not info["struck"]
    np.testing.assert_array_equal(info["near_reference"], info["tip_position"])
    assert info["closest_distance_ball_goal"] == info["distance_ball_goal"]


def test_reward_dist_keeps_the_closest_distance_when_the_ball_moves_away() -> None:
    gym_env = gym.make("ede/Striker-v0")
    gym_env.reset(seed=4)
    env = unwrapped(gym_env, StrikerEnv)
    goal = env.get_body_com("goal")[:2].copy()
    qvel = env.data.qvel.copy()
    away = BALL_START - goal
    qvel[NUM_ARM_JOINTS : NUM_ARM_JOINTS + 2] = 2.0 * away / np.linalg.norm(away)
    env.set_state(env.data.qpos.copy(), qvel)
    infos = [gym_env.step(np.zeros(7, dtype=np.float32))[4] for _ in range(5)]
    distances = [info["distance_ball_goal"] for info in infos]
    assert np.all(np.diff(distances) > 0.0)  # the ball does move away
    for info in infos:
        assert info["reward_dist"] == pytest.approx(-W_DIST * distances[0])


def test_goal_distribution_and_starting_state() -> None:
    env = gym.make("ede/Striker-v0")
    goals = []
    for seed in range(200):
        obs, _ = env.reset(seed=seed)
        data = unwrapped(env, StrikerEnv).data
        goal = obs[20:22]
        assert np.all(goal >= GOAL_LOW) and np.all(goal <= GOAL_HIGH)
        assert np.linalg.norm(goal - np.array(BALL_START)) >= MIN_GOAL_BALL_DISTANCE
        np.testing.assert_array_equal(obs[17:19], BALL_START)
        np.testing.assert_array_equal(data.qpos[:NUM_ARM_JOINTS], 0.0)
        assert np.all(np.abs(data.qvel[:NUM_ARM_JOINTS]) <= ARM_VELOCITY_NOISE)
        np.testing.assert_array_equal(data.qvel[NUM_ARM_JOINTS:], 0.0)
        goals.append(goal)
    drawn = np.array(goals)
    # Spread over the box, not stuck in a corner: each coordinate's range covers most of it.
    spread = (drawn.max(axis=0) - drawn.min(axis=0)) / (np.array(GOAL_HIGH) - np.array(GOAL_LOW))
    assert np.all(spread > 0.9)


def test_observation_layout() -> None:
    env = gym.make("ede/Striker-v0")
    obs, _ = env.reset(seed=5)
    env.action_space.seed(5)
    for _ in range(10):
        obs, *_ = env.step(env.action_space.sample())
    data = unwrapped(env, StrikerEnv).data
    assert obs.shape == (23,) and obs.dtype == np.float64
    np.testing.assert_array_equal(obs[0:7], data.qpos[:7])
    np.testing.assert_array_equal(obs[7:14], data.qvel[:7])
    np.testing.assert_array_equal(obs[14:17], data.body("tips_arm").xpos)
    np.testing.assert_array_equal(obs[17:20], data.body("object").xpos)
    np.testing.assert_array_equal(obs[20:23], data.body("goal").xpos)
    model = unwrapped(env, StrikerEnv).model
    ball_xy = [data.joint("obj_slidex").qpos[0], data.joint("obj_slidey").qpos[0]]
    np.testing.assert_array_equal(obs[17:19], ball_xy)  # ball bodies sit at the origin
    assert model.nq == model.nv == 11
