"""A training run's checkpoint: its format, and reading, writing and applying it.

A checkpoint is a folder of three files, the same for a run trained alone and for a member of a
group, so either resumes the other:

* ``state.safetensors``: the member's slice of the agent (``agent.*``: networks' parameters by
  name, optimiser moments, update count, diagnostics sums, generator states;
  :meth:`ede.method.agent.Agent.state_dict`, opaque here) and of the replay buffer (``buffer.*``: its filled rows and ``buffer.count``, the
  run's environment steps; :meth:`ede.method.replay.ReplayBuffer.state_dict`), the code under way
  (``code``, ``plan``), the current episode's actions (``episode_actions``) and the observation
  their replay must reach (``obs``);
* ``state.json``: the format version, the run's identity and fingerprint
  (:meth:`ede.run.spec.RunSpec.identity`), ``step`` (equal to ``buffer.count``), ``episodes``,
  ``i`` (steps of the code executed), ``wall_seconds``, ``episode_start``, ``episode_return``,
  the evaluation ``history`` and the training ``diagnostics``;
* ``checksums.json``: the SHA-256 of the other two.

:func:`read` verifies all of it against the run and the group it is to continue, touching no live
object; :func:`apply` then restores the run; :func:`write` writes one atomically.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import load_file

from ede.errors import first_line
from ede.io.atomic import NotWritten, save_tensors, sha256, write_atomically
from ede.run.spec import identity_difference
from ede.run.vector import Episode

if TYPE_CHECKING:
    from ede.method.agent import Agent
    from ede.method.replay import ReplayBuffer
    from ede.run.executor import CodeExecutor
    from ede.run.spec import RunSpec

__all__ = [
    "VERSION",
    "Checkpoint",
    "CheckpointError",
    "CheckpointWriteError",
    "Layout",
    "apply",
    "read",
    "read_files",
    "write",
    "write_files",
]

VERSION = 5  # 2: diagnostics; 3: checksums, identity; 4: a member's slice; 5: named parameters
CHECKSUMS = "checksums.json"
FILES = ("state.safetensors", "state.json")  # what CHECKSUMS signs
STATE: dict[str, type | tuple[type, ...]] = {  # state.json's values beside its version and
    # identity, and their JSON types
    "step": int,
    "episodes": int,
    "i": int,
    "wall_seconds": (int, float),
    "episode_start": dict,
    "episode_return": (int, float),
    "history": list,
    "diagnostics": list,
}

Shapes = dict[str, tuple[tuple[int, ...], torch.dtype]]


class CheckpointError(Exception):
    """A checkpoint that cannot be used: unreadable, damaged, another run's, or another shape."""


class CheckpointWriteError(Exception):
    """A checkpoint could not be written (a full disk, ...); the previous one is intact."""


@dataclass(frozen=True, eq=False)
class Checkpoint:
    """What a checkpoint holds, verified (:func:`read`) or about to be written (:func:`write`)."""

    agent: dict[str, torch.Tensor]  # the member's Agent.state_dict, opaque
    buffer: dict[str, torch.Tensor]  # the member's ReplayBuffer.state_dict: rows and count
    code: torch.Tensor  # (C,) the code under way
    plan: np.ndarray  # (K, A) its actions
    i: int  # steps of it executed
    episode: Episode
    obs: np.ndarray  # the observation the episode's replay reaches
    episodes: int  # episodes ended
    history: list[dict[str, float]]  # eval.csv's rows
    diagnostics: list[dict[str, float]]  # diagnostics.csv's rows
    wall_seconds: float  # over every session of the run

    @property
    def step(self) -> int:
        """Environment steps taken: the replay buffer's count, their one owner."""
        return int(self.buffer["count"])


@dataclass(frozen=True)
class Layout:
    """The tensors a member's checkpoint must hold to continue in a group: :func:`read` refuses
    any other name, shape or dtype."""

    agent: Shapes  # Agent.state_dict(member)'s
    buffer: Shapes  # ReplayBuffer.state_dict(member)'s fields, each one row's shape
    capacity: int  # the buffer's rows: a member holds its last min(count, capacity) steps
    obs: tuple[int, ...]  # an observation's shape
    plan: tuple[int, ...]  # (K, A): a code's actions

    @classmethod
    def of(
        cls, agent: Agent, buffer: ReplayBuffer, obs: tuple[int, ...], plan: tuple[int, ...]
    ) -> Layout:
        """The layout of a group's members, from its agent and its (still empty) buffer."""
        rows = {k: v for k, v in buffer.state_dict(0).items() if k != "count"}
        return cls(
            _shapes(agent.state_dict(0)),
            {k: (tuple(v.shape[1:]), v.dtype) for k, v in rows.items()},
            buffer.capacity,
            tuple(obs),
            tuple(plan),
        )


