"""One training run of TD3 or EDE-TD3: the environment loop, evaluation, checkpoints, outputs.

A run is determined by its :class:`ede.run.runs.RunSpec` and (for EDE-TD3) its embedding. It writes
its folder's files (:mod:`ede.run.runs`: ``eval.csv`` and ``diagnostics.csv`` after every
evaluation, ``policy/``, ``run.json`` and, last, ``metrics.json``) and, while it trains,
``checkpoint/``: everything needed to continue exactly, in the format of :mod:`ede.run.checkpoint` —
the same for a run trained alone and for a member of a group, so either resumes the other. A run
started where a checkpoint of the same configuration exists continues from it; on CPU a run
killed at any point and resumed ends with the same ``eval.csv`` returns as an uninterrupted one.

A group of runs (several seeds of one task and algorithm) is one :class:`ede.method.agent.Agent` with a
member per run; a run alone is a group of one. Each run's outputs are what it gets alone.

This module orchestrates: :class:`_Run` keeps one run's counters, episode and history,
:class:`_Group` steps every member's environment at once (:class:`ede.run.vector.MemberEnvs`: one
batched action per step, one write to the replay buffer) and schedules the batched updates, and
:class:`_Session` writes one run's outputs.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import torch

from ede.config import ALGOS
from ede.io.atomic import claim, remove_stale_temporaries
from ede.method.adapters import ActionAdapter, EmbeddingAdapter, IdentityAdapter
from ede.method.agent import Agent
from ede.method.embedding import ActionEmbedding
from ede.method.nets import flush_denormals
from ede.method.replay import ReplayBuffer
from ede.run import checkpoint
from ede.run.checkpoint import CheckpointError, Layout
from ede.run.executor import CodeExecutor
from ede.run.runs import (
    POLICY,
    RUN_KIND,
    RUN_OWNS,
    RunSpec,
    area_under_curve,
    write_curves,
    write_finished,
    write_policy,
)
from ede.run.vector import Episode, MemberEnvs
from ede.tasks import make

__all__ = ["Diverged", "evaluate", "train_group", "train_run"]


class Diverged(Exception):
    """Runs whose numbers stopped being finite: one line each (task, algorithm, seed, step, the
    quantity). Each stopped there, its last checkpoint kept and no ``metrics.json`` written;
    the group's other runs finished."""


EVAL_SEED_OFFSET = 1_000_003  # evaluation episodes are seeded apart from training ones


def evaluate(
    envs: MemberEnvs,
    policy: Callable[[np.ndarray], torch.Tensor],
    adapter: ActionAdapter,
    episodes: int,
    seeds: Sequence[int],
    members: np.ndarray | None = None,
) -> np.ndarray:
    """Returns ``(M, episodes)`` of ``policy`` (deterministic: μ(s), ``(M, O) -> (M, C)``) in each
    member's environment of ``envs`` (the members of ``members``, every one by default; rows of
    others zero); member m's episode e starts from ``reset(seeds[m] + e)``. The members' episodes
    are stepped together, one batched action per step."""
    members = np.ones(envs.members, dtype=bool) if members is None else members
    returns = np.zeros((envs.members, episodes))
    executor = CodeExecutor(envs, adapter)
    for step, stepped, episode in executor.episodes(
        lambda obs, _: policy(obs), episodes, seeds, members
    ):
        which = np.flatnonzero(stepped)
        returns[which, episode[which]] += step.reward[which]
    return returns


def _adapter(
    spec: RunSpec,
    space: gymnasium.spaces.Box,
    embedding: ActionEmbedding | None,
    device: torch.device,
) -> ActionAdapter:
    if spec.algo == "td3":
        return IdentityAdapter(space.low, space.high, device, spec.td3.noise_units)
    assert embedding is not None
    ede = spec.ede_td3
    return EmbeddingAdapter(
        embedding,
        ede.bound_scale,
        ede.target_noise_scale,
        ede.target_noise_clip,
        ede.plan_step_input,
    )


