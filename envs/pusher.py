"""``ede/Pusher-v0``: gymnasium's ``Pusher-v5``, with a reward that has the same bits everywhere."""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium.envs.mujoco.pusher_v5 import PusherEnv as GymnasiumPusherEnv
from numpy.typing import NDArray

from ede_envs._actions import check_action
from ede_envs._numerics import norm

__all__ = ["PusherEnv"]


class PusherEnv(GymnasiumPusherEnv):
    """## Description

    Gymnasium's `Pusher-v5` — the 7-DoF family's source task — as it is: the same model, action
    space, observation, reward terms and weights, reset and episode length (100 steps). See
    `gymnasium.envs.mujoco.pusher_v5.PusherEnv` for the full specification.

    The one difference in what a rollout holds is arithmetic. `Pusher-v5` computes its distances with `np.linalg.norm`,
    which hands the 3-vectors to BLAS, whose kernel (chosen by the CPU at run time) decides how
    the squares are added and fused: the last bit of the reward then depends on the machine.
    Here the same norms are summed in a fixed order (`ede_envs._numerics`), so a rollout is
    bit-identical on every machine; it agrees with `Pusher-v5`'s to within rounding (tested).

    ## Rewards

    `reward = reward_dist + reward_ctrl + reward_near`, with `reward_near = -0.5 ‖object -
    tips_arm‖`, `reward_dist = -1 ‖object - goal‖` and `reward_ctrl = -0.1 ‖a‖²` (the weights are
    `Pusher-v5`'s constructor arguments, unchanged).

    ## Version History

    * v0: `Pusher-v5` with its reward's norms summed in a fixed order, refusing a non-finite
      action (`ede_envs._actions`).
    """

    # Pusher-v5's step, after the check every ede/ task makes; the types are gymnasium's Env API.
    def step(  # type: ignore[override]
        self, action: NDArray[np.float32]
    ) -> tuple[NDArray[np.float64], float, bool, bool, dict[str, Any]]:
        check_action(self, action)
        return super().step(action)

    def _get_rew(self, action: NDArray[np.float32]) -> tuple[float, dict[str, Any]]:
        object_com = self.get_body_com("object")
        # np.float64, as np.linalg.norm returns: the sum below is then float64, as in Pusher-v5.
        near = np.float64(norm(object_com - self.get_body_com("tips_arm")))
        dist = np.float64(norm(object_com - self.get_body_com("goal")))
        reward_near = -near * self._reward_near_weight
        reward_dist = -dist * self._reward_dist_weight
        # Pusher-v5's own expression, in the action's dtype: an elementwise square and numpy's
        # pairwise sum, whose order is fixed by numpy's source on every CPU.
        reward_ctrl = -np.square(action).sum() * self._reward_control_weight
        reward_info = {
            "reward_dist": reward_dist,
            "reward_ctrl": reward_ctrl,
            "reward_near": reward_near,
        }
        return reward_dist + reward_ctrl + reward_near, reward_info
