"""A trained policy as a video plays it: its run's final policy checked against its run
(:func:`policy_of`: ``policy.json`` an actor of the run ``run.json`` describes, its tensors that
actor's), the embedding it trained with (:func:`trained_embedding`), and how its codes become
actions (:func:`adapter_of`). :mod:`ede.analysis.video` plays it."""

from __future__ import annotations

import json
from collections.abc import Mapping
from itertools import pairwise
from pathlib import Path
from typing import Annotated, Any

import gymnasium
import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field, StrictInt, ValidationError, model_validator

from ede.config import ALGO_LABELS, SB3_ALGOS, SEED_MAX, Algo
from ede.errors import first_line
from ede.method.adapters import ActionAdapter, EmbeddingAdapter, IdentityAdapter
from ede.method.embedding import ActionEmbedding
from ede.run.artifacts import ArtifactError, load_action_embedding
from ede.run.runs import RunRejected, read_policy
from ede.run.spec import identity_difference
from ede.tasks import make


class PolicyRejected(ValueError):
    """A policy, its run or its embedding that a video cannot play, or a task that cannot be
    made to render: one line naming the file or the task and what is wrong."""


# The keys of a run's identity (ede.run.spec.RunSpec.identity) that say which run a policy is and how
# it acts: a policy is its run's where those its policy.json and its run.json both hold agree.
IDENTITY = ("task", "algo", "seed", "embedding")


class PolicyMeta(BaseModel):
    """What ``policy.json`` says of its actor (:func:`ede.run.training.save_policy`), as rendering
    reads it; its other keys (the run's identity) are checked against ``run.json``."""

    model_config = ConfigDict(extra="allow")

    task: str
    algo: Algo
    seed: Annotated[StrictInt, Field(ge=0, le=SEED_MAX)]
    hidden: list[Annotated[StrictInt, Field(gt=0)]]
    k: Annotated[StrictInt, Field(gt=0)]
    code_size: Annotated[StrictInt, Field(gt=0)]
    code_low: list[float]
    code_high: list[float]
    params: dict[str, Any] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _a_box(self) -> PolicyMeta:
        low, high = np.array(self.code_low), np.array(self.code_high)
        if not (len(low) == len(high) == self.code_size):
            raise ValueError(f"code_low and code_high: expected {self.code_size} numbers each")
        if not (np.isfinite(low).all() and np.isfinite(high).all() and (low < high).all()):
            raise ValueError("code_low and code_high: expected finite bounds, each low < high")
        ede_td3 = self.params.get("ede_td3")
        scale = ede_td3.get("bound_scale") if isinstance(ede_td3, dict) else None
        if self.algo == "ede-td3" and (
            isinstance(scale, bool) or not isinstance(scale, int | float)
        ):
            raise ValueError("params.ede_td3.bound_scale: expected a number (EDE-TD3's code bound)")
        return self


