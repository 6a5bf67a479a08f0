"""``ede/ReacherVertical-v0``: the Reacher family's source task, fingertip to a random target."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Final

import numpy as np
from gymnasium import utils
from numpy.typing import NDArray

from ede_envs._numerics import norm
from ede_envs.reacher import ASSETS_DIR, ReacherFamilyEnv, control_cost

__all__ = ["ReacherVerticalEnv"]

TARGET_CENTER_XZ: Final[NDArray[np.float64]] = np.array([0.0, 0.25])  # the arm's base
TARGET_HALF_WIDTH: Final[float] = 0.2  # target uniform in a square of side 0.4 around the base


class ReacherVerticalEnv(ReacherFamilyEnv):
    r"""Bring the fingertip of a 2-link arm, moving in a vertical plane under gravity, to a target.

    ## Description
    The Reacher family's source task (the one its action embedding is learned on). The arm of
    :class:`~ede_envs.reacher.ReacherFamilyEnv` has to hold its fingertip on a target that is
    placed at random in the arm's plane and never moves; gravity pulls the arm away from it.
    The target is a mocap body without collisions, so it adds nothing to `qpos`.

    ## Action Space
    `Box(-1, 1, (2,), float32)`: the torques at `joint0` and `joint1`, times the gear 200,
    identical across the family (see `ReacherFamilyEnv`).

    ## Observation Space
    `Box(-inf, inf, (10,), float64)`:

    | Num | Observation                           | Min  | Max | Name (in XML)        | Joint | Type (Unit)              |
    |-----|---------------------------------------|------|-----|----------------------|-------|--------------------------|
    | 0   | cosine of the base angle              | -Inf | Inf | joint0               | hinge | unitless                 |
    | 1   | cosine of the elbow angle             | -Inf | Inf | joint1               | hinge | unitless                 |
    | 2   | sine of the base angle                | -Inf | Inf | joint0               | hinge | unitless                 |
    | 3   | sine of the elbow angle               | -Inf | Inf | joint1               | hinge | unitless                 |
    | 4   | x of the target                       | -Inf | Inf | target (mocap body)  | -     | position (m)             |
    | 5   | z of the target                       | -Inf | Inf | target (mocap body)  | -     | position (m)             |
    | 6   | angular velocity of the base          | -Inf | Inf | joint0               | hinge | angular velocity (rad/s) |
    | 7   | angular velocity of the elbow         | -Inf | Inf | joint1               | hinge | angular velocity (rad/s) |
    | 8   | x of fingertip - target               | -Inf | Inf | fingertip, target    | -     | position (m)             |
    | 9   | z of fingertip - target               | -Inf | Inf | fingertip, target    | -     | position (m)             |

    ## Rewards
    reward = reward_dist + reward_ctrl, from the state after the step:

    - reward_dist = $-w_{dist} \|p_{fingertip} - p_{target}\|_2$, with $w_{dist}$ =
      `reward_dist_weight` (default 1);
    - reward_ctrl = $-w_{control} \|a\|_2^2$, with $w_{control}$ = `reward_control_weight`
      (default 1).

    `info` holds `reward_dist`, `reward_ctrl` and the raw quantities: `distance`
    ($\|p_{fingertip} - p_{target}\|_2$), `action_norm_sq` ($\|a\|_2^2$), `fingertip_xz` and
    `target_xz`.

    ## Starting State
    Arm angles uniform in [-pi, pi] (`joint1` within its limit [-3, 3]), arm velocities uniform
    in [-0.005, 0.005]; the target's (x, z) uniform in [-0.2, 0.2] x [0.05, 0.45], a square of
    side 0.4 around the arm's base. Redrawn until nothing touches (at most 1000 times, then
    `RuntimeError`).

    ## Episode End
    Never terminates; truncated after 100 steps by the `TimeLimit` of `gymnasium.make`.

    ## Arguments
    | Parameter               | Type      | Default                    | Description                      |
    |-------------------------|-----------|----------------------------|----------------------------------|
    | `xml_file`              | **str**   | `assets/reacher_vertical.xml` | Path to the MuJoCo model      |
    | `default_camera_config` | **dict**  | `DEFAULT_CAMERA_CONFIG`    | Free camera for rendering        |
    | `reward_dist_weight`    | **float** | `1`                        | $w_{dist}$ of reward_dist        |
    | `reward_control_weight` | **float** | `1`                        | $w_{control}$ of reward_ctrl     |

    Further keyword arguments (`render_mode`, `width`, `height`, ...) go to `MujocoEnv`.

    ## Version History
    * v0: port to `gymnasium.envs.mujoco.MujocoEnv` of `ReacherVerticalEnv` from
      willwhitney/dynamics-aware-embeddings. Differences: the reward is computed after the
      physics step (the original, like gym's Reacher-v2, used the state before it); the target
      is a mocap body instead of a moved model body; the constant-zero y of fingertip - target
      is left out of the observation (10 entries instead of 11); `joint1` starts within its
      limit (the original drew it in [-pi, pi]); `info` splits the reward terms.
    """

    def __init__(
        self,
        xml_file: str | Path = ASSETS_DIR / "reacher_vertical.xml",
        default_camera_config: dict[str, Any] | None = None,
        reward_dist_weight: float = 1.0,
        reward_control_weight: float = 1.0,
        **kwargs: Any,
    ) -> None:
        utils.EzPickle.__init__(
            self,
            xml_file,
            default_camera_config,
            reward_dist_weight,
            reward_control_weight,
            **kwargs,
        )
        self._reward_dist_weight = reward_dist_weight
        self._reward_control_weight = reward_control_weight
        super().__init__(xml_file, default_camera_config, **kwargs)

    def _reset_task(self, qpos: NDArray[np.float64], qvel: NDArray[np.float64]) -> None:
        self._set_target(
            TARGET_CENTER_XZ + self.np_random.uniform(-TARGET_HALF_WIDTH, TARGET_HALF_WIDTH, size=2)
        )

    def _get_obs(self) -> NDArray[np.float64]:
        return np.concatenate(
            [
                self._arm_angle_features(),
                self.target_xz,
                self.data.qvel,
                self.fingertip_xz - self.target_xz,
            ]
        )

    def _get_rew(self, action: NDArray[np.float64]) -> tuple[float, dict[str, Any]]:
        fingertip_xz, target_xz = self.fingertip_xz, self.target_xz
        distance = norm(fingertip_xz - target_xz)
        action_norm_sq = control_cost(action)
        reward_dist = -self._reward_dist_weight * distance
        reward_ctrl = -self._reward_control_weight * action_norm_sq
        info = {
            "reward_dist": reward_dist,
            "reward_ctrl": reward_ctrl,
            "distance": distance,
            "action_norm_sq": action_norm_sq,
            "fingertip_xz": fingertip_xz,
            "target_xz": target_xz,
        }
        return reward_dist + reward_ctrl, info
