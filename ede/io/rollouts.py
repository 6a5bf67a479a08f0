"""A rollouts store: random-policy rollouts in a Zarr v3 store, written, checked, and read back
as k-step windows (:mod:`ede.run.collect` collects them).

A store is a Zarr group of arrays over steps (rows), one row per environment step taken:

=========== ======== ==========================================================================
array       shape    meaning
=========== ======== ==========================================================================
``obs``     (N, O)   the observation the action was chosen from
``state``   (N, S)   the state at that moment, which the embedding learns from (see below)
``action``  (N, A)   the random action taken, uniform or saturated (:mod:`ede.run.collect`)
``reward``  (N,)     the reward it earned
``episode`` (N,)     global episode index; episodes are contiguous and in order
``t``       (N,)     step within the episode, 0, 1, ...
=========== ======== ==========================================================================

The ``state`` of a MuJoCo task is its physics state, qpos then qvel; a task without MuJoCo physics
(e.g. ``Pendulum-v1``) has none to read, so its state is the observation itself, as float64.
:func:`state_source` tells the two apart by what the unwrapped environment has (MuJoCo ``data``
with ``qpos`` and ``qvel``), and the collect stage records its answer in the ``state_source``
attribute: ``"physics"`` or ``"observation"``.

The group's attributes name the task, seed, spaces and params, ``collector`` (the store format,
:data:`COLLECTOR_VERSION`) and ``fingerprint``: a SHA-256 over the arrays and every attribute but
itself and ``software`` (see :func:`fingerprint`), so an edited array or attribute is refused.

Rows are whole episodes. The state *after* an episode's last action is not a row, so a k-step
window ``(state[t], action[t:t+k], state[t+k])`` needs ``t + k`` inside the same episode.

Chunking: a reader loads every array into memory at once and then samples windows at random, so
arrays are cut only along steps, in chunks of :data:`CHUNK_STEPS` rows spanning all columns, and
compressed with Blosc/zstd with byte shuffling (float columns compress about 2x). Large chunks keep
the store to a few dozen files and make the whole read one sequential pass.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from itertools import pairwise
from pathlib import Path
from typing import Any, cast

import gymnasium
import numpy as np
import zarr
from zarr.codecs import BloscCodec

from ede.io.atomic import write_atomically

KIND = "rollouts store"  # what its folder is called where a stage refuses to replace another's

__all__ = [
    "ARRAYS",
    "CHUNK_STEPS",
    "COLLECTOR_VERSION",
    "UNFINGERPRINTED_ATTRS",
    "Rollouts",
    "RolloutsError",
    "Whitening",
    "fingerprint",
    "physics_state",
    "state_of",
    "state_source",
    "write_store",
]

# 2: the fingerprint covers the attributes as well as the arrays
# 3: a task without MuJoCo physics has its observation as state (attribute ``state_source``)
COLLECTOR_VERSION = 3
CHUNK_STEPS = 16_384
ARRAYS = ("obs", "state", "action", "reward", "episode", "t")
REQUIRED_ATTRS = (
    "env_id",
    "family",
    "seed",
    "num_envs",
    "steps",
    "spaces",
    "params",
    "fingerprint",
)
# Attributes the fingerprint leaves out: itself, and the versions of the software that wrote the
# store, which name the machine rather than the content (the same rollouts collected in the
# container and on the host share one fingerprint; scripts/container-test.sh checks this).
UNFINGERPRINTED_ATTRS = ("fingerprint", "software")
_STD_FLOOR = 1e-6  # columns that never move (e.g. a velocity held at zero) are left unscaled


class RolloutsError(ValueError):
    """A store that cannot be used; the message names the path and what is wrong."""


def state_source(env: gymnasium.Env) -> str:
    """``"physics"`` when ``env`` runs on MuJoCo (its unwrapped environment has ``data`` with
    ``qpos`` and ``qvel``), else ``"observation"``."""
    data = getattr(env.unwrapped, "data", None)
    return "physics" if hasattr(data, "qpos") and hasattr(data, "qvel") else "observation"


def physics_state(env: gymnasium.Env) -> np.ndarray:
    """The MuJoCo state of ``env``: qpos then qvel, as one float64 vector."""
    data = cast(Any, env.unwrapped).data  # any env state_source calls "physics", not only MujocoEnv
    return np.concatenate((data.qpos, data.qvel))  # MuJoCo keeps both in float64


def state_of(env: gymnasium.Env, obs: np.ndarray, source: str | None = None) -> np.ndarray:
    """The ``state`` row of ``env`` whose observation is now ``obs``; ``source`` is
    :func:`state_source` of ``env``, found here unless given (a loop asks once per env)."""
    if (source or state_source(env)) == "physics":
        return physics_state(env)
    return np.asarray(obs, dtype=np.float64).reshape(-1)


# --------------------------------------------------------------------------------------------
# Writing


def fingerprint(arrays: dict[str, np.ndarray], attrs: dict[str, Any]) -> str:
    """A SHA-256 over every array's name, dtype, shape and bytes, then over the attributes.

    The attributes (all but :data:`UNFINGERPRINTED_ATTRS`) enter as canonical JSON, keys sorted,
    so a store whose ``env_id``, ``family`` or ``params`` were edited no longer matches.
    """
    digest = hashlib.sha256()
    for key in ARRAYS:
        array = np.ascontiguousarray(arrays[key])
        digest.update(f"{key}:{array.dtype.str}:{array.shape};".encode())
        digest.update(array.tobytes())
    content = {key: value for key, value in attrs.items() if key not in UNFINGERPRINTED_ATTRS}
    digest.update(b"attrs:" + json.dumps(content, sort_keys=True, allow_nan=False).encode())
    return digest.hexdigest()


def write_store(path: str | Path, arrays: dict[str, np.ndarray], attrs: dict[str, Any]) -> None:
    """Write a store atomically: into a temporary sibling, renamed onto ``path`` when complete.

    A killed writer leaves only ``<path>.tmp-<pid>``, which no reader accepts and which the next
    write removes.
    """

    def write(tmp: Path) -> None:
        group = zarr.open_group(tmp, mode="w", zarr_format=3)
        for key in ARRAYS:
            array = arrays[key]
            group.create_array(
                key,
                data=array,
                chunks=(min(CHUNK_STEPS, len(array)), *array.shape[1:]),
                compressors=BloscCodec(cname="zstd", clevel=3, shuffle="shuffle"),
            )
        content = {**attrs, "collector": COLLECTOR_VERSION}
        group.attrs.update({**content, "fingerprint": fingerprint(arrays, content)})

    write_atomically(path, write, kind=KIND)


# --------------------------------------------------------------------------------------------
# Reading


@dataclass(frozen=True)
class Whitening:
    """Per-column mean and standard deviation; ``(x - mean) / std`` whitens."""

    mean: np.ndarray
    std: np.ndarray

    @classmethod
    def of(cls, x: np.ndarray) -> Whitening:
        std = x.std(axis=0)
        return cls(mean=x.mean(axis=0), std=np.where(std < _STD_FLOOR, 1.0, std))

    def apply(self, x: np.ndarray) -> np.ndarray:
        return (x - self.mean) / self.std


def _array(group: zarr.Group, key: str, path: Path) -> np.ndarray:
    """The array ``key`` of a store's group, read whole."""
    found = group[key]
    if not isinstance(found, zarr.Array):
        raise RolloutsError(f"{path}: {key} is a group, expected an array")
    return np.asarray(found[...])


