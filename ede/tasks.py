"""What the library needs to know about the tasks: descriptions, construction, and whether ede can
use one at all."""

from __future__ import annotations

import functools
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import gymnasium
import numpy as np

import ede_envs
from ede.errors import first_line

if TYPE_CHECKING:  # for annotations only: importing it imports MuJoCo
    from gymnasium.envs.mujoco.mujoco_env import MujocoEnv

__all__ = ["TaskInfo", "action_box", "describe_tasks", "make", "unusable"]


@dataclass(frozen=True)
class TaskInfo:
    """The facts of one task that ``ede-pipeline envs`` prints."""

    id: str
    family: str
    role: str  # "source" or "target"
    observation_shape: tuple[int, ...]
    action_space: str
    max_episode_steps: int


def make(task_id: str, **kwargs: Any) -> gymnasium.Env:
    """``gymnasium.make`` with the ``ede/`` tasks registered."""
    ede_envs.register_envs()
    return gymnasium.make(task_id, **kwargs)


@functools.cache  # params validation asks about the same few tasks often
def unusable(task_id: str) -> str | None:
    """Why ede cannot use ``task_id``, in one short phrase, or None when it can.

    ede draws uniform random actions from a flat Box and feeds flat observation vectors to its
    networks, so both spaces must be rank-1 Boxes. Builds the task once to read its spaces.
    """
    try:
        with warnings.catch_warnings():  # an old version's deprecation: the answer says enough
            warnings.simplefilter("ignore")
            env = make(task_id)
    except (gymnasium.error.Error, ImportError) as error:  # DependencyNotInstalled, Ant-v2 (moved)
        return f"it cannot be made ({type(error).__name__}: {first_line(error)})"
    try:
        action, observation = env.action_space, env.observation_space
    finally:
        env.close()
    if not (isinstance(action, gymnasium.spaces.Box) and len(action.shape) == 1):
        return f"its actions are {_describe(action)}; ede needs a flat Box action space"
    if not action.is_bounded():
        return "its actions are unbounded; ede draws uniform random actions from bounded ones"
    if not (isinstance(observation, gymnasium.spaces.Box) and len(observation.shape) == 1):
        return f"its observations are {_describe(observation)}; ede needs flat observation vectors"
    return None


def _describe(space: gymnasium.Space) -> str:
    if isinstance(space, gymnasium.spaces.Box):
        kind = "images" if len(space.shape) == 3 else "a Box"
        return f"{kind} of shape {space.shape}"
    text = str(space)  # Discrete(2) reads well; a Dict's full text would not fit a line
    return text if len(text) <= 40 else type(space).__name__


def describe_tasks(families: Mapping[str, Any]) -> list[TaskInfo]:
    """Every task this package registers and every task of ``families`` (the params'
    ``FamilyConfig`` by name), each built once to read its spaces; a task in no family has
    family and role "-"."""
    roles = {
        task: (name, "source" if task == family.source else "target")
        for name, family in families.items()
        for task in family.tasks
    }
    infos = []
    for task_id in dict.fromkeys([*ede_envs.TASKS, *roles]):
        family, role = roles.get(task_id, ("-", "-"))
        env = make(task_id)
        try:
            space = env.action_space
            assert isinstance(space, gymnasium.spaces.Box)
            low, high = np.unique(space.low), np.unique(space.high)
            bounds = f"[{low[0]:g},{high[0]:g}]" if low.size == high.size == 1 else "mixed"
            infos.append(
                TaskInfo(
                    id=task_id,
                    family=family,
                    role=role,
                    observation_shape=env.observation_space.shape or (),
                    action_space=f"Box{bounds}^{space.shape[0]}",
                    max_episode_steps=(env.spec.max_episode_steps or 0) if env.spec else 0,
                )
            )
        finally:
            env.close()
    return infos


def action_bounds(env: gymnasium.Env) -> tuple[np.ndarray, np.ndarray]:
    """The low and high bounds of ``env``'s action Box (every usable task's actions are one)."""
    space = env.action_space
    if not isinstance(space, gymnasium.spaces.Box):
        raise TypeError(f"{env.spec.id if env.spec else env}: its actions are not a Box")
    return space.low, space.high


def simulator(env: gymnasium.Env) -> MujocoEnv:
    """``env``'s innermost environment, a MuJoCo task (its ``data``, ``model``, ``set_state``)."""
    from gymnasium.envs.mujoco.mujoco_env import MujocoEnv  # imports MuJoCo

    inner = env.unwrapped
    if not isinstance(inner, MujocoEnv):
        raise TypeError(f"{env.spec.id if env.spec else env}: not a MuJoCo task")
    return inner


def observation_size(env: gymnasium.Env) -> int:
    """The length of ``env``'s flat observation vector."""
    shape = env.observation_space.shape
    if shape is None or len(shape) != 1:
        raise TypeError(f"{env.spec.id if env.spec else env}: observations are not a flat vector")
    return shape[0]


@functools.cache
def action_box(task_id: str) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The bounds (low, high) of a usable task's action Box, for comparing tasks."""
    env = make(task_id)
    try:
        low, high = action_bounds(env)
        return tuple(np.asarray(low, np.float64).tolist()), tuple(
            np.asarray(high, np.float64).tolist()
        )
    finally:
        env.close()
