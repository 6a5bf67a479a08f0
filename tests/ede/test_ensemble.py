"""The member axis (``ede.method.ensemble``): a member computes the same bits alone and stacked with others,
and the stack's layout round-trips."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ede.method import ensemble
from ede.method.nets import initial_mlp

CPU = torch.device("cpu")
SIZES = [5, 32, 24, 3]


def members(count: int, networks: int = 1) -> list[ensemble.Params]:
    """``count`` members' parameters, member m's drawn from seed m (``networks`` stacked each)."""
    out = []
    for m in range(count):
        generator = torch.Generator().manual_seed(m)
        drawn = [initial_mlp(SIZES, generator) for _ in range(networks)]
        out.append(
            drawn[0]
            if networks == 1
            else {name: torch.stack([d[name] for d in drawn]) for name in drawn[0]}
        )
    return out


@pytest.mark.parametrize("networks", [1, 2])
@pytest.mark.parametrize("rows", [9, 10])  # an odd batch is padded to halves
def test_a_member_computes_the_same_bits_alone_and_in_a_stack(networks: int, rows: int) -> None:
    torch.set_num_threads(1)
    generator = torch.Generator().manual_seed(100)
    shape = (rows, SIZES[0]) if networks == 1 else (networks, rows, SIZES[0])
    x = [torch.randn(shape, generator=generator) for _ in range(3)]
    together = ensemble.Stack(members(3, networks), CPU, networks)
    alone = ensemble.Stack(members(3, networks)[2:], CPU, networks)
    y = ensemble.mlp(together.params, torch.stack(x))  # (3, ..., B, out)
    assert y.shape == (3, *shape[:-1], SIZES[-1])
    assert torch.equal(ensemble.mlp(alone.params, x[2][None])[0], y[2])
    # and what nn.Linear computes for that network, within rounding (other kernels)
    one = together.member(2)
    if networks == 1:
        torch.testing.assert_close(ensemble.mlp(one, x[2]), y[2], rtol=1e-5, atol=1e-6)


def test_views_and_flatten_round_trip_and_rows_are_whole_vectors() -> None:
    stack = ensemble.Stack(members(2, 2), CPU, networks=2)
    assert stack.flat.shape[1] % ensemble.ROW_ALIGN == 0
    assert stack.params["0.weight"].shape == (2, 2, SIZES[1], SIZES[0])
    assert torch.equal(stack.flatten(stack.params), stack.flat)
    for m, params in enumerate(members(2, 2)):
        assert all(torch.equal(stack.member(m)[k], v) for k, v in params.items())
    # The members' networks stack as (M·L, out, in) views of the one tensor, uncopied.
    weight = stack.params["2.weight"]
    assert weight.flatten(0, 1).data_ptr() == weight.data_ptr()
    assert weight.flatten(0, 1)._base is not None


def adam_step(
    adam: ensemble.Adam, grad: torch.Tensor, steps: list[int], due: list[bool], fused: bool
) -> None:
    """One step of ``adam`` as the agent takes it: eager, torch's fused kernel on the due members'
    rows (``fused``), or the arithmetic the compiled update runs."""
    counts, mask = np.array(steps), np.array(due)
    masked = None if mask.all() else torch.as_tensor(mask)
    adam.step(
        grad, torch.from_numpy(adam.corrections(counts)), masked, (counts, mask) if fused else None
    )


@pytest.mark.parametrize("fused", [True, False])
def test_a_member_not_due_keeps_its_weights_and_moments_bit_for_bit(fused: bool) -> None:
    stack = ensemble.Stack(members(3), CPU)
    adam = ensemble.Adam(stack, lr=1e-2)
    grad = torch.randn(stack.flat.shape, generator=torch.Generator().manual_seed(0))
    adam_step(adam, grad, [1, 1, 1], [True] * 3, fused)
    before = [t[1].clone() for t in (stack.flat, adam.exp_avg, adam.exp_avg_sq)]
    adam_step(adam, grad, [2, 1, 2], [True, False, True], fused)
    assert all(
        torch.equal(b, t[1])
        for b, t in zip(before, (stack.flat, adam.exp_avg, adam.exp_avg_sq), strict=True)
    )
    assert not torch.equal(stack.flat[0], stack.flat[1])  # the others did step


def test_a_members_adam_steps_are_the_same_bits_alone_and_in_a_stack() -> None:
    """The fused kernel on member 2's row, among three members at other step counts and alone."""
    torch.set_num_threads(1)
    together, alone = ensemble.Stack(members(3), CPU), ensemble.Stack(members(3)[2:], CPU)
    adams = ensemble.Adam(together, lr=1e-3), ensemble.Adam(alone, lr=1e-3)
    generator = torch.Generator().manual_seed(2)
    for t in range(1, 4):
        grad = torch.randn(together.flat.shape, generator=generator)
        adam_step(adams[0], grad, [t + 5, t, t], [True, t != 2, True], fused=True)
        adam_step(adams[1], grad[2:], [t], [True], fused=True)
    assert torch.equal(together.flat[2], alone.flat[0])
    assert torch.equal(adams[0].exp_avg_sq[2], adams[1].exp_avg_sq[0])


