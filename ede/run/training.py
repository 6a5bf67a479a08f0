"""One training run of TD3 or EDE-TD3, or a group of them: the loop, checkpoints, outputs.

A run is determined by its :class:`ede.run.spec.RunSpec` and (for EDE-TD3) its embedding. It writes
its folder's files (:mod:`ede.run.runs`: ``eval.csv`` and ``diagnostics.csv`` after every
evaluation, ``policy/``, ``run.json`` and, last, ``metrics.json``) and, while it trains,
``checkpoint/``: everything needed to continue exactly, in the format of :mod:`ede.run.checkpoint` —
the same for a run trained alone and for a member of a group, so either resumes the other. A run
started where a checkpoint of the same configuration exists continues from it; on CPU a run
killed at any point and resumed ends with the same ``eval.csv`` returns as an uninterrupted one.

A group of runs (several seeds of one task and algorithm) is one :class:`ede.method.agent.Agent` with a
member per run; a run alone is a group of one. Each run's outputs are what it gets alone.

This module is the loop: :func:`train_group` steps the group (:class:`ede.run.group.Group`, which
steps every member's environment at once and schedules the batched updates), evaluates its runs
when due (:func:`ede.run.evaluation.evaluate`) and checkpoints them; :class:`_Session` resumes one
run and writes its outputs.
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ede.config import PAPER_ALGOS
from ede.io.atomic import claim, remove_stale_temporaries
from ede.method.adapters import ActionAdapter
from ede.method.agent import Agent
from ede.method.embedding import ActionEmbedding
from ede.method.nets import flush_denormals
from ede.run import checkpoint
from ede.run.checkpoint import CheckpointError
from ede.run.group import Group, Member
from ede.run.runs import (
    POLICY,
    RUN_KIND,
    RUN_OWNS,
    area_under_curve,
    write_curves,
    write_finished,
    write_policy,
)
from ede.run.spec import RunSpec

__all__ = ["Diverged", "move_aside", "run_metrics", "train_group", "train_run"]


class Diverged(Exception):
    """Runs whose numbers stopped being finite: one line each (task, algorithm, seed, step, the
    quantity). Each stopped there, its last checkpoint kept and no ``metrics.json`` written;
    the group's other runs finished."""


