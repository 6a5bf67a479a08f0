"""``ede-pipeline experiment``: the committed experiments, run by the sweep and recorded by DVC.

An experiment is a committed file, ``experiments/NAME.yaml``: the params sections with only the
keys it changes against ``params.yaml`` (as ``params-quick.yaml``), each key replacing its value
whole. ``experiment run NAME`` runs it in a working copy of its own,
``.dvc/tmp/experiments/NAME/`` (a git worktree sharing this checkout's DVC cache): this
checkout's files (the code that runs, committed or not), the experiment's params, and its
outputs, so that experiments neither touch this workspace nor each other, and a killed one
resumes there. Running it again brings the copy's code up to this checkout's, but not over
finished runs made with other code (DVC would run them again): that is refused unless
``--keep-code`` (finish with the copy's code and the params.yaml of its commit) or ``--update-code`` (run them again) says which.
Families that none of its tasks uses and no figure draws are left out, so it learns only the
embeddings it needs; an embedding another experiment already made with the same code and
params comes from DVC's run cache instead of being made again. The train stages run through
``ede-pipeline sweep`` (side by side, ``--jobs``, Ray when asked, each run resuming from its
checkpoint), the rest (the report) through ``dvc repro``, and ``dvc exp save`` records it as the
DVC experiment NAME: ``dvc exp show`` lists it with its metrics, ``dvc exp apply NAME`` brings it
into the workspace, ``dvc exp push`` shares it.

``experiment export NAME`` copies its finished runs' files into the published layout
(``docs/results/runs/<task>/<algo>/seed<N>/``, with a ``source.json`` per task naming the
experiment file and the commit, and the held-out metrics of the embedding its EDE-TD3 runs used;
an experiment adding seeds to a published task adds its part to that task's ``source.json``), from which ``ede-pipeline results`` draws the results page.

``experiment show`` prints DVC's experiments readably: ``dvc exp show`` puts every param, metric
and dependency hash of an experiment on one line, far wider than a terminal; this prints, per
experiment, a block — its name and commit, the params it changed against the commit it started
from, and per task the report's headline numbers for each algorithm (mean final return and area
under the curve, and the seeds that ran). It reads ``dvc exp show --json``, so it shows exactly
what DVC holds.
"""

from __future__ import annotations

import itertools
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
from collections.abc import Iterable
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import click
import yaml

from ede.atomic import write_json, write_text
from ede.config import (
    ALGO_LABELS,
    Params,
    ParamsError,
    overridden,
    parse_yaml,
    read_yaml,
    validate_params,
)
from ede.errors import first_line
from ede.locks import OutputBusy, exclusive
from ede.runs import PUBLISHED
from ede_pipeline import layout
from ede_pipeline.common import DEFAULT_PARAMS, PARENT_ENV, BadInput, Failed, read_params

__all__ = ["experiment", "experiment_blocks", "experiment_params", "prepare_workspace"]

WIDTH = 80
PARAMS_FILE = "params.yaml"


