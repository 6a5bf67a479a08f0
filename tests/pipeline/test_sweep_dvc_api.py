"""The DVC internals that ``ede-pipeline sweep`` drives, checked by name, signature and behaviour.

``pipeline/sweep/`` does the steps of ``dvc repro`` itself, through DVC's Python API, two of them
with no public form (the repository's lock, the run cache), which any DVC release may move. So
``pyproject.toml`` bounds dvc below the next minor release, and this file is what moving that bound
takes: install the new DVC, run it, and each failure names the internal that moved — here, in
seconds, rather than in a sweep hours in.

The behaviour is checked on a toy repository: two train stages of one line of Python each and an
upstream stage, with the project's params (the sweep validates them), and DVC's own ``dvc repro``
in a twin of it as the reference.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml
from click.testing import CliRunner, Result

from ede_pipeline.cli import main
from tests.support import REPO, dvc

# Everything of DVC's that pipeline/sweep/ imports or calls ("module:attribute"), with the
# parameters it passes by name (None: not called, or called with no arguments).
INTERNALS: dict[str, list[str] | None] = {
    "dvc.repo:Repo": ["root_dir"],
    "dvc.repo:Repo.__enter__": None,
    "dvc.repo:lock_repo": ["repo"],
    "dvc.repo.stage:StageLoad.collect": ["target", "glob"],
    "dvc.repo.index:Index.graph": None,
    "dvc.stage:Stage": None,
    "dvc.stage:Stage.changed": None,
    "dvc.stage:Stage.remove_outs": ["ignore_remove", "force"],
    "dvc.stage:Stage.save_deps": None,
    "dvc.repo:Repo.commit": ["target", "force"],
    "dvc.stage.cache:StageCache.restore": ["stage"],
    "dvc.stage.cache:RunCacheNotFoundError": None,
    "dvc.env:DVC_ROOT": None,
    "dvc.env:DVC_STAGE": None,
    "dvc.lock:LockError": None,
    "dvc.exceptions:DvcException": None,
    "dvc.exceptions:NotDvcRepoError": None,
    "dvc.utils.serialize:EncodingError": None,
    "dvc.utils.strictyaml:YAMLSyntaxError": None,
    "dvc.utils.strictyaml:YAMLValidationError": None,
}


def _dvc_version() -> str:
    from importlib.metadata import version

    return version("dvc")


def _resolve(name: str) -> Any:
    module_name, _, attributes = name.partition(":")
    found: Any = importlib.import_module(module_name)
    for attribute in attributes.split("."):
        if inspect.isclass(found):  # the attribute as defined: a property, not what it computes
            found = inspect.getattr_static(found, attribute)
        else:
            found = getattr(found, attribute)
    return found


def test_every_dvc_import_of_the_sweep_is_checked_here() -> None:
    imported = {
        f"{node.module}:{alias.name}"
        for module in sorted((REPO / "pipeline/sweep").glob("*.py"))
        for node in ast.walk(ast.parse(module.read_text()))
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("dvc")
        for alias in node.names
    }
    assert imported, "no import of DVC found: the search looks in the wrong place"
    missing = sorted(imported - INTERNALS.keys())
    assert not missing, f"pipeline/sweep/ imports {missing}: add them to INTERNALS"


@pytest.mark.parametrize("name", list(INTERNALS))
def test_the_internals_the_sweep_calls_are_there_with_the_arguments_it_passes(name: str) -> None:
    try:
        found = _resolve(name)
    except (ImportError, AttributeError) as error:
        pytest.fail(
            f"pipeline/sweep/ uses {name}, which DVC {_dvc_version()} does not have "
            f"({error}); see the docstring of this file"
        )
    passed = INTERNALS[name]
    if not passed:
        return
    function = found.__init__ if inspect.isclass(found) else found
    parameters = inspect.signature(function).parameters
    absent = [p for p in passed if p not in parameters]
    assert not absent, (
        f"pipeline/sweep/ passes {', '.join(absent)} to {name}, whose signature "
        f"in DVC {_dvc_version()} is {inspect.signature(function)}"
    )


# ---------------------------------------------------------------------------------------------
# Behaviour, on a toy repository.

STEP = """\
import json, os, sys
from pathlib import Path

import yaml

params = yaml.safe_load(Path("params.yaml").read_text())
if sys.argv[1] == "prepare":
    if Path("refuse").exists():  # a test's way to make this stage fail
        sys.exit("prepare: refused")
    Path("data").mkdir(exist_ok=True)
    Path("data/prepared.txt").write_text(f"seed {params['collect']['seed']}")
