"""``ede-pipeline experiment export``: an experiment's finished runs into the published layout."""

from __future__ import annotations

import itertools
import json
import shutil
from pathlib import Path

import click

from ede.atomic import write_json
from ede.config import ALGO_LABELS, Params
from ede.runs import POLICY, PUBLISHED
from ede_pipeline import layout
from ede_pipeline.common import DEFAULT_PARAMS, BadInput, read_params
from ede_pipeline.experiments.workspace import WORKSPACES, experiment_file

EVERY_SEED = "all"  # --policies given alone: every finished run's policy


@click.command("export")
@click.argument("name")
@click.option(
    "--to",
    "to",
    type=click.Path(file_okay=False, path_type=Path),
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
    TO/<task>/<algo>/seed<N>/, checked first (`ede.runs.read_run`: the run the experiment's
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
    not the one its run.json records) or that were made with other params than this export's.
    Nothing is written unless every task's runs pass.
    """
    experiment_file(name)
    workspace = WORKSPACES / name
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
    exported = {}  # task: its runs and its source.json's parts, all checked before any is written
    for task in params.runs.tasks:
        runs = [
            (algo, seed, folder, made)
            for (t, algo, seed), (folder, made) in finished.items()
            if t == task
        ]
        if not runs:  # none of this task's runs has finished yet
            click.echo(f"{task}: no run finished yet; nothing exported", err=True)
            continue
        if playable is not None and (
            problem := _unplayable(task, runs, playable, listed, params, workspace)
        ):
            raise BadInput(problem)
        published = _published_beside(task, runs, to)
        commits = sorted(
            {made["code"]["commit"] for *_, made in runs} | _earlier_commits(task, params, runs, to)
        )
        part = {
            "experiment": experiment_file(name).as_posix(),
            "commit": commits[0] if len(commits) == 1 else commits,
            "seeds": list(params.runs.seeds),
        }
        if task in params.report.thresholds:
            part["thresholds"] = params.report.thresholds[task]
        exported[task] = runs, _merged_source(layout.task_runs(task, to), part, published)
    for task, (runs, source) in exported.items():
        for algo, seed, folder, _ in runs:
            target = layout.run(task, algo, seed, to)
            target.mkdir(parents=True, exist_ok=True)
            for file in PUBLISHED:
                if (folder / file).is_file():
                    shutil.copy2(folder / file, target / file)
            if playable is None:  # no --policies: what is published beside the run stays
                continue
            if seed in playable:
                shutil.copytree(folder / POLICY, target / POLICY, dirs_exist_ok=True)
            elif (target / POLICY).is_dir():  # an earlier export's, of a run this one does not play
                shutil.rmtree(target / POLICY)
                click.echo(f"{target / POLICY}: removed (--policies {policies})", err=True)
        embedding = workspace / layout.embedding(params.runs.tasks[task])
        acting = {seed: made["embedding"] for algo, seed, _, made in runs if algo == "ede-td3"}
        played = {checksum for seed, checksum in acting.items() if seed in (playable or ())}
        for checksum in set(acting.values()):
            kept = layout.published_embedding(task, checksum, to)
            kept.mkdir(parents=True, exist_ok=True)
            for file in EMBEDDING_METRICS:
                shutil.copy2(embedding / file, kept / file)
            if checksum in played:  # the decoder a published EDE-TD3 policy acts through
                shutil.copytree(
                    embedding / layout.DECODER, kept / layout.DECODER, dirs_exist_ok=True
                )
        _drop_unused_embeddings(task, to)
        write_json(layout.task_runs(task, to) / "source.json", source)
        click.echo(f"{task}: {len(runs)} runs to {layout.task_runs(task, to)}", err=True)


EMBEDDING_METRICS = ("encoder_metrics.json", "decoder_metrics.json")  # as pretrain writes them


def _drop_unused_embeddings(task: str, to: Path) -> None:
    """Remove the task's published embeddings that none of its published EDE-TD3 runs names: an
    experiment made again (its family's embedding with it) and exported over its earlier runs
    leaves the earlier embedding to no run."""
    from ede_pipeline.published import published_runs

    named = {
        layout.published_embedding(task, record.made["embedding"], to)
        for _, record in published_runs(to, task)
        if record.made["algo"] == "ede-td3"
    }
    folder = layout.task_runs(task, to) / layout.PUBLISHED_EMBEDDINGS
    for kept in sorted(folder.iterdir() if folder.is_dir() else []):
        if kept not in named:
            shutil.rmtree(kept)
            click.echo(f"{kept}: removed (no published run acts through it now)", err=True)


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
    from ede.artifacts import DecoderMeta

    done = {(algo, seed) for algo, seed, *_ in runs}
    if listed:
        for algo, seed in itertools.product(params.runs.algos, sorted(playable)):
            if (algo, seed) not in done:
                return (
                    f"--policies: {task} seed {seed} has no finished {ALGO_LABELS[algo]} run "
                    "yet; publish its policies once its runs have finished"
                )
    decoder = workspace / layout.embedding(params.runs.tasks[task]) / layout.DECODER
    for algo, seed, folder, made in runs:
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


def _earlier_commits(task: str, params: Params, runs: list[tuple], to: Path) -> set[str]:
    """The commits of this experiment's runs of ``task`` that an earlier export published to
    ``to`` and the working copy no longer holds (a copy made again after they were exported):
    the part's commits name every run it publishes, not only this export's."""
    now = {(algo, seed) for algo, seed, *_ in runs}
    commits = set()
    for algo, seed in itertools.product(params.runs.algos, params.runs.seeds):
        record = layout.run(task, algo, seed, to) / "run.json"
        if (algo, seed) not in now and record.is_file():
            commits.add(json.loads(record.read_text())["code"]["commit"])
    return commits


def _published_beside(task: str, runs: list[tuple], to: Path) -> set[int]:
    """The seeds of ``task`` with finished runs in ``to``, beside which this export puts its
    ``runs``: those there read and checked as ``results`` reads them
    (:func:`ede_pipeline.published.published_runs`: folders named seed<N>, files those their
    run.json records), and the ones that stay made with the same params as ``runs``
    (:func:`ede.runs.unshared_params`). Raises :class:`BadInput` where not."""
    from ede.runs import unshared_params
    from ede_pipeline.published import published_runs

    published = published_runs(to, task)
    replaced = {(algo, seed) for algo, seed, *_ in runs}
    staying = [
        (run, record.made)
        for run, record in published
        if (record.made["algo"], record.curve.seed) not in replaced
    ]
    joining = [(folder, made) for *_, folder, made in runs]
    if (difference := unshared_params(staying + joining)) is not None:
        raise BadInput(difference)
    return {record.curve.seed for _, record in published}


def _merged_source(folder: Path, part: dict, published: set[int]) -> dict | list[dict]:
    """A task folder's source.json with ``part`` (one experiment's) in it: the part alone, or
    beside the parts of other experiments already there, replacing an earlier export of the same
    experiment file. A seed another part already names is refused (:class:`BadInput`), and so is
    one of ``published`` (the seeds with runs there) that no earlier export of it named."""
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
    ours = {
        seed for read in checked if read.experiment == part["experiment"] for seed in read.seeds
    }
    if twice := sorted(published & set(part["seeds"]) - ours):
        raise BadInput(
            f"{folder}: seeds {twice} have runs there that no earlier export of "
            f"{part['experiment']} made; an experiment adds seeds the task has not"
        )
    return [*(json_part for json_part, _ in kept), part] if kept else part


def _finished_runs(workspace: Path, params: Params) -> tuple[dict, list[str]]:
    """Every finished run of ``params`` in ``workspace``, checked, by (task, algo, seed): its
    folder and run.json; and one line per run that cannot be published."""
    from ede.runs import RunRejected, RunSpec, read_run

    finished, problems = {}, []
    for task, algo, seed in itertools.product(
        params.runs.tasks, params.runs.algos, params.runs.seeds
    ):
        out = workspace / layout.run(task, algo, seed)
        spec = RunSpec(task, algo, seed, params.runs.budgets[task], params.td3, params.ede_td3)
        expected = {k: v for k, v in spec.identity().items() if k != "embedding"}
        try:
            run = read_run(out, expected)
        except RunRejected as error:
            problems.append(str(error))
            continue
        if run is not None and not (run.made.get("code") or {}).get("commit"):
            problems.append(
                f"{out / 'run.json'}: names no commit (an image built without "
                "EDE_COMMIT?); only runs whose code is known are published"
            )
        elif run is not None:
            finished[(task, algo, seed)] = (out, run.made)
    return finished, problems
