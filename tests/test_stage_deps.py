"""Each DVC stage depends on all of our code it runs: its import closure, found statically.

A stage runs ``ede-pipeline <command>``: the stage's own module of ``pipeline/`` and everything of
ours it imports, transitively (imports inside functions too). The CLI's dispatcher imports every
stage module but runs only one, so it contributes only its own imports of ``ede``. Importing
``ede_envs`` at all counts as all of ``envs/``: gymnasium loads the task classes from entry-point
strings, which no import statement names.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
import yaml

from tests.conftest import REPO

PACKAGES = {"ede": REPO / "ede", "ede_envs": REPO / "envs", "ede_pipeline": REPO / "pipeline"}
STAGE_MODULES = {
    "collect": "ede_pipeline.collect",
    "pretrain_encoder": "ede_pipeline.pretrain",
    "pretrain_decoder": "ede_pipeline.pretrain",
    "train_reacher": "ede_pipeline.train",
    "train_sevendof": "ede_pipeline.train",
    "report": "ede_pipeline.report",
}


def module_file(name: str) -> Path | None:
    package, _, rest = name.partition(".")
    if package not in PACKAGES:
        return None
    base = PACKAGES[package].joinpath(*rest.split(".")) if rest else PACKAGES[package]
    if base.is_dir():
        return base / "__init__.py"
    return base.with_suffix(".py") if base.with_suffix(".py").is_file() else None


def imports_of(path: Path, name: str) -> set[str]:
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            module = node.module if node.level == 0 else name.rsplit(".", node.level)[0] + "." + node.module
            found.add(module)
            found |= {f"{module}.{alias.name}" for alias in node.names}  # submodules imported by name
    return found


def closure(roots: list[str]) -> set[Path]:
    seen: set[str] = set()
    files: set[Path] = set()
    todo = list(roots)
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        path = module_file(name)
        if path is None:
            continue
        files.add(path)
        todo += [m for m in imports_of(path, name) if m.partition(".")[0] in PACKAGES]
    if any(path.is_relative_to(PACKAGES["ede_envs"]) for path in files):
        files |= {p for p in PACKAGES["ede_envs"].rglob("*") if p.is_file() and "__pycache__" not in p.parts}
    return files


def dispatcher_imports() -> list[str]:
    cli = REPO / "pipeline" / "cli.py"
    return [m for m in imports_of(cli, "ede_pipeline.cli") if m.partition(".")[0] == "ede"]


@pytest.mark.parametrize("stage", list(STAGE_MODULES))
def test_a_stages_deps_cover_the_code_it_runs(stage: str) -> None:
    definition = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"][stage]
    deps = [REPO / d for d in definition.get("do", definition)["deps"]]
    needed = closure([STAGE_MODULES[stage], *dispatcher_imports()]) | {REPO / "pipeline/cli.py"}
    missing = sorted(str(p.relative_to(REPO)) for p in needed
                     if not any(p == d or p.is_relative_to(d) for d in deps))
    assert not missing, f"dvc.yaml: stage {stage} runs {', '.join(missing)} but does not depend on it"


def test_the_closure_follows_imports_inside_functions_and_entry_points() -> None:
    files = closure(["ede_pipeline.train"])
    assert REPO / "ede/td3.py" in files and REPO / "ede/nets.py" in files
    assert REPO / "envs/reacher_push.py" in files  # via ede.tasks -> ede_envs
    assert REPO / "pipeline/sweep.py" not in files
