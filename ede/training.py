"""One training run of TD3 or EDE-TD3: the environment loop, evaluation, checkpoints, outputs.

A run is determined by its :class:`ede.runs.RunSpec` and (for EDE-TD3) its embedding. It writes
its folder's files (:mod:`ede.runs`: ``eval.csv`` and ``diagnostics.csv`` after every
evaluation, ``policy/``, ``run.json`` and, last, ``metrics.json``) and, while it trains,
``checkpoint/``: everything needed to continue exactly, in the format of :mod:`ede.checkpoint` —
the same for a run trained alone and for a member of a group, so either resumes the other. A run
started where a checkpoint of the same configuration exists continues from it; on CPU a run
killed at any point and resumed ends with the same ``eval.csv`` returns as an uninterrupted one.

A group of runs (several seeds of one task and algorithm) is one :class:`ede.td3.Agent` with a
member per run; a run alone is a group of one. Each run's outputs are what it gets alone.

This module orchestrates: :class:`_Run` steps one run's environment, :class:`_Group` schedules
the runs' steps and batched updates, and :class:`_Session` writes one run's outputs.
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import torch

from ede import checkpoint
from ede.atomic import claim, remove_stale_temporaries
from ede.checkpoint import CheckpointError, Episode, Layout
from ede.config import ALGOS
from ede.embedding import ActionEmbedding
from ede.nets import flush_denormals
from ede.runs import RUN_KIND, RUN_OWNS, RunSpec, write_curves, write_finished, write_policy
from ede.stats import area_under_curve
from ede.tasks import make
from ede.td3 import (
    ActionAdapter,
    Agent,
    CodeExecutor,
    EmbeddingAdapter,
    IdentityAdapter,
    ReplayBuffer,
)

__all__ = ["Diverged", "evaluate", "train_group", "train_run"]


class Diverged(Exception):
    """Runs whose numbers stopped being finite: one line each (task, algorithm, seed, step, the
    quantity). Each stopped there, its last checkpoint kept and no ``metrics.json`` written;
    the group's other runs finished."""


EVAL_SEED_OFFSET = 1_000_003  # evaluation episodes are seeded apart from training ones


