"""Stage 4, ``ede-pipeline train``: one TD3 or EDE-TD3 run of one task and seed."""

from __future__ import annotations

import functools
from pathlib import Path

import click
import torch

from ede.artifacts import ArtifactError, load_action_embedding, params_mismatches
from ede.config import ALGOS, Params
from ede.nets import pick_device
from ede.training import CheckpointError, CheckpointWriteError, RunSpec, train_run
from ede_pipeline import layout
from ede_pipeline.common import BadInput, holding, params_option
from ede_pipeline.progress import progress


@click.command()
@click.option("--task", required=True, help="A task of params.yaml's runs.tasks.")
@click.option("--algo", required=True, help="td3 or ede-td3.")
@click.option("--seed", type=int, required=True, help="Seed of the run (>= 0).")
@click.option("--out", type=click.Path(path_type=Path),
              help="Run directory  [default: data/runs/<task>/<algo>/seed<N>]")
@click.option("--encoder", type=click.Path(path_type=Path),
              help="EDE-TD3: the family's encoder  [default: data/<family>/embedding/encoder]")
@click.option("--decoder", type=click.Path(path_type=Path),
              help="EDE-TD3: the family's decoder  [default: data/<family>/embedding/decoder]")
@click.option("--keep-checkpoint", is_flag=True,
              help="Keep the checkpoint (replay buffer included) once the run is complete.")
@click.option("--bad-checkpoint", type=click.Choice(["restart", "refuse"]), default="restart",
              show_default=True,
              help="A checkpoint that is damaged or another run's: move it aside to "
                   "checkpoint.bad-<time> and start over, or refuse (exit 2) and touch nothing.")
@params_option
def train(
    params: Params, task: str, algo: str, seed: int, out: Path | None, encoder: Path | None,
    decoder: Path | None, keep_checkpoint: bool, bad_checkpoint: str,
) -> None:
    """Stage 4: train one run; resumes from its checkpoint if one of the same run exists."""
    if algo not in ALGOS:
        raise BadInput(f"--algo {algo!r}: unknown; expected one of {', '.join(ALGOS)}")
    if seed < 0:
        raise BadInput(f"--seed {seed}: expected a seed >= 0")
    families = [family for family, tasks in params.runs.tasks.items() if task in tasks]
    if not families:
        raise BadInput(f"--task {task!r}: not in params.yaml's runs.tasks "
                       f"({', '.join(params.runs.all_tasks)})")
    family = families[0]
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
            raise BadInput(f"{error} (EDE-TD3 on {task} needs the {family} family's embedding)") from None
        if meta.family != family:
            raise BadInput(f"{decoder or folder / 'decoder'}: the embedding of family "
                           f"{meta.family}, but {task} is in family {family}")
        mismatches = params_mismatches(decoder or folder / "decoder", meta, params.embedding,
                                       params.decoder)
        if mismatches:
            raise BadInput("\n".join(mismatches))
        embedding_id = meta.weights_sha256
    torch.set_num_threads(config.threads)
    spec = RunSpec(task, algo, seed, params.runs.budgets[task], config, params.ede_td3, embedding_id)
    out = out or layout.run(task, algo, seed)
    notice = functools.partial(click.echo, err=True)
    try:
        with holding(out), progress(spec.budget, f"{algo} {task} seed {seed}") as advance:
            metrics = train_run(spec, out, embedding, device, advance, keep_checkpoint,
                                bad_checkpoint, notice)
    except CheckpointError as error:
        raise BadInput(f"{error} (--bad-checkpoint refuse)") from None
    except CheckpointWriteError as error:
        raise click.ClickException(str(error)) from None
    click.echo(f"{out}: final return {metrics['final_return']:.2f}, best {metrics['best_return']:.2f}, "
               f"{metrics['steps_per_second'] or 0:.0f} steps/s")
