"""``ede/PointMass-v0``: a force-driven, damped point mass in a walled arena (Figure 7)."""

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

XML_FILE: Final[Path] = Path(__file__).parent / "assets" / "point_mass.xml"
# The dynamics live in the MJCF: mass 1 kg, damping 10 N s/m, gear 8, timestep 0.01 s. With frame
# skip 5 a step lasts 0.05 s, the velocity's time constant m/b = 0.1 s is two steps and the terminal
# speed g/b = 0.8 m/s is 0.04 m a step. So a force held for 4 steps moves the mass ~0.09 m and for
# 10 steps ~0.32 m (the arena is 2 m wide), while 100 steps of uniform random per-step forces end
# a random walk of ~0.04 * sqrt(100 / 3) ~ 0.23 m per axis from the start.
FRAME_SKIP: Final[int] = 5
# No "human": offscreen modes only, so nothing (check_env included) ever needs a display;
# gymnasium.make(..., render_mode="human") still works through its HumanRendering wrapper.
RENDER_MODES: Final[tuple[str, ...]] = ("rgb_array", "depth_array", "rgbd_tuple")
DEFAULT_CAMERA_CONFIG: Final[dict[str, Any]] = {
    "trackbodyid": -1,
    "distance": 3.0,
    "azimuth": 90.0,
    "elevation": -90.0,
    "lookat": np.array([0.0, 0.0, 0.0]),
}

ARENA_HALF_WIDTH: Final[float] = 1.0  # inner faces of the walls at x, y = +-1 (see the MJCF)
START_HALF_WIDTH: Final[float] = 0.1  # start position ~ U([-0.1, 0.1]^2), at rest
GOAL_HALF_WIDTH: Final[float] = 0.8  # goal ~ U([-0.8, 0.8]^2)