def _flatten(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Dotted keys to leaves; lists are leaves."""
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        if isinstance(value, dict) and value:
            flat.update(_flatten(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def _params(entry: dict[str, Any]) -> dict[str, Any]:
    files = (entry.get("data") or {}).get("params") or {}
    return _flatten((files.get(PARAMS_FILE) or {}).get("data") or {})


def _headline(entry: dict[str, Any]) -> dict[str, dict[str, dict[str, Any]]]:
    """{task: {algo: {"final_return", "auc", "seeds"}}} from the report's metrics, if it ran."""
    files = (entry.get("data") or {}).get("metrics") or {}
    report = (files.get(layout.REPORT_METRICS.as_posix()) or {}).get("data") or {}
    return {
        task: per_algo
        for task, per_algo in report.items()
        if isinstance(per_algo, dict) and any(a in per_algo for a in ALGO_LABELS)
    }


def _number(value: Any, digits: int = 2) -> str:
    return f"{value:.{digits}f}" if isinstance(value, (int, float)) else "–"


def _changes(params: dict[str, Any], baseline: dict[str, Any]) -> list[str]:
    def shown(value: Any) -> str:  # as params.yaml spells it: null, true, false
        return (
            yaml.safe_dump(value, default_flow_style=True, width=1_000_000)
            .strip()
            .removesuffix("\n...")
        )

    return [
        f"{key}: {shown(baseline.get(key))} → {shown(value)}"
        for key, value in params.items()
        if value != baseline.get(key)
    ]


def _block(entry: dict[str, Any], base: str, baseline: dict[str, Any]) -> list[str]:
    rev = str(entry.get("rev"))[:7]
    lines = [f"{entry.get('name') or rev}  ({rev}, from {base})"]
    changed = _changes(_params(entry), baseline)
    lines += textwrap.wrap(
        f"changed: {'; '.join(changed) if changed else 'none'}",
        WIDTH,
        initial_indent="  ",
        subsequent_indent="    ",
        break_on_hyphens=False,
    )
    tasks = _headline(entry)
    if not tasks:
        lines.append("  no report yet" if entry.get("error") is None else "  failed")
        return lines
    algos = [a for a in ALGO_LABELS if any(a in per_algo for per_algo in tasks.values())]
    header = "".join(f"{ALGO_LABELS[a] + ' final':>15s}{'AUC':>8s}" for a in algos)
    lines.append(f"  {'task':24s}{header}{'seeds':>7s}")
    for task, per_algo in tasks.items():
        cells = "".join(
            f"{_number(per_algo.get(a, {}).get('final_return')):>15s}"
            f"{_number(per_algo.get(a, {}).get('auc')):>8s}"
            for a in algos
        )
        seeds = "/".join(_number(per_algo.get(a, {}).get("seeds"), 0) for a in algos)
        lines.append(f"  {task[-24:]:24s}{cells}{seeds:>7s}")
    lines += _across_tasks(entry)
    return lines


def _across_tasks(entry: dict[str, Any]) -> list[str]:
    """One line: P(EDE-TD3 > TD3) across tasks, over final returns and areas, with intervals."""
    files = (entry.get("data") or {}).get("metrics") or {}
    report = (files.get(layout.REPORT_METRICS.as_posix()) or {}).get("data") or {}
    across = report.get("across_tasks")
    if not isinstance(across, dict):
        return []
    cells = []
    for score, label in (("final_return", "final"), ("auc", "AUC")):
        p = (across.get(score) or {}).get("probability_of_improvement") or {}
        cells.append(
            f"{label} {_number(p.get('value'))} [{_number(p.get('low'))}, {_number(p.get('high'))}]"
        )
    count = _number(across.get("task_count"), 0)
    return [f"  P(EDE-TD3 > TD3), {count} task{'s' * (count != '1')}: {'; '.join(cells)}"]


def experiment_blocks(commits: Iterable[dict[str, Any]]) -> list[str]:
    """The printed lines for ``dvc exp show --json``: one block per experiment.

    An experiment's changes are against the commit it started from; the workspace is skipped.
    """
    lines: list[str] = []
    for commit in commits:
        if commit.get("rev") == "workspace":
            continue
        base, baseline = commit.get("name") or str(commit.get("rev"))[:7], _params(commit)
        for experiment in commit.get("experiments") or []:
            for entry in experiment.get("revs") or []:
                if lines:
                    lines.append("")
                lines += _block(entry, base, baseline)
    return lines


# Running and exporting ------------------------------------------------------------------------

EXPERIMENTS = Path("experiments")  # the committed experiment files
WORKSPACES = Path(".dvc") / "tmp" / "experiments"  # each one's working copy (git-ignored by DVC)


def experiment_file(name: str) -> Path:
    """``experiments/NAME.yaml``; one line naming the experiments there when it is not one."""
    path = EXPERIMENTS / f"{name}.yaml"
    if "/" in name or not path.is_file():
        known = ", ".join(sorted(p.stem for p in EXPERIMENTS.glob("*.yaml"))) or "none"
        raise BadInput(f"experiment {name!r}: no {path}; the experiments are: {known}")
    # DVC saves an experiment as a git ref of its name: one git refuses would fail only at the
    # end, after all its runs (`dvc exp save`).
    ref = subprocess.run(["git", "check-ref-format", f"refs/exps/{name}"], capture_output=True)
    if ref.returncode:
        raise BadInput(
            f"experiment {name!r}: not a name git takes for a ref (no spaces, '..', '~', '^', "
            f"':', '?', '*', '[', '\\', and no '.' at either end): rename {path}"
        )
    return path


def experiment_params(name: str, base: dict[str, Any] | None = None) -> dict[str, Any]:
    """The experiment's params: ``base`` (``params.yaml``'s content by default) with
    ``experiments/NAME.yaml`` applied (:func:`ede.config.overridden`), less the families that
    none of its tasks uses and no figure draws. Bad params end here: one line naming the file
    and the key."""
    try:
        base = read_yaml(DEFAULT_PARAMS) if base is None else base
        merged, _ = overridden(base, experiment_file(name))
    except ParamsError as error:
        raise BadInput(first_line(error)) from None
    used = set(merged["runs"]["tasks"].values())
    used |= {merged["report"].get(key) for key in ("effect_space_family", "exploration_family")}
    merged["families"] = {f: family for f, family in merged["families"].items() if f in used}
    validate_params(merged, experiment_file(name))  # the pruned file is as valid: checked anyway
    return merged


def _git(*args: str, cwd: Path | None = None) -> str:
    done = subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True)
    if done.returncode:
        raise Failed(f"git {' '.join(args)}: {first_line(done.stderr)}")
    return done.stdout


