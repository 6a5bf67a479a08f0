"""DVC's side of a sweep: which stages, the command each runs, bringing upstream stages up to
date, and recording a run as ``dvc repro`` records it.

DVC's public ground where it has one: a stage's command runs as DVC documents it, a run is
recorded as ``dvc commit`` records it (``Repo.commit``). Two steps of ``dvc repro`` have no
public form — holding the repository's lock across many runs, and restoring a run from the run
cache — and are marked where they are used; ``tests/pipeline/test_sweep_dvc_api.py`` guards
every name of DVC used here, which is what ``pyproject.toml``'s bound on dvc is for.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import click

from ede_pipeline.common import BadInput

if TYPE_CHECKING:
    from dvc.repo import Repo
    from dvc.stage import Stage

TRAIN_STAGES = "train*"  # dvc.yaml's train stage (one instance per run), unless told others

# The shells DVC starts without reading their startup files, and the options that say so.
QUIET_SHELLS = {"bash": ["--noprofile", "--norc"], "zsh": ["--no-rcs"]}


def dvc_executable() -> str:
    beside = Path(sys.executable).parent / "dvc"
    return str(beside) if beside.exists() else (shutil.which("dvc") or "dvc")


def stage_argvs(stage: Stage) -> list[list[str]]:
    """A stage's command as ``dvc repro`` runs it: each line of ``cmd`` in turn, through the
    user's shell (``$SHELL``, ``/bin/sh`` where unset) without its startup files."""
    shell = os.environ.get("SHELL") or "/bin/sh"
    quiet = QUIET_SHELLS.get(Path(shell).name, [])
    lines = stage.cmd if isinstance(stage.cmd, list) else [stage.cmd]
    return [[shell, *quiet, "-c", line] for line in lines]


def stage_env(stage: Stage) -> dict[str, str]:
    """The variables DVC sets for a stage's command."""
    from dvc.env import DVC_ROOT, DVC_STAGE

    return {DVC_ROOT: stage.repo.root_dir, DVC_STAGE: stage.addressing}


def collect_stages(repo: Repo, targets: tuple[str, ...]) -> list[Stage]:
    from dvc.exceptions import DvcException

    stages: dict[str, Stage] = {}
    for target in targets or (TRAIN_STAGES,):
        try:
            found = repo.stage.collect(target, glob="*" in target)
        except DvcException as error:
            raise BadInput(f"{target}: {error}") from None
        stages.update((stage.addressing, stage) for stage in found)
    if not stages:
        raise BadInput(f"no stages match {' '.join(targets or (TRAIN_STAGES,))}")
    return list(stages.values())


def upstream_of(repo: Repo, stages: list[Stage]) -> list[Stage]:
    """Every stage the given ones depend on, directly or not, that is not one of them."""
    import networkx as nx

    graph = repo.index.graph
    names = {stage.addressing for stage in stages}
    upstream: dict[str, Stage] = {}
    for stage in stages:
        for dependency in nx.descendants(graph, stage):  # DVC's edges point to dependencies
            if dependency.addressing not in names:
                upstream[dependency.addressing] = dependency
    return list(upstream.values())


def bring_upstream_up_to_date(repo: Repo, stages: list[Stage]) -> None:
    """``dvc repro`` of the stages the given ones depend on that are out of date, if any."""
    with repo_lock(repo):
        stale = [stage.addressing for stage in upstream_of(repo, stages) if stage.changed()]
    if not stale:
        return
    click.echo(f"sweep: dvc repro {' '.join(stale)}", err=True)
    result = subprocess.run([dvc_executable(), "repro", *stale], check=False)
    if result.returncode != 0:
        raise click.ClickException(
            f"dvc repro of the upstream stages failed "
            f"(exit {result.returncode}); nothing else was run"
        )


def record(stage: Stage) -> None:
    """What ``dvc repro`` does once a stage's command has succeeded, as ``dvc commit --force``
    does it: hash the dependencies and outputs, save the run to the run cache, commit the outputs
    to the cache, write ``dvc.lock``."""
    stage.repo.commit(stage.addressing, force=True)


def restore_from_run_cache(stage: Stage) -> bool:
    """``dvc repro``'s first resort: check out this very run's outputs if DVC has them.
    DVC has no public way to ask its run cache for one stage: this is ``dvc repro``'s own call."""
    from dvc.stage.cache import RunCacheNotFoundError

    try:
        stage.repo.stage_cache.restore(stage)
    except RunCacheNotFoundError:
        return False
    return True


@contextmanager
def repo_lock(repo: Repo) -> Iterator[None]:
    """The repository's lock, held as ``dvc repro`` holds it, for as long as the sweep runs.
    DVC has no public way to hold it across commands: this is the lock its commands take."""
    from dvc.lock import LockError
    from dvc.repo import lock_repo

    try:
        with lock_repo(repo):
            yield
    except LockError as error:
        raise BadInput(f"{error} (a `dvc` command or another sweep is running here)") from None