class _Run:
    """One run of a group: its counters, the episode under way and its history. Its learner
    state is member ``index`` of the group's agent and replay buffer, whose count is the run's
    environment steps (:attr:`step`); its environments are member ``index`` of the group's."""

    def __init__(self, index: int, spec: RunSpec, group: _Group) -> None:
        self.index, self.spec, self.group = index, spec, group
        self.episodes = 0
        self.history: list[dict[str, float]] = []
        self.diagnostics: list[dict[str, float]] = []  # training's means between evaluations
        self.wall = 0.0  # seconds spent, over every session of this run
        self.failed: str | None = None  # why it stopped, once it diverged
        self.episode = Episode({"seed": spec.seed})  # the actions taken, its return

    @property
    def step(self) -> int:
        """Environment steps taken: the steps this run's member wrote to the replay buffer."""
        return int(self.group.buffer.count[self.index])

    def diverged(self, step: int, quantity: str) -> str:
        spec = self.spec
        return (
            f"{spec.task} {spec.algo} seed {spec.seed}: diverged at step {step}: "
            f"{quantity} is not finite"
        )

    def record(self, returns: np.ndarray) -> dict[str, float]:
        """An evaluation's ``returns``: its row of ``eval.csv``, and of ``diagnostics.csv``."""
        row = {
            "step": self.step,
            "episode": self.episodes,
            "mean_return": float(returns.mean()),
            "std_return": float(returns.std()),
            "wall_seconds": round(self.wall, 3),
        }
        self.history.append(row)
        trained = self.group.agent.take_diagnostics(self.index)
        if trained["updates"]:
            self.diagnostics.append({"step": self.step, **trained})
        return row

    # Checkpoints ---------------------------------------------------------------------------

    def save(self, path: Path) -> None:
        """Write this run's checkpoint (:func:`ede.run.checkpoint.write`): its member's slice of the
        agent and the replay buffer, its code, episode and history.

        Raises:
            CheckpointWriteError: it could not be written; the previous one is intact.
        """
        group, executor, j = self.group, self.group.executor, self.index
        episode = Episode(group.envs.starts()[j], self.episode.actions, self.episode.ret)
        state = checkpoint.Checkpoint(
            agent=group.agent.state_dict(j),
            buffer=group.buffer.state_dict(j),
            code=executor.code[j],
            plan=executor.plan[j],
            i=int(executor.i[j]),
            episode=episode,
            obs=group.envs.obs[j],
            episodes=self.episodes,
            history=self.history,
            diagnostics=self.diagnostics,
            wall_seconds=self.wall,
        )
        checkpoint.write(path, self.spec, state)

    def load(self, path: Path) -> bool:
        """Continue from the checkpoint at ``path``: :func:`ede.run.checkpoint.read` verifies it,
        :func:`ede.run.checkpoint.apply` restores it. False where there is none.

        Raises:
            CheckpointError: it cannot be used. The agent and the replay buffer are untouched;
                this run's environment may be mid-replay: the caller restarts the run
                (:meth:`_Group.restart`).
        """
        if not path.exists():
            return False
        group, j = self.group, self.index
        saved = checkpoint.read(path, self.spec, group.layout)
        self.episode = checkpoint.apply(
            saved,
            group.agent,
            group.buffer,
            j,
            group.executor,
            lambda episode: group.envs.restore({j: episode})[j],
        )
        self.episodes, self.wall = saved.episodes, saved.wall_seconds
        self.history, self.diagnostics = list(saved.history), list(saved.diagnostics)
        return True