def evaluate(
    env: gymnasium.Env,
    policy: Callable[[np.ndarray], torch.Tensor],
    adapter: ActionAdapter,
    episodes: int,
    seed: int,
) -> np.ndarray:
    """Returns of ``episodes`` episodes of ``policy`` (deterministic: μ(s)); episode e starts
    from ``reset(seed + e)``."""
    executor = CodeExecutor(env, adapter)
    returns = np.zeros(episodes)
    for e in range(episodes):
        obs, _ = env.reset(seed=seed + e)
        for step in executor.episode(obs, policy):
            returns[e] += step.reward
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
    """One run of a group: its environments, the episode under way, its counters and history.
    Its learner state is member ``index`` of the group's agent and replay buffer, whose count is
    the run's environment steps (:attr:`step`)."""

    def __init__(self, index: int, spec: RunSpec, group: _Group) -> None:
        self.index, self.spec, self.group = index, spec, group
        self.env = make(spec.task)
        self.eval_env = make(spec.task)
        self.executor = CodeExecutor(self.env, group.adapter)
        self.episodes = 0
        self.history: list[dict[str, float]] = []
        self.diagnostics: list[dict[str, float]] = []  # training's means between evaluations
        self.wall = 0.0  # seconds spent, over every session of this run
        self.failed: str | None = None  # why it stopped, once it diverged
        self.obs, self.episode = Episode.begin(self.env, spec.seed)

    @property
    def step(self) -> int:
        """Environment steps taken: the steps this run's member wrote to the replay buffer."""
        return int(self.group.buffer.count[self.index])

    # The loop ------------------------------------------------------------------------------

    def act(self, obs: np.ndarray) -> torch.Tensor:
        """μ(s) of this run's member: what evaluation executes."""
        return self.group.agent.act(self.index, obs, explore=False)

    def _behaviour(self, obs: np.ndarray) -> torch.Tensor:
        """The code training acts with: uniform for ``td3.start_steps`` steps, then μ(s) + noise."""
        agent = self.group.agent
        if self.step < self.spec.td3.start_steps:
            return agent.random_code(self.index)
        code = agent.act(self.index, obs, explore=True)
        if not bool(torch.isfinite(code).all()):
            raise self.diverged(
                self.step + 1, "the actor's " + ("action" if self.spec.algo == "td3" else "code")
            )
        return code

    def diverged(self, step: int, quantity: str) -> Diverged:
        spec = self.spec
        return Diverged(
            f"{spec.task} {spec.algo} seed {spec.seed}: diverged at step {step}: "
            f"{quantity} is not finite"
        )

    def env_step(self) -> int:
        """One environment step (Section 3: learn from every step).

        Returns:
            The number of updates due after it: with ``td3.update_schedule: step`` one; with
            ``episode`` none until the episode ends, then one per step of it; none while the
            start steps last or no batch can be sampled yet.
        """
        config, buffer = self.spec.td3, self.group.buffer
        step = self.executor.step(self.obs, self._behaviour)
        if not np.isfinite(step.reward):
            raise self.diverged(self.step + 1, "the environment's reward")
        if not np.isfinite(step.next_obs).all():
            raise self.diverged(self.step + 1, "the environment's observation")
        buffer.add(
            self.index,
            self.obs,
            step.code,
            step.i,
            step.reward,
            step.next_obs,
            step.terminated,
            step.truncated,
        )
        self.episode.actions.append(step.action)
        self.episode.ret += step.reward
        updates = 1 if config.update_schedule == "step" else 0
        if step.ended:
            if config.update_schedule == "episode":
                updates = len(self.episode.actions)  # one per step of the episode just ended
            self.episodes += 1
            self.obs, self.episode = Episode.begin(self.env, None)
        else:
            self.obs = step.next_obs
        if self.step < config.start_steps or buffer.sampleable(self.index) < config.batch_size:
            return 0
        return updates

    def evaluate(self) -> dict[str, float]:
        returns = evaluate(
            self.eval_env,
            self.act,
            self.group.adapter,
            self.spec.td3.eval_episodes,
            EVAL_SEED_OFFSET * (self.spec.seed + 1),
        )
        if not np.isfinite(returns).all():
            raise self.diverged(self.step, "the evaluation's return")
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
        """Write this run's checkpoint (:func:`ede.checkpoint.write`): its member's slice of the
        agent and the replay buffer, its code, episode and history.

        Raises:
            CheckpointWriteError: it could not be written; the previous one is intact.
        """
        group, executor = self.group, self.executor
        state = checkpoint.Checkpoint(
            agent=group.agent.state_dict(self.index),
            buffer=group.buffer.state_dict(self.index),
            code=executor.code,
            plan=executor.plan,
            i=executor.i,
            episode=self.episode,
            obs=self.obs,
            episodes=self.episodes,
            history=self.history,
            diagnostics=self.diagnostics,
            wall_seconds=self.wall,
        )
        checkpoint.write(path, self.spec, state)

    def load(self, path: Path) -> bool:
        """Continue from the checkpoint at ``path``: :func:`ede.checkpoint.read` verifies it,
        :func:`ede.checkpoint.apply` restores it. False where there is none.

        Raises:
            CheckpointError: it cannot be used. The agent and the replay buffer are untouched;
                this run's environment may be mid-replay: the caller restarts the run
                (:meth:`_Group.restart`).
        """
        if not path.exists():
            return False
        group = self.group
        saved = checkpoint.read(path, self.spec, group.layout)
        self.obs, self.episode = checkpoint.apply(
            saved, group.agent, group.buffer, self.index, self.executor, self.env
        )
        self.episodes, self.wall = saved.episodes, saved.wall_seconds
        self.history, self.diagnostics = list(saved.history), list(saved.diagnostics)
        return True