elif sys.argv[1] == "train":
    run = Path("data/runs") / sys.argv[2]
    (run / "policy").mkdir(parents=True, exist_ok=True)
    tau = params["td3"]["tau"]
    prepared = Path("data/prepared.txt").read_text()
    (run / "policy/weights.txt").write_text(f"tau {tau}, run {sys.argv[2]}, {prepared}")
    (run / "metrics.json").write_text(json.dumps({"final_return": tau * int(sys.argv[2])}))
    (run / "eval.csv").write_text(f"step,mean_return\\n0,{tau}\\n")
else:  # the command's second line: run in the repository's root, with DVC's variables set
    expected = {"DVC_STAGE": f"train_toy@{sys.argv[2]}", "DVC_ROOT": os.getcwd()}
    found = {name: os.environ.get(name) for name in expected}
    sys.exit(0 if found == expected else f"expected {expected}, found {found}")
"""


def _pipeline() -> dict[str, Any]:
    """Stages shaped like the project's: an upstream stage, and train stages from a matrix."""
    python = f"{sys.executable} step.py"
    return {
        "stages": {
            "prepare": {
                "cmd": f"{python} prepare",
                "deps": ["step.py"],
                "params": ["collect.seed"],
                "outs": ["data/prepared.txt"],
            },
            "train_toy": {
                "matrix": {"seed": "${runs.seeds}"},
                "cmd": [f"{python} train ${{item.seed}}", f"{python} check ${{item.seed}}"],
                "deps": ["step.py", "data/prepared.txt"],
                "params": ["td3.tau"],
                "outs": ["data/runs/${item.seed}/policy", "data/runs/${item.seed}/metrics.json"],
                "plots": [{"data/runs/${item.seed}/eval.csv": {"x": "step", "y": "mean_return"}}],
            },
        }
    }


def _toy(path: Path, params: dict[str, Any]) -> Path:
    path.mkdir()
    (path / "step.py").write_text(STEP)
    (path / "dvc.yaml").write_text(yaml.safe_dump(_pipeline(), sort_keys=False))
    (path / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    subprocess.run(["git", "init", "-q"], cwd=path, check=True)
    assert dvc(path, "init", "-q").returncode == 0
    return path


def _set_tau(path: Path, tau: float) -> None:
    params = yaml.safe_load((path / "params.yaml").read_text())
    params["td3"]["tau"] = tau
    (path / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))


def _lock(path: Path) -> dict[str, Any]:
    return yaml.safe_load((path / "dvc.lock").read_text())["stages"]


def _outputs(path: Path) -> dict[str, str]:
    return {
        str(file.relative_to(path)): file.read_text()
        for file in sorted((path / "data").rglob("*"))
        if file.is_file()
    }


def _sweep(path: Path, monkeypatch: pytest.MonkeyPatch) -> Result:
    monkeypatch.chdir(path)
    return CliRunner().invoke(main, ["sweep", "--jobs", "2"])


@pytest.fixture
def toy_params(committed_params: dict[str, Any]) -> dict[str, Any]:
    """The project's params with two seeds: two train stages."""
    return {**committed_params, "runs": {**committed_params["runs"], "seeds": [0, 1]}}


