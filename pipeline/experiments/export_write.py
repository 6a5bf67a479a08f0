"""What an export writes to a task's folder (:class:`TaskExport`), and the writing, all or nothing:
each task's folder built whole beside the old one, then put in its place; and what it may write
over (:func:`links`, :func:`refuse_in_the_way`, :func:`not_ours`)."""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from ede.errors import first_line
from ede.io.atomic import MARK, claim, ownership_problem, place, write_json
from ede.run.runs import POLICY, PUBLISHED, Run
from ede_pipeline import layout
from ede_pipeline.common import BadInput, Failed

EMBEDDING_METRICS = ("encoder_metrics.json", "decoder_metrics.json")  # as pretrain writes them
# The mark (ede.io.atomic.MARK) of a published embedding's folder that an export wrote: only such a
# folder is ever removed (where no published run acts through it any more), or written into.
EMBEDDING_KIND = "published embedding"
EMBEDDING_OWNS = (*EMBEDDING_METRICS, layout.DECODER)
# <to>/.export.tmp-<pid>: where an export builds its task folders (new/), and puts the old ones
# (old/) as the new ones take their place; gone when it ends, and a killed export's with the next
# (an old folder put back where its place is empty).
STAGING = ".export"


@dataclass
class TaskExport:
    """What an export writes to one task's folder, checked: the runs it copies there (each its
    algorithm, seed, folder in the working copy and :class:`ede.run.runs.Run`), the seeds whose
    policies it copies (None: it leaves the policies there alone), the embeddings it keeps
    (each its checksum, and whether with its decoder), the folders it removes, its source.json."""

    task: str
    runs: list[tuple[str, int, Path, Run]]
    playable: set[int] | None
    embeddings: dict[str, bool]
    embedding: Path  # the working copy's embedding folder (its metrics, its decoder)
    removed: list[tuple[Path, str]]  # each the folder's path under TO, and why
    source: dict | list[dict]


def write(plans: list[TaskExport], to: Path) -> list[str]:
    """Each task's folder of ``plans`` built whole beside the old one (under ``<to>/.export.tmp-
    <pid>/new/``: the old one's files, then the runs, policies, embeddings and source.json the
    plan writes, the folders it removes gone), then every one put in its old one's place, which
    goes; what the export says it did. A write that fails (a full disk) leaves ``to`` as it was:
    one line, exit 1 (:class:`Failed`)."""
    root = place(to)
    created = not root.exists()
    stage = root / f"{STAGING}.tmp-{os.getpid()}"
    said = []
    try:
        root.mkdir(parents=True, exist_ok=True)
        for plan in plans:
            said += _build(plan, to, root, stage / "new")
            for tree in (root, stage / "old"):
                layout.task_runs(plan.task, tree).parent.mkdir(parents=True, exist_ok=True)
    except BaseException as error:
        shutil.rmtree(stage, ignore_errors=True)
        if created:
            shutil.rmtree(root, ignore_errors=True)
        cause = error.error if isinstance(error, _CopyFailed) else error
        if isinstance(cause, OSError):
            reason = cause.strerror or first_line(cause)
            raise Failed(f"{to}: nothing exported ({reason}); it is as it was") from None
        raise
    for plan in plans:  # renames alone: no byte to write, so none to fail for want of room
        final, new, old = (
            layout.task_runs(plan.task, tree) for tree in (root, stage / "new", stage / "old")
        )
        if final.exists():
            os.rename(final, old)
        os.rename(new, final)
    shutil.rmtree(stage)
    return said


def put_back(root: Path) -> None:
    """Undo what an export killed midway left in ``root``: a task folder it had moved aside to
    put its new one in its place goes back where that place is empty, and the rest of what it
    left goes (whoever left it is gone: this export holds the place's lock)."""
    for stage in sorted(root.glob(f"{STAGING}.tmp-*")):
        for source in sorted((stage / "old").rglob("source.json")):
            final = root / source.parent.relative_to(stage / "old")
            if not final.exists():
                final.parent.mkdir(parents=True, exist_ok=True)
                os.rename(source.parent, final)
        shutil.rmtree(stage)


