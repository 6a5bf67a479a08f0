"""What the library needs to know about the tasks: descriptions and construction."""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium
import numpy as np

import ede_envs

__all__ = ["TaskInfo", "describe_tasks", "make"]


@dataclass(frozen=True)
class TaskInfo:
    """The facts of one task that ``ede-pipeline envs`` prints."""

    id: str
    family: str
    role: str  # "source" or "target"
    observation_shape: tuple[int, ...]
    action_space: str
    max_episode_steps: int


def make(task_id: str, **kwargs: object) -> gymnasium.Env:
    """``gymnasium.make`` with the ``ede/`` tasks registered."""
    ede_envs.register_envs()
    return gymnasium.make(task_id, **kwargs)


def describe_tasks() -> list[TaskInfo]:
    """Every task of every shipped family, built once to read its spaces."""
    infos = []
    for family in ede_envs.FAMILIES.values():
        for task_id in family.tasks:
            env = make(task_id)
            try:
                space = env.action_space
                assert isinstance(space, gymnasium.spaces.Box)
                low, high = np.unique(space.low), np.unique(space.high)
                bounds = f"[{low[0]:g},{high[0]:g}]" if low.size == high.size == 1 else "mixed"
                infos.append(
                    TaskInfo(
                        id=task_id,
                        family=family.name,
                        role="source" if task_id == family.source else "target",
                        observation_shape=env.observation_space.shape or (),
                        action_space=f"Box{bounds}^{space.shape[0]}",
                        max_episode_steps=env.spec.max_episode_steps if env.spec else 0,
                    )
                )
            finally:
                env.close()
    return infos