def _checkout_files() -> list[str]:
    """This checkout's files as git sees them: committed, changed or new, never ignored ones."""
    listed = _git("ls-files", "-z", "--cached", "--others", "--exclude-standard").split("\0")
    return [name for name in listed if name and Path(name).is_file()]


def prepare_workspace(name: str, params: dict[str, Any], update_code: bool = True) -> Path:
    """The experiment's working copy, made or brought up to date: a git worktree at this
    checkout's commit holding this checkout's files as they are (the code that runs there,
    :func:`_tool`) and the experiment's params, its DVC cache this checkout's. Its ``data/``
    (outputs and checkpoints) and ``dvc.lock`` are kept. With ``update_code`` false, a working
    copy that exists keeps its files as they are and gets only the params."""
    workspace = WORKSPACES / name
    head = _git("rev-parse", "HEAD").strip()
    # The copy's record of its finished runs. DVC's autostage (.dvc/config) adds it to the
    # copy's git index, so the checkout below would delete it, and DVC then restore every
    # finished run from its run cache, or run it again where the run cache lacks it.
    lock = workspace / "dvc.lock"
    records = lock.read_text() if lock.is_file() else None
    if records is not None and not _records_readable(records):  # a kill while DVC wrote it
        records = None
        lock.unlink()
        click.echo(
            f"experiment {name}: its working copy's dvc.lock was damaged (empty, or not DVC's "
            "YAML) and is removed; DVC restores the finished runs from its run cache",
            err=True,
        )
    if not (workspace / ".git").exists():
        _git("worktree", "prune")  # a working copy deleted by hand leaves its registration
        workspace.parent.mkdir(parents=True, exist_ok=True)
        _git("worktree", "add", "--detach", "--force", str(workspace), head)
        update_code = True
    elif update_code:
        _git("checkout", "--quiet", "--detach", "--force", head, cwd=workspace)
    if update_code:
        files = _checkout_files()
        for file in files:
            source, copy = Path(file), workspace / file
            if _contents(copy) != source.read_bytes():
                copy.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(source, copy)
        present = set(files)
        for file in _git("ls-files", "-z", cwd=workspace).split("\0"):
            if file and file not in present:  # deleted here, not yet committed
                (workspace / file).unlink(missing_ok=True)
    if records is not None:
        write_text(lock, records)
    write_text(
        workspace / DEFAULT_PARAMS,
        f"# experiments/{name}.yaml applied to params.yaml "
        f"(ede-pipeline experiment run {name})\n" + yaml.safe_dump(params, sort_keys=False),
    )
    write_text(workspace / ".dvc" / "config.local", _shared_config())
    (workspace / layout.DATA).mkdir(exist_ok=True)
    return workspace


