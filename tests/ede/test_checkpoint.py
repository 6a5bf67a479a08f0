"""A run's checkpoint (``ede.run.checkpoint``): read verifies it all before anything live changes."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

from ede.config import EdeTD3Config, TD3Config
from ede.io.atomic import sha256
from ede.run import checkpoint
from ede.run.checkpoint import CheckpointError
from ede.run.group import Group
from ede.run.spec import RunSpec

CPU = torch.device("cpu")
CONFIG = TD3Config(
    hidden=[16, 16], batch_size=8, start_steps=0, update_schedule="step", eval_episodes=1
)
SAVED_AT = 30  # steps: inside the first episode, after updates began (a batch of 8 from step 8)


def spec(seed: int = 0, config: TD3Config = CONFIG) -> RunSpec:
    return RunSpec("ede/Point-v0", "td3", seed, 1_000, config, EdeTD3Config())


def trained(steps: int, config: TD3Config = CONFIG) -> Group:
    """A run alone of ede/Point-v0's TD3 after ``steps`` steps (and their updates), then an
    evaluation."""
    group = Group([spec(config=config)], None, CPU)
    for _ in range(steps):
        group.advance()
    group.evaluate(np.ones(1, dtype=bool))
    return group


@pytest.fixture(scope="module")
def saved(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A checkpoint of the run at step :data:`SAVED_AT`."""
    path = tmp_path_factory.mktemp("saved") / "checkpoint"
    trained(SAVED_AT).runs[0].save(path)
    return path


@pytest.fixture
def copy(saved: Path, tmp_path: Path) -> Path:
    """A copy of :func:`saved` to damage."""
    return Path(shutil.copytree(saved, tmp_path / "checkpoint"))


def sign(path: Path) -> None:
    """Checksums for a checkpoint's files as they are now: damage its checksums cannot see."""
    sums = {name: sha256(path / name) for name in ("state.safetensors", "state.json")}
    (path / "checksums.json").write_text(json.dumps(sums))


def edit_tensors(path: Path, edit: Callable[[dict[str, torch.Tensor]], None]) -> None:
    """Change a checkpoint's tensors and sign them again."""
    tensors = load_file(path / "state.safetensors")
    edit(tensors)
    save_file(tensors, path / "state.safetensors")
    sign(path)


def read(path: Path, run: RunSpec | None = None) -> checkpoint.Checkpoint:
    return checkpoint.read(path, run or spec(), Group([spec()], None, CPU).layout)


def learner_state(group: Group) -> dict[str, torch.Tensor]:
    return {f"agent.{k}": v for k, v in group.agent.state_dict(0).items()} | {
        f"buffer.{k}": v for k, v in group.buffer.state_dict(0).items()
    }


def test_read_gives_back_what_the_run_held(saved: Path) -> None:
    group = trained(SAVED_AT)
    run, held = group.runs[0], read(saved)
    assert held.step == run.step == SAVED_AT
    assert held.agent.keys() == group.agent.state_dict(0).keys()
    assert all(torch.equal(held.agent[k], v) for k, v in group.agent.state_dict(0).items())
    assert all(torch.equal(held.buffer[k], v) for k, v in group.buffer.state_dict(0).items())
    assert held.i == group.executor.i[0] and np.array_equal(held.plan, group.executor.plan[0])
    assert np.array_equal(held.obs, group.envs.obs[0]) and held.episode.start == {"seed": 0}
    assert len(held.episode.actions) == SAVED_AT and held.episode.ret == run.episode.ret
    assert held.history == run.history and len(held.history) == 1
    assert held.diagnostics == run.diagnostics and held.diagnostics[0]["updates"] > 0
    assert held.episodes == 0


def test_a_resumed_run_steps_on_as_the_run_it_was_saved_from(saved: Path) -> None:
    ahead, resumed = trained(SAVED_AT), Group([spec()], None, CPU)
    assert resumed.runs[0].load(saved) and resumed.runs[0].step == SAVED_AT
    for _ in range(10):
        ahead.advance()
        resumed.advance()
    first, second = learner_state(ahead), learner_state(resumed)
    assert all(torch.equal(v, second[k]) for k, v in first.items())
    assert np.array_equal(ahead.envs.obs, resumed.envs.obs)


def test_an_interval_without_an_actor_step_is_saved_and_read_back(tmp_path: Path) -> None:
    # The first update comes at step 8 (a batch of 8), a critic step alone (policy delay 2): an
    # evaluation right after it records no actor loss, NaN, which JSON cannot hold.
    group = trained(8)
    row = group.runs[0].diagnostics[0]
    assert row["updates"] == 1 and np.isnan(row["actor_loss"]) and np.isnan(row["mean_q"])
    group.runs[0].save(tmp_path / "checkpoint")
    held = read(tmp_path / "checkpoint").diagnostics[0]
    assert held.keys() == row.keys() and np.isnan(held["actor_loss"]) and np.isnan(held["mean_q"])
    assert held["critic_loss"] == row["critic_loss"]


