"""What code of ours a stage or a task runs, found from the source: the static import closure.

A stage's DVC dependencies must cover every file of ours it executes (``tests/test_stage_deps.py``
checks ``dvc.yaml`` against :func:`closure`), and a task's code fingerprint
(:func:`task_code`, the ``task_code`` stage) names exactly the files that define one environment,
so that editing one task's module reruns that task's runs and nothing else.

Imports are read with :mod:`ast`, not executed: every ``import`` and ``from … import`` of our three
packages, at module level or inside functions, transitively. Files are named relative to their
package's parent (``ede_envs/reacher_push.py``), so that a fingerprint is the same for an editable
install, an installed wheel and a container.
"""

from __future__ import annotations

import ast
import importlib.util
import re
from pathlib import Path
from typing import Any

from ede.io.atomic import sha256

__all__ = ["OURS", "closure", "package_dirs", "relative_name", "task_code", "task_record"]

OURS = ("ede", "ede_envs", "ede_pipeline")


def package_dirs() -> dict[str, Path]:
    """Where each of our packages' source lives (``envs/`` for ``ede_envs`` in a checkout)."""
    dirs = {}
    for name in OURS:
        spec = importlib.util.find_spec(name)
        assert spec is not None and spec.submodule_search_locations, name
        dirs[name] = Path(next(iter(spec.submodule_search_locations))).resolve()
    return dirs


def module_file(name: str, dirs: dict[str, Path]) -> Path | None:
    """The source file of module ``name`` if it is one of ours, else None."""
    package, _, rest = name.partition(".")
    if package not in dirs:
        return None
    base = dirs[package].joinpath(*rest.split(".")) if rest else dirs[package]
    if base.is_dir():
        return base / "__init__.py"
    return base.with_suffix(".py") if base.with_suffix(".py").is_file() else None


def imports_of(path: Path, name: str) -> set[str]:
    """Every module name that ``path`` (module ``name``) imports, relative imports resolved."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            module = (
                node.module
                if node.level == 0
                else name.rsplit(".", node.level)[0] + "." + node.module
            )
            found.add(module)
            found |= {
                f"{module}.{alias.name}" for alias in node.names
            }  # submodules imported by name
    return found


def closure(roots: list[str], dirs: dict[str, Path] | None = None) -> set[Path]:
    """The source files of ``roots`` and of every module of ours they import, transitively."""
    dirs = package_dirs() if dirs is None else dirs
    seen: set[str] = set()
    files: set[Path] = set()
    todo = list(roots)
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        path = module_file(name, dirs)
        if path is None:
            continue
        files.add(path)
        todo += [m for m in imports_of(path, name) if m.partition(".")[0] in dirs]
    return files


def relative_name(path: Path, dirs: dict[str, Path]) -> str:
    """``path`` named from its package: ``ede_envs/assets/reacher_arm.xml``."""
    for package, root in dirs.items():
        if path.is_relative_to(root):
            return f"{package}/{path.relative_to(root).as_posix()}"
    raise ValueError(f"{path} is in none of our packages")


_INCLUDE = re.compile(r"<include\s+file\s*=\s*[\"']([^\"']+)[\"']")


def _model_files(path: Path) -> list[Path]:
    """An MJCF file and the files it includes, transitively (paths relative to the includer)."""
    files, todo = [], [path.resolve()]
    while todo:
        current = todo.pop()
        if current in files:
            continue
        files.append(current)
        todo += [
            (current.parent / name).resolve() for name in _INCLUDE.findall(current.read_text())
        ]
    return files


def task_code(task_id: str) -> dict[str, Any]:
    """What defines task ``task_id``: its registration and the SHA-256 of every file it runs.

    The registration (entry point, episode length, keyword arguments) comes from gymnasium's
    registry, and the model file from the environment itself (``MujocoEnv.fullpath``, if it has
    one); :func:`task_record` does the rest. The simulator's versions are pinned by
    ``simulator.lock``, which the stages that step a task depend on as well.
    """
    from ede.tasks import make

    env = make(task_id)
    try:
        spec = env.spec
        assert spec is not None
        entry_point = (
            spec.entry_point if isinstance(spec.entry_point, str) else repr(spec.entry_point)
        )
        fullpath = getattr(env.unwrapped, "fullpath", None)
    finally:
        env.close()
    return task_record(
        task_id,
        entry_point,
        spec.max_episode_steps,
        spec.kwargs,
        Path(fullpath) if fullpath else None,
        package_dirs(),
    )


def task_record(
    task_id: str,
    entry_point: str,
    max_episode_steps: int | None,
    kwargs: dict[str, Any],
    model: Path | None,
    dirs: dict[str, Path],
) -> dict[str, Any]:
    """A task's record: its registration, and the SHA-256 of the Python files of ours that its
    entry point's module imports (transitively) and of its model file with the files that
    includes. A file outside our packages (gymnasium's own Pusher model, say) is named from its
    package. Nothing else of ``envs/`` is recorded: editing one task's module changes that
    task's record and no other's.
    """
    module = entry_point.partition(":")[0]
    files = {relative_name(p, dirs): sha256(p) for p in closure([module], dirs)}
    for path in _model_files(model) if model else []:
        try:
            name = relative_name(path, dirs)
        except ValueError:
            name = _outside_name(path)
        files[name] = sha256(path)
    return {
        "task": task_id,
        "entry_point": entry_point,
        "max_episode_steps": max_episode_steps,
        "kwargs": {k: repr(v) for k, v in sorted(kwargs.items())},
        "files": dict(sorted(files.items())),
    }


def _outside_name(path: Path) -> str:
    """A file of another installed package, named from that package (``gymnasium/…``)."""
    for parent in path.parents:
        if (parent / "__init__.py").is_file() and not (parent.parent / "__init__.py").is_file():
            return f"{parent.name}/{path.relative_to(parent).as_posix()}"
    return path.name
