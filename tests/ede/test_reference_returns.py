"""The reference returns a task's results are read against: random actions and zero actions."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest

import ede.analysis.probes
from ede.analysis.probes import random_policy_return, zero_action_return


class Penalised(gymnasium.Env):
    """Three steps an episode; the reward is minus the action's sum, plus the episode's seed so
    that episodes differ; the action box excludes zero in its first dimension."""

    observation_space = gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32)
    action_space = gymnasium.spaces.Box(np.array([0.5, -1.0], np.float32), np.ones(2, np.float32))

    def reset(self, *, seed=None, options=None):
        self.offset, self.t = float(seed), 0
        return np.zeros(1, np.float32), {}

    def step(self, action):
        assert self.action_space.contains(action)
        self.t += 1
        return np.zeros(1, np.float32), self.offset - float(np.sum(action)), False, self.t == 3, {}


@pytest.fixture(autouse=True)
def penalised(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ede.analysis.probes, "make", lambda task: Penalised())


def test_zero_actions_take_the_nearest_action_in_the_box_and_report_their_standard_error() -> None:
    # Action (0.5, 0) every step: episode e from seed 10 + e returns 3 * (10 + e - 0.5).
    mean, error = zero_action_return("penalised", episodes=4, seed=10)
    returns = 3 * (10 + np.arange(4) - 0.5)
    assert mean == pytest.approx(returns.mean())
    assert error == pytest.approx(returns.std(ddof=1) / 2)


def test_random_actions_are_uniform_over_the_box_and_seeded() -> None:
    # The action sum has mean 0.75 and sd 0.60: over 400 episodes from seed 0 the mean return is
    # 3 * (199.5 - 0.75) to within 3 * 0.60 / sqrt(1200) = 0.05 (one sd; the tolerance is three).
    mean = random_policy_return("penalised", episodes=400, seed=0)
    assert mean == pytest.approx(3 * (199.5 - 0.75), abs=0.15)
    assert mean == random_policy_return("penalised", episodes=400, seed=0)