class PointMassEnv(MujocoEnv, utils.EzPickle):
    r"""
    ## Description
    A point mass in a walled 2-D arena, like the DeepMind Control Suite's `point_mass`: a ball
    (radius 0.05, mass 1 kg) on two damped slide joints `root_x`, `root_y` (damping 10 N s/m),
    pushed by one motor per joint (gear 8), inside four frictionless walls whose inner faces are
    at $x, y = \pm 1$. The state `(qpos, qvel)` is exactly the position and the velocity (the goal
    is a site, not a joint).

    The constants are chosen for the paper's Figure 7 (area covered by ten episodes of random
    actions): the velocity's time constant $m / b = 0.1$ s is two steps and the terminal speed
    $g / b = 0.8$ m/s is 0.04 m per step. Uniform random per-step forces average out, so over a
    100-step episode the mass random-walks about 0.23 m (per axis) from its start, whereas a force
    held for 4 steps moves it about 0.09 m and for 10 steps about 0.32 m, and a force held for a
    whole episode drives it into a wall.

    ## Action Space
    The action space is a `Box(-1, 1, (2,), float32)`: the motor controls (force = 8 N x control).

    | Num | Action              | Control Min | Control Max | Name (in XML) | Joint  | Type (Unit) |
    |-----|---------------------|-------------|-------------|---------------|--------|-------------|
    | 0   | force along x / 8 N | -1          | 1           | force_x       | root_x | force (N)   |
    | 1   | force along y / 8 N | -1          | 1           | force_y       | root_y | force (N)   |

    ## Observation Space
    The observation space is a `Box(-Inf, Inf, (6,), float64)`:

    | Num | Observation         | Name (in XML)    | Type (Unit)    |
    |-----|---------------------|------------------|----------------|
    | 0   | x of the mass       | root_x (qpos 0)  | position (m)   |
    | 1   | y of the mass       | root_y (qpos 1)  | position (m)   |
    | 2   | x velocity          | root_x (qvel 0)  | velocity (m/s) |
    | 3   | y velocity          | root_y (qvel 1)  | velocity (m/s) |
    | 4   | x of the goal       | site `goal`      | position (m)   |
    | 5   | y of the goal       | site `goal`      | position (m)   |

    ## Rewards
    The total reward is: ***reward*** *=* *reward_dist + reward_ctrl*, after the physics step:

    - *reward_dist* $= -w_{dist} \|P_{mass} - P_{goal}\|_2$, where $w_{dist}$ is
      `reward_dist_weight` (default $1$).
    - *reward_ctrl* $= -w_{control} \|a\|_2^2$, where $w_{control}$ is `reward_control_weight`
      (default $0.01$).

    `info` holds `reward_dist` and `reward_ctrl` (whose sum is the reward) and the raw quantities
    `distance` ($\|P_{mass} - P_{goal}\|_2$), `position`, `velocity`, `goal` and `action_norm_sq`
    ($\|a\|_2^2$).

    ## Starting State
    The position is drawn from $\mathcal{U}_{[-0.1, 0.1]^2}$ with velocity $0_2$, then the goal
    from $\mathcal{U}_{[-0.8, 0.8]^2}$. The frame skip is 5 with a timestep of 0.01 (RK4), so
    *dt = 0.05*.

    ## Episode End
    ### Termination
    The PointMass never terminates.

    ### Truncation
    The default duration of an episode is 100 timesteps (`max_episode_steps` at registration).

    ## Arguments
    | Parameter               | Type      | Default                 | Description                  |
    |-------------------------|-----------|-------------------------|------------------------------|
    | `xml_file`              | **str**   | `assets/point_mass.xml` | Path to a MuJoCo model       |
    | `frame_skip`            | **int**   | `5`                     | MuJoCo steps per `step()`    |
    | `default_camera_config` | **dict**  | `DEFAULT_CAMERA_CONFIG` | The rendering camera         |
    | `reward_dist_weight`    | **float** | `1`                     | $w_{dist}$ of _reward_dist_  |
    | `reward_control_weight` | **float** | `0.01`                  | $w_{control}$, _reward_ctrl_ |

    Other keyword arguments (`render_mode`, `width`, `height`, `camera_id`, ...) go to `MujocoEnv`.
    The render modes are `rgb_array`, `depth_array` and `rgbd_tuple`, all offscreen (headless with
    `MUJOCO_GL=egl` or `osmesa`); `"human"` is not declared, so `gymnasium.make` wraps the env in
    `HumanRendering` when asked for it.

    ## Version History
    * v0: Initial version.
    """

    # An instance attribute in gymnasium's Env, which a subclass may set per instance.
    metadata: dict[str, Any] = {"render_modes": list(RENDER_MODES)}  # noqa: RUF012

    def __init__(
        self,
        xml_file: str = str(XML_FILE),
        frame_skip: int = FRAME_SKIP,
        default_camera_config: dict[str, Any] = DEFAULT_CAMERA_CONFIG,
        reward_dist_weight: float = 1.0,
        reward_control_weight: float = 0.01,
        **kwargs: Any,
    ):
        utils.EzPickle.__init__(
            self,
            xml_file,
            frame_skip,
            default_camera_config,
            reward_dist_weight,
            reward_control_weight,
            **kwargs,
        )
        self._reward_dist_weight = reward_dist_weight
        self._reward_control_weight = reward_control_weight

        observation_space = Box(low=-np.inf, high=np.inf, shape=(6,), dtype=np.float64)
        MujocoEnv.__init__(
            self,
            xml_file,
            frame_skip,
            observation_space=observation_space,
            default_camera_config=default_camera_config,
            **kwargs,
        )
        self._goal_site = self.model.site("goal").id
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
        position = self.data.qpos.copy()
        goal = self._goal()
        distance = norm(position - goal)
        action_norm_sq = sum_of_squares(action)

        reward_dist = -self._reward_dist_weight * distance
        reward_ctrl = -self._reward_control_weight * action_norm_sq
        reward = reward_dist + reward_ctrl

        reward_info = {
            "reward_dist": reward_dist,
            "reward_ctrl": reward_ctrl,
            "distance": distance,
            "position": position,
            "velocity": self.data.qvel.copy(),
            "goal": goal,
            "action_norm_sq": action_norm_sq,
        }
        return reward, reward_info

    def reset_model(self) -> NDArray[np.float64]:
        position = self.np_random.uniform(low=-START_HALF_WIDTH, high=START_HALF_WIDTH, size=2)
        goal = self.np_random.uniform(low=-GOAL_HALF_WIDTH, high=GOAL_HALF_WIDTH, size=2)
        self.model.site_pos[self._goal_site, :2] = goal
        self.set_state(position, np.zeros(self.model.nv))
        return self._get_obs()

    def _goal(self) -> NDArray[np.float64]:
        return self.model.site_pos[self._goal_site, :2].copy()

    def _get_obs(self) -> NDArray[np.float64]:
        return np.concatenate([self.data.qpos, self.data.qvel, self._goal()])