def _build(plan: TaskExport, to: Path, root: Path, new: Path) -> list[str]:
    """``plan``'s task folder as it will be, under ``new`` (the one under ``root``, the place
    ``to`` names, copied, then changed as the plan says); one line for each thing written or
    removed, naming it under ``to``."""
    task = plan.task
    folder, built = layout.task_runs(task, root), layout.task_runs(task, new)
    if folder.is_dir():
        shutil.copytree(folder, built, symlinks=True, copy_function=_copy)
    built.mkdir(parents=True, exist_ok=True)
    said = []
    for algo, seed, made, _ in plan.runs:
        target = layout.run(task, algo, seed, new)
        target.mkdir(parents=True, exist_ok=True)
        for file in PUBLISHED:
            if (made / file).is_file():
                shutil.copy2(made / file, target / file)
        if plan.playable is not None and seed in plan.playable:
            shutil.rmtree(target / POLICY, ignore_errors=True)
            shutil.copytree(made / POLICY, target / POLICY, copy_function=_copy)
    for checksum, with_decoder in plan.embeddings.items():
        kept = built / layout.PUBLISHED_EMBEDDINGS / checksum
        claim(kept, EMBEDDING_KIND, EMBEDDING_OWNS)
        for file in EMBEDDING_METRICS:
            shutil.copy2(plan.embedding / file, kept / file)
        if with_decoder:  # the decoder a published EDE-TD3 policy acts through
            shutil.rmtree(kept / layout.DECODER, ignore_errors=True)
            shutil.copytree(
                plan.embedding / layout.DECODER, kept / layout.DECODER, copy_function=_copy
            )
    for gone, why in plan.removed:
        shutil.rmtree(new / gone.relative_to(to))
        said.append(f"{gone}: removed ({why})")
    write_json(built / "source.json", plan.source)
    said.append(f"{task}: {len(plan.runs)} runs to {layout.task_runs(task, to)}")
    return said


class _CopyFailed(Exception):
    """A file :func:`shutil.copytree` could not copy (a full disk): raised through it whole,
    where it would gather each file's error as text."""

    def __init__(self, error: OSError) -> None:
        super().__init__(str(error))
        self.error = error


def _copy(source: str, target: str) -> object:
    try:
        return shutil.copy2(source, target)
    except OSError as error:
        raise _CopyFailed(error) from None


def links(folder: Path, to: Path) -> str | None:
    """Why a task's ``folder`` under ``to`` would lead an export's writes elsewhere: a symbolic
    link on its way from ``to`` or in it (a seed folder, say). None where none is."""
    path = to
    for part in folder.relative_to(to).parts:
        path = path / part
        if path.is_symlink():
            return _a_link(path)
    for where, names, files in os.walk(folder):
        for entry in (*names, *files):
            if (Path(where) / entry).is_symlink():
                return _a_link(Path(where) / entry)
    return None


def _a_link(path: Path) -> str:
    return (
        f"{path}: a symbolic link (to {os.readlink(path)}); a published folder holds its own "
        "files, so that an export writes nothing outside it: put what it names there instead"
    )


def refuse_in_the_way(paths: list[tuple[Path, bool]]) -> None:
    """Each of ``paths`` (a path an export writes, and whether a folder) is nothing yet, or a
    folder where a folder goes and a file where a file goes; :class:`BadInput` where not."""
    for path, folder in paths:
        if folder and path.exists() and not path.is_dir():
            raise BadInput(f"{path}: a file is in the way; expected a folder there, or nothing")
        if not folder and path.is_dir():
            raise BadInput(f"{path}: a folder is in the way; expected a file there, or nothing")


def not_ours(path: Path, kind: str) -> str | None:
    """Why an export may not replace or remove ``path``: not a folder, or not one of ``kind``
    holding only what its mark owns (:func:`ede.io.atomic.ownership_problem`)."""
    if not path.is_dir():
        return f"{path}: a file where an export writes {kind} folders; move it out first"
    if not any(path.iterdir()):
        return None
    if not (path / MARK).is_file():
        return (
            f"{path}: holds {entries(path)}, which no export wrote there (no {MARK} of one); "
            "move it out first"
        )
    return ownership_problem(path, kind)


def entries(folder: Path) -> str:
    """``a, b, c and 2 more``: what ``folder`` holds, by name."""
    names = sorted(entry.name for entry in folder.iterdir())
    return ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
