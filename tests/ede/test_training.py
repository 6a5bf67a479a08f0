"""The training loop's schedule: when the policy starts to act and when updates start."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch

from ede.config import EdeTD3Config, TD3Config
from ede.run.group import Group
from ede.run.spec import RunSpec

CPU = torch.device("cpu")


def run_of(config: TD3Config, budget: int = 1_000):
    """A run alone (a group of one) of ede/Point-v0's TD3, and its group."""
    group = Group([RunSpec("ede/Point-v0", "td3", 0, budget, config, EdeTD3Config())], None, CPU)
    return group.runs[0], group


def schedule(start_steps: int, steps: int, monkeypatch: pytest.MonkeyPatch) -> tuple[list, list]:
    """Which behaviour chose each step's code, and at which steps updates ran."""
    config = TD3Config(
        hidden=[16, 16], batch_size=8, start_steps=start_steps, update_schedule="step"
    )
    run, group = run_of(config)
    chosen_by, updated_at = [], []
    behave, update = group.agent.behave, group.agent.update

    def recording_behave(obs, members, uniform):
        chosen_by.extend(
            "uniform" if uniform[m] else "actor+noise" for m in np.flatnonzero(members)
        )
        return behave(obs, members, uniform)

    def recording_update(buffer, due):
        updated_at.append(run.step)
        return update(buffer, due)

    monkeypatch.setattr(group.agent, "behave", recording_behave)
    monkeypatch.setattr(group.agent, "update", recording_update)
    for _ in range(steps):
        group.advance()
    return chosen_by, updated_at


def test_with_no_start_steps_the_actor_acts_first_and_updates_start_with_the_first_batch(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    chosen_by, updated_at = schedule(0, 12, monkeypatch)
    assert chosen_by == ["actor+noise"] * 12
    assert updated_at == [8, 9, 10, 11, 12]  # a batch of 8 can be sampled from step 8 on


def test_start_steps_are_uniform_and_without_updates(monkeypatch: pytest.MonkeyPatch) -> None:
    chosen_by, updated_at = schedule(10, 12, monkeypatch)
    assert chosen_by == ["uniform"] * 10 + ["actor+noise"] * 2
    assert updated_at == [10, 11, 12]


def test_the_episode_schedule_updates_once_per_step_when_an_episode_ends(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    config = TD3Config(hidden=[16, 16], batch_size=8, start_steps=0, update_schedule="episode")
    run, group = run_of(config)
    updated_at = []
    update = group.agent.update

    def watched(buffer: Any, due: Any) -> Any:  # the update, noting the step it came at
        updated_at.append(run.step)
        return update(buffer, due)

    monkeypatch.setattr(group.agent, "update", watched)
    for _ in range(150):
        group.advance()
    assert run.episodes == 1 and updated_at == [100] * 100  # Point-v0's episodes are 100 steps


def test_diagnostics_are_the_means_of_the_updates_since_the_last_evaluation(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    config = TD3Config(
        hidden=[16, 16], batch_size=8, start_steps=0, eval_episodes=1, update_schedule="step"
    )
    run, group = run_of(config)
    losses = []  # what each step added to the sums

    for _ in range(20):
        before = group.agent.loss_sums[:, 0].clone()
        group.advance()
        losses.append((group.agent.loss_sums[:, 0] - before).tolist())
    group.evaluate(np.ones(1, dtype=bool))
    (row,) = run.diagnostics
    steps = [loss for loss in losses if loss[1]]  # the updates (from step 8 on)
    assert row["step"] == 20 and row["updates"] == len(steps) == 13
    assert row["critic_loss"] == pytest.approx(sum(loss[0] for loss in steps) / 13)
    actor = [loss[2] for loss in steps if loss[3]]
    assert len(actor) == 6 and row["mean_q"] == pytest.approx(-sum(actor) / 6)
    assert row["actor_loss"] == pytest.approx(-row["mean_q"])
    assert group.agent.loss_sums.abs().sum() == 0  # taken: the next interval starts from zero


def test_building_an_agent_or_an_embedding_reseeds_nothing_outside(point_store) -> None:
    from ede.config import EmbeddingConfig
    from ede.io.rollouts import Rollouts
    from ede.method.adapters import IdentityAdapter
    from ede.method.agent import Agent
    from ede.method.embedding import train_encoder

    torch.manual_seed(1234)
    expected = torch.rand(3)
    torch.manual_seed(1234)
    adapter = IdentityAdapter(-torch.ones(2).numpy(), torch.ones(2).numpy(), torch.device("cpu"))
    first = Agent(4, adapter, TD3Config(hidden=[8]), CPU, seeds=[0])
    train_encoder(Rollouts.open(point_store), EmbeddingConfig(hidden=[8], epochs=1))
    assert torch.equal(torch.rand(3), expected)  # the caller's stream went on untouched
    second = Agent(4, adapter, TD3Config(hidden=[8]), CPU, seeds=[0])
    assert torch.equal(first.actor.flat, second.actor.flat)  # the same seed, the same weights
    assert torch.equal(first.critic.flat, second.critic.flat)


def test_a_checkpoint_taken_inside_a_code_resumes_its_remaining_actions(
    point_store, tmp_path
) -> None:
    from ede.config import DecoderConfig, EmbeddingConfig
    from ede.io.rollouts import Rollouts
    from ede.method.embedding import ActionEmbedding, train_decoder, train_encoder

    rollouts = Rollouts.open(point_store)
    small: dict[str, Any] = {"hidden": [8], "epochs": 1}
    encoded = train_encoder(rollouts, EmbeddingConfig(**small))
    decoded = train_decoder(rollouts, encoded, DecoderConfig(**small), 4, -np.ones(2), np.ones(2))
    embedding = ActionEmbedding(
        encoded.encoder, decoded.decoder, encoded.code_whitening, decoded.bound
    )
    spec = RunSpec(
        "ede/Point-v0",
        "ede-td3",
        0,
        1_000,
        TD3Config(hidden=[16, 16], batch_size=8),
        EdeTD3Config(),
        "test",
    )

    def actions_after(group: Group, steps: int) -> list[np.ndarray]:
        for _ in range(steps):
            group.advance()
        return group.runs[0].episode.actions[-steps:]

    group = Group([spec], embedding, CPU)
    run = group.runs[0]
    actions_after(group, 6)
    assert group.executor.i[0] == 2  # two actions of the second code are left
    run.save(tmp_path / "checkpoint")
    again = Group([spec], embedding, CPU)
    resumed = again.runs[0]
    assert resumed.load(tmp_path / "checkpoint")
    assert resumed.step == run.step
    assert again.executor.i[0] == 2 and np.array_equal(again.executor.plan, group.executor.plan)
    assert torch.equal(again.executor.code, group.executor.code)
    ahead, after = actions_after(group, 6), actions_after(again, 6)
    assert all(np.array_equal(a, b) for a, b in zip(ahead, after, strict=True))
