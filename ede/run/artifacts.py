"""Saving and loading embedding artifacts: safetensors weights beside JSON metadata. No pickle.

An artifact is a directory holding ``weights.safetensors`` and ``meta.json``; the metadata is
validated by a pydantic model and records two checksums, each verified on loading: ``weights_sha256``
of the weights file and ``meta_sha256`` of the metadata's own result-relevant fields (every field
but :data:`PROVENANCE` and the two checksums), so an edited, tampered or mismatched file is refused
with a clear error. An artifact's :attr:`~ArtifactMeta.identity` is one SHA-256 over both: every
byte that changes what it computes. A decoder records its encoder's identity, so the decoder's
identity names the whole embedding; EDE-TD3 runs record it. :func:`params_mismatches` names every
way an artifact contradicts the params in force (its ``k``, ``dim`` and the recorded training params).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any, Literal, TypeVar

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from safetensors import SafetensorError
from safetensors.torch import load_file
from torch import nn

from ede.config import DecoderConfig, EmbeddingConfig, result_neutral
from ede.io.atomic import save_tensors, sha256, write_atomically
from ede.io.provenance import software_versions
from ede.io.rollouts import Whitening
from ede.method.embedding import ActionDecoder, ActionEmbedding, Encoder, EncoderResult, Predictor

__all__ = [
    "ArtifactError",
    "ArtifactMeta",
    "DecoderMeta",
    "EncoderMeta",
    "WhiteningMeta",
    "load_action_embedding",
    "load_encoder",
    "params_mismatches",
    "save_decoder",
    "save_encoder",
]

WEIGHTS = "weights.safetensors"
META = "meta.json"
AGAIN = "make it again (`ede-pipeline pretrain`)"
# Metadata fields that record how an artifact was made, not what it computes.
PROVENANCE = frozenset({"software"})


class ArtifactError(ValueError):
    """An artifact that cannot be used; the message names the path and what is wrong."""


class _Meta(BaseModel):
    model_config = ConfigDict(extra="forbid")


class WhiteningMeta(_Meta):
    mean: list[float]
    std: list[float] = Field(description="per-column standard deviation, > 0")

    @classmethod
    def of(cls, whitening: Whitening) -> WhiteningMeta:
        return cls(mean=whitening.mean.tolist(), std=whitening.std.tolist())

    def whitening(self) -> Whitening:
        return Whitening(np.asarray(self.mean), np.asarray(self.std))


class ActionSpaceMeta(_Meta):
    low: list[float]
    high: list[float]


class ArtifactMeta(_Meta):
    """What every artifact's metadata records about itself: its provenance and its checksums."""

    software: dict[str, str] = Field(description="the versions that made it (ede.io.provenance)")
    weights_sha256: str = Field(description="the SHA-256 of the weights file")
    meta_sha256: str = Field(description="the SHA-256 of this metadata's result-relevant fields")

    def content_sha256(self) -> str:
        """The SHA-256 of the result-relevant fields as they are: what ``meta_sha256`` must be."""
        content = self.model_dump(
            mode="json", exclude=set(PROVENANCE | {"weights_sha256", "meta_sha256"})
        )
        return hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()

    @property
    def identity(self) -> str:
        """The artifact's identity: the SHA-256 of ``"<weights_sha256> <meta_sha256>"``, which
        covers every byte of the weights and every result-relevant field of the metadata."""
        return hashlib.sha256(f"{self.weights_sha256} {self.meta_sha256}".encode()).hexdigest()


class EncoderMeta(ArtifactMeta):
    kind: Literal["ede-encoder"] = "ede-encoder"
    family: str
    env_id: str
    k: int = Field(gt=0)
    dim: int = Field(gt=0)
    state_size: int = Field(gt=0)
    action_space: ActionSpaceMeta
    hidden: list[int]
    state_whitening: WhiteningMeta
    delta_whitening: WhiteningMeta
    code_whitening: WhiteningMeta
    train_episodes: list[int]
    holdout_episodes: list[int]
    params: dict[str, Any] = Field(description="the params sections that made it")
    data_fingerprint: str


