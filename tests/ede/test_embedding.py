"""The embedding: its losses, its training on a linear task, and its artifacts."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

from ede.config import DecoderConfig, EmbeddingConfig
from ede.io.rollouts import Rollouts
from ede.method.embedding import (
    ActionEmbedding,
    EncoderResult,
    gaussian_kl,
    prediction_loss,
    split_episodes,
    train_decoder,
    train_encoder,
)
from ede.run.artifacts import (
    ArtifactError,
    load_action_embedding,
    load_encoder,
    save_decoder,
    save_encoder,
)

SMALL: dict[str, Any] = {"hidden": [64, 64], "lr": 1e-3, "batch_size": 64}
LOW, HIGH = np.array([-1.0, -1.0]), np.array([1.0, 1.0])


@pytest.fixture(scope="module")
def point(point_store: Path) -> Rollouts:
    return Rollouts.open(point_store)


@pytest.fixture(scope="module")
def trained(point: Rollouts) -> EncoderResult:
    torch.set_num_threads(1)
    return train_encoder(point, EmbeddingConfig(epochs=12, **SMALL))


def test_kl_matches_torch_distributions_on_fixed_tensors() -> None:
    mean = torch.tensor([[0.0, 1.0, -2.0], [0.5, 0.0, 0.0]])
    log_var = torch.tensor([[0.0, -1.0, 0.5], [2.0, 0.0, -3.0]])
    q = torch.distributions.Normal(mean, (0.5 * log_var).exp())
    p = torch.distributions.Normal(torch.zeros(3), torch.ones(3))
    expected = torch.distributions.kl_divergence(q, p).sum(-1)
    torch.testing.assert_close(gaussian_kl(mean, log_var), expected)
    assert gaussian_kl(torch.zeros(1, 3), torch.zeros(1, 3)).item() == 0.0


def test_prediction_loss_is_the_squared_error_averaged_over_state_dimensions() -> None:
    predicted = torch.tensor([[1.0, 2.0], [0.0, 0.0]])
    target = torch.tensor([[0.0, 0.0], [3.0, -1.0]])
    torch.testing.assert_close(prediction_loss(predicted, target), torch.tensor([2.5, 5.0]))


def test_held_out_episodes_are_disjoint_from_training_ones() -> None:
    train, held = split_episodes(40, 0.1, seed=3)
    assert len(held) == 4 and len(train) == 36
    assert not set(train) & set(held) and set(train) | set(held) == set(range(40))
    assert np.array_equal(split_episodes(40, 0.1, seed=3)[1], held)


def test_on_the_linear_point_the_k_step_effect_is_predicted_almost_exactly(
    trained: EncoderResult,
) -> None:
    assert trained.metrics["prediction_ratio"] < 0.02, trained.metrics
    assert trained.history[-1]["holdout_mse"] < trained.history[0]["holdout_mse"]


def test_the_decoder_output_re_encodes_to_its_input(
    point: Rollouts, trained: EncoderResult
) -> None:
    result = train_decoder(point, trained, DecoderConfig(epochs=10, **SMALL), 4, LOW, HIGH)
    assert result.metrics["inverse_error"] < 0.01, result.metrics
    embedding = ActionEmbedding(
        trained.encoder, result.decoder, trained.code_whitening, result.bound
    )
    z = torch.empty(256, 2).uniform_(-1.5, 1.5, generator=torch.Generator().manual_seed(0))
    actions = embedding.decode(z)
    assert actions.shape == (256, 4, 2) and actions.abs().max() <= 1.0
    torch.testing.assert_close(embedding.encode(actions), z, atol=0.15, rtol=0)
    # Minimum norm: of all sequences with a random sequence's effect, D picks a small one. On the
    # linear point that is the effect split evenly over the k steps, a quarter of the norm.
    sequences = torch.rand(512, 4, 2, generator=torch.Generator().manual_seed(1)) * 2 - 1
    decoded = embedding.decode(embedding.encode(sequences))
    assert decoded.pow(2).sum() < 0.5 * sequences.pow(2).sum()
    assert embedding.decode(embedding.encode(torch.zeros(1, 4, 2))).abs().max() < 0.1


def test_training_is_determined_by_the_seed(point: Rollouts, trained: EncoderResult) -> None:
    def weights(seed: int, noise: int) -> list[torch.Tensor]:
        torch.manual_seed(noise)  # whatever the global generator holds must not matter
        encoded = train_encoder(point, EmbeddingConfig(epochs=1, seed=seed, **SMALL))
        torch.manual_seed(noise + 1)
        decoded = train_decoder(
            point, encoded, DecoderConfig(epochs=1, seed=seed, **SMALL), 4, LOW, HIGH
        )
        return [*encoded.encoder.state_dict().values(), *decoded.decoder.state_dict().values()]

    first, again, other = weights(0, noise=1), weights(0, noise=2), weights(1, noise=1)
    assert all(torch.equal(a, b) for a, b in zip(first, again, strict=True))
    assert not all(torch.equal(a, b) for a, b in zip(first, other, strict=True))


@pytest.mark.parametrize("beta", [0.0, 1e3])
def test_beta_zero_keeps_information_and_a_huge_beta_collapses_to_the_prior(
    point: Rollouts, beta: float
) -> None:
    result = train_encoder(point, EmbeddingConfig(epochs=4, beta=beta, **SMALL))
    if beta == 0:
        assert result.metrics["prediction_ratio"] < 0.1 and result.metrics["kl"] > 1.0
    else:
        assert result.metrics["kl"] < 0.05, result.metrics  # E(a) ~ N(0, I) whatever a is
        assert result.metrics["prediction_ratio"] > 0.8  # the code tells P nothing


@pytest.fixture
def saved(tmp_path: Path, point: Rollouts, trained: EncoderResult) -> tuple[Path, Path]:
    encoder_dir, decoder_dir = tmp_path / "encoder", tmp_path / "decoder"
    save_encoder(
        encoder_dir,
        trained,
        family="point",
        env_id="ede/Point-v0",
        low=LOW,
        high=HIGH,
        params={"embedding": {}},
        data_fingerprint=point.attrs["fingerprint"],
    )
    result = train_decoder(point, trained, DecoderConfig(epochs=1, **SMALL), 4, LOW, HIGH)
    save_decoder(decoder_dir, result.decoder, result.bound, encoder_path=encoder_dir, params={})
    return encoder_dir, decoder_dir


def test_save_then_load_gives_identical_outputs(
    saved: tuple[Path, Path], trained: EncoderResult
) -> None:
    meta, embedding = load_action_embedding(*saved)
    _, reloaded = load_encoder(saved[0])
    actions = torch.rand(32, 4, 2) * 2 - 1
    torch.testing.assert_close(
        reloaded.encoder(actions)[0], trained.encoder(actions)[0], rtol=0, atol=0
    )
    assert meta.k == 4 and meta.dim == 2 and meta.bound > 0
    z = embedding.encode(actions)
    again = load_action_embedding(*saved)[1]
    torch.testing.assert_close(again.decode(z), embedding.decode(z), rtol=0, atol=0)
    # The decoder alone (a published one) decodes as the whole embedding does, and encodes nothing.
    alone_meta, alone = load_action_embedding(None, saved[1])
    assert alone_meta.identity == meta.identity and (alone.k, alone.dim) == (4, 2)
    torch.testing.assert_close(alone.decode(z), embedding.decode(z), rtol=0, atol=0)
    with pytest.raises(ValueError, match="without its encoder"):
        alone.encode(actions)


def test_a_tampered_metadata_file_is_refused(saved: tuple[Path, Path]) -> None:
    meta_file = saved[1] / "meta.json"
    meta = json.loads(meta_file.read_text())
    meta["bound"] = -1.0
    meta_file.write_text(json.dumps(meta))
    with pytest.raises(ArtifactError, match="bound"):
        load_action_embedding(*saved)


def test_weights_that_do_not_match_their_checksum_are_refused(saved: tuple[Path, Path]) -> None:
    weights = saved[0] / "weights.safetensors"
    weights.write_bytes(weights.read_bytes()[:-8] + b"\0" * 8)
    with pytest.raises(ArtifactError, match="checksum"):
        load_encoder(saved[0])


def test_a_weight_of_the_wrong_shape_is_refused_by_name(saved: tuple[Path, Path]) -> None:
    weights, meta_file = saved[1] / "weights.safetensors", saved[1] / "meta.json"
    tensors = load_file(weights)
    tensors["decoder.net.0.weight"] = torch.zeros(7, 2)
    save_file(tensors, weights)
    meta = json.loads(meta_file.read_text())
    import hashlib

    meta["weights_sha256"] = hashlib.sha256(weights.read_bytes()).hexdigest()
    meta_file.write_text(json.dumps(meta))
    with pytest.raises(ArtifactError, match=r"decoder.net.0.weight has shape \(7, 2\)"):
        load_action_embedding(*saved)


def test_a_decoder_of_another_encoder_is_refused(
    saved: tuple[Path, Path], tmp_path: Path, point: Rollouts
) -> None:
    other = train_encoder(point, EmbeddingConfig(epochs=1, seed=9, **SMALL))
    save_encoder(
        tmp_path / "other",
        other,
        family="point",
        env_id="ede/Point-v0",
        low=LOW,
        high=HIGH,
        params={},
        data_fingerprint="x",
    )
    with pytest.raises(ArtifactError, match="another encoder"):
        load_action_embedding(tmp_path / "other", saved[1])


def test_a_window_stride_of_k_keeps_non_overlapping_windows_from_each_episodes_start(
    point: Rollouts,
) -> None:
    from ede.method.embedding import strided

    every = point.window_starts(4)
    starts = strided(point, every, 4)
    # 0, 4, ..., 92: a window needs the state k steps on, and an episode stores its 100 pre-step states
    assert set(point.t[starts]) == set(range(0, 96, 4))
    assert len(starts) == point.num_episodes * 24 and set(starts) <= set(every)
    assert np.array_equal(strided(point, every, 1), every)


def test_without_the_state_the_predictor_learns_nothing_from_it(point: Rollouts) -> None:
    from ede.method.embedding import Encoder, Predictor

    torch.set_num_threads(1)
    config = EmbeddingConfig(epochs=2, predictor_state=False, **SMALL)
    result = train_encoder(point, config)
    torch.manual_seed(config.seed)  # the initial weights train_encoder starts from
    Encoder(4, 2, 2, SMALL["hidden"])
    initial = Predictor(point.state.shape[1], 2, SMALL["hidden"])
    first, start = linear_layers(result.predictor)[0].weight, linear_layers(initial)[0].weight
    state_size = point.state.shape[1]
    # The state's input weights never moved (their gradient is zero); the code's did.
    assert torch.equal(first[:, :state_size], start[:, :state_size])
    assert not torch.equal(first[:, state_size:], start[:, state_size:])
    assert result.metrics["prediction_ratio"] < 1.0


def linear_layers(module: torch.nn.Module) -> list[torch.nn.Linear]:
    return [m for m in module.modules() if isinstance(m, torch.nn.Linear)]


def test_a_unit_range_decoder_acts_within_one_on_a_wider_box_as_the_authors_code(
    point: Rollouts, trained: EncoderResult, tmp_path: Path
) -> None:
    """The authors' decoder ends in a tanh it never rescales (docs/fidelity.md, row 11a): on a
    ±2 box its actions stay within ±1; ours spans the box. Saved and loaded, the choice stays."""
    low, high = 2 * LOW, 2 * HIGH
    config = DecoderConfig(epochs=1, **SMALL)
    z = torch.linspace(-3, 3, 64)[:, None].expand(64, 2)
    for output_range, widest in (("bounds", 2.0), ("unit", 1.0)):
        result = train_decoder(
            point, trained, config.model_copy(update={"output_range": output_range}), 4, low, high
        )
        actions = result.decoder(z)
        assert actions.abs().max() <= widest
        encoder_dir, decoder_dir = (
            tmp_path / output_range / "encoder",
            tmp_path / output_range / "decoder",
        )
        save_encoder(
            encoder_dir,
            trained,
            family="point",
            env_id="ede/Point-v0",
            low=low,
            high=high,
            params={},
            data_fingerprint=point.attrs["fingerprint"],
        )
        save_decoder(decoder_dir, result.decoder, result.bound, encoder_path=encoder_dir, params={})
        meta, embedding = load_action_embedding(encoder_dir, decoder_dir)
        assert meta.output_range == output_range
        torch.testing.assert_close(embedding.decoder(z), actions, rtol=0, atol=0)
    # The same network: the unit range is the tanh itself, clipped; the bounds twice it.
    net_out = torch.tanh(result.decoder.net(z)).unflatten(-1, (4, 2))
    torch.testing.assert_close(result.decoder(z), net_out, rtol=0, atol=0)
    with pytest.raises(ValueError, match="'bounds' or 'unit'"):
        type(result.decoder)(2, 4, low, high, [8], output_range="half")