def _records_readable(text: str) -> bool:
    """Whether ``text`` is a ``dvc.lock`` DVC reads: YAML, a mapping of its stages."""
    try:
        records = yaml.safe_load(text)
    except yaml.YAMLError:
        return False
    return isinstance(records, dict) and isinstance(records.get("stages"), dict)


def _copy_params(workspace: Path) -> dict[str, Any]:
    """The params of the commit a working copy holds (before its experiment's were applied):
    the base an experiment keeping the copy's code runs on, whose keys that code knows."""
    committed = Path(f"{workspace}@HEAD") / DEFAULT_PARAMS  # a name for errors only
    try:
        return parse_yaml(_git("show", f"HEAD:{DEFAULT_PARAMS}", cwd=workspace), committed)
    except ParamsError as error:
        raise BadInput(first_line(error)) from None


def _contents(path: Path) -> bytes | None:
    return path.read_bytes() if path.is_file() else None


def _run_code() -> list[str]:
    """The code that makes an experiment's runs, as this checkout's ``dvc.yaml`` names it: the
    files and folders every stage but the report depends on (data aside), and ``dvc.yaml``."""
    stages = yaml.safe_load(Path("dvc.yaml").read_text())["stages"]
    code = {"dvc.yaml"}
    for name, stage in stages.items():
        if name != "report":
            deps = stage.get("do", stage).get("deps", [])
            code.update(d for d in deps if "${" not in d and Path(d).parts[0] != layout.DATA.name)
    return sorted(code)


def _changed_run_code(workspace: Path) -> list[str]:
    """The files of :func:`_run_code` that differ between this checkout and ``workspace``."""
    code = _run_code()

    def is_code(file: str) -> bool:
        return any(file == path or file.startswith(f"{path}/") for path in code)

    here = set(_checkout_files())
    there = set(_git("ls-files", "-z", cwd=workspace).split("\0"))
    return sorted(
        file
        for file in filter(is_code, here | there)
        if _contents(Path(file)) != _contents(workspace / file)
    )


def _check_code_keeps_runs(name: str, workspace: Path) -> None:
    """Refuse (:class:`BadInput`) to bring ``workspace``'s code up to date where that would make
    DVC discard finished runs: their stages depend on the code, so DVC runs them again."""
    if not (workspace / ".git").exists():
        return
    finished = list((workspace / layout.RUNS).glob("**/metrics.json"))
    changed = _changed_run_code(workspace) if finished else []
    if changed:
        listed = ", ".join(changed[:3]) + (
            f" and {len(changed) - 3} more" if len(changed) > 3 else ""
        )
        raise BadInput(
            f"experiment {name}: code its finished runs depend on changed here ({listed}), "
            f"and DVC would run them ({len(finished)}) again; --keep-code finishes the experiment "
            "with the code they were made with, --update-code runs them again with this "
            "checkout's"
        )


def _shared_config() -> str:
    """The working copy's ``.dvc/config.local``: this checkout's cache, and its remotes' local
    paths as this checkout resolves them (a relative one is relative to ``.dvc/``, which in the
    copy is elsewhere)."""
    from dvc.repo import Repo

    lines = [f"[cache]\n    dir = {(Path('.dvc') / 'cache').resolve()}\n"]
    with Repo(".") as repo:  # its config, local paths resolved
        remotes = {name: remote["url"] for name, remote in repo.config["remote"].items()}
    for name, url in remotes.items():
        if "://" not in url:
            lines.append(f"['remote \"{name}\"']\n    url = {url}\n")
    return "".join(lines)