class DecoderMeta(ArtifactMeta):
    kind: Literal["ede-decoder"] = "ede-decoder"
    family: str
    k: int = Field(gt=0)
    dim: int = Field(gt=0)
    action_space: ActionSpaceMeta
    hidden: list[int]
    bound: float = Field(gt=0, description="largest whitened |z| seen: the EDE actor's bound")
    output_range: Literal["bounds", "unit"] = Field(
        "bounds", description="the decoder's squashing (DecoderConfig.output_range)"
    )
    code_whitening: WhiteningMeta
    params: dict[str, Any]
    data_fingerprint: str
    encoder_sha256: str = Field(description="the identity of the encoder this decoder inverts")


# What each artifact's folder is called where a stage refuses to replace another's.
KIND: dict[type, str] = {EncoderMeta: "encoder", DecoderMeta: "decoder"}


def _save(
    path: Path, modules: dict[str, nn.Module], meta: dict[str, Any], model: type[ArtifactMeta]
) -> None:
    def write(tmp: Path) -> None:
        tensors = {
            f"{name}.{key}": value.detach().cpu().contiguous()
            for name, module in modules.items()
            for key, value in module.state_dict().items()
        }
        save_tensors(tensors, tmp / WEIGHTS)
        validated = model.model_validate(
            {
                **meta,
                "software": software_versions(),
                "weights_sha256": sha256(tmp / WEIGHTS),
                "meta_sha256": "",
            }
        )
        sealed = validated.model_copy(update={"meta_sha256": validated.content_sha256()})
        (tmp / META).write_text(sealed.model_dump_json(indent=2) + "\n")

    write_atomically(Path(path), write, kind=KIND[model])


M = TypeVar("M", bound=ArtifactMeta)


def _load_meta(path: Path, model: type[M]) -> tuple[M, dict[str, torch.Tensor]]:
    meta_file, weights_file = path / META, path / WEIGHTS
    if not meta_file.is_file() or not weights_file.is_file():
        raise ArtifactError(
            f"{path}: no {model.__name__.removesuffix('Meta').lower()} here "
            f"(expected {META} and {WEIGHTS}; run `ede-pipeline pretrain`)"
        )
    try:
        meta = model.model_validate_json(meta_file.read_bytes())  # UTF-8 JSON, or one line
    except ValidationError as error:
        first = error.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        if first["loc"] == ("meta_sha256",) and first["type"] == "missing":
            raise ArtifactError(
                f"{meta_file}: records no meta_sha256 (made by an earlier version); {AGAIN}"
            ) from None
        raise ArtifactError(f"{meta_file}: {where + ': ' if where else ''}{first['msg']}") from None
    if meta.content_sha256() != meta.meta_sha256:
        raise ArtifactError(
            f"{meta_file}: does not match its checksum (meta_sha256): edited or "
            f"damaged since it was made; {AGAIN}"
        )
    if sha256(weights_file) != meta.weights_sha256:
        raise ArtifactError(f"{weights_file}: does not match the checksum in {META}")
    try:
        tensors = load_file(weights_file)
    except (SafetensorError, OSError) as error:
        raise ArtifactError(f"{weights_file}: unreadable ({error})") from None
    return meta, tensors


def _fill(path: Path, name: str, module: nn.Module, tensors: dict[str, torch.Tensor]) -> None:
    """Load ``name.*`` tensors into ``module``, checking every name and shape first."""
    expected = module.state_dict()
    found = {k.removeprefix(f"{name}."): v for k, v in tensors.items() if k.startswith(f"{name}.")}
    if set(found) != set(expected):
        missing, extra = set(expected) - set(found), set(found) - set(expected)
        raise ArtifactError(
            f"{path / WEIGHTS}: {name} tensors differ (missing {sorted(missing)}, "
            f"unexpected {sorted(extra)})"
        )
    for key, value in expected.items():
        if found[key].shape != value.shape:
            raise ArtifactError(
                f"{path / WEIGHTS}: {name}.{key} has shape {tuple(found[key].shape)}, "
                f"expected {tuple(value.shape)} from {META}"
            )
    module.load_state_dict(found)


