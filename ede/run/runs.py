"""A run's folder: the files it writes, and how they are read back and checked.

A run (task × algorithm × seed, :class:`ede.run.spec.RunSpec`) trains into its own folder
(:mod:`ede.run.training` writes it). This module is the one place that knows the folder's files:

* ``eval.csv``: :data:`EVAL_COLUMNS` after every evaluation (the first at step 0);
* ``diagnostics.csv``: :data:`DIAGNOSTIC_COLUMNS`, the means over the updates since the previous
  evaluation (mean_q: Q_1(s, μ(s), 0) on the actor's batches);
* ``run.json``: what made the run — its identity (:meth:`ede.run.spec.RunSpec.identity`: task,
  algorithm, seed, budget, the params that change its result, the embedding's checksum), the
  versions of the software, the code (commit, and whether the tree differed from it) and the
  machine (CPU model, the instruction sets that change results, torch's threads), and the SHA-256
  of each of its result files (:data:`CHECKSUMMED`) as it wrote them (the runs published before it
  recorded them record none: :data:`ede.run.early_runs.EARLY_RUNS` names each by its files);
* ``metrics.json``: final and best return, area under the curve, steps per second (of the last
  session and of the whole run), episodes, the step the last session resumed from; written last,
  so a run with ``metrics.json`` is finished;
* ``policy/``: the final actor (``policy.safetensors`` beside ``policy.json``);
* ``checkpoint/`` while it trains (:mod:`ede.run.checkpoint`).

:func:`read_run` reads a finished run back for the report and the results page, checked against
the identity it must have (:func:`ede.run.spec.identity_difference`) and against the checksums its
``run.json`` records; :func:`same_files` finds two runs that are one.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ede.config import EMBEDDED_ALGOS
from ede.errors import first_line
from ede.io.atomic import save_tensors, sha256, write_atomically, write_json, write_text
from ede.io.provenance import code_version, machine, software_versions
from ede.run.early_runs import EARLY_RUNS, early_run
from ede.run.spec import RunSpec, identity_difference

if TYPE_CHECKING:  # torch loads only where a policy is read: the results model stays free of it
    import torch

__all__ = [
    "CHECKSUMMED",
    "DIAGNOSTIC_COLUMNS",
    "EVAL_COLUMNS",
    "POLICY",
    "PUBLISHED",
    "RUN_KIND",
    "RUN_OWNS",
    "Curve",
    "Run",
    "RunRejected",
    "area_under_curve",
    "read_policy",
    "read_run",
    "same_files",
    "write_curves",
    "write_finished",
    "write_policy",
]

EVAL_COLUMNS = ("step", "episode", "mean_return", "std_return", "wall_seconds")
DIAGNOSTIC_COLUMNS = ("step", "updates", "critic_loss", "actor_loss", "mean_q")
# What a run's folder may hold while it trains (a stage refuses any other folder as its output).
RUN_KIND = "training run"
POLICY = "policy"  # the folder of a finished run's final actor (write_policy)
RUN_OWNS = (
    "eval.csv",
    "diagnostics.csv",
    "run.json",
    "metrics.json",
    POLICY,
    "checkpoint",
    "checkpoint.bad-*",
    "*.tmp-*",
)
# A finished run's files that are published (docs/results/runs/): its numbers and what made it;
# its policy too where `ede-pipeline experiment export --policies` publishes it (the clips').
PUBLISHED = ("eval.csv", "diagnostics.csv", "run.json", "metrics.json")
# A finished run's files whose SHA-256 its run.json records.
CHECKSUMMED = (
    "eval.csv",
    "diagnostics.csv",
    "metrics.json",
    "policy/policy.safetensors",
    "policy/policy.json",
)


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


def read_policy(run_dir: Path) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """A finished run's final actor (``policy/``, :func:`write_policy`): its ``policy.json`` and
    its tensors, each file the one its run wrote where ``run.json`` records their SHA-256.

    Raises:
        RunRejected: no policy there (a published copy keeps none), or a file damaged or not the
            run's, naming the file.
    """
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    policy = run_dir / POLICY
    missing = [n for n in ("policy.safetensors", "policy.json") if not (policy / n).is_file()]
    if missing:
        raise RunRejected(
            f"{policy}: no final policy ({' and '.join(missing)} missing); a run writes it as it "
            "finishes, and a published copy of a run keeps one only where exported with --policies"
        )
    if (run_dir / "run.json").is_file():
        try:
            made = json.loads((run_dir / "run.json").read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
            raise RunRejected(f"{run_dir / 'run.json'}: not JSON ({first_line(error)})") from None
        if not isinstance(made, dict):
            raise RunRejected(f"{run_dir / 'run.json'}: expected a JSON object")
        _check_files(run_dir, made, published=False)
    try:
        meta = json.loads((policy / "policy.json").read_text())
        tensors = load_file(policy / "policy.safetensors")
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, SafetensorError) as error:
        raise RunRejected(f"{policy}: unreadable ({first_line(error)})") from None
    wanted = {"task", "algo", "seed", "hidden", "k", "code_size", "code_low", "code_high"}
    if not isinstance(meta, dict) or not wanted <= meta.keys():
        raise RunRejected(
            f"{policy / 'policy.json'}: expected the keys {', '.join(sorted(wanted))}"
        )
    return meta, tensors


def write_finished(
    out: Path,
    spec: RunSpec,
    metrics: dict[str, Any],
    device: torch.device,
    software: Mapping[str, str] | None = None,
    compiled: bool | None = None,
) -> None:
    """``run.json``, with the SHA-256 of each result file there (:data:`CHECKSUMMED`;
    ``metrics.json``'s as it is about to be written), then ``metrics.json``: from then on the run
    is finished. ``software``: versions to record beside :func:`software_versions`'
    (stable-baselines3's, for its runs); ``compiled``: whether the last session's updates ran
    compiled (``td3.compile``), recorded as ``update``: "compiled" or "eager"."""
    text = json.dumps(metrics, indent=2, allow_nan=False) + "\n"
    checksums = {
        name: sha256(out / name)
        for name in CHECKSUMMED
        if name != "metrics.json" and (out / name).is_file()
    }
    checksums["metrics.json"] = hashlib.sha256(text.encode()).hexdigest()
    write_json(
        out / "run.json",
        {
            **spec.identity(),
            "software": {**software_versions(), **(software or {})},
            "code": code_version(),
            "machine": machine(device),
            **({} if compiled is None else {"update": "compiled" if compiled else "eager"}),
            "sha256": checksums,
        },
    )
    write_text(out / "metrics.json", text)


# Reading ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Curve:
    """One run's evaluation curve."""

    seed: int
    steps: np.ndarray
    returns: np.ndarray


def area_under_curve(steps: np.ndarray, returns: np.ndarray) -> float:
    """Trapezoidal area under a return curve divided by the steps it spans: its mean return
    (``metrics.json``'s ``auc``, and the results' area under the curve).

    A curve of one point has that point's return; an empty one is NaN.
    """
    steps, returns = np.asarray(steps, dtype=float), np.asarray(returns, dtype=float)
    if len(steps) != len(returns):
        raise ValueError(f"{len(steps)} steps but {len(returns)} returns")
    if len(steps) == 0:
        return float("nan")
    if len(steps) == 1 or steps[-1] == steps[0]:
        return float(returns[0])
    return float(np.trapezoid(returns, steps) / (steps[-1] - steps[0]))


class RunRejected(ValueError):
    """A finished run's folder that must not be averaged: one line saying which file and why."""


@dataclass(frozen=True)
class Run:
    """A finished run as the report averages it: its curve, its training diagnostics, and what
    made it (``run.json``)."""

    curve: Curve
    diagnostics: dict[str, np.ndarray] | None  # None: the run has no diagnostics.csv
    # run.json: identity, software, code, machine, sha256 (the last three since 2026-12)
    made: dict[str, Any]
    sha256: dict[str, str]  # of each of its files there, as checked (eval.csv's at least)

    @property
    def software(self) -> dict[str, Any] | None:
        return self.made.get("software")


def read_run(run_dir: Path, expected: dict[str, Any], published: bool = False) -> Run | None:
    """A finished run, checked against ``expected``; None when it is not finished.

    A run is finished when its ``metrics.json`` exists: ``train`` writes it (atomically) last.
    ``expected`` holds what the run must be, any of :meth:`RunSpec.identity`'s keys (task, algo,
    seed, budget, params, embedding): each must equal its value in ``run.json``. Each file whose
    SHA-256 ``run.json`` records must be the one the run wrote (a published copy holds no policy),
    and every one of :data:`CHECKSUMMED` there has its SHA-256 recorded. ``eval.csv`` must hold
    its columns, finite numbers, and steps that start at 0, rise, and end at the run's budget;
    ``diagnostics.csv``, where there is one, its columns and numbers.

    A run read to be ``published`` (``experiment export``, ``results``) must record its
    checksums too, unless it is one of the runs published before runs recorded any
    (:data:`ede.run.early_runs.EARLY_RUNS`), every byte as published; the embedding of a run acting
    in one (:data:`ede.config.EMBEDDED_ALGOS`) must be a SHA-256 (a published folder keeps the embedding under its first characters).

    Raises:
        RunRejected: the first problem found, naming the file.
    """
    if not (run_dir / "metrics.json").is_file():
        return None
    made = _run_json(run_dir / "run.json")
    difference = identity_difference(made, expected)
    if difference is not None:
        raise RunRejected(f"{run_dir / 'run.json'}: {difference}")
    checksums = _check_files(run_dir, made, published)
    embedding = made.get("embedding")
    if published and made.get("algo") in EMBEDDED_ALGOS and not _is_sha256(embedding):
        raise RunRejected(
            f"{run_dir / 'run.json'}: 'embedding' is {json.dumps(embedding)}; expected the "
            "SHA-256 of the decoder the run acted through (64 hexadecimal digits)"
        )
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
    return Run(Curve(int(made["seed"]), steps, returns), diagnostics, made, checksums)


def recorded_task(run_dir: Path) -> str:
    """The task a run's ``run.json`` names: where its folder must be kept.

    Raises:
        RunRejected: ``run.json`` is missing, not a JSON object, or names no task.
    """
    made = _run_json(run_dir / "run.json")
    if not isinstance(made.get("task"), str):
        raise RunRejected(f"{run_dir / 'run.json'}: names no 'task'; a run records its task")
    return made["task"]


def same_files(runs: Sequence[tuple[Path, Run]]) -> str | None:
    """The first of ``runs`` (each its folder and its :func:`read_run`) whose ``eval.csv`` is
    byte for byte a run's before it, in one line naming both: one run copied under another
    folder, whatever its folder or its ``run.json`` says (a run's curve holds its wall times, so
    no two runs write the same one); None where every run's is its own."""
    first: dict[str, Path] = {}
    for folder, run in runs:
        digest = run.sha256["eval.csv"]
        if (earlier := first.setdefault(digest, folder)) != folder:
            return (
                f"{folder}: the same run as {earlier} (their eval.csv's SHA-256 are both "
                f"{digest[:12]}…); a run is published once, in the folder of its own seed"
            )
    return None


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


def _check_files(run_dir: Path, made: dict[str, Any], published: bool) -> dict[str, str]:
    """The SHA-256 of each of a run's files there, checked: those ``run.json`` records
    (``sha256``) are the run's, every file of :data:`CHECKSUMMED` there and every one published
    (:data:`PUBLISHED`) is recorded, and those published are there. A ``run.json`` without ``sha256`` (a run finished
    before runs recorded it) is read as it is, unless ``published`` (:func:`read_run`)."""
    where = run_dir / "run.json"
    if "sha256" not in made:
        found = {name: sha256(run_dir / name) for name in PUBLISHED if (run_dir / name).is_file()}
        if published and early_run(found) not in EARLY_RUNS:
            raise RunRejected(
                f"{where}: records no 'sha256' of the run's files; every run made since runs "
                "recorded them does, and those published before are kept unchanged (ede/run/early_runs.py)"
            )
        return found
    recorded = made["sha256"]
    if not isinstance(recorded, dict) or not all(
        name in CHECKSUMMED and _is_sha256(digest) for name, digest in recorded.items()
    ):
        raise RunRejected(
            f"{where}: 'sha256' is not a SHA-256 by file name ({', '.join(CHECKSUMMED)})"
        )
    unrecorded = [
        name
        for name in CHECKSUMMED
        if name not in recorded and (name in PUBLISHED or (run_dir / name).is_file())
    ]
    if unrecorded:
        raise RunRejected(
            f"{where}: 'sha256' records no SHA-256 of {', '.join(unrecorded)}; a run records "
            "one for each of its files"
        )
    for name, digest in recorded.items():
        path = run_dir / name
        if not path.is_file():
            if name in PUBLISHED:
                raise RunRejected(f"{path}: missing, though run.json records its SHA-256")
            continue
        if (actual := sha256(path)) != digest:
            raise RunRejected(
                f"{path}: not the file its run wrote (SHA-256 {actual[:12]}…, run.json "
                f"records {digest[:12]}…)"
            )
    return {name: digest for name, digest in recorded.items() if (run_dir / name).is_file()}


def _is_sha256(value: Any) -> bool:
    return isinstance(value, str) and re.fullmatch("[0-9a-f]{64}", value) is not None


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
