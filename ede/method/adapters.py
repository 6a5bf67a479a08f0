"""What the actor's outputs mean: the one difference between TD3 and EDE-TD3.

An :class:`ActionAdapter` fixes the codes' box, their noise scales and k, and decodes a code into
k raw actions: the identity for TD3 (k = 1, the code is the action), the learned decoder D for
EDE-TD3 (a whitened code z of k actions; :mod:`ede.method.embedding`).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
import torch

from ede.method import ensemble
from ede.method.embedding import ActionEmbedding

__all__ = ["ActionAdapter", "EmbeddingAdapter", "IdentityAdapter"]


class ActionAdapter(Protocol):
    """What the actor's outputs mean: codes in a box, each decoded to K raw actions."""

    k: int
    code_size: int
    code_low: torch.Tensor  # (C,)
    code_high: torch.Tensor  # (C,)
    noise_scale: torch.Tensor  # (C,) the unit of exploration and target noise stds
    target_noise_scale: float  # target smoothing noise std, × noise_scale × this
    clip_scale: torch.Tensor  # (C,) the unit of the target noise clip
    plan_step: str  # how the critic sees i: "onehot" (size K) or "scalar" (the raw count)

    def decode(self, codes: torch.Tensor) -> torch.Tensor:
        """(B, C) -> (B, K, A) raw actions."""
        ...


class IdentityAdapter:
    """TD3: the code is the raw action, K = 1.

    ``noise_units``: "absolute" — noises in action units, whatever the box (sfujim's TD3 and the
    authors' code); "range" — × the half-range of the action box (stable-baselines3, which
    rescales actions to [−1, 1]). The two agree on a ±1 box.
    """

    k = 1
    target_noise_scale = 1.0
    plan_step = "onehot"  # unused: K = 1 has no plan step

    def __init__(
        self, low: np.ndarray, high: np.ndarray, device: torch.device, noise_units: str = "absolute"
    ) -> None:
        self.code_size = len(low)
        self.code_low = torch.as_tensor(low, dtype=torch.float32, device=device)
        self.code_high = torch.as_tensor(high, dtype=torch.float32, device=device)
        half_range = (self.code_high - self.code_low) / 2
        self.noise_scale = half_range if noise_units == "range" else torch.ones_like(half_range)
        self.clip_scale = self.noise_scale

    def decode(self, codes: torch.Tensor) -> torch.Tensor:
        return codes.unsqueeze(1)  # (B, A) -> (B, 1, A)


class EmbeddingAdapter:
    """EDE-TD3: the code is a whitened z in [−bound, bound]^D, decoded to K actions by D.

    Noise stds are × the bound (the authors' code); the target noise clip is in code units
    (``target_noise_clip="absolute"``, the authors' code) or × the bound × ``target_noise_scale``
    ("scaled").
    """

    def __init__(
        self,
        embedding: ActionEmbedding,
        bound_scale: float = 1.0,
        target_noise_scale: float = 1.0,
        target_noise_clip: str = "absolute",
        plan_step: str = "onehot",
    ) -> None:
        self.embedding = embedding
        self.target_noise_scale = target_noise_scale
        self.plan_step = plan_step
        self.k, self.code_size = embedding.k, embedding.dim
        bound = embedding.bound * bound_scale
        device = embedding.device
        self.code_low = torch.full((self.code_size,), -bound, device=device)
        self.code_high = torch.full((self.code_size,), bound, device=device)
        self.noise_scale = self.code_high
        ones = torch.ones_like(self.code_high)
        scaled = target_noise_clip == "scaled"
        self.clip_scale = bound * target_noise_scale * ones if scaled else ones

    @torch.no_grad()
    def decode(self, codes: torch.Tensor) -> torch.Tensor:
        """(B, D) -> (B, K, A), each code alone (:func:`ede.method.ensemble.row_by_row`): a member's
        actions do not depend on how many members chose a code with it."""
        return ensemble.row_by_row(self.embedding.decode, codes)
