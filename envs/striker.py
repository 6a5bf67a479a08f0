"""``ede/Striker-v0``: strike a ball with a flat paddle so that it slides to a goal (7-DoF)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Final

import numpy as np
from gymnasium import utils
from gymnasium.envs.mujoco import MujocoEnv
from gymnasium.spaces import Box
from numpy.typing import NDArray

from ede_envs._actions import check_action
from ede_envs._numerics import norm, sum_of_squares

XML_FILE: Final[Path] = Path(__file__).parent / "assets" / "striker.xml"
FRAME_SKIP: Final[int] = 5
# No "human": offscreen modes only, so nothing (check_env included) ever needs a display;
# gymnasium.make(..., render_mode="human") still works through its HumanRendering wrapper.
RENDER_MODES: Final[tuple[str, ...]] = ("rgb_array", "depth_array", "rgbd_tuple")
DEFAULT_CAMERA_CONFIG: Final[dict[str, Any]] = {
    "trackbodyid": -1,
    "distance": 2.6,
    "azimuth": 135.0,
    "elevation": -35.0,
    "lookat": np.array([0.35, 0.05, -0.3]),
}

NUM_ARM_JOINTS: Final[int] = 7
BALL_START: Final[tuple[float, float]] = (0.5, -0.175)  # (x, y) in the table plane
GOAL_LOW: Final[tuple[float, float]] = (0.15, 0.1)  # goal (x, y) ~ U(GOAL_LOW, GOAL_HIGH)
GOAL_HIGH: Final[tuple[float, float]] = (0.7, 1.0)
MIN_GOAL_BALL_DISTANCE: Final[float] = 0.17  # goals closer to the ball are resampled
ARM_VELOCITY_NOISE: Final[float] = 0.1  # arm qvel ~ U(-0.1, 0.1) at reset, as in Striker-v2
STRIKE_THRESHOLD: Final[float] = 0.1  # the ball counts as struck once the tip comes this close


class StrikerEnv(MujocoEnv, utils.EzPickle):
    r"""
    ## Description
    A port of gym's `Striker-v2` onto gymnasium's `Pusher-v5` robot. The 7-DoF arm has to strike a
    ball lying on the table with a flat paddle so that the ball slides to a goal marker.

    The arm (its bodies, geoms, its 7 joints with their names, axes, ranges, damping and armature,
    the physics options and the motors) is Pusher-v5's; only the end effector differs: a flat
    paddle, as in the original Striker, instead of Pusher's C-shaped tip. The ball is the original
    Striker's (a sphere of radius 0.05 on two damped slide joints). The goal is a marker that
    collides with nothing (the original's cup around the goal is left out).

    ## Action Space
    The action space is a `Box(-2, 2, (7,), float32)`, exactly Pusher-v5's: the torques at the 7
    hinge joints. **The original Striker's motors allowed [-3, 3]; this port uses Pusher's motors
    ([-2, 2], same gear and control settings) so that Pusher and Striker share one action space.**

    | Num | Action (torque at)   | Min | Max | Name (in XML)          | Type (Unit)  |
    |-----|----------------------|-----|-----|------------------------|--------------|
    | 0   | the shoulder pan     | -2  | 2   | r_shoulder_pan_joint   | torque (N m) |
    | 1   | the shoulder lift    | -2  | 2   | r_shoulder_lift_joint  | torque (N m) |
    | 2   | the upper arm roll   | -2  | 2   | r_upper_arm_roll_joint | torque (N m) |
    | 3   | the elbow flex       | -2  | 2   | r_elbow_flex_joint     | torque (N m) |
    | 4   | the forearm roll     | -2  | 2   | r_forearm_roll_joint   | torque (N m) |
    | 5   | the wrist flex       | -2  | 2   | r_wrist_flex_joint     | torque (N m) |
    | 6   | the wrist roll       | -2  | 2   | r_wrist_roll_joint     | torque (N m) |

    ## Observation Space
    The observation space is a `Box(-Inf, Inf, (23,), float64)`, laid out as Pusher-v5's:

    | Num | Observation                                | Source          | Type (Unit)           |
    |-----|--------------------------------------------|-----------------|-----------------------|
    | 0   | angle of r_shoulder_pan_joint              | qpos[0]         | angle (rad)           |
    | 1   | angle of r_shoulder_lift_joint             | qpos[1]         | angle (rad)           |
    | 2   | angle of r_upper_arm_roll_joint            | qpos[2]         | angle (rad)           |
    | 3   | angle of r_elbow_flex_joint                | qpos[3]         | angle (rad)           |
    | 4   | angle of r_forearm_roll_joint              | qpos[4]         | angle (rad)           |
    | 5   | angle of r_wrist_flex_joint                | qpos[5]         | angle (rad)           |
    | 6   | angle of r_wrist_roll_joint                | qpos[6]         | angle (rad)           |
    | 7   | angular velocity of r_shoulder_pan_joint   | qvel[0]         | ang. velocity (rad/s) |
    | 8   | angular velocity of r_shoulder_lift_joint  | qvel[1]         | ang. velocity (rad/s) |
    | 9   | angular velocity of r_upper_arm_roll_joint | qvel[2]         | ang. velocity (rad/s) |
    | 10  | angular velocity of r_elbow_flex_joint     | qvel[3]         | ang. velocity (rad/s) |
    | 11  | angular velocity of r_forearm_roll_joint   | qvel[4]         | ang. velocity (rad/s) |
    | 12  | angular velocity of r_wrist_flex_joint     | qvel[5]         | ang. velocity (rad/s) |
    | 13  | angular velocity of r_wrist_roll_joint     | qvel[6]         | ang. velocity (rad/s) |
    | 14  | x of the arm tip (wrist)                   | body `tips_arm` | position (m)          |
    | 15  | y of the arm tip (wrist)                   | body `tips_arm` | position (m)          |
    | 16  | z of the arm tip (wrist)                   | body `tips_arm` | position (m)          |
    | 17  | x of the ball                              | body `object`   | position (m)          |
    | 18  | y of the ball                              | body `object`   | position (m)          |
    | 19  | z of the ball                              | body `object`   | position (m)          |
    | 20  | x of the goal                              | body `goal`     | position (m)          |
    | 21  | y of the goal                              | body `goal`     | position (m)          |
    | 22  | z of the goal                              | body `goal`     | position (m)          |

    The full physical state is `qpos` (11: 7 arm joints, ball x, ball y, goal x, goal y; joints
    `obj_slidex`, `obj_slidey`, `goal_slidex`, `goal_slidey`) and `qvel` (11).

    ## Rewards
    The total reward is: ***reward*** *=* *reward_dist + reward_ctrl + reward_near*, all computed
    after the physics step:

    - *reward_dist* $= -w_{dist} \min_{t' \le t} \|P_{ball}(t') - P_{goal}\|_2$: minus the closest
      the ball has come to the goal so far in the episode, where $w_{dist}$ is
      `reward_dist_weight` (default $3$).
    - *reward_ctrl* $= -w_{control} \|a\|_2^2$, where $w_{control}$ is `reward_control_weight`
      (default $0.1$).
    - *reward_near* $= -w_{near} \|P_{ball} - P_{ref}\|_2$, where $P_{ref}$ is the arm tip until the
      ball is struck (the tip comes within `STRIKE_THRESHOLD` $= 0.1$ of the ball) and the tip's
      position at that moment ever after; $w_{near}$ is `reward_near_weight` (default $0.5$).

    `info` holds the three weighted terms (`reward_dist`, `reward_ctrl`, `reward_near`, whose sum is
    the reward) and the raw quantities: `distance_ball_goal`, `closest_distance_ball_goal`,
    `distance_tip_ball`, `struck`, `near_reference` ($P_{ref}$), `tip_position`,
    `ball_position`, `goal_position` and `action_norm_sq` ($\|a\|_2^2$).

    ## Starting State
    The arm starts at its initial joint angles ($0_7$) with joint velocities
    $\mathcal{U}_{[-0.1, 0.1]}$ (as in Striker-v2). The ball starts at rest at $(0.5, -0.175)$.
    The goal $(x, y)$ is drawn from $\mathcal{U}_{[0.15, 0.7] \times [0.1, 1.0]}$ and resampled
    until it is at least $0.17$ from the ball (a rule kept from Striker-v2 that never binds with
    this box: every goal in it is at least 0.275 from the ball). The episode's closest ball-goal
    distance and strike state are reset with the model.

    The frame skip is 5 with a timestep of 0.01, so *dt = 0.05*.

    ## Episode End
    ### Termination
    The Striker never terminates.

    ### Truncation
    The default duration of an episode is 100 timesteps (`max_episode_steps` at registration).

    ## Arguments
    | Parameter               | Type      | Default                 | Description                 |
    |-------------------------|-----------|-------------------------|-----------------------------|
    | `xml_file`              | **str**   | `assets/striker.xml`    | Path to a MuJoCo model      |
    | `frame_skip`            | **int**   | `5`                     | MuJoCo steps per `step()`   |
    | `default_camera_config` | **dict**  | `DEFAULT_CAMERA_CONFIG` | The rendering camera        |
    | `reward_dist_weight`    | **float** | `3`                     | $w_{dist}$ of _reward_dist_ |
    | `reward_control_weight` | **float** | `0.1`                   | $w_{control}$, _reward_ctrl_ |
    | `reward_near_weight`    | **float** | `0.5`                   | $w_{near}$ of _reward_near_ |

    Other keyword arguments (`render_mode`, `width`, `height`, `camera_id`, ...) go to `MujocoEnv`.
    The render modes are `rgb_array`, `depth_array` and `rgbd_tuple`, all offscreen (headless with
    `MUJOCO_GL=egl` or `osmesa`); `"human"` is not declared, so `gymnasium.make` wraps the env in
    `HumanRendering` when asked for it.

    ## Version History
    * v0: Initial version: gym's Striker-v2 on Pusher-v5's arm and motors ([-2, 2] instead of
      [-3, 3]); rewards computed after the physics step (Striker-v2 computed them before it); the
      goal has no cup walls and slides instead of being a free body.
    """

    # An instance attribute in gymnasium's Env, which a subclass may set per instance.
    metadata: dict[str, Any] = {"render_modes": list(RENDER_MODES)}  # noqa: RUF012

    def __init__(
        self,
        xml_file: str = str(XML_FILE),
        frame_skip: int = FRAME_SKIP,
        default_camera_config: dict[str, Any] = DEFAULT_CAMERA_CONFIG,
        reward_dist_weight: float = 3.0,
        reward_control_weight: float = 0.1,
        reward_near_weight: float = 0.5,
        **kwargs: Any,
    ):
        utils.EzPickle.__init__(
            self,
            xml_file,
            frame_skip,
            default_camera_config,
            reward_dist_weight,
            reward_control_weight,
            reward_near_weight,
            **kwargs,
        )
        self._reward_dist_weight = reward_dist_weight
        self._reward_control_weight = reward_control_weight
        self._reward_near_weight = reward_near_weight

        # Episode state, reset in reset_model.
        self._closest_distance = np.inf
        self._struck = False
        self._strike_position = np.zeros(3)

        observation_space = Box(low=-np.inf, high=np.inf, shape=(23,), dtype=np.float64)
        MujocoEnv.__init__(
            self,
            xml_file,
            frame_skip,
            observation_space=observation_space,
            default_camera_config=default_camera_config,
            **kwargs,
        )
        self.metadata = {
            "render_modes": list(RENDER_MODES),
            "render_fps": int(np.round(1.0 / self.dt)),
        }

    # gymnasium's MujocoEnv annotates step's reward np.float64 and its info's values too; the
    # Env API, which every caller reads, has a float reward and any info.
    def step(  # type: ignore[override]
        self, action: NDArray[np.float32]
    ) -> tuple[NDArray[np.float64], float, bool, bool, dict[str, Any]]:
        check_action(self, action)
        self.do_simulation(action, self.frame_skip)

        observation = self._get_obs()
        reward, reward_info = self._get_rew(action)

        # truncated=False: the time limit is the TimeLimit wrapper's, added by `make`.
        return observation, reward, False, False, reward_info

    def _get_rew(self, action: NDArray[np.float32]) -> tuple[float, dict[str, Any]]:
        """The reward after the physics step; updates the closest distance and the strike state."""
        tip = self.get_body_com("tips_arm").copy()
        ball = self.get_body_com("object").copy()
        goal = self.get_body_com("goal").copy()

        distance_ball_goal = norm(ball - goal)
        distance_tip_ball = norm(ball - tip)
        self._closest_distance = min(self._closest_distance, distance_ball_goal)
        if not self._struck and distance_tip_ball < STRIKE_THRESHOLD:
            self._struck = True
            self._strike_position = tip
        near_reference = self._strike_position.copy() if self._struck else tip
        action_norm_sq = sum_of_squares(action)

        reward_dist = -self._reward_dist_weight * self._closest_distance
        reward_ctrl = -self._reward_control_weight * action_norm_sq
        reward_near = -self._reward_near_weight * norm(ball - near_reference)
        reward = reward_dist + reward_ctrl + reward_near

        reward_info = {
            "reward_dist": reward_dist,
            "reward_ctrl": reward_ctrl,
            "reward_near": reward_near,
            "distance_ball_goal": distance_ball_goal,
            "closest_distance_ball_goal": self._closest_distance,
            "distance_tip_ball": distance_tip_ball,
            "struck": self._struck,
            "near_reference": near_reference,
            "tip_position": tip,
            "ball_position": ball,
            "goal_position": goal,
            "action_norm_sq": action_norm_sq,
        }
        return reward, reward_info

    def reset_model(self) -> NDArray[np.float64]:
        self._closest_distance = np.inf
        self._struck = False
        self._strike_position = np.zeros(3)

        ball = np.asarray(BALL_START)
        while True:
            goal = self.np_random.uniform(low=GOAL_LOW, high=GOAL_HIGH)
            if norm(ball - goal) >= MIN_GOAL_BALL_DISTANCE:
                break

        qpos = self.init_qpos.copy()
        qpos[NUM_ARM_JOINTS : NUM_ARM_JOINTS + 2] = ball
        qpos[NUM_ARM_JOINTS + 2 : NUM_ARM_JOINTS + 4] = goal
        qvel = self.init_qvel.copy()
        qvel[:NUM_ARM_JOINTS] += self.np_random.uniform(
            low=-ARM_VELOCITY_NOISE, high=ARM_VELOCITY_NOISE, size=NUM_ARM_JOINTS
        )
        self.set_state(qpos, qvel)
        return self._get_obs()

    def _get_obs(self) -> NDArray[np.float64]:
        return np.concatenate(
            [
                self.data.qpos[:NUM_ARM_JOINTS],
                self.data.qvel[:NUM_ARM_JOINTS],
                self.get_body_com("tips_arm"),
                self.get_body_com("object"),
                self.get_body_com("goal"),
            ]
        )
