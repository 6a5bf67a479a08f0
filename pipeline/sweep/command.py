"""``ede-pipeline sweep``: the command, and what it reports of each run (the package's
docstring says what a sweep does)."""

from __future__ import annotations

import contextlib
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING

import click
from click.core import ParameterSource

from ede.io.atomic import MARK, NotOurs, claim, place, unwritable
from ede_pipeline.common import DEFAULT_PARAMS, BadInput, Failed, check_outputs, read_params
from ede_pipeline.sweep.execute import (
    Executor,
    LocalExecutor,
    Outcome,
    attempts_file,
    problem,
)
from ede_pipeline.sweep.on_ray import RETRIES, RayExecutor, check_ray_address
from ede_pipeline.sweep.plan import (
    Job,
    RunId,
    default_group_size,
    group_jobs,
    pipeline_repo,
    seed_by_seed,
    train_runs,
)
from ede_pipeline.sweep.stages import (
    collect_stages,
    dependencies,
    in_waves,
    out_of_date,
    record,
    repo_lock,
    restore_from_run_cache,
    stage_argvs,
    stage_env,
)
from ede_pipeline.sweep.tally import Tally

if TYPE_CHECKING:
    from dvc.repo import Repo
    from dvc.stage import Stage

    from ede.config import Params

LOGS = Path(".dvc") / "tmp" / "sweep"  # DVC's own git-ignored scratch folder
LOGS_KIND = "folder of sweep logs"
# What a sweep writes into its logs folder, each job's: its log, its attempts (attempts_file) and
# its run's progress file (progress_file, EDE_PROGRESS); and beside each what a writer of a file
# may put there (ede.io.atomic, ede.io.locks): its temporary, its lock, its mark and the mark's
# temporary. The folder's mark owns them all, so that the next sweep writes there again; a file
# of any other name is a user's.
LOGS_OWN = tuple(
    pattern
    for name in ("*.log", "*.attempts", "*.progress")
    for pattern in (
        name,
        f"{name}.tmp-*",
        f".{name}.lock",
        f".{name}{MARK}",
        f".{name}{MARK}.tmp-*",
    )
)
TAIL = 20  # lines of a failed run's log shown in the report


def _finite(param: click.Parameter, value: float) -> float:
    """Refuse ``inf`` and ``nan``, which click's ranges let through."""
    if not math.isfinite(value):
        raise click.BadParameter(f"{value} is not a finite number", param=param)
    return value


