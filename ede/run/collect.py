"""Random-policy rollouts collected by stepping a task's environments in worker processes.

:func:`collect` returns the rows of a rollouts store (:mod:`ede.io.rollouts`, which describes its
arrays and writes and reads it): ``num_envs`` sub-environments, each with its own seed and its own
stream of random actions, stepped in lock step by one gymnasium ``SyncVectorEnv`` per worker
process, so the rows depend on the task, the steps, ``num_envs``, the seed and the saturated share,
never on how many processes stepped them. It lives with the run loop's other code that steps
environments; the store's format, which the method reads too, stays in ``io/``.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing import get_context
from typing import Any

import gymnasium
import numpy as np
from gymnasium.spaces import Box

import ede_envs
from ede.io.rollouts import ARRAYS, state_of, state_source
from ede.tasks import make, unusable

__all__ = ["collect", "row_bytes"]


@dataclass(frozen=True)
class _SubEnvJob:
    env_id: str
    index: int  # which sub-environment of the whole collection
    seed: int
    quota: int  # steps this sub-environment records, rounded up to whole episodes
    saturated: float = 0.0  # the chance that an episode's actions are saturated (:func:`collect`)


def _quotas(steps: int, num_envs: int) -> list[int]:
    base, extra = divmod(steps, num_envs)
    return [base + (i < extra) for i in range(num_envs)]


class _ActionStream:
    """Random actions of one sub-environment, drawn in blocks.

    A numpy ``Generator`` fills ``uniform(size=(n, A))`` from the same sequence of draws as ``n``
    calls of size ``A``, so the blocks change the speed, not the actions. In a saturated episode
    (:meth:`new_episode`) each draw is snapped to the nearer bound of its component: a corner of
    the box, each component at its low or high bound with equal chance. Which episodes are
    saturated is drawn from a generator of its own, so with ``saturated`` 0 the actions are those
    of uniform draws alone, draw for draw.
    """

    BLOCK = 256

    def __init__(
        self,
        rng: np.random.Generator,
        low: np.ndarray,
        high: np.ndarray,
        dtype: Any,
        saturated: float = 0.0,
        episodes: np.random.Generator | None = None,
    ):
        self._rng, self._low, self._high, self._dtype = rng, low, high, dtype
        self._block = np.empty((0, low.size), dtype=dtype)
        self._next = 0
        self._saturated, self._episodes, self._corners = saturated, episodes, False
        self._middle = (low + high) / 2  # a saturated episode's draws snap to the nearer bound

    def new_episode(self) -> None:
        """The next action starts an episode: draw whether its actions are saturated."""
        if self._saturated > 0:
            assert self._episodes is not None  # given with every saturated share above 0
            self._corners = bool(self._episodes.random() < self._saturated)

    def __call__(self) -> np.ndarray:
        if self._next == len(self._block):
            draws = self._rng.uniform(self._low, self._high, size=(self.BLOCK, self._low.size))
            self._block, self._next = draws.astype(self._dtype), 0
        self._next += 1
        action = self._block[self._next - 1]
        if self._corners:
            action = np.where(action < self._middle, self._low, self._high).astype(self._dtype)
        return action


class _NoInfo(gymnasium.Wrapper):
    """Drops ``info``: the collector records none of it, and batching it is the vector env's
    largest per-step cost."""

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, _ = self.env.reset(**kwargs)
        return obs, {}

    def step(self, action: Any) -> tuple[Any, Any, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, _ = self.env.step(action)
        return obs, reward, terminated, truncated, {}


def _run_sub_envs(
    jobs: list[_SubEnvJob], progress: Callable[[int], None] | None = None
) -> list[list[dict[str, np.ndarray]]]:
    """Step a group of sub-environments in lock step (one gymnasium ``SyncVectorEnv``).

    Each sub-environment has its own seed and its own action generator, so its episodes do not
    depend on how sub-environments are grouped into worker processes.

    Returns:
        Per job, its episodes in order, each a dict of the row arrays.
    """
    ede_envs.register_envs()
    env_id = jobs[0].env_id
    vec = gymnasium.vector.SyncVectorEnv(
        [lambda: _NoInfo(gymnasium.make(env_id)) for _ in jobs],
        autoreset_mode=gymnasium.vector.AutoresetMode.NEXT_STEP,
    )
    space = vec.single_action_space
    assert isinstance(space, Box)
    low, high = space.low.astype(np.float64), space.high.astype(np.float64)
    streams = [
        _ActionStream(
            np.random.default_rng([job.seed, job.index, 1]),
            low,
            high,
            space.dtype,
            job.saturated,
            np.random.default_rng([job.seed, job.index, 2]),
        )
        for job in jobs
    ]
    for stream in streams:
        stream.new_episode()
    idle = np.zeros(space.shape, dtype=space.dtype)
    obs, _ = vec.reset(seed=[job.seed + job.index for job in jobs])

    episodes: list[list[dict[str, np.ndarray]]] = [[] for _ in jobs]
    current: list[dict[str, list[Any]]] = [_empty_episode() for _ in jobs]
    recorded = [0] * len(jobs)
    resetting = np.zeros(len(jobs), dtype=bool)
    sources = [state_source(env) for env in vec.envs]
    while any(recorded[j] < job.quota for j, job in enumerate(jobs)):
        states = [state_of(env, obs[j], sources[j]) for j, env in enumerate(vec.envs)]
        # A resetting sub-env ignores its action: draw none, so its stream stays in step with a
        # plain reset-and-step loop over the same env.
        actions = np.stack([idle if resetting[j] else draw() for j, draw in enumerate(streams)])
        next_obs, rewards, terminated, truncated, _ = vec.step(actions)
        for j, job in enumerate(jobs):
            if resetting[j] or recorded[j] >= job.quota:
                continue  # this call reset the sub-env, or it has recorded its share
            episode = current[j]
            episode["obs"].append(obs[j])
            episode["state"].append(states[j])
            episode["action"].append(actions[j])
            episode["reward"].append(rewards[j])
            if terminated[j] or truncated[j]:
                episodes[j].append({key: np.asarray(rows) for key, rows in episode.items()})
                recorded[j] += len(episode["reward"])
                current[j] = _empty_episode()
                streams[j].new_episode()
                if progress is not None:
                    progress(len(episode["reward"]))
        resetting = terminated | truncated
        obs = next_obs
    vec.close()
    return episodes


def _empty_episode() -> dict[str, list[Any]]:
    return {"obs": [], "state": [], "action": [], "reward": []}


def _run_in_worker(jobs: list[_SubEnvJob]) -> list[list[dict[str, np.ndarray]]]:
    return _run_sub_envs(jobs)


def collect(
    env_id: str,
    steps: int,
    num_envs: int,
    seed: int,
    workers: int | None = None,
    progress: Callable[[int], None] | None = None,
    saturated: float = 0.0,
) -> dict[str, np.ndarray]:
    """Step ``env_id`` with random actions for at least ``steps`` steps: uniform in the action
    box (the paper's), or in a ``saturated`` share of the episodes (chosen at random, episode by
    episode) bang-bang, every component at its low or high bound, so that the embedding also
    learns what sequences at the box's corners do (``collect.saturated_episodes``).

    ``num_envs`` sub-environments (sub-environment ``i`` reset with seed ``seed + i``) each record
    an equal share of the steps, in whole episodes; they run in ``workers`` processes (default: one
    per core, at most ``num_envs``), each process stepping its group with gymnasium's
    ``SyncVectorEnv``, so no step waits on inter-process traffic. The result depends only on
    ``env_id``, ``steps``, ``num_envs``, ``seed`` and ``saturated``, never on ``workers``.

    Returns:
        The row arrays of :data:`ARRAYS`, episodes ordered by sub-environment, then by time.

    Raises:
        ValueError: non-positive ``steps`` or ``num_envs``, ``saturated`` outside [0, 1], or a
            task ede cannot use (:func:`ede.tasks.unusable`).
    """
    if steps <= 0 or num_envs <= 0:
        raise ValueError(f"steps and num_envs must be positive, got {steps} and {num_envs}")
    if not 0 <= saturated <= 1:
        raise ValueError(f"saturated is a share of episodes in [0, 1], got {saturated}")
    reason = unusable(env_id)
    if reason is not None:
        raise ValueError(f"{env_id} cannot be used: {reason}")
    jobs = [
        _SubEnvJob(env_id, i, seed, quota, saturated)
        for i, quota in enumerate(_quotas(steps, num_envs))
    ]
    workers = max(1, min(workers or os.cpu_count() or 1, num_envs))
    groups = [jobs[w::workers] for w in range(workers)]
    if workers == 1:
        per_job = _run_sub_envs(jobs, progress)
    else:
        per_job = [[] for _ in jobs]
        with ProcessPoolExecutor(workers, mp_context=get_context("spawn")) as pool:
            for group, result in zip(groups, pool.map(_run_in_worker, groups), strict=True):
                for job, episodes in zip(group, result, strict=True):
                    per_job[job.index] = episodes
                    if progress is not None:
                        progress(sum(len(e["reward"]) for e in episodes))
    return _concatenate([episode for episodes in per_job for episode in episodes])


# The dtypes of the columns :func:`_concatenate` makes; an observation and an action keep their
# spaces' dtypes, and a state is float64 (:func:`ede.io.rollouts.state_of`).
_COUNTED = {"reward": np.float64, "episode": np.int64, "t": np.int32}


def _concatenate(episodes: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    lengths = np.array([len(e["reward"]) for e in episodes])
    arrays = {key: np.concatenate([e[key] for e in episodes]) for key in episodes[0]}
    arrays["episode"] = np.repeat(np.arange(len(episodes), dtype=_COUNTED["episode"]), lengths)
    arrays["t"] = np.concatenate([np.arange(n, dtype=_COUNTED["t"]) for n in lengths])
    arrays["reward"] = arrays["reward"].astype(_COUNTED["reward"])
    return {key: arrays[key] for key in ARRAYS}


def row_bytes(env_id: str) -> int:
    """The bytes of one row (one step) of what :func:`collect` returns for ``env_id``, read from
    its spaces and from its state after one reset, without taking a step."""
    env = make(env_id)
    try:
        obs, _ = env.reset(seed=0)
        state = state_of(env, obs)
        observation, action = env.observation_space, env.action_space
    finally:
        env.close()
    assert isinstance(observation, Box) and isinstance(action, Box)  # or unusable (ede.tasks)
    vectors = sum(space.dtype.itemsize * space.shape[0] for space in (observation, action))
    return vectors + state.nbytes + sum(np.dtype(dtype).itemsize for dtype in _COUNTED.values())
