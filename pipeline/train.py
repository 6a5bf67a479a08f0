"""Stage 4, ``ede-pipeline train``: one TD3 or EDE-TD3 run of one task and seed."""

from __future__ import annotations

import functools
from contextlib import ExitStack
from pathlib import Path

import click
import torch

from ede.artifacts import ArtifactError, load_action_embedding, params_mismatches
from ede.checkpoint import CheckpointError, CheckpointWriteError
from ede.config import ALGOS, SEED_RANGE, Params, is_seed
from ede.nets import pick_device
from ede.runs import RUN_KIND, RunSpec
from ede.training import Diverged, train_group
from ede_pipeline import layout
from ede_pipeline.common import BadInput, Failed, check_outputs, holding, params_option
from ede_pipeline.progress import progress


@click.command()
@click.option("--task", required=True, help="A task of params.yaml's runs.tasks.")
@click.option("--algo", required=True, help="td3 or ede-td3.")
@click.option(
    "--seed",
    "--seeds",
    "seeds",
    required=True,
    help="The run's seed (0 to 2**32 - 1), or several (0,1,2,3 or 0-3): the runs of one task and "
    "algorithm trained in one process, their updates batched, each with the "
    "outputs it gets alone.",
)
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    help="Run directory; with several seeds, a pattern with {seed}  "
    "[default: data/runs/<task>/<algo>/seed<N>]",
)
@click.option(
    "--encoder",
    type=click.Path(path_type=Path),
    help="EDE-TD3: the family's encoder  [default: data/families/<family>/embedding/encoder]",
)
@click.option(
    "--decoder",
    type=click.Path(path_type=Path),
    help="EDE-TD3: the family's decoder  [default: data/families/<family>/embedding/decoder]",
)
@click.option(
    "--keep-checkpoint",
    is_flag=True,
    help="Keep the checkpoint (replay buffer included) once the run is complete.",
)
@click.option(
    "--bad-checkpoint",
    type=click.Choice(["restart", "refuse"]),
    default="restart",
    show_default=True,
    help="A checkpoint that is damaged or another run's: move it aside to "
    "checkpoint.bad-<time> and start over, or refuse (exit 2) and touch nothing.",
)
@params_option
def train(
    params: Params,
    task: str,
    algo: str,
    seeds: str,
    out: Path | None,
    encoder: Path | None,
    decoder: Path | None,
    keep_checkpoint: bool,
    bad_checkpoint: str,
) -> None:
    """Stage 4: train one run, or the runs of several seeds in one process; each resumes from
    its checkpoint if one of the same run exists."""
    if algo not in ALGOS:
        raise BadInput(f"--algo {algo!r}: unknown; expected one of {', '.join(ALGOS)}")
    seed_list = parse_seeds(seeds)
    outs = run_dirs(task, algo, seed_list, out)
    if task not in params.runs.tasks:
        raise BadInput(
            f"--task {task!r}: not in params.yaml's runs.tasks ({', '.join(params.runs.all_tasks)})"
        )
    family = params.runs.tasks[task]
    config = params.td3
    try:
        device = pick_device(config.device)
    except ValueError as error:
        raise BadInput(str(error)) from None
    embedding, embedding_id = None, ""
    if algo == "ede-td3":
        folder = layout.embedding(family)
        try:
            meta, embedding = load_action_embedding(
                encoder or folder / "encoder", decoder or folder / "decoder", device
            )
        except ArtifactError as error:
            raise BadInput(
                f"{error} (EDE-TD3 on {task} needs the {family} family's embedding)"
            ) from None
        if meta.family != family:
            raise BadInput(
                f"{decoder or folder / 'decoder'}: the embedding of family "
                f"{meta.family}, but {task} is in family {family}"
            )
        mismatches = params_mismatches(
            decoder or folder / "decoder", meta, params.embedding, params.decoder
        )
        if mismatches:
            raise BadInput("\n".join(mismatches))
        embedding_id = meta.identity
    torch.set_num_threads(config.threads)
    budget = params.runs.budgets[task]
    specs = [
        RunSpec(task, algo, seed, budget, config, params.ede_td3, embedding_id)
        for seed in seed_list
    ]
    notice = functools.partial(click.echo, err=True)
    label = f"{algo} {task} seed{'s' if len(seed_list) > 1 else ''} {seeds}"
    inputs = (encoder or folder / "encoder", decoder or folder / "decoder") if embedding else ()
    for run_dir in outs:  # every run's, before the first lock is taken
        check_outputs((run_dir, RUN_KIND), inputs=inputs)
    try:
        with ExitStack() as locks:
            for run_dir in outs:
                locks.enter_context(holding((run_dir, RUN_KIND), inputs=inputs))
            with progress(budget * len(specs), label) as advance:
                results = train_group(
                    specs, outs, embedding, device, advance, keep_checkpoint, bad_checkpoint, notice
                )
    except CheckpointError as error:
        raise BadInput(f"{error} (--bad-checkpoint refuse)") from None
    except CheckpointWriteError as error:
        raise click.ClickException(str(error)) from None
    except Diverged as error:
        raise Failed(str(error)) from None
    for run_dir, metrics in zip(outs, results, strict=True):
        click.echo(
            f"{run_dir}: final return {metrics['final_return']:.2f}, best "
            f"{metrics['best_return']:.2f}, {metrics['steps_per_second'] or 0:.0f} steps/s"
        )


MAX_GROUP = 4096  # seeds in one process: far more than a machine trains at once


def parse_seeds(text: str) -> list[int]:
    """``3``, ``0,1,2,3`` or ``0-3`` as a list of distinct seeds (:data:`ede.config.SEED_RANGE`),
    at most :data:`MAX_GROUP` of them."""
    try:
        if "-" in text.strip("-") and "," not in text:
            first, last = (int(part) for part in text.split("-"))
            ends = [first, last]
        else:
            ends = [int(part) for part in text.split(",")]
    except ValueError:
        raise BadInput(
            f"--seed {text!r}: expected a seed, a list (0,1,2) or a range (0-3)"
        ) from None
    if not all(map(is_seed, ends)):  # before a range is built: its ends may be anything
        raise BadInput(f"--seed {text}: expected distinct seeds {SEED_RANGE}")
    seeds = list(range(ends[0], ends[1] + 1)) if "-" in text else ends
    if not seeds or len(set(seeds)) != len(seeds):
        raise BadInput(
            f"--seed {text}: expected distinct seeds {SEED_RANGE}, a range's first "
            "no greater than its last"
        )
    if len(seeds) > MAX_GROUP:
        raise BadInput(
            f"--seed {text}: {len(seeds)} seeds; expected at most {MAX_GROUP} in one process"
        )
    return seeds


def run_dirs(task: str, algo: str, seeds: list[int], out: Path | None) -> list[Path]:
    """Each seed's run directory: ``--out`` (a pattern with ``{seed}`` for several) or the
    layout's."""
    if out is None:
        return [layout.run(task, algo, seed) for seed in seeds]
    if len(seeds) == 1:
        return [out]
    if "{seed}" not in str(out):
        raise BadInput(
            f"--out {out}: several seeds need a pattern with {{seed}}, e.g. runs/seed{{seed}}"
        )
    return [Path(str(out).replace("{seed}", str(seed))) for seed in seeds]