def read(path: Path, spec: RunSpec, layout: Layout) -> Checkpoint:
    """The checkpoint at ``path``, verified to be ``spec``'s and to fit ``layout``; reads only.

    Raises:
        CheckpointError: with one reason: ``path`` not a folder, a file missing, damaged or changed
            (its checksum), unreadable, an older format, another run's (the first identity key
            that differs), or a value or tensor missing, unexpected or of another shape or type.
    """
    state, tensors = read_files(path)
    if state.get("version") != VERSION:
        raise CheckpointError(
            f"format version {state.get('version')}, this version reads {VERSION}"
        )
    if state.get("fingerprint") != spec.fingerprint():
        raise CheckpointError(
            "another run's: "
            + (
                identity_difference(state.get("identity"), spec.identity())
                or "made by another configuration"
            )
        )
    for key, kind in STATE.items():
        if not isinstance(state.get(key), kind):
            raise CheckpointError(
                f"state.json: {key} is missing or not a {getattr(kind, '__name__', 'number')}"
            )
    _check_tensors(tensors, state, layout)
    return Checkpoint(
        agent=_part(tensors, "agent"),
        buffer=_part(tensors, "buffer"),
        code=tensors["code"],
        plan=tensors["plan"].numpy(),
        i=state["i"],
        episode=Episode(
            state["episode_start"],
            list(tensors["episode_actions"].numpy()),
            state["episode_return"],
        ),
        obs=tensors["obs"].numpy(),
        episodes=state["episodes"],
        history=state["history"],
        diagnostics=[row_from_json(row) for row in state["diagnostics"]],
        wall_seconds=state["wall_seconds"],
    )


def apply(
    checkpoint: Checkpoint,
    agent: Agent,
    buffer: ReplayBuffer,
    member: int,
    executor: CodeExecutor,
    replay: Callable[[Episode], np.ndarray],
) -> Episode:
    """Continue ``member`` from a read checkpoint: ``replay`` its episode in the member's
    environment (:meth:`Episode.replay` where that environment lives), then, once that reached
    the saved observation, load the agent's and the buffer's member and the executor's.

    Returns:
        The episode under way (the caller's own copy).

    Raises:
        CheckpointError: the replay did not reach the saved state (another environment);
            only the member's environment was touched.
    """
    saved = checkpoint.episode
    episode = Episode(dict(saved.start), list(saved.actions), saved.ret)
    try:
        obs = replay(episode)
    except (ValueError, TypeError, KeyError) as error:  # a start the environment rejects
        raise CheckpointError(f"not restorable ({first_line(error)})") from None
    if not np.array_equal(obs, checkpoint.obs):
        raise CheckpointError(
            "not restorable (replaying the episode did not reach the saved state)"
        )
    agent.load_state_dict(member, checkpoint.agent)
    buffer.load_state_dict(member, checkpoint.buffer)
    executor.code[member] = checkpoint.code.to(executor.code.device)
    executor.plan[member] = checkpoint.plan
    executor.i[member] = checkpoint.i
    return episode


def write(path: Path, spec: RunSpec, checkpoint: Checkpoint) -> None:
    """Write ``checkpoint`` of ``spec``'s run to ``path``, atomically.

    Raises:
        CheckpointWriteError: it could not be written; the previous one at ``path`` is intact.
    """
    plan = checkpoint.plan
    tensors = {f"agent.{k}": v for k, v in checkpoint.agent.items()}
    tensors |= {f"buffer.{k}": v for k, v in checkpoint.buffer.items()}
    tensors["code"] = checkpoint.code
    tensors["plan"] = torch.as_tensor(plan)
    tensors["episode_actions"] = torch.as_tensor(
        np.array(checkpoint.episode.actions, dtype=plan.dtype).reshape(-1, plan.shape[1])
    )
    tensors["obs"] = torch.as_tensor(np.asarray(checkpoint.obs))
    state = {
        "version": VERSION,
        "fingerprint": spec.fingerprint(),
        "identity": spec.identity(),
        "step": checkpoint.step,
        "episodes": checkpoint.episodes,
        "i": checkpoint.i,
        "wall_seconds": checkpoint.wall_seconds,
        "episode_start": checkpoint.episode.start,
        "episode_return": checkpoint.episode.ret,
        "history": checkpoint.history,
        "diagnostics": [row_to_json(row) for row in checkpoint.diagnostics],
    }

    write_files(path, tensors, state)


def write_files(path: Path, tensors: Mapping[str, torch.Tensor], state: dict[str, Any]) -> None:
    """A checkpoint's three files at ``path``, atomically: ``tensors`` as ``state.safetensors``,
    ``state`` as ``state.json`` and their SHA-256 as ``checksums.json`` (:func:`write`, and the
    stable-baselines3 runs' checkpoints, :mod:`ede.run.sb3`).

    Raises:
        CheckpointWriteError: they could not be written; the previous checkpoint is intact.
    """

    def fill(tmp: Path) -> None:
        save_tensors(
            {k: v.detach().cpu().clone() for k, v in tensors.items()}, tmp / "state.safetensors"
        )
        (tmp / "state.json").write_text(json.dumps(state, allow_nan=False))
        sums = {name: sha256(tmp / name) for name in FILES}
        (tmp / CHECKSUMS).write_text(json.dumps(sums, allow_nan=False))

    try:
        write_atomically(path, fill, kind="checkpoint")
    except OSError as error:
        reason = error.reason if isinstance(error, NotWritten) else error.strerror or error
        raise CheckpointWriteError(
            f"{path}: not written ({reason}); the previous checkpoint is kept"
        ) from None


