"""A stable-baselines3 run's checkpoint (:mod:`ede.run.sb3`), without a pickle.

The files are :mod:`ede.run.checkpoint`'s (``state.safetensors``, ``state.json`` and their
checksums, written atomically); what they hold:

* ``model/...``: SB3's ``get_parameters()`` (the policy's and each optimiser's state dicts) and
  SAC's ``log_ent_coef``, each tensor under its path, their structure in ``state.json``'s
  ``model`` (:func:`_split`: an optimiser's integer keys stay integers);
* ``buffer.*``: the replay buffer's filled rows, its ``pos`` and ``full`` in ``counters``;
* ``counters``: SB3's ``num_timesteps`` (codes, or raw steps on raw actions), ``_n_updates``,
  ``_episode_num``; ``step``: the run's raw environment steps;
* ``rng``: every generator SB3 and the agent draw from (torch's and numpy's global ones, Python's
  ``random``, the action space's for the uniform start codes); the environment's is rebuilt by
  replaying the episode under way (``episode_start``, ``episode_actions``, :class:`Episode`),
  which must reach the saved observation (``obs``);
* ``run``: the evaluations so far, the diagnostics and their running sums, episodes, wall time.

Never SB3's ``save``, ``save_replay_buffer`` or ``load``: they pickle.
"""

from __future__ import annotations

import random
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import torch
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm

from ede.errors import first_line
from ede.run import checkpoint
from ede.run.checkpoint import CheckpointError
from ede.run.spec import RunSpec, identity_difference
from ede.run.vector import Episode

__all__ = ["VERSION", "read", "restore", "write"]

VERSION = "sb3-1"
BUFFER = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")
STATE = {  # state.json's values beside its version and identity, and their JSON types
    "step": int,
    "model": dict,
    "counters": dict,
    "rng": dict,
    "episode_start": dict,
    "run": dict,
}


def write(
    path: Path,
    spec: RunSpec,
    model: OffPolicyAlgorithm,
    step: int,
    episode: Episode,
    run: dict[str, Any],
) -> None:
    """Write the checkpoint of ``spec``'s run at raw step ``step``: ``model`` (its ``_last_obs``
    the observation ``episode`` reaches) and ``run``'s JSON values.

    Raises:
        CheckpointWriteError: it could not be written; the previous one is intact.
    """
    buffer = model.replay_buffer
    assert buffer is not None
    filled = buffer.buffer_size if buffer.full else buffer.pos
    tensors: dict[str, torch.Tensor] = {}
    skeleton = _split(_learner_state(model), "model", tensors)
    for name in BUFFER:
        tensors[f"buffer.{name}"] = torch.as_tensor(getattr(buffer, name)[:filled])
    actions = np.array(episode.actions) if episode.actions else np.zeros((0, 1), np.float32)
    tensors["episode_actions"] = torch.as_tensor(actions)  # the raw actions since its start
    tensors["obs"] = torch.as_tensor(np.asarray(model._last_obs))
    tensors["torch_rng"] = torch.get_rng_state()
    numpy_rng: Any = np.random.get_state(legacy=True)
    state = {
        "version": VERSION,
        "fingerprint": spec.fingerprint(),
        "identity": spec.identity(),
        "step": step,
        "model": skeleton,
        "counters": {
            "num_timesteps": model.num_timesteps,
            "n_updates": model._n_updates,
            "episode_num": model._episode_num,
            "buffer_pos": buffer.pos,
            "buffer_full": buffer.full,
        },
        "rng": {
            "numpy": [numpy_rng[0], numpy_rng[1].tolist(), *numpy_rng[2:]],
            "python": [random.getstate()[0], list(random.getstate()[1]), None],
            "action_space": model.action_space.np_random.bit_generator.state,
        },
        "episode_start": episode.start,
        "episode_return": episode.ret,
        "run": {**run, "diagnostics": [checkpoint.row_to_json(r) for r in run["diagnostics"]]},
    }
    checkpoint.write_files(path, tensors, state)


def read(path: Path, spec: RunSpec) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """The checkpoint at ``path``, its files verified and made by ``spec``'s run.

    Raises:
        CheckpointError: damaged, unreadable, another format, or another run's (the first
            identity key that differs).
    """
    state, tensors = checkpoint.read_files(path)
    if state.get("version") != VERSION:
        raise CheckpointError(
            f"format version {state.get('version')}, this version reads {VERSION}"
        )
    if state.get("fingerprint") != spec.fingerprint():
        difference = identity_difference(state.get("identity"), spec.identity())
        raise CheckpointError(f"another run's: {difference or 'made by another configuration'}")
    for key, kind in STATE.items():
        if not isinstance(state.get(key), kind):
            raise CheckpointError(f"state.json: {key} is missing or not a {kind.__name__}")
    return state, tensors