class _Group:
    """The runs of one task and algorithm that differ in their seeds, as one agent with a
    member per run (M = 1 for a run alone), one replay buffer, and the members' training and
    evaluation environments as two vector environments (:class:`ede.run.vector.MemberEnvs`)."""

    def __init__(
        self, specs: list[RunSpec], embedding: ActionEmbedding | None, device: torch.device
    ) -> None:
        spec, self.device = specs[0], device
        probe = make(spec.task)
        space, obs_shape = probe.action_space, probe.observation_space.shape
        assert isinstance(space, gymnasium.spaces.Box) and obs_shape is not None
        obs_size = int(np.prod(obs_shape))
        probe.close()
        self.adapter = _adapter(spec, space, embedding, device)
        self.agent = Agent(obs_size, self.adapter, spec.td3, device, [s.seed for s in specs])
        capacity = min(spec.td3.buffer_size, spec.budget)
        self.buffer = ReplayBuffer(
            capacity, obs_size, self.adapter.code_size, self.adapter.k, device, len(specs)
        )
        self.layout = Layout.of(self.agent, self.buffer, obs_shape, (self.adapter.k, *space.shape))
        workers = env_workers(spec.td3.env_workers, len(specs), device)
        self.envs = MemberEnvs.of_task(spec.task, len(specs), workers)
        self.eval_envs = MemberEnvs.of_task(spec.task, len(specs), workers)
        self.executor = CodeExecutor(self.envs, self.adapter)
        self.runs = [_Run(j, s, self) for j, s in enumerate(specs)]
        self.envs.reset(np.ones(len(specs), dtype=bool), [s.seed for s in specs])

    def close(self) -> None:
        self.envs.close()
        self.eval_envs.close()

    def restart(self, index: int) -> _Run:
        """Run ``index`` from its start again, in a fresh episode from its seed (after a
        checkpoint that could not be used, which left its member of the agent and buffer as
        they were)."""
        run = self.runs[index] = _Run(index, self.runs[index].spec, self)
        only = np.arange(len(self.runs)) == index
        self.envs.reset(only, [r.spec.seed for r in self.runs])
        self.executor.i[index] = 0
        return run

    def _behaviour(self, obs: np.ndarray, choosing: np.ndarray) -> torch.Tensor:
        """The codes training acts with: uniform for ``td3.start_steps`` steps, then μ(s) +
        noise (:meth:`ede.method.agent.Agent.behave`)."""
        start_steps = self.runs[0].spec.td3.start_steps
        uniform = self.buffer.count < start_steps
        return self.agent.behave(obs, choosing, uniform)

    def evaluate(self, members: np.ndarray) -> None:
        """Evaluate the runs of ``members`` (their μ(s), ``td3.eval_episodes`` episodes each)
        and record each one's row."""
        runs = self.runs
        seeds = [EVAL_SEED_OFFSET * (run.spec.seed + 1) for run in runs]
        episodes = runs[0].spec.td3.eval_episodes
        returns = evaluate(self.eval_envs, self.agent.act, self.adapter, episodes, seeds, members)
        for m in np.flatnonzero(members):
            if not np.isfinite(returns[m]).all():
                runs[m].failed = runs[m].diverged(runs[m].step, "the evaluation's return")
            else:
                runs[m].record(returns[m])

    def update(self, due: np.ndarray) -> None:
        """The updates due after a step, ``due[m]`` for member m: as many batched updates as
        the most any member is due, each member masked out once it has had its own."""
        for u in range(int(due.max(initial=0))):
            self.agent.update(self.buffer, due > u)

    def advance(self) -> list[_Run]:
        """One environment step (Section 3: learn from every step) of the runs furthest behind
        (every run, while they are in step), then the updates it makes due; returns the runs
        that stepped (none once every run is done).

        A run is due one update after a step with ``td3.update_schedule: step``; with
        ``episode`` none until its episode ends, then one per step of it; none while the start
        steps last or no batch can be sampled yet.
        """
        runs, config, buffer = self.runs, self.runs[0].spec.td3, self.buffer
        active = np.array([run.step < run.spec.budget and run.failed is None for run in runs])
        if not active.any():
            return []
        stepping = active & (buffer.count == buffer.count[active].min())
        obs = self.envs.obs.copy()
        if self.executor.choose(obs, self._behaviour, stepping).any():
            code = "the actor's " + ("action" if runs[0].spec.algo == "td3" else "code")
            finite = np.isfinite(self.executor.code.cpu().numpy()).all(-1)
            self._stop(stepping, ~finite, code)
        step = self.executor.step(stepping)
        self._stop(stepping, ~np.isfinite(step.reward), "the environment's reward")
        self._stop(stepping, ~np.isfinite(step.next_obs).all(-1), "the environment's observation")
        buffer.add(stepping, obs, step.code, step.i, step.reward, step.next_obs,
                   step.terminated, step.truncated)  # fmt: skip
        due, ended = np.zeros(len(runs), dtype=np.int64), step.ended
        for m in np.flatnonzero(stepping):
            run = runs[m]
            run.episode.actions.append(step.action[m])
            run.episode.ret += float(step.reward[m])
            due[m] = 1 if config.update_schedule == "step" else 0
            if ended[m]:
                if config.update_schedule == "episode":
                    due[m] = len(run.episode.actions)  # one per step of the episode just ended
                run.episodes += 1
                run.episode = Episode({})
            if run.step < config.start_steps or buffer.sampleable(int(m)) < config.batch_size:
                due[m] = 0
        if ended.any():  # each starts its next episode from its environment's own generator
            self.envs.reset(ended, [None] * len(runs))
        self.update(due)
        losses = self.agent.non_finite() if due.any() else {}  # they change only in updates
        for member, quantity in losses.items():
            run = runs[member]
            if run.failed is None:  # a member that stopped earlier keeps its first reason
                run.failed = run.diverged(run.step, quantity)
        return [runs[m] for m in np.flatnonzero(stepping) if runs[m].failed is None]

    def _stop(self, stepping: np.ndarray, bad: np.ndarray, quantity: str) -> None:
        """The members of ``stepping`` where ``bad`` stop at this step, ``quantity`` not finite:
        they are out of ``stepping`` (nothing of the step is written for them)."""
        for m in np.flatnonzero(stepping & bad):
            run = self.runs[m]
            run.failed, stepping[m] = run.diverged(run.step + 1, quantity), False


