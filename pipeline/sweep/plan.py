"""What a sweep runs: the pipeline DVC reads (``dvc.yaml``, ``dvc.lock``), the train runs of
``dvc.yaml``'s matrix, their commands, and the jobs that run them — one stage each, or one process
for several seeds of a task and algorithm (a group)."""

from __future__ import annotations

import shlex
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from ede.config import SB3_ALGOS, Params
from ede.errors import first_line
from ede_pipeline import layout
from ede_pipeline.common import BadInput

if TYPE_CHECKING:
    from dvc.exceptions import DvcException
    from dvc.repo import Repo

# What each file of the pipeline is, and how to mend it when DVC cannot read it.
PIPELINE_FILES = {
    "dvc.yaml": "mend it (`git diff dvc.yaml` shows your edits; `git checkout dvc.yaml` restores "
    "the committed one)",
    "dvc.lock": "remove it: DVC then restores the stages it recorded from its run cache (or runs "
    "them again where the cache lacks them)",
}


class DamagedPipeline(BadInput):
    """``dvc.yaml`` or ``dvc.lock`` that DVC cannot read: one line naming the file, what is
    wrong and how to mend it; ``file`` is the file's path, ``problem`` what is wrong."""

    def __init__(self, file: Path, problem: str) -> None:
        self.file, self.problem = file, problem
        super().__init__(f"{file}: {problem}; {PIPELINE_FILES[file.name]}")


@contextmanager
def pipeline_repo(root: Path = Path(".")) -> Iterator[Repo]:
    """The DVC repository at ``root`` with its pipeline read: ``dvc.yaml``'s stages and what
    ``dvc.lock`` records of them, the one place a command reads them, so that a damaged file is
    one line rather than DVC's traceback. DVC's lock on the repository is not taken.

    Raises:
        BadInput: ``root`` is no DVC repository, or DVC cannot open it.
        DamagedPipeline: DVC cannot read ``dvc.yaml`` or ``dvc.lock``, or ``dvc.yaml`` has no
            stages.
    """
    from dvc.exceptions import DvcException, NotDvcRepoError
    from dvc.repo import Repo

    # A folder in a file's place: DVC skips it, or says "not a .dvc file".
    for name in PIPELINE_FILES:
        if (root / name).exists() and not (root / name).is_file():
            raise DamagedPipeline(root / name, "not a file")
    try:
        repo = Repo(str(root))
    except NotDvcRepoError:
        raise BadInput(
            f"{root.resolve()}: dvc.yaml but no DVC repository; run `dvc init` (in a git "
            "repository) first"
        ) from None
    except DvcException as error:  # its .dvc/config, say
        raise BadInput(f"{root.resolve()}: DVC cannot open it: {first_line(error)}") from None
    with repo:
        try:
            stages = repo.stage.collect()
            repo.index.graph  # noqa: B018 (built here: a cycle, or two stages with one output)
        except DvcException as error:
            raise DamagedPipeline(*_damage(root, error)) from None
        if not stages:
            raise DamagedPipeline(root / "dvc.yaml", "no stages")
        yield repo


def _damage(root: Path, error: DvcException) -> tuple[Path, str]:
    """Which file of the pipeline DVC could not read, and what is wrong with it, in one line."""
    from dvc.utils.serialize import EncodingError
    from dvc.utils.strictyaml import YAMLSyntaxError, YAMLValidationError

    named = getattr(error, "path", None) or getattr(error, "relpath", None) or "dvc.yaml"
    file = root / ("dvc.lock" if Path(str(named)).name == "dvc.lock" else "dvc.yaml")
    if file.is_file() and not file.read_bytes().strip():
        return file, "empty"
    if isinstance(error, YAMLValidationError):
        problems = [
            f"{'.'.join(map(str, invalid.path)) or '(top level)'}: {invalid.error_message}"
            for invalid in error.exc.errors
        ]
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        return file, f"not what DVC expects: {problems[0]}{more}"
    if isinstance(error, YAMLSyntaxError):
        cause = error.exc.__cause__
        mark = getattr(cause, "problem_mark", None)
        where = f"line {mark.line + 1}: " if mark is not None else ""
        return file, f"not YAML ({where}{getattr(cause, 'problem', None) or first_line(error)})"
    if isinstance(error, EncodingError):
        return file, "not UTF-8 text"
    return file, " ".join(str(error).split())  # DVC's own words, some of several lines


@dataclass(frozen=True)
class RunId:
    """Which run a train stage is: what determines its command and its output folder."""

    task: str
    algo: str
    seed: int


def train_runs(params: Params) -> dict[str, RunId]:
    """Every run of ``dvc.yaml``'s train matrix, by the name DVC gives its stage
    (``train@<task>-<algo>-<seed>``): a stage's run known from the params, not from its command."""
    return {
        f"train@{task}-{algo}-{seed}": RunId(task, algo, seed)
        for task in params.runs.tasks
        for algo in params.runs.algos
        for seed in params.runs.seeds
    }