@pytest.mark.slow
def test_a_sweep_records_what_dvc_repro_records_and_restores_runs_from_the_run_cache(
    tmp_path: Path, toy_params: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    reference = _toy(tmp_path / "reference", toy_params)
    result = dvc(reference, "repro")
    assert result.returncode == 0, result.stdout + result.stderr
    swept = _toy(tmp_path / "swept", toy_params)
    first = _sweep(swept, monkeypatch)
    assert first.exit_code == 0, first.output
    # Every stage, the upstream one in a wave before both train stages.
    assert "3 of 3 stages out of date" in first.stderr and first.stdout.count(" ok ") == 3
    assert first.stdout.splitlines()[0].split()[2] == "prepare", first.stdout
    assert _lock(swept) == _lock(reference)
    assert _outputs(swept) == _outputs(reference)
    assert "0 of 3 stages out of date" in _sweep(swept, monkeypatch).stderr

    # A changed param: only the stages that track it; a changed-back param: the run cache.
    tau = toy_params["td3"]["tau"]
    _set_tau(swept, 2 * tau)
    changed = _sweep(swept, monkeypatch)
    assert "2 of 3 stages out of date" in changed.stderr, changed.output
    assert changed.stdout.count(" ok ") == 2 and "prepare" not in changed.stdout, changed.output
    assert _lock(swept) != _lock(reference)
    _set_tau(swept, tau)
    back = _sweep(swept, monkeypatch)
    assert back.stdout.count("restored from the run cache") == 2, back.output
    assert _lock(swept) == _lock(reference) and _outputs(swept) == _outputs(reference)
    # A lost output: that stage alone is out of date, and comes back from the cache.
    shutil.rmtree(swept / "data/runs/1")
    lost = _sweep(swept, monkeypatch)
    assert "1 of 3 stages out of date" in lost.stderr and "cached" in lost.stdout, lost.output
    assert _outputs(swept) == _outputs(reference)
    status = dvc(swept, "status")
    assert "up to date" in status.stdout, status.stdout + status.stderr


@pytest.mark.slow
def test_a_stage_waits_for_what_it_depends_on_and_is_not_run_when_that_fails(
    tmp_path: Path, toy_params: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    swept = _toy(tmp_path / "toy", toy_params)
    assert _sweep(swept, monkeypatch).exit_code == 0
    recorded = _lock(swept)
    # The upstream stage out of date: the runs downstream would run after it, and are asked again
    # then; made again as it was, they are up to date, as `dvc repro` finds them.
    (swept / "data/prepared.txt").unlink()
    again = _sweep(swept, monkeypatch)
    assert again.exit_code == 0, again.output
    assert "3 of 3 stages out of date" in again.stderr, again.output
    assert again.stdout.count("up to date: its inputs came out as before") == 2, again.output
    assert _lock(swept) == recorded
    # The upstream stage fails (its param changed, so no earlier run of it is cached): the runs
    # downstream are not run, and say why; nothing is recorded.
    params = yaml.safe_load((swept / "params.yaml").read_text())
    params["collect"]["seed"] += 1
    (swept / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    (swept / "refuse").touch()
    failed = _sweep(swept, monkeypatch)
    assert failed.exit_code == 1, failed.output
    assert failed.stdout.count("not run: prepare failed") == 2, failed.output
    assert "sweep: 0 recorded, 3 failed" in failed.stderr, failed.output
    assert _lock(swept) == recorded
    # Mended, the next sweep runs them all.
    (swept / "refuse").unlink()
    mended = _sweep(swept, monkeypatch)
    assert mended.exit_code == 0 and mended.stdout.count(" ok ") == 3, mended.output


@pytest.mark.slow
def test_a_sweep_does_not_start_while_dvc_holds_the_repository_lock(
    tmp_path: Path, toy_params: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    from dvc.repo import Repo, lock_repo

    swept = _toy(tmp_path / "toy", toy_params)
    with Repo(str(swept)) as repo, lock_repo(repo):
        blocked = _sweep(swept, monkeypatch)
    assert blocked.exit_code == 2, blocked.output
    assert "another sweep is running here" in blocked.stderr, blocked.stderr
    assert not (swept / "data").exists()


# A damaged file of the pipeline, its content (None: a folder in its place), and the start of the
# line that refuses it. The line names the file and how to mend it; the checkout's files are the
# user's, so nothing is repaired here (an experiment's working copy is: test_experiment_run.py).
DAMAGED = {
    "an entry of dvc.lock replaced": (
        "dvc.lock",
        "schema: '2.0'\nstages:\n  prepare: 5\n",
        "dvc.lock: not what DVC expects: stages.prepare: expected a dictionary; remove it: ",
    ),
    "dvc.lock not YAML": ("dvc.lock", "stages: {\n", "dvc.lock: not YAML (line 2: "),
    "dvc.lock empty": ("dvc.lock", "", "dvc.lock: empty; remove it: "),
    "dvc.lock a folder": ("dvc.lock", None, "dvc.lock: not a file; remove it: "),
    "dvc.yaml not YAML": ("dvc.yaml", "stages: {{{\n", "dvc.yaml: not YAML (line 2: "),
    "dvc.yaml of a wrong type": (
        "dvc.yaml",
        "stages:\n  prepare:\n    cmd: 5\n",
        "dvc.yaml: not what DVC expects: stages.prepare.cmd: expected str; mend it (",
    ),
    "dvc.yaml empty": ("dvc.yaml", "", "dvc.yaml: no stages; mend it ("),
    "dvc.yaml a folder": ("dvc.yaml", None, "dvc.yaml: not a file; mend it ("),
    "dvc.yaml not UTF-8": ("dvc.yaml", "stages:\n  caf\xe9:\n", "dvc.yaml: not UTF-8 text; "),
}


@pytest.mark.parametrize("damage", list(DAMAGED))
def test_a_damaged_dvc_yaml_or_dvc_lock_is_one_line_and_runs_nothing(
    tmp_path: Path, toy_params: dict[str, Any], monkeypatch: pytest.MonkeyPatch, damage: str
) -> None:
    name, content, line = DAMAGED[damage]
    toy = _toy(tmp_path / "toy", toy_params)
    damaged = toy / name
    damaged.unlink(missing_ok=True)
    if content is None:
        damaged.mkdir()
    else:
        damaged.write_bytes(content.encode("latin-1"))
    refused = _sweep(toy, monkeypatch)
    assert refused.exit_code == 2, refused.output
    assert refused.stderr.startswith(f"Error: {line}"), refused.stderr
    assert len(refused.stderr.splitlines()) == 1, refused.stderr
    assert not (toy / "data").exists()
    assert content is None or damaged.read_bytes() == content.encode("latin-1")  # left as it is
