"""``ede/ReacherTurn-v0``: turn a free spinner with the Reacher arm until its tip meets a target."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Final

import numpy as np
from gymnasium import utils
from numpy.typing import NDArray

from ede_envs._numerics import cos_sin, norm
from ede_envs.reacher import ASSETS_DIR, ReacherFamilyEnv, control_cost

__all__ = ["ReacherTurnEnv"]

SPINNER_HINGE_XZ: Final[NDArray[np.float64]] = np.array([0.35, 0.25])  # as in reacher_turn.xml
TARGET_RADIUS: Final[float] = 0.15  # the target's circle around the hinge; the tip turns at 0.14
SPINNER_INIT_ANGLE_HIGH: Final[float] = np.pi  # spinner angle uniform in [-pi, pi], at rest


class ReacherTurnEnv(ReacherFamilyEnv):
    r"""Turn a free spinner with the Reacher arm so that the spinner's tip reaches a target.

    ## Description
    A target task of the Reacher family. Beside the arm of
    :class:`~ede_envs.reacher.ReacherFamilyEnv` stands a spinner: two capsules on a hinge at
    (x, z) = (0.35, 0.25) that turns about -y, like the arm, with damping 3 and friction loss
    0.1 (and the family's armature 1). Its tip (site `spinner_tip`) is 0.14 from the hinge. The
    arm has to knock the spinner round until the tip is on a target placed at random on the
    circle of radius 0.15 around the hinge; the target never moves and does not collide.

    ## Action Space
    `Box(-1, 1, (2,), float32)`: the torques at `joint0` and `joint1`, times the gear 200,
    identical across the family (see `ReacherFamilyEnv`).

    ## Observation Space
    `Box(-inf, inf, (11,), float64)`. The spinner's angle is left out, since it grows without
    bound as the spinner turns; the tip's position stands in for it.

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
    | 8   | angular velocity of the spinner       | -Inf | Inf | spinner              | hinge | angular velocity (rad/s) |
    | 9   | x of the spinner's tip                | -Inf | Inf | spinner_tip (site)   | -     | position (m)             |
    | 10  | z of the spinner's tip                | -Inf | Inf | spinner_tip (site)   | -     | position (m)             |

    ## Rewards
    reward = reward_dist + reward_ctrl, from the state after the step:

    - reward_dist = $-w_{dist} \|p_{tip} - p_{target}\|_2$, with $w_{dist}$ =
      `reward_dist_weight` (default 10);
    - reward_ctrl = $-w_{control} \|a\|_2^2$, with $w_{control}$ = `reward_control_weight`
      (default 0.5).

    `info` holds `reward_dist`, `reward_ctrl` and the raw quantities: `distance`
    ($\|p_{tip} - p_{target}\|_2$), `action_norm_sq` ($\|a\|_2^2$), `tip_xz` and `target_xz`.

    ## Starting State
    Arm angles uniform in [-pi, pi] (`joint1` within its limit [-3, 3]), arm velocities uniform
    in [-0.005, 0.005]; the spinner's angle uniform in [-pi, pi], at rest; the target at an
    angle uniform in [-pi, pi] on the circle of radius 0.15 around the hinge. Redrawn until
    nothing touches (at most 1000 times, then `RuntimeError`).

    ## Episode End
    Never terminates; truncated after 100 steps by the `TimeLimit` of `gymnasium.make`.

    ## Arguments
    | Parameter               | Type      | Default                    | Description                      |
    |-------------------------|-----------|----------------------------|----------------------------------|
    | `xml_file`              | **str**   | `assets/reacher_turn.xml`  | Path to the MuJoCo model         |
    | `default_camera_config` | **dict**  | `DEFAULT_CAMERA_CONFIG`    | Free camera for rendering        |
    | `reward_dist_weight`    | **float** | `10`                       | $w_{dist}$ of reward_dist        |
    | `reward_control_weight` | **float** | `0.5`                      | $w_{control}$ of reward_ctrl     |

    Further keyword arguments (`render_mode`, `width`, `height`, ...) go to `MujocoEnv`.

    ## Version History
    * v0: port to `gymnasium.envs.mujoco.MujocoEnv` of `ReacherTurnEnv` from
      willwhitney/dynamics-aware-embeddings. Differences: the reward is computed after the
      physics step (the original used the state before it); the target is a mocap body instead
      of a moved model body; `joint1` starts within its limit (the original drew it in
      [-pi, pi]); `info` holds the reward terms (the original's was empty).
    """

    def __init__(
        self,
        xml_file: str | Path = ASSETS_DIR / "reacher_turn.xml",
        default_camera_config: dict[str, Any] | None = None,
        reward_dist_weight: float = 10.0,
        reward_control_weight: float = 0.5,
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
        spinner = self.model.joint("spinner")
        qpos[spinner.qposadr[0]] = self.np_random.uniform(
            -SPINNER_INIT_ANGLE_HIGH, SPINNER_INIT_ANGLE_HIGH
        )
        qvel[spinner.dofadr[0]] = 0.0
        target_angle = self.np_random.uniform(-np.pi, np.pi)
        direction = cos_sin([target_angle])
        self._set_target(SPINNER_HINGE_XZ + TARGET_RADIUS * direction)

    @property
    def tip_xz(self) -> NDArray[np.float64]:
        return self.data.site("spinner_tip").xpos[[0, 2]]

    def _get_obs(self) -> NDArray[np.float64]:
        return np.concatenate(
            [self._arm_angle_features(), self.target_xz, self.data.qvel, self.tip_xz]
        )

    def _get_rew(self, action: NDArray[np.float64]) -> tuple[float, dict[str, Any]]:
        tip_xz, target_xz = self.tip_xz, self.target_xz
        distance = norm(tip_xz - target_xz)
        action_norm_sq = control_cost(action)
        reward_dist = -self._reward_dist_weight * distance
        reward_ctrl = -self._reward_control_weight * action_norm_sq
        info = {
            "reward_dist": reward_dist,
            "reward_ctrl": reward_ctrl,
            "distance": distance,
            "action_norm_sq": action_norm_sq,
            "tip_xz": tip_xz,
            "target_xz": target_xz,
        }
        return reward_dist + reward_ctrl, info
