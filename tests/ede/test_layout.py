"""``ede/`` is in folders by role, and its imports run one way (docs/pipeline.md, "The code").

errors/tasks → config → io → method → run → analysis, and the pipeline above them all: a module
imports only from its own layer or the layers before it (``ede/__init__.py``, the package's face,
comes after them all: it hands out ``ede.EmbeddedActions`` of ``ede.run`` on first use), and no
module reaches itself again through its imports — read from the source
(``ede_pipeline.closure.imports_of``), so imports under ``TYPE_CHECKING`` and inside functions
count as much as the others.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from ede_pipeline.closure import imports_of, module_file, package_dirs

DIRS = package_dirs()
EDE = DIRS["ede"]
# Each layer: the modules and folders of ede/ it holds; a module may import from its own layer
# and the ones before it.
LAYERS = [
    ("errors and tasks", {"ede.errors", "ede.tasks"}),
    ("config", {"ede.config"}),
    ("io", {"ede.io"}),
    ("method", {"ede.method"}),
    ("run", {"ede.run"}),
    ("analysis", {"ede.analysis"}),
    ("the package's face", {"ede"}),
]


def module_name(path: Path) -> str:
    parts = path.relative_to(EDE).with_suffix("").parts
    return ".".join(["ede", *parts[: -1 if parts[-1] == "__init__" else None]])


MODULES = {module_name(path): path for path in sorted(EDE.rglob("*.py"))}


def layer(module: str) -> int:
    """The index in :data:`LAYERS` of ``module``, by its own name or its folder's."""
    for index, (_, members) in enumerate(LAYERS):
        if any(module == m or (m != "ede" and module.startswith(m + ".")) for m in members):
            return index
    raise AssertionError(f"{module}: in no layer of tests/ede/test_layout.py (place it there)")


def ours(module: str, path: Path) -> set[str]:
    """The modules of ede/ that ``module`` imports (its package's ``__init__`` aside)."""
    found = {m for m in imports_of(path, module) if m.partition(".")[0] == "ede"}
    return {m for m in found if m != "ede" and module_file(m, DIRS) is not None} - {module}


GRAPH = {module: ours(module, path) for module, path in MODULES.items()}


def test_every_module_has_a_layer() -> None:
    assert {"ede.method.td3", "ede.run.training", "ede.analysis.results"} <= MODULES.keys()
    for module in MODULES:
        layer(module)


@pytest.mark.parametrize("module", sorted(MODULES))
def test_a_module_imports_only_its_own_layer_and_the_ones_before(module: str) -> None:
    above = sorted(m for m in GRAPH[module] if layer(m) > layer(module))
    assert not above, (
        f"{module} ({LAYERS[layer(module)][0]}) imports {', '.join(above)}, a later layer: "
        "the imports of ede/ run errors/tasks → config → io → method → run → analysis"
    )


def test_ede_imports_nothing_of_the_pipeline() -> None:
    for module, path in MODULES.items():
        assert not any(m.startswith("ede_pipeline") for m in imports_of(path, module)), module


def cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as the modules along it, or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(node: str, path: list[str]) -> list[str] | None:
        state[node] = 1
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return [*path[path.index(nxt) :], nxt]
            if nxt not in state and (found := visit(nxt, [*path, nxt])):
                return found
        state[node] = 2
        return None

    for start in sorted(graph):
        if start not in state and (found := visit(start, [start])):
            return found
    return None


def test_no_module_reaches_itself_through_its_imports() -> None:
    found = cycle(GRAPH)
    assert found is None, f"an import cycle in ede/: {' → '.join(found or [])}"


def test_the_cycle_check_finds_a_cycle() -> None:
    assert cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert cycle({"a": {"b"}, "b": set()}) is None


def test_a_folders_init_is_its_docstring_alone() -> None:
    """Importing ede.run.training runs ede/run/__init__.py, which no stage's deps name
    (``ede_pipeline.closure`` follows what is imported): it must compute nothing."""
    for path in EDE.glob("*/__init__.py"):
        if path.parent.name == "config":  # the package's names, re-exported (its deps name it)
            continue
        body = path.read_text().strip()
        assert body.startswith('"""') and body.endswith('"""') and body.count('"""') == 2, path


def test_the_results_model_loads_no_torch_nor_the_simulator() -> None:
    heavy = ("torch", "gymnasium", "mujoco", "ede.analysis.probes")
    code = (
        "import sys, ede.analysis.results, ede.analysis.stats; "
        f"print(' '.join(m for m in {heavy!r} if m in sys.modules))"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    assert done.stdout.strip() == ""