def train_command(task: str, algo: str, seeds: list[int]) -> list[str]:
    """The ``ede-pipeline train`` command of runs of one task and algorithm, their paths from
    :mod:`ede_pipeline.layout` (``dvc.yaml``'s train command for one seed;
    ``tests/pipeline/test_layout.py`` holds the two together)."""
    inputs = layout.task_inputs(task)
    out = (
        layout.run(task, algo, seeds[0])
        if len(seeds) == 1
        else layout.run(task, algo, 0).with_name("seed{seed}")
    )
    return [
        "ede-pipeline",
        "train",
        "--task",
        task,
        "--algo",
        algo,
        "--seed",
        ",".join(map(str, seeds)),
        "--out",
        str(out),
        "--encoder",
        str(inputs / layout.ENCODER),
        "--decoder",
        str(inputs / layout.DECODER),
    ]


@dataclass(frozen=True)
class Job:
    """One stage's command, ready for any executor: plain data that pickles."""

    stage: str
    argvs: list[list[str]]  # one argv per line of the stage's ``cmd``, as DVC would run them
    cwd: str  # the checkout, the same path on every node
    env: dict[str, str]  # set on top of the executing process's environment
    log: str  # where the commands' output goes
    members: tuple[str, ...] = ()  # a group's stages (one process trains them all); () for one
    runs: tuple[RunId, ...] = ()  # the train runs it makes (several for a group); () for others


def group_jobs(jobs: list[Job], size: int) -> list[Job]:
    """Jobs of train runs that differ only in their seed, as jobs of up to ``size`` runs each:
    one ``ede-pipeline train --seed a,b,… --out …/seed{seed}`` per group
    (docs/performance.md). A job is grouped by its run's identity
    (``Job.runs``); jobs of other stages stay alone. A group runs its command as DVC runs the
    members' (through the same shell, with the same environment). Stable-baselines3's runs
    (:data:`ede.config.SB3_ALGOS`) stay alone: nothing of theirs is batched, a group would only
    train its seeds one after another on one core."""
    if size <= 1:
        return jobs
    groups: dict[tuple[str, str], list[Job]] = {}
    alone: list[Job] = []
    for job in jobs:
        if len(job.runs) == 1 and len(job.argvs) == 1 and job.runs[0].algo not in SB3_ALGOS:
            groups.setdefault((job.runs[0].task, job.runs[0].algo), []).append(job)
        else:
            alone.append(job)
    grouped: list[Job] = []
    for (task, algo), members in groups.items():
        members.sort(key=lambda job: job.runs[0].seed)
        for start in range(0, len(members), size):
            chunk = members[start : start + size]
            if len(chunk) == 1:
                grouped.append(chunk[0])
                continue
            first = chunk[0]
            command = train_command(task, algo, [job.runs[0].seed for job in chunk])
            shell = first.argvs[0][:-1]  # DVC's ``sh -c``: the command is its last word
            argv = [*shell, shlex.join(command)] if shell else command
            stages = tuple(job.stage for job in chunk)
            log = str(Path(first.log).with_name(f"{Path(first.log).stem}+{len(chunk) - 1}.log"))
            grouped.append(
                Job(
                    " + ".join(stages),
                    [argv],
                    first.cwd,
                    first.env,
                    log,
                    stages,
                    tuple(job.runs[0] for job in chunk),
                )
            )
    return alone + grouped


def seed_by_seed(jobs: list[Job]) -> list[Job]:
    """Jobs in the order of their runs' lowest seed, and within a seed in the order given
    (dvc.yaml's: task, then algorithm); jobs that train nothing first. A sweep stopped partway
    (a time limit, a lost cluster) so leaves every task and algorithm at the same seeds, a
    comparison, where dvc.yaml's order would leave every seed of one algorithm and none of the
    other."""
    return sorted(jobs, key=lambda job: min(run.seed for run in job.runs) if job.runs else -1)


def default_group_size(params: Params, runs: int, workers: int | None) -> int:
    """Seeds per process when ``--group-size`` is not given.

    On CUDA every seed of a task and algorithm: the update is bound by kernel launches, so a group
    costs about what one run costs. On CPU as many as still leave every worker a process
    (``runs // workers``): batching saves per-operation overhead (``benchmarks/
    train_throughput.py`` measures groups against one run), but a group runs on one core; on Ray
    without ``--jobs`` (workers unknown) one.
    """
    seeds = len(params.runs.seeds)
    if _on_cuda(params.td3.device):
        return seeds
    if workers is None:
        return 1
    return max(1, min(seeds, runs // workers))


def _on_cuda(device: str) -> bool:
    if device == "cpu":
        return False
    import torch

    return torch.cuda.is_available()
