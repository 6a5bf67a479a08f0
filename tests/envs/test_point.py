"""Facts of the two small environments: ``ede/Point-v0`` and ``ede/PointMass-v0``."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import ede_envs
from ede.tasks import simulator
from ede_envs.point import STEP_SIZE, PointEnv
from ede_envs.point_mass import ARENA_HALF_WIDTH
from tests.support import unwrapped

gym.register_envs(ede_envs)

K = 4  # the paper's number of actions per EDE action


def _state(env: gym.Env) -> np.ndarray:
    data = simulator(env).data
    return np.concatenate([data.qpos, data.qvel])


# ---------------------------------------------------------------------------------------- Point


def test_point_state_is_the_position() -> None:
    env = gym.make("ede/Point-v0")
    obs, _ = env.reset(seed=0)
    model = simulator(env).model
    assert model.nq == model.nv == 2  # the goal is a site, not a joint
    np.testing.assert_array_equal(_state(env), np.concatenate([obs[:2], [0.0, 0.0]]))
    assert env.action_space == gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    assert unwrapped(env, PointEnv).step_size == STEP_SIZE


@pytest.mark.parametrize("seed", [0, 1])
def test_point_effect_of_k_actions_is_linear(seed: int) -> None:
    env = gym.make("ede/Point-v0")
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    # Half the actions leave [-1, 1] and must be clipped.
    actions = rng.uniform(-2.0, 2.0, size=(24, 2)).astype(np.float32)
    visited = [_state(env)]
    for action in actions:
        env.step(action)
        visited.append(_state(env))
    states = np.array(visited)
    clipped = np.clip(actions.astype(np.float64), -1.0, 1.0)
    assert np.any(np.abs(actions) > 1.0)
    for t in range(len(actions) - K + 1):
        effect = states[t + K] - states[t]
        expected = np.concatenate([STEP_SIZE * clipped[t : t + K].sum(axis=0), [0.0, 0.0]])
        np.testing.assert_allclose(effect, expected, rtol=0.0, atol=1e-12)
    assert simulator(env).data.nefc == 0  # no constraint ever acts


def test_point_can_cross_the_square_in_an_episode() -> None:
    env = gym.make("ede/Point-v0")
    obs, _ = env.reset(seed=0)
    start = obs[:2].copy()
    for _ in range(100):
        obs, *_ = env.step(np.ones(2, dtype=np.float32))
    np.testing.assert_allclose(obs[:2] - start, 100 * STEP_SIZE * np.ones(2), atol=1e-10)
    assert 100 * STEP_SIZE > 2.0  # the start/goal square is [-1, 1]^2


def test_point_reward_and_observation_layout() -> None:
    env = gym.make("ede/Point-v0")
    env.reset(seed=2)
    rng = np.random.default_rng(2)
    for _ in range(20):
        action = rng.uniform(-1.5, 1.5, size=2).astype(np.float32)
        obs, reward, terminated, _, info = env.step(action)
        data = simulator(env).data
        assert obs.shape == (4,) and obs.dtype == np.float64 and not terminated
        np.testing.assert_array_equal(obs[:2], data.qpos)
        np.testing.assert_array_equal(obs[2:], data.site("goal").xpos[:2])
        np.testing.assert_array_equal(info["position"], obs[:2])
        np.testing.assert_array_equal(info["goal"], obs[2:])
        np.testing.assert_array_equal(info["action_clipped"], np.clip(action, -1.0, 1.0))
        np.testing.assert_allclose(info["displacement"], STEP_SIZE * info["action_clipped"])
        assert info["distance"] == pytest.approx(np.linalg.norm(obs[:2] - obs[2:]))
        assert reward == pytest.approx(-np.linalg.norm(obs[:2] - obs[2:]), abs=1e-12)
        assert sum(v for k, v in info.items() if k.startswith("reward_")) == reward


def test_point_reset_draws_start_and_goal_in_the_square() -> None:
    env = gym.make("ede/Point-v0")
    observations = np.array([env.reset(seed=seed)[0] for seed in range(100)])
    assert np.all(np.abs(observations) <= 1.0)
    assert np.all(observations.std(axis=0) > 0.4)  # uniform on [-1, 1] has std 0.58


# ------------------------------------------------------------------------------------ PointMass


def test_pointmass_state_is_position_and_velocity() -> None:
    env = gym.make("ede/PointMass-v0")
    obs, _ = env.reset(seed=0)
    model = simulator(env).model
    assert model.nq == model.nv == 2  # the goal is a site, not a joint
    np.testing.assert_array_equal(_state(env), obs[:4])
    assert env.action_space == gym.spaces.Box(-1.0, 1.0, (2,), np.float32)


def test_pointmass_held_force_builds_up_velocity() -> None:
    env = gym.make("ede/PointMass-v0")
    obs, _ = env.reset(seed=0)
    np.testing.assert_array_equal(obs[2:4], 0.0)
    positions, speeds = [obs[0]], []
    for _ in range(2 * K):
        obs, *_ = env.step(np.array([1.0, 0.0], dtype=np.float32))
        positions.append(obs[0])
        speeds.append(obs[2])
    assert np.all(np.diff(speeds) > 0.0)  # inertia: the velocity grows while the force is held
    assert np.all(np.diff(np.diff(positions)) > 0.0)  # so each step moves further than the last
    assert speeds[0] < 0.5 * speeds[-1]  # a single step is far from the terminal speed
    # Four held steps move the mass a visible fraction of the 2 m wide arena.
    assert positions[K] - positions[0] > 0.03 * 2 * ARENA_HALF_WIDTH


@pytest.mark.parametrize("direction", [(1.0, 1.0), (-1.0, 0.3), (0.0, -1.0)])
def test_pointmass_walls_bind(direction: tuple[float, float]) -> None:
    env = gym.make("ede/PointMass-v0")
    env.reset(seed=1)
    visited = []
    for _ in range(100):
        obs, *_ = env.step(np.array(direction, dtype=np.float32))
        visited.append(obs[:2])
    positions = np.array(visited)
    radius = simulator(env).model.geom("pointmass").size[0]
    assert np.all(np.abs(positions) <= ARENA_HALF_WIDTH - radius + 1e-2)
    # It did reach a wall: without walls the push would carry it several metres.
    assert np.max(np.abs(positions[-1])) > ARENA_HALF_WIDTH - radius - 1e-2


def test_pointmass_reward_and_observation_layout() -> None:
    env = gym.make("ede/PointMass-v0")
    env.reset(seed=2)
    env.action_space.seed(2)
    for _ in range(20):
        action = env.action_space.sample()
        obs, reward, terminated, _, info = env.step(action)
        data = simulator(env).data
        assert obs.shape == (6,) and obs.dtype == np.float64 and not terminated
        np.testing.assert_array_equal(obs[0:2], data.qpos)
        np.testing.assert_array_equal(obs[2:4], data.qvel)
        np.testing.assert_array_equal(obs[4:6], data.site("goal").xpos[:2])
        np.testing.assert_array_equal(info["position"], obs[0:2])
        np.testing.assert_array_equal(info["velocity"], obs[2:4])
        np.testing.assert_array_equal(info["goal"], obs[4:6])
        assert info["distance"] == pytest.approx(np.linalg.norm(obs[0:2] - obs[4:6]))
        assert info["action_norm_sq"] == pytest.approx(float(np.sum(np.square(action))))
        expected = -info["distance"] - 0.01 * info["action_norm_sq"]
        assert reward == pytest.approx(expected, abs=1e-12)
        assert sum(v for k, v in info.items() if k.startswith("reward_")) == pytest.approx(
            reward, abs=1e-12
        )


def _covered_cells(hold: int, seed: int, episodes: int = 10, cell: float = 0.05) -> int:
    """Grid cells visited by ``episodes`` episodes of random actions, each held ``hold`` steps."""
    env = gym.make("ede/PointMass-v0")
    rng = np.random.default_rng(seed)
    visited: set[tuple[int, int]] = set()
    for episode in range(episodes):
        env.reset(seed=seed * 1000 + episode)
        for t in range(100):
            if t % hold == 0:
                action = rng.uniform(-1.0, 1.0, size=2).astype(np.float32)
            obs, *_ = env.step(action)
            visited.add(tuple(np.floor(obs[:2] / cell).astype(int)))
    return len(visited)


@pytest.mark.parametrize("seed", [0, 1])
def test_pointmass_held_actions_cover_more_than_per_step_actions(seed: int) -> None:
    # Over 40 independent sets of ten episodes the ratio of covered cells ranged 1.4x to 4x (mean
    # 2.4x); these seeds are fixed, so the assertion is deterministic.
    per_step, held = _covered_cells(hold=1, seed=seed), _covered_cells(hold=K, seed=seed)
    assert held > 1.5 * per_step
