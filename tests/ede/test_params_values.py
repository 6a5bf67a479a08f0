"""Params values are what they say (no coercion); seeds are what every consumer of a seed takes."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner

from ede.analysis.probes import random_policy_return
from ede.analysis.stats import across_tasks, global_numpy_seed
from ede.config import (
    SEED_MAX,
    DecoderConfig,
    EdeTD3Config,
    EmbeddingConfig,
    Params,
    ParamsError,
    TD3Config,
    load_params,
)
from ede.io.rollouts import Rollouts
from ede.method.embedding import train_decoder, train_encoder
from ede.run.collect import collect
from ede.run.spec import RunSpec
from ede.run.training import train_run
from ede_pipeline.cli import main
from ede_pipeline.common import BadInput
from ede_pipeline.train import parse_seeds
from tests.support import REPO

RANGE = "expected a seed from 0 to 4294967295 (2**32 - 1)"


def problems(write_params, edit) -> list[str]:
    with pytest.raises(ParamsError) as caught:
        load_params(write_params(edit))
    return caught.value.problems


@pytest.mark.parametrize(
    ("edit", "line"),
    [
        (
            lambda p: p["td3"].update(batch_size=True),
            "td3.batch_size: got true, a boolean; expected an integer",
        ),
        (
            lambda p: p["td3"].update(batch_size="100"),
            "td3.batch_size: got '100', a string; expected an integer",
        ),
        (
            lambda p: p["collect"].update(steps=100_000.0),
            "collect.steps: got 100000.0, a number; expected an integer",
        ),
        (
            lambda p: p["collect"].update(num_envs=False),
            "collect.num_envs: got false, a boolean; expected an integer",
        ),
        (lambda p: p["collect"].update(seed=None), "collect.seed: got null; expected an integer"),
        (lambda p: p["td3"].update(lr="0.001"), "td3.lr: got '0.001', a string; expected a number"),
        (
            lambda p: p["td3"].update(discount=True),
            "td3.discount: got true, a boolean; expected a number",
        ),
        (
            lambda p: p["embedding"].update(predictor_state=1),
            "embedding.predictor_state: got 1, an integer; expected true or false",
        ),
        (
            lambda p: p["embedding"].update(predictor_state="false"),
            "embedding.predictor_state: got 'false', a string; expected true or false",
        ),
        (
            lambda p: p["embedding"].update(hidden="400"),
            "embedding.hidden: got '400', a string; expected a list",
        ),
        (
            lambda p: p["decoder"].update(hidden=[400, True]),
            "decoder.hidden.1: got true, a boolean; expected an integer",
        ),
        (
            lambda p: p["decoder"].update(z_source=True),
            "decoder.z_source: got true; expected 'prior' or 'marginal'",
        ),
        (
            lambda p: p["families"]["point"].update(source=5),
            "families.point.source: got 5, an integer; expected a string",
        ),
        (
            lambda p: p["runs"]["tasks"].update({"ede/Pusher-v0": 1}),
            "runs.tasks.ede/Pusher-v0: got 1, an integer; expected a string",
        ),
        (
            lambda p: p["runs"].update(seeds=[0, "1"]),
            "runs.seeds.1: got '1', a string; expected an integer",
        ),
        (
            lambda p: p["runs"]["budgets"].update({"ede/Pusher-v0": True}),
            "runs.budgets.ede/Pusher-v0: got true, a boolean; expected an integer",
        ),
        (
            lambda p: p["report"]["thresholds"].update({"ede/Pusher-v0": "5"}),
            "report.thresholds.ede/Pusher-v0: got '5'; expected a return or a non-empty list of "
            "returns",
        ),
        (
            lambda p: p["report"]["thresholds"].update({"ede/Pusher-v0": []}),
            "report.thresholds.ede/Pusher-v0: got []; expected a return or a non-empty list of "
            "returns",
        ),
        (
            lambda p: p["report"].update(bin_steps=2_500.0),
            "report.bin_steps: got 2500.0, a number; expected an integer",
        ),
        (
            lambda p: p["td3"].update(critic_action_repeat=True),
            "td3.critic_action_repeat: got true; expected a positive integer or 'auto'",
        ),
        (lambda p: p.update(td3="fast"), "td3: got 'fast', a string; expected a mapping"),
    ],
)
def test_a_value_of_another_type_is_refused_not_coerced(write_params, edit, line: str) -> None:
    assert problems(write_params, edit) == [line]


def test_yamls_spellings_of_numbers_are_numbers(tmp_path: Path) -> None:
    """An integer where a number is expected, and exponents as YAML 1.2 writes them (DVC's
    ``-S embedding.beta=0.00001`` leaves ``beta: 1e-05``; PyYAML alone reads a string)."""
    text = (REPO / "params.yaml").read_text()
    for old, new in [
        ("  lr: 1.0e-3", "  lr: 1"),
        ("  beta: 1.0e-4", "  beta: 1e-05"),
        ("  lam: 1.0e-4", "  lam: 2.5E-4"),
        ("  tau: 0.005", "  tau: 5e-3"),
        ("  bound_scale: 1.0", "  bound_scale: 1.5e0"),
        ("  steps: 100000", "  steps: 100_000"),
    ]:
        assert text.count(old + " ") + text.count(old + "\n") == 1, old
        text = text.replace(old, new, 1)
    path = tmp_path / "params.yaml"
    path.write_text(text)
    params = load_params(path)
    assert (
        params.td3.lr,
        params.embedding.beta,
        params.decoder.lam,
        params.td3.tau,
        params.ede_td3.bound_scale,
    ) == (1.0, 1e-5, 2.5e-4, 5e-3, 1.5)
    assert type(params.td3.lr) is float and params.collect.steps == 100_000


def test_validated_params_validate_again_from_their_json() -> None:
    """``experiment run`` merges overrides into the params as JSON data and validates the result."""
    params = load_params(REPO / "params.yaml")
    assert Params.model_validate(params.model_dump(mode="json")) == params


# --------------------------------------------------------------------------------------------
# Seeds

SEED_KEYS = {
    "collect.seed": lambda p, seed: p["collect"].update(seed=seed),
    "embedding.seed": lambda p, seed: p["embedding"].update(seed=seed),
    "decoder.seed": lambda p, seed: p["decoder"].update(seed=seed),
    "report.seed": lambda p, seed: p["report"].update(seed=seed),
    "runs.seeds.1": lambda p, seed: p["runs"].update(seeds=[0, seed]),
}


@pytest.mark.parametrize("key", SEED_KEYS)
@pytest.mark.parametrize("seed", [SEED_MAX + 1, 2**64, -1])
def test_a_seed_out_of_range_is_one_line_naming_key_value_and_range(
    write_params, key: str, seed: int
) -> None:
    assert problems(write_params, lambda p: SEED_KEYS[key](p, seed)) == [
        f"{key}: got {seed}; {RANGE}"
    ]


@pytest.mark.parametrize("key", SEED_KEYS)
def test_the_largest_seed_validates(write_params, key) -> None:
    load_params(write_params(lambda p: SEED_KEYS[key](p, SEED_MAX)))


def test_every_consumer_takes_the_largest_seed_with_what_is_added_to_it(
    tmp_path: Path, point_store: Path
) -> None:
    # collect.seed: sub-environment i resets with seed + i and draws from default_rng.
    arrays = collect("ede/Point-v0", steps=200, num_envs=2, seed=SEED_MAX, workers=1)
    assert len(arrays["reward"]) == 200
    # embedding.seed and decoder.seed: torch generators, seeded with seed and seed + 1.
    rollouts = Rollouts.open(point_store)
    small: dict[str, Any] = {"hidden": [8], "epochs": 1, "seed": SEED_MAX}
    encoded = train_encoder(rollouts, EmbeddingConfig(**small))
    train_decoder(rollouts, encoded, DecoderConfig(**small), 4, -np.ones(2), np.ones(2))
    # runs.seeds: SeedSequence streams, the first reset, evaluation resets 1_000_003 (seed + 1) + e.
    config = TD3Config(hidden=[8], batch_size=8, eval_every=100, eval_episodes=1)
    metrics = train_run(
        RunSpec("ede/Point-v0", "td3", SEED_MAX, 100, config, EdeTD3Config()),
        tmp_path / "run",
        notice=lambda line: None,
    )
    assert np.isfinite(metrics["final_return"])
    # report.seed: NumPy's global generator (rliable), default_rng, resets seed + e.
    assert np.isfinite(random_policy_return("ede/Point-v0", 2, SEED_MAX))
    scores = np.arange(6.0).reshape(3, 2)
    assert "probability_of_improvement" in across_tasks(scores, scores + 1, 0.9, 20, SEED_MAX)


def test_the_bound_is_what_numpys_global_generator_takes() -> None:
    """The tightest consumer (the report's): one past the bound, and it fails."""
    with pytest.raises(ValueError, match="2\\*\\*32"):
        with global_numpy_seed(SEED_MAX + 1):
            pass


@pytest.mark.parametrize(
    ("text", "seeds"),
    [
        ("4294967295", [SEED_MAX]),
        ("4294967294-4294967295", [SEED_MAX - 1, SEED_MAX]),
        ("0,4294967295", [0, SEED_MAX]),
    ],
)
def test_train_takes_seeds_up_to_the_bound(text: str, seeds: list[int]) -> None:
    assert parse_seeds(text) == seeds


@pytest.mark.parametrize(
    "text", ["4294967296", "18446744073709551616", "0,4294967296", "4294967295-4294967296"]
)
def test_train_refuses_seeds_past_the_bound(text: str) -> None:
    with pytest.raises(
        BadInput, match=f"^--seed {text}: expected distinct seeds from 0 to 4294967295$"
    ):
        parse_seeds(text)


STAGES = [
    ["validate"],
    ["collect", "--family", "point"],
    ["inspect", "--family", "point"],
    ["task-code", "--family", "point"],
    ["pretrain", "encoder", "--family", "point"],
    ["pretrain", "decoder", "--family", "point"],
    ["task-inputs", "--task", "ede/Pusher-v0"],
    ["train", "--task", "ede/Pusher-v0", "--algo", "td3", "--seed", "0"],
    ["report"],
]


@pytest.mark.parametrize("argv", STAGES, ids=lambda argv: " ".join(argv[:2]))
def test_every_stage_refuses_bad_params_in_one_line_and_writes_nothing(
    tmp_path: Path, write_params, monkeypatch, argv: list[str]
) -> None:
    def bad(p: dict) -> None:
        p["embedding"]["seed"] = 2**64
        p["td3"]["batch_size"] = True

    write_params(bad)
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(main, [*argv, "--params", "params.yaml"])
    assert result.exit_code == 2, result.output
    assert result.stderr.splitlines() == [
        f"Error: params.yaml: embedding.seed: got {2**64}; {RANGE}",
        "Error: params.yaml: td3.batch_size: got true, a boolean; expected an integer",
    ]
    assert os.listdir(tmp_path) == ["params.yaml"]


def test_train_refuses_a_seed_past_the_bound_in_one_line_and_writes_nothing(
    tmp_path: Path, monkeypatch
) -> None:
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(
        main,
        [
            "train",
            "--task",
            "ede/Pusher-v0",
            "--algo",
            "td3",
            "--seed",
            str(2**64),
            "--params",
            str(REPO / "params.yaml"),
        ],
    )
    assert result.exit_code == 2
    assert result.stderr == f"Error: --seed {2**64}: expected distinct seeds from 0 to {SEED_MAX}\n"
    assert os.listdir(tmp_path) == []
