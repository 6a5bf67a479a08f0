"""Progress for long stages: a live bar on a terminal, a few plain lines in a log, and — for a
sweep watching many stages — a small file with the counts.

``EDE_PROGRESS=<path>`` in the environment makes :func:`progress` also keep ``<path>`` up to date
(atomically, at most once a second, and when it ends) with ``{"done": n, "total": N, "start": s}``
(``s``: what a resumed run had done before it started, 0 for a stage that starts afresh);
``ede-pipeline sweep`` sets it for each run it starts and reads it back (:func:`read_progress`) to
show one line for the whole sweep.

The file is an output like any other (:func:`ede_pipeline.common.check_outputs` holds it to the
same rule before any work): while a stage publishes it holds the file's lock (``.<name>.lock``
beside it, gone when it ends) and marks it as a progress writer's (``.<name>.ede-output.json``
beside it, :func:`ede.io.atomic.writing_files`), so that a later stage may replace it and nothing
replaces a file it did not write.
"""

from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import click
from tqdm import tqdm

from ede.io.atomic import write_json, writing_files
from ede.io.locks import exclusive

LOG_EVERY = 0.1  # fraction of the total between two log lines when stderr is not a terminal
PROGRESS_ENV = "EDE_PROGRESS"
PROGRESS_KIND = (
    "progress"  # what a progress file's mark says wrote it (ede.io.atomic.writing_files)
)
PUBLISH_EVERY = 1.0  # seconds between two writes of the progress file


@contextmanager
def progress(
    total: int, desc: str, unit: str = "step", resumable: bool = False
) -> Iterator[Callable[[int], None]]:
    """Yield ``advance(n)``: a tqdm bar when stderr is a TTY, else a line per 10% done. A
    ``resumable`` stage's first ``advance`` is what it had done before it started (the progress
    file's ``start``; 0 for any other stage)."""
    with _publisher(total, resumable) as publish:
        if sys.stderr.isatty():
            with tqdm(
                total=total, desc=desc, unit=unit, unit_scale=True, dynamic_ncols=True
            ) as bar:

                def advance_bar(n: int) -> None:
                    bar.update(n)
                    publish(bar.n)

                yield advance_bar
            publish(bar.n, final=True)
            return
        start = time.perf_counter()
        done = 0
        next_report = LOG_EVERY

        def advance(n: int) -> None:
            nonlocal done, next_report
            done += n
            publish(done)
            if done >= next_report * total or done >= total:
                elapsed = time.perf_counter() - start
                click.echo(f"{desc}: {done}/{total} {unit}s ({elapsed:.1f}s)", err=True)
                while next_report * total <= done:
                    next_report += LOG_EVERY

        yield advance
        publish(done, final=True)


@contextmanager
def _publisher(total: int, resumable: bool) -> Iterator[Callable[..., None]]:
    """Yield ``publish(done, final=False)``: the progress file's update, if ``EDE_PROGRESS``
    names one, its lock held and its mark kept for the block.

    Raises:
        OutputBusy: another process publishes to the same file.
    """
    path = os.environ.get(PROGRESS_ENV)
    last = -PUBLISH_EVERY
    start = None if resumable else 0  # None: the first count, what it had done before

    def publish(done: int, final: bool = False) -> None:
        nonlocal last, start, path
        start = done if start is None else start
        now = time.monotonic()
        if path and (final or now - last >= PUBLISH_EVERY):
            last = now
            try:
                write_json(path, {"done": done, "total": total, "start": start})
            except OSError as error:  # a full disk: the file is for display, the stage goes on
                click.echo(f"{PROGRESS_ENV}={path}: no longer kept up to date ({error})", err=True)
                path = None

    if not path:
        yield publish
        return
    with (
        exclusive(path, shown=f"{PROGRESS_ENV}={path}"),
        writing_files([(Path(path), PROGRESS_KIND)]),
    ):
        yield publish


def read_progress(path: Path) -> tuple[int, int, int] | None:
    """(done, total, start) from a progress file; None while there is none (or it cannot be
    read)."""
    try:
        counts = json.loads(path.read_text())
        return int(counts["done"]), int(counts["total"]), int(counts["start"])
    # OverflowError: int() of an infinite count; RecursionError: JSON nested past the limit.
    except (OSError, ValueError, KeyError, TypeError, OverflowError, RecursionError):
        return None