def save_encoder(
    path: Path,
    result: EncoderResult,
    *,
    family: str,
    env_id: str,
    low: np.ndarray,
    high: np.ndarray,
    params: dict[str, Any],
    data_fingerprint: str,
) -> None:
    encoder = result.encoder
    hidden = [m.out_features for m in encoder.body if isinstance(m, nn.Linear)]
    meta = {
        "family": family,
        "env_id": env_id,
        "k": encoder.k,
        "dim": encoder.dim,
        "state_size": len(result.state_whitening.mean),
        "action_space": {"low": low.tolist(), "high": high.tolist()},
        "hidden": hidden,
        "state_whitening": WhiteningMeta.of(result.state_whitening),
        "delta_whitening": WhiteningMeta.of(result.delta_whitening),
        "code_whitening": WhiteningMeta.of(result.code_whitening),
        "train_episodes": result.train_episodes.tolist(),
        "holdout_episodes": result.holdout_episodes.tolist(),
        "params": params,
        "data_fingerprint": data_fingerprint,
    }
    _save(path, {"encoder": encoder, "predictor": result.predictor}, meta, EncoderMeta)


def load_encoder(
    path: str | Path, device: torch.device | str = "cpu"
) -> tuple[EncoderMeta, EncoderResult]:
    """Load an encoder artifact as an :class:`EncoderResult` (history and metrics empty)."""
    path = Path(path)
    meta, tensors = _load_meta(path, EncoderMeta)
    action_size = len(meta.action_space.low)
    encoder = Encoder(meta.k, action_size, meta.dim, meta.hidden)
    predictor = Predictor(meta.state_size, meta.dim, meta.hidden)
    _fill(path, "encoder", encoder, tensors)
    _fill(path, "predictor", predictor, tensors)
    result = EncoderResult(
        encoder=encoder.to(device).eval(),
        predictor=predictor.to(device).eval(),
        state_whitening=meta.state_whitening.whitening(),
        delta_whitening=meta.delta_whitening.whitening(),
        code_whitening=meta.code_whitening.whitening(),
        train_episodes=np.asarray(meta.train_episodes, dtype=int),
        holdout_episodes=np.asarray(meta.holdout_episodes, dtype=int),
    )
    return meta, result


def save_decoder(
    path: Path,
    decoder: ActionDecoder,
    bound: float,
    *,
    encoder_path: Path,
    params: dict[str, Any],
) -> None:
    encoder_meta, _ = _load_meta(Path(encoder_path), EncoderMeta)
    hidden = [m.out_features for m in decoder.net if isinstance(m, nn.Linear)][:-1]
    meta = {
        "family": encoder_meta.family,
        "k": decoder.k,
        "dim": encoder_meta.dim,
        "action_space": encoder_meta.action_space,
        "hidden": hidden,
        "bound": bound,
        "output_range": decoder.output_range,
        "code_whitening": encoder_meta.code_whitening,
        "params": params,
        "data_fingerprint": encoder_meta.data_fingerprint,
        "encoder_sha256": encoder_meta.identity,
    }
    _save(path, {"decoder": decoder}, meta, DecoderMeta)


