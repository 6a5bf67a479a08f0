"""What every ``ede-pipeline`` command shares: params loading, bad-input errors, default paths."""

from __future__ import annotations

import functools
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import AbstractContextManager, ExitStack, contextmanager
from pathlib import Path
from typing import Any

import click

from ede.config import Params, ParamsError, load_params
from ede.io.atomic import (
    NotOurs,
    NotWritten,
    file_problem,
    ownership_problem,
    place,
    unwritable,
    writing_files,
)
from ede.io.locks import OutputBusy, exclusive
from ede_pipeline.progress import PROGRESS_ENV, PROGRESS_KIND

DEFAULT_PARAMS = Path("params.yaml")


class Failed(click.ClickException):
    """Work that failed (a run that diverged): ``Error: <line>`` per line, exit code 1, no
    traceback."""

    def show(self, file: Any = None) -> None:
        for line in self.format_message().splitlines():
            click.echo(f"Error: {line}", err=True)


class BadInput(Failed):
    """Input the user must fix: printed as ``Error: <message>``, exit code 2, no traceback."""

    exit_code = 2


def embedding_options(command: Callable[..., Any]) -> Callable[..., Any]:
    """Add ``--encoder DIR`` and ``--decoder DIR``: the family embedding an EDE-TD3 run acts
    through (by default the pipeline's, ``data/families/<family>/embedding/``)."""
    for name in ("decoder", "encoder"):  # click lists them in the other order: encoder first
        command = click.option(
            f"--{name}",
            type=click.Path(path_type=Path),
            help=f"EDE-TD3: the family's {name}  "
            f"[default: data/families/<family>/embedding/{name}]",
        )(command)
    return command


def params_option(command: Callable[..., Any]) -> Callable[..., Any]:
    """Add ``--params FILE`` to a command and hand it the validated :class:`Params`."""

    @click.option(
        "--params",
        "params_path",
        type=click.Path(path_type=Path),  # a directory is refused in one line as it is read
        default=DEFAULT_PARAMS,
        show_default=True,
        help="The parameters file.",
    )
    @functools.wraps(command)
    def wrapper(params_path: Path, **kwargs: Any) -> Any:
        return command(params=read_params(params_path), **kwargs)

    return wrapper


def read_params(path: Path) -> Params:
    try:
        return load_params(path)
    except ParamsError as error:
        raise BadInput(str(error)) from None


def family_option(command: Callable[..., Any]) -> Callable[..., Any]:
    return click.option(
        "--family", required=True, help="A family of params.yaml's `families`, e.g. reacher."
    )(command)


def check_family(params: Params, family: str) -> None:
    if family not in params.families:
        raise BadInput(
            f"--family {family!r}: unknown; params.yaml's families are {', '.join(params.families)}"
        )


Output = tuple[Path | None, str]  # a place a stage writes, and the kind of output it is


def check_outputs(
    output: Output,
    files: tuple[Output, ...] = (),
    dirs: tuple[Output, ...] = (),
    inputs: tuple[Path | None, ...] = (),
) -> None:
    """Before any work, the one rule for every place a stage writes — ``output`` (a folder) with
    its lock and temporaries, the other folders ``dirs`` and files ``files``, each with its
    kind, and the progress file ``EDE_PROGRESS`` names (a file of its own kind) — each taken
    where its symbolic links lead: it can be written (:func:`ede.io.atomic.unwritable`: its name
    fits, nothing in the way, a location that takes data); it is new or this kind's own earlier
    output (a folder holding only what its mark owns, :func:`ede.io.atomic.ownership_problem`; a
    file as its mark records it, :func:`ede.io.atomic.file_problem`), never a user's or another
    stage's; a folder is not the working directory or a folder above it; and none is, holds or
    lies inside one of ``inputs``, the params file, or another of these places.

    Raises:
        BadInput: one line naming the place (the variable, for the progress file) and what is
            in the way.
    """
    sources = [path for path in (*inputs, _params_file()) if path is not None and path.exists()]
    places = [(output, True), *((d, True) for d in dirs), *((f, False) for f in files)]
    written = [where for (where, _), _ in places if where is not None]
    for (where, kind), folder in places:
        if where is None:
            continue
        problem = (
            unwritable(where, folder)
            or (folder and above_working_directory(where))
            or overlap(where, sources)
            or (ownership_problem(where, kind) if folder else file_problem(where, kind))
        )
        if problem:
            raise BadInput(problem)
    for where in written:  # each apart from the others, once each is a place of its own
        if problem := overlap(where, _others(written, where), "output"):
            raise BadInput(problem)
    if progress_file := os.environ.get(PROGRESS_ENV):
        where = Path(progress_file)
        problem = (
            unwritable(where, directory=False)
            or overlap(where, sources)
            or overlap(where, written, "output")
            or file_problem(where, PROGRESS_KIND)
        )
        if problem:
            raise BadInput(f"{PROGRESS_ENV}={problem}")