def env_workers(setting: str, members: int, device: torch.device) -> bool:
    """Whether a group's environments step in worker processes (``AsyncVectorEnv``):
    ``td3.env_workers`` "yes" or "no", or for "auto" where it pays — a group of several members
    on a GPU machine with a core for each of at least four workers (on CPU the cores are the
    sweep's, one run or group per core)."""
    if setting != "auto":
        return setting == "yes"
    return device.type == "cuda" and members > 1 and (os.cpu_count() or 1) >= 4


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
    A checkpoint that cannot be used (:meth:`_Run.load`) is reported through ``notice`` and
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
    if spec.algo not in ALGOS:
        raise ValueError(f"unknown algorithm {spec.algo!r}; expected one of {', '.join(ALGOS)}")
    if spec.algo == "ede-td3" and embedding is None:
        raise ValueError("ede-td3 needs the family's action embedding")
    alike = all(replace(s, seed=0) == replace(spec, seed=0) for s in specs)
    if not alike or len({s.seed for s in specs}) != len(specs):
        raise ValueError("a group's runs must differ in their seeds only")
    group = _Group(specs, embedding, device)
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


def _evaluate(sessions: list[_Session], runs: list[_Run]) -> None:
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

    group: _Group
    index: int
    out: Path
    resumed: bool
    started: float = field(default_factory=time.perf_counter)
    steps_at_start: int = 0
    wall_at_start: float = 0.0

    @property
    def run(self) -> _Run:
        return self.group.runs[self.index]

    @classmethod
    def start(
        cls,
        group: _Group,
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
            aside = _move_aside(path)
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
        """The run's final outputs; ``metrics.json`` last."""
        run, out, spec = self.run, self.out, self.run.spec
        self.clock()
        write_curves(out, run.history, run.diagnostics)
        steps = np.array([row["step"] for row in run.history], dtype=float)
        returns = np.array([row["mean_return"] for row in run.history])
        session_steps = run.step - self.steps_at_start
        session_seconds = time.perf_counter() - self.started
        metrics = {
            "final_return": float(returns[-1]),
            "best_return": float(returns.max()),
            "auc": area_under_curve(steps, returns),
            "steps_per_second": session_steps / session_seconds if session_steps else None,
            "episodes": run.episodes,
            "resumed_from_step": self.steps_at_start if self.resumed else None,
        }
        save_policy(out / POLICY, self.group.agent, self.index, spec, self.group.adapter)
        write_finished(out, spec, metrics, self.group.device)
        path = out / "checkpoint"
        if not keep_checkpoint:
            shutil.rmtree(path, ignore_errors=True)
        remove_stale_temporaries(path)  # a killed session's half-written checkpoint
        return metrics


def _move_aside(path: Path) -> Path:
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
