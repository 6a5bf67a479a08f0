"""Invariants that every task must satisfy, parametrised over all of them; the families are the
committed params' (``envs/`` registers tasks and knows nothing of families)."""

from __future__ import annotations

import os
import subprocess
import sys

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import ede_envs
from ede.config import FamilyConfig, load_params
from ede.tasks import action_bounds, make
from tests.support import REPO

FAMILIES = load_params(REPO / "params.yaml").families
ALL_TASKS = [task for family in FAMILIES.values() for task in family.tasks]
OUR_TASKS = list(ede_envs.TASKS)


def rollout(task: str, seed: int, steps: int = 30) -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """Observations and rewards of ``steps`` seeded random actions after ``reset(seed=seed)``."""
    env = make(task)
    low, high = action_bounds(env)
    actions = np.random.default_rng(1234).uniform(low, high, size=(steps, *low.shape))
    obs, _ = env.reset(seed=seed)
    observations, rewards, infos = [obs], [], []
    for action in actions:
        obs, reward, terminated, _truncated, info = env.step(action.astype(np.float32))
        observations.append(obs)
        rewards.append(reward)
        infos.append(info)
        assert not terminated
    env.close()
    return np.array(observations), np.array(rewards), infos


def test_every_shipped_task_is_in_exactly_one_family_of_the_committed_params() -> None:
    assert len(ALL_TASKS) == len(set(ALL_TASKS)) == 7
    assert set(ALL_TASKS) == set(ede_envs.TASKS)
    assert FAMILIES["sevendof"].source == "ede/Pusher-v0"
    assert not hasattr(ede_envs, "FAMILIES") and not hasattr(ede_envs, "family_of")


@pytest.mark.parametrize("task", OUR_TASKS)
def test_gymnasium_env_checker_passes(task: str) -> None:
    env = make(task)
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


@pytest.mark.parametrize("task", ALL_TASKS)
def test_same_seed_same_trajectory_other_seed_differs(task: str) -> None:
    obs_a, rew_a, _ = rollout(task, seed=3)
    obs_b, rew_b, _ = rollout(task, seed=3)
    obs_c, _, _ = rollout(task, seed=4)
    np.testing.assert_array_equal(obs_a, obs_b)
    np.testing.assert_array_equal(rew_a, rew_b)
    assert not np.array_equal(obs_a[0], obs_c[0]), "the initial state ignores the seed"


@pytest.mark.parametrize("task", ALL_TASKS)
def test_observation_moves_and_is_finite(task: str) -> None:
    observations, rewards, _ = rollout(task, seed=0)
    assert np.all(np.isfinite(observations)) and np.all(np.isfinite(rewards))
    assert np.ptp(observations, axis=0).max() > 1e-3, "random actions change nothing"


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("task", OUR_TASKS)
def test_a_non_finite_action_is_refused_and_later_steps_are_unaffected(
    task: str, bad: float
) -> None:
    refused, untouched = make(task), make(task)
    low, high = action_bounds(refused)
    actions = np.random.default_rng(7).uniform(low, high, size=(6, *low.shape)).astype(np.float32)
    poisoned = actions[0].copy()
    poisoned[-1] = bad
    for env in (refused, untouched):
        env.reset(seed=5)
        env.step(actions[0])
    with pytest.raises(ValueError, match=rf"^{task}: expected a finite action, got \[.*{bad}\]$"):
        refused.step(poisoned)
    for action in actions[1:]:
        obs, reward, *_ = refused.step(action)
        expected_obs, expected_reward, *_ = untouched.step(action)
        np.testing.assert_array_equal(obs, expected_obs)
        assert reward == expected_reward
    refused.close()
    untouched.close()


def test_a_task_made_by_its_class_names_its_class_when_it_refuses() -> None:
    from ede_envs.point import PointEnv

    env = PointEnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"^PointEnv: expected a finite action, got \[0.0, nan\]$"):
        env.step(np.array([0.0, np.nan], dtype=np.float32))
    env.close()


@pytest.mark.parametrize("task", OUR_TASKS)
def test_weighted_reward_terms_in_info_sum_to_the_reward(task: str) -> None:
    _, rewards, infos = rollout(task, seed=1)
    terms = sorted(key for key in infos[0] if key.startswith("reward_"))
    assert terms, "info names no reward term"
    summed = np.array([sum(info[key] for key in terms) for info in infos])
    np.testing.assert_allclose(summed, rewards, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("task", ALL_TASKS)
def test_episode_is_truncated_at_its_registered_length(task: str) -> None:
    env = make(task)
    env.reset(seed=0)
    length = ede_envs.TASKS[task].max_episode_steps
    assert env.spec is not None and env.spec.max_episode_steps == length
    for step in range(1, length + 1):
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        assert not terminated
        assert truncated == (step == length)
    env.close()


@pytest.mark.parametrize("family", list(FAMILIES.values()), ids=list(FAMILIES))
def test_a_family_shares_one_action_space(family: FamilyConfig) -> None:
    spaces = []
    for task in family.tasks:
        env = make(task)
        spaces.append(env.action_space)
        env.close()
    assert all(space == spaces[0] for space in spaces), spaces


@pytest.mark.parametrize("task", OUR_TASKS)
def test_renders_headless_to_a_picture(task: str) -> None:
    env = make(task, render_mode="rgb_array", width=96, height=72)
    env.reset(seed=0)
    frame = env.render()
    env.close()
    assert isinstance(frame, np.ndarray)
    assert frame.shape == (72, 96, 3) and frame.dtype == np.uint8
    assert frame.std() > 5, "the frame is blank"


def _fresh_python(code: str) -> str:
    """What ``code`` prints in a new interpreter of this environment."""
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=os.environ, check=False
    )
    assert result.returncode == 0, result.stderr
    return result.stdout.strip()


def test_a_fresh_interpreter_does_not_import_us_unless_asked() -> None:
    code = (
        "import sys, gymnasium\n"
        "print('ede_envs' in sys.modules, 'ede/ReacherTurn-v0' in gymnasium.registry)\n"
    )
    assert _fresh_python(code) == "False False"


def test_importing_the_package_registers_the_tasks() -> None:
    code = (
        "import gymnasium as gym\n"
        "import ede_envs\n"
        "gym.register_envs(ede_envs)\n"
        "print(type(gym.make('ede/ReacherTurn-v0').unwrapped).__module__)\n"
    )
    assert _fresh_python(code) == "ede_envs.reacher_turn"


def test_a_task_is_made_by_module_and_id_with_no_import() -> None:
    code = (
        "import gymnasium\n"
        "print(type(gymnasium.make('ede_envs:ede/ReacherTurn-v0').unwrapped).__module__)\n"
    )
    assert _fresh_python(code) == "ede_envs.reacher_turn"


def test_registration_is_idempotent() -> None:
    ede_envs.register_envs()
    ede_envs.register_envs()
    assert sum(task.startswith("ede/") for task in gymnasium.registry) == len(OUR_TASKS)
