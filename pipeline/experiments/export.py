"""``ede-pipeline experiment export``: an experiment's finished runs into the published layout."""

from __future__ import annotations

import itertools
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import click

from ede.config import ALGO_LABELS, Params
from ede.errors import first_line
from ede.io.atomic import (
    MARK,
    claim,
    ownership_problem,
    place,
    sha256,
    unwritable,
    write_json,
)
from ede.io.locks import OutputBusy, exclusive
from ede.run.runs import POLICY, PUBLISHED, Run
from ede_pipeline import layout
from ede_pipeline.common import (
    DEFAULT_PARAMS,
    BadInput,
    Failed,
    above_working_directory,
    overlap,
    read_params,
)
from ede_pipeline.experiments.workspace import EXPERIMENTS, WORKSPACES, experiment_file

EVERY_SEED = "all"  # --policies given alone: every finished run's policy
EMBEDDING_METRICS = ("encoder_metrics.json", "decoder_metrics.json")  # as pretrain writes them
# The mark (ede.io.atomic.MARK) of a published embedding's folder that an export wrote: only such a
# folder is ever removed (where no published run acts through it any more), or written into.
EMBEDDING_KIND = "published embedding"
EMBEDDING_OWNS = (*EMBEDDING_METRICS, layout.DECODER)
# <to>/.export.tmp-<pid>: where an export builds its task folders (new/), and puts the old ones
# (old/) as the new ones take their place; gone when it ends, and a killed export's with the next
# (an old folder put back where its place is empty).
STAGING = ".export"


@click.command("export")
@click.argument("name")
@click.option(
    "--to",
    "to",
    type=click.Path(path_type=Path),
    default=layout.RESULTS_RUNS,
    show_default=True,
    help="The published runs' folder.",
)
@click.option(
    "--policies",
    "policies",
    is_flag=False,
    flag_value=EVERY_SEED,
    default=None,
    metavar="[SEEDS]",
    help="Publish each run's final policy too (policy/, about 0.5 MB a run), and the decoder "
    "its EDE-TD3 runs act through, so that `ede-pipeline render` plays them; followed by "
    "seeds (4 or 4,6), those seeds' policies only.",
)
def export(name: str, to: Path, policies: str | None) -> None:
    """Copy experiment NAME's finished runs into the published layout.

    Each finished run's eval.csv, diagnostics.csv, run.json and metrics.json go to
    TO/<task>/<algo>/seed<N>/, checked first (`ede.run.runs.read_run`: the run the experiment's
    params name, finished, its files whole), and the held-out metrics of the embedding its
    EDE-TD3 runs used to TO/<task>/embedding/<checksum>/. Each task's source.json names the
    experiment file, the commits its runs were made at (an earlier export's too), its seeds,
    and report.thresholds' returns for it. With --policies, each run's policy/ goes beside its
    files, and the embedding's decoder/ beside its metrics (its encoder is not needed to play a
    policy, and stays out); with --policies SEEDS, those seeds' runs' only (a results page's clip
    plays one seed's pair: each listed seed's runs must have finished), and a policy an earlier
    export put beside one of this export's other runs goes. Without --policies, the policies
    published beside its runs stay as they are. Where the task's folder already holds seeds from
    other experiments (an experiment adding seeds to a published task), source.json keeps their
    parts beside this one; seeds already published by another experiment are refused, and so
    are runs there that `ede-pipeline results` would refuse (a folder not named seed<N>, a file
    not the one its run.json records, a seed source.json does not name, one run copied as
    another) or that were made with other params than this export's.

    An export removes or replaces only what an export wrote: a policy/ or an embedding's folder
    of its mark (`ede.io.atomic.MARK`), a published run of the experiment's own seeds; anything else
    in its way (a user's folder among the embeddings, a file where a folder goes, a symbolic
    link in a task's folder) is refused. TO is never the working directory or a folder above it,
    nor the experiment's working copy. Nothing is written unless every task's runs pass, and
    then all or nothing: each task's folder is built beside the old one and takes its place
    once every one is whole (a full disk leaves TO as it was).
    """
    workspace = WORKSPACES / name
    if problem := (
        unwritable(to, directory=True)
        or above_working_directory(to)
        or overlap(to, (workspace, EXPERIMENTS / f"{name}.yaml"))
    ):
        raise BadInput(problem)
    experiment = experiment_file(name)
    if not (workspace / DEFAULT_PARAMS).is_file():
        raise BadInput(
            f"experiment {name}: not run here yet (no {workspace}); "
            f"`ede-pipeline experiment run {name}` first"
        )
    params = read_params(workspace / DEFAULT_PARAMS)
    playable = _policy_seeds(policies, name, params.runs.seeds)  # None: no --policies
    listed = policies != EVERY_SEED  # seeds named, not every one whose runs finished
    finished, problems = _finished_runs(workspace, params)
    if problems:
        raise BadInput(problems[0])
    if not finished:
        raise BadInput(f"experiment {name}: no run has finished yet")
    try:
        with exclusive(to):  # one export to a place at a time
            _put_back(place(to))
            plans = []  # each task's, all checked before any is written
            for task in params.runs.tasks:
                runs = [
                    (algo, seed, folder, run)
                    for (t, algo, seed), (folder, run) in finished.items()
                    if t == task
                ]
                if not runs:  # none of this task's runs has finished yet
                    click.echo(f"{task}: no run finished yet; nothing exported", err=True)
                    continue
                if playable is not None and (
                    problem := _unplayable(task, runs, playable, listed, params, workspace)
                ):
                    raise BadInput(problem)
                plans.append(
                    _plan(task, runs, params, experiment, playable, policies, workspace, to)
                )
            said = _write(plans, to)
    except OutputBusy as error:
        raise BadInput(str(error)) from None
    for line in said:
        click.echo(line, err=True)


