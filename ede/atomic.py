"""Outputs that appear whole or not at all: write under a temporary name, rename when complete."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["remove_stale_temporaries", "sha256", "write_atomically", "write_json", "write_text"]


def write_atomically(path: str | Path, write: Callable[[Path], None]) -> None:
    """Call ``write(tmp)`` on a fresh sibling directory and rename it onto ``path`` when it returns.

    A writer killed midway leaves only ``<path>.tmp-<pid>``, which nothing reads and the next
    write to ``path`` removes once that process is gone (a live writer's temporary is left alone);
    an old ``path`` is replaced only by a complete new one.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
    tmp.mkdir()
    try:
        write(tmp)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if path.exists():
        shutil.rmtree(path)
    os.replace(tmp, path)


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return False  # this process's own leftover
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # another user's live process
    return True


def remove_stale_temporaries(path: Path) -> None:
    """Remove ``<path>.tmp-<pid>`` siblings whose writer is no longer running."""
    for stale in path.parent.glob(f"{path.name}.tmp-*"):
        pid = stale.name.rpartition("-")[2]
        if pid.isdigit() and _alive(int(pid)):
            continue
        if stale.is_dir():
            shutil.rmtree(stale, ignore_errors=True)
        else:
            stale.unlink(missing_ok=True)


def sha256(path: str | Path) -> str:
    """The SHA-256 of a file's bytes, read in blocks (checkpoints hold whole replay buffers)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def write_text(path: str | Path, text: str) -> None:
    """Write a file atomically (temporary file, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)


def write_json(path: str | Path, data: Any) -> None:
    """Write JSON atomically."""
    write_text(path, json.dumps(data, indent=2, allow_nan=False) + "\n")


def unwritable(path: str | Path, directory: bool) -> str | None:
    """Why ``path`` cannot be written as a stage writes it, or None where it can.

    ``path`` is a directory (``directory``) or a file, written through a temporary beside it,
    with a lock file beside it too: nothing may be in its way (a file where a directory goes, a
    directory where a file goes, a file among its parents), and the nearest existing parent must
    take a new file with data (a read-only or full location cannot). Creates nothing it leaves.
    """
    path = Path(path)
    if directory and path.exists() and not path.is_dir():
        return f"{path}: a file is in the way; expected a directory there, or nothing"
    if not directory and path.is_dir():
        return f"{path}: a directory is in the way; expected a file there, or nothing"
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        return f"{path}: cannot be created: {parent} is a file, not a directory"
    try:
        fd, probe = tempfile.mkstemp(dir=parent, prefix=".ede-probe-")
    except OSError as error:
        return f"{path}: cannot be written: {parent} does not take new files ({error.strerror})"
    try:
        os.write(fd, bytes(4096))
        os.fsync(fd)
    except OSError as error:
        return f"{path}: cannot be written: {parent} does not take data ({error.strerror})"
    finally:
        os.close(fd)
        os.unlink(probe)
    return None