def test_a_damaged_file_is_refused_by_its_checksum(copy: Path) -> None:
    data = bytearray((copy / "state.safetensors").read_bytes())
    data[-1] ^= 0xFF
    (copy / "state.safetensors").write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match=r"^state\.safetensors does not match its checksum"):
        read(copy)


@pytest.mark.parametrize("name", ["state.json", "state.safetensors", "checksums.json"])
def test_a_missing_file_is_named(copy: Path, name: str) -> None:
    (copy / name).unlink()
    with pytest.raises(CheckpointError, match=f"^{name} is missing$"):
        read(copy)


def test_another_runs_checkpoint_names_the_first_difference(saved: Path) -> None:
    with pytest.raises(CheckpointError, match=r"^another run's: seed is 0, expected 1$"):
        read(saved, spec(seed=1))
    other = CONFIG.model_copy(update={"lr": 3e-4})
    with pytest.raises(
        CheckpointError,
        match=r"^another run's: made with td3.lr = 0.001, but the params say 0.0003$",
    ):
        read(saved, spec(config=other))


def test_another_format_version_is_refused(copy: Path) -> None:
    state = json.loads((copy / "state.json").read_text())
    (copy / "state.json").write_text(json.dumps(state | {"version": 3}))
    sign(copy)
    with pytest.raises(
        CheckpointError, match=f"^format version 3, this version reads {checkpoint.VERSION}$"
    ):
        read(copy)


def test_a_tensor_of_other_hidden_sizes_is_refused_by_name_and_shape(copy: Path) -> None:
    narrower = trained(0, CONFIG.model_copy(update={"hidden": [8, 8]})).agent.state_dict(0)
    name = "actor.0.weight"
    expected = Group([spec()], None, CPU).agent.state_dict(0)[name].shape
    edit_tensors(copy, lambda tensors: tensors.update({f"agent.{name}": narrower[name]}))
    shape = ", ".join(map(str, narrower[name].shape))
    with pytest.raises(
        CheckpointError,
        match=(
            rf"^agent.{name} is \[{shape}\] torch.float32, "
            rf"expected \[{', '.join(map(str, expected))}\] torch.float32$"
        ),
    ):
        read(copy)


@pytest.mark.parametrize(
    ("edit", "reason"),
    [
        (lambda t: t.pop("buffer.reward"), "^buffer.reward is missing$"),
        (
            lambda t: t.update({"buffer.reward": t["buffer.reward"][:-1]}),
            rf"^buffer.reward is \[{SAVED_AT - 1}\] torch.float32, "
            rf"expected \[{SAVED_AT}\] torch.float32$",
        ),
        (
            lambda t: t.update({"buffer.terminated": t["buffer.terminated"].float()}),
            "^buffer.terminated is .* torch.float32, expected .* torch.bool$",
        ),
        (
            lambda t: t.update({"buffer.count": torch.tensor(SAVED_AT + 1)}),
            "^the replay buffer does not hold the run's steps$",
        ),
        (lambda t: t.update({"agent.extra": torch.zeros(1)}), "^agent.extra is not this run's$"),
    ],
)
def test_a_missing_or_misshapen_tensor_is_refused(copy: Path, edit, reason: str) -> None:
    edit_tensors(copy, edit)
    with pytest.raises(CheckpointError, match=reason):
        read(copy)


def bad_shape(path: Path) -> None:
    """The agent's tensors intact, the buffer's one row short: the old loader had loaded the
    agent's member before it found that out."""
    edit_tensors(path, lambda t: t.update({"buffer.obs": t["buffer.obs"][:-1]}))


def elsewhere(path: Path) -> None:
    """Every tensor fits, but the episode's replay does not reach the saved observation."""
    edit_tensors(path, lambda t: t.update({"obs": t["obs"] + 1}))


@pytest.mark.parametrize("damage", [bad_shape, elsewhere])
def test_a_checkpoint_that_cannot_be_used_leaves_the_live_agent_and_buffer_bit_for_bit(
    copy: Path, damage: Callable[[Path], None]
) -> None:
    group = trained(SAVED_AT + 10)  # its learner state differs from the checkpoint's
    before = learner_state(group)
    damage(copy)
    with pytest.raises(CheckpointError):
        group.runs[0].load(copy)
    after = learner_state(group)
    assert after.keys() == before.keys()
    assert all(torch.equal(v, after[k]) for k, v in before.items())
    assert group.runs[0].step == SAVED_AT + 10
