"""A group of runs stepped as one: the runs of one task and algorithm that differ in their seeds.

:class:`Group` is one :class:`ede.method.agent.Agent` with a member per run (M = 1 for a run
alone), one replay buffer, and the members' training and evaluation environments
(:class:`ede.run.vector.MemberEnvs`): :meth:`Group.advance` takes one environment step of the runs
furthest behind (one batched action, one write to the replay buffer) and the batched updates it
makes due, :meth:`Group.evaluate` evaluates them (:func:`ede.run.evaluation.evaluate`).
:class:`Member` keeps one run's counters, episode and history, and writes and reads its checkpoint
(:mod:`ede.run.checkpoint`). The loop around them, and each run's outputs, are
:mod:`ede.run.training`'s.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import sys
import sysconfig
from collections.abc import Callable
from pathlib import Path

import gymnasium
import numpy as np
import torch

from ede.method.adapters import ActionAdapter, EmbeddingAdapter, IdentityAdapter
from ede.method.agent import Agent
from ede.method.embedding import ActionEmbedding
from ede.method.replay import ReplayBuffer
from ede.run import checkpoint
from ede.run.checkpoint import Layout
from ede.run.evaluation import EVAL_SEED_OFFSET, evaluate
from ede.run.executor import CodeExecutor
from ede.run.spec import RunSpec
from ede.run.vector import Episode, MemberEnvs
from ede.tasks import make

__all__ = [
    "COMPILE_FROM_UPDATES",
    "Group",
    "Member",
    "compile_mode",
    "compiler_missing",
    "env_workers",
]


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


class Member:
    """One run of a group: its counters, the episode under way and its history. Its learner
    state is member ``index`` of the group's agent and replay buffer, whose count is the run's
    environment steps (:attr:`step`); its environments are member ``index`` of the group's."""

    def __init__(self, index: int, spec: RunSpec, group: Group) -> None:
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
                (:meth:`Group.restart`).
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


class Group:
    """The runs of one task and algorithm that differ in their seeds, as one agent with a
    member per run (M = 1 for a run alone), one replay buffer, and the members' training and
    evaluation environments as two vector environments (:class:`ede.run.vector.MemberEnvs`)."""

    def __init__(
        self,
        specs: list[RunSpec],
        embedding: ActionEmbedding | None,
        device: torch.device,
        notice: Callable[[str], None] = print,
    ) -> None:
        """``notice``: told, in one line, where ``td3.compile: auto`` leaves a run's updates
        eager that would have paid to compile (:func:`compile_mode`), or falls back to eager
        where compiling fails."""
        spec, self.device = specs[0], device
        probe = make(spec.task)
        space, obs_shape = probe.action_space, probe.observation_space.shape
        assert isinstance(space, gymnasium.spaces.Box) and obs_shape is not None
        obs_size = int(np.prod(obs_shape))
        probe.close()
        self.adapter = _adapter(spec, space, embedding, device)
        updates = spec.budget - min(spec.td3.start_steps, spec.budget)
        mode = compile_mode(spec.td3.compile, updates, device)
        if spec.td3.compile == "auto" and mode == "none" and updates >= COMPILE_FROM_UPDATES:
            notice(
                f"td3.compile auto: {compiler_missing(device)} not found, so the updates run "
                "eager, slower (docs/performance.md)"
            )
        td3 = spec.td3.model_copy(update={"compile": mode})
        self.agent = Agent(
            obs_size,
            self.adapter,
            td3,
            device,
            [s.seed for s in specs],
            fallback=notice if spec.td3.compile == "auto" else None,
        )
        capacity = min(spec.td3.buffer_size, spec.budget)
        self.buffer = ReplayBuffer(
            capacity, obs_size, self.adapter.code_size, self.adapter.k, device, len(specs)
        )
        self.layout = Layout.of(self.agent, self.buffer, obs_shape, (self.adapter.k, *space.shape))
        workers = env_workers(spec.td3.env_workers, len(specs), device)
        self.envs = MemberEnvs.of_task(spec.task, len(specs), workers)
        self.eval_envs = MemberEnvs.of_task(spec.task, len(specs), workers)
        self.executor = CodeExecutor(self.envs, self.adapter)
        self.runs = [Member(j, s, self) for j, s in enumerate(specs)]
        self.envs.reset(np.ones(len(specs), dtype=bool), [s.seed for s in specs])

    def close(self) -> None:
        self.envs.close()
        self.eval_envs.close()

    def restart(self, index: int) -> Member:
        """Run ``index`` from its start again, in a fresh episode from its seed (after a
        checkpoint that could not be used, which left its member of the agent and buffer as
        they were)."""
        run = self.runs[index] = Member(index, self.runs[index].spec, self)
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

    def advance(self) -> list[Member]:
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


# ``td3.compile: auto`` compiles the update of a run of at least this many updates. Compiling
# costs about 40 s at the start with Inductor's on-disk cache empty (about 6 s with it filled by
# an earlier run of the same shapes on the machine) and saves about 1.2 ms an update at the
# paper's sizes on our CPUs, so it pays from some 33,000 updates cold and 5,000 warm: a sweep's
# first run fills the cache for the rest (docs/performance.md).
COMPILE_FROM_UPDATES = 25_000


def compile_mode(setting: str, updates: int, device: torch.device) -> str:
    """How a run of ``updates`` updates runs them: ``td3.compile`` as set, or for "auto"
    "default" (``torch.compile``) where it pays and can — from :data:`COMPILE_FROM_UPDATES`
    updates on, with what compiling needs here (:func:`compiler_missing`) — and "none" (eager)
    elsewhere."""
    if setting != "auto":
        return setting
    if updates < COMPILE_FROM_UPDATES or compiler_missing(device):
        return "none"
    return "default"


def compiler_missing(device: torch.device) -> str | None:
    """What ``torch.compile`` needs to compile the update on ``device`` and cannot find, in
    words; None where it is there. On the CPU, the C++ compiler Inductor calls (``$CXX``, else
    g++; clang++ on macOS); on a GPU, Triton (torch's CUDA builds carry it) and the C compiler it
    builds its launchers with (``$CC``, else gcc); on both, Python's C headers, which those
    include (Debian's python3-dev)."""
    if device.type == "cuda":
        if not importlib.util.find_spec("triton"):
            return "Triton"
        name, what = os.environ.get("CC") or "gcc", "a C compiler ({}, or $CC)"
    else:
        name = os.environ.get("CXX") or ("clang++" if sys.platform == "darwin" else "g++")
        what = "a C++ compiler ({}, or $CXX)"
    if not shutil.which(name):
        return what.format(name)
    if not (Path(sysconfig.get_paths()["include"]) / "Python.h").is_file():
        return "Python's C headers (Python.h; Debian's python3-dev)"
    return None
