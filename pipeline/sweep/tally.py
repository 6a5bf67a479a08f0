"""The sweep's progress: a line per finished stage and one overall line (stages, retries, steps,
rate, ETA), from the step counts the runs publish (``EDE_PROGRESS``)."""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import click
from tqdm import tqdm

from ede_pipeline.progress import read_progress
from ede_pipeline.sweep.execute import attempts, progress_file
from ede_pipeline.sweep.plan import Job


def _duration(seconds: float) -> str:
    seconds = round(seconds)
    hours, rest = divmod(seconds, 3600)
    return (
        f"{hours}h{rest // 60:02d}m{rest % 60:02d}s" if hours else f"{rest // 60}m{rest % 60:02d}s"
    )


def job_steps(job: Job, budgets: dict[str, int]) -> int:
    """The environment steps a train job runs: its runs' budgets (0: not a train job)."""
    return sum(budgets.get(run.task, 0) for run in job.runs)


class Tally:
    """The sweep's progress: a line per finished stage, and one overall line — stages finished,
    retries (jobs started again after a lost Ray worker or node), environment steps done of all,
    the aggregate rate and an ETA — live at the bottom of a terminal (``watch``), or printed at
    every tenth of the steps in a log.

    Steps come from the runs' progress files (``EDE_PROGRESS``); the steps a resumed run had
    already done (the file's ``start``) count as done but not towards the rate. Without step
    counts (stages other than train) the ETA is from the pace of finished stages.

    Two threads use a tally: the sweep's, which tracks each wave's jobs and reports each stage as
    it finishes, and :meth:`watch`'s, which reads the counts every :data:`POLL` seconds. Every
    method that reads or changes the tally's state holds ``lock`` throughout (a dictionary read
    while the other thread adds to it is an error); it is re-entrant, since these methods call
    one another.
    """

    POLL = 2.0  # seconds between two reads of the progress files

    def __init__(self, total: int) -> None:
        self.total, self.done, self.start = total, 0, time.perf_counter()
        self.jobs: dict[str, Job] = {}
        self.steps: dict[str, int] = {}
        self.finished: set[str] = set()
        self.resumed: dict[str, int] = {}  # per job: the steps done before it started
        self.lock = threading.RLock()
        self.bar: tqdm | None = None
        self.next_line = 0.1

    def track(self, jobs: list[Job], budgets: dict[str, int]) -> None:
        """Count the steps of these jobs too (``budgets``: the environment steps of a run per
        task); the sweep tracks each wave's as it starts."""
        with self.lock:
            self.steps.update((job.stage, job_steps(job, budgets)) for job in jobs)
            self.jobs.update((job.stage, job) for job in jobs)

    # The counts --------------------------------------------------------------------------

    def _counts(self) -> tuple[int, int, int]:
        """(steps done, steps in all, steps done before this sweep) over the jobs."""
        done = total = before = 0
        with self.lock:
            for name, job in self.jobs.items():
                if not self.steps[name]:  # not a run: its progress (epochs, say) is not in steps
                    continue
                read = None if name in self.finished else _read_progress(job)
                steps = read[1] if read else self.steps[name]
                if read:
                    self.resumed[name] = read[2]
                total += steps
                done += steps if name in self.finished else (read[0] if read else 0)
                before += self.resumed.get(name, 0)
        return done, total, before

    def _eta(self, elapsed: float, counts: tuple[int, int, int]) -> str:  # the lock held
        done, total, before = counts
        if total and done > before:
            rate = (done - before) / elapsed
            return f"ETA {_duration((total - done) / rate)}" if total > done else "done"
        left = self.total - self.done
        if not left:
            return "done"
        return f"ETA {_duration(elapsed / self.done * left)}" if self.done else "ETA unknown"

    def retries(self) -> int:
        """The jobs' starts after their first: each a job lost with its Ray worker or node."""
        with self.lock:
            return sum(max(attempts(job) - 1, 0) for job in self.jobs.values())

    def overall(self) -> str:
        """The one line: stages, retries (if any), steps, rate, ETA."""
        with self.lock:
            elapsed = max(time.perf_counter() - self.start, 1e-9)
            counts = done, total, before = self._counts()
            retries = self.retries()
            again = f", {retries} {'retry' if retries == 1 else 'retries'}" if retries else ""
            steps = ""
            if total:
                rate = (done - before) / elapsed
                steps = (
                    f", {_count(done)}/{_count(total)} steps ({done / total:.0%}), "
                    f"{rate:,.0f} steps/s"
                )
            return (
                f"sweep: {self.done}/{self.total} stages{again}{steps}, "
                f"elapsed {_duration(elapsed)}, {self._eta(elapsed, counts)}"
            )

    # Output ------------------------------------------------------------------------------

    def line(self, status: str, stage: str, detail: str, job: str | None = None) -> str:
        """A finished stage's line (``job``: the job it was part of, when all of it is over)."""
        with self.lock:
            self.done += 1
            if job is not None:
                self.finished.add(job)
            elapsed = time.perf_counter() - self.start
            return (
                f"[{self.done}/{self.total}] {status:<6} {stage}  {detail}  "
                f"(elapsed {_duration(elapsed)}, {self._eta(elapsed, self._counts())})"
            )

    def echo(self, text: str) -> None:
        with self.lock:
            if self.bar is not None:
                self.bar.write(text)
            else:
                click.echo(text)

    def tick(self) -> None:
        """Refresh the overall line (terminal), or print it at each further tenth (log)."""
        with self.lock:
            text = self.overall()
            if self.bar is not None:
                self.bar.set_description_str(text, refresh=True)
                return
            done, total, _ = self._counts()
            if total and done >= self.next_line * total:
                click.echo(text, err=True)
                while self.next_line * total <= done:
                    self.next_line += 0.1

    @contextmanager
    def watch(self) -> Iterator[None]:
        """Keep the overall line up to date while the stages run. An error in keeping it (a bug:
        what it reads is checked) ends the line with one line saying so, never the sweep."""
        stop = threading.Event()
        if sys.stderr.isatty():
            self.bar = tqdm(total=0, bar_format="{desc}", file=sys.stderr, dynamic_ncols=True)

        def loop() -> None:
            while not stop.wait(self.POLL):
                try:
                    self.tick()
                except Exception as error:  # any: the stages run on regardless
                    self.echo(
                        f"sweep: the overall line stops here ({type(error).__name__}: "
                        f"{error}); the stages run on, each reported as it ends"
                    )
                    return

        thread = threading.Thread(target=loop, name="sweep-progress", daemon=True)
        thread.start()
        try:
            yield
        finally:
            stop.set()
            thread.join()
            if self.bar is not None:
                self.bar.close()
                self.bar = None
            click.echo(self.overall(), err=True)


def _read_progress(job: Job) -> tuple[int, int, int] | None:
    """A running job's (done, total, start) from its progress file; None while there is none,
    and where the file holds no counts that make sense (``0 <= start <= done <= total``, finite:
    a file damaged by hand, say), so that the overall line goes on without them."""
    read = read_progress(progress_file(job))
    if read is None or not 0 <= read[2] <= read[0] <= read[1]:
        return None
    return read


def _count(steps: int) -> str:
    for size, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if steps >= size:
            return f"{steps / size:.3g}{suffix}"
    return str(steps)
