"""Fixtures of the end-to-end tests: scratch copies of the repository and the params they run."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.support import scratch_copy


@pytest.fixture
def repo_copy(tmp_path: Path) -> Path:
    """The repository's files in a fresh git repository, collecting 200 steps with one env."""
    return scratch_copy(
        tmp_path / "repo", lambda params: params["collect"].update(steps=200, num_envs=1)
    )
