"""``ede/Point-v0``: a point in the plane moved by exactly linear displacements (paper Figure 6)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Final

import mujoco
import numpy as np
from gymnasium import utils
from gymnasium.envs.mujoco import MujocoEnv
from gymnasium.spaces import Box
from numpy.typing import NDArray

from ede_envs._actions import check_action
from ede_envs._numerics import norm

XML_FILE: Final[Path] = Path(__file__).parent / "assets" / "point.xml"
# Nothing is integrated: dt = the model's timestep (0.05) only sets the render rate.
FRAME_SKIP: Final[int] = 1
# No "human": offscreen modes only, so nothing (check_env included) ever needs a display;
# gymnasium.make(..., render_mode="human") still works through its HumanRendering wrapper.
RENDER_MODES: Final[tuple[str, ...]] = ("rgb_array", "depth_array", "rgbd_tuple")
DEFAULT_CAMERA_CONFIG: Final[dict[str, Any]] = {
    "trackbodyid": -1,
    "distance": 3.8,
    "azimuth": 90.0,
    "elevation": -90.0,
    "lookat": np.array([0.0, 0.0, 0.0]),
}

ACTION_LIMIT: Final[float] = 1.0  # actions are clipped to [-1, 1]^2
STEP_SIZE: Final[float] = 0.05  # c in s' = s + c a: 40 steps cross the square [-1, 1]^2
START_HALF_WIDTH: Final[float] = 1.0  # start position ~ U([-1, 1]^2)
GOAL_HALF_WIDTH: Final[float] = 1.0  # goal ~ U([-1, 1]^2)


class PointEnv(MujocoEnv, utils.EzPickle):
    r"""
    ## Description
    A point in the plane whose state is its position and whose action is a displacement: the step
    is exactly linear, $s_{t+1} = s_t + c \cdot \mathrm{clip}(a_t, -1, 1)$ with $c$ = `step_size`.
    Used for the paper's Figure 6 (the EDE space against the effect $s_{t+4} - s_t$) and as an
    easy "reach the goal" task.

    The model is a small body on two unlimited slide joints `slide_x`, `slide_y`; the environment
    writes the new position straight into `qpos`, keeps `qvel` at zero and calls `mj_forward` (no
    integration, no contacts, no walls), so the state `(qpos, qvel)` is `((x, y), (0, 0))`. The
    goal is a site (`goal`), not a joint, so it is not part of `qpos`.

    ## Action Space
    The action space is a `Box(-1, 1, (2,), float32)`. Actions outside it are clipped; a NaN or
    infinite one is refused (`ValueError`), as by every `ede/` task.

    | Num | Action                        | Min | Max | Name (in XML) | Type (Unit)        |
    |-----|-------------------------------|-----|-----|---------------|--------------------|
    | 0   | displacement along x / `c`    | -1  | 1   | slide_x       | position (m / `c`) |
    | 1   | displacement along y / `c`    | -1  | 1   | slide_y       | position (m / `c`) |

    ## Observation Space
    The observation space is a `Box(-Inf, Inf, (4,), float64)`:

    | Num | Observation            | Name (in XML)    | Type (Unit)  |
    |-----|------------------------|------------------|--------------|
    | 0   | x of the point         | slide_x (qpos 0) | position (m) |
    | 1   | y of the point         | slide_y (qpos 1) | position (m) |
    | 2   | x of the goal          | site `goal`      | position (m) |
    | 3   | y of the goal          | site `goal`      | position (m) |

    ## Rewards
    ***reward*** *=* *reward_dist* $= -\|P_{point} - P_{goal}\|_2$, after the step.

    `info` holds `reward_dist` (equal to the reward) and the raw quantities `distance`
    ($\|P_{point} - P_{goal}\|_2$), `position`, `goal`, `action_clipped` and `displacement`
    ($c \cdot$ `action_clipped`).

    ## Starting State
    The position is drawn from $\mathcal{U}_{[-1, 1]^2}$, then the goal from
    $\mathcal{U}_{[-1, 1]^2}$; the velocity is $0_2$.

    ## Episode End
    ### Termination
    The Point never terminates.

    ### Truncation
    The default duration of an episode is 100 timesteps (`max_episode_steps` at registration).

    ## Arguments
    | Parameter               | Type      | Default                 | Description                  |
    |-------------------------|-----------|-------------------------|------------------------------|
    | `xml_file`              | **str**   | `assets/point.xml`      | Path to a MuJoCo model       |
    | `step_size`             | **float** | `0.05`                  | `c`: a unit action's move    |
    | `default_camera_config` | **dict**  | `DEFAULT_CAMERA_CONFIG` | The rendering camera         |

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
        step_size: float = STEP_SIZE,
        default_camera_config: dict[str, Any] = DEFAULT_CAMERA_CONFIG,
        **kwargs: Any,
    ):
        utils.EzPickle.__init__(self, xml_file, step_size, default_camera_config, **kwargs)
        self.step_size = step_size

        observation_space = Box(low=-np.inf, high=np.inf, shape=(4,), dtype=np.float64)
        MujocoEnv.__init__(
            self,
            xml_file,
            FRAME_SKIP,
            observation_space=observation_space,
            default_camera_config=default_camera_config,
            **kwargs,
        )
        self._goal_site = self.model.site("goal").id
        self.metadata = {
            "render_modes": list(RENDER_MODES),
            "render_fps": int(np.round(1.0 / self.dt)),
        }

    def _set_action_space(self) -> Box:
        # The model has no actuators: the action is a displacement, not a control.
        self.action_space = Box(low=-ACTION_LIMIT, high=ACTION_LIMIT, shape=(2,), dtype=np.float32)
        return self.action_space

    # gymnasium's MujocoEnv annotates step's reward np.float64 and its info's values too; the
    # Env API, which every caller reads, has a float reward and any info.
    def step(  # type: ignore[override]
        self, action: NDArray[np.float32]
    ) -> tuple[NDArray[np.float64], float, bool, bool, dict[str, Any]]:
        check_action(self, action)
        action_clipped = np.clip(np.asarray(action, dtype=np.float64), -ACTION_LIMIT, ACTION_LIMIT)
        if action_clipped.shape != (2,):
            raise ValueError(f"Action shape mismatch: expected (2,), found {action_clipped.shape}")
        displacement = self.step_size * action_clipped
        self.data.qpos[:] = self.data.qpos + displacement
        self.data.qvel[:] = 0.0
        self.data.time += self.dt
        mujoco.mj_forward(self.model, self.data)

        observation = self._get_obs()
        reward, reward_info = self._get_rew(action)
        info = {**reward_info, "action_clipped": action_clipped, "displacement": displacement}

        # truncated=False: the time limit is the TimeLimit wrapper's, added by `make`.
        return observation, reward, False, False, info

    def _get_rew(self, action: NDArray[np.float32]) -> tuple[float, dict[str, Any]]:
        del action  # the reward does not depend on the action
        position = self.data.qpos.copy()
        goal = self._goal()
        distance = norm(position - goal)
        reward_dist = -distance
        reward_info = {
            "reward_dist": reward_dist,
            "distance": distance,
            "position": position,
            "goal": goal,
        }
        return reward_dist, reward_info

    def reset_model(self) -> NDArray[np.float64]:
        position = self.np_random.uniform(low=-START_HALF_WIDTH, high=START_HALF_WIDTH, size=2)
        goal = self.np_random.uniform(low=-GOAL_HALF_WIDTH, high=GOAL_HALF_WIDTH, size=2)
        self.model.site_pos[self._goal_site, :2] = goal
        self.set_state(position, np.zeros(self.model.nv))
        return self._get_obs()

    def _goal(self) -> NDArray[np.float64]:
        return self.model.site_pos[self._goal_site, :2].copy()

    def _get_obs(self) -> NDArray[np.float64]:
        return np.concatenate([self.data.qpos, self._goal()])
