"""``td3.precision``: what each setting computes, that it stays inside updates, reproducibility."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ede.config import TD3Config
from ede.method.adapters import IdentityAdapter
from ede.method.agent import Agent
from ede.method.nets import matmul_precision, product_error
from ede.method.replay import ReplayBuffer
from tests.support import add_step

PRECISIONS = ["fp32", "bf16-matmul", "bf16"]


# Between fp32-accurate products (~3e-7) and products of bf16-rounded inputs (~3e-3).
ROUNDED = 1e-4


def medium_rounds_to_bf16() -> bool:
    """Whether this machine's "medium" products round their inputs to bf16, as observed.

    Where oneDNN multiplies with AMX they do; on CPUs without AMX (AVX-512-BF16 or not) torch's
    "medium" products were found fp32-accurate — so this is measured, never read off a flag.
    """
    return product_error("bf16-matmul") > ROUNDED


def relative_error(a: torch.Tensor, b: torch.Tensor) -> float:
    return ((a - b).abs().max() / b.abs().max()).item()


@pytest.mark.parametrize("rows", [64, 100, 256])
def test_bf16_matmul_is_either_fp32_or_exactly_bf16_inputs_and_only_inside_its_block(
    rows: int,
) -> None:
    generator = torch.Generator().manual_seed(rows)
    x, w = torch.randn(rows, 256, generator=generator), torch.randn(256, 256, generator=generator)
    exact = x.double() @ w.double()
    rounded = x.bfloat16().double() @ w.bfloat16().double()  # bf16 inputs, exact accumulation
    before = torch.get_float32_matmul_precision()
    with matmul_precision("bf16-matmul"):
        inside = (x @ w).double()
        inside_linear = torch.nn.functional.linear(x, w.T).double()
    outside = (x @ w).double()
    assert torch.get_float32_matmul_precision() == before
    assert relative_error(outside, exact) < 1e-5
    for product in (inside, inside_linear):
        if medium_rounds_to_bf16():
            # fp32 accumulation of bf16-rounded inputs: ~3e-3 away from the fp32 product
            assert relative_error(product, rounded) < 1e-5 < 1e-3 < relative_error(product, exact)
        else:
            assert relative_error(product, exact) < 1e-5


def test_autocast_bf16_rounds_products_on_every_machine_and_fp32_never_does() -> None:
    assert product_error("fp32") < 1e-5
    assert 1e-3 < product_error("bf16") < 2e-2


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_the_other_precisions_keep_fp32_products(precision: str) -> None:
    with matmul_precision(precision):
        assert torch.get_float32_matmul_precision() == "highest"


def test_the_process_wide_setting_comes_back_after_an_error() -> None:
    torch.set_float32_matmul_precision("high")
    try:
        with pytest.raises(RuntimeError), matmul_precision("bf16-matmul"):
            raise RuntimeError("inside")
        assert torch.get_float32_matmul_precision() == "high"
    finally:
        torch.set_float32_matmul_precision("highest")


def trained_agent(precision: str, updates: int = 6) -> Agent:
    config = TD3Config.model_validate(
        {"hidden": [64, 64], "batch_size": 32, "precision": precision}
    )
    device = torch.device("cpu")
    agent = Agent(5, IdentityAdapter(-np.ones(2), np.ones(2), device), config, device, seeds=[0])
    buffer = ReplayBuffer(256, 5, 2, 1, device)
    rng = np.random.default_rng(0)
    for t in range(200):
        add_step(
            buffer,
            0,
            rng.normal(size=5),
            torch.as_tensor(rng.uniform(-1, 1, 2), dtype=torch.float32),
            0,
            float(rng.normal()),
            rng.normal(size=5),
            False,
            t % 50 == 49,
        )
    for _ in range(updates):
        agent.update(buffer)
    return agent


def actor_weights(agent: Agent) -> list[torch.Tensor]:
    return [p.detach().clone() for p in agent.actor.params.values()]


@pytest.mark.parametrize("precision", PRECISIONS)
def test_each_precision_is_reproducible_and_keeps_fp32_weights(precision: str) -> None:
    first, second = trained_agent(precision), trained_agent(precision)
    for a, b in zip(actor_weights(first), actor_weights(second), strict=True):
        assert a.dtype == torch.float32 and torch.equal(a, b)
    assert torch.get_float32_matmul_precision() == "highest"  # nothing leaks out of update()


@pytest.mark.parametrize("precision", ["bf16-matmul", "bf16"])
def test_reduced_precisions_change_the_updates_only_slightly(precision: str) -> None:
    reference = actor_weights(trained_agent("fp32"))
    reduced = actor_weights(trained_agent(precision))
    errors = [relative_error(r, f) for r, f in zip(reduced, reference, strict=True)]
    assert max(errors) < 0.05, errors
    if precision == "bf16" or medium_rounds_to_bf16():
        assert max(errors) > 0, "the setting had no effect"
    else:  # "medium" products are fp32-accurate here, if perhaps summed in another order
        assert max(errors) < 1e-4
