"""One writer per output: an exclusive lock beside it, released by the OS when its holder dies.

Every stage holds :func:`exclusive` on each of its outputs, folders and files alike, while it
writes them, so that two processes given the same output (two ``train`` of one run, a rerun
started while the first still runs, two ``report`` given one ``--metrics``) cannot interleave: the second is refused at once, naming the holder's PID, and touches nothing. The lock
is ``flock`` on a hidden file beside the output (``.<name>.lock``); the kernel drops it when the
process exits however it exits, so a killed stage never leaves a lock that blocks its rerun. The
file is removed on release; a process that opened it just before is detected (the path no longer
names the file it locked) and takes the new one.
"""

from __future__ import annotations

import fcntl
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from ede.io.atomic import place

__all__ = ["OutputBusy", "exclusive", "lock_path"]


class OutputBusy(Exception):
    """Another live process is writing this output."""

    def __init__(self, output: Path, holder: int | None, shown: str | None = None) -> None:
        self.output, self.holder = output, holder
        who = f"process {holder}" if holder else "another process"
        super().__init__(
            f"{shown or output}: being written by {who} (lock {lock_path(output)}); wait for it "
            "to finish, or stop it, and run again"
        )


def lock_path(output: Path) -> Path:
    """The lock of the place ``output`` names (every symbolic link followed: two names of one
    place share it)."""
    real = place(output)
    return real.with_name(f".{real.name}.lock")


def _holder(fd: int) -> int | None:
    try:
        text = os.pread(fd, 32, 0).decode().strip()
        return int(text) if text else None
    except (OSError, ValueError):
        return None


@contextmanager
def exclusive(output: str | Path, shown: str | None = None) -> Iterator[None]:
    """Hold the lock of ``output`` for the block; :class:`OutputBusy` if another process does
    (naming the output as ``shown``, e.g. the variable that named it, where given)."""
    output = Path(output)
    lock = lock_path(output)
    lock.parent.mkdir(parents=True, exist_ok=True)
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd)
            os.close(fd)
            raise OutputBusy(output, holder, shown) from None
        try:
            current = os.stat(lock).st_ino
        except FileNotFoundError:
            current = None
        if current == os.fstat(fd).st_ino:
            break
        os.close(fd)  # its holder released and removed it meanwhile: take the new file
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    try:
        yield
    finally:
        try:
            os.unlink(lock)
        except FileNotFoundError:
            pass
        os.close(fd)
