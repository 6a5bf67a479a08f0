"""The EDE tasks as gymnasium environments, registered under the ``ede/`` namespace. Which tasks
form a family (share a robot, and so an embedding) is the experiment's business: ``params.yaml``.

Importing the package registers the tasks, as gymnasium's other task packages do (ale-py,
gymnasium-robotics)::

    import gymnasium as gym
    import ede_envs

    gym.register_envs(ede_envs)  # a no-op that keeps linters from calling the import unused
    env = gym.make("ede/ReacherTurn-v0")

or, with no import at all, ``gym.make("ede_envs:ede/ReacherTurn-v0")``: gymnasium imports the
module named before the colon first. Registration imports gymnasium's registry, not MuJoCo: a
task's module loads when the task is made.

Every task refuses a NaN or infinite action with a ``ValueError`` before its simulator sees it
(``ede_envs._actions``), so a later valid step is unaffected.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["TASKS", "Task", "register_envs"]


@dataclass(frozen=True)
class Task:
    """One registered task: its gymnasium id, where its class lives and its episode length."""

    id: str
    entry_point: str
    max_episode_steps: int


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


def register_envs() -> None:
    """Register every ``ede/`` task with gymnasium; calling it again is harmless."""
    from gymnasium.envs.registration import register, registry

    for task in TASKS.values():
        if task.id in registry:
            continue
        register(id=task.id, entry_point=task.entry_point, max_episode_steps=task.max_episode_steps)


register_envs()