def _code_path(workspace: Path) -> Path:
    """A folder that puts the working copy's packages first on ``PYTHONPATH``: a link per
    package to its folder there (``ede_pipeline`` is ``pipeline/``, as ``pyproject.toml``'s
    ``package-dir`` maps it). The tools run the copy's code, frozen when the experiment was
    (re)started, not this checkout's as it is edited meanwhile; and its ``run.json`` files name
    the copy's commit (:func:`ede.provenance.code_version`)."""
    import tomllib

    packages = tomllib.loads(Path("pyproject.toml").read_text())["tool"]["setuptools"][
        "package-dir"
    ]
    code = workspace / ".dvc" / "tmp" / "python"
    code.mkdir(parents=True, exist_ok=True)
    for package, folder in packages.items():
        link = code / package
        if not link.is_symlink():
            link.symlink_to(Path("..", "..", "..", folder))
    return code.resolve()


def _tool(workspace: Path, *argv: str) -> int:
    """Run one of this environment's tools (``ede-pipeline``, ``dvc``) in ``workspace`` with its
    code (:func:`_code_path`), its output to ours; a signal that stops us stops it first."""
    bin_dir = Path(sys.executable).parent
    python_path = os.pathsep.join(
        filter(None, [str(_code_path(workspace)), os.environ.get("PYTHONPATH")])
    )
    env = {
        **os.environ,
        "PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}",
        "PYTHONPATH": python_path,
    }
    if argv[0] == "ede-pipeline":  # it ends with this process, however this one ends
        env[PARENT_ENV] = str(os.getpid())
    child = subprocess.Popen([str(bin_dir / argv[0]), *argv[1:]], cwd=workspace, env=env)
    before = signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))
    try:
        return child.wait()
    except BaseException:  # Ctrl-C, or SIGTERM (a batch system stopping the job)
        child.terminate()
        child.wait()
        raise
    finally:
        signal.signal(signal.SIGTERM, before)


def _git_identity() -> dict[str, str]:
    """``dvc exp save`` commits: where git has no user, one named for the tool."""
    if subprocess.run(["git", "config", "user.email"], capture_output=True).returncode == 0:
        return {}
    return {
        "GIT_AUTHOR_NAME": "ede-pipeline",
        "GIT_AUTHOR_EMAIL": "ede-pipeline@localhost",
        "GIT_COMMITTER_NAME": "ede-pipeline",
        "GIT_COMMITTER_EMAIL": "ede-pipeline@localhost",
    }


@click.group()
def experiment() -> None:
    """The committed experiments (experiments/NAME.yaml): run, export, show."""


@experiment.command("list")
def list_experiments() -> None:
    """The experiment files, each with the first sentence of its description (its opening
    comment)."""
    for path in sorted(EXPERIMENTS.glob("*.yaml")):
        lines = path.read_text().splitlines()
        comment = " ".join(
            line.lstrip("#").strip()
            for line in lines[
                : next((i for i, line in enumerate(lines) if not line.startswith("#")), len(lines))
            ]
        )
        first = comment.split(". ")[0].rstrip(".")
        click.echo(f"{path.stem:22s}{textwrap.shorten(first, WIDTH - 22, placeholder=' …')}")


