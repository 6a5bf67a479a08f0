"""What determines a run, and how two runs' identities differ.

A run (task × algorithm × seed) is determined by its :class:`RunSpec`: the task, the algorithm,
the seed, the budget, the params that change its result and (for EDE-TD3) the checksum of the
embedding it acts through. :meth:`RunSpec.identity` is what its ``run.json``
(:mod:`ede.run.runs`), its checkpoint (:mod:`ede.run.checkpoint`) and its policy record, and what
each is checked against on reading (:func:`identity_difference`); :func:`unshared_params` finds
the run of a task made with other params than its others.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ede.config import EMBEDDED_ALGOS, Algo, EdeTD3Config, TD3Config, result_neutral

__all__ = ["RunSpec", "identity_difference", "unshared_params"]


@dataclass(frozen=True)
class RunSpec:
    """What determines a run."""

    task: str
    algo: Algo
    seed: int
    budget: int  # environment steps
    td3: TD3Config
    ede_td3: EdeTD3Config
    embedding_id: str = ""  # the decoder's weights checksum, for EDE-TD3

    def identity(self) -> dict[str, Any]:
        return {
            "task": self.task,
            "algo": self.algo,
            "seed": self.seed,
            "budget": self.budget,
            "params": {  # what changes the result: not where or how fast it runs
                "td3": self.td3.model_dump(mode="json", exclude=set(result_neutral(TD3Config))),
                "ede_td3": self.ede_td3.model_dump(mode="json"),
            },
            "embedding": self.embedding_id,
        }

    def fingerprint(self) -> str:
        text = json.dumps(self.identity(), sort_keys=True, allow_nan=False)
        return hashlib.sha256(text.encode()).hexdigest()


def identity_difference(
    found: Any, expected: Mapping[str, Any], said: str = "the params say"
) -> str | None:
    """How a recorded identity differs from ``expected`` (any of :meth:`RunSpec.identity`'s keys),
    the first key that does, in words: ``seed is 0, expected 1``, ``made with td3.lr = 0.01, but
    the params say 0.001`` (``said`` names where ``expected``'s params come from); None where
    every key of ``expected`` agrees."""
    if not isinstance(found, dict):
        return "its identity is not recorded"
    for key, value in expected.items():
        if found.get(key) == value:
            continue
        if key == "embedding":
            return "made with another embedding than the family's (its decoder's checksum differs)"
        recorded = found.get(key)
        if key == "params" and isinstance(recorded, dict) and isinstance(value, dict):
            for section in sorted(set(recorded) | set(value)):
                ours, theirs = recorded.get(section) or {}, value.get(section) or {}
                for name in sorted(set(ours) | set(theirs)) if isinstance(ours, dict) else []:
                    if ours.get(name) != theirs.get(name):
                        return (
                            f"made with {section}.{name} = {json.dumps(ours.get(name))}, but "
                            f"{said} {json.dumps(theirs.get(name))}"
                        )
        return f"{key} is {json.dumps(recorded)}, expected {json.dumps(value)}"
    return None


# Per section of run.json's params, the keys that leave a result alone.
_NEUTRAL = {"td3": result_neutral(TD3Config), "ede_td3": result_neutral(EdeTD3Config)}


def unshared_params(runs: Sequence[tuple[Path, Mapping[str, Any]]]) -> str | None:
    """The first of a task's ``runs`` (each its folder and its ``run.json``) made with other
    params than a run before it, in one line naming its folder, the key and both values
    (:func:`identity_difference`); None where they agree. Every run shares td3's params (every
    algorithm trains with them), the runs acting in the embedding
    (:data:`ede.config.EMBEDDED_ALGOS`) ede_td3's too; keys that leave a result alone
    (:func:`ede.config.result_neutral`, which an older ``run.json`` may record) are set aside."""
    first: dict[str, tuple[Path, Mapping[str, Any]]] = {}  # the first run, and of each algorithm
    for folder, made in runs:
        for which in ("any", str(made.get("algo"))):
            earlier, theirs = first.setdefault(which, (folder, made))
            both = {made.get("algo"), theirs.get("algo")} <= EMBEDDED_ALGOS
            sections = ("td3", "ede_td3") if both else ("td3",)
            difference = identity_difference(
                _result_params(made, sections),
                _result_params(theirs, sections),
                said=f"{earlier} was made with",
            )
            if difference is not None:
                return (
                    f"{folder / 'run.json'}: {difference}; a task's runs share every param "
                    "that changes a result"
                )
    return None


def _result_params(made: Mapping[str, Any], sections: tuple[str, ...]) -> dict[str, Any]:
    """The params ``sections`` of a ``run.json`` that change a result, as an identity's."""
    params = made.get("params")
    if not isinstance(params, dict):
        return {"params": params}
    kept = {}
    for section in sections:
        values = params.get(section)
        kept[section] = (
            {k: v for k, v in values.items() if k not in _NEUTRAL[section]}
            if isinstance(values, dict)
            else values
        )
    return {"params": kept}
