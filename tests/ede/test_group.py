"""Runs trained as a group: every member ends with the outputs it gets alone, and resumes exactly."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch

from ede.config import EdeTD3Config, TD3Config
from ede.training import RunSpec, train_group, train_run

pytestmark = pytest.mark.slow

SEEDS = [0, 1, 2, 3]
CONFIG = TD3Config(hidden=[64, 64], batch_size=32, eval_every=200, eval_episodes=2,
                   update_schedule="step",
                   checkpoint_every=200)
CPU = torch.device("cpu")


def spec(seed: int, config: TD3Config = CONFIG) -> RunSpec:
    return RunSpec("ede/Point-v0", "td3", seed, 600, config, EdeTD3Config())


def outputs(run: Path) -> dict[str, object]:
    """What a run's result is: its returns and diagnostics (not wall times), its policy."""
    returns = [line.rsplit(",", 1)[0] for line in (run / "eval.csv").read_text().splitlines()]
    return {"returns": returns, "diagnostics": (run / "diagnostics.csv").read_text(),
            "policy": (run / "policy" / "policy.safetensors").read_bytes()}


@pytest.fixture(scope="module")
def group(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The four seeds trained as one group, checkpoints kept (the last at step 400)."""
    root = tmp_path_factory.mktemp("group")
    train_group([spec(s) for s in SEEDS], [root / f"seed{s}" for s in SEEDS], device=CPU,
                keep_checkpoint=True)
    return root


def test_a_member_of_a_group_ends_as_it_ends_alone(group: Path, tmp_path: Path) -> None:
    train_run(spec(3), tmp_path / "alone", device=CPU)
    assert outputs(group / "seed3") == outputs(tmp_path / "alone")
    assert outputs(group / "seed0") != outputs(group / "seed3")  # members are different runs


def test_a_group_resumes_exactly_even_when_its_members_stopped_at_different_steps(
    group: Path, tmp_path: Path
) -> None:
    outs = [tmp_path / f"seed{s}" for s in SEEDS]
    for seed, out in zip(SEEDS, outs):
        if seed != 0:  # seed 0 lost its checkpoint: it starts over and catches up alone
            shutil.copytree(group / f"seed{seed}" / "checkpoint", out / "checkpoint")
    metrics = train_group([spec(s) for s in SEEDS], outs, device=CPU)
    assert [m["resumed_from_step"] for m in metrics] == [None, 400, 400, 400]
    for seed, out in zip(SEEDS, outs):
        assert outputs(out) == outputs(group / f"seed{seed}"), seed


def test_a_group_is_one_task_and_algorithm_differing_in_seeds_only(tmp_path: Path) -> None:
    other = CONFIG.model_copy(update={"lr": 3e-4})
    with pytest.raises(ValueError, match="differ in their seeds only"):
        train_group([spec(0), spec(1, other)], [tmp_path / "a", tmp_path / "b"], device=CPU)


@pytest.mark.parametrize("task", [
    "ede/Point-v0",  # never ends early: every member's episode ends together, one batch for all
    "InvertedPendulum-v5",  # ends when the pole falls: the group dissolves, members go on alone
])
def test_per_episode_batches_in_a_group_are_each_members_own(task: str, tmp_path: Path) -> None:
    config = CONFIG.model_copy(update={"update_schedule": "episode", "eval_every": 100,
                                       "checkpoint_every": 150})
    specs = [RunSpec(task, "td3", seed, 300, config, EdeTD3Config()) for seed in (0, 1)]
    notices: list[str] = []
    train_group(specs, [tmp_path / f"group{s}" for s in (0, 1)], device=CPU,
                notice=notices.append)
    assert any("go on one by one" in n for n in notices) == (task == "InvertedPendulum-v5")
    for seed in (0, 1):
        train_run(specs[seed], tmp_path / f"alone{seed}", device=CPU)
        assert outputs(tmp_path / f"group{seed}") == outputs(tmp_path / f"alone{seed}"), seed
