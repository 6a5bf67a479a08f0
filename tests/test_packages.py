"""pyproject.toml names every package of the tree: a folder of code it leaves out installs
without it (the image's ``pip install .``), though an editable install finds it all the same."""

from __future__ import annotations

import tomllib

from tests.support import REPO


def test_every_package_folder_is_named_in_pyproject() -> None:
    setuptools = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    found = set()
    for name, folder in setuptools["package-dir"].items():
        for init in (REPO / folder).rglob("__init__.py"):
            parts = init.parent.relative_to(REPO / folder).parts
            found.add(".".join((name, *parts)))
    assert "ede_pipeline.sweep" in found  # the search finds subpackages
    assert set(setuptools["packages"]) == found
