"""An artifact's identity covers every byte that changes a result: its weights and its metadata.

Editing a result-relevant field of ``meta.json`` is refused as an edit; an edit sealed again (its
``meta_sha256`` recomputed) is an artifact of another identity, which EDE-TD3 runs record.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from safetensors.torch import load_file, save_file

from ede.config import load_params
from ede.io.atomic import sha256
from ede.io.rollouts import Whitening
from ede.method.embedding import ActionDecoder, Encoder, EncoderResult, Predictor
from ede.run.artifacts import (
    ArtifactError,
    ArtifactMeta,
    DecoderMeta,
    EncoderMeta,
    load_action_embedding,
    load_encoder,
    save_decoder,
    save_encoder,
)
from ede_pipeline.cli import main

TASK, STATES, ACTIONS = "ede/Point-v0", 4, 2
LOW, HIGH = -np.ones(ACTIONS), np.ones(ACTIONS)
Edit = Callable[[dict[str, Any]], None]


@pytest.fixture
def params(write_params, tiny_pipeline) -> Path:
    def edit(p: dict[str, Any]) -> None:
        tiny_pipeline(p)
        p["runs"].update(tasks={TASK: "point"}, budgets={TASK: 200})

    return write_params(edit)


@pytest.fixture
def saved(tmp_path: Path, params: Path) -> tuple[Path, Path]:
    """A tiny untrained point embedding made with the params, saved as `pretrain` saves it."""
    config = load_params(params)
    embedding, decoder = config.embedding, config.decoder
    torch.manual_seed(0)
    whitening = Whitening(np.zeros(STATES), np.ones(STATES))
    result = EncoderResult(
        Encoder(embedding.k, ACTIONS, ACTIONS, embedding.hidden),
        Predictor(STATES, ACTIONS, embedding.hidden),
        whitening,
        whitening,
        Whitening(np.zeros(ACTIONS), np.ones(ACTIONS)),
    )
    recorded = {"embedding": embedding.model_dump(mode="json")}
    encoder_dir, decoder_dir = tmp_path / "encoder", tmp_path / "decoder"
    save_encoder(
        encoder_dir,
        result,
        family="point",
        env_id=TASK,
        low=LOW,
        high=HIGH,
        params=recorded,
        data_fingerprint="f" * 64,
    )
    save_decoder(
        decoder_dir,
        ActionDecoder(ACTIONS, embedding.k, LOW, HIGH, decoder.hidden),
        1.5,
        encoder_path=encoder_dir,
        params={"decoder": decoder.model_dump(mode="json"), **recorded},
    )
    return encoder_dir, decoder_dir


def edit(folder: Path, change: Edit, model: type[ArtifactMeta] | None = None) -> None:
    """Apply ``change`` to ``folder``'s meta.json; with ``model``, seal it again as its maker would."""
    meta_file = folder / "meta.json"
    data = json.loads(meta_file.read_text())
    change(data)
    if model is not None:
        data["meta_sha256"] = model.model_validate(data).content_sha256()
    meta_file.write_text(json.dumps(data, indent=2))


def identity(saved: tuple[Path, Path]) -> str:
    return load_action_embedding(*saved)[0].identity


def set_first(key: str, field: str, value: float) -> Edit:
    return lambda data: data[key][field].__setitem__(0, value)


DECODER_EDITS: dict[str, Edit] = {
    "bound": lambda data: data.update(bound=100.0),
    "output_range": lambda data: data.update(output_range="unit"),
    "code whitening": set_first("code_whitening", "mean", 0.5),
    "action space": set_first("action_space", "high", 2.0),
    "a param": lambda data: data["params"]["decoder"].update(lam=1.0),
    "a recorded embedding param": lambda data: data["params"]["embedding"].update(beta=0.5),
    "data fingerprint": lambda data: data.update(data_fingerprint="0" * 64),
}
DECODER_REFUSED_ONLY: dict[str, Edit] = {  # edits that also break the weights or the encoder link
    "k": lambda data: data.update(k=2),
    "hidden": lambda data: data.update(hidden=[8, 8]),
    "encoder": lambda data: data.update(encoder_sha256="0" * 64),
}
ENCODER_EDITS: dict[str, Edit] = {
    "action space": set_first("action_space", "high", 2.0),
    "code whitening": set_first("code_whitening", "std", 3.0),
    "state whitening": set_first("state_whitening", "mean", 0.5),
    "a param": lambda data: data["params"]["embedding"].update(beta=0.5),
}
ENCODER_REFUSED_ONLY: dict[str, Edit] = {
    "k": lambda data: data.update(k=2),
    "dim": lambda data: data.update(dim=3),
}


def refused_as_edited(saved: tuple[Path, Path], part: int) -> None:
    with pytest.raises(ArtifactError) as error:
        load_action_embedding(*saved)
    message = str(error.value)
    assert message.startswith(f"{saved[part] / 'meta.json'}: does not match its checksum"), message
    assert "\n" not in message and "make it again" in message


