"""Fixtures shared by every test package."""

from __future__ import annotations

import copy
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]

# Render headless (Mesa's EGL needs no GPU or display); `MUJOCO_GL=osmesa pytest` overrides.
os.environ.setdefault("MUJOCO_GL", "egl")


@pytest.fixture(scope="session")
def committed_params() -> dict[str, Any]:
    """The committed ``params.yaml`` as plain data."""
    return yaml.safe_load((REPO / "params.yaml").read_text())


@pytest.fixture
def write_params(
    tmp_path: Path, committed_params: dict[str, Any]
) -> Callable[..., Path]:
    """Write the committed params with changes applied; returns the file's path.

    ``write_params(edit)`` calls ``edit(data)`` on a deep copy of the committed params.
    """

    def write(edit: Callable[[dict[str, Any]], None] | None = None, name: str = "params.yaml") -> Path:
        data = copy.deepcopy(committed_params)
        if edit is not None:
            edit(data)
        path = tmp_path / name
        path.write_text(yaml.safe_dump(data, sort_keys=False))
        return path

    return write
