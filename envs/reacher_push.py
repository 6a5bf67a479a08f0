"""``ede/ReacherPush-v0``: push a free box along the floor to a target with the Reacher arm."""

from __future__ import annotations

from functools import cached_property
from pathlib import Path
from typing import Any, Final

import numpy as np
from gymnasium import utils
from numpy.typing import NDArray

from ede_envs._numerics import norm
from ede_envs.reacher import ASSETS_DIR, ReacherFamilyEnv, control_cost

__all__ = ["ReacherPushEnv"]

BOX_JOINTS: Final[tuple[str, str, str]] = ("box_x", "box_z", "box_angle")
BOX_INIT_X_HIGH: Final[float] = 0.2  # box x uniform in [-0.2, 0.2]
BOX_INIT_Z_RANGE: Final[tuple[float, float]] = (0.03, 0.05)  # its centre's height; half-size 0.04
BOX_INIT_ANGLE_HIGH: Final[float] = np.pi  # box angle uniform in [-pi, pi]
TARGET_X_HIGH: Final[float] = 0.2  # target x uniform in [-0.2, 0.2]
TARGET_Z: Final[float] = 0.03  # on the floor


class ReacherPushEnv(ReacherFamilyEnv):
    r"""Push a free box along the floor to a target with the Reacher arm.

    ## Description
    A target task of the Reacher family. Under the arm of
    :class:`~ede_envs.reacher.ReacherFamilyEnv` lies a box of half-size 0.04 that is free in the
    arm's plane: it slides along x (`box_x`) and z (`box_z`) and turns about y (`box_angle`),
    undamped (it keeps the family's armature 1). The arm has to push it onto a target on the
    floor; the target never moves and does not collide. The slanted walls keep the box in
    the arena.

    ## Action Space
    `Box(-1, 1, (2,), float32)`: the torques at `joint0` and `joint1`, times the gear 200,
    identical across the family (see `ReacherFamilyEnv`).

    ## Observation Space
    `Box(-inf, inf, (14,), float64)`:

    | Num | Observation                           | Min  | Max | Name (in XML)        | Joint | Type (Unit)              |
    |-----|---------------------------------------|------|-----|----------------------|-------|--------------------------|
    | 0   | cosine of the base angle              | -Inf | Inf | joint0               | hinge | unitless                 |
    | 1   | cosine of the elbow angle             | -Inf | Inf | joint1               | hinge | unitless                 |
    | 2   | sine of the base angle                | -Inf | Inf | joint0               | hinge | unitless                 |
    | 3   | sine of the elbow angle               | -Inf | Inf | joint1               | hinge | unitless                 |
    | 4   | x of the box                          | -Inf | Inf | box_x                | slide | position (m)             |
    | 5   | z of the box                          | -Inf | Inf | box_z                | slide | position (m)             |
    | 6   | angle of the box                      | -Inf | Inf | box_angle            | hinge | angle (rad)              |
    | 7   | x of the target                       | -Inf | Inf | target (mocap body)  | -     | position (m)             |
    | 8   | z of the target                       | -Inf | Inf | target (mocap body)  | -     | position (m)             |
    | 9   | angular velocity of the base          | -Inf | Inf | joint0               | hinge | angular velocity (rad/s) |
    | 10  | angular velocity of the elbow         | -Inf | Inf | joint1               | hinge | angular velocity (rad/s) |
    | 11  | x velocity of the box                 | -Inf | Inf | box_x                | slide | velocity (m/s)           |
    | 12  | z velocity of the box                 | -Inf | Inf | box_z                | slide | velocity (m/s)           |
    | 13  | angular velocity of the box           | -Inf | Inf | box_angle            | hinge | angular velocity (rad/s) |

    ## Rewards
    reward = reward_dist + reward_near + reward_ctrl, from the state after the step:

    - reward_dist = $-w_{dist} \|p_{box} - p_{target}\|_2$, with $w_{dist}$ =
      `reward_dist_weight` (default 10);
    - reward_near = $-w_{near} \|p_{fingertip} - p_{box}\|_2$, with $w_{near}$ =
      `reward_near_weight` (default 0.5);
    - reward_ctrl = $-w_{control} \|a\|_2^2$, with $w_{control}$ = `reward_control_weight`
      (default 1).

    `info` holds `reward_dist`, `reward_near`, `reward_ctrl` and the raw quantities: `distance`
    ($\|p_{box} - p_{target}\|_2$), `near_distance` ($\|p_{fingertip} - p_{box}\|_2$),
    `action_norm_sq` ($\|a\|_2^2$), `box_xz`, `fingertip_xz` and `target_xz`.

    ## Starting State
    Arm angles uniform in [-pi, pi] (`joint1` within its limit [-3, 3]), arm velocities uniform
    in [-0.005, 0.005]; the box at rest, x uniform in [-0.2, 0.2], height uniform in
    [0.03, 0.05] and angle uniform in [-pi, pi]; the target at x uniform in [-0.2, 0.2],
    height 0.03. Redrawn until nothing touches (at most 1000 times, then `RuntimeError`): only
    boxes clear of the floor survive, so the box starts a few millimetres up (centre above 0.04)
    and settles onto the floor in the first steps.

    ## Episode End
    Never terminates; truncated after 100 steps by the `TimeLimit` of `gymnasium.make`.

    ## Arguments
    | Parameter               | Type      | Default                    | Description                      |
    |-------------------------|-----------|----------------------------|----------------------------------|
    | `xml_file`              | **str**   | `assets/reacher_push.xml`  | Path to the MuJoCo model         |
    | `default_camera_config` | **dict**  | `DEFAULT_CAMERA_CONFIG`    | Free camera for rendering        |
    | `reward_dist_weight`    | **float** | `10`                       | $w_{dist}$ of reward_dist        |
    | `reward_near_weight`    | **float** | `0.5`                      | $w_{near}$ of reward_near        |
    | `reward_control_weight` | **float** | `1`                        | $w_{control}$ of reward_ctrl     |

    Further keyword arguments (`render_mode`, `width`, `height`, ...) go to `MujocoEnv`.

    ## Version History
    * v0: port to `gymnasium.envs.mujoco.MujocoEnv` of `ReacherPushEnv` from
      willwhitney/dynamics-aware-embeddings. Differences: the reward is computed after the
      physics step (the original used the state before it); the target is a mocap body instead
      of a moved model body; `joint1` starts within its limit (the original drew it in
      [-pi, pi]); `info` splits the distance term into `reward_dist` and `reward_near`.
    """

    def __init__(
        self,
        xml_file: str | Path = ASSETS_DIR / "reacher_push.xml",
        default_camera_config: dict[str, Any] | None = None,
        reward_dist_weight: float = 10.0,
        reward_near_weight: float = 0.5,
        reward_control_weight: float = 1.0,
        **kwargs: Any,
    ) -> None:
        utils.EzPickle.__init__(
            self,
            xml_file,
            default_camera_config,
            reward_dist_weight,
            reward_near_weight,
            reward_control_weight,
            **kwargs,
        )
        self._reward_dist_weight = reward_dist_weight
        self._reward_near_weight = reward_near_weight
        self._reward_control_weight = reward_control_weight
        super().__init__(xml_file, default_camera_config, **kwargs)

    def _reset_task(self, qpos: NDArray[np.float64], qvel: NDArray[np.float64]) -> None:
        x, z, angle = (self.model.joint(j) for j in BOX_JOINTS)
        qpos[x.qposadr[0]] = self.np_random.uniform(-BOX_INIT_X_HIGH, BOX_INIT_X_HIGH)
        qpos[z.qposadr[0]] = self.np_random.uniform(*BOX_INIT_Z_RANGE)
        qpos[angle.qposadr[0]] = self.np_random.uniform(-BOX_INIT_ANGLE_HIGH, BOX_INIT_ANGLE_HIGH)
        qvel[[x.dofadr[0], z.dofadr[0], angle.dofadr[0]]] = 0.0
        self._set_target(
            np.array([self.np_random.uniform(-TARGET_X_HIGH, TARGET_X_HIGH), TARGET_Z])
        )

    @cached_property
    def _box_qpos_ids(self) -> NDArray[np.int32]:
        # Lazy: the model exists only once the base __init__ has loaded it (and observed once).
        return self.model.jnt_qposadr[[self.model.joint(j).id for j in BOX_JOINTS]]

    @property
    def box_xz(self) -> NDArray[np.float64]:
        return self.data.body("box").xpos[[0, 2]]

    def _get_obs(self) -> NDArray[np.float64]:
        return np.concatenate(
            [
                self._arm_angle_features(),
                self.data.qpos[self._box_qpos_ids],
                self.target_xz,
                self.data.qvel,
            ]
        )

    def _get_rew(self, action: NDArray[np.float64]) -> tuple[float, dict[str, Any]]:
        box_xz, fingertip_xz, target_xz = self.box_xz, self.fingertip_xz, self.target_xz
        distance = norm(box_xz - target_xz)
        near_distance = norm(fingertip_xz - box_xz)
        action_norm_sq = control_cost(action)
        reward_dist = -self._reward_dist_weight * distance
        reward_near = -self._reward_near_weight * near_distance
        reward_ctrl = -self._reward_control_weight * action_norm_sq
        info = {
            "reward_dist": reward_dist,
            "reward_near": reward_near,
            "reward_ctrl": reward_ctrl,
            "distance": distance,
            "near_distance": near_distance,
            "action_norm_sq": action_norm_sq,
            "box_xz": box_xz,
            "fingertip_xz": fingertip_xz,
            "target_xz": target_xz,
        }
        return reward_dist + reward_near + reward_ctrl, info
