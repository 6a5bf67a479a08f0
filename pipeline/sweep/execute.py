"""How a sweep runs its jobs: each job's commands in a child process, its output to its log, on
this machine (:class:`LocalExecutor`) or as Ray tasks (:mod:`ede_pipeline.sweep.on_ray`), both
behind one interface (:class:`Executor`): submit jobs, get their outcomes as they finish."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from ede_pipeline.common import PARENT_ENV
from ede_pipeline.progress import PROGRESS_ENV
from ede_pipeline.sweep.plan import Job


@dataclass(frozen=True)
class Outcome:
    stage: str
    returncode: int | None  # None: no exit status (``error`` says why)
    seconds: float
    error: str = ""
    attempts: int = 1  # the job's starts: more than one after a lost Ray worker or node
    lost: bool = True  # with no exit status: lost by the executor, or (False) could not run


def run_job(job: Job, where: str = "") -> Outcome:
    """Run a job's commands one after the other, output to its log; stop at the first failure.

    Each start is an attempt, counted in :func:`attempts_file`: Ray starts a job again when its
    worker or node is lost. A first attempt starts the log afresh; a later one adds to it, under
    a line saying which attempt it is and ``where`` it runs. A job that cannot be run (its log
    cannot be written: the logs folder removed or full; the shell missing) has no exit status,
    and the error says why: the job's failure, reported as any other.

    Module-level and free of DVC so that a Ray worker can import and run it.
    """
    start = time.perf_counter()
    env = {**os.environ, **job.env}
    # The interpreter's own scripts first: `ede-pipeline` and `dvc` of the environment running this.
    bin_dir = str(Path(sys.executable).parent)
    env["PATH"] = os.pathsep.join([bin_dir, env.get("PATH", "")])
    env[PROGRESS_ENV] = str(progress_file(job))  # the sweep's overall line reads it
    env[PARENT_ENV] = str(os.getpid())  # the run ends with this process (follow_parent)
    log_path = Path(job.log)
    attempt, returncode = 1, 0
    try:
        progress_file(job).unlink(missing_ok=True)  # an earlier sweep's, or the lost attempt's
        log_path.parent.mkdir(parents=True, exist_ok=True)
        attempt = _start_attempt(job, where)
        with log_path.open("w" if attempt == 1 else "a") as log:
            if where or attempt > 1:
                log.write(f"# attempt {attempt}{f' on {where}' if where else ''}\n")
            for argv in job.argvs:
                log.write(f"$ {' '.join(argv)}\n")
                log.flush()
                returncode = subprocess.run(
                    argv, cwd=job.cwd, env=env, stdout=log, stderr=subprocess.STDOUT, check=False
                ).returncode
                if returncode != 0:
                    break
    except OSError as error:
        named = f"{error.filename}: " if error.filename else ""
        return Outcome(
            job.stage,
            None,
            time.perf_counter() - start,
            error=f"{named}{error.strerror or error}",
            attempts=attempt,
            lost=False,
        )
    return Outcome(job.stage, returncode, time.perf_counter() - start, attempts=attempt)


def attempts_file(job: Job) -> Path:
    """Where each start of a job adds a line, beside its log.

    Only the job sees that Ray started it again (the task's result says nothing of the lost
    attempts, and Ray's state API needs its dashboard): a file on the shared filesystem, like the
    log, is counted by the sweep wherever the attempts ran. The sweep removes an earlier sweep's
    before it starts the job; the attempts of one job never run at once.
    """
    return Path(job.log).with_suffix(".attempts")


def _start_attempt(job: Job, where: str) -> int:
    """Count a start of the job; its number (1 for the first)."""
    with attempts_file(job).open("a") as file:
        file.write(f"{where or socket.gethostname()}\n")
    return attempts(job)


def attempts(job: Job) -> int:
    """How many times the job has started in this sweep (0: not yet)."""
    try:
        return len(attempts_file(job).read_bytes().splitlines())
    except OSError:  # none yet; or the logs folder removed, or something else in its place
        return 0


def progress_file(job: Job) -> Path:
    """Where the job's command publishes its step counts (``EDE_PROGRESS``)."""
    return Path(job.log).with_suffix(".progress")


def problem(outcome: Outcome) -> str:
    """What went wrong with a job, in words ("" if nothing did)."""
    if outcome.returncode is None and not outcome.lost:
        return f"could not run ({outcome.error})"
    if outcome.returncode is None:
        tries = f" in each of {outcome.attempts} attempts" if outcome.attempts > 1 else ""
        return f"lost{tries} after {outcome.seconds:.1f}s ({outcome.error})"
    if outcome.returncode < 0:
        return f"killed by signal {-outcome.returncode} after {outcome.seconds:.1f}s"
    if outcome.returncode > 0:
        return f"exit {outcome.returncode} after {outcome.seconds:.1f}s"
    return ""


# ---------------------------------------------------------------------------------------------
# Executors: submit jobs, hand back outcomes as they finish.


class Executor(Protocol):
    def map_unordered(self, jobs: list[Job]) -> Iterator[Outcome]:
        """Run the jobs, at most as many at once as the executor allows; each outcome as its
        job finishes."""
        ...


class LocalExecutor:
    """At most ``jobs`` child processes at once, on this machine."""

    def __init__(self, jobs: int) -> None:
        self.jobs = jobs

    def map_unordered(self, jobs: list[Job]) -> Iterator[Outcome]:
        pool = ThreadPoolExecutor(max_workers=self.jobs)  # one a call: the sweep's waves
        pending: set[Future[Outcome]] = {pool.submit(run_job, job) for job in jobs}
        try:
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                yield from (future.result() for future in done)
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
