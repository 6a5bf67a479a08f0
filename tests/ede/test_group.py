"""Runs trained as a group: every member ends with the outputs it gets alone, and resumes exactly.

Alone and in a group a run computes with the same kernels (``ede.method.ensemble``), so these
compare bits: same code path, different numbers of members."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import cast

import numpy as np
import pytest
import torch

from ede.config import EdeTD3Config, TD3Config
from ede.io.atomic import MARK
from ede.method.adapters import IdentityAdapter
from ede.method.agent import Agent
from ede.method.embedding import ActionEmbedding
from ede.method.replay import ReplayBuffer
from ede.run.spec import RunSpec
from ede.run.training import train_group, train_run

pytestmark = pytest.mark.slow

SEEDS = [0, 1, 2, 3]
CONFIG = TD3Config(
    hidden=[64, 64],
    batch_size=32,
    eval_every=200,
    eval_episodes=2,
    update_schedule="step",
    checkpoint_every=200,
)
CPU = torch.device("cpu")


def spec(seed: int, config: TD3Config = CONFIG) -> RunSpec:
    return RunSpec("ede/Point-v0", "td3", seed, 600, config, EdeTD3Config())


def outputs(run: Path) -> dict[str, object]:
    """What a run's result is: its returns and diagnostics (not wall times), its policy."""
    returns = [line.rsplit(",", 1)[0] for line in (run / "eval.csv").read_text().splitlines()]
    return {
        "returns": returns,
        "diagnostics": (run / "diagnostics.csv").read_text(),
        "policy": (run / "policy" / "policy.safetensors").read_bytes(),
    }


