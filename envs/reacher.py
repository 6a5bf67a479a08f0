"""What the Reacher family's three tasks share: the arm, its arena, its reset and its stepping.

The robot and arena live in ``assets/reacher_arm.xml``, which each task's model includes; this
module is the Python side of the same split. A task subclasses :class:`ReacherFamilyEnv` and
supplies its model file, where its target and objects start (:meth:`_reset_task`), its
observation (:meth:`_get_obs`) and its reward (:meth:`_get_rew`).
"""

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
from ede_envs._numerics import cos_sin, sum_of_squares

__all__ = ["ASSETS_DIR", "DEFAULT_CAMERA_CONFIG", "FRAME_SKIP", "ReacherFamilyEnv", "control_cost"]

ASSETS_DIR: Final[Path] = Path(__file__).resolve().parent / "assets"

FRAME_SKIP: Final[int] = 2  # with the model's timestep 0.01: dt = 0.02 s
RENDER_FPS: Final[int] = 50  # 1 / dt; MujocoEnv asserts that it agrees with the model

ARM_JOINTS: Final[tuple[str, str]] = ("joint0", "joint1")
ARM_INIT_ANGLE_HIGH: Final[float] = np.pi  # both arm angles start uniform in [-pi, pi]
ARM_INIT_VELOCITY_HIGH: Final[float] = 0.005  # arm velocities start uniform in [-0.005, 0.005]
MAX_RESET_TRIES: Final[int] = 1000

# A free camera looking along +y at the x-z plane from slightly above, just right of the arm's
# base so that ReacherTurn's spinner (out to x = 0.5) stays in the picture.
DEFAULT_CAMERA_CONFIG: Final[dict[str, Any]] = {
    "lookat": np.array([0.05, 0.0, 0.22]),
    "distance": 1.3,
    "azimuth": 90.0,
    "elevation": -10.0,
}