def _params_file() -> Path:
    """The params file the running command reads (``--params``, or params.yaml)."""
    context = click.get_current_context(silent=True)
    given = context.params.get("params_path") if context is not None else None
    return Path(given or DEFAULT_PARAMS)


def above_working_directory(folder: Path) -> str | None:
    """Why ``folder`` may not be an output: it is the working directory or a folder above it."""
    here, there = Path.cwd().resolve(), folder.resolve()
    if there == here or there in here.parents:
        return (
            f"{folder}: the working directory{' or a folder above it' if there != here else ''}"
            "; expected a folder of the output's own, e.g. one inside it"
        )
    return None


def _others(places: list[Path], one: Path) -> list[Path]:
    """``places`` without the one entry that is ``one`` (another entry naming the same path
    stays: two outputs given one place)."""
    others = list(places)
    others.remove(one)
    return others


def overlap(output: Path, places: Iterable[Path], role: str = "input") -> str | None:
    """Why ``output`` may not be written: it is, holds or lies inside one of ``places``, the
    stage's ``role`` (its inputs, or its other outputs); None where it is apart from them."""
    there = output.resolve()
    for given in places:
        source = given.resolve()
        if there == source or source.is_relative_to(there) or there.is_relative_to(source):
            how = (
                "is"
                if there == source
                else "holds"
                if source.is_relative_to(there)
                else "lies inside"
            )
            return f"{output}: {how} the stage's {role} {given}; expected a place apart from it"
    return None


def _lock(
    places: Iterable[Path | None], enter: Callable[[AbstractContextManager[Any]], Any]
) -> None:
    """Take each place's exclusive lock (:func:`ede.io.locks.exclusive`), handing it to ``enter``
    (which holds it as long as its owner lasts).

    Raises:
        BadInput: another process holds one: one line naming it and its PID.
    """
    for where in places:
        if where is not None:
            try:
                enter(exclusive(where))
            except OutputBusy as error:
                raise BadInput(str(error)) from None


def hold(*places: Path | None) -> None:
    """Each place's lock held until the running command ends: one writer per output for a
    command that writes its outputs at its end, outside a :func:`holding` block. A place the
    command holds already (by another of its names) is held once."""
    context = click.get_current_context()
    held: set[Path] = context.meta.setdefault("ede_pipeline.held", set())
    named = {place(where): where for where in places if where is not None}  # real: as given
    fresh = {real: where for real, where in named.items() if real not in held}
    _lock(fresh.values(), context.with_resource)
    held.update(fresh)


def hold_outputs(
    output: Output,
    files: tuple[Output, ...] = (),
    dirs: tuple[Output, ...] = (),
    inputs: tuple[Path | None, ...] = (),
) -> None:
    """:func:`check_outputs`, then each place's lock held until the running command ends
    (:func:`hold`), for a command that writes its outputs without a :func:`holding` block."""
    check_outputs(output, files, dirs, inputs)
    hold(output[0], *(d for d, _ in dirs), *(f for f, _ in files))


@contextmanager
def holding(
    output: Output,
    files: tuple[Output, ...] = (),
    dirs: tuple[Output, ...] = (),
    inputs: tuple[Path | None, ...] = (),
) -> Iterator[None]:
    """The stage's exclusive lock on each of its outputs — the folder ``output``, the folders
    ``dirs`` and the files ``files`` (:func:`ede.io.locks.exclusive`) — for the block, after
    :func:`check_outputs`, and each file of ``files`` marked as its kind's once the block has
    written it. A place that cannot be written or that holds what the stage did not write,
    and a second process on one of the outputs (or on the progress file), are refused as bad
    input: one line, exit 2, nothing written. A write that fails in the block (a full disk) is
    one line, exit 1, its temporaries removed (:class:`ede.io.atomic.NotWritten`)."""
    check_outputs(output, files, dirs, inputs)
    assert output[0] is not None
    with ExitStack() as held:
        _lock((output[0], *(d for d, _ in dirs), *(f for f, _ in files)), held.enter_context)
        try:
            with writing_files((file, kind) for file, kind in files if file is not None):
                yield
        # What the checks above could not see (a nested folder), or the progress file's lock,
        # taken in the block (ede_pipeline.progress).
        except (NotOurs, OutputBusy) as error:
            raise BadInput(str(error)) from None
        except NotWritten as error:
            raise Failed(error.strerror or str(error)) from None


