"""Stage 1, ``ede-pipeline collect``: random-policy rollouts of a family's source task."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import click
import numpy as np

from ede.config import Params, episode_length
from ede.io.provenance import software_versions
from ede.io.rollouts import KIND as ROLLOUTS
from ede.io.rollouts import Rollouts, RolloutsError, state_source, write_store
from ede.run.collect import collect as collect_steps
from ede.run.collect import row_bytes
from ede.tasks import action_bounds, make
from ede_pipeline import layout
from ede_pipeline.common import (
    USABLE_SHARE,
    BadInput,
    available_memory,
    check_family,
    family_option,
    holding,
    in_units,
    params_option,
)
from ede_pipeline.progress import progress


@click.command()
@family_option
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    help="Store to write  [default: data/families/<family>/rollouts.zarr]",
)
@click.option("--workers", type=click.IntRange(min=1), help="Processes  [default: one per core]")
@params_option
def collect(params: Params, family: str, out: Path | None, workers: int | None) -> None:
    """Stage 1: random steps of a family's source task into a Zarr store."""
    check_family(params, family)
    out = out or layout.rollouts(family)
    env_id = params.families[family].source
    config = params.collect
    num_envs = config.num_envs or default_num_envs(config.steps, episode_length(env_id))
    check_collect_memory(env_id, config.steps)
    with holding((out, ROLLOUTS)), progress(config.steps, f"collect {family}") as advance:
        arrays = collect_steps(
            env_id, config.steps, num_envs, config.seed, workers, advance, config.saturated_episodes
        )
        write_store(out, arrays, store_attrs(params, family, num_envs, arrays))
    click.echo(f"{out}: {len(arrays['reward'])} steps, {int(arrays['episode'][-1]) + 1} episodes")


def check_collect_memory(env_id: str, steps: int) -> None:
    """Refuse more steps than this machine can hold, before any work: collect keeps every
    episode's rows, then their concatenation (twice the store's rows), a row's size read from the
    task's spaces and state (:func:`ede.run.collect.row_bytes`, no episode stepped); pretrain loads
    the store whole again.

    Raises:
        BadInput: naming the key, the steps, the memory they need and what is available.
    """
    row = row_bytes(env_id)
    need, free = 2 * steps * row, available_memory()
    if need > USABLE_SHARE * free:
        raise BadInput(
            f"collect.steps: {steps:,} steps of {env_id} need about {in_units(need)} of memory "
            f"(collected whole, {row} bytes a step, twice), more than {USABLE_SHARE:.0%} of the "
            f"{in_units(free)} available; at most {int(USABLE_SHARE * free) // (2 * row):,} fit"
        )


def default_num_envs(steps: int, length: int | None) -> int:
    """``collect.num_envs: null``: one sub-environment per core, but no more than the steps hold
    whole episodes of (each records one at least: more would record more steps than asked)."""
    cores = os.cpu_count() or 1
    return max(1, min(cores, steps // length if length else steps))


def store_attrs(
    params: Params, family: str, num_envs: int, arrays: dict[str, np.ndarray]
) -> dict[str, Any]:
    env = make(params.families[family].source)
    try:
        low, high = action_bounds(env)
        spaces = {
            "observation_shape": list(env.observation_space.shape or ()),
            "action_low": low.tolist(),
            "action_high": high.tolist(),
            "state_size": int(arrays["state"].shape[1]),
        }
        source = state_source(env)
    finally:
        env.close()
    return {
        "env_id": params.families[family].source,
        "family": family,
        "state_source": source,  # what the state column is: "physics" or "observation"
        "seed": params.collect.seed,
        "steps": params.collect.steps,
        "num_envs": num_envs,
        "spaces": spaces,
        "params": {"collect": params.collect.model_dump(mode="json")},
        "software": software_versions(),
    }


def open_rollouts(params: Params, family: str, path: Path | None) -> Any:
    """Open a family's store, turning every problem with it into one line of bad input."""
    try:
        return Rollouts.open(path or layout.rollouts(family), env_id=params.families[family].source)
    except RolloutsError as error:
        raise BadInput(str(error)) from None


@click.command("inspect")
@family_option
@click.option("--rollouts", "path", type=click.Path(path_type=Path), help="Store to read.")
@params_option
def inspect_rollouts(params: Params, family: str, path: Path | None) -> None:
    """Check a family's rollouts store and summarise it."""
    check_family(params, family)
    rollouts = open_rollouts(params, family, path)
    state, delta = rollouts.whitening(params.embedding.k)
    click.echo(f"{rollouts.path}: {rollouts.attrs['env_id']}, seed {rollouts.attrs['seed']}")
    click.echo(f"  {len(rollouts)} steps in {rollouts.num_episodes} episodes")
    click.echo(f"  state size {rollouts.state.shape[1]}, action size {rollouts.action.shape[1]}")
    click.echo(
        f"  {len(rollouts.window_starts(params.embedding.k))} windows of k={params.embedding.k}"
    )
    click.echo(
        f"  whitening: state std {state.std.min():.3g} to {state.std.max():.3g}, "
        f"{params.embedding.k}-step change std {delta.std.min():.3g} to {delta.std.max():.3g}"
    )
    click.echo(f"  fingerprint {rollouts.attrs['fingerprint']}")
