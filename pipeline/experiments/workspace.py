"""An experiment's file, its params, and its working copy (a git worktree under
``.dvc/tmp/experiments/``), and running a tool there."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import click
import yaml

from ede.config import (
    ParamsError,
    name_problem,
    overridden,
    parse_yaml,
    read_yaml,
    shown,
    validate_params,
)
from ede.errors import first_line
from ede.io.atomic import write_text
from ede_pipeline import layout
from ede_pipeline.common import DEFAULT_PARAMS, PARENT_ENV, BadInput, Failed
from ede_pipeline.experiments.show import flatten
from ede_pipeline.sweep.plan import DamagedPipeline, pipeline_repo

EXPERIMENTS = Path("experiments")  # the committed experiment files
WORKSPACES = Path(".dvc") / "tmp" / "experiments"  # each one's working copy (git-ignored by DVC)


def experiment_file(name: str) -> Path:
    """``experiments/NAME.yaml``; one line when NAME is no name (:data:`ede.config.NAME_RULE`:
    it becomes a path, a git ref and a word of commands) or names no experiment there."""
    if (problem := name_problem(name)) is not None:
        raise BadInput(f"experiment {shown(name)}: {problem}")
    path = EXPERIMENTS / f"{name}.yaml"
    if not path.exists():  # one that is no file is refused as it is read (ede.config.read_yaml)
        known = ", ".join(sorted(p.stem for p in EXPERIMENTS.glob("*.yaml") if p.is_file()))
        raise BadInput(f"experiment {name!r}: no {path}; the experiments are: {known or 'none'}")
    return path


def experiment_params(name: str, base: dict[str, Any] | None = None) -> dict[str, Any]:
    """The experiment's params: ``base`` (by default the ``params.yaml`` of this checkout's
    commit, :func:`committed_params`, whatever the workspace's holds) with
    ``experiments/NAME.yaml`` applied (:func:`ede.config.overridden`), less the families that
    none of its tasks uses and no figure draws. Bad params end here: one line naming the file
    and the key."""
    base = committed_params() if base is None else base
    try:
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


def prepare_workspace(
    name: str, params: dict[str, Any], update_code: bool = True, applied_to: str = "its commit's"
) -> Path:
    """The experiment's working copy, made or brought up to date: a git worktree at this
    checkout's commit holding this checkout's files as they are (the code that runs there,
    :func:`run_tool`) and the experiment's params (``applied_to`` says, in the copy's
    ``params.yaml``, to which ``params.yaml`` its file was applied), its DVC cache this
    checkout's. Its ``data/`` (outputs and checkpoints) and ``dvc.lock`` are kept (one DVC
    cannot read: :func:`mend_records`). With ``update_code`` false, a working copy that exists
    keeps its files as they are and gets only the params."""
    workspace = WORKSPACES / name
    head = _git("rev-parse", "HEAD").strip()
    # The copy's record of its finished runs. DVC's autostage (.dvc/config) adds it to the
    # copy's git index, so the checkout below would delete it, and DVC then restore every
    # finished run from its run cache, or run it again where the run cache lacks it.
    lock = workspace / "dvc.lock"
    records = lock.read_bytes() if lock.is_file() else None
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
    if records is not None:  # text that is not UTF-8 comes back as text DVC cannot read
        write_text(lock, records.decode(errors="replace"))
    write_text(
        workspace / DEFAULT_PARAMS,
        f"# experiments/{name}.yaml applied to {applied_to} {DEFAULT_PARAMS} "
        f"(ede-pipeline experiment run {name})\n" + yaml.safe_dump(params, sort_keys=False),
    )
    write_text(workspace / ".dvc" / "config.local", _shared_config())
    (workspace / layout.DATA).mkdir(exist_ok=True)
    return workspace


def mend_records(name: str, workspace: Path) -> None:
    """Read a working copy's pipeline as DVC will (:func:`pipeline_repo`). A ``dvc.lock``
    DVC cannot read (left empty by a kill while DVC wrote it, or edited) is removed, said in one
    line: DVC restores the finished runs it recorded from its run cache. Anything else DVC
    cannot read is refused (:class:`DamagedPipeline`)."""
    try:
        with pipeline_repo(workspace):
            return
    except DamagedPipeline as damage:
        if damage.file.name != "dvc.lock" or not damage.file.is_file():
            raise
        damage.file.unlink()
        click.echo(
            f"experiment {name}: its working copy's dvc.lock was damaged ({damage.problem}) and "
            "is removed; DVC restores the finished runs from its run cache",
            err=True,
        )
    with pipeline_repo(workspace):  # its dvc.yaml, which DVC read no further than that lock
        pass


def committed_params(checkout: Path = Path(".")) -> dict[str, Any]:
    """The ``params.yaml`` of the commit ``checkout`` (this one, or an experiment's working
    copy) is at: what every experiment's file is applied to, so that what runs is what is
    committed (a copy's commit is the base an experiment keeping the copy's code runs on, whose
    keys that code knows)."""
    committed = checkout / f"HEAD:{DEFAULT_PARAMS}"  # git's name for it, in errors
    shown = subprocess.run(
        ["git", "show", f"HEAD:{DEFAULT_PARAMS}"], cwd=checkout, capture_output=True, text=True
    )
    if shown.returncode:
        raise BadInput(
            f"{committed}: {first_line(shown.stderr)}; commit {DEFAULT_PARAMS} (an experiment "
            "applies its file to the committed one), or --workspace-params applies it to yours"
        )
    try:
        return _sections(parse_yaml(shown.stdout, committed), committed)
    except ParamsError as error:
        raise BadInput(first_line(error)) from None


def workspace_params() -> dict[str, Any]:
    """This checkout's ``params.yaml`` as it is, uncommitted edits included
    (``experiment run --workspace-params``)."""
    try:
        return _sections(read_yaml(DEFAULT_PARAMS), DEFAULT_PARAMS)
    except ParamsError as error:
        raise BadInput(first_line(error)) from None


def _sections(params: Any, path: Path) -> dict[str, Any]:
    """``params``, a params file's content, where it is a mapping (of sections)."""
    if not isinstance(params, dict):
        raise ParamsError(path, [f"expected a mapping of sections, found {type(params).__name__}"])
    return params


def uncommitted_params(committed: dict[str, Any]) -> list[str]:
    """The keys (``td3.lr``) in which this checkout's ``params.yaml`` differs from
    ``committed``, its commit's; the file's name where it cannot be read."""
    try:
        here = flatten(_sections(read_yaml(DEFAULT_PARAMS), DEFAULT_PARAMS))
    except ParamsError:
        return [str(DEFAULT_PARAMS)]
    there = flatten(committed)
    keys = list(here) + [key for key in there if key not in here]
    missing = object()
    return [key for key in keys if here.get(key, missing) != there.get(key, missing)]


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


def check_code_keeps_runs(name: str, workspace: Path) -> None:
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
    the copy's commit (:func:`ede.io.provenance.code_version`)."""
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


def run_tool(workspace: Path, *argv: str) -> int:
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


def git_identity() -> dict[str, str]:
    """``dvc exp save`` commits: where git has no user, one named for the tool."""
    if subprocess.run(["git", "config", "user.email"], capture_output=True).returncode == 0:
        return {}
    return {
        "GIT_AUTHOR_NAME": "ede-pipeline",
        "GIT_AUTHOR_EMAIL": "ede-pipeline@localhost",
        "GIT_COMMITTER_NAME": "ede-pipeline",
        "GIT_COMMITTER_EMAIL": "ede-pipeline@localhost",
    }
