"""``ede-pipeline pretrain encoder|decoder`` end to end on tiny params, and bad input."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner, Result

from ede.io.provenance import software_versions
from ede.run.artifacts import load_action_embedding
from ede_pipeline.cli import main


def tiny(params: dict) -> None:
    params["collect"].update(steps=2_000, num_envs=1)
    for section in ("embedding", "decoder"):
        params[section].update(hidden=[32, 32], epochs=2, lr=1e-3)


def run(*args: str) -> Result:
    return CliRunner().invoke(main, list(args))


@pytest.fixture
def collected(tmp_path: Path, write_params, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A scratch working directory with tiny params and the point family's rollouts."""
    monkeypatch.chdir(tmp_path)
    write_params(tiny)
    for family in ("point", "pointmass"):
        assert run("collect", "--family", family).exit_code == 0
    return tmp_path


def test_encoder_then_decoder_write_artifacts_metrics_and_curves(collected: Path) -> None:
    encoder = run("pretrain", "encoder", "--family", "point")
    assert encoder.exit_code == 0, encoder.output
    assert "x the mean-change baseline" in encoder.stdout
    decoder = run("pretrain", "decoder", "--family", "point")
    assert decoder.exit_code == 0, decoder.output
    folder = collected / "data/families/point/embedding"
    metrics = json.loads((folder / "encoder_metrics.json").read_text())
    assert metrics["prediction_ratio"] < 1.0
    assert set(json.loads((folder / "decoder_metrics.json").read_text())) == {
        "inverse_error",
        "at_bounds",
        "bound",
    }
    assert (folder / "encoder_history.csv").read_text().splitlines()[0].startswith("epoch,")
    assert len((folder / "decoder_history.csv").read_text().splitlines()) == 3  # header + 2 epochs
    meta, embedding = load_action_embedding(folder / "encoder", folder / "decoder")
    assert meta.family == "point" and meta.params["embedding"]["epochs"] == 2
    for name in ("encoder", "decoder"):
        recorded = json.loads((folder / name / "meta.json").read_text())["software"]
        assert recorded == software_versions() and recorded["mujoco"] != "not installed"
    assert embedding.k == 4 and embedding.dim == 2


def bad(result: Result, message: str) -> None:
    assert result.exit_code == 2, result.output
    assert result.stderr.count("\n") == 1 and message in result.stderr, result.stderr
    assert "Traceback" not in result.output


def test_missing_rollouts_are_one_line(tmp_path: Path, write_params, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    write_params(tiny)
    bad(run("pretrain", "encoder", "--family", "reacher"), "no rollouts store here")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["params.yaml"]


def test_rollouts_of_another_family_are_one_line(collected: Path) -> None:
    result = run(
        "pretrain",
        "encoder",
        "--family",
        "point",
        "--rollouts",
        "data/families/pointmass/rollouts.zarr",
    )
    bad(result, "collected on ede/PointMass-v0 (family pointmass), expected ede/Point-v0")
    assert not (collected / "data/families/point/embedding").exists()


def test_episodes_shorter_than_k_are_one_line(collected: Path, write_params) -> None:
    def long_k(p: dict) -> None:
        tiny(p)
        p["embedding"].update(k=150)

    write_params(long_k)
    bad(run("pretrain", "encoder", "--family", "point"), "no episode is longer than k=150")


def test_a_decoder_needs_its_familys_encoder(collected: Path) -> None:
    bad(run("pretrain", "decoder", "--family", "point"), "no encoder here")
    assert run("pretrain", "encoder", "--family", "pointmass").exit_code == 0
    result = run(
        "pretrain",
        "decoder",
        "--family",
        "point",
        "--encoder",
        "data/families/pointmass/embedding/encoder",
    )
    bad(result, "trained on family pointmass's rollouts")
    assert not (collected / "data/families/point/embedding/decoder").exists()


def test_rollouts_of_one_episode_are_one_line(tmp_path: Path, write_params, monkeypatch) -> None:
    """One episode leaves nothing to hold out: the line says to collect more."""
    monkeypatch.chdir(tmp_path)

    def one_episode(params: dict) -> None:
        tiny(params)
        params["collect"]["steps"] = 100  # one of ede/Point-v0's 100-step episodes
        for section in ("embedding", "decoder"):
            params[section]["batch_size"] = 16

    write_params(one_episode)
    assert run("collect", "--family", "point").exit_code == 0
    bad(run("pretrain", "encoder", "--family", "point"), "1 episode; expected at least 2")
    assert not (tmp_path / "data/families/point/embedding").exists()