@experiment.command("run", context_settings={"ignore_unknown_options": True})
@click.argument("name")
@click.option(
    "--push",
    is_flag=True,
    help="Then send its outputs to the artifact store (`dvc "
    "push`: the DVC remote, `store` by default).",
)
@click.option(
    "--keep-code/--update-code",
    default=None,
    help="Run again after the code changed: finish the experiment with the code its working "
    "copy holds (its finished runs' code, with the params.yaml of its commit), or bring the copy up to this checkout, which runs "
    "its finished runs again. Without either, a change to the code the runs depend on is "
    "refused while the experiment has finished runs.",
)
@click.argument("sweep_args", nargs=-1, type=click.UNPROCESSED)
def run_experiment(
    name: str, push: bool, keep_code: bool | None, sweep_args: tuple[str, ...]
) -> None:
    """Run experiments/NAME.yaml in its working copy and record it as the DVC experiment NAME.

    SWEEP_ARGS go to `ede-pipeline sweep` as they are (e.g. `--jobs 2`, `--executor ray`).
    Run it again after a kill or a failure: finished runs are kept, the others resume from their
    checkpoints. The copy's code is brought up to this checkout's each time, unless that would
    run finished runs again (see --keep-code).
    """
    from ede_pipeline.sweep.command import sweep

    if not Path("dvc.yaml").is_file() or not (Path(".dvc")).is_dir():
        raise BadInput(f"run from the repository root (no dvc.yaml and .dvc/ in {Path.cwd()})")
    try:  # bad sweep options end here, before anything is made
        targets = sweep.make_context("sweep", list(sweep_args)).params["targets"]
    except click.UsageError as error:
        raise BadInput(f"sweep options: {error.format_message()}") from None
    if targets:  # `dvc repro` would run the other runs after the sweep all the same
        raise BadInput(
            f"experiment {name}: stages ({', '.join(targets)}) are not taken: an experiment runs "
            f"all of experiments/{name}.yaml's runs (its runs.seeds and runs.algos choose them)"
        )
    workspace = WORKSPACES / name
    if keep_code and (workspace / ".git").exists():  # the copy's code reads the copy's params
        params = experiment_params(name, _copy_params(workspace))
    else:  # an unknown name, one git refuses, and bad params end here, before the lock
        params = experiment_params(name)
    with ExitStack() as held:
        try:  # one writer per experiment: a second run of it is refused before it changes anything
            held.enter_context(exclusive(workspace))
        except OutputBusy as error:
            raise BadInput(f"experiment {name}: {error}") from None
        _run_held(name, workspace, params, push, keep_code, sweep_args)


def _run_held(
    name: str,
    workspace: Path,
    params: dict[str, Any],
    push: bool,
    keep_code: bool | None,
    sweep_args: tuple[str, ...],
) -> None:
    """:func:`run_experiment`'s work, its working copy's lock held."""
    if keep_code is None:
        _check_code_keeps_runs(name, workspace)
    prepare_workspace(name, params, update_code=not keep_code)
    kept = " with the code it started with" if keep_code else ""
    click.echo(f"experiment {name}: in {workspace}{kept}", err=True)
    if code := _tool(workspace, "ede-pipeline", "sweep", *sweep_args):
        raise Failed(f"experiment {name}: the sweep failed (exit {code}); run it again to resume")
    if code := _tool(workspace, "dvc", "repro"):
        raise Failed(f"experiment {name}: dvc repro failed (exit {code}); run it again to resume")
    os.environ.update(_git_identity())
    if code := _tool(workspace, "dvc", "exp", "save", "--name", name, "--force"):
        raise Failed(f"experiment {name}: dvc exp save failed (exit {code})")
    if push and (code := _tool(workspace, "dvc", "push")):
        raise Failed(
            f"experiment {name}: dvc push failed (exit {code}); it is recorded here, "
            "run it again to push"
        )
    click.echo(
        f"experiment {name}: recorded (`dvc exp show`, `ede-pipeline experiment show`); "
        f"export its runs with `ede-pipeline experiment export {name}`",
        err=True,
    )


