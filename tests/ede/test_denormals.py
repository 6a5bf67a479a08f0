"""Training flushes subnormal numbers to zero, where the CPU can, and leaves the setting as found."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from ede.config import EdeTD3Config, TD3Config
from ede.nets import flush_denormals, flushes_denormals
from ede.training import RunSpec, train_run

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
    train_run(RunSpec("ede/Point-v0", "td3", 0, 100, config, EdeTD3Config()), tmp_path / "run",
              progress=lambda steps: observed.append(flushes_denormals()))
    assert observed and all(flushing == cpu_can_flush() for flushing in observed)
    assert not flushes_denormals()
