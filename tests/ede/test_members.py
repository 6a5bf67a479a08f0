"""Stacked members compute, per member, exactly what each network computes alone (CPU, fp32)."""

from __future__ import annotations

import pytest
import torch

from ede.members import MemberAdam, StackedMLP
from ede.nets import initial_weights, mlp

IN, HIDDEN, BATCH = 12, [400, 300], 100


def networks(seeds: list[int], out: int) -> list[torch.nn.Sequential]:
    nets = []
    for seed in seeds:
        with initial_weights(seed):
            nets.append(mlp(IN, HIDDEN, out))
    return nets


def inputs(seeds: list[int]) -> torch.Tensor:
    return torch.stack([torch.randn(BATCH, IN, generator=torch.Generator().manual_seed(100 + s))
                        for s in seeds])


@pytest.mark.parametrize("out", [1, 2])  # a critic's head and an actor's output
@pytest.mark.parametrize("seeds", [[3], [0, 1, 2, 3]])
def test_each_member_computes_its_own_networks_values_and_gradients(out: int,
                                                                      seeds: list[int]) -> None:
    alone = networks(seeds, out)
    stacked = StackedMLP(networks(seeds, out))
    x = inputs(seeds).requires_grad_(True)
    y = stacked(x)
    (y ** 2).sum().backward()
    for j, net in enumerate(alone):
        xj = x[j].detach().clone().requires_grad_(True)
        yj = net(xj)
        assert torch.equal(y[j], yj)
        (yj ** 2).sum().backward()
        assert torch.equal(x.grad[j], xj.grad)
        linears = [m for m in net if isinstance(m, torch.nn.Linear)]
        for layer, w, b in zip(linears, stacked.weights, stacked.biases):
            assert torch.equal(w.grad[j], layer.weight.grad)
            assert torch.equal(b.grad[j], layer.bias.grad)


def test_a_member_does_not_depend_on_the_others_and_comes_back_out_whole() -> None:
    x = inputs([0, 1, 2, 3])
    group = StackedMLP(networks([0, 1, 2, 3], 1))
    alone = StackedMLP(networks([3], 1))
    assert torch.equal(group(x)[3], alone(x[3:])[0])
    assert torch.equal(group.member(3)(x[3]), networks([3], 1)[0](x[3]))
    with pytest.raises(ValueError, match="different shapes"):
        StackedMLP(networks([0], 1) + networks([1], 2))


def test_member_adam_steps_each_member_as_fused_adam_steps_it_alone() -> None:
    seeds = [0, 1, 2, 3]
    alone = networks(seeds, 1)
    optimisers = [torch.optim.Adam(net.parameters(), lr=1e-3, fused=True) for net in alone]
    stacked = StackedMLP(networks(seeds, 1))
    adam = MemberAdam(list(stacked.parameters()), lr=1e-3)
    for step in range(5):
        x = inputs([s + 10 * step for s in seeds])
        for p in stacked.parameters():
            p.grad = None
        (stacked(x) ** 2).mean(dim=(1, 2)).sum().backward()  # per-member means, summed
        adam.step()
        for j, (net, optimiser) in enumerate(zip(alone, optimisers)):
            optimiser.zero_grad()
            (net(x[j]) ** 2).mean().backward()
            optimiser.step()
    for j, net in enumerate(alone):
        linears = [m for m in net if isinstance(m, torch.nn.Linear)]
        for layer, w, b in zip(linears, stacked.weights, stacked.biases):
            assert torch.equal(w[j], layer.weight) and torch.equal(b[j], layer.bias)
    restored = MemberAdam(list(StackedMLP(networks(seeds, 1)).parameters()), lr=1e-3)
    restored.load_state_dict(adam.state_dict())
    assert all(torch.equal(a, b) for a, b in zip(restored.exp_avg_sq, adam.exp_avg_sq))