def policy_of(run: Path) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """The run's final policy (:func:`ede.run.runs.read_policy`), checked to be one this command can
    play: ``policy.json`` describes an actor, of the run its ``run.json`` describes, and
    ``policy.safetensors`` holds that actor's tensors, each of its shape.

    Raises:
        PolicyRejected: naming the file and what disagrees.
    """
    try:
        meta, tensors = read_policy(run)
    except RunRejected as error:
        raise PolicyRejected(str(error)) from None
    described = run / "policy/policy.json"
    if meta.get("algo") in SB3_ALGOS:  # their actor is SB3's network, not ours
        raise PolicyRejected(
            f"{described}: a {ALGO_LABELS[meta['algo']]} run; TD3's and EDE-TD3's policies are "
            "played, not stable-baselines3's actors"
        )
    try:
        checked = PolicyMeta.model_validate(meta)
    except ValidationError as error:
        problem = error.errors()[0]
        where = ".".join(str(part) for part in problem["loc"])
        said = problem["msg"].removeprefix("Value error, ")
        raise PolicyRejected(f"{described}: {where + ': ' if where else ''}{said}") from None
    made = _run_json(run)
    if made is not None:
        expected = {key: made[key] for key in IDENTITY if key in made and key in meta}
        if difference := identity_difference(meta, expected, said="run.json says"):
            raise PolicyRejected(
                f"{described}: not the policy of the run its run.json describes ({difference})"
            )
    sizes = [
        observation_size(checked.task),
        *checked.hidden,
        checked.code_size,
    ]  # ede.method.td3.Actor's
    wanted = {
        f"net.{2 * j}.{part}": (n_out, n_in) if part == "weight" else (n_out,)
        for j, (n_in, n_out) in enumerate(pairwise(sizes))
        for part in ("weight", "bias")
    } | {"centre": (checked.code_size,), "half_range": (checked.code_size,)}
    found = {name: tuple(tensor.shape) for name, tensor in tensors.items()}
    layers = [tensor for name, tensor in tensors.items() if name.startswith("net.")]
    if found != wanted or any(t.dtype != torch.float32 for t in layers):  # as observations are
        held = run / "policy/policy.safetensors"
        missing = [name for name in wanted if name not in found]  # the first layer's first
        other = [name for name in wanted if name in found and found[name] != wanted[name]]
        if missing:
            why = f"no tensor {missing[0]}"
        elif other:
            why = f"{other[0]} of shape {list(found[other[0]])}, expected {list(wanted[other[0]])}"
        elif extra := sorted(found.keys() - wanted.keys()):
            why = f"a tensor {extra[0]} that the actor has not"
        else:
            why = "layers other than float32"
        raise PolicyRejected(
            f"{held}: not the actor {described.name} describes ({why}: an actor of layers "
            f"{sizes} for {checked.task})"
        )
    return meta, tensors


def _run_json(run: Path) -> dict[str, Any] | None:
    """The run's ``run.json``, where it has one (read_policy has read it already)."""
    try:
        made = json.loads((run / "run.json").read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as error:
        raise PolicyRejected(f"{run / 'run.json'}: not JSON ({first_line(error)})") from None
    return made if isinstance(made, dict) else None


def observation_size(task: str) -> int:
    """The size of ``task``'s observations, the task made as a video makes it.

    Raises:
        PolicyRejected: the task cannot be made to render.
    """
    try:
        env = make(task, render_mode="rgb_array")
    except (gymnasium.error.Error, ValueError, TypeError) as error:
        raise PolicyRejected(f"{task}: cannot be made to render ({first_line(error)})") from None
    try:
        return int(np.prod(env.observation_space.shape or ()))
    finally:
        env.close()


def trained_embedding(
    meta: Mapping[str, Any], encoder: Path | None, decoder: Path
) -> ActionEmbedding:
    """The embedding an EDE-TD3 policy (its ``policy.json``, ``meta``) acts through, read from
    ``encoder`` (None: the decoder alone, as a published run keeps it) and ``decoder``, which
    must be the one its run trained with.

    Raises:
        PolicyRejected: the embedding cannot be read, or is another than the run's.
    """
    try:
        found, embedding = load_action_embedding(encoder, decoder)
    except ArtifactError as error:
        raise PolicyRejected(
            f"{error} (an EDE-TD3 run on {meta['task']} acts through its family's embedding)"
        ) from None
    if found.identity != meta.get("embedding"):
        raise PolicyRejected(
            f"{decoder}: not the embedding the run trained with (its "
            f"checksum {found.identity[:12]}…, the run's policy.json names "
            f"{str(meta.get('embedding'))[:12]}…); name the run's with --encoder and --decoder"
        )
    return embedding


def adapter_of(meta: dict, embedding: ActionEmbedding | None) -> ActionAdapter:
    """How the policy's codes become actions: as they are (TD3), or decoded by the embedding
    (EDE-TD3), in the code box its run acted in."""
    if embedding is None:
        low, high = np.array(meta["code_low"]), np.array(meta["code_high"])
        return IdentityAdapter(low, high, torch.device("cpu"))
    return EmbeddingAdapter(embedding, meta["params"]["ede_td3"]["bound_scale"])