@pytest.fixture(scope="module")
def group(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The four seeds trained as one group, checkpoints kept (the last at step 400)."""
    root = tmp_path_factory.mktemp("group")
    train_group(
        [spec(s) for s in SEEDS],
        [root / f"seed{s}" for s in SEEDS],
        device=CPU,
        keep_checkpoint=True,
    )
    return root


def test_a_member_of_a_group_ends_as_it_ends_alone(group: Path, tmp_path: Path) -> None:
    train_run(spec(3), tmp_path / "alone", device=CPU)
    assert outputs(group / "seed3") == outputs(tmp_path / "alone")
    assert outputs(group / "seed0") != outputs(group / "seed3")  # members are different runs


def test_a_group_resumes_exactly_even_when_its_members_stopped_at_different_steps(
    group: Path, tmp_path: Path
) -> None:
    outs = [tmp_path / f"seed{s}" for s in SEEDS]
    for seed, out in zip(SEEDS, outs, strict=True):
        if seed != 0:  # seed 0 lost its checkpoint: it starts over and catches up alone
            shutil.copytree(group / f"seed{seed}" / "checkpoint", out / "checkpoint")
            shutil.copy(group / f"seed{seed}" / MARK, out / MARK)  # the run folder's own
    metrics = train_group([spec(s) for s in SEEDS], outs, device=CPU)
    assert [m["resumed_from_step"] for m in metrics] == [None, 400, 400, 400]
    for seed, out in zip(SEEDS, outs, strict=True):
        assert outputs(out) == outputs(group / f"seed{seed}"), seed


def test_a_run_alone_resumes_in_a_group_and_a_member_resumes_alone(
    group: Path, tmp_path: Path
) -> None:
    alone = tmp_path / "alone2"
    train_run(spec(2), alone, device=CPU, keep_checkpoint=True)  # its checkpoint: step 400
    outs = [tmp_path / "seed2", tmp_path / "seed3"]
    shutil.copytree(alone / "checkpoint", outs[0] / "checkpoint")
    shutil.copy(alone / MARK, outs[0] / MARK)  # the run folder's own
    metrics = train_group([spec(2), spec(3)], outs, device=CPU)  # seed 3 from its start
    assert [m["resumed_from_step"] for m in metrics] == [400, None]
    assert outputs(outs[0]) == outputs(alone) == outputs(group / "seed2")
    shutil.copytree(group / "seed1" / "checkpoint", tmp_path / "seed1" / "checkpoint")
    shutil.copy(group / "seed1" / MARK, tmp_path / "seed1" / MARK)  # the run folder's own
    assert train_run(spec(1), tmp_path / "seed1", device=CPU)["resumed_from_step"] == 400
    assert outputs(tmp_path / "seed1") == outputs(group / "seed1")


def test_a_group_is_one_task_and_algorithm_differing_in_seeds_only(tmp_path: Path) -> None:
    other = CONFIG.model_copy(update={"lr": 3e-4})
    with pytest.raises(ValueError, match="differ in their seeds only"):
        train_group([spec(0), spec(1, other)], [tmp_path / "a", tmp_path / "b"], device=CPU)


@pytest.mark.parametrize(
    "task",
    [
        "ede/Point-v0",  # never ends early: every member's episode ends together, one batch for all
        "InvertedPendulum-v5",  # ends when the pole falls: members are due different numbers of
        # updates at different steps, and each is masked out of the updates it is not due
    ],
)
def test_per_episode_batches_in_a_group_are_each_members_own(task: str, tmp_path: Path) -> None:
    config = CONFIG.model_copy(
        update={"update_schedule": "episode", "eval_every": 100, "checkpoint_every": 150}
    )
    specs = [RunSpec(task, "td3", seed, 300, config, EdeTD3Config()) for seed in (0, 1)]
    grouped = train_group(specs, [tmp_path / f"group{s}" for s in (0, 1)], device=CPU)
    episodes = {m["episodes"] for m in grouped}
    assert (len(episodes) > 1) == (task == "InvertedPendulum-v5")  # episodes ended apart
    for seed in (0, 1):
        train_run(specs[seed], tmp_path / f"alone{seed}", device=CPU)
        assert outputs(tmp_path / f"group{seed}") == outputs(tmp_path / f"alone{seed}"), seed


def test_a_member_masked_out_of_an_update_keeps_its_learner_state_bit_for_bit() -> None:
    config = CONFIG.model_copy(update={"policy_delay": 1})
    adapter = IdentityAdapter(-np.ones(2), np.ones(2), CPU)
    agent = Agent(3, adapter, config, CPU, seeds=[0, 1, 2])
    buffer = ReplayBuffer(100, 3, 2, 1, CPU, members=3)
    rng = np.random.default_rng(0)
    every, no = np.ones(3, dtype=bool), np.zeros(3, dtype=bool)
    for _ in range(50):
        obs, next_obs = rng.normal(size=(3, 3)), rng.normal(size=(3, 3))
        buffer.add(every, obs, torch.zeros(3, 2), np.zeros(3, int), np.ones(3), next_obs, no, no)
    agent.update(buffer)  # everyone: every member's moments are no longer zero
    before = agent.state_dict(1)
    agent.update(buffer, np.array([True, False, True]))
    after = agent.state_dict(1)
    assert all(torch.equal(before[k], after[k]) for k in before), "member 1 was touched"
    assert not torch.equal(agent.state_dict(0)["critic.0.weight"], before["critic.0.weight"])
    steps = [int(state["updates"]) for state in (after, agent.state_dict(0))]
    assert steps[0] == steps[1] - 1


def test_adding_a_member_or_a_purpose_shifts_no_stream() -> None:
    """Each member's generators are seeded from (its seed, the purpose) alone."""
    from ede.method.agent import PURPOSES, Streams

    alone, third = (
        Streams(7, CPU),
        Agent(
            3, IdentityAdapter(-np.ones(2), np.ones(2), CPU), CONFIG, CPU, seeds=[5, 6, 7]
        ).streams[2],
    )
    for purpose in Streams.SAVED:  # (the weights' stream was spent on the initial weights)
        draws = [torch.rand(4, generator=getattr(s, purpose)) for s in (alone, third)]
        assert torch.equal(*draws), purpose
    firsts = {
        purpose: torch.rand(4, generator=getattr(Streams(7, CPU), purpose)) for purpose in PURPOSES
    }
    assert len({tuple(d.tolist()) for d in firsts.values()}) == len(PURPOSES)  # all apart


@pytest.fixture(scope="module")
def point_embedding(point_store: Path) -> object:
    """A small embedding of ede/Point-v0's actions (k = 4), trained for one epoch."""
    from ede.config import DecoderConfig, EmbeddingConfig
    from ede.io.rollouts import Rollouts
    from ede.method.embedding import ActionEmbedding, train_decoder, train_encoder

    rollouts = Rollouts.open(point_store)
    small = {"hidden": [64, 64], "epochs": 1}
    encoded = train_encoder(rollouts, EmbeddingConfig.model_validate(small))
    decoded = train_decoder(
        rollouts, encoded, DecoderConfig.model_validate(small), 4, -np.ones(2), np.ones(2)
    )
    return ActionEmbedding(encoded.encoder, decoded.decoder, encoded.code_whitening, decoded.bound)


def test_an_ede_td3_member_of_a_group_ends_as_it_ends_alone(
    point_embedding: object, tmp_path: Path
) -> None:
    """Codes chosen in one batched forward and decoded for the members choosing at that step:
    each member's codes, actions and outputs are those it has alone."""
    config = CONFIG.model_copy(update={"start_steps": 100})
    specs = [RunSpec("ede/Point-v0", "ede-td3", s, 400, config, EdeTD3Config()) for s in (0, 1, 2)]
    embedding = cast(ActionEmbedding, point_embedding)
    train_group(specs, [tmp_path / f"seed{s.seed}" for s in specs], embedding, CPU)
    train_run(specs[1], tmp_path / "alone", embedding, CPU)
    assert outputs(tmp_path / "seed1") == outputs(tmp_path / "alone")
    assert outputs(tmp_path / "seed0") != outputs(tmp_path / "seed1")


def test_environments_in_worker_processes_change_nothing(group: Path, tmp_path: Path) -> None:
    """``td3.env_workers: yes`` (gymnasium's AsyncVectorEnv) steps each member's episodes as the
    training process does (SyncVectorEnv): the same outputs, also where a member resumes from a
    checkpoint (its episode replayed in its worker) while another starts over and catches up
    (the one ahead sitting steps out)."""
    config = CONFIG.model_copy(update={"env_workers": "yes"})
    outs = [tmp_path / f"seed{s}" for s in (0, 1)]
    shutil.copytree(group / "seed1" / "checkpoint", outs[1] / "checkpoint")  # at step 400
    shutil.copy(group / "seed1" / MARK, outs[1] / MARK)  # the run folder's own
    metrics = train_group([spec(s, config) for s in (0, 1)], outs, device=CPU)
    assert [m["resumed_from_step"] for m in metrics] == [None, 400]
    for seed, out in zip((0, 1), outs, strict=True):
        assert outputs(out) == outputs(group / f"seed{seed}"), seed