def read_files(path: Path) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """A checkpoint's ``state.json`` and tensors (:func:`write_files`), each file verified
    against its checksum; nothing else is checked.

    Raises:
        CheckpointError: ``path`` not a folder, a file missing, damaged or unreadable.
    """
    if not path.is_dir():
        raise CheckpointError("not a folder")
    state = _verified_state(path)
    try:
        return state, load_file(path / "state.safetensors")
    except (SafetensorError, OSError) as error:
        raise CheckpointError(f"state.safetensors not readable ({first_line(error)})") from None


def row_to_json(row: dict[str, float]) -> dict[str, float | None]:
    """A diagnostics row for JSON, which has no NaN: an interval with critic steps but no actor
    step has no actor loss (NaN), kept as null."""
    return {k: None if isinstance(v, float) and math.isnan(v) else v for k, v in row.items()}


def row_from_json(row: dict[str, float | None]) -> dict[str, float]:
    return {k: math.nan if v is None else v for k, v in row.items()}


def _shapes(tensors: Mapping[str, torch.Tensor]) -> Shapes:
    return {k: (tuple(v.shape), v.dtype) for k, v in tensors.items()}


def _part(tensors: Mapping[str, torch.Tensor], owner: str) -> dict[str, torch.Tensor]:
    """The tensors of ``owner`` ("agent", "buffer"), without its prefix."""
    return {k.removeprefix(f"{owner}."): v for k, v in tensors.items() if k.startswith(f"{owner}.")}


def _check_tensors(
    tensors: Mapping[str, torch.Tensor], state: dict[str, Any], layout: Layout
) -> None:
    """Every tensor ``layout`` calls for, of its shape and dtype, and no other; the buffer holding
    ``state``'s steps."""
    _expect(tensors, "buffer.count", (), torch.int64)
    count = int(tensors["buffer.count"])
    if count != state["step"]:
        raise CheckpointError("the replay buffer does not hold the run's steps")
    rows = min(count, layout.capacity)
    expected: dict[str, tuple[tuple[int | None, ...], torch.dtype | None]] = {
        f"agent.{k}": v for k, v in layout.agent.items()
    }
    expected |= {
        f"buffer.{k}": ((rows, *shape), dtype) for k, (shape, dtype) in layout.buffer.items()
    }
    expected |= {  # the executor's and the episode's: in the environment's dtypes
        "buffer.count": ((), torch.int64),
        "code": (layout.buffer["code"][0], None),
        "plan": (layout.plan, None),
        "episode_actions": ((None, *layout.plan[1:]), None),  # any number of steps
        "obs": (layout.obs, None),
    }
    for name, (shape, dtype) in expected.items():
        _expect(tensors, name, shape, dtype)
    unexpected = sorted(set(tensors) - set(expected))
    if unexpected:
        raise CheckpointError(f"{unexpected[0]} is not this run's")
    if not 0 <= state["i"] < layout.plan[0]:
        raise CheckpointError(f"i = {state['i']}, not a step of a code of {layout.plan[0]}")


def _expect(
    tensors: Mapping[str, torch.Tensor],
    name: str,
    shape: tuple[int | None, ...],
    dtype: torch.dtype | None = None,
) -> None:
    """``tensors[name]`` has ``shape`` (None: any size) and ``dtype`` (None: any)."""
    if name not in tensors:
        raise CheckpointError(f"{name} is missing")
    found = tensors[name]
    fits = len(found.shape) == len(shape) and all(
        e is None or e == f for e, f in zip(shape, found.shape, strict=True)
    )
    if not fits or (dtype is not None and found.dtype != dtype):
        wanted = "[" + ", ".join("any" if e is None else str(e) for e in shape) + "]"
        raise CheckpointError(
            f"{name} is {list(found.shape)} {found.dtype}, expected {wanted}"
            + ("" if dtype is None else f" {dtype}")
        )


def _verified_state(path: Path) -> dict[str, Any]:
    """``state.json`` of a checkpoint whose files all match their checksums."""
    try:
        sums = json.loads((path / CHECKSUMS).read_text())
        for name in FILES:
            if sha256(path / name) != sums[name]:
                raise CheckpointError(f"{name} does not match its checksum (damaged or changed)")
        state = json.loads((path / "state.json").read_text())
    except CheckpointError:
        raise
    except FileNotFoundError as error:
        raise CheckpointError(f"{Path(error.filename).name} is missing") from None
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise CheckpointError(f"not readable ({first_line(error)})") from None
    if not isinstance(state, dict):
        raise CheckpointError("state.json is not an object")
    return state