@dataclass
class _TaskExport:
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


def _plan(
    task: str,
    runs: list[tuple[str, int, Path, Run]],
    params: Params,
    experiment: Path,
    playable: set[int] | None,
    policies: str | None,
    workspace: Path,
    to: Path,
) -> _TaskExport:
    """What exporting ``runs`` (one task's) to ``to`` writes and removes, every place checked:
    the runs there and its source.json as ``results`` reads them, and nothing in the way that an
    export did not write (:func:`_refuse_in_the_way`, :func:`_not_ours`). Raises
    :class:`BadInput` naming the first."""
    folder = layout.task_runs(task, to)
    if problem := _links(folder, to):
        raise BadInput(problem)
    _refuse_in_the_way([(folder, True), (folder / "source.json", False)])
    published = _published_beside(task, runs, to)
    commits = sorted(
        {run.made["code"]["commit"] for *_, run in runs} | _earlier_commits(params, runs, published)
    )
    part = {
        "experiment": experiment.as_posix(),
        "commit": commits[0] if len(commits) == 1 else commits,
        "seeds": list(params.runs.seeds),
    }
    if task in params.report.thresholds:
        part["thresholds"] = params.report.thresholds[task]
    source = _merged_source(folder, part)
    replaced = {run for run, _ in published}
    removed = []
    for algo, seed, _, run in runs:
        target = layout.run(task, algo, seed, to)
        _refuse_in_the_way(
            [(target.parent, True), (target, True), *((target / f, False) for f in PUBLISHED)]
        )
        if target.is_dir() and target not in replaced and (entries := _entries(target)):
            raise BadInput(
                f"{target}: holds {entries}, and no finished run an export published; move "
                "them out first"
            )
        policy = target / POLICY
        if not policy.exists():
            continue
        stale = playable is None and not _recorded(policy, run)
        if (playable is not None or stale) and (problem := _not_ours(policy, "policy")):
            raise BadInput(problem)
        if playable is not None and seed not in playable:
            removed.append((policy, f"--policies {policies}"))
        elif stale:  # an earlier run's, which the run exported over it does not record
            removed.append((policy, "not the policy of the run exported over it"))
    acting = {seed: run.made["embedding"] for algo, seed, _, run in runs if algo == "ede-td3"}
    embeddings = {
        checksum[:12]: any(s in (playable or ()) for s, c in acting.items() if c == checksum)
        for checksum in acting.values()
    }
    joining = {(algo, seed) for algo, seed, *_ in runs}
    named = set(embeddings) | {
        record.made["embedding"][:12]
        for _, record in published
        if record.made["algo"] == "ede-td3"
        and (record.made["algo"], record.curve.seed) not in joining
    }
    kept = folder / layout.PUBLISHED_EMBEDDINGS
    _refuse_in_the_way([(kept, True)])
    for checksum in embeddings:
        place_of = kept / checksum
        _refuse_in_the_way(
            [(place_of, True), *((place_of / file, False) for file in EMBEDDING_METRICS)]
        )
        if place_of.exists() and (problem := _not_ours(place_of, EMBEDDING_KIND)):
            raise BadInput(problem)
    for entry in sorted(kept.iterdir() if kept.is_dir() else []):
        if entry.name in named:
            continue
        if _not_ours(entry, EMBEDDING_KIND):
            raise BadInput(
                f"{entry}: no published run acts through it, but no export wrote it (it holds "
                f"what an export's mark does not own); an export removes only its own: move it "
                f"out of {kept}"
            )
        removed.append((entry, "no published run acts through it now"))
    embedding = workspace / layout.embedding(params.runs.tasks[task])
    for file in EMBEDDING_METRICS if embeddings else ():
        if not (embedding / file).is_file():
            raise BadInput(
                f"{embedding / file}: missing; the EDE-TD3 runs' embedding is published with "
                "its metrics, as pretrain writes them"
            )
    return _TaskExport(task, runs, playable, embeddings, embedding, removed, source)