class _Group:
    """The runs of one task and algorithm that differ in their seeds, as one agent with a
    member per run (M = 1 for a run alone) and one replay buffer."""

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
        self.runs = [_Run(j, s, self) for j, s in enumerate(specs)]

    def restart(self, index: int) -> _Run:
        """Run ``index`` from its start again, with fresh environments (after a checkpoint that
        could not be used, which left its member of the agent and buffer as they were)."""
        self.runs[index] = _Run(index, self.runs[index].spec, self)
        return self.runs[index]

    def update(self, due: np.ndarray) -> None:
        """The updates due after a step, ``due[m]`` for member m: as many batched updates as
        the most any member is due, each member masked out once it has had its own."""
        for u in range(int(due.max(initial=0))):
            self.agent.update(self.buffer, due > u)

    def advance(self) -> list[_Run]:
        """One step of the runs furthest behind (every run, while they are in step) and the
        updates it makes due; returns the runs that stepped (none once every run is done)."""
        active = [run for run in self.runs if run.step < run.spec.budget and run.failed is None]
        if not active:
            return []
        behind = min(run.step for run in active)
        stepping = [run for run in active if run.step == behind]
        due = np.zeros(len(self.runs), dtype=np.int64)
        for run in stepping:
            try:
                due[run.index] = run.env_step()
            except Diverged as error:
                run.failed = str(error)
        self.update(due)
        losses = self.agent.non_finite() if due.any() else {}  # they change only in updates
        for member, quantity in losses.items():
            run = self.runs[member]
            if run.failed is None:  # a member that stopped earlier keeps its first reason
                run.failed = str(run.diverged(run.step, quantity))
        return [run for run in stepping if run.failed is None]


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
    ``out``, in one process: one agent with a member per run (:class:`ede.td3.Agent`), their
    environments stepped in turn, their updates as one. Each member's outputs are those it gets
    alone. Members due different numbers of updates (per-episode batches of episodes that ended
    apart) are masked in the updates they are not due; members resumed from different steps
    step in turn, the ones behind first, until they are in step.
    CPU arithmetic flushes subnormal numbers to zero throughout (:func:`ede.nets.flush_denormals`).

    Each resumes from its ``out/checkpoint`` when there is one (written alone or in a group).
    A checkpoint that cannot be used (:meth:`_Run.load`) is reported through ``notice`` and
    moved aside to ``out/checkpoint.bad-<time>``, and that run starts over; with
    ``bad_checkpoint="refuse"`` it raises :class:`CheckpointError` instead, touching nothing.

    Returns:
        Each member's metrics, as written to its ``metrics.json``.

    Raises:
        CheckpointError: a bad checkpoint under "refuse".
        CheckpointWriteError: a checkpoint could not be written; the previous one is kept
            (:func:`ede.checkpoint.write`).
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
    sessions = [_Session.start(group, j, out, bad_checkpoint, notice) for j, out in enumerate(outs)]
    if progress is not None:
        progress(sum(run.step for run in group.runs))
    while stepped := group.advance():
        for run in stepped:
            try:
                sessions[run.index].after_step(progress)
            except Diverged as error:
                run.failed = str(error)
    results = [s.finish(keep_checkpoint) for s in sessions if s.run.failed is None]
    failed = [s.stopped() for s in sessions if s.run.failed is not None]
    if failed:
        raise Diverged("\n".join(failed))
    return results


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
        session = cls(group, index, out, resumed, steps_at_start=run.step, wall_at_start=run.wall)
        if not run.history:
            run.evaluate()
            write_curves(out, run.history, run.diagnostics)
        return session

    def clock(self) -> None:
        self.run.wall = self.wall_at_start + time.perf_counter() - self.started

    def after_step(self, progress: Callable[[int], None] | None) -> None:
        """Evaluate and checkpoint when the step calls for it."""
        run, config = self.run, self.run.spec.td3
        if progress is not None:
            progress(1)
        if run.step % config.eval_every == 0 or run.step == run.spec.budget:
            self.clock()
            run.evaluate()
            write_curves(self.out, run.history, run.diagnostics)
        if run.step % config.checkpoint_every == 0 and run.step < run.spec.budget:
            self.clock()
            run.save(self.out / "checkpoint")

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
        save_policy(out / "policy", self.group.agent, self.index, spec, self.group.adapter)
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
    ``ede.nets.mlp`` of ``hidden`` loads ``net.*``) beside ``policy.json``."""
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