def train_run(
    spec: RunSpec,
    out: Path,
    embedding: ActionEmbedding | None = None,
    device: torch.device = torch.device("cpu"),
    progress: Callable[[int], None] | None = None,
    keep_checkpoint: bool = False,
    bad_checkpoint: str = "restart",
    notice: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Train one run into ``out``: :func:`train_group` of one member."""
    return train_group(
        [spec], [out], embedding, device, progress, keep_checkpoint, bad_checkpoint, notice
    )[0]


@flush_denormals()
def train_group(
    specs: list[RunSpec],
    outs: list[Path],
    embedding: ActionEmbedding | None = None,
    device: torch.device = torch.device("cpu"),
    progress: Callable[[int], None] | None = None,
    keep_checkpoint: bool = False,
    bad_checkpoint: str = "restart",
    notice: Callable[[str], None] = print,
) -> list[dict[str, Any]]:
    """Train runs of one task and algorithm that differ only in their seeds, each into its
    ``out``, in one process: one agent with a member per run (:class:`ede.method.agent.Agent`), their
    environments stepped in turn, their updates as one. Each member's outputs are those it gets
    alone. Members due different numbers of updates (per-episode batches of episodes that ended
    apart) are masked in the updates they are not due; members resumed from different steps
    step in turn, the ones behind first, until they are in step.
    CPU arithmetic flushes subnormal numbers to zero throughout (:func:`ede.method.nets.flush_denormals`).

    Each resumes from its ``out/checkpoint`` when there is one (written alone or in a group).
    A checkpoint that cannot be used (:meth:`Member.load`) is reported through ``notice`` and
    moved aside to ``out/checkpoint.bad-<time>``, and that run starts over; with
    ``bad_checkpoint="refuse"`` it raises :class:`CheckpointError` instead, touching nothing.

    Returns:
        Each member's metrics, as written to its ``metrics.json``.

    Raises:
        CheckpointError: a bad checkpoint under "refuse".
        CheckpointWriteError: a checkpoint could not be written; the previous one is kept
            (:func:`ede.run.checkpoint.write`).
    """
    spec = specs[0]
    if spec.algo not in PAPER_ALGOS:  # stable-baselines3's train alone: ede.run.sb3
        raise ValueError(f"{spec.algo!r}: expected one of {', '.join(PAPER_ALGOS)}")
    if spec.algo == "ede-td3" and embedding is None:
        raise ValueError("ede-td3 needs the family's action embedding")
    alike = all(replace(s, seed=0) == replace(spec, seed=0) for s in specs)
    if not alike or len({s.seed for s in specs}) != len(specs):
        raise ValueError("a group's runs must differ in their seeds only")
    group = Group(specs, embedding, device, notice)
    try:
        sessions = [
            _Session.start(group, j, out, bad_checkpoint, notice) for j, out in enumerate(outs)
        ]
        _evaluate(sessions, [s.run for s in sessions if not s.run.history])  # from the start
        if progress is not None:
            progress(sum(run.step for run in group.runs))
        while stepped := group.advance():
            if progress is not None:
                progress(len(stepped))
            _evaluate(
                sessions,
                [
                    r
                    for r in stepped
                    if r.step % r.spec.td3.eval_every == 0 or r.step == r.spec.budget
                ],
            )
            for run in stepped:
                if run.failed is None and run.step % run.spec.td3.checkpoint_every == 0:
                    if run.step < run.spec.budget:
                        sessions[run.index].clock()
                        run.save(sessions[run.index].out / "checkpoint")
        results = [s.finish(keep_checkpoint) for s in sessions if s.run.failed is None]
        failed = [s.stopped() for s in sessions if s.run.failed is not None]
    finally:
        group.close()
    if failed:
        raise Diverged("\n".join(failed))
    return results


def _evaluate(sessions: list[_Session], runs: list[Member]) -> None:
    """Evaluate ``runs`` together and write each one's curves."""
    if not runs:
        return
    for run in runs:
        sessions[run.index].clock()
    group = sessions[0].group
    group.evaluate(np.isin(np.arange(len(group.runs)), [run.index for run in runs]))
    for run in runs:
        if run.failed is None:
            write_curves(sessions[run.index].out, run.history, run.diagnostics)


@dataclass
class _Session:
    """One run of a group in this process: its outputs and wall clock."""

    group: Group
    index: int
    out: Path
    resumed: bool
    started: float = field(default_factory=time.perf_counter)
    steps_at_start: int = 0
    wall_at_start: float = 0.0

    @property
    def run(self) -> Member:
        return self.group.runs[self.index]

    @classmethod
    def start(
        cls,
        group: Group,
        index: int,
        out: Path,
        bad_checkpoint: str,
        notice: Callable[[str], None],
    ) -> _Session:
        claim(out, RUN_KIND, RUN_OWNS)
        path = out / "checkpoint"
        run = group.runs[index]
        try:
            resumed = run.load(path)
        except CheckpointError as error:
            if bad_checkpoint == "refuse":
                raise CheckpointError(f"{path}: {error}") from None
            aside = move_aside(path)
            notice(f"{path}: {error}; moved aside to {aside.name}, starting over")
            run, resumed = group.restart(index), False
        return cls(group, index, out, resumed, steps_at_start=run.step, wall_at_start=run.wall)

    def clock(self) -> None:
        self.run.wall = self.wall_at_start + time.perf_counter() - self.started

    def stopped(self) -> str:
        """A diverged run's line, with where it would resume: its last checkpoint."""
        path = self.out / "checkpoint"
        try:
            step = checkpoint.read(path, self.run.spec, self.group.layout).step
            last = f"its last checkpoint, {path}, is at step {step}"
        except CheckpointError:
            last = "it has no checkpoint"
        return f"{self.run.failed}; stopped there, no metrics.json written; {last}"

    def finish(self, keep_checkpoint: bool) -> dict[str, Any]:
        """The run's final outputs; ``metrics.json`` last: its steps per second are this
        session's (``steps_per_second``, from ``resumed_from_step``) and the whole run's
        (``whole_run_steps_per_second``)."""
        run, out, spec = self.run, self.out, self.run.spec
        self.clock()
        write_curves(out, run.history, run.diagnostics)
        session_seconds = time.perf_counter() - self.started
        metrics = run_metrics(
            run.history,
            run.episodes,
            run.step,
            run.step - self.steps_at_start,
            session_seconds,
            self.wall_at_start + session_seconds,
            self.steps_at_start if self.resumed else None,
        )
        save_policy(out / POLICY, self.group.agent, self.index, spec, self.group.adapter)
        write_finished(out, spec, metrics, self.group.device, compiled=self.group.agent.compiled)
        path = out / "checkpoint"
        if not keep_checkpoint:
            shutil.rmtree(path, ignore_errors=True)
        remove_stale_temporaries(path)  # a killed session's half-written checkpoint
        return metrics


def run_metrics(
    history: list[dict[str, float]],
    episodes: int,
    step: int,
    session_steps: int,
    session_seconds: float,
    run_seconds: float,
    resumed_from: int | None,
) -> dict[str, Any]:
    """A finished run's ``metrics.json``: from its evaluations (``history``), its ``episodes`` and
    ``step``, the steps and seconds of this session and the run's wall time (``run_seconds``):
    every session's up to the checkpoint the next one resumed from (checkpointed with it), and
    this one's; a killed session's time after its last checkpoint is not counted, as its steps
    are not: they are taken again."""
    steps = np.array([row["step"] for row in history], dtype=float)
    returns = np.array([row["mean_return"] for row in history])
    return {
        "final_return": float(returns[-1]),
        "best_return": float(returns.max()),
        "auc": area_under_curve(steps, returns),
        "steps_per_second": session_steps / session_seconds if session_steps else None,
        "whole_run_steps_per_second": step / run_seconds,
        "episodes": episodes,
        "resumed_from_step": resumed_from,
    }


def move_aside(path: Path) -> Path:
    """Rename a checkpoint that cannot be used to ``<name>.bad-<time>``, kept for a look."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    aside = path.with_name(f"{path.name}.bad-{stamp}")
    n = 1
    while aside.exists():
        n += 1
        aside = path.with_name(f"{path.name}.bad-{stamp}-{n}")
    path.rename(aside)
    return aside


def save_policy(
    path: Path, agent: Agent, member: int, spec: RunSpec, adapter: ActionAdapter
) -> None:
    """Member ``member``'s final actor: ``policy.safetensors`` (the single-network ``Actor``'s
    tensors: ``net.0.weight``, ``net.0.bias``, ..., ``centre``, ``half_range``; an
    ``ede.method.nets.mlp`` of ``hidden`` loads ``net.*``) beside ``policy.json``."""
    write_policy(
        path,
        agent.policy(member),
        {
            **spec.identity(),
            "k": adapter.k,
            "code_size": adapter.code_size,
            "code_low": adapter.code_low.tolist(),
            "code_high": adapter.code_high.tolist(),
            "hidden": spec.td3.hidden,
        },
    )