@experiment.command("export")
@click.argument("name")
@click.option(
    "--to",
    "to",
    type=click.Path(file_okay=False, path_type=Path),
    default=layout.RESULTS_RUNS,
    show_default=True,
    help="The published runs' folder.",
)
def export(name: str, to: Path) -> None:
    """Copy experiment NAME's finished runs into the published layout.

    Each finished run's eval.csv, diagnostics.csv, run.json and metrics.json go to
    TO/<task>/<algo>/seed<N>/, checked first (`ede.runs.read_run`: the run the experiment's
    params name, finished, its files whole), and the held-out metrics of the embedding its
    EDE-TD3 runs used to TO/<task>/embedding/<checksum>/. Each task's source.json names the
    experiment file, the commits its runs were made at (an earlier export's too), its seeds,
    and report.thresholds' returns for it. Where the task's folder already holds seeds from
    other experiments (an experiment adding seeds to a published task), source.json keeps their
    parts beside this one; seeds already published by another experiment are refused, and so
    are runs there that `ede-pipeline results` would refuse (a folder not named seed<N>, a file
    not the one its run.json records) or that were made with other params than this export's.
    Nothing is written unless every task's runs pass.
    """
    experiment_file(name)
    workspace = WORKSPACES / name
    if not (workspace / DEFAULT_PARAMS).is_file():
        raise BadInput(
            f"experiment {name}: not run here yet (no {workspace}); "
            f"`ede-pipeline experiment run {name}` first"
        )
    params = read_params(workspace / DEFAULT_PARAMS)
    finished, problems = _finished_runs(workspace, params)
    if problems:
        raise BadInput(problems[0])
    if not finished:
        raise BadInput(f"experiment {name}: no run has finished yet")
    exported = {}  # task: its runs and its source.json's parts, all checked before any is written
    for task in params.runs.tasks:
        runs = [
            (algo, seed, folder, made)
            for (t, algo, seed), (folder, made) in finished.items()
            if t == task
        ]
        if not runs:  # none of this task's runs has finished yet
            click.echo(f"{task}: no run finished yet; nothing exported", err=True)
            continue
        published = _published_beside(task, runs, to)
        commits = sorted(
            {made["code"]["commit"] for *_, made in runs} | _earlier_commits(task, params, runs, to)
        )
        part = {
            "experiment": experiment_file(name).as_posix(),
            "commit": commits[0] if len(commits) == 1 else commits,
            "seeds": list(params.runs.seeds),
        }
        if task in params.report.thresholds:
            part["thresholds"] = params.report.thresholds[task]
        exported[task] = runs, _merged_source(layout.task_runs(task, to), part, published)
    for task, (runs, source) in exported.items():
        for algo, seed, folder, _ in runs:
            target = layout.run(task, algo, seed, to)
            target.mkdir(parents=True, exist_ok=True)
            for file in PUBLISHED:
                if (folder / file).is_file():
                    shutil.copy2(folder / file, target / file)
        embedding = workspace / layout.embedding(params.runs.tasks[task])
        for checksum in {made["embedding"] for algo, *_, made in runs if algo == "ede-td3"}:
            kept = layout.published_embedding(task, checksum, to)
            kept.mkdir(parents=True, exist_ok=True)
            for file in EMBEDDING_METRICS:
                shutil.copy2(embedding / file, kept / file)
        write_json(layout.task_runs(task, to) / "source.json", source)
        click.echo(f"{task}: {len(runs)} runs to {layout.task_runs(task, to)}", err=True)


EMBEDDING_METRICS = ("encoder_metrics.json", "decoder_metrics.json")  # as pretrain writes them


def _earlier_commits(task: str, params: Params, runs: list[tuple], to: Path) -> set[str]:
    """The commits of this experiment's runs of ``task`` that an earlier export published to
    ``to`` and the working copy no longer holds (a copy made again after they were exported):
    the part's commits name every run it publishes, not only this export's."""
    now = {(algo, seed) for algo, seed, *_ in runs}
    commits = set()
    for algo, seed in itertools.product(params.runs.algos, params.runs.seeds):
        record = layout.run(task, algo, seed, to) / "run.json"
        if (algo, seed) not in now and record.is_file():
            commits.add(json.loads(record.read_text())["code"]["commit"])
    return commits


