"""``ede/Pusher-v0`` is gymnasium's ``Pusher-v5`` up to the rounding of its reward's norms."""

from __future__ import annotations

import gymnasium as gym
import numpy as np

import ede_envs

gym.register_envs(ede_envs)


def test_pusher_v0_is_pusher_v5_with_fixed_order_norms() -> None:
    ours, theirs = gym.make("ede/Pusher-v0"), gym.make("Pusher-v5")
    assert ours.spec is not None and theirs.spec is not None
    assert ours.spec.max_episode_steps == theirs.spec.max_episode_steps == 100
    assert ours.action_space == theirs.action_space
    actions = np.random.default_rng(0).uniform(-2, 2, size=(150, 7)).astype(np.float32)
    obs_a, _ = ours.reset(seed=5)
    obs_b, _ = theirs.reset(seed=5)
    np.testing.assert_array_equal(obs_a, obs_b)
    for action in actions:
        obs_a, reward_a, term_a, trunc_a, info_a = ours.step(action)
        obs_b, reward_b, term_b, trunc_b, info_b = theirs.step(action)
        np.testing.assert_array_equal(obs_a, obs_b)
        assert (term_a, trunc_a) == (term_b, trunc_b)
        reward_a, reward_b = float(reward_a), float(reward_b)
        assert abs(reward_a - reward_b) <= 1e-12 * max(1.0, abs(reward_b))
        assert info_a.keys() == info_b.keys()
        assert sum(info_a[k] for k in ("reward_dist", "reward_ctrl", "reward_near")) == reward_a
        if trunc_a:
            obs_a, _ = ours.reset(seed=6)
            obs_b, _ = theirs.reset(seed=6)
            np.testing.assert_array_equal(obs_a, obs_b)
