"""An embedding artifact checked against the params in force: each contradiction named, one line each."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from ede.config import DecoderConfig, EmbeddingConfig
from ede.io.rollouts import Whitening
from ede.method.embedding import ActionDecoder, Encoder, EncoderResult, Predictor
from ede.run.artifacts import (
    DecoderMeta,
    EncoderMeta,
    load_action_embedding,
    load_encoder,
    params_mismatches,
    save_decoder,
    save_encoder,
)

K, ACTIONS, STATES = 3, 2, 4
LOW, HIGH = -np.ones(ACTIONS), np.ones(ACTIONS)
EMBEDDING = EmbeddingConfig(k=K, hidden=[8], beta=1e-3, epochs=1)  # dim null: the action size
DECODER = DecoderConfig(hidden=[8], lam=1e-3, epochs=1)


def whitening(size: int) -> Whitening:
    return Whitening(np.zeros(size), np.ones(size))


@pytest.fixture
def saved(tmp_path: Path) -> tuple[Path, Path]:
    """A tiny untrained encoder and decoder, saved as `ede-pipeline pretrain` saves them."""
    torch.manual_seed(0)
    encoder = Encoder(K, ACTIONS, ACTIONS, EMBEDDING.hidden)
    result = EncoderResult(
        encoder,
        Predictor(STATES, ACTIONS, EMBEDDING.hidden),
        whitening(STATES),
        whitening(STATES),
        whitening(ACTIONS),
    )
    encoder_dir, decoder_dir = tmp_path / "encoder", tmp_path / "decoder"
    embedding_params = {"embedding": EMBEDDING.model_dump(mode="json")}
    save_encoder(
        encoder_dir,
        result,
        family="point",
        env_id="ede/Point-v0",
        low=LOW,
        high=HIGH,
        params=embedding_params,
        data_fingerprint="f" * 64,
    )
    decoder = ActionDecoder(ACTIONS, K, LOW, HIGH, DECODER.hidden)
    save_decoder(
        decoder_dir,
        decoder,
        1.0,
        encoder_path=encoder_dir,
        params={"decoder": DECODER.model_dump(mode="json"), **embedding_params},
    )
    return encoder_dir, decoder_dir


def metas(saved: tuple[Path, Path]) -> tuple[EncoderMeta, DecoderMeta]:
    return load_encoder(saved[0])[0], load_action_embedding(*saved)[0]


def test_the_params_it_was_made_with_give_no_lines(saved: tuple[Path, Path]) -> None:
    encoder, decoder = metas(saved)
    assert params_mismatches(saved[0], encoder, EMBEDDING) == []
    assert params_mismatches(saved[1], decoder, EMBEDDING, DECODER) == []
    assert params_mismatches(saved[0], encoder, EMBEDDING, action_size=ACTIONS) == []
    assert params_mismatches(saved[0], encoder, EMBEDDING.model_copy(update={"dim": ACTIONS})) == []


def test_where_and_how_fast_it_was_made_do_not_matter(saved: tuple[Path, Path]) -> None:
    elsewhere = {"device": "auto", "threads": 4}
    _, decoder = metas(saved)
    assert (
        params_mismatches(
            saved[1],
            decoder,
            EMBEDDING.model_copy(update=elsewhere),
            DECODER.model_copy(update=elsewhere),
        )
        == []
    )


@pytest.mark.parametrize(
    ("key", "value", "line"),
    [
        ("k", 2, "made with embedding.k = 3, but params.yaml has embedding.k = 2"),
        ("dim", 5, "made with embedding.dim = 2, but params.yaml has embedding.dim = 5"),
        (
            "beta",
            1e-4,
            "made with embedding.beta = 0.001, but params.yaml has embedding.beta = 0.0001",
        ),
        (
            "hidden",
            [16, 16],
            "made with embedding.hidden = [8], but params.yaml has embedding.hidden = [16, 16]",
        ),
        (
            "predictor_state",
            False,
            "made with embedding.predictor_state = true, but params.yaml has embedding.predictor_state = false",
        ),
        (
            "change_whitening",
            "all",
            "made with embedding.change_whitening = final, but params.yaml has embedding.change_whitening = all",
        ),
    ],
)
def test_each_embedding_param_that_differs_is_one_line_naming_the_key(
    saved: tuple[Path, Path], key: str, value: object, line: str
) -> None:
    encoder, decoder = metas(saved)
    changed = EMBEDDING.model_copy(update={key: value})
    assert params_mismatches(saved[0], encoder, changed) == [f"{saved[0]}: {line}"]
    assert params_mismatches(saved[1], decoder, changed, DECODER) == [f"{saved[1]}: {line}"]


def test_each_decoder_param_that_differs_is_one_line(saved: tuple[Path, Path]) -> None:
    _, decoder = metas(saved)
    changed = DECODER.model_copy(update={"lam": 1.0, "z_source": "prior"})
    assert params_mismatches(saved[1], decoder, EMBEDDING, changed) == [
        f"{saved[1]}: made with decoder.lam = 0.001, but params.yaml has decoder.lam = 1.0",
        f"{saved[1]}: made with decoder.z_source = marginal, but params.yaml has decoder.z_source = prior",
    ]


def test_several_contradictions_give_a_line_each(saved: tuple[Path, Path]) -> None:
    encoder, _ = metas(saved)
    changed = EMBEDDING.model_copy(update={"k": 4, "dim": 3, "beta": 0.5})
    lines = params_mismatches(saved[0], encoder, changed)
    assert [line.split(" = ")[0].split()[-1] for line in lines] == [
        "embedding.k",
        "embedding.dim",
        "embedding.beta",
    ]


def test_a_null_dim_means_the_action_size_given(saved: tuple[Path, Path]) -> None:
    encoder, _ = metas(saved)
    assert params_mismatches(saved[0], encoder, EMBEDDING, action_size=7) == [
        f"{saved[0]}: made with embedding.dim = 2, but params.yaml has embedding.dim = null "
        "(the action size, 7)"
    ]


def test_params_recorded_on_one_side_only_are_named(saved: tuple[Path, Path]) -> None:
    encoder, _ = metas(saved)
    recorded = dict(encoder.params["embedding"])
    del recorded["window_stride"]
    recorded["temperature"] = 2.0  # a key the params no longer have
    older = encoder.model_copy(update={"params": {"embedding": recorded}})
    assert params_mismatches(saved[0], older, EMBEDDING) == [
        f"{saved[0]}: made with no record of embedding.window_stride, but params.yaml has "
        "embedding.window_stride = 1",
        f"{saved[0]}: made with embedding.temperature = 2.0, which params.yaml does not have",
    ]


def test_an_artifact_that_records_no_params_is_one_line(saved: tuple[Path, Path]) -> None:
    encoder, _ = metas(saved)
    bare = encoder.model_copy(update={"params": {}})
    assert params_mismatches(saved[0], bare, EMBEDDING) == [
        f"{saved[0]}: records no embedding params, so it cannot be checked against params.yaml; "
        "make it again (`ede-pipeline pretrain`)"
    ]
