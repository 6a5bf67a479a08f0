"""Training flushes subnormal numbers to zero, where the CPU can, and leaves the setting as found."""

from __future__ import annotations

from contextlib import nullcontext
from pathlib import Path

import pytest
import torch

from ede.config import EdeTD3Config, TD3Config
from ede.method.agent import Agent
from ede.method.nets import flush_denormals, flushes_denormals
from ede.run.group import Group
from ede.run.spec import RunSpec
from ede.run.training import train_run

SUBNORMAL = 1e-40  # below fp32's smallest normal number, 1.18e-38


def cpu_can_flush() -> bool:
    """What the hardware does, observed: whether asking for flushing makes subnormals vanish."""
    before = flushes_denormals()
    torch.set_flush_denormal(True)
    can = flushes_denormals()
    torch.set_flush_denormal(before)
    return can


def adam_first_moment_after_a_zero_gradient() -> float:
    """Adam's first moment of a weight with no gradient, starting one step from a subnormal."""
    weight = torch.nn.Parameter(torch.zeros(1))
    optimizer = torch.optim.Adam([weight], fused=True)
    weight.grad = torch.ones(1)
    optimizer.step()
    optimizer.state[weight]["exp_avg"].fill_(SUBNORMAL)
    weight.grad = torch.zeros(1)
    optimizer.step()
    return optimizer.state[weight]["exp_avg"].item()


def test_inside_the_block_adam_moments_that_decay_below_normal_become_zero() -> None:
    assert adam_first_moment_after_a_zero_gradient() != 0.0  # 0.9 x a subnormal, kept
    with flush_denormals():
        inside = adam_first_moment_after_a_zero_gradient()
    assert (inside == 0.0) == cpu_can_flush()
    assert not flushes_denormals()


def test_the_setting_found_on_entry_is_restored() -> None:
    if not cpu_can_flush():
        pytest.skip("this CPU cannot flush subnormals: there is no setting to restore")
    torch.set_flush_denormal(True)
    try:
        with flush_denormals():
            pass
        assert flushes_denormals()
    finally:
        torch.set_flush_denormal(False)


def test_a_run_trains_with_flushing_and_leaves_it_off(tmp_path: Path) -> None:
    config = TD3Config(hidden=[16, 16], batch_size=8, start_steps=0, eval_every=50, eval_episodes=1)
    observed = []
    train_run(
        RunSpec("ede/Point-v0", "td3", 0, 100, config, EdeTD3Config()),
        tmp_path / "run",
        progress=lambda steps: observed.append(flushes_denormals()),
    )
    assert observed and all(flushing == cpu_can_flush() for flushing in observed)
    assert not flushes_denormals()


def subnormal_first_moments(agent: Agent) -> int:
    moments = [adam.exp_avg for adam in (agent.actor_adam, agent.critic_adam)]
    values = torch.cat([m.flatten() for m in moments]).abs()
    return int(((values > 0) & (values < torch.finfo(torch.float32).tiny)).sum())


def test_flushing_changes_no_weight_where_moments_sink_below_normal() -> None:
    """Dead units' first moments sink to subnormals within ~800 updates; what an Adam step makes
    of them is below a weight's last bit, so flushing them leaves every weight as it was."""
    config = TD3Config(hidden=[32, 32], batch_size=16, start_steps=0, update_schedule="step")
    spec = RunSpec("ede/Point-v0", "td3", 0, 1_500, config, EdeTD3Config())
    agents = []
    for flush in (False, True):
        group = Group([spec], None, torch.device("cpu"))
        with flush_denormals() if flush else nullcontext():
            while group.advance():
                pass
        agents.append(group.agent)
    kept, flushed = agents
    assert subnormal_first_moments(kept) > 0
    assert (subnormal_first_moments(flushed) == 0) == cpu_can_flush()
    for network in ("actor", "critic", "actor_target", "critic_target"):
        for name, weight in getattr(kept, network).params.items():
            assert torch.equal(weight, getattr(flushed, network).params[name]), f"{network}.{name}"