@pytest.mark.parametrize("fused", [True, False])
def test_adam_is_torchs_adam_for_one_member(fused: bool) -> None:
    torch.set_num_threads(1)
    params = members(1)[0]
    stack = ensemble.Stack([params], CPU)
    theirs = {k: v.clone().requires_grad_(True) for k, v in params.items()}
    optimizer = torch.optim.Adam(theirs.values(), lr=1e-3, foreach=False)
    adam = ensemble.Adam(stack, lr=1e-3)
    generator = torch.Generator().manual_seed(1)
    for t in range(1, 4):
        grads = {k: torch.randn(v.shape, generator=generator) for k, v in params.items()}
        for k, v in theirs.items():
            v.grad = grads[k].clone()
        optimizer.step()
        adam_step(adam, stack.flatten({k: g[None] for k, g in grads.items()}), [t], [True], fused)
    # The same arithmetic in the same order, but other kernels (torch's fused kernel on the whole
    # row, or a per-member tensor against torch's Python scalars, addcdiv against a product then
    # a quotient), which may round apart in the last bit: a tolerance.
    for k, v in theirs.items():
        torch.testing.assert_close(stack.member(0)[k], v.detach(), rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("count", [2, 5, 64])
def test_acting_one_row_per_member_gives_each_member_its_bits_alone(count: int) -> None:
    """Acting: the stacked actor on one observation per member; member m's action is the one
    it computes alone (a stack of one) whatever the number of members, at the paper's sizes."""
    torch.set_num_threads(1)
    sizes = [11, 400, 300, 2]
    params = []
    for m in range(count):
        params.append(initial_mlp(sizes, torch.Generator().manual_seed(m)))
    x = torch.randn(count, 1, sizes[0], generator=torch.Generator().manual_seed(100))
    together = ensemble.mlp(ensemble.Stack(params, CPU).params, x)  # (M, 1, O) -> (M, 1, C)
    for m in (0, count - 1):
        alone = ensemble.mlp(ensemble.Stack(params[m : m + 1], CPU).params, x[m : m + 1])
        assert torch.equal(together[m], alone[0]), m


@pytest.mark.parametrize("count", [1, 3, 64])
def test_a_shared_network_row_by_row_gives_each_row_its_bits_alone(count: int) -> None:
    torch.set_num_threads(1)
    network = torch.nn.Sequential(
        torch.nn.Linear(7, 400), torch.nn.SELU(), torch.nn.Linear(400, 28)
    )
    x = torch.randn(count, 7, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        rows = ensemble.row_by_row(network, x)
        assert torch.equal(rows[-1:], network(x[-1:]))