@pytest.mark.parametrize(
    "change",
    [*DECODER_EDITS.values(), *DECODER_REFUSED_ONLY.values()],
    ids=[*DECODER_EDITS, *DECODER_REFUSED_ONLY],
)
def test_an_edited_decoder_meta_is_refused_in_one_line(
    saved: tuple[Path, Path], change: Edit
) -> None:
    edit(saved[1], change)
    refused_as_edited(saved, 1)


@pytest.mark.parametrize(
    "change",
    [*ENCODER_EDITS.values(), *ENCODER_REFUSED_ONLY.values()],
    ids=[*ENCODER_EDITS, *ENCODER_REFUSED_ONLY],
)
def test_an_edited_encoder_meta_is_refused_in_one_line(
    saved: tuple[Path, Path], change: Edit
) -> None:
    edit(saved[0], change)
    refused_as_edited(saved, 0)
    with pytest.raises(ArtifactError, match="does not match its checksum"):
        load_encoder(saved[0])


@pytest.mark.parametrize("change", DECODER_EDITS.values(), ids=DECODER_EDITS)
def test_a_decoder_edit_sealed_again_is_another_identity(
    saved: tuple[Path, Path], change: Edit
) -> None:
    before = identity(saved)
    edit(saved[1], change, DecoderMeta)
    assert identity(saved) != before


@pytest.mark.parametrize("change", ENCODER_EDITS.values(), ids=ENCODER_EDITS)
def test_an_encoder_edit_sealed_again_is_another_identity_its_decoder_does_not_invert(
    saved: tuple[Path, Path], change: Edit
) -> None:
    before = load_encoder(saved[0])[0].identity
    edit(saved[0], change, EncoderMeta)
    assert load_encoder(saved[0])[0].identity != before
    with pytest.raises(ArtifactError, match="trained against another encoder"):
        load_action_embedding(*saved)


def test_other_weights_are_another_identity(saved: tuple[Path, Path]) -> None:
    before = identity(saved)
    weights = saved[1] / "weights.safetensors"
    tensors = load_file(weights)
    tensors["decoder.net.0.bias"] = tensors["decoder.net.0.bias"] + 1
    save_file(tensors, weights)
    with pytest.raises(ArtifactError, match="does not match the checksum"):
        load_action_embedding(*saved)
    edit(saved[1], lambda data: data.update(weights_sha256=sha256(weights)))
    assert identity(saved) != before


@pytest.mark.parametrize("part", [0, 1])
def test_the_software_that_made_it_is_provenance_not_identity(
    saved: tuple[Path, Path], part: int
) -> None:
    before = identity(saved)
    edit(saved[part], lambda data: data.update(software={"python": "2.7", "torch": "0.1"}))
    assert identity(saved) == before


def test_the_decoder_records_the_encoders_whole_identity(saved: tuple[Path, Path]) -> None:
    encoder = load_encoder(saved[0])[0]
    decoder = load_action_embedding(*saved)[0]
    assert decoder.encoder_sha256 == encoder.identity != encoder.weights_sha256


@pytest.mark.parametrize("part", [0, 1])
def test_an_artifact_made_before_metadata_checksums_is_one_line(
    saved: tuple[Path, Path], part: int
) -> None:
    edit(saved[part], lambda data: data.pop("meta_sha256"))
    with pytest.raises(ArtifactError) as error:
        load_action_embedding(*saved)
    assert str(error.value) == (
        f"{saved[part] / 'meta.json'}: records no meta_sha256 (made by an "
        "earlier version); make it again (`ede-pipeline pretrain`)"
    )


def train(params: Path, saved: tuple[Path, Path], out: Path):
    return CliRunner().invoke(
        main,
        [
            "train",
            "--task",
            TASK,
            "--algo",
            "ede-td3",
            "--seed",
            "0",
            "--out",
            str(out),
            "--encoder",
            str(saved[0]),
            "--decoder",
            str(saved[1]),
            "--params",
            str(params),
        ],
    )


def test_an_ede_td3_run_records_the_embeddings_identity(
    params: Path, saved: tuple[Path, Path], tmp_path: Path
) -> None:
    out = tmp_path / "run"
    result = train(params, saved, out)
    assert result.exit_code == 0, result.output
    expected = identity(saved)
    assert json.loads((out / "run.json").read_text())["embedding"] == expected
    assert json.loads((out / "policy" / "policy.json").read_text())["embedding"] == expected


def test_train_refuses_an_edited_decoder_in_one_line_and_writes_nothing(
    params: Path, saved: tuple[Path, Path], tmp_path: Path
) -> None:
    edit(saved[1], DECODER_EDITS["bound"])
    out = tmp_path / "run"
    result = train(params, saved, out)
    assert result.exit_code == 2, result.output
    assert result.stderr.count("\n") == 1 and "Traceback" not in result.output
    assert f"Error: {saved[1] / 'meta.json'}: does not match its checksum" in result.stderr
    assert not out.exists()
