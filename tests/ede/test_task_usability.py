"""Which gymnasium tasks ede can use: rank-1 Box actions (bounded) and flat observation vectors."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import gymnasium
import numpy as np
import pytest

from ede.tasks import unusable


class _Camera(gymnasium.Env):
    """A task seen only through an 8x8 RGB image: no MuJoCo state, no flat observation."""

    observation_space = gymnasium.spaces.Box(0, 255, (8, 8, 3), dtype=np.uint8)
    action_space = gymnasium.spaces.Box(-1.0, 1.0, (2,), dtype=np.float32)

    def reset(self, *, seed: int | None = None, options: Any = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        return self.observation_space.sample(), 0.0, False, False, {}


class _Unbounded(_Camera):
    observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (3,))
    action_space = gymnasium.spaces.Box(-np.inf, np.inf, (2,))


@pytest.fixture(scope="module", autouse=True)
def _test_tasks() -> Iterator[None]:
    for name, kind in [("Camera", _Camera), ("Unbounded", _Unbounded)]:
        gymnasium.register(
            f"ede-test/{name}-v0", entry_point=lambda kind=kind, **_: kind(), max_episode_steps=10
        )
    yield
    for name in ("Camera", "Unbounded"):
        del gymnasium.registry[f"ede-test/{name}-v0"]


@pytest.mark.parametrize("task_id", ["Pendulum-v1", "HalfCheetah-v5", "ede/ReacherVertical-v0"])
def test_box_tasks_with_or_without_mujoco_physics_can_be_used(task_id: str) -> None:
    assert unusable(task_id) is None


@pytest.mark.parametrize(
    ("task_id", "reason"),
    [
        ("CartPole-v1", "its actions are Discrete(2); ede needs a flat Box action space"),
        (
            "ede-test/Camera-v0",
            "its observations are images of shape (8, 8, 3); ede needs flat observation vectors",
        ),
        (
            "ede-test/Unbounded-v0",
            "its actions are unbounded; ede draws uniform random actions from bounded ones",
        ),
    ],
)
def test_other_tasks_are_refused_in_one_phrase(task_id: str, reason: str) -> None:
    assert unusable(task_id) == reason


def test_a_task_is_built_once_however_often_it_is_asked_about(monkeypatch) -> None:
    built: list[str] = []

    def make(task_id: str) -> gymnasium.Env:
        built.append(task_id)
        return gymnasium.make(task_id)

    monkeypatch.setattr("ede.tasks.make", make)
    unusable.cache_clear()
    reasons = {unusable("ede-test/Camera-v0") for _ in range(3)}
    assert len(reasons) == 1 and None not in reasons
    assert built == ["ede-test/Camera-v0"]