def restore(
    state: dict[str, Any],
    tensors: dict[str, torch.Tensor],
    model: OffPolicyAlgorithm,
    env: gymnasium.Env,
) -> tuple[Episode, dict[str, Any]]:
    """Continue from a :func:`read` checkpoint: replay its episode in ``env`` (the task, as the
    run steps it raw), then restore ``model``, its buffer and every generator.

    Returns:
        The episode under way, and the run's values (``run``).

    Raises:
        CheckpointError: the replay did not reach the saved observation, or a value or tensor
            is missing or does not fit; the caller starts over with a fresh model.
    """
    try:
        actions = list(tensors["episode_actions"].numpy())
        episode = Episode(dict(state["episode_start"]), actions, state["episode_return"])
        obs = Episode(episode.start, list(actions)).replay(env)
        if not np.array_equal(np.asarray(obs)[None], tensors["obs"].numpy()):
            raise CheckpointError(
                "not restorable (replaying the episode did not reach the saved state)"
            )
        model._last_obs = tensors["obs"].numpy()
        _load_learner_state(model, _join(state["model"], tensors))
        _load_buffer(model, state["counters"], tensors)
        _load_rng(model, state["rng"], tensors["torch_rng"])
        run = state["run"]
        return episode, {
            **run,
            "diagnostics": [checkpoint.row_from_json(r) for r in run["diagnostics"]],
        }
    except (KeyError, TypeError, ValueError, RuntimeError, IndexError) as error:
        raise CheckpointError(f"not restorable ({first_line(error)})") from None


def _load_buffer(
    model: OffPolicyAlgorithm, counters: dict[str, Any], tensors: dict[str, torch.Tensor]
) -> None:
    buffer = model.replay_buffer
    assert buffer is not None
    for name in BUFFER:
        rows = tensors[f"buffer.{name}"].numpy()
        getattr(buffer, name)[: len(rows)] = rows
    buffer.pos, buffer.full = int(counters["buffer_pos"]), bool(counters["buffer_full"])
    model.num_timesteps = int(counters["num_timesteps"])
    model._n_updates = int(counters["n_updates"])
    model._episode_num = int(counters["episode_num"])


def _load_rng(model: OffPolicyAlgorithm, rng: dict[str, Any], torch_rng: torch.Tensor) -> None:
    torch.set_rng_state(torch_rng)
    kind, keys, *rest = rng["numpy"]
    np.random.set_state((kind, np.array(keys, dtype=np.uint32), *rest))
    version, internal, _ = rng["python"]
    random.setstate((version, tuple(internal), None))
    model.action_space.np_random.bit_generator.state = rng["action_space"]


def _learner_state(model: OffPolicyAlgorithm) -> dict[str, Any]:
    """The networks' and optimisers' state dicts, and SAC's entropy coefficient."""
    state: dict[str, Any] = model.get_parameters()
    if getattr(model, "log_ent_coef", None) is not None:
        state["log_ent_coef"] = model.log_ent_coef.detach()  # type: ignore[attr-defined]
    return state


def _load_learner_state(model: OffPolicyAlgorithm, state: dict[str, Any]) -> None:
    log_ent_coef = state.pop("log_ent_coef", None)
    model.set_parameters(state, exact_match=True)
    if log_ent_coef is not None:
        with torch.no_grad():
            model.log_ent_coef.copy_(log_ent_coef)  # type: ignore[attr-defined]


def _split(tree: Any, name: str, tensors: dict[str, torch.Tensor]) -> Any:
    """``tree`` (dicts, lists, tensors, JSON values) as JSON, each tensor moved into ``tensors``
    under its path; dict keys stay what they were (an optimiser's are ints)."""
    if isinstance(tree, torch.Tensor):
        tensors[name] = tree.detach().cpu().clone()
        return {"tensor": name}
    if isinstance(tree, dict):
        return {"dict": [[k, _split(v, f"{name}/{k}", tensors)] for k, v in tree.items()]}
    if isinstance(tree, list | tuple):
        return {"list": [_split(v, f"{name}/{i}", tensors) for i, v in enumerate(tree)]}
    return {"value": tree}


def _join(skeleton: Any, tensors: dict[str, torch.Tensor]) -> Any:
    """The tree :func:`_split` took apart."""
    if "tensor" in skeleton:
        return tensors[skeleton["tensor"]]
    if "dict" in skeleton:
        return {k: _join(v, tensors) for k, v in skeleton["dict"]}
    if "list" in skeleton:
        return [_join(v, tensors) for v in skeleton["list"]]
    return skeleton["value"]
