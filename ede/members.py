"""Many runs' networks as one: stacked weights with a member axis, each member computing exactly
what it computes alone.

The building blocks of training several runs (seeds) of one task and algorithm in one process
(issue 17): every member's network has the same shape, so M of them are one set of tensors with a
leading member axis, and a layer is one batched product for all members instead of M small ones.
The contract is independence: a member's numbers never depend on which other members share its
process, and equal those of the same network alone, bit for bit on CPU in fp32. What keeps it
(measured on torch 2.13's CPU kernels; ``tests/ede/test_members.py`` holds it):

* a layer with two or more outputs is ``baddbmm(b, x, Wᵀ)`` over the member axis: per member the
  same bits as ``nn.Linear`` (``F.linear``), forward and backward, whatever M is;
* a layer with one output (a critic's head) takes another kernel inside ``baddbmm`` once M ≥ 2, so
  it is computed member by member with ``F.linear``: M small products, still bit-exact;
* Adam runs as one fused kernel over the members' *views* (:class:`MemberAdam`): a fused Adam over
  a stacked tensor vectorises a member's elements differently than over the member alone (the
  last ``numel % 16`` elements of a tensor take a scalar path), which changes rounding.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["MemberAdam", "StackedMLP"]


class StackedMLP(nn.Module):
    """M multilayer perceptrons of one shape (``ede.nets.mlp``: Linear layers with in-place ReLU
    between them) as stacked weights ``(M, out, in)`` and biases ``(M, out)``.

    ``forward`` maps ``(M, B, in)`` to ``(M, B, out)``: member j's slice is what member j's own
    network gives for ``x[j]``.
    """

    def __init__(self, members: Sequence[nn.Sequential]) -> None:
        super().__init__()
        layers = [[m for m in member if isinstance(m, nn.Linear)] for member in members]
        shapes = {tuple(layer.weight.shape for layer in member) for member in layers}
        if len(shapes) != 1:
            raise ValueError(f"members of different shapes: {sorted(shapes)}")
        self.members = len(members)
        self.weights = nn.ParameterList(
            nn.Parameter(torch.stack([member[i].weight.detach() for member in layers]).clone())
            for i in range(len(layers[0]))
        )
        self.biases = nn.ParameterList(
            nn.Parameter(torch.stack([member[i].bias.detach() for member in layers]).clone())
            for i in range(len(layers[0]))
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            if w.shape[1] == 1:  # one output: member by member (see the module's notes)
                x = torch.stack([F.linear(x[j], w[j], b[j]) for j in range(self.members)])
            else:
                x = torch.baddbmm(b.unsqueeze(1), x, w.mT)  # (M, B, in) -> (M, B, out)
            if i < last:
                x = torch.relu_(x)
        return x

    def member(self, j: int) -> nn.Sequential:
        """Member j as a plain ``nn.Sequential`` of its own (copies of its weights)."""
        layers: list[nn.Module] = []
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            linear = nn.Linear(w.shape[2], w.shape[1])
            with torch.no_grad():
                linear.weight.copy_(w[j])
                linear.bias.copy_(b[j])
            layers.append(linear)
            if i < len(self.weights) - 1:
                layers.append(nn.ReLU(inplace=True))
        return nn.Sequential(*layers)


class MemberAdam:
    """Adam (torch's fused CPU/CUDA kernel) over stacked parameters, member by member in one call.

    The kernel is handed each member's view of each parameter, so every member's tensors are
    split into vector and scalar parts exactly as ``torch.optim.Adam(fused=True)`` splits them for
    that member alone: the same bits. All members share one step count (they step together).
    """

    def __init__(self, params: Sequence[torch.Tensor], lr: float,
                 betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8) -> None:
        self.params = list(params)
        self.lr, self.betas, self.eps = lr, betas, eps
        self.members = len(self.params[0])
        self.exp_avg = [torch.zeros_like(p) for p in self.params]
        self.exp_avg_sq = [torch.zeros_like(p) for p in self.params]
        self.step_count = torch.zeros((), dtype=torch.float32, device=self.params[0].device)
        self._views = [p.detach()[j] for p in self.params for j in range(self.members)]
        self._avg = [t[j] for t in self.exp_avg for j in range(self.members)]
        self._avg_sq = [t[j] for t in self.exp_avg_sq for j in range(self.members)]

    @torch.no_grad()
    def step(self) -> None:
        grads = [p.grad[j] for p in self.params for j in range(self.members)]
        self.step_count += 1
        torch._fused_adam_(
            self._views, grads, self._avg, self._avg_sq, [], [self.step_count] * len(grads),
            lr=self.lr, beta1=self.betas[0], beta2=self.betas[1], weight_decay=0.0, eps=self.eps,
            amsgrad=False, maximize=False,
        )

    def state_dict(self) -> dict[str, torch.Tensor]:
        state = {"step": self.step_count.clone()}
        for i, (avg, avg_sq) in enumerate(zip(self.exp_avg, self.exp_avg_sq)):
            state[f"{i}.exp_avg"], state[f"{i}.exp_avg_sq"] = avg.clone(), avg_sq.clone()
        return state

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        self.step_count.copy_(state["step"])
        for i, (avg, avg_sq) in enumerate(zip(self.exp_avg, self.exp_avg_sq)):
            avg.copy_(state[f"{i}.exp_avg"])
            avg_sq.copy_(state[f"{i}.exp_avg_sq"])
