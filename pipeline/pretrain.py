"""Stages 2 and 3, ``ede-pipeline pretrain encoder|decoder``: learn E and P, then D."""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any

import click
import numpy as np
import torch

from ede.config import Params
from ede.io.atomic import write_json, write_text
from ede.method.embedding import train_decoder, train_encoder
from ede.method.nets import pick_device
from ede.run.artifacts import (
    ArtifactError,
    load_encoder,
    params_mismatches,
    save_decoder,
    save_encoder,
)
from ede_pipeline import layout
from ede_pipeline.collect import open_rollouts
from ede_pipeline.common import BadInput, check_family, family_option, holding, params_option
from ede_pipeline.progress import progress


def _csv(rows: list[dict[str, float]]) -> str:
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return out.getvalue()


def _write_reports(result: Any, metrics: Path, plots: Path) -> dict[str, float]:
    """The held-out metrics (DVC metrics) and the per-epoch losses (DVC plots)."""
    write_json(metrics, result.metrics)
    write_text(plots, _csv(result.history))
    return result.metrics


def _device(name: str) -> Any:
    try:
        return pick_device(name)
    except ValueError as error:
        raise BadInput(str(error)) from None


def _paths_option(name: str) -> Any:
    def decorate(command: Any) -> Any:
        for option, what in (
            (
                "--out",
                f"{name} artifact directory  [default: data/families/<family>/embedding/{name}]",
            ),
            ("--metrics", f"held-out metrics JSON  [default: …/{name}_metrics.json]"),
            ("--plots", f"per-epoch losses CSV  [default: …/{name}_history.csv]"),
        ):
            command = click.option(option, type=click.Path(path_type=Path), help=what)(command)
        return command

    return decorate


def _rollouts_option(command: Any) -> Any:
    return click.option(
        "--rollouts",
        type=click.Path(path_type=Path),
        help="[default: data/families/<family>/rollouts.zarr]",
    )(command)


@click.group()
def pretrain() -> None:
    """Stages 2 and 3: the embedding of a family (encoder, then decoder)."""


@pretrain.command()
@family_option
@_rollouts_option
@_paths_option("encoder")
@params_option
def encoder(
    params: Params,
    family: str,
    rollouts: Path | None,
    out: Path | None,
    metrics: Path | None,
    plots: Path | None,
) -> None:
    """Train E and P on MSE + β·KL; held-out metrics against a mean-change baseline."""
    check_family(params, family)
    config = params.embedding
    device = _device(config.device)
    torch.set_num_threads(config.threads)
    data = open_rollouts(params, family, rollouts)
    if len(data.window_starts(config.k)) == 0:
        raise BadInput(f"{data.path}: no episode is longer than k={config.k} steps")
    if data.num_episodes < 2:
        raise BadInput(
            f"{data.path}: {data.num_episodes} episode; expected at least 2, one to "
            "train on and one to hold out (embedding.holdout): raise collect.steps "
            f"above the length of an episode of {data.attrs['env_id']}"
        )
    folder = layout.embedding(family)
    out = out or folder / "encoder"
    metrics = metrics or folder / "encoder_metrics.json"
    plots = plots or folder / "encoder_history.csv"
    files = ((metrics, "encoder metrics"), (plots, "encoder history"))
    with holding((out, "encoder"), files=files, inputs=(data.path,)):
        with progress(config.epochs, f"encoder {family}", unit="epoch") as advance:
            result = train_encoder(data, config, device, on_epoch=lambda row: advance(1))
        low, high = (np.asarray(data.attrs["spaces"][key]) for key in ("action_low", "action_high"))
        save_encoder(
            out,
            result,
            family=family,
            env_id=data.attrs["env_id"],
            low=low,
            high=high,
            params={"embedding": config.model_dump(mode="json")},
            data_fingerprint=data.attrs["fingerprint"],
        )
        m = _write_reports(result, metrics, plots)
    click.echo(
        f"encoder {family}: held-out prediction MSE {m['prediction_mse']:.4f} "
        f"({m['prediction_ratio']:.3f}x the mean-change baseline, raw actions "
        f"{m['raw_prediction_ratio']:.3f}x)"
    )


@pretrain.command()
@family_option
@_rollouts_option
@click.option(
    "--encoder",
    "encoder_path",
    type=click.Path(path_type=Path),
    help="[default: data/families/<family>/embedding/encoder]",
)
@_paths_option("decoder")
@params_option
def decoder(
    params: Params,
    family: str,
    rollouts: Path | None,
    encoder_path: Path | None,
    out: Path | None,
    metrics: Path | None,
    plots: Path | None,
) -> None:
    """Train D, the minimum-norm one-sided inverse of the frozen E."""
    check_family(params, family)
    config = params.decoder
    device = _device(config.device)
    torch.set_num_threads(config.threads)
    data = open_rollouts(params, family, rollouts)
    folder = layout.embedding(family)
    encoder_path = encoder_path or folder / "encoder"
    try:
        meta, encoded = load_encoder(encoder_path, device)
    except ArtifactError as error:
        raise BadInput(str(error)) from None
    mismatches = params_mismatches(
        encoder_path, meta, params.embedding, action_size=data.action.shape[1]
    )
    if mismatches:
        raise BadInput("\n".join(mismatches))
    if meta.family != family or meta.data_fingerprint != data.attrs["fingerprint"]:
        raise BadInput(
            f"{encoder_path}: trained on family {meta.family}'s rollouts "
            f"{meta.data_fingerprint[:12]}, not on {data.path} ({family})"
        )
    low, high = np.asarray(meta.action_space.low), np.asarray(meta.action_space.high)
    out = out or folder / "decoder"
    metrics = metrics or folder / "decoder_metrics.json"
    plots = plots or folder / "decoder_history.csv"
    files = ((metrics, "decoder metrics"), (plots, "decoder history"))
    with holding((out, "decoder"), files=files, inputs=(data.path, encoder_path)):
        with progress(config.epochs, f"decoder {family}", unit="epoch") as advance:
            result = train_decoder(
                data, encoded, config, meta.k, low, high, device, on_epoch=lambda row: advance(1)
            )
        save_decoder(
            out,
            result.decoder,
            result.bound,
            encoder_path=encoder_path,
            params={"decoder": config.model_dump(mode="json"), **meta.params},
        )
        m = _write_reports(result, metrics, plots)
    click.echo(
        f"decoder {family}: held-out inverse error {m['inverse_error']:.4f} of the code variance, "
        f"{100 * m['at_bounds']:.1f}% of actions at a bound, |z| bound {m['bound']:.2f}"
    )
