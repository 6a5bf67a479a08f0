"""Small building blocks shared by the embedding models and the agents."""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["mlp", "pick_device"]


def mlp(
    in_size: int, hidden: list[int], out_size: int, activation: type[nn.Module] = nn.ReLU
) -> nn.Sequential:
    """A fully connected network: ``in_size -> hidden... -> out_size``, no output activation."""
    sizes = [in_size, *hidden]
    layers: list[nn.Module] = []
    for a, b in zip(sizes[:-1], sizes[1:]):
        layers += [nn.Linear(a, b), activation()]
    layers.append(nn.Linear(sizes[-1], out_size))
    return nn.Sequential(*layers)


def pick_device(name: str) -> torch.device:
    """``"cpu"``, ``"cuda"`` (an error if there is none) or ``"auto"`` (CUDA when available)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("device 'cuda' was asked for, but torch sees no CUDA device")
    return torch.device(name)
