"""Codes into environment steps: the one place a code becomes K actions, stepped in order.

Training, evaluation, the probes and the videos all act through a :class:`CodeExecutor` over a
group's environments (:mod:`ede.run.vector`); its state is part of a run's checkpoint.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import torch

from ede.method.adapters import ActionAdapter

if TYPE_CHECKING:
    from ede.run.vector import MemberEnvs

__all__ = ["CodeExecutor", "CodeStep"]


class CodeStep(NamedTuple):
    """One environment step of every member's code (rows of members that sat it out: unused)."""

    code: torch.Tensor  # (M, C) the codes being executed
    i: np.ndarray  # (M,) steps of each executed before this one
    action: np.ndarray  # (M, A) each code's i-th action
    reward: np.ndarray  # (M,)
    next_obs: np.ndarray  # (M, O)
    terminated: np.ndarray  # (M,) bool
    truncated: np.ndarray  # (M,) bool

    @property
    def ended(self) -> np.ndarray:
        return self.terminated | self.truncated


class CodeExecutor:
    """Acts in M members' environments with codes (Section 3), one step of them at a time.

    For each member, when its i = 0 the policy chooses a code, which the adapter decodes into K
    actions; they are executed in order, one per step, and the next code is chosen after the K-th
    — or at the first step of the next episode, since an episode's end cuts the code short. Its
    state (each member's code, its actions, i) is part of a training run's checkpoint.

    A step is two calls, so that the caller can look at the codes before any environment moves
    (a code that is not finite stops its run there): :meth:`choose`, then :meth:`step`.
    """

    def __init__(self, envs: MemberEnvs, adapter: ActionAdapter) -> None:
        space = envs.vector.single_action_space
        self.envs, self.adapter, members = envs, adapter, envs.members
        self.code = torch.zeros(members, adapter.code_size, device=adapter.code_low.device)
        self.plan = np.zeros((members, adapter.k, *(space.shape or ())), dtype=space.dtype)
        self.i = np.zeros(members, dtype=np.int64)  # steps of each code executed
        self._rows = np.arange(members)

    def choose(
        self,
        obs: np.ndarray,
        policy: Callable[[np.ndarray, np.ndarray], torch.Tensor],
        members: np.ndarray,
    ) -> np.ndarray:
        """New codes for the members of ``members`` (``(M,)`` bool) at i = 0: rows of
        ``policy(obs, choosing)`` ``(M, O) -> (M, C)``. Returns ``choosing``."""
        choosing = members & (self.i == 0)
        if choosing.all():  # every member: the common case, without indexing
            self.code = policy(obs, choosing)  # (M, C)
            self.plan = self.adapter.decode(self.code).cpu().numpy()  # the group's one host copy
        elif choosing.any():
            rows = torch.as_tensor(np.flatnonzero(choosing), device=self.code.device)
            codes = policy(obs, choosing)[rows]  # (M, C) -> (N, C)
            self.code[rows] = codes
            plans = self.adapter.decode(codes)  # (N, C) -> (N, K, A)
            self.plan[choosing] = plans.cpu().numpy()  # the group's one copy to the host
        return choosing

    def step(self, members: np.ndarray) -> CodeStep:
        """One environment step of the members in ``members``, each with its code's next
        action."""
        i = self.i
        action = self.plan[self._rows, i]  # (M, K, A) -> (M, A)
        next_obs, reward, terminated, truncated = self.envs.step(action, members)
        if self.adapter.k > 1:  # (with k = 1 every step chooses: i stays 0)
            after = (i + 1) % self.adapter.k  # an episode's end cuts the code short: i = 0
            after[terminated | truncated] = 0
            self.i = np.where(members, after, i)
        return CodeStep(self.code.clone(), i, action, reward, next_obs, terminated, truncated)

    def episodes(
        self,
        policy: Callable[[np.ndarray, np.ndarray], torch.Tensor],
        episodes: int,
        seeds: Sequence[int],
        members: np.ndarray,
    ) -> Iterator[tuple[CodeStep, np.ndarray, np.ndarray]]:
        """``episodes`` episodes of each member of ``members``, one after another, episode e of
        member m from ``reset(seeds[m] + e)``; the members step together, each through its own
        episodes. Yields each step with the members that took it and the episode each is in."""
        members = np.asarray(members, dtype=bool)
        done = np.zeros(len(members), dtype=np.int64)  # episodes ended, per member
        seeds = [int(s) for s in seeds]
        obs = self.envs.reset(members, seeds)
        self.i[members] = 0
        while members.any():
            self.choose(obs, policy, members)
            step = self.step(members)
            yield step, members, done
            ended = step.ended  # (only members step)
            if ended.any():  # each starts its next (one done, an unused one: the vector wants it)
                done = done + ended
                members = members & (done < episodes)
                obs = self.envs.reset(ended, [s + int(e) for s, e in zip(seeds, done, strict=True)])
            else:
                obs = step.next_obs