@dataclass(frozen=True)
class Rollouts:
    """A validated store, loaded into memory."""

    path: Path
    attrs: dict[str, Any]
    obs: np.ndarray = field(repr=False)
    state: np.ndarray = field(repr=False)
    action: np.ndarray = field(repr=False)
    reward: np.ndarray = field(repr=False)
    episode: np.ndarray = field(repr=False)
    t: np.ndarray = field(repr=False)

    @classmethod
    def open(cls, path: str | Path, env_id: str | None = None) -> Rollouts:
        """Open and check a store.

        Args:
            path: the store written by :func:`write_store`.
            env_id: when given, the task the store must come from.

        Raises:
            RolloutsError: missing, truncated, inconsistent or foreign stores.
        """
        path = Path(path)
        if not (path / "zarr.json").is_file():
            raise RolloutsError(f"{path}: no rollouts store here (run `ede-pipeline collect`)")
        try:
            group = zarr.open_group(path, mode="r", zarr_format=3)
            attrs = dict(group.attrs)
            missing = [key for key in REQUIRED_ATTRS if key not in attrs]
            if missing:
                raise RolloutsError(f"{path}: attributes {', '.join(missing)} are missing")
            if attrs.get("collector") != COLLECTOR_VERSION:
                raise RolloutsError(
                    f"{path}: written by collector version {attrs.get('collector')}, but this "
                    f"code reads version {COLLECTOR_VERSION} only; collect it again "
                    "(`ede-pipeline collect`)"
                )
            absent = [key for key in ARRAYS if key not in group]
            if absent:
                raise RolloutsError(f"{path}: arrays {', '.join(absent)} are missing")
            arrays = {key: _array(group, key, path) for key in ARRAYS}
        except RolloutsError:
            raise
        except (OSError, ValueError, KeyError, RuntimeError, json.JSONDecodeError) as error:
            raise RolloutsError(
                f"{path}: unreadable store ({type(error).__name__}: {error})"
            ) from error
        rollouts = cls(path=path, attrs=attrs, **arrays)
        rollouts._check()  # first: an edited env_id must not be reported as where it came from
        if env_id is not None and attrs["env_id"] != env_id:
            raise RolloutsError(
                f"{path}: collected on {attrs['env_id']} (family {attrs['family']}), "
                f"expected {env_id}"
            )
        return rollouts

    def _check(self) -> None:
        lengths = {key: len(getattr(self, key)) for key in ARRAYS}
        if len(set(lengths.values())) != 1:
            raise RolloutsError(f"{self.path}: arrays differ in length {lengths}")
        if len(self) == 0:
            raise RolloutsError(f"{self.path}: the store is empty")
        starts = np.flatnonzero(self.t == 0)
        if starts.size == 0 or starts[0] != 0:
            raise RolloutsError(f"{self.path}: the first row does not start an episode")
        expected_t = np.arange(len(self)) - np.repeat(starts, np.diff([*starts, len(self)]))
        expected_episode = np.repeat(np.arange(starts.size), np.diff([*starts, len(self)]))
        if not (
            np.array_equal(self.t, expected_t) and np.array_equal(self.episode, expected_episode)
        ):
            raise RolloutsError(f"{self.path}: episodes are not contiguous and in order")
        if self.attrs["fingerprint"] != fingerprint(self.arrays(), self.attrs):
            raise RolloutsError(
                f"{self.path}: content does not match its fingerprint (its arrays or attributes "
                "were changed since collection)"
            )

    def __len__(self) -> int:
        return len(self.reward)

    def arrays(self) -> dict[str, np.ndarray]:
        return {key: getattr(self, key) for key in ARRAYS}

    @property
    def num_episodes(self) -> int:
        return int(self.episode[-1]) + 1

    def window_starts(self, k: int, episodes: np.ndarray | None = None) -> np.ndarray:
        """Every row ``t`` whose k-step window stays inside its episode (optionally only in
        ``episodes``)."""
        if k <= 0:
            raise ValueError(f"k must be positive, got {k}")
        t = np.arange(len(self) - k)
        valid = self.episode[t + k] == self.episode[t]
        if episodes is not None:
            valid &= np.isin(self.episode[t], episodes)
        return t[valid]

    def windows(self, starts: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(state[t], action[t:t+k], state[t+k])`` for each ``t`` of ``starts``.

        Returns:
            States (B, S), action sequences (B, K, A) and states k steps later (B, S).
        """
        steps = starts[:, None] + np.arange(k)  # (B, K)
        return self.state[starts], self.action[steps], self.state[starts + k]

    def whitening(
        self, k: int, starts: np.ndarray | None = None, change: str = "final"
    ) -> tuple[Whitening, Whitening]:
        """Whitening of the state and of its k-step change, over ``starts`` (default: all).

        ``change="final"`` takes the change's moments from the k-step changes themselves;
        ``"all"`` from the changes after 0, 1, ..., k steps pooled, as the authors' code (its
        ``GymData.make_stats`` over every row of a delta-encoded window), whose smaller spread
        leaves the whitened k-step change with a variance above 1.
        """
        if starts is None:
            starts = self.window_starts(k)
        state, _, later = self.windows(starts, k)
        if change == "final":
            return Whitening.of(state), Whitening.of(later - state)
        if change == "all":
            pooled = [self.state[starts + j] - state for j in range(k + 1)]
            return Whitening.of(state), Whitening.of(np.concatenate(pooled))
        raise ValueError(f"change whitening {change!r}: expected 'final' or 'all'")

    def iter_episodes(self) -> Iterator[slice]:
        """The row range of each episode, in order."""
        bounds = [*np.flatnonzero(self.t == 0), len(self)]
        for start, stop in pairwise(bounds):
            yield slice(int(start), int(stop))
