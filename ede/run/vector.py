"""A group's environments: one per member, stepped together as one gymnasium vector environment.

The M members of a group (:mod:`ede.run.group`) each act in an environment of their own; the
group steps all of them with one call of a gymnasium ``VectorEnv`` — ``SyncVectorEnv`` in this
process, or ``AsyncVectorEnv`` with a worker process per environment where there are cores to
spare (``td3.env_workers``). Either way a member's episode is the one it has alone: its
environment is its own, reset from its own seed or its own generator, and stepped with its own
actions, so the choice changes the speed, never a result.

Autoreset is off (``AutoresetMode.DISABLED``): the loop resets the members whose episode ended,
itself, so that an episode starts exactly as a run alone starts it. Each environment is wrapped in
:class:`MemberEnv`, which adds the three things a group needs beyond stepping everything at once:
a member may sit out a step (``paused``: finished, stopped, or ahead of members catching up), a
checkpoint needs to know how its episode began (``start``), and resuming replays that episode in
the process that holds the environment (``restore``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import gymnasium
import numpy as np
from gymnasium.vector import AsyncVectorEnv, AutoresetMode, SyncVectorEnv

from ede.tasks import make

__all__ = ["Episode", "MemberEnv", "MemberEnvs"]


@dataclass
class Episode:
    """The training episode under way, as a checkpoint keeps it: how it started and the actions
    taken since, which rebuild the environment's state (:meth:`replay`)."""

    start: dict[str, Any]  # {"seed": s} for the first episode, else {"rng": bit generator state}
    actions: list[np.ndarray] = field(default_factory=list)
    ret: float = 0.0

    def replay(self, env: gymnasium.Env) -> np.ndarray:
        """Rebuild the environment's state: the same reset, then the same actions."""
        if "seed" in self.start:
            obs, _ = env.reset(seed=self.start["seed"])
        else:
            env.unwrapped.np_random.bit_generator.state = self.start["rng"]
            obs, _ = env.reset()
        for action in self.actions:
            obs, *_ = env.step(action)
        return obs


class MemberEnv(gymnasium.Wrapper):
    """Member ``index``'s environment inside a vector environment.

    While ``paused`` a step leaves the environment untouched and returns its current observation,
    no reward and no end. ``start`` is how the current episode began, as :class:`Episode` keeps
    it: ``{"seed": s}``, or the generator's state before an unseeded reset. Steps return no
    ``info``: nothing here reads it, and batching it is a vector environment's largest cost.
    """

    def __init__(self, env: gymnasium.Env, index: int) -> None:
        super().__init__(env)
        self.index, self.paused = index, False
        self.start: dict[str, Any] = {}
        self._obs: Any = None

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        if seed is None:
            self.start = {"rng": self.env.unwrapped.np_random.bit_generator.state}
        else:
            self.start = {"seed": seed}
        self._obs, _ = self.env.reset(seed=seed, options=options)
        return self._obs, {}

    def step(self, action: Any) -> tuple[Any, Any, bool, bool, dict[str, Any]]:
        if self.paused:
            return self._obs, 0.0, False, False, {}
        self._obs, reward, terminated, truncated, _ = self.env.step(action)
        return self._obs, reward, terminated, truncated, {}

    def restore(self, episodes: dict[int, Episode]) -> Any:
        """Replay this member's episode of ``episodes`` (:meth:`Episode.replay`), if it has one:
        the observation reached, else None."""
        episode = episodes.get(self.index)
        if episode is None:
            return None
        self._obs = episode.replay(self.env)
        self.start = dict(episode.start)
        return self._obs


def _wrap(make_env: Callable[[], gymnasium.Env], index: int) -> MemberEnv:
    return MemberEnv(make_env(), index)


class MemberEnvs:
    """M members' environments as one vector environment, each member's rows (observation,
    reward, ends) at its index. Every call takes a mask ``(M,)`` of the members it is for; the
    others sit it out, their observations kept.

    ``makers``: a function per member that makes its environment (picklable with ``workers``:
    :meth:`of_task` makes such). ``workers``: each in a worker process of its own.
    """

    def __init__(
        self, makers: Sequence[Callable[[], gymnasium.Env]], workers: bool = False
    ) -> None:
        members = [partial(_wrap, make_env, j) for j, make_env in enumerate(makers)]
        self.vector: SyncVectorEnv | AsyncVectorEnv  # copy=False: its rows are copied below
        if workers:
            # forkserver: a worker never inherits this process's threads (torch's among them).
            self.vector = AsyncVectorEnv(
                members, copy=False, autoreset_mode=AutoresetMode.DISABLED, context="forkserver"
            )
        else:
            self.vector = SyncVectorEnv(members, copy=False, autoreset_mode=AutoresetMode.DISABLED)
        self.members = len(members)
        self._paused = np.zeros(self.members, dtype=bool)
        space = self.vector.single_observation_space
        self.obs = np.zeros((self.members, *(space.shape or ())), dtype=space.dtype)  # now
        self._started = False  # the first reset starts every member: the vector needs them all

    @classmethod
    def of_task(cls, task: str, members: int, workers: bool = False) -> MemberEnvs:
        """``members`` environments of ``task`` (:func:`ede.tasks.make`)."""
        return cls([partial(make, task)] * members, workers)

    def reset(self, members: np.ndarray, seeds: Sequence[int | None]) -> np.ndarray:
        """Start a new episode of each member in ``members``: from its seed in ``seeds`` (one per
        member), or from its generator where None; the first reset starts every member, each
        from its seed. Returns every member's observation ``(M, O)``."""
        members = np.asarray(members, dtype=bool) | (not self._started)
        obs, _ = self.vector.reset(
            seed=[None if s is None else int(s) for s in seeds],
            options={"reset_mask": members},
        )
        self._started = True
        self.obs[members] = obs[members]
        return self.obs.copy()

    def step(
        self, actions: np.ndarray, members: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """One step of the members in ``members`` with their rows of ``actions`` ``(M, A)``.

        Returns:
            Every member's observation ``(M, O)``, and the rewards, ``terminated`` and
            ``truncated`` ``(M,)`` of this step (zero and false for the others).
        """
        paused = ~members
        if (paused != self._paused).any():
            self.vector.set_attr("paused", paused.tolist())
            self._paused = paused
        obs, reward, terminated, truncated, _ = self.vector.step(actions)
        if not paused.any():  # every member stepped: the common case, without masks
            self.obs[:] = obs
            return self.obs.copy(), reward, terminated, truncated
        self.obs[members] = obs[members]
        return self.obs.copy(), reward, terminated & members, truncated & members

    def starts(self) -> tuple[dict[str, Any], ...]:
        """How each member's current episode began (:attr:`MemberEnv.start`)."""
        return self.vector.get_attr("start")

    def restore(self, episodes: dict[int, Episode]) -> dict[int, np.ndarray]:
        """Replay member m's episode ``episodes[m]`` in its environment, for each m given: the
        observation each reached."""
        reached = self.vector.call("restore", episodes)
        for m in episodes:
            self.obs[m] = reached[m]
        return {m: np.asarray(reached[m]) for m in episodes}

    def close(self) -> None:
        self.vector.close()