@click.command()
@click.argument("targets", nargs=-1)
@click.option(
    "-j",
    "--jobs",
    type=click.IntRange(min=1),
    help="Runs at once  [default: local: the number of cores; ray: as the cluster fits]",
)
@click.option(
    "--executor",
    type=click.Choice(["local", "ray"]),
    default="local",
    show_default=True,
    help="Child processes on this machine, or Ray tasks on a cluster.",
)
@click.option(
    "--address",
    help="Ray: the cluster to join (`ray start --head` prints it; "
    "default: $RAY_ADDRESS, else a new local Ray instance). One where no Ray cluster "
    "answers within 10 s is refused before anything runs.",
)
@click.option(
    "--retries",
    type=click.IntRange(min=0),
    default=RETRIES,
    show_default=True,
    help="Ray: times a run lost with its Ray worker or node is started again on the "
    "nodes there are (it resumes from its checkpoint). A run whose command fails "
    "is not.",
)
@click.option(
    "--cpus-per-run",
    type=click.FloatRange(min=0, min_open=True),
    default=1.0,
    callback=lambda ctx, param, value: _finite(param, value),
    show_default=True,
    help="Ray: the num_cpus of each run's task.",
)
@click.option(
    "--group-size",
    type=click.IntRange(min=1),
    help="Runs of one task and algorithm trained by one process (`train --seeds`)  "
    "[default: on CUDA (td3.device cuda, or auto with a GPU) every seed; on CPU as "
    "many as leave every job a process]",
)
@click.option(
    "--logs",
    type=click.Path(path_type=Path),
    default=LOGS,
    show_default=True,
    help="Where each run's output goes, one file per stage.",
)
@click.pass_context
def sweep(
    ctx: click.Context,
    targets: tuple[str, ...],
    jobs: int | None,
    executor: str,
    address: str | None,
    retries: int,
    cpus_per_run: float,
    group_size: int | None,
    logs: Path,
) -> None:
    """Run the out-of-date stages in parallel, in dependency order, and record each with DVC.

    TARGETS are stages as `dvc repro` takes them, `*` a wildcard (default: every stage of
    dvc.yaml; e.g. `'train@ede/Reacher*'` only those runs), with the stages they depend on.
    Exits 1 if any stage failed (what depends on it is not run); what succeeded is recorded all
    the same, and running the sweep again runs only the rest.
    """
    if not Path("dvc.yaml").exists():
        raise BadInput(f"run from the repository root (no dvc.yaml in {Path.cwd()})")
    if executor == "local" and address:
        raise BadInput("--address is for --executor ray")
    if executor == "local" and ctx.get_parameter_source("retries") != ParameterSource.DEFAULT:
        raise BadInput(
            "--retries is for --executor ray (a local run that fails is reported, "
            "and the next sweep resumes it)"
        )
    if executor == "ray":
        given = address is not None
        check_ray_address(
            address if given else os.environ.get("RAY_ADDRESS"),
            name="--address" if given else "RAY_ADDRESS",
        )
    params = read_params(DEFAULT_PARAMS)  # bad params end here, before anything runs
    runs = train_runs(params)
    # A folder given for the logs is checked as every output is (new, empty or an earlier
    # sweep's), and marked; the default is inside DVC's own scratch folder, where no user's file
    # is, whether or not it is given by name.
    chosen = place(logs) != place(LOGS)
    try:
        if chosen:
            check_outputs((logs, LOGS_KIND))
        elif problem := unwritable(logs, directory=True):
            raise BadInput(problem)
    except BadInput as error:
        raise BadInput(f"--logs {error.format_message()}") from None

    with pipeline_repo() as repo, repo_lock(repo):  # a damaged dvc.yaml or dvc.lock ends here
        waves = in_waves(repo, collect_stages(repo, targets))
        stale, downstream = out_of_date(repo, waves)
        count = sum(map(len, waves))
        click.echo(f"sweep: {len(stale)} of {count} stages out of date", err=True)
        if not stale:
            return
        if chosen:
            try:
                claim(logs, LOGS_KIND, LOGS_OWN)
            except NotOurs as error:  # a file put there since the check above
                raise BadInput(f"--logs {error}") from None
            except OSError as error:  # a full disk: its mark not written
                raise Failed(f"--logs {logs}: {error.strerror or error}") from None
        sweeping = _Sweep(repo, params, runs, logs, downstream, Tally(len(stale)))
        runner = _executor(executor, jobs, address, cpus_per_run, retries)
        workers = jobs or (os.cpu_count() if executor == "local" else None)
        with sweeping.tally.watch():
            for wave in waves:
                sweeping.run_wave(
                    [stage for stage in wave if stage.addressing in stale],
                    runner,
                    group_size,
                    workers,
                )

    failed = sweeping.failed
    click.echo(f"sweep: {len(stale) - len(failed)} recorded, {len(failed)} failed", err=True)
    if failed:
        click.echo(
            "failed (run `ede-pipeline sweep` again to resume them): " + " ".join(failed), err=True
        )
        ctx.exit(1)


