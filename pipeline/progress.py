"""Progress for long stages: a live bar on a terminal, a few plain lines in a log."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import click
from tqdm import tqdm

LOG_EVERY = 0.1  # fraction of the total between two log lines when stderr is not a terminal


@contextmanager
def progress(total: int, desc: str, unit: str = "step") -> Iterator[Callable[[int], None]]:
    """Yield ``advance(n)``: a tqdm bar when stderr is a TTY, else a line per 10% done."""
    if sys.stderr.isatty():
        with tqdm(total=total, desc=desc, unit=unit, unit_scale=True, dynamic_ncols=True) as bar:
            yield bar.update
        return
    start = time.perf_counter()
    done = 0
    next_report = LOG_EVERY

    def advance(n: int) -> None:
        nonlocal done, next_report
        done += n
        if done >= next_report * total or done >= total:
            elapsed = time.perf_counter() - start
            click.echo(f"{desc}: {done}/{total} {unit}s ({elapsed:.1f}s)", err=True)
            while next_report * total <= done:
                next_report += LOG_EVERY

    yield advance
