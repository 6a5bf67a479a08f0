"""A run's folder: what determines a run, the files it writes, and how they are read back.

A run (task × algorithm × seed) trains into its own folder (:mod:`ede.training` writes it). This
module is the one place that knows the folder's files:

* ``eval.csv``: :data:`EVAL_COLUMNS` after every evaluation (the first at step 0);
* ``diagnostics.csv``: :data:`DIAGNOSTIC_COLUMNS`, the means over the updates since the previous
  evaluation (mean_q: Q_1(s, μ(s), 0) on the actor's batches);
* ``run.json``: what made the run — its identity (:meth:`RunSpec.identity`: task, algorithm,
  seed, budget, the params that change its result, the embedding's checksum), the versions of
  the software, the code (commit, and whether the tree differed from it) and the machine (CPU
  model, the instruction sets that change results, torch's threads);
* ``metrics.json``: final and best return, area under the curve, steps per second, episodes;
  written last, so a run with ``metrics.json`` is finished;
* ``policy/``: the final actor (``policy.safetensors`` beside ``policy.json``);
* ``checkpoint/`` while it trains (:mod:`ede.checkpoint`).

:func:`read_run` reads a finished run back for the report and the results page, checked against
the identity it must have (:func:`identity_difference`, which the checkpoint uses too).
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ede.atomic import save_tensors, write_atomically, write_json, write_text
from ede.config import Algo, EdeTD3Config, TD3Config, result_neutral
from ede.errors import first_line
from ede.provenance import code_version, machine, software_versions

__all__ = [
    "DIAGNOSTIC_COLUMNS",
    "EVAL_COLUMNS",
    "PUBLISHED",
    "RUN_KIND",
    "RUN_OWNS",
    "Curve",
    "Run",
    "RunRejected",
    "RunSpec",
    "identity_difference",
    "read_run",
    "write_curves",
    "write_finished",
    "write_policy",
]

EVAL_COLUMNS = ("step", "episode", "mean_return", "std_return", "wall_seconds")
DIAGNOSTIC_COLUMNS = ("step", "updates", "critic_loss", "actor_loss", "mean_q")
# What a run's folder may hold while it trains (a stage refuses any other folder as its output).
RUN_KIND = "training run"
RUN_OWNS = (
    "eval.csv",
    "diagnostics.csv",
    "run.json",
    "metrics.json",
    "policy",
    "checkpoint",
    "checkpoint.bad-*",
    "*.tmp-*",
)
# A finished run's files that are published (docs/results/runs/): its numbers and what made it.
PUBLISHED = ("eval.csv", "diagnostics.csv", "run.json", "metrics.json")


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


def identity_difference(found: Any, expected: Mapping[str, Any]) -> str | None:
    """How a recorded identity differs from ``expected`` (any of :meth:`RunSpec.identity`'s keys),
    the first key that does, in words: ``seed is 0, expected 1``, ``made with td3.lr = 0.01, but
    the params say 0.001``; None where every key of ``expected`` agrees."""
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
                            f"the params say {json.dumps(theirs.get(name))}"
                        )
        return f"{key} is {json.dumps(recorded)}, expected {json.dumps(value)}"
    return None


# Writing ----------------------------------------------------------------------------------------


def _csv(rows: list[dict[str, float]], columns: tuple[str, ...]) -> str:
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=columns, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return out.getvalue()


def write_curves(
    out: Path, history: list[dict[str, float]], diagnostics: list[dict[str, float]]
) -> None:
    """``eval.csv`` and ``diagnostics.csv`` as they stand (each replaced whole)."""
    write_text(out / "diagnostics.csv", _csv(diagnostics, DIAGNOSTIC_COLUMNS))
    write_text(out / "eval.csv", _csv(history, EVAL_COLUMNS))


def write_policy(path: Path, tensors: Mapping[str, torch.Tensor], meta: dict[str, Any]) -> None:
    """The final actor, ``policy.safetensors`` beside ``policy.json``, as one atomic folder."""

    def write(tmp: Path) -> None:
        save_tensors(
            {k: v.detach().cpu().contiguous() for k, v in tensors.items()},
            tmp / "policy.safetensors",
        )
        write_json(tmp / "policy.json", meta)

    write_atomically(path, write, kind="policy")


def write_finished(out: Path, spec: RunSpec, metrics: dict[str, Any], device: torch.device) -> None:
    """``run.json``, then ``metrics.json``: from then on the run is finished."""
    write_json(
        out / "run.json",
        {
            **spec.identity(),
            "software": software_versions(),
            "code": code_version(),
            "machine": machine(device),
        },
    )
    write_json(out / "metrics.json", metrics)


# Reading ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Curve:
    """One run's evaluation curve."""

    seed: int
    steps: np.ndarray
    returns: np.ndarray


class RunRejected(ValueError):
    """A finished run's folder that must not be averaged: one line saying which file and why."""


@dataclass(frozen=True)
class Run:
    """A finished run as the report averages it: its curve, its training diagnostics, and what
    made it (``run.json``)."""

    curve: Curve
    diagnostics: dict[str, np.ndarray] | None  # None: the run has no diagnostics.csv
    made: dict[str, Any]  # run.json: identity, software, code, machine (the last two since 2026-12)

    @property
    def software(self) -> dict[str, Any] | None:
        return self.made.get("software")


def read_run(run_dir: Path, expected: dict[str, Any]) -> Run | None:
    """A finished run, checked against ``expected``; None when it is not finished.

    A run is finished when its ``metrics.json`` exists: ``train`` writes it (atomically) last.
    ``expected`` holds what the run must be, any of :meth:`RunSpec.identity`'s keys (task, algo,
    seed, budget, params, embedding): each must equal its value in ``run.json``.
    ``eval.csv`` must hold its columns, finite numbers, and steps that start at 0, rise, and end
    at the run's budget; ``diagnostics.csv``, where there is one, its columns and numbers.

    Raises:
        RunRejected: the first problem found, naming the file.
    """
    if not (run_dir / "metrics.json").is_file():
        return None
    made = _run_json(run_dir / "run.json")
    difference = identity_difference(made, expected)
    if difference is not None:
        raise RunRejected(f"{run_dir / 'run.json'}: {difference}")
    table = _numbers(run_dir / "eval.csv", ("step", "mean_return"), finite=True)
    steps, returns = table["step"], table["mean_return"]
    where = run_dir / "eval.csv"
    if steps[0] != 0 or np.any(np.diff(steps) <= 0):
        raise RunRejected(f"{where}: steps must start at 0 and rise; found {_short(steps)}")
    budget = made.get("budget")
    if steps[-1] != budget:
        raise RunRejected(
            f"{where}: the last evaluation is at step {steps[-1]:g}, not at the "
            f"run's budget {budget}"
        )
    diagnostics = None
    if (run_dir / "diagnostics.csv").is_file():
        diagnostics = _numbers(
            run_dir / "diagnostics.csv",
            ("step", "updates", "critic_loss"),
            finite=False,
            allow_empty=True,
        )
    return Run(Curve(int(made["seed"]), steps, returns), diagnostics, made)


def _run_json(path: Path) -> dict[str, Any]:
    try:
        made = json.loads(path.read_text())
    except FileNotFoundError:
        raise RunRejected(f"{path}: missing; a finished run records what made it there") from None
    except (OSError, UnicodeDecodeError, ValueError) as error:
        raise RunRejected(f"{path}: not readable JSON ({first_line(error)})") from None
    if not isinstance(made, dict):
        raise RunRejected(f"{path}: expected a JSON object, found {type(made).__name__}")
    return made


def _short(values: np.ndarray) -> str:
    shown = ", ".join(f"{v:g}" for v in values[:6])
    return f"[{shown}{', ...' if len(values) > 6 else ''}]"


def _numbers(
    path: Path, columns: tuple[str, ...], finite: bool, allow_empty: bool = False
) -> dict[str, np.ndarray]:
    """A CSV of numbers as columns: ``columns`` must be there, every cell a number (finite ones
    when ``finite``), at least one row unless ``allow_empty``."""
    try:
        with open(path, newline="") as handle:
            reader = csv.DictReader(handle)
            header, rows = reader.fieldnames or [], list(reader)
    except FileNotFoundError:
        raise RunRejected(f"{path}: missing") from None
    except (OSError, UnicodeDecodeError, csv.Error) as error:
        raise RunRejected(f"{path}: not readable CSV ({first_line(error)})") from None
    absent = [c for c in columns if c not in header]
    if absent:
        raise RunRejected(
            f"{path}: no column {', '.join(absent)}; found {', '.join(header) or 'none'}"
        )
    if not rows and not allow_empty:
        raise RunRejected(f"{path}: no rows")
    table = {name: np.zeros(len(rows)) for name in header}
    for line, row in enumerate(rows, start=2):
        for name in header:
            try:
                table[name][line - 2] = value = float(row[name])
            except (TypeError, ValueError):
                raise RunRejected(
                    f"{path}: line {line}, {name}: {row[name]!r} is not a number"
                ) from None
            if finite and not np.isfinite(value):
                raise RunRejected(f"{path}: line {line}, {name}: {row[name]}, not a finite number")
    return table
