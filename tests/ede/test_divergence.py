"""A run whose numbers stop being finite stops there: one line, its last checkpoint kept, no
``metrics.json``; the other runs of its group finish as they would alone."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import gymnasium
import numpy as np
import pytest
import torch

from ede.config import EdeTD3Config, TD3Config
from ede.method.adapters import IdentityAdapter
from ede.method.agent import Agent
from ede.run.spec import RunSpec
from ede.run.training import Diverged, train_group, train_run
from ede.tasks import make

CPU = torch.device("cpu")
SMALL = dict(
    hidden=[16, 16],
    batch_size=8,
    eval_every=100,
    eval_episodes=2,
    checkpoint_every=200,
    update_schedule="step",
)


class BreaksAt(gymnasium.Wrapper):
    """ede/Point-v0 whose ``what`` (observation or reward) turns NaN at its ``at``-th step,
    counted over episodes, in the run whose first reset has seed ``seed``."""

    def __init__(self, what: str, at: int, seed: int) -> None:
        super().__init__(make("ede/Point-v0"))
        self.what, self.at, self.seed, self.steps, self.armed = what, at, seed, 0, False

    def reset(self, **kwargs):
        if "seed" in kwargs and kwargs["seed"] is not None and self.steps == 0:
            self.armed = kwargs["seed"] == self.seed
        return self.env.reset(**kwargs)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.steps += 1
        if self.armed and self.steps == self.at:
            if self.what == "observation":
                obs = np.full_like(obs, np.nan)
            else:
                reward = float("inf")
        return obs, reward, terminated, truncated, info


for what in ("observation", "reward"):
    gymnasium.register(
        f"ede_test/PointNaN{what.title()}-v0",
        entry_point=lambda what=what, **_: BreaksAt(what, 350, seed=1),
        max_episode_steps=None,
    )


def spec(task: str, seed: int = 0, budget: int = 600, **td3) -> RunSpec:
    return RunSpec(task, "td3", seed, budget, TD3Config.model_validate(SMALL | td3), EdeTD3Config())


def rows(path: Path) -> list[dict[str, str]]:
    with open(path) as handle:
        return list(csv.DictReader(handle))


def test_a_learning_rate_that_blows_up_stops_the_run_at_the_non_finite_loss(tmp_path: Path) -> None:
    with pytest.raises(Diverged) as caught:
        train_run(spec("ede/Point-v0", lr=1e30), tmp_path)
    line = str(caught.value)
    assert len(line.splitlines()) == 1
    assert line.startswith("ede/Point-v0 td3 seed 0: diverged at step ")
    assert "the critic's loss is not finite" in line or "the actor's" in line
    assert line.endswith("stopped there, no metrics.json written; it has no checkpoint")
    step = int(line.split("diverged at step ")[1].split(":")[0])
    assert 8 <= step < 100  # the first update comes with the first batch of 8
    assert not (tmp_path / "metrics.json").exists() and not (tmp_path / "policy").exists()
    assert [float(r["mean_return"]) for r in rows(tmp_path / "eval.csv")] != []
    assert all(np.isfinite(float(r["mean_return"])) for r in rows(tmp_path / "eval.csv"))


@pytest.mark.parametrize("what", ["observation", "reward"])
def test_what_the_environment_produces_is_checked_and_the_last_good_checkpoint_kept(
    tmp_path: Path, what: str
) -> None:
    task = f"ede_test/PointNaN{what.title()}-v0"
    with pytest.raises(Diverged) as caught:
        train_run(spec(task, seed=1), tmp_path)
    assert str(caught.value) == (
        f"{task} td3 seed 1: diverged at step 350: the environment's {what} is not finite; stopped "
        f"there, no metrics.json written; its last checkpoint, {tmp_path / 'checkpoint'}, is at "
        "step 200"
    )
    assert not (tmp_path / "metrics.json").exists()
    assert [int(r["step"]) for r in rows(tmp_path / "eval.csv")] == [0, 100, 200, 300]
    state = json.loads((tmp_path / "checkpoint" / "state.json").read_text())
    assert state["step"] == 200


def test_in_a_group_the_diverged_run_stops_and_the_others_finish_as_alone(tmp_path: Path) -> None:
    task = "ede_test/PointNaNObservation-v0"  # breaks in seed 1's run only
    outs = [tmp_path / "group" / f"seed{s}" for s in (0, 1, 2)]
    with pytest.raises(Diverged) as caught:
        train_group([spec(task, seed=s) for s in (0, 1, 2)], outs)
    assert str(caught.value).splitlines()[0].startswith(f"{task} td3 seed 1: diverged at step 350")
    assert len(str(caught.value).splitlines()) == 1
    assert not (outs[1] / "metrics.json").exists()
    alone = tmp_path / "alone"
    train_run(spec(task, seed=2), alone)
    for out in (outs[0], outs[2]):
        assert (out / "metrics.json").exists()
    assert rows(outs[2] / "eval.csv") != [] and [
        r["mean_return"] for r in rows(outs[2] / "eval.csv")
    ] == [r["mean_return"] for r in rows(alone / "eval.csv")]


def test_every_json_written_is_valid_json(tmp_path: Path) -> None:
    from ede.io.atomic import write_json

    with pytest.raises(ValueError, match="not JSON compliant"):
        write_json(tmp_path / "x.json", {"final_return": float("nan")})
    assert not (tmp_path / "x.json").exists()


def test_non_finite_names_each_member_whose_loss_is_not_finite_and_no_other() -> None:
    config = TD3Config.model_validate(SMALL)
    agent = Agent(
        3, IdentityAdapter(np.array([-1.0]), np.array([1.0]), CPU), config, CPU, (0, 1, 2)
    )
    big = torch.finfo(torch.float32).max
    agent.loss_sums[0] = torch.tensor([big, big, 1.0])  # finite terms whose sum overflows
    assert agent.non_finite() == {}
    agent.loss_sums[2, 1] = float("nan")
    agent.loss_sums[0, 2] = float("-inf")
    assert agent.non_finite() == {1: "the actor's loss (its Q value)", 2: "the critic's loss"}
