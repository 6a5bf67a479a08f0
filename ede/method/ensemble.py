"""The member axis: M runs of TD3 trained as one computation, each member computing what it
computes alone.

``ede/method/td3.py`` writes TD3 for one member: a network is a dict of parameters named as an
``nn.Sequential`` of ``nn.Linear`` layers names them (``0.weight`` ``(out, in)``, ``0.bias``
``(out,)``, ``2.weight``, ...), and every operation of the update acts on trailing dimensions.
This module stacks M members on a leading axis — a parameter ``(M, out, in)``, a batch
``(M, B, ...)``, a loss ``(M,)`` — and runs that same code on the stacks: the one place that knows
how members are laid out. A run alone is M = 1.

Bits. On CPU, with one torch thread (``td3.threads: 1``), a member's results are the same bit for
bit alone and among others (``tests/ede/test_group.py``). Three kernels would break that, and this
module avoids each:

* MKL multiplies a batch of one matrix through another entry point than a batch of two or more,
  whose bits differ on some CPUs for some shapes: where each member is one network, :func:`mlp`
  splits its rows into two halves, so every batched product holds two matrices or more;
* a layer with one output (the critic's last) is a product and a sum, no BLAS;
* an elementwise kernel runs whole vectors, then a scalar loop for the tail, which may round a
  fused multiply-add differently: a :class:`Stack` pads each member's row to whole vectors, so
  no member's elements fall in a tail whatever M is (and each row starts 64-byte aligned).

Acting runs the stacked actor on one observation per member (:func:`mlp` of one row each): each
member is then a product of its own, a stack of one evaluated beside a second view of itself. A
network all members share (the EDE decoder) runs on each member's row alone
(:func:`row_by_row`), since a product's rows are not computed alike for every number of rows.

``torch.func.vmap`` would lift the one-member update without the first trick, but at M = 1 its
batched products are a batch of one: it cannot keep a run's bits equal alone and in a group.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch.optim.adam import adam

__all__ = [
    "Adam",
    "Layers",
    "Params",
    "Stack",
    "Steps",
    "grad",
    "mlp",
    "one_row_each",
    "one_row_layers",
    "row_by_row",
]

Params = dict[str, torch.Tensor]  # a network's parameters by name; stacked: member axis first
# An optimiser step's host side: each member's step count after it, and which members take it.
Steps = tuple[np.ndarray, np.ndarray]
ROW_ALIGN = 32  # floats: two AVX-512 vectors, the widest step of torch's CPU elementwise loops


class Stack(torch.nn.Module):
    """A network's parameters of M members as one tensor ``flat`` ``(M, L·W)``: row m holds member
    m's L networks (L = 2 for the twin critics), each as its parameters one after another,
    flattened, then zeros to W, a multiple of ``ROW_ALIGN``. ``params`` names views of it,
    ``(M, *shape)`` each, or ``(M, L, *shape)`` where L > 1.

    One tensor per network, not one per layer, because Adam and the targets' moves are then one
    kernel call a member (:class:`Adam`) or a few operations over it instead of a few per layer:
    measured at 400-300 networks on one thread of an AMD EPYC, the critic's Adam step took 0.6 ms
    over the stack instead of 1.6-1.9 ms over its layers. A member's L networks are rows of their own so that the
    members' networks stack as ``(M·L, out, in)`` views, which a batched product takes uncopied.

    ``flat`` is a module's buffer, as every tensor the update writes in place (:class:`Adam`'s
    moments, the agent's loss sums): ``torch.compile`` treats a module's buffers as static inputs,
    the only inputs a CUDA graph (``td3.compile: reduce-overhead``) may write.
    """

    flat: torch.Tensor

    def __init__(self, members: Sequence[Params], device: torch.device, networks: int = 1) -> None:
        super().__init__()
        self.networks = networks
        lead = 1 if networks > 1 else 0  # a member's parameters: (L, *shape) where L > 1
        self.shapes = {name: tuple(value.shape[lead:]) for name, value in members[0].items()}
        used = sum(math.prod(shape) for shape in self.shapes.values())
        self.width = -(-used // ROW_ALIGN) * ROW_ALIGN
        self.register_buffer(
            "flat", torch.zeros(len(members), networks * self.width, device=device)
        )
        self._params = self.views(self.flat)
        self._members = [self.views(row) for row in self.flat]  # acting reads them every step
        for m, params in enumerate(members):
            self.load(m, params)

    @property
    def params(self) -> Params:
        """The members' named parameters, ``(M, *shape)`` or ``(M, L, *shape)`` views of
        :attr:`flat`. Made anew where ``torch.compile`` traces: the compiled update's inputs are
        then the buffers alone, none a view of another (aliased inputs lose their static mark)."""
        return self.views(self.flat) if torch.compiler.is_compiling() else self._params

    def views(self, flat: torch.Tensor) -> Params:
        """The named parameters of which ``flat`` (``(M, L·W)``, or one row ``(L·W,)``) holds the
        values, as views."""
        rows = flat.unflatten(-1, (self.networks, self.width))  # (..., L, W)
        views, at = {}, 0
        for name, shape in self.shapes.items():
            size = math.prod(shape)
            view = rows[..., at : at + size].unflatten(-1, shape)  # (..., L, *shape)
            views[name] = view if self.networks > 1 else view.squeeze(-1 - len(shape))
            at += size
        return views

    def flatten(self, tensors: Params) -> torch.Tensor:
        """Named tensors shaped as :attr:`params` (a gradient) as one ``(M, L·W)`` tensor."""
        members = self.flat.shape[0]
        parts = [tensors[name].reshape(members, self.networks, -1) for name in self.shapes]
        padding = self.width - sum(p.shape[2] for p in parts)
        parts.append(parts[0].new_zeros(members, self.networks, padding))
        return torch.cat(parts, dim=2).flatten(1)

    def member(self, m: int) -> Params:
        """Member ``m``'s parameters, views of its row (valid for good: every change is in
        place)."""
        return self._members[m]

    @torch.no_grad()
    def load(self, m: int, params: Params) -> None:
        for name, value in self.member(m).items():
            value.copy_(params[name])

    def clone(self) -> Stack:
        members = [self.member(m) for m in range(self.flat.shape[0])]
        return Stack(members, self.flat.device, self.networks)

    @torch.no_grad()
    def polyak(self, online: Stack, tau: float, due: torch.Tensor | None = None) -> None:
        """This (target) ← (1 − τ) this + τ online, for every member or those ``due``."""
        if due is None:
            self.flat.lerp_(online.flat, tau)
        else:
            self.flat.copy_(torch.where(due[:, None], self.flat.lerp(online.flat, tau), self.flat))


def mlp(params: Params, x: torch.Tensor) -> torch.Tensor:
    """A ReLU network (no output activation) of one member or of a stack.

    One network (weights ``(out, in)``): ``(..., in) -> (..., out)``, ``nn.Linear``'s products
    (acting and evaluation). A stack (weights ``(M, *L, out, in)``, each member ``L`` networks,
    as the twin critics are): ``(M, *L, B, in) -> (M, *L, B, out)``, each network on its rows.
    Where each member is one network, its rows are split into two halves, so that every batched
    product holds two matrices or more whatever M is (the module docstring says why). A stack's
    layers run on transposed activations, ``W @ xᵀ``: measured at 400-300 on one thread of an AMD
    EPYC, an update runs 12-15% faster than with ``x @ Wᵀ``, whose weight gradients come back
    transposed and were copied into place.
    """
    layers = [(params[f"{2 * j}.weight"], params[f"{2 * j}.bias"]) for j in range(len(params) // 2)]
    if layers[0][0].dim() == 2:
        for j, (weight, bias) in enumerate(layers):
            x = F.linear(x, weight, bias)
            x = torch.relu_(x) if j < len(layers) - 1 else x
        return x
    lead, rows = x.shape[:-2], x.shape[-2]
    x = x.reshape(-1, rows, x.shape[-1])  # (G, B, in): G networks
    if rows == 1 and layers[0][0].dim() == 3:
        return one_row_each(one_row_layers(params), x).reshape(*lead, 1, -1)
    halves = layers[0][0].dim() == 3
    if halves:
        if rows % 2:
            x = torch.cat([x, x.new_zeros(x.shape[0], 1, x.shape[2])], dim=1)
        x = x.reshape(2 * x.shape[0], -1, x.shape[2])  # (G, B, in) -> (2G, B/2, in)
    # Transposed, (G, in, B): each layer is W @ xᵀ, so that autograd hands a weight's gradient
    # back in the weight's own layout (a product's second operand gets its gradient transposed,
    # and copying it into place cost as much as the product).
    x = x.mT
    for j, (weight, bias) in enumerate(layers):
        weight, bias = weight.flatten(0, -3), bias.flatten(0, -2)  # (G, out, in), (G, out)
        if halves:  # each network twice: a stack of one as a view, others copied
            weight, bias = (
                (weight.expand(2, -1, -1), bias.expand(2, -1))
                if weight.shape[0] == 1
                else (weight.repeat_interleave(2, 0), bias.repeat_interleave(2, 0))
            )
        if weight.shape[1] == 1:  # one output: a product and a sum over the inputs
            x = (x * weight.mT).sum(-2, keepdim=True) + bias.unsqueeze(-1)
        else:
            x = torch.baddbmm(bias.unsqueeze(-1), weight, x)
        x = torch.relu_(x) if j < len(layers) - 1 else x
    return x.mT.reshape(*lead, -1, x.shape[-2])[..., :rows, :]


Layers = list[tuple[torch.Tensor, torch.Tensor]]  # (weight, bias) per layer, as products take them


def one_row_layers(params: Params) -> Layers:
    """A stack of M one-network members' layers as :func:`one_row_each` takes them: weights
    ``(G, in, out)``, biases ``(G, 1, out)``, views (valid as long as the stack's tensor), with
    G = M, or 2 for a stack of one: its network beside a second view of itself, so that every
    product is a batch of two matrices or more without a weight copied (halving one row, as
    :func:`mlp` halves batches, would copy every weight at every step)."""
    count = max(2, params["0.weight"].shape[0])
    return [
        (
            params[f"{2 * j}.weight"].mT.expand(count, -1, -1),  # (M, out, in) -> (G, in, out)
            params[f"{2 * j}.bias"].unsqueeze(1).expand(count, -1, -1),  # (M, out) -> (G, 1, out)
        )
        for j in range(len(params) // 2)
    ]


def one_row_each(layers: Layers, x: torch.Tensor) -> torch.Tensor:
    """:func:`mlp` of M members on one row each (acting): ``(M, 1, in) -> (M, 1, out)``, from
    :func:`one_row_layers`."""
    members = x.shape[0]
    x = x.expand(layers[0][0].shape[0], -1, -1)  # a stack of one: beside itself
    for j, (weight, bias) in enumerate(layers):
        if weight.shape[2] == 1:  # one output: a product and a sum over the inputs
            x = (x * weight.mT).sum(-1, keepdim=True) + bias
        else:
            x = torch.baddbmm(bias, x, weight)
        x = torch.relu_(x) if j < len(layers) - 1 else x
    return x[:members]


def row_by_row(network: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor) -> torch.Tensor:
    """``network`` (one network shared by every member, as the decoder is) on each row of ``x``
    ``(N, in)`` alone: the bits of a product's row depend on how many rows it has (measured on an
    AMD EPYC: products of 1 to 3 rows differ from those of 64), and a member's result must not
    depend on how many others compute beside it."""
    return torch.cat([network(row[None]) for row in x])


def grad(
    loss: Callable[..., torch.Tensor], stack: Stack, *args: Any
) -> tuple[torch.Tensor, torch.Tensor]:
    """The gradient ``(M, N)`` of every member's ``loss(params, *args)`` ``(M,)`` with respect to
    its own parameters, and the losses.

    Members share no parameter, so the gradient of the sum of their losses is each member's own.
    """
    if torch.compiler.is_compiling():
        # Dynamo traces torch.func.grad, not torch.autograd.grad; eager, torch.func.grad's
        # wrappers cost ~20% of a critic step (measured at 400-300), so eager uses autograd. The
        # derivatives are the same: both run the same backward kernels.
        def total(params: Params) -> tuple[torch.Tensor, torch.Tensor]:
            losses = loss(params, *args)
            return losses.sum(), losses.detach()

        grads, losses = torch.func.grad(total, has_aux=True)(stack.params)
        return stack.flatten(grads), losses
    params = {name: value.detach().requires_grad_(True) for name, value in stack.params.items()}
    losses = loss(params, *args)
    grads = torch.autograd.grad(losses.sum(), list(params.values()))
    return stack.flatten(dict(zip(params, grads, strict=True))), losses.detach()


class Adam(torch.nn.Module):
    """Adam (Kingma and Ba, 2015) on a :class:`Stack`, with a step count per member, masked: a
    member not due a step keeps its weights and moments bit for bit.

    Each member's step is torch's ``Adam`` on that member alone; the caller counts the steps. Its
    moments are buffers, as the stack's parameters are (:class:`Stack` says why). Eager, a step is
    torch's fused kernel (``torch.optim.adam.adam(fused=True)``) on each due member's row: one
    pass over the row instead of eight tensor operations over the stack (measured at 400-300 on
    one thread of an AMD EPYC, the critic's step 0.13 ms against 0.36 ms); a member not due is not
    handed to it. Each row is a tensor of its own, in whole vectors (:class:`Stack`), so a
    member's elements go through the same vector loop whatever M is. Where ``torch.compile``
    traces, it is the same arithmetic as tensor operations over the stack, which Inductor fuses,
    with the bias corrections handed in as a tensor (host numbers would be baked into the graph).
    """

    exp_avg: torch.Tensor
    exp_avg_sq: torch.Tensor
    _steps: torch.Tensor

    def __init__(
        self, stack: Stack, lr: float, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8
    ) -> None:
        super().__init__()
        self.stack, self.lr, self.betas, self.eps = stack, lr, betas, eps
        self.register_buffer("exp_avg", torch.zeros_like(stack.flat))
        self.register_buffer("exp_avg_sq", torch.zeros_like(stack.flat))
        # The fused kernel's step counts, one a member, set from the caller's before each step.
        self.register_buffer("_steps", torch.zeros(stack.flat.shape[0], device=stack.flat.device))
        self._rows = [  # member m's (weights, moments, step count): what the kernel takes
            (stack.flat[m], self.exp_avg[m], self.exp_avg_sq[m], self._steps[m])
            for m in range(stack.flat.shape[0])
        ]

    def corrections(self, steps: Sequence[int] | np.ndarray) -> np.ndarray:
        """``(2, M, 1)`` float32, on the host: each member's step size lr / (1 − β₁ᵗ) and
        √(1 − β₂ᵗ), for its t-th step (members at t = 0 take t = 1: they are not due and the
        values are unused)."""
        beta1, beta2 = self.betas
        rows = [
            (self.lr / (1 - beta1 ** max(t, 1)), math.sqrt(1 - beta2 ** max(t, 1))) for t in steps
        ]
        return np.array(rows, dtype=np.float32).T[..., None]

    @torch.no_grad()
    def step(
        self,
        grad: torch.Tensor,
        corrections: torch.Tensor,
        due: torch.Tensor | None = None,
        steps: Steps | None = None,
    ) -> None:
        """One step of every member, or of those where ``due`` (``(M,)`` bool) is true, along
        ``grad`` ``(M, N)``; ``corrections``: :meth:`corrections` of the members' step counts
        after this step. Eager, ``steps`` (:data:`Steps`: the same counts and mask on the host)
        chooses the fused kernel's members; where Dynamo traces, the arithmetic below runs."""
        if steps is not None and not torch.compiler.is_compiling():
            self._fused(grad, steps)
            return
        (beta1, beta2), (step_size, root) = self.betas, corrections
        param, m, v = self.stack.flat, self.exp_avg, self.exp_avg_sq
        kept = None if due is None else [t.clone() for t in (param, m, v)]
        m.lerp_(grad, 1 - beta1)
        v.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
        denom = torch.sqrt(v).div_(root).add_(self.eps)
        param.sub_(torch.mul(step_size, m).div_(denom))
        if due is not None and kept is not None:
            for new, old in zip((param, m, v), kept, strict=True):
                new.copy_(torch.where(due[:, None], new, old))

    def _fused(self, grad: torch.Tensor, steps: Steps) -> None:
        counts, due = steps
        members = np.flatnonzero(due)
        # The kernel counts each step it takes: it starts from the count before this one.
        self._steps.copy_(torch.as_tensor(counts - 1, dtype=torch.float32))
        rows = [self._rows[m] for m in members]
        grads = grad.unbind(0)
        beta1, beta2 = self.betas
        adam(
            [row[0] for row in rows],
            [grads[m] for m in members],
            [row[1] for row in rows],
            [row[2] for row in rows],
            [],
            [row[3] for row in rows],
            fused=True,
            amsgrad=False,
            beta1=beta1,
            beta2=beta2,
            lr=self.lr,
            weight_decay=0.0,
            eps=self.eps,
            maximize=False,
        )

    def member(self, m: int) -> dict[str, Params]:
        """Member ``m``'s moments by parameter name (views)."""
        return {
            "exp_avg": self.stack.views(self.exp_avg[m]),
            "exp_avg_sq": self.stack.views(self.exp_avg_sq[m]),
        }