def _write(plans: list[_TaskExport], to: Path) -> list[str]:
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


def _put_back(root: Path) -> None:
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


def _build(plan: _TaskExport, to: Path, root: Path, new: Path) -> list[str]:
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


def _policy_seeds(policies: str | None, name: str, seeds: list[int]) -> set[int] | None:
    """The seeds whose policies ``--policies`` publishes: None without it, every one of the
    experiment's alone, else those it lists (``4`` or ``4,6``), each one of the experiment's."""
    if policies is None:
        return None
    if policies == EVERY_SEED:
        return set(seeds)
    try:
        listed = {int(seed) for seed in policies.split(",")}
    except ValueError:
        raise BadInput(
            f"--policies {policies!r}: expected seeds of experiment {name} (4 or 4,6), "
            "or nothing for all of them; give --policies after NAME"
        ) from None
    if unknown := sorted(listed - set(seeds)):
        raise BadInput(f"--policies: seeds {unknown} are not among experiment {name}'s {seeds}")
    return listed


def _unplayable(
    task: str,
    runs: list[tuple],
    playable: set[int],
    listed: bool,
    params: Params,
    workspace: Path,
) -> str | None:
    """Why ``runs`` (one task's finished runs) cannot publish the policies of ``playable``: a
    seed ``--policies`` lists whose runs have not all finished, a run without its policy/ (made
    before runs kept one), or a decoder in the working copy that is not the embedding a played
    EDE-TD3 run trained with (the family's made again since). None where they can. ``listed``:
    the seeds were named (``--policies 4``), not every seed's runs that finished."""
    from ede.run.artifacts import DecoderMeta

    done = {(algo, seed) for algo, seed, *_ in runs}
    if listed:
        for algo, seed in itertools.product(params.runs.algos, sorted(playable)):
            if (algo, seed) not in done:
                return (
                    f"--policies: {task} seed {seed} has no finished {ALGO_LABELS[algo]} run "
                    "yet; publish its policies once its runs have finished"
                )
    decoder = workspace / layout.embedding(params.runs.tasks[task]) / layout.DECODER
    for algo, seed, folder, run in runs:
        made = run.made
        if seed not in playable:
            continue
        if not (folder / POLICY).is_dir():
            return f"{folder}: no {POLICY}/ to publish (a run made before runs kept their policy)"
        if algo == "ede-td3":
            try:
                identity = DecoderMeta.model_validate_json(
                    (decoder / "meta.json").read_text()
                ).identity
            except (OSError, ValueError):
                return f"{decoder}: no readable decoder to publish beside {folder}'s policy"
            if identity != made["embedding"]:
                return (
                    f"{decoder}: not the embedding {folder} trained with (its checksum "
                    f"{identity[:12]}…, the run's {made['embedding'][:12]}…): its family's "
                    "embedding was made again since; run the experiment again to publish it"
                )
    return None


def _earlier_commits(
    params: Params, runs: list[tuple], published: list[tuple[Path, Run]]
) -> set[str]:
    """The commits of this experiment's runs that an earlier export published (``published``,
    the task's runs there) and the working copy no longer holds (a copy made again after they
    were exported): the part's commits name every run it publishes, not only this export's."""
    now = {(algo, seed) for algo, seed, *_ in runs}
    commits = set()
    for folder, record in published:
        algo, seed = record.made["algo"], record.curve.seed
        if (algo, seed) in now or algo not in params.runs.algos or seed not in params.runs.seeds:
            continue
        commit = (record.made.get("code") or {}).get("commit")
        if not isinstance(commit, str):
            raise BadInput(
                f"{folder / 'run.json'}: names no commit; the runs an export publishes do"
            )
        commits.add(commit)
    return commits


