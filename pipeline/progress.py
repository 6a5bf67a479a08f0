"""Progress for long stages: a live bar on a terminal, a few plain lines in a log, and — for a
sweep watching many stages — a small file with the counts.

``EDE_PROGRESS=<path>`` in the environment makes :func:`progress` also keep ``<path>`` up to date
(atomically, at most once a second, and when it ends) with ``{"done": n, "total": N, "start": s}``
(``s``: what a resumed run had done before it started, 0 for a stage that starts afresh);
``ede-pipeline sweep`` sets it for each run it starts and reads it back (:func:`read_progress`) to
show one line for the whole sweep.
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

from ede.atomic import write_json

LOG_EVERY = 0.1  # fraction of the total between two log lines when stderr is not a terminal
PROGRESS_ENV = "EDE_PROGRESS"
PUBLISH_EVERY = 1.0  # seconds between two writes of the progress file


@contextmanager
def progress(
    total: int, desc: str, unit: str = "step", resumable: bool = False
) -> Iterator[Callable[[int], None]]:
    """Yield ``advance(n)``: a tqdm bar when stderr is a TTY, else a line per 10% done. A
    ``resumable`` stage's first ``advance`` is what it had done before it started (the progress
    file's ``start``; 0 for any other stage)."""
    publish = _publisher(total, resumable)
    if sys.stderr.isatty():
        with tqdm(total=total, desc=desc, unit=unit, unit_scale=True, dynamic_ncols=True) as bar:

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


def _publisher(total: int, resumable: bool) -> Callable[..., None]:
    """``publish(done, final=False)``: the progress file's update, if ``EDE_PROGRESS`` names one."""
    path = os.environ.get(PROGRESS_ENV)
    last = -PUBLISH_EVERY
    start = None if resumable else 0  # None: the first count, what it had done before

    def publish(done: int, final: bool = False) -> None:
        nonlocal last, start
        start = done if start is None else start
        now = time.monotonic()
        if path and (final or now - last >= PUBLISH_EVERY):
            last = now
            write_json(path, {"done": done, "total": total, "start": start})

    return publish


def read_progress(path: Path) -> tuple[int, int, int] | None:
    """(done, total, start) from a progress file; None while there is none (or it cannot be
    read)."""
    try:
        counts = json.loads(path.read_text())
        return int(counts["done"]), int(counts["total"]), int(counts["start"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