def load_action_embedding(
    encoder_path: str | Path | None, decoder_path: str | Path, device: torch.device | str = "cpu"
) -> tuple[DecoderMeta, ActionEmbedding]:
    """The ready :class:`ActionEmbedding` of a family: its encoder and the decoder that inverts it.
    Without ``encoder_path``, the decoder alone (which names its encoder): an embedding that
    decodes, for playing a trained policy from a published decoder.

    Raises:
        ArtifactError: missing, tampered or mismatched artifacts.
    """
    decoder_path = Path(decoder_path)
    encoder = None
    meta, tensors = _load_meta(decoder_path, DecoderMeta)
    if encoder_path is not None:
        encoder_meta, encoded = load_encoder(encoder_path)
        if meta.encoder_sha256 != encoder_meta.identity:
            raise ArtifactError(
                f"{decoder_path}: was trained against another encoder than {encoder_path}"
            )
        encoder = encoded.encoder
    low, high = np.asarray(meta.action_space.low), np.asarray(meta.action_space.high)
    decoder = ActionDecoder(meta.dim, meta.k, low, high, meta.hidden, meta.output_range)
    _fill(decoder_path, "decoder", decoder, tensors)
    embedding = ActionEmbedding(encoder, decoder, meta.code_whitening.whitening(), meta.bound)
    return meta, embedding.to(device)


def params_mismatches(
    path: str | Path,
    meta: EncoderMeta | DecoderMeta,
    embedding: EmbeddingConfig,
    decoder: DecoderConfig | None = None,
    action_size: int | None = None,
) -> list[str]:
    """Every way an artifact contradicts the params in force, one line each.

    ``k`` and ``dim`` are compared as the artifact has them; every other param recorded in
    ``meta.params`` (all but the result-neutral ones, :func:`ede.config.result_neutral`) is
    compared key by key, and a key recorded on one side only is a contradiction too.

    Args:
        path: the artifact's directory, which each line names.
        meta: its metadata, from :func:`load_encoder` or :func:`load_action_embedding`.
        embedding: the ``embedding`` params in force.
        decoder: the ``decoder`` params in force, to check a decoder's own params as well
            (a :class:`DecoderMeta` records both sections, an :class:`EncoderMeta` only ``embedding``).
        action_size: what a null ``embedding.dim`` means; default: the artifact's action size.

    Returns:
        Lines such as ``data/families/reacher/embedding/encoder: made with embedding.k = 4, but
        params.yaml has embedding.k = 2``; none when the artifact agrees with the params.
    """
    lines: list[str] = []

    def differ(name: str, made: Any, given: str) -> None:
        lines.append(
            f"{path}: made with {name} = {_show(made)}, but params.yaml has {name} = {given}"
        )

    if meta.k != embedding.k:
        differ("embedding.k", meta.k, _show(embedding.k))
    size = len(meta.action_space.low) if action_size is None else action_size
    if meta.dim != (size if embedding.dim is None else embedding.dim):
        differ(
            "embedding.dim",
            meta.dim,
            _show(embedding.dim)
            if embedding.dim is not None
            else f"null (the action size, {size})",
        )
    sections: list[tuple[str, EmbeddingConfig | DecoderConfig]] = [("embedding", embedding)]
    if decoder is not None:
        sections.append(("decoder", decoder))
    for section, config in sections:
        recorded = meta.params.get(section)
        if not isinstance(recorded, dict):
            lines.append(
                f"{path}: records no {section} params, so it cannot be checked against "
                "params.yaml; make it again (`ede-pipeline pretrain`)"
            )
            continue
        given = config.model_dump(mode="json")
        done = result_neutral(type(config)) | ({"k", "dim"} if section == "embedding" else set())
        for key in [*given, *(key for key in recorded if key not in given)]:
            name = f"{section}.{key}"
            if key in done:
                continue
            if key not in recorded:
                lines.append(
                    f"{path}: made with no record of {name}, but params.yaml has "
                    f"{name} = {_show(given[key])}"
                )
            elif key not in given:
                lines.append(
                    f"{path}: made with {name} = {_show(recorded[key])}, which params.yaml "
                    "does not have"
                )
            elif recorded[key] != given[key]:
                differ(name, recorded[key], _show(given[key]))
    return lines


def _show(value: Any) -> str:
    """A param's value as params.yaml would spell it: null, true, [400, 400], 0.0001, marginal."""
    return value if isinstance(value, str) else json.dumps(value, allow_nan=False)
