"""Outputs that appear whole or not at all: write under a temporary name, rename when complete."""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import tempfile
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from fnmatch import fnmatchcase
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import torch

__all__ = [
    "MARK",
    "NotOurs",
    "NotWritten",
    "claim",
    "file_problem",
    "mark_file",
    "ownership_problem",
    "place",
    "remove_stale_temporaries",
    "save_tensors",
    "sha256",
    "write_atomically",
    "write_json",
    "write_text",
    "writing_files",
]

# Every folder a stage writes holds this file: what wrote it (its ``kind``) and the names of the
# entries it owns (fnmatch patterns). A stage replaces or writes into an existing folder only where
# that folder is empty or is its own kind's, holding nothing but what the mark owns: a folder of a
# user's files, another stage's output, or a folder with a user's file added is never deleted.
# A file a stage writes outside such a folder (a metrics JSON) has its mark beside it,
# ``.<name>.ede-output.json``: its kind and the SHA-256 of the bytes written, so that the file is
# replaced only while it is what that stage wrote (:func:`file_problem`).
MARK = ".ede-output.json"
# The longest name a temporary or lock adds to an output's: ``.tmp-<pid>`` (PIDs reach 4194304),
# ``.<name>.lock``, ``.<name>.ede-output.json``.
NAME_ROOM = len(".ede-output.json") + 1


def place(path: str | Path) -> Path:
    """The place ``path`` names, every symbolic link in it followed: a stage writes there, so
    that a link to a folder is written through, never replaced or deleted, and two names of
    one place are one output (one lock)."""
    return Path(os.path.realpath(path))


class NotOurs(ValueError):
    """A folder a writer would replace or write into that it did not recognisably write."""


class NotWritten(OSError):
    """An output that could not be written whole (a full disk, a quota, ...): its temporary is
    removed and what was at its place before is left as it was. ``reason``: the system's word."""

    def __init__(self, path: Path, error: OSError) -> None:
        self.reason = str(error.strerror or error)
        super().__init__(
            error.errno,
            f"{path}: not written ({self.reason}); nothing of it is "
            "left, and what was there before is as it was",
        )


def ownership_problem(path: str | Path, kind: str) -> str | None:
    """Why a writer of ``kind`` may not replace or write into the folder ``path``; None where it
    may (nothing there, an empty folder, or its own kind's folder holding only what it owns)."""
    path = Path(path)
    if not path.is_dir():
        return None
    entries = sorted(entry.name for entry in path.iterdir())
    if not entries:
        return None
    mark = _read_mark(path)
    if mark is None:
        return (
            f"{path}: holds {_listed(entries)}, which no ede stage wrote there; expected a new "
            f"or empty folder, or {_a(kind)} written before: move them, or choose another place"
        )
    if mark["kind"] != kind:
        return (
            f"{path}: holds {_a(mark['kind'])}, not {_a(kind)}; choose another place (a stage "
            "replaces only its own kind of output)"
        )
    foreign = [
        name
        for name in entries
        if name != MARK and not any(fnmatchcase(name, own) for own in mark["owns"])
    ]
    if foreign:
        return (
            f"{path}: holds {_listed(foreign)} beside the {kind} written there; move "
            f"{'it' if len(foreign) == 1 else 'them'} out first"
        )
    return None


def _file_mark(path: Path) -> Path:
    return path.with_name(f".{path.name}{MARK}")


