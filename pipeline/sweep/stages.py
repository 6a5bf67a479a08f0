"""DVC's side of a sweep: which stages, in which waves, which of them are out of date, the
command each runs, and recording a run as ``dvc repro`` records it.

DVC's public ground where it has one: a stage's command runs as DVC documents it, a run is
recorded as ``dvc commit`` records it (``Repo.commit``). Two steps of ``dvc repro`` have no
public form — holding the repository's lock across many runs, and restoring a run from the run
cache — and are marked where they are used; ``tests/pipeline/test_sweep_dvc_api.py`` guards
every name of DVC used here, which is what ``pyproject.toml``'s bound on dvc is for.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from ede_pipeline.common import BadInput

if TYPE_CHECKING:
    from dvc.repo import Repo
    from dvc.stage import Stage

# The shells DVC starts without reading their startup files, and the options that say so.
QUIET_SHELLS = {"bash": ["--noprofile", "--norc"], "zsh": ["--no-rcs"]}


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
    """The stages the targets name (``*`` a wildcard), or every stage of ``dvc.yaml``.

    Raises:
        BadInput: a target that names no stage (a damaged ``dvc.yaml`` or ``dvc.lock`` ends
            earlier, where the repository is opened: :func:`ede_pipeline.sweep.plan.pipeline_repo`).
    """
    from dvc.exceptions import DvcException

    if not targets:
        return list(repo.stage.collect())
    stages: dict[str, Stage] = {}
    for target in targets:
        try:
            found = repo.stage.collect(target, glob="*" in target)
        except DvcException as error:
            raise BadInput(f"{target}: {error}") from None
        stages.update((stage.addressing, stage) for stage in found)
    if not stages:
        raise BadInput(f"no stages match {' '.join(targets)}")
    return list(stages.values())


def dependencies(repo: Repo, stage: Stage) -> list[Stage]:
    """The stages whose outputs this one reads (DVC's edges point to dependencies)."""
    return list(repo.index.graph.successors(stage))


def in_waves(repo: Repo, stages: list[Stage]) -> list[list[Stage]]:
    """The given stages and every stage they depend on, directly or not, in waves: a stage is
    in the wave after that of its last dependency, so the stages of a wave can run side by side
    once the waves before have run. Within a wave, ``dvc.yaml``'s order."""
    import networkx as nx

    graph = repo.index.graph
    wanted = {stage.addressing: stage for stage in stages}
    for stage in stages:
        wanted.update((upstream.addressing, upstream) for upstream in nx.descendants(graph, stage))
    depth: dict[str, int] = {}
    for stage in reversed(list(nx.topological_sort(graph))):  # dependencies first
        if stage.addressing in wanted:
            depth[stage.addressing] = 1 + max(
                (depth[dependency.addressing] for dependency in dependencies(repo, stage)),
                default=-1,
            )
    order = {stage.addressing: index for index, stage in enumerate(repo.stage.collect())}
    waves: list[list[Stage]] = [[] for _ in range(max(depth.values(), default=-1) + 1)]
    for name in sorted(depth, key=order.__getitem__):
        waves[depth[name]].append(wanted[name])
    return waves


def out_of_date(repo: Repo, waves: list[list[Stage]]) -> tuple[set[str], set[str]]:
    """The stages that will run — those out of date now (``Stage.changed``, what ``dvc status``
    reports) and those downstream of them — and, of these, the ones downstream. Those are not
    asked now but at their turn: if what they depend on came out as before, they are up to date
    after all, as ``dvc repro`` finds them."""
    stale: set[str] = set()
    downstream: set[str] = set()
    for wave in waves:
        for stage in wave:
            if any(dep.addressing in stale for dep in dependencies(repo, stage)):
                downstream.add(stage.addressing)
            if stage.addressing in downstream or stage.changed():
                stale.add(stage.addressing)
    return stale, downstream


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
