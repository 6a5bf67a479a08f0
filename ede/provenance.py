"""What made an output: the versions of the software that decides a stage's results."""

from __future__ import annotations

import platform
from importlib.metadata import PackageNotFoundError, version

__all__ = ["SOFTWARE", "describe_software", "software_versions"]

# Python, the array and learning libraries, and the simulator. Each is pinned by
# requirements.lock; recording them beside every output says which pins made it.
SOFTWARE = ("python", "numpy", "torch", "mujoco", "gymnasium")


def software_versions() -> dict[str, str]:
    """``{"python": "3.11.7", "numpy": …, "torch": …, "mujoco": …, "gymnasium": …}``."""
    versions = {"python": platform.python_version()}
    for name in SOFTWARE[1:]:
        try:
            versions[name] = version(name)
        except PackageNotFoundError:
            versions[name] = "not installed"
    return versions


def describe_software(versions: dict[str, str] | None) -> str:
    """One line for people: ``Python 3.11.7, numpy 2.4.6, …``; ``unrecorded`` for ``None``."""
    if not versions:
        return "unrecorded"
    return ", ".join(f"{'Python' if name == 'python' else name} {value}"
                     for name, value in versions.items())