def _published_beside(task: str, runs: list[tuple], to: Path) -> set[int]:
    """The seeds of ``task`` with finished runs in ``to``, beside which this export puts its
    ``runs``: those there read and checked as ``results`` reads them
    (:func:`ede_pipeline.results.published_runs`: folders named seed<N>, files those their
    run.json records), and the ones that stay made with the same params as ``runs``
    (:func:`ede.runs.unshared_params`). Raises :class:`BadInput` where not."""
    from ede.runs import unshared_params
    from ede_pipeline.results import published_runs

    published = published_runs(to, task)
    replaced = {(algo, seed) for algo, seed, *_ in runs}
    staying = [
        (run, record.made)
        for run, record in published
        if (record.made["algo"], record.curve.seed) not in replaced
    ]
    joining = [(folder, made) for *_, folder, made in runs]
    if (difference := unshared_params(staying + joining)) is not None:
        raise BadInput(difference)
    return {record.curve.seed for _, record in published}


def _merged_source(folder: Path, part: dict, published: set[int]) -> dict | list[dict]:
    """A task folder's source.json with ``part`` (one experiment's) in it: the part alone, or
    beside the parts of other experiments already there, replacing an earlier export of the same
    experiment file. A seed another part already names is refused (:class:`BadInput`), and so is
    one of ``published`` (the seeds with runs there) that no earlier export of it named."""
    from ede_pipeline.results import read_source

    there = (folder / "source.json").is_file()
    checked = read_source(folder).parts if there else []
    written = json.loads((folder / "source.json").read_text()) if there else []
    kept = [
        (json_part, read)
        for json_part, read in zip(
            written if isinstance(written, list) else [written], checked, strict=True
        )
        if read.experiment != part["experiment"]
    ]
    for _, read in kept:
        if twice := sorted(set(read.seeds) & set(part["seeds"])):
            raise BadInput(
                f"{folder / 'source.json'}: seeds {twice} are already published by "
                f"{read.maker()}; an experiment adds seeds the task has not"
            )
    ours = {
        seed for read in checked if read.experiment == part["experiment"] for seed in read.seeds
    }
    if twice := sorted(published & set(part["seeds"]) - ours):
        raise BadInput(
            f"{folder}: seeds {twice} have runs there that no earlier export of "
            f"{part['experiment']} made; an experiment adds seeds the task has not"
        )
    return [*(json_part for json_part, _ in kept), part] if kept else part


def _finished_runs(workspace: Path, params: Params) -> tuple[dict, list[str]]:
    """Every finished run of ``params`` in ``workspace``, checked, by (task, algo, seed): its
    folder and run.json; and one line per run that cannot be published."""
    from ede.runs import RunRejected, RunSpec, read_run

    finished, problems = {}, []
    for task, algo, seed in itertools.product(
        params.runs.tasks, params.runs.algos, params.runs.seeds
    ):
        out = workspace / layout.run(task, algo, seed)
        spec = RunSpec(task, algo, seed, params.runs.budgets[task], params.td3, params.ede_td3)
        expected = {k: v for k, v in spec.identity().items() if k != "embedding"}
        try:
            run = read_run(out, expected)
        except RunRejected as error:
            problems.append(str(error))
            continue
        if run is not None and not (run.made.get("code") or {}).get("commit"):
            problems.append(
                f"{out / 'run.json'}: names no commit (an image built without "
                "EDE_COMMIT?); only runs whose code is known are published"
            )
        elif run is not None:
            finished[(task, algo, seed)] = (out, run.made)
    return finished, problems


@experiment.command()
@click.option(
    "--num",
    "-n",
    type=int,
    default=1,
    show_default=True,
    help="The experiments of the last N commits (first parents); -1: all of them.",
)
def show(num: int) -> None:
    """The DVC experiments, in 80 columns: name, changed params, headline returns per task."""
    command = [sys.executable, "-m", "dvc", "exp", "show", "--json", "--num", str(num)]
    shown = subprocess.run(command, capture_output=True, text=True)
    if shown.returncode:
        raise click.ClickException(f"dvc exp show failed: {shown.stderr.strip()}")
    lines = experiment_blocks(json.loads(shown.stdout))
    click.echo(
        "\n".join(lines)
        if lines
        else "no experiments yet (`ede-pipeline experiment run NAME` or `make quick` makes one)"
    )
