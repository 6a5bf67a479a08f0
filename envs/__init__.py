"""The EDE task families as gymnasium environments, registered under the ``ede/`` namespace.

Installing the distribution registers the tasks in every interpreter as soon as gymnasium is
imported, with no import of ours (see :mod:`ede_envs._autoregister`), so
``gymnasium.make("ede/ReacherTurn-v0")`` just works. This module stays free of heavy imports: it
runs at interpreter start.
"""

from __future__ import annotations

from dataclasses import dataclass

from ede_envs import _autoregister

__all__ = ["FAMILIES", "TASKS", "Family", "Task", "family_of", "register_envs"]


@dataclass(frozen=True)
class Task:
    """One registered task: its gymnasium id, where its class lives and its episode length."""

    id: str
    entry_point: str
    max_episode_steps: int


@dataclass(frozen=True)
class Family:
    """Tasks that share one robot and so one action space: the embedding is learned on ``source``."""

    name: str
    source: str
    targets: tuple[str, ...]

    @property
    def tasks(self) -> tuple[str, ...]:
        return (self.source, *self.targets)


TASKS: dict[str, Task] = {
    task.id: task
    for task in (
        Task("ede/ReacherVertical-v0", "ede_envs.reacher_vertical:ReacherVerticalEnv", 100),
        Task("ede/ReacherTurn-v0", "ede_envs.reacher_turn:ReacherTurnEnv", 100),
        Task("ede/ReacherPush-v0", "ede_envs.reacher_push:ReacherPushEnv", 100),
        Task("ede/Pusher-v0", "ede_envs.pusher:PusherEnv", 100),
        Task("ede/Striker-v0", "ede_envs.striker:StrikerEnv", 100),
        Task("ede/Point-v0", "ede_envs.point:PointEnv", 100),
        Task("ede/PointMass-v0", "ede_envs.point_mass:PointMassEnv", 100),
    )
}

FAMILIES: dict[str, Family] = {
    family.name: family
    for family in (
        Family("reacher", "ede/ReacherVertical-v0", ("ede/ReacherTurn-v0", "ede/ReacherPush-v0")),
        Family("sevendof", "ede/Pusher-v0", ("ede/Striker-v0",)),
        Family("point", "ede/Point-v0", ()),
        Family("pointmass", "ede/PointMass-v0", ()),
    )
}


def family_of(task_id: str) -> Family:
    """The family a task belongs to.

    Raises:
        KeyError: if no family holds ``task_id``.
    """
    for family in FAMILIES.values():
        if task_id in family.tasks:
            return family
    raise KeyError(f"{task_id!r} is in no family; known tasks: {', '.join(TASKS)}")


def register_envs() -> None:
    """Register every ``ede/`` task with gymnasium; calling it again is harmless."""
    from gymnasium.envs.registration import register, registry

    for task in TASKS.values():
        if task.id in registry:
            continue
        register(
            id=task.id, entry_point=task.entry_point, max_episode_steps=task.max_episode_steps
        )


_autoregister.install(register_envs)
