"""Small building blocks shared by the embedding models and the agents."""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, nullcontext
from functools import cache
from itertools import pairwise

import numpy as np
import torch
from torch import nn

__all__ = [
    "flush_denormals",
    "initial_mlp",
    "initial_weights",
    "matmul_precision",
    "mlp",
    "pick_device",
    "product_error",
    "to_device",
]


def mlp(
    in_size: int, hidden: list[int], out_size: int, activation: type[nn.Module] = nn.ReLU
) -> nn.Sequential:
    """A fully connected network: ``in_size -> hidden... -> out_size``, no output activation.

    The activations work in place on the linear layers' outputs, which their backward passes do
    not need: one fresh tensor fewer per layer (~5% of a TD3 update on CPU).
    """
    sizes = [in_size, *hidden]
    layers: list[nn.Module] = []
    for a, b in pairwise(sizes):
        layers += [nn.Linear(a, b), activation(inplace=True)]
    layers.append(nn.Linear(sizes[-1], out_size))
    return nn.Sequential(*layers)


def initial_mlp(sizes: Sequence[int], generator: torch.Generator) -> dict[str, torch.Tensor]:
    """The parameters of :func:`mlp` for ``sizes`` (``in, hidden..., out``), named as its
    ``nn.Sequential`` names them (``0.weight`` ``(out, in)``, ``0.bias``, ``2.weight``, ...), each
    layer initialised as ``nn.Linear`` initialises it, drawn from ``generator`` alone."""
    params = {}
    for j, (fan_in, fan_out) in enumerate(pairwise(sizes)):
        weight, bias = torch.empty(fan_out, fan_in), torch.empty(fan_out)
        nn.init.kaiming_uniform_(weight, a=math.sqrt(5), generator=generator)
        bound = 1 / math.sqrt(fan_in)
        nn.init.uniform_(bias, -bound, bound, generator=generator)
        params[f"{2 * j}.weight"], params[f"{2 * j}.bias"] = weight, bias
    return params


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


def to_device(values: np.ndarray | list, device: torch.device) -> torch.Tensor:
    """Host values as a tensor on ``device``, without waiting: on a GPU a copy from ordinary host
    memory first waits for every kernel queued before it, one from pinned memory does not, so
    the updates of an episode queue one after another with no round trip to the host."""
    tensor = torch.from_numpy(np.ascontiguousarray(values))
    if device.type == "cuda":
        return tensor.pin_memory().to(device, non_blocking=True)
    return tensor.to(device)


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