def _published_beside(task: str, runs: list[tuple], to: Path) -> list[tuple[Path, Run]]:
    """The finished runs of ``task`` in ``to``, beside which this export puts its ``runs``:
    those there read and checked as ``results`` reads them
    (:func:`ede_pipeline.published.published_runs`: folders named seed<N>, files those their
    run.json records, seeds source.json names, no run twice), and the ones that stay made with
    the same params as ``runs`` (:func:`ede.run.spec.unshared_params`), and no run of ``runs`` one
    of them (:func:`ede.run.runs.same_files`). Raises :class:`BadInput` where not."""
    from ede.run.runs import same_files
    from ede.run.spec import unshared_params
    from ede_pipeline.published import published_runs

    published = published_runs(to, task)
    replaced = {(algo, seed) for algo, seed, *_ in runs}
    staying = [
        (folder, record)
        for folder, record in published
        if (record.made["algo"], record.curve.seed) not in replaced
    ]
    joining = [(folder, run) for *_, folder, run in runs]
    both = staying + joining
    if (problem := unshared_params([(f, r.made) for f, r in both]) or same_files(both)) is not None:
        raise BadInput(problem)
    return published


def _merged_source(folder: Path, part: dict) -> dict | list[dict]:
    """A task folder's source.json with ``part`` (one experiment's) in it: the part alone, or
    beside the parts of other experiments already there, replacing an earlier export of the same
    experiment file. A seed another part already names is refused (:class:`BadInput`); a run
    there of a seed no part names was refused before (``published_runs``)."""
    from ede_pipeline.published import read_source

    there = (folder / "source.json").is_file()
    checked = read_source(folder).parts if there else []
    written = json.loads((folder / "source.json").read_text()) if there else []
    kept = [
        (json_part, read)
        for json_part, read in zip(
            written if isinstance(written, list) else [written], checked, strict=True
        )
        if read.experiment != part["experiment"]
    ]
    for _, read in kept:
        if twice := sorted(set(read.seeds) & set(part["seeds"])):
            raise BadInput(
                f"{folder / 'source.json'}: seeds {twice} are already published by "
                f"{read.maker()}; an experiment adds seeds the task has not"
            )
    return [*(json_part for json_part, _ in kept), part] if kept else part


def _finished_runs(workspace: Path, params: Params) -> tuple[dict, list[str]]:
    """Every finished run of ``params`` in ``workspace``, checked as a published run, by (task,
    algo, seed): its folder and :class:`ede.run.runs.Run`; and one line per run that cannot be
    published."""
    from ede.run.runs import RunRejected, read_run
    from ede.run.spec import RunSpec

    finished, problems = {}, []
    for task, algo, seed in itertools.product(
        params.runs.tasks, params.runs.algos, params.runs.seeds
    ):
        out = workspace / layout.run(task, algo, seed)
        spec = RunSpec(task, algo, seed, params.runs.budgets[task], params.td3, params.ede_td3)
        expected = {k: v for k, v in spec.identity().items() if k != "embedding"}
        try:
            run = read_run(out, expected, published=True)
        except RunRejected as error:
            problems.append(str(error))
            continue
        if run is not None and not (run.made.get("code") or {}).get("commit"):
            problems.append(
                f"{out / 'run.json'}: names no commit (an image built without "
                "EDE_COMMIT?); only runs whose code is known are published"
            )
        elif run is not None:
            finished[(task, algo, seed)] = (out, run)
    return finished, problems


def _recorded(policy: Path, run: Run) -> bool:
    """Whether the files of ``policy`` (a published policy/) are those ``run``'s run.json
    records, no more and no fewer."""
    recorded = run.made.get("sha256") or {}
    for name in ("policy.safetensors", "policy.json"):
        path, digest = policy / name, recorded.get(f"{POLICY}/{name}")
        if path.is_file() != (digest is not None) or (digest and sha256(path) != digest):
            return False
    return True


def _links(folder: Path, to: Path) -> str | None:
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


def _refuse_in_the_way(paths: list[tuple[Path, bool]]) -> None:
    """Each of ``paths`` (a path an export writes, and whether a folder) is nothing yet, or a
    folder where a folder goes and a file where a file goes; :class:`BadInput` where not."""
    for path, folder in paths:
        if folder and path.exists() and not path.is_dir():
            raise BadInput(f"{path}: a file is in the way; expected a folder there, or nothing")
        if not folder and path.is_dir():
            raise BadInput(f"{path}: a folder is in the way; expected a file there, or nothing")


def _not_ours(path: Path, kind: str) -> str | None:
    """Why an export may not replace or remove ``path``: not a folder, or not one of ``kind``
    holding only what its mark owns (:func:`ede.io.atomic.ownership_problem`)."""
    if not path.is_dir():
        return f"{path}: a file where an export writes {kind} folders; move it out first"
    if not any(path.iterdir()):
        return None
    if not (path / MARK).is_file():
        return (
            f"{path}: holds {_entries(path)}, which no export wrote there (no {MARK} of one); "
            "move it out first"
        )
    return ownership_problem(path, kind)


def _entries(folder: Path) -> str:
    """``a, b, c and 2 more``: what ``folder`` holds, by name."""
    names = sorted(entry.name for entry in folder.iterdir())
    return ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
