"""Fixtures of the end-to-end tests: scratch copies of the repository and the params they run."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from ede_pipeline.checkout import scratch_copy


def _tiny_pipeline(params: dict[str, Any]) -> None:
    params["collect"].update(steps=200, num_envs=1)
    small = {"hidden": [16, 16], "epochs": 1, "batch_size": 64}
    params["embedding"].update(small, holdout=0.5)
    params["decoder"].update(small)
    params["td3"].update(hidden=[16, 16], batch_size=32, start_steps=50, eval_every=100,
                         eval_episodes=1, checkpoint_every=1000, buffer_size=1000)
    params["runs"].update(seeds=[0], budgets={task: 200 for task in params["runs"]["budgets"]})
    params["report"].update(bootstrap_samples=100)


@pytest.fixture(scope="session")
def tiny_pipeline() -> Callable[[dict[str, Any]], None]:
    """Shrinks params (plain data, in place) to every stage at the smallest size that still
    exercises it."""
    return _tiny_pipeline


@pytest.fixture
def repo_copy(tmp_path: Path) -> Path:
    """The repository's files in a fresh git repository, collecting 200 steps with one env."""
    return scratch_copy(tmp_path / "repo",
                        lambda params: params["collect"].update(steps=200, num_envs=1))
