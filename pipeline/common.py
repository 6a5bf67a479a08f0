"""What every ``ede-pipeline`` command shares: params loading, bad-input errors, default paths."""

from __future__ import annotations

import functools
import os
import subprocess
import sys
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import click

from ede.atomic import NotOurs, NotWritten, ownership_problem, unwritable
from ede.config import Params, ParamsError, load_params
from ede.locks import OutputBusy, exclusive
from ede_pipeline.progress import PROGRESS_ENV

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


def params_option(command: Callable[..., Any]) -> Callable[..., Any]:
    """Add ``--params FILE`` to a command and hand it the validated :class:`Params`."""

    @click.option(
        "--params",
        "params_path",
        type=click.Path(dir_okay=False, path_type=Path),
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


Folder = tuple[Path | None, str]  # an output folder and the kind of output it is


def check_outputs(
    output: Folder,
    files: tuple[Path | None, ...] = (),
    dirs: tuple[Folder, ...] = (),
    inputs: tuple[Path | None, ...] = (),
) -> None:
    """Before any work: every place a stage will write can be written
    (:func:`ede.atomic.unwritable`) — ``output`` (a folder, with its kind) with its lock and
    temporaries, the other outputs ``files`` and ``dirs``, and the progress file ``EDE_PROGRESS``
    names — and no output folder would delete what the stage did not write: each is new, empty
    or its own kind's earlier output (:func:`ede.atomic.ownership_problem`), and none is the
    working directory or a folder above it. No output is, holds or lies inside one of ``inputs``.

    Raises:
        BadInput: one line naming the place and what is in the way.
    """
    progress_file = os.environ.get(PROGRESS_ENV)
    places = [output, *dirs, *((f, None) for f in files)]
    for place, kind in places:
        if place is None:
            continue
        folder = kind is not None
        problem = (
            unwritable(place, folder)
            or (folder and _above_working_directory(place))
            or _overlap(place, inputs)
            or (kind is not None and ownership_problem(place, kind))
        )
        if problem:
            raise BadInput(problem)
    if progress_file and (problem := unwritable(Path(progress_file), directory=False)):
        raise BadInput(f"{PROGRESS_ENV}={problem}")


def _above_working_directory(folder: Path) -> str | None:
    here, there = Path.cwd().resolve(), folder.resolve()
    if there == here or there in here.parents:
        return (
            f"{folder}: the working directory{' or a folder above it' if there != here else ''}"
            "; expected a folder of the output's own, e.g. one inside it"
        )
    return None


def _overlap(output: Path, inputs: tuple[Path | None, ...]) -> str | None:
    there = output.resolve()
    for given in filter(None, inputs):
        source = given.resolve()
        if there == source or source.is_relative_to(there) or there.is_relative_to(source):
            how = (
                "is"
                if there == source
                else "holds"
                if source.is_relative_to(there)
                else "lies inside"
            )
            return f"{output}: {how} the stage's input {given}; expected a place apart from it"
    return None


@contextmanager
def holding(
    output: Folder,
    files: tuple[Path | None, ...] = (),
    dirs: tuple[Folder, ...] = (),
    inputs: tuple[Path | None, ...] = (),
) -> Iterator[None]:
    """The stage's exclusive lock on its output (:func:`ede.locks.exclusive`) for the block,
    after :func:`check_outputs`. A place that cannot be written or that holds what the stage did
    not write, and a second process on the same output, are refused as bad input: one line,
    exit 2, nothing written. A write that fails in the block (a full disk) is one line, exit 1,
    its temporaries removed (:class:`ede.atomic.NotWritten`)."""
    check_outputs(output, files, dirs, inputs)
    folder = output[0]
    assert folder is not None
    lock = ExitStack()
    try:
        lock.enter_context(exclusive(folder))
    except OutputBusy as error:
        raise BadInput(str(error)) from None
    with lock:
        try:
            yield
        except NotOurs as error:  # what the checks above could not see (a nested folder)
            raise BadInput(str(error)) from None
        except NotWritten as error:
            raise Failed(error.strerror or str(error)) from None


# The values of MUJOCO_GL that MuJoCo accepts on Linux, and "disable", which needs no OpenGL.
MUJOCO_GL_VALUES = ("egl", "osmesa", "glfw", "glx", "disable")


def check_mujoco_gl() -> None:
    """An ``MUJOCO_GL`` that MuJoCo cannot start with (a value it does not know, or a backend
    whose libraries this machine lacks) is one line naming the values this machine supports.

    MuJoCo reads the variable when it is first imported and fails there, in every stage; no
    stage renders, so leaving it unset (or ``disable``) always works.

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
            "or leave it unset: no stage renders"
        ) from None


def _mujoco_starts_with(value: str) -> bool:
    environ = {**os.environ, "MUJOCO_GL": value}
    probe = subprocess.run(
        [sys.executable, "-c", "import mujoco"], env=environ, capture_output=True, timeout=60
    )
    return probe.returncode == 0