def file_problem(path: str | Path, kind: str) -> str | None:
    """Why a writer of ``kind`` may not replace the file ``path``; None where it may: nothing
    there, or the very file a writer of ``kind`` wrote (its mark names the kind, and the bytes
    are those it wrote: a file edited since, or put there by hand, is kept). A file that another
    live writer of ``kind`` is writing is said to be, naming its PID."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        mark = json.loads(_file_mark(place(path)).read_text())
        writing = mark["kind"] == kind and mark["sha256"] is None
        if writing and _alive(writer := int(mark["writer"])):
            return (
                f"{path}: being written by process {writer}; wait for it to finish, or stop "
                "it, and run again"
            )
        # (a writer of this kind that stopped midway left its own or its forerunner's file)
        ours = writing or (mark["kind"] == kind and mark["sha256"] == sha256(path))
    except (OSError, ValueError, KeyError, TypeError):
        ours = False
    if ours:
        return None
    return (
        f"{path}: a file {_a(kind)} writer did not write there, or one changed since; expected "
        "a new path or that writer's own file: move it, or choose another place"
    )


def mark_file(path: str | Path, kind: str, writing: bool = False) -> None:
    """Record that a writer of ``kind`` wrote the file ``path`` as it is now
    (:func:`file_problem`); with ``writing``, that this process is about to write it (before it
    does, so that a writer killed between its write and its mark leaves a file still its own)."""
    path = place(path)
    # A written file's mark is its kind and bytes alone: the same file made again marks the same
    # (a committed figure redrawn unchanged leaves its mark unchanged). Only a file being written
    # names its writer, for a rerun to tell a killed writer's leftovers from a live one's.
    if writing:
        mark = {"kind": kind, "sha256": None, "writer": os.getpid()}
    else:
        mark = {"kind": kind, "sha256": sha256(path)}
    write_text(_file_mark(path), json.dumps(mark) + "\n")


@contextmanager
def writing_files(files: Iterable[tuple[Path, str]]) -> Iterator[None]:
    """The block writes ``files`` (each a path and its writer's kind): each is marked as being
    written before (a writer killed between its write and its final mark leaves a file still its
    own, :func:`file_problem`), then, however the block ends, marked as it is, or left with no
    mark where there is no file."""
    files = list(files)
    for path, kind in files:
        mark_file(path, kind, writing=True)
    try:
        yield
    finally:
        for path, kind in files:
            if path.is_file():
                mark_file(path, kind)
            else:
                _file_mark(place(path)).unlink(missing_ok=True)


def _read_mark(folder: Path) -> dict[str, Any] | None:
    try:
        mark = json.loads((folder / MARK).read_text())
    except (OSError, ValueError):
        return None
    if not (
        isinstance(mark, dict)
        and isinstance(mark.get("kind"), str)
        and isinstance(mark.get("owns"), list)
        and all(isinstance(name, str) for name in mark["owns"])
    ):
        return None
    return mark


def _a(kind: str) -> str:
    return f"{'an' if kind[0] in 'aeiou' else 'a'} {kind}"


def _listed(names: list[str]) -> str:
    shown = ", ".join(names[:3])
    return shown + (f" and {len(names) - 3} more" if len(names) > 3 else "")


def _mark(folder: Path, kind: str, owns: Iterable[str]) -> None:
    write_text(folder / MARK, json.dumps({"kind": kind, "owns": sorted(owns)}, indent=2) + "\n")


def claim(path: str | Path, kind: str, owns: Iterable[str]) -> None:
    """Make ``path`` a folder of ``kind`` that its writer fills over time (a training run),
    owning the entries whose names match ``owns``; an existing one must be its own
    (:func:`ownership_problem`).

    Raises:
        NotOurs: naming the folder and what is in it.
    """
    path = place(path)
    if problem := ownership_problem(path, kind):
        raise NotOurs(problem)
    path.mkdir(parents=True, exist_ok=True)
    if _read_mark(path) is None:
        _mark(path, kind, owns)


def write_atomically(path: str | Path, write: Callable[[Path], object], kind: str) -> None:
    """Call ``write(tmp)`` on a fresh sibling directory, mark it as ``kind``'s (:data:`MARK`,
    owning what ``write`` put there) and rename it onto ``path`` when it returns.

    A writer killed midway leaves only ``<path>.tmp-<pid>``, which nothing reads and the next
    write to ``path`` removes once that process is gone (a live writer's temporary is left alone);
    an old ``path`` is replaced only by a complete new one, and only where it is this kind's own
    (:func:`ownership_problem`). A write that fails (a full disk) removes its temporary.

    Raises:
        NotOurs: ``path`` holds what this writer did not write; nothing is touched.
        NotWritten: the write failed with an OSError; the old ``path`` is left as it was.
    """
    given, path = Path(path), place(path)
    if problem := ownership_problem(given, kind):
        raise NotOurs(problem)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
    try:
        tmp.mkdir()
        write(tmp)
        _mark(tmp, kind, (entry.name for entry in tmp.iterdir()))
    except BaseException as error:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(error, OSError) and not isinstance(error, NotWritten):
            raise NotWritten(given, error) from None
        raise
    if path.exists():
        shutil.rmtree(path)
    os.replace(tmp, path)


def save_tensors(tensors: dict[str, torch.Tensor], path: Path) -> None:
    """safetensors' ``save_file``, whose failures to write (a full disk) are OSErrors, as every
    other write's: safetensors reports them as ``SafetensorError: ... (os error N)``."""
    # Imported here: the stages that write no tensors (task-code) need not import torch.
    from safetensors import SafetensorError
    from safetensors.torch import save_file

    try:
        save_file(tensors, path)
    except SafetensorError as error:
        code = re.search(r"os error (\d+)", str(error))
        if code is None:
            raise
        raise OSError(int(code[1]), os.strerror(int(code[1])), str(path)) from None


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
    """Write a file atomically (temporary file, then rename), through a symbolic link to it."""
    given, path = Path(path), place(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
    try:
        tmp.write_text(text)
    except OSError as error:
        tmp.unlink(missing_ok=True)
        raise NotWritten(given, error) from None
    os.replace(tmp, path)


def write_json(path: str | Path, data: Any) -> None:
    """Write JSON atomically."""
    write_text(path, json.dumps(data, indent=2, allow_nan=False) + "\n")


def _too_long(path: Path) -> str | None:
    """Why ``path``'s name, with what a writer adds to it, does not fit the filesystem."""
    real = place(path)
    parent = real.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    try:
        longest = os.pathconf(parent, "PC_NAME_MAX")
    except (OSError, ValueError):
        longest = 255
    for part in real.parts:
        fits = longest - NAME_ROOM if part == real.name else longest
        if len(os.fsencode(part)) > fits:
            shown = part if len(part) <= 40 else f"{part[:20]}…{part[-12:]}"
            return (
                f"{path}: the name {shown!r} is {len(os.fsencode(part))} bytes; at most {fits} "
                f"fit here, with the temporary and lock a stage writes beside it"
            )
    return None


def unwritable(path: str | Path, directory: bool) -> str | None:
    """Why ``path`` cannot be written as a stage writes it, or None where it can.

    ``path`` is a directory (``directory``) or a file, written through a temporary beside it,
    with a lock file beside it too: nothing may be in its way (a file where a directory goes, a
    directory where a file goes, a file among its parents), and the nearest existing parent must
    take a new file with data (a read-only or full location cannot). Creates nothing it leaves.
    """
    path = Path(path)
    if problem := _too_long(path):
        return problem
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