class ReacherFamilyEnv(MujocoEnv, utils.EzPickle):
    r"""Base of the Reacher family: a 2-link arm in a vertical plane, under gravity.

    Not registered itself; see :class:`~ede_envs.reacher_vertical.ReacherVerticalEnv`,
    :class:`~ede_envs.reacher_turn.ReacherTurnEnv` and
    :class:`~ede_envs.reacher_push.ReacherPushEnv`.

    ## Robot
    Two capsule links of length 0.2 (radius 0.02) in the x-z plane, the first hinged at
    (0, 0.25), both hinges turning about -y (angle 0 points along +x, positive angles turn
    counterclockwise as the default camera sees them). `joint0` is unlimited, `joint1` is limited
    to [-3, 3] rad. The fingertip is a sphere of radius 0.02 at 0.21 along the second link.
    Every joint has armature 1 and damping 1 unless a task says otherwise. Gravity is -9.81 on z,
    the integrator RK4, the timestep 0.01 and the frame skip 2, so `dt = 0.02`.

    ## Action Space
    The action space is `Box(-1, 1, (2,), float32)`, the same for every task in the family. An
    action is the pair of motor commands, each multiplied by the gear 200 into a torque.

    | Num | Action                               | Control Min | Control Max | Name (in XML) | Joint | Type (Unit)  |
    |-----|--------------------------------------|-------------|-------------|---------------|-------|--------------|
    | 0   | Torque at the base hinge (x 200)     | -1          | 1           | joint0        | hinge | torque (N m) |
    | 1   | Torque at the elbow hinge (x 200)    | -1          | 1           | joint1        | hinge | torque (N m) |

    ## Starting State
    Both arm angles are uniform in [-pi, pi] within their limits (so `joint1` in [-3, 3]) and
    both arm velocities uniform in [-0.005, 0.005]; the task then places its target and objects.
    The whole draw is repeated until no two geoms touch (at most 1000 times, then `reset` raises
    `RuntimeError`). The fingertip is welded to the second link, so MuJoCo never counts it as
    touching the first (its parent's parent); hence the limit, not the contact test, keeps the
    elbow from folding the fingertip onto the base.

    ## Episode End
    The environment never terminates; `gymnasium.make` adds a `TimeLimit` of 100 steps.
    """

    # An instance attribute in gymnasium's Env, which a subclass may set per instance.
    metadata: dict[str, Any] = {  # noqa: RUF012
        "render_modes": ["human", "rgb_array", "depth_array", "rgbd_tuple"],
        "render_fps": RENDER_FPS,
    }

    def __init__(
        self,
        xml_file: str | Path,
        default_camera_config: dict[str, Any] | None = None,
        **kwargs: Any,
    ) -> None:
        """Load the task's model and size the observation space from a first observation.

        Args:
            xml_file: the task's MJCF file, which includes ``reacher_arm.xml``.
            default_camera_config: attributes of the free rendering camera; ``None`` for
                :data:`DEFAULT_CAMERA_CONFIG`.
            **kwargs: passed to :class:`~gymnasium.envs.mujoco.MujocoEnv` (``render_mode``,
                ``width``, ``height``, ...).
        """
        MujocoEnv.__init__(
            self,
            str(Path(xml_file).resolve()),
            FRAME_SKIP,
            observation_space=None,
            default_camera_config=(
                DEFAULT_CAMERA_CONFIG if default_camera_config is None else default_camera_config
            ),
            **kwargs,
        )
        arm_joint_ids = np.array([self.model.joint(j).id for j in ARM_JOINTS])
        self._arm_qpos_ids = self.model.jnt_qposadr[arm_joint_ids]
        self._arm_qvel_ids = self.model.jnt_dofadr[arm_joint_ids]
        # Drawing inside a limit is drawing in [-pi, pi] and rejecting what breaks the limit:
        # a start beyond joint1's [-3, 3] would be kicked back hard by the limit constraint.
        limited = self.model.jnt_limited[arm_joint_ids].astype(bool)
        joint_range = self.model.jnt_range[arm_joint_ids]
        self._arm_init_low = np.where(
            limited, np.maximum(joint_range[:, 0], -ARM_INIT_ANGLE_HIGH), -ARM_INIT_ANGLE_HIGH
        )
        self._arm_init_high = np.where(
            limited, np.minimum(joint_range[:, 1], ARM_INIT_ANGLE_HIGH), ARM_INIT_ANGLE_HIGH
        )
        self._target_mocap_id = int(self.model.body("target").mocapid[0])
        self.observation_space = Box(
            low=-np.inf, high=np.inf, shape=self._get_obs().shape, dtype=np.float64
        )

    # gymnasium's MujocoEnv annotates step's reward np.float64 and its info's values too; the
    # Env API, which every caller reads, has a float reward and any info.
    def step(  # type: ignore[override]
        self, action: NDArray[np.float32]
    ) -> tuple[NDArray[np.float64], float, bool, bool, dict[str, Any]]:
        check_action(self, action)
        self.do_simulation(action, self.frame_skip)
        # mj_step leaves body and site positions one substep behind qpos; bring them level so
        # that the observation and the reward describe a single state.
        mujoco.mj_forward(self.model, self.data)
        observation = self._get_obs()
        reward, info = self._get_rew(np.asarray(action, dtype=np.float64))
        if self.render_mode == "human":
            self.render()
        # Never terminated; truncation is the TimeLimit wrapper's job.
        return observation, reward, False, False, info

    def reset_model(self) -> NDArray[np.float64]:
        """Draw a starting state in which nothing touches.

        Raises:
            RuntimeError: if no contact-free state turned up in ``MAX_RESET_TRIES`` draws.
        """
        for _ in range(MAX_RESET_TRIES):
            qpos = self.init_qpos.copy()
            qvel = self.init_qvel.copy()
            qpos[self._arm_qpos_ids] = self.np_random.uniform(
                self._arm_init_low, self._arm_init_high
            )
            qvel[self._arm_qvel_ids] = self.np_random.uniform(
                -ARM_INIT_VELOCITY_HIGH, ARM_INIT_VELOCITY_HIGH, size=len(ARM_JOINTS)
            )
            self._reset_task(qpos, qvel)
            self.set_state(qpos, qvel)  # runs mj_forward, which finds the contacts
            if self.data.ncon == 0:
                return self._get_obs()
        raise RuntimeError(
            f"{type(self).__name__}: no contact-free starting state in {MAX_RESET_TRIES} draws; "
            f"{self.data.ncon} contacts in the last one"
        )

    def _reset_task(self, qpos: NDArray[np.float64], qvel: NDArray[np.float64]) -> None:
        """Place the task's target and objects: write ``qpos``/``qvel`` in place, set the target.

        Args:
            qpos: the starting positions, arm angles already drawn.
            qvel: the starting velocities, arm velocities already drawn.
        """
        raise NotImplementedError

    def _get_obs(self) -> NDArray[np.float64]:
        raise NotImplementedError

    def _get_rew(self, action: NDArray[np.float64]) -> tuple[float, dict[str, Any]]:
        """The step's reward and ``info``: each weighted term as ``reward_<name>`` (they sum to
        the reward) and the raw quantities the terms are computed from."""
        raise NotImplementedError

    # Shared pieces of observations and rewards; the world is planar, so positions are (x, z).

    def _arm_angle_features(self) -> NDArray[np.float64]:
        """cos(joint0), cos(joint1), sin(joint0), sin(joint1)."""
        angles = self.data.qpos[self._arm_qpos_ids]
        return cos_sin(angles)

    @property
    def fingertip_xz(self) -> NDArray[np.float64]:
        return self.data.body("fingertip").xpos[[0, 2]]

    @property
    def target_xz(self) -> NDArray[np.float64]:
        return self.data.mocap_pos[self._target_mocap_id, [0, 2]]

    def _set_target(self, target_xz: NDArray[np.float64]) -> None:
        self.data.mocap_pos[self._target_mocap_id] = (target_xz[0], 0.0, target_xz[1])


def control_cost(action: NDArray[np.float64]) -> float:
    """``‖a‖²``, the squared norm that every task's control term is a multiple of."""
    return sum_of_squares(action)
