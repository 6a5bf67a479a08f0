"""What an export of an experiment publishes, checked before anything is written: its finished
runs (:func:`finished_runs`), the seeds whose policies go with them (:func:`policy_seeds`,
:func:`unplayable`), and per task what its folder will hold and lose (:func:`plan`) beside the runs
other exports published there (the writing: :mod:`ede_pipeline.experiments.export_write`)."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

from ede.config import ALGO_LABELS, EMBEDDED_ALGOS, Params
from ede.io.atomic import sha256
from ede.run.runs import POLICY, PUBLISHED, Run
from ede_pipeline import layout
from ede_pipeline.common import BadInput
from ede_pipeline.experiments.export_write import (
    EMBEDDING_KIND,
    EMBEDDING_METRICS,
    TaskExport,
    entries,
    links,
    not_ours,
    refuse_in_the_way,
)

EVERY_SEED = "all"  # --policies given alone: every finished run's policy


def plan(
    task: str,
    runs: list[tuple[str, int, Path, Run]],
    params: Params,
    experiment: Path,
    playable: set[int] | None,
    policies: str | None,
    workspace: Path,
    to: Path,
) -> TaskExport:
    """What exporting ``runs`` (one task's) to ``to`` writes and removes, every place checked:
    the runs there and its source.json as ``results`` reads them, and nothing in the way that an
    export did not write (:func:`~ede_pipeline.experiments.export_write.refuse_in_the_way`,
    :func:`~ede_pipeline.experiments.export_write.not_ours`). Raises :class:`BadInput` naming
    the first."""
    folder = layout.task_runs(task, to)
    if problem := links(folder, to):
        raise BadInput(problem)
    refuse_in_the_way([(folder, True), (folder / "source.json", False)])
    published = _published_beside(task, runs, to)
    source = _merged_source(folder, _source_part(task, runs, params, experiment, published))
    replaced = {run_folder for run_folder, _ in published}
    removed = []
    for algo, seed, _, run in runs:
        target = layout.run(task, algo, seed, to)
        _check_run_place(target, replaced)
        if why := _policy_removed(target / POLICY, seed, run, playable, policies):
            removed.append((target / POLICY, why))
    embeddings = _embeddings(runs, playable)
    kept = folder / layout.PUBLISHED_EMBEDDINGS
    _check_embedding_places(kept, embeddings)
    removed += _unused_embeddings(kept, embeddings, runs, published)
    embedding = workspace / layout.embedding(params.runs.tasks[task])
    for file in EMBEDDING_METRICS if embeddings else ():
        if not (embedding / file).is_file():
            raise BadInput(
                f"{embedding / file}: missing; the EDE-TD3 runs' embedding is published with "
                "its metrics, as pretrain writes them"
            )
    return TaskExport(task, runs, playable, embeddings, embedding, removed, source)


def _source_part(
    task: str,
    runs: list[tuple[str, int, Path, Run]],
    params: Params,
    experiment: Path,
    published: list[tuple[Path, Run]],
) -> dict:
    """This experiment's part of the task's source.json: its file, the commits of its runs the
    task's folder will hold (an earlier export's too: :func:`_earlier_commits`), its seeds, and
    report.thresholds' returns for the task."""
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
    return part


def _check_run_place(target: Path, replaced: set[Path]) -> None:
    """A run's folder under TO (``target``) can take the run: nothing in the way of its files,
    and nothing in it unless it is a published run (one of ``replaced``, the task's runs there).
    Raises :class:`BadInput` where not."""
    refuse_in_the_way(
        [(target.parent, True), (target, True), *((target / f, False) for f in PUBLISHED)]
    )
    if target.is_dir() and target not in replaced and (held := entries(target)):
        raise BadInput(
            f"{target}: holds {held}, and no finished run an export published; move them out first"
        )


def _policy_removed(
    policy: Path, seed: int, run: Run, playable: set[int] | None, policies: str | None
) -> str | None:
    """Why the policy/ published at ``policy``, beside the place of seed ``seed``'s ``run``, goes
    with this export: ``--policies`` lists other seeds, or, without it, it is an earlier run's,
    which ``run`` does not record. None where it stays (or there is none). Raises
    :class:`BadInput` where it would be replaced or removed but no export wrote it."""
    if not policy.exists():
        return None
    stale = playable is None and not _recorded(policy, run)
    if (playable is not None or stale) and (problem := not_ours(policy, "policy")):
        raise BadInput(problem)
    if playable is not None and seed not in playable:
        return f"--policies {policies}"
    if stale:  # an earlier run's, which the run exported over it does not record
        return "not the policy of the run exported over it"
    return None


def _embeddings(
    runs: list[tuple[str, int, Path, Run]], playable: set[int] | None
) -> dict[str, bool]:
    """The embeddings ``runs``' EDE-TD3 runs act through, by their checksum's first 12
    characters, each with whether its decoder goes with it: where one of ``playable``'s seeds
    acts through it."""
    acting = {seed: run.made["embedding"] for algo, seed, _, run in runs if algo in EMBEDDED_ALGOS}
    return {
        checksum[:12]: any(s in (playable or ()) for s, c in acting.items() if c == checksum)
        for checksum in acting.values()
    }


def _check_embedding_places(kept: Path, embeddings: dict[str, bool]) -> None:
    """The task's published embeddings' folder (``kept``) and each of ``embeddings``' places in
    it can take what the export writes: nothing in the way, and each one there an export's.
    Raises :class:`BadInput` where not."""
    refuse_in_the_way([(kept, True)])
    for checksum in embeddings:
        place_of = kept / checksum
        refuse_in_the_way(
            [(place_of, True), *((place_of / file, False) for file in EMBEDDING_METRICS)]
        )
        if place_of.exists() and (problem := not_ours(place_of, EMBEDDING_KIND)):
            raise BadInput(problem)


def _unused_embeddings(
    kept: Path,
    embeddings: dict[str, bool],
    runs: list[tuple[str, int, Path, Run]],
    published: list[tuple[Path, Run]],
) -> list[tuple[Path, str]]:
    """The folders of the task's published embeddings' (``kept``) that no EDE-TD3 run acts
    through once ``runs`` are exported (neither one of ``embeddings`` nor one of the runs of
    ``published`` that stay), each with why it goes. Raises :class:`BadInput` where one is not
    an export's."""
    joining = {(algo, seed) for algo, seed, *_ in runs}
    named = set(embeddings) | {
        record.made["embedding"][:12]
        for _, record in published
        if record.made["algo"] in EMBEDDED_ALGOS
        and (record.made["algo"], record.curve.seed) not in joining
    }
    removed = []
    for entry in sorted(kept.iterdir() if kept.is_dir() else []):
        if entry.name in named:
            continue
        if not_ours(entry, EMBEDDING_KIND):
            raise BadInput(
                f"{entry}: no published run acts through it, but no export wrote it (it holds "
                f"what an export's mark does not own); an export removes only its own: move it "
                f"out of {kept}"
            )
        removed.append((entry, "no published run acts through it now"))
    return removed


def policy_seeds(policies: str | None, name: str, seeds: list[int]) -> set[int] | None:
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


def unplayable(
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


def finished_runs(workspace: Path, params: Params) -> tuple[dict, list[str]]:
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