# A command that starts ede-pipeline commands of its own (the sweep its runs, an experiment its
# sweep) names itself here, and each such child ends when it does (follow_parent).
PARENT_ENV = "EDE_PARENT"
FOLLOW_SECONDS = 1.0  # how often a follower looks for the process it follows


def follow_parent() -> None:
    """End with the process ``EDE_PARENT`` names, however it ends (SIGKILL included), so that
    killing an experiment stops its sweep, and killing a sweep stops its runs (they resume from
    their checkpoints), instead of leaving them running on, holding their outputs' locks.

    The named process need not be this one's parent: DVC starts a stage's command through a
    shell, and ``/bin/sh`` (dash) waits for the command instead of becoming it. So a thread
    looks, once a :data:`FOLLOW_SECONDS`, whether the process is still among this one's
    ancestors; once it is not (it ended, and what it started was handed to init, or its PID
    was taken since), this process gets SIGTERM, as from ``kill``. A process that ended before
    this call is seen at once. Without ``/proc``, only the parent itself is followed.

    The variable names this process's follower only: it is removed here, so that what this
    process starts (DVC's stages, say) does not take it for its own."""
    parent = os.environ.pop(PARENT_ENV, "")
    if not parent.isdigit():
        return
    followed = int(parent)
    if followed not in _ancestors():
        _end()
        return
    threading.Thread(target=_follow, args=(followed,), name="follow-parent", daemon=True).start()


def _follow(followed: int) -> None:
    while followed in _ancestors():
        time.sleep(FOLLOW_SECONDS)
    _end()


def _end() -> None:
    os.kill(os.getpid(), signal.SIGTERM)


def _ancestors() -> Iterator[int]:
    """This process's parent, its parent's parent, and so on up to (not including) init."""
    pid = os.getppid()
    while pid > 1:
        yield pid
        try:
            stat = Path(f"/proc/{pid}/stat").read_text()
        except OSError:  # no /proc here, or the process has just ended
            return
        pid = int(stat.rsplit(")", 1)[1].split()[1])  # after the name: state, then the PPID


# The values of MUJOCO_GL that MuJoCo accepts on Linux, and "disable", which needs no OpenGL.
MUJOCO_GL_VALUES = ("egl", "osmesa", "glfw", "glx", "disable")


def check_mujoco_gl() -> None:
    """An ``MUJOCO_GL`` that MuJoCo cannot start with (a value it does not know, or a backend
    whose libraries this machine lacks) is one line naming the values this machine supports.

    MuJoCo reads the variable when it is first imported and fails there, in every command. Only
    the commands that play videos (``render``, ``report``, ``results``) render, and unset they
    take ``egl``; the others never render, so unset (or ``disable``) always works for them.

    Raises:
        BadInput: naming the variable, its value, why, and the working values.
    """
    value = os.environ.get("MUJOCO_GL")
    if value is None:
        return
    try:
        import mujoco  # noqa: F401 — it reads MUJOCO_GL on import
    except Exception as error:
        reason = (str(error).strip().splitlines() or [type(error).__name__])[-1]
        works = [v for v in MUJOCO_GL_VALUES if _mujoco_starts_with(v)]
        raise BadInput(
            f"MUJOCO_GL={value}: MuJoCo cannot start with it ({reason}); this machine "
            f"supports {', '.join(works) or 'none of ' + ', '.join(MUJOCO_GL_VALUES)}, "
            "or leave it unset (render, report and results then take egl; no other command renders)"
        ) from None


def _mujoco_starts_with(value: str) -> bool:
    environ = {**os.environ, "MUJOCO_GL": value}
    probe = subprocess.run(
        [sys.executable, "-c", "import mujoco"], env=environ, capture_output=True, timeout=60
    )
    return probe.returncode == 0


# The share of the host's available memory a command may fill by its own count of what it holds:
# the rest is for what the count leaves out (Python and its libraries, a few hundred MB).
USABLE_SHARE = 0.8


def available_memory() -> int:
    """The bytes of memory this machine can give without swapping (Linux's MemAvailable)."""
    for line in Path("/proc/meminfo").read_text().splitlines():
        if line.startswith("MemAvailable:"):
            return int(line.split()[1]) * 1024
    raise OSError("/proc/meminfo holds no MemAvailable line")


def in_units(size: int) -> str:
    """``size`` bytes in the largest binary unit it fills, to a tenth."""
    for unit, scale in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if size >= scale:
            return f"{size / scale:.1f} {unit}"
    return f"{size} bytes"
