"""The replay buffer of M members: each member's rows, sampled as k-step windows.

A sample is a step and the K steps from it on, which Equation 1's target needs
(:func:`ede.method.td3.k_step_targets`); each member samples its own rows from its own stream.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch

__all__ = ["ReplayBatch", "ReplayBuffer"]


class ReplayBatch(NamedTuple):
    """Sampled steps of every member and, for each, the K steps from it on (the k-step target).

    Leading dimensions ``(M, B)``: member, sample.
    """

    obs: torch.Tensor  # (M, B, O)
    code: torch.Tensor  # (M, B, C)
    i: torch.Tensor  # (M, B) int64
    rewards: torch.Tensor  # (M, B, K): r_t ... r_{t+K-1}
    terminated: torch.Tensor  # (M, B, K) bool
    truncated: torch.Tensor  # (M, B, K) bool
    next_obs: torch.Tensor  # (M, B, K, O): s_{t+1} ... s_{t+K}


class ReplayBuffer:
    """Every member's steps, stored step-first: row t mod N of each field holds step t of every
    member (``(N, M, …)``), so members in step share one write head.

    Each step stores the code being executed and its index i. A sample's K-step future is read by
    index arithmetic (``idx[..., None] + arange(K)``), never by a Python loop; the newest K − 1
    steps are not sampled because their future is not written yet. ``count[m]`` is the number of
    steps member m has written: its head is ``count[m] mod N``.
    """

    FIELDS = ("obs", "next_obs", "code", "i", "reward", "terminated", "truncated")

    def __init__(
        self,
        capacity: int,
        obs_size: int,
        code_size: int,
        k: int,
        device: torch.device,
        members: int = 1,
    ) -> None:
        self.capacity, self.k, self.device, self.members = capacity, k, device, members
        shape = (capacity, members)
        self.obs = torch.zeros((*shape, obs_size), device=device)
        self.next_obs = torch.zeros((*shape, obs_size), device=device)
        self.code = torch.zeros((*shape, code_size), device=device)
        self.i = torch.zeros(shape, dtype=torch.int64, device=device)
        self.reward = torch.zeros(shape, device=device)
        self.terminated = torch.zeros(shape, dtype=torch.bool, device=device)
        self.truncated = torch.zeros(shape, dtype=torch.bool, device=device)
        self.count = np.zeros(members, dtype=np.int64)

    def add(
        self,
        members: np.ndarray,
        obs: np.ndarray,
        code: torch.Tensor,
        i: np.ndarray,
        reward: np.ndarray,
        next_obs: np.ndarray,
        terminated: np.ndarray,
        truncated: np.ndarray,
    ) -> None:
        """One step of each member in ``members`` (``(M,)`` bool), from its rows of the others
        (``(M, ...)``): one write per field for the group, each member at its own head."""
        which = np.flatnonzero(members)
        values = {
            "obs": obs,
            "next_obs": next_obs,
            "code": code,
            "i": i,
            "reward": reward,
            "terminated": terminated,
            "truncated": truncated,
        }
        heads = self.count[which] % self.capacity
        if len(which) == self.members and (heads == heads[0]).all():  # in step: one row
            for name, value in values.items():
                row = getattr(self, name)[int(heads[0])]
                row.copy_(value if isinstance(value, torch.Tensor) else torch.from_numpy(value))
        else:
            rows = torch.as_tensor(heads, device=self.device)
            cols = torch.as_tensor(which, device=self.device)
            for name, value in values.items():
                field = getattr(self, name)
                field[rows, cols] = torch.as_tensor(value, dtype=field.dtype, device=self.device)[
                    cols
                ]
        self.count[which] += 1

    def size(self, member: int) -> int:
        return int(min(self.count[member], self.capacity))

    def sampleable(self, member: int) -> int:
        return max(0, self.size(member) - (self.k - 1))

    def indices(
        self, batch_size: int, generators: Sequence[torch.Generator | None]
    ) -> torch.Tensor:
        """``(M, B)`` rows to sample: member m's drawn from ``generators[m]``, uniform over its
        sampleable steps; a member given ``None`` draws nothing (it is not updated) and gets
        row 0."""
        rows = []
        for member, generator in enumerate(generators):
            if generator is None:
                rows.append(torch.zeros(batch_size, dtype=torch.int64, device=self.device))
                continue
            if self.sampleable(member) == 0:
                raise ValueError("the buffer holds no step whose K-step future is written")
            offset = torch.randint(
                self.sampleable(member), (batch_size,), generator=generator, device=generator.device
            )
            oldest = int(self.count[member]) - self.size(member)
            rows.append(((oldest + offset) % self.capacity).to(self.device))
        return torch.stack(rows)

    def gather(self, idx: torch.Tensor) -> ReplayBatch:
        """The batch at rows ``idx`` ``(M, B)``, every member from its own column."""
        member = torch.arange(self.members, device=self.device)[:, None]  # (M, 1)
        steps = (idx[..., None] + torch.arange(self.k, device=self.device)) % self.capacity
        return ReplayBatch(
            obs=self.obs[idx, member],
            code=self.code[idx, member],
            i=self.i[idx, member],
            rewards=self.reward[steps, member[..., None]],
            terminated=self.terminated[steps, member[..., None]],
            truncated=self.truncated[steps, member[..., None]],
            next_obs=self.next_obs[steps, member[..., None]],
        )

    def sample(self, batch_size: int, generators: Sequence[torch.Generator | None]) -> ReplayBatch:
        return self.gather(self.indices(batch_size, generators))

    def state_dict(self, member: int) -> dict[str, torch.Tensor]:
        """Member ``member``'s filled rows (row order) and its step count."""
        n = self.size(member)
        state = {name: getattr(self, name)[:n, member].cpu() for name in self.FIELDS}
        return state | {"count": torch.tensor(int(self.count[member]))}

    def load_state_dict(self, member: int, state: dict[str, torch.Tensor]) -> None:
        count = int(state["count"])
        n = min(count, self.capacity)
        for name in self.FIELDS:
            if state[name].shape[0] != n:
                raise ValueError(f"buffer.{name}: {state[name].shape[0]} rows, expected {n}")
            getattr(self, name)[:n, member] = state[name].to(self.device)
        self.count[member] = count
