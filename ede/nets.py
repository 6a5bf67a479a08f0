"""Small building blocks shared by the embedding models and the agents."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, nullcontext
from functools import cache
from typing import Any

import torch
from torch import nn

__all__ = ["Layers", "StackedMLP", "flatten", "gradients", "initial_weights", "matmul_precision",
           "mlp", "pick_device", "product_error"]


def mlp(
    in_size: int, hidden: list[int], out_size: int, activation: type[nn.Module] = nn.ReLU
) -> nn.Sequential:
    """A fully connected network: ``in_size -> hidden... -> out_size``, no output activation.

    The activations work in place on the linear layers' outputs, which their backward passes do
    not need: one fresh tensor fewer per layer (~5% of a TD3 update on CPU).
    """
    sizes = [in_size, *hidden]
    layers: list[nn.Module] = []
    for a, b in zip(sizes[:-1], sizes[1:]):
        layers += [nn.Linear(a, b), activation(inplace=True)]
    layers.append(nn.Linear(sizes[-1], out_size))
    return nn.Sequential(*layers)


Layers = list[tuple[torch.Tensor, torch.Tensor]]  # (weight (G, out, in), bias (G, out)) per layer


def flatten(layers: Sequence[torch.Tensor], width: int) -> torch.Tensor:
    """The ``(G, width)`` rows of which ``layers`` (weight, bias, weight, ...) are views
    (:meth:`StackedMLP.layers`), as one tensor: where per-layer gradients become one flat
    gradient (zero in the padding)."""
    parts = [t.flatten(1) for t in layers]
    used = sum(p.shape[1] for p in parts)
    return torch.cat([*parts, parts[0].new_zeros(parts[0].shape[0], width - used)], dim=1)


def gradients(
    loss: Callable[..., tuple[torch.Tensor, torch.Tensor]], params: Sequence[torch.Tensor],
    *args: Any,
) -> tuple[list[torch.Tensor], torch.Tensor]:
    """The gradients of ``loss(params, *args)[0]`` with respect to ``params``, and its second
    output: torch's autograd in eager mode, ``torch.func.grad`` when compiled (Dynamo traces
    that, not ``torch.autograd.grad``); the same derivatives either way."""
    if torch.compiler.is_compiling():
        grads, aux = torch.func.grad(loss, has_aux=True)(list(params), *args)
        return grads, aux
    leaves = [p.detach().requires_grad_(True) for p in params]
    total, aux = loss(leaves, *args)
    return list(torch.autograd.grad(total, leaves)), aux.detach()


class StackedMLP(nn.Module):
    """G ReLU networks of one shape (``in_size -> hidden... -> out_size``) as one parameter.

    ``flat`` has shape ``(G, N)``: row g is network g's weights and biases, layer by layer, each
    layer's weight ``(out, in)`` row-major then its bias — the layout of :meth:`layers` and of
    :meth:`state_of`, which names them as an ``nn.Sequential`` of ``nn.Linear`` layers would
    (``0.weight``, ``0.bias``, ``2.weight``, ...). Row g is initialised as ``nn.Linear``
    initialises its layers, from ``generators[g]`` alone, so a network's initial weights do not
    depend on the others.

    :meth:`forward` computes every network on its own batch as one product per layer. What it
    computes for network g never depends on G — its bits are the same alone and among others —
    because every product it hands to the BLAS library is a batch of at least two matrices (with
    ``halves``, each network's rows split in two), and such a batch takes one kernel whatever its
    size (MKL computes a batch of one through another entry point, whose bits differ on some CPUs
    for some shapes); a layer with one output is a product and a sum, no BLAS at all. Everything
    else is elementwise or a reduction within one network's rows.
    """

    def __init__(self, in_size: int, hidden: Sequence[int], out_size: int,
                 generators: Sequence[torch.Generator]) -> None:
        super().__init__()
        sizes = [in_size, *hidden, out_size]
        self.shapes = [(b, a) for a, b in zip(sizes[:-1], sizes[1:])]  # (out, in) per layer
        # Rows padded to 64 bytes, so that every network's tensors sit at the same alignment
        # whatever row it has (some BLAS kernels round by alignment).
        width = -(-sum(out * inp + out for out, inp in self.shapes) // 16) * 16
        flat = torch.zeros(len(generators), width)
        for row, generator in zip(flat, generators):
            for weight, bias in self.layers(row):  # nn.Linear.reset_parameters, drawn from g
                nn.init.kaiming_uniform_(weight, a=math.sqrt(5), generator=generator)
                bound = 1 / math.sqrt(weight.shape[1])
                nn.init.uniform_(bias, -bound, bound, generator=generator)
        self.flat = nn.Parameter(flat)
        self._views: tuple[int, Layers] | None = None  # the layers of ``flat``, listed once

    def layers(self, flat: torch.Tensor) -> Layers:
        """Views of each layer's weight ``(..., out, in)`` and bias ``(..., out)`` in ``flat``
        (``(..., N)``: one network's row, or several)."""
        views, at = [], 0
        for out, inp in self.shapes:
            weight = flat[..., at:at + out * inp].unflatten(-1, (out, inp))
            at += out * inp
            views.append((weight, flat[..., at:at + out]))
            at += out
        return views

    def state_of(self, row: torch.Tensor) -> dict[str, torch.Tensor]:
        """One network's row as an ``nn.Sequential`` of ``mlp`` names its tensors."""
        state = {}
        for index, (weight, bias) in enumerate(self.layers(row)):
            state[f"{2 * index}.weight"], state[f"{2 * index}.bias"] = weight, bias
        return state

    def forward(self, x: torch.Tensor, layers: Layers | None = None,
                halves: bool = False) -> torch.Tensor:
        """``(G, B, in) -> (G, B, out)``: network g on ``x[g]``.

        ``layers`` replaces the parameter's layers (:meth:`layers` of a detached copy, a
        functional transform's input, a slice of rows); ``halves`` splits each network's rows
        into two products of one batch, which keeps every batch at two matrices or more when G
        may be 1.
        """
        if layers is None and torch.compiler.is_compiling():
            layers = self.layers(self.flat.detach())
        elif layers is None:
            if self._views is None or self._views[0] != self.flat.data_ptr():
                self._views = (self.flat.data_ptr(), self.layers(self.flat.detach()))
            layers = self._views[1]  # the parameter's own layers: constants (no gradient)
        groups, rows = x.shape[:2]
        if halves:
            if rows % 2:
                x = torch.cat([x, x.new_zeros(groups, 1, x.shape[2])], dim=1)
            x = x.reshape(2 * groups, -1, x.shape[2])
        last = len(self.shapes) - 1
        for index, (weight, bias) in enumerate(layers):
            if halves:
                weight, bias = weight.repeat_interleave(2, 0), bias.repeat_interleave(2, 0)
            if weight.shape[1] == 1:  # one output: a product and a sum over the inputs
                x = (x * weight).sum(-1, keepdim=True) + bias.unsqueeze(1)
            else:
                x = torch.baddbmm(bias.unsqueeze(1), x, weight.mT)
            if index < last:
                x = torch.relu_(x)
        if halves:
            x = x.reshape(groups, -1, x.shape[2])[:, :rows]
        return x

    def one(self, g: int, x: torch.Tensor) -> torch.Tensor:
        """Network g alone on ``x`` ``(B, in)``, layer by layer as ``nn.Linear`` computes it
        (acting and evaluation: the same kernels whatever G is)."""
        last = len(self.shapes) - 1
        for index, (weight, bias) in enumerate(self.layers(self.flat[g])):
            x = torch.nn.functional.linear(x, weight, bias)
            if index < last:
                x = torch.relu_(x)
        return x


@contextmanager
def initial_weights(seed: int) -> Iterator[None]:
    """Modules built inside the block draw their initial weights from a generator seeded ``seed``.

    ``nn.Module`` constructors draw from torch's global CPU generator; the block seeds it and
    puts its state back on leaving, so nothing outside (a caller's draws, another run in the
    process) is reseeded or disturbed.
    """
    with torch.random.fork_rng(devices=[]):
        torch.default_generator.manual_seed(seed)
        yield


def pick_device(name: str) -> torch.device:
    """``"cpu"``, ``"cuda"`` (an error if there is none) or ``"auto"`` (CUDA when available)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("device 'cuda' was asked for, but torch sees no CUDA device")
    return torch.device(name)


@contextmanager
def matmul_precision(precision: str) -> Iterator[None]:
    """Within the block, fp32 matrix products follow ``precision`` (a ``td3.precision`` value).

    ``bf16-matmul`` is torch's "medium" float32 matmul precision: what it computes depends on
    the machine (TF32 on CUDA; on CPUs, bf16-rounded inputs with fp32 accumulation where oneDNN
    uses AMX, fp32-accurate products elsewhere — :func:`product_error` tells which). ``fp32`` and
    ``bf16`` (autocast, which casts explicitly) keep torch's full fp32 products.
    The process-wide setting is restored on leaving.
    """
    before = torch.get_float32_matmul_precision()
    torch.set_float32_matmul_precision("medium" if precision == "bf16-matmul" else "highest")
    try:
        yield
    finally:
        torch.set_float32_matmul_precision(before)


def flushes_denormals() -> bool:
    """Whether this thread's float arithmetic flushes subnormal numbers to zero, as observed."""
    return torch.tensor([1e-39]).mul(1.0).item() == 0.0


@contextmanager
def flush_denormals() -> Iterator[None]:
    """Within the block, CPU float arithmetic of this thread (and of threads it starts) treats
    subnormal numbers (below 1.2e-38 in fp32) as zero.

    A long TD3 run needs this for speed, not accuracy: Adam's first moment of a weight whose
    gradient is zero (a dead ReLU unit's) decays by ``beta1`` each update down into the
    subnormal range, where rounding keeps it a few units above zero for ever, and x86 CPUs
    compute on subnormals through a slow microcode path. Measured on a HalfCheetah-v5 run's
    state after 50,000 updates (73 % of the critic's first moments subnormal): the critic's
    fused Adam step took 2.35 ms instead of 0.32 ms. The step such a moment makes is far below
    its weight's last bit, so flushing leaves the weights as they were (tested). Where the CPU
    cannot flush, nothing changes. The setting found on entry is restored on leaving.
    """
    before = flushes_denormals()
    torch.set_flush_denormal(True)
    try:
        yield
    finally:
        torch.set_flush_denormal(before)


@cache
def product_error(precision: str, device: str = "cpu") -> float:
    """The relative error of a product as an update under ``precision`` computes it, here.

    What ``bf16-matmul`` computes is a property of the machine, not of a flag (see
    :func:`matmul_precision`), so it is observed: a fixed (100, 400) x (400, 300) fp32 product —
    the paper's batch and first hidden layer — under ``precision`` (and autocast for ``bf16``),
    against the same product in float64. About 3e-7 means fp32-accurate; about 3e-3 means the
    inputs were rounded to bf16.

    Args:
        precision: a ``td3.precision`` value.
        device: where to multiply.

    Returns:
        max |computed - exact| / max |exact|.
    """
    generator = torch.Generator().manual_seed(12345)
    x = torch.randn(100, 400, generator=generator)
    w = torch.randn(300, 400, generator=generator)
    exact = torch.nn.functional.linear(x.double(), w.double())
    x, w = x.to(device), w.to(device)
    autocast = (
        torch.autocast(torch.device(device).type, dtype=torch.bfloat16)
        if precision == "bf16"
        else nullcontext()
    )
    with matmul_precision(precision), autocast:
        computed = torch.nn.functional.linear(x, w)
    computed = computed.double().cpu()
    return ((computed - exact).abs().max() / exact.abs().max()).item()