class _Sweep:
    """The sweep's state as its waves run: the progress, and the stages that failed (or could not
    run, since one they depend on failed)."""

    def __init__(
        self,
        repo: Repo,
        params: Params,
        runs: dict[str, RunId],
        logs: Path,
        downstream: set[str],
        tally: Tally,
    ) -> None:
        self.repo, self.params, self.runs, self.logs = repo, params, runs, logs
        self.downstream, self.tally = downstream, tally  # (downstream: out_of_date's)
        self.failed: list[str] = []

    def run_wave(
        self, stages: list[Stage], runner: Executor, group_size: int | None, workers: int | None
    ) -> None:
        """Run a wave's out-of-date stages side by side and record each as it finishes. A stage
        downstream of others that ran is first asked whether it is out of date, as ``dvc repro``
        asks at its turn; a stage is restored from the run cache where DVC has this very run."""
        from dvc.exceptions import DvcException

        tally, pending = self.tally, []
        for stage in stages:
            name = stage.addressing
            if broken := [
                dep.addressing
                for dep in dependencies(self.repo, stage)
                if dep.addressing in self.failed
            ]:
                self.failed.append(name)
                tally.echo(tally.line("FAILED", name, f"not run: {broken[0]} failed"))
                continue
            try:
                if name in self.downstream and not stage.changed():
                    tally.echo(tally.line("ok", name, "up to date: its inputs came out as before"))
                    continue
                stage.remove_outs(ignore_remove=False, force=False)
                if restore_from_run_cache(stage):
                    record(stage)
                    tally.echo(tally.line("cached", name, "restored from the run cache"))
                    continue
                stage.save_deps()
            except (DvcException, OSError) as error:  # this stage only; the others go on
                self.failed.append(name)
                tally.echo(
                    tally.line("FAILED", name, f"not started: {type(error).__name__}: {error}")
                )
                continue
            log = (Path(self.repo.root_dir) / self.logs / f"{_safe(name)}.log").resolve()
            run = self.runs.get(name)
            pending.append(
                Job(
                    name,
                    stage_argvs(stage),
                    self.repo.root_dir,
                    stage_env(stage),
                    str(log),
                    runs=(run,) if run else (),
                )
            )
        if not pending:
            return
        size = group_size or default_group_size(self.params, len(pending), workers)
        pending = seed_by_seed(group_jobs(pending, size))
        logs_of = {job.stage: Path(job.log) for job in pending}
        for job in pending:
            # An earlier sweep's; where it cannot be removed (the logs folder replaced by a file,
            # say), the job cannot write it either, and fails saying so (run_job).
            with contextlib.suppress(OSError):
                attempts_file(job).unlink(missing_ok=True)
        by_name = {stage.addressing: stage for stage in stages}
        tally.track(pending, self.params.runs.budgets)
        for outcome in runner.map_unordered(pending):
            _report(outcome, by_name, logs_of[outcome.stage], tally, self.failed)


def _report(
    outcome: Outcome, by_name: dict[str, Stage], log: Path, tally: Tally, failed: list[str]
) -> None:
    """Record each run of a finished job, or say why not; a line per run."""
    from dvc.exceptions import DvcException

    members = outcome.stage.split(" + ")
    for name in members:
        why = problem(outcome)
        if not why:
            try:
                record(by_name[name])
            except (DvcException, OSError) as error:  # reported with the run
                why = f"not recorded: {type(error).__name__}: {error}"
        if why:
            failed.append(name)
            tally.echo(tally.line("FAILED", name, f"{why}; log: {log}", outcome.stage))
        else:
            shared = f" (one process for {len(members)})" if len(members) > 1 else ""
            lost = outcome.attempts - 1
            again = (
                f" (attempt {outcome.attempts}: {lost} lost with a Ray worker or node)"
                if lost
                else ""
            )
            tally.echo(
                tally.line("ok", name, f"{outcome.seconds:.1f}s{shared}{again}", outcome.stage)
            )
    if problem(outcome) and (tail := _tail(log)):
        tally.echo(tail)


def _executor(
    kind: str, jobs: int | None, address: str | None, cpus_per_run: float, retries: int
) -> Executor:
    if kind == "local":
        return LocalExecutor(jobs or os.cpu_count() or 1)
    return RayExecutor(address, cpus_per_run, jobs, retries)


def _tail(log: Path) -> str:
    """The log's last lines, indented ("" where there is no log to read: the logs folder
    removed, say); bytes that are not UTF-8 text (a command's binary output) shown as �."""
    try:
        text = log.read_text(errors="replace")
    except OSError:
        return ""
    lines = text.rstrip().splitlines()[-TAIL:]
    return "\n".join(f"    | {line}" for line in lines)


def _safe(name: str) -> str:
    return name.replace("/", "_").replace("@", "__")
