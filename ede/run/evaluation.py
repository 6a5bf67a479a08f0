"""How a run is evaluated: its deterministic policy μ(s), ``td3.eval_episodes`` episodes in each
member's evaluation environment, seeded apart from its training episodes (episode e of seed s
resets with ``EVAL_SEED_OFFSET·(s+1) + e``, :meth:`ede.run.group.Group.evaluate`). The probes of
the analysis and the videos play policies the same way.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch

from ede.method.adapters import ActionAdapter
from ede.run.executor import CodeExecutor
from ede.run.vector import MemberEnvs

__all__ = ["EVAL_SEED_OFFSET", "evaluate"]

EVAL_SEED_OFFSET = 1_000_003  # evaluation episodes are seeded apart from training ones


def evaluate(
    envs: MemberEnvs,
    policy: Callable[[np.ndarray], torch.Tensor],
    adapter: ActionAdapter,
    episodes: int,
    seeds: Sequence[int],
    members: np.ndarray | None = None,
) -> np.ndarray:
    """Returns ``(M, episodes)`` of ``policy`` (deterministic: μ(s), ``(M, O) -> (M, C)``) in each
    member's environment of ``envs`` (the members of ``members``, every one by default; rows of
    others zero); member m's episode e starts from ``reset(seeds[m] + e)``. The members' episodes
    are stepped together, one batched action per step."""
    members = np.ones(envs.members, dtype=bool) if members is None else members
    returns = np.zeros((envs.members, episodes))
    executor = CodeExecutor(envs, adapter)
    for step, stepped, episode in executor.episodes(
        lambda obs, _: policy(obs), episodes, seeds, members
    ):
        which = np.flatnonzero(stepped)
        returns[which, episode[which]] += step.reward[which]
    return returns
