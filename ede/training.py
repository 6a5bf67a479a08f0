"""One training run of TD3 or EDE-TD3: the environment loop, evaluation, checkpoints, outputs.

A run is determined by its task, algorithm, seed, budget, params and (for EDE-TD3) embedding. It
writes, into its directory:

* ``eval.csv``: ``step, episode, mean_return, std_return, wall_seconds`` after every evaluation;
* ``run.json``: what made the run — its identity (task, algo, seed, budget, the params that
  change its result, the embedding's checksum) and the versions of the software;
* ``diagnostics.csv``: ``step, updates, critic_loss, actor_loss, mean_q``, the means over the
  updates since the previous evaluation (mean_q: Q_1(s, μ(s), 0) on the actor's batches);
* ``metrics.json``: final and best return, area under the curve, steps per second, episodes;
  written last, so a run with ``metrics.json`` is complete;
* ``policy/``: the final actor as safetensors beside its JSON metadata;
* ``checkpoint/`` while it runs: everything needed to continue exactly (networks, optimisers,
  replay buffer, generator states, counters, the evaluation history, and the current episode as
  its start plus the actions taken since, replayed on resume). A run started where a checkpoint of
  the same configuration exists continues from it; on CPU a run killed at any point and resumed
  ends with the same ``eval.csv`` returns as an uninterrupted one.
"""

from __future__ import annotations

import csv
import functools
import hashlib
import io
import json
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

import gymnasium
import numpy as np
import torch
from safetensors.torch import load_file, save_file

from ede.atomic import remove_stale_temporaries, sha256, write_atomically, write_json, write_text
from ede.config import EdeTD3Config, TD3Config
from ede.embedding import ActionEmbedding
from ede.group import GroupAgent
from ede.nets import flush_denormals
from ede.provenance import software_versions
from ede.stats import area_under_curve
from ede.tasks import make
from ede.td3 import (
    ActionAdapter,
    Agent,
    CodeExecutor,
    EmbeddingAdapter,
    IdentityAdapter,
    ReplayBatch,
    ReplayBuffer,
)

__all__ = ["CheckpointError", "CheckpointWriteError", "RunSpec", "evaluate", "train_group",
           "train_run"]

CHECKSUMS = "checksums.json"


class CheckpointError(Exception):
    """A checkpoint that cannot be used: unreadable, damaged, or another run's."""


class CheckpointWriteError(Exception):
    """A checkpoint could not be written (a full disk, ...); the previous one is intact."""


CHECKPOINT_VERSION = 3  # 2: training diagnostics; 3: checksums, the run's identity
EVAL_SEED_OFFSET = 1_000_003  # evaluation episodes are seeded apart from training ones
EVAL_COLUMNS = ("step", "episode", "mean_return", "std_return", "wall_seconds")
DIAGNOSTIC_COLUMNS = ("step", "updates", "critic_loss", "actor_loss", "mean_q")
RESOURCES = {"threads", "device", "checkpoint_every"}  # td3 settings that leave results alone


@dataclass(frozen=True)
class RunSpec:
    """What determines a run."""

    task: str
    algo: str  # "td3" or "ede-td3"
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
                "td3": self.td3.model_dump(mode="json", exclude=RESOURCES),
                "ede_td3": self.ede_td3.model_dump(mode="json"),
            },
            "embedding": self.embedding_id,
        }

    def fingerprint(self) -> str:
        return hashlib.sha256(json.dumps(self.identity(), sort_keys=True).encode()).hexdigest()


def evaluate(
    env: gymnasium.Env, agent: Agent | _Actor, adapter: ActionAdapter, episodes: int, seed: int
) -> np.ndarray:
    """Returns of ``episodes`` deterministic episodes; episode e starts from ``reset(seed + e)``."""
    executor, policy = CodeExecutor(env, adapter), functools.partial(agent.act, explore=False)
    returns = np.zeros(episodes)
    for e in range(episodes):
        obs, _ = env.reset(seed=seed + e)
        for step in executor.episode(obs, policy):
            returns[e] += step.reward
    return returns


class _Actor(Protocol):
    def act(self, obs: np.ndarray, explore: bool) -> torch.Tensor: ...


@dataclass
class _Member:
    """Member j of a group, acting as its agent alone would (``GroupAgent.act``)."""

    group: GroupAgent
    j: int

    def act(self, obs: np.ndarray, explore: bool) -> torch.Tensor:
        return self.group.act(self.j, obs, explore)


@dataclass
class _Episode:
    """The training episode under way, and how to rebuild it: its start and its actions."""

    start: dict[str, Any]  # {"seed": s} for the first episode, else {"rng": bit generator state}
    actions: list[np.ndarray] = field(default_factory=list)
    ret: float = 0.0


def _reset(env: gymnasium.Env, seed: int | None) -> tuple[np.ndarray, _Episode]:
    if seed is not None:
        start: dict[str, Any] = {"seed": seed}
        obs, _ = env.reset(seed=seed)
    else:
        start = {"rng": env.unwrapped.np_random.bit_generator.state}
        obs, _ = env.reset()
    return obs, _Episode(start)


def _replay(env: gymnasium.Env, episode: _Episode) -> np.ndarray:
    """Rebuild the environment's state: the same reset, then the same actions."""
    if "seed" in episode.start:
        obs, _ = env.reset(seed=episode.start["seed"])
    else:
        env.unwrapped.np_random.bit_generator.state = episode.start["rng"]
        obs, _ = env.reset()
    for action in episode.actions:
        obs, *_ = env.step(action)
    return obs


def _csv(rows: list[dict[str, float]], columns: tuple[str, ...] = EVAL_COLUMNS) -> str:
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=columns, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return out.getvalue()


class _Run:
    """The mutable state of a run, and its checkpoint."""

    def __init__(self, spec: RunSpec, embedding: ActionEmbedding | None, device: torch.device):
        self.spec = spec
        self.env = make(spec.task)
        self.eval_env = make(spec.task)
        space = self.env.action_space
        assert isinstance(space, gymnasium.spaces.Box)
        obs_size = int(np.prod(self.env.observation_space.shape))
        if spec.algo == "td3":
            self.adapter: ActionAdapter = IdentityAdapter(
                space.low, space.high, device, spec.td3.noise_units
            )
        else:
            assert embedding is not None
            ede = spec.ede_td3
            self.adapter = EmbeddingAdapter(
                embedding, ede.bound_scale, ede.target_noise_scale, ede.target_noise_clip,
                ede.plan_step_input,
            )
        self.agent = Agent(obs_size, self.adapter, spec.td3, device, spec.seed)
        self.actor: Agent | _Actor = self.agent  # who acts: the agent, or its seat in a group
        capacity = min(spec.td3.buffer_size, spec.budget)
        self.buffer = ReplayBuffer(capacity, obs_size, self.adapter.code_size, self.adapter.k, device)
        self.executor = CodeExecutor(self.env, self.adapter)
        self.step = 0
        self.episodes = 0
        self.history: list[dict[str, float]] = []
        self.diagnostics: list[dict[str, float]] = []  # training's means between evaluations
        self.wall = 0.0  # seconds spent, over every session of this run
        self.obs, self.episode = _reset(self.env, spec.seed)

    # Checkpoints ---------------------------------------------------------------------------

    def save(self, path: Path) -> None:
        tensors: dict[str, torch.Tensor] = {}
        for name, module in self.agent.modules().items():
            for key, value in module.state_dict().items():
                tensors[f"{name}.{key}"] = value
        for name, optimizer in self.agent.optimizers().items():
            for index, state in optimizer.state_dict()["state"].items():
                for key, value in state.items():
                    tensors[f"{name}.{index}.{key}"] = value
        buffer_tensors, buffer_counters = self.buffer.state()
        tensors |= {f"buffer.{key}": value for key, value in buffer_tensors.items()}
        tensors["generator"] = self.agent.generator.get_state()
        plan = self.executor.plan
        tensors["code"] = self.executor.code
        tensors["plan"] = torch.as_tensor(plan)
        tensors["episode_actions"] = torch.as_tensor(
            np.array(self.episode.actions, dtype=plan.dtype).reshape(-1, plan.shape[1])
        )
        tensors["obs"] = torch.as_tensor(np.asarray(self.obs))
        tensors["loss_sums"] = self.agent.loss_sums
        state = {
            "version": CHECKPOINT_VERSION,
            "fingerprint": self.spec.fingerprint(),
            "identity": self.spec.identity(),
            "step": self.step,
            "episodes": self.episodes,
            "i": self.executor.i,
            "updates": self.agent.updates,
            "wall_seconds": self.wall,
            "buffer": buffer_counters,
            "episode_start": self.episode.start,
            "episode_return": self.episode.ret,
            "history": self.history,
            "diagnostics": self.diagnostics,
        }

        def write(tmp: Path) -> None:
            save_file({k: v.detach().cpu().clone() for k, v in tensors.items()},
                      tmp / "state.safetensors")
            (tmp / "state.json").write_text(json.dumps(state))
            sums = {name: sha256(tmp / name) for name in ("state.safetensors", "state.json")}
            (tmp / CHECKSUMS).write_text(json.dumps(sums))

        write_atomically(path, write)

    def load(self, path: Path) -> bool:
        """Continue from the checkpoint at ``path``; False where there is none.

        Raises:
            CheckpointError: it cannot be used — a file missing, damaged or changed (its checksum),
                an older format, another run's (another seed, task, params or embedding), or a
                state its episode's replay does not reach. This run's state may then be partly
                overwritten: the caller starts from a fresh run.
        """
        if not path.exists():
            return False
        state = _verified_state(path)
        if state.get("version") != CHECKPOINT_VERSION:
            raise CheckpointError(f"format version {state.get('version')}, this version reads "
                                  f"{CHECKPOINT_VERSION}")
        if state.get("fingerprint") != self.spec.fingerprint():
            raise CheckpointError(f"another run's: {_difference(state.get('identity'), self.spec)}")
        try:
            self._restore(path, state)
        except Exception as error:  # noqa: BLE001 — whatever is wrong, the run must restart
            raise CheckpointError(f"not restorable ({_first_line(error)})") from None
        return True

    def _restore(self, path: Path, state: dict[str, Any]) -> None:
        tensors = load_file(path / "state.safetensors", device=str(self.agent.device))
        for name, module in self.agent.modules().items():
            module.load_state_dict({k.removeprefix(f"{name}."): v for k, v in tensors.items()
                                    if k.startswith(f"{name}.")})
        for name, optimizer in self.agent.optimizers().items():
            saved = optimizer.state_dict()
            per_param: dict[int, dict[str, torch.Tensor]] = {}
            for key, value in tensors.items():
                parts = key.split(".")
                if parts[0] == name:
                    per_param.setdefault(int(parts[1]), {})[parts[2]] = value
            saved["state"] = per_param
            optimizer.load_state_dict(saved)
        self.buffer.load({k.removeprefix("buffer."): v for k, v in tensors.items()
                          if k.startswith("buffer.")}, state["buffer"])
        self.agent.generator.set_state(tensors["generator"].cpu())
        self.agent.updates = state["updates"]
        self.executor.code = tensors["code"]
        self.executor.plan = tensors["plan"].cpu().numpy()
        self.executor.i = state["i"]
        self.step, self.episodes = state["step"], state["episodes"]
        self.wall, self.history = state["wall_seconds"], state["history"]
        self.diagnostics = state["diagnostics"]
        self.agent.loss_sums.copy_(tensors["loss_sums"])
        self.episode = _Episode(
            state["episode_start"], list(tensors["episode_actions"].cpu().numpy()),
            state["episode_return"],
        )
        self.obs = _replay(self.env, self.episode)
        if not np.array_equal(self.obs, tensors["obs"].cpu().numpy()):
            raise RuntimeError("replaying the episode did not reach the saved state")


    # The loop ------------------------------------------------------------------------------

    def evaluate(self) -> dict[str, float]:
        returns = evaluate(self.eval_env, self.actor, self.adapter, self.spec.td3.eval_episodes,
                           EVAL_SEED_OFFSET * (self.spec.seed + 1))
        row = {"step": self.step, "episode": self.episodes, "mean_return": float(returns.mean()),
               "std_return": float(returns.std()), "wall_seconds": round(self.wall, 3)}
        self.history.append(row)
        trained = self.agent.take_diagnostics()
        if trained["updates"]:
            self.diagnostics.append({"step": self.step, **trained})
        return row

    def _behaviour(self, obs: np.ndarray) -> torch.Tensor:
        """The code training acts with: uniform for ``td3.start_steps`` steps, then μ(s) + noise."""
        if self.step < self.spec.td3.start_steps:
            return self.agent.random_code()
        return self.actor.act(obs, explore=True)

    def env_step(self, update: bool = True) -> int:
        """One environment step and its updates (Section 3: learn from every step).

        With ``td3.update_schedule: step``, one update after the step; with ``episode``, none
        until the episode ends, then one per step of it. With ``update=False`` the updates are
        left to the caller (a group updates its members together).

        Returns:
            The number of updates due after this step.
        """
        config = self.spec.td3
        step = self.executor.step(self.obs, self._behaviour)
        self.buffer.add(self.obs, step.code, step.i, step.reward, step.next_obs, step.terminated,
                        step.truncated)
        self.episode.actions.append(step.action)
        self.episode.ret += step.reward
        self.step += 1
        updates = 1 if config.update_schedule == "step" else 0
        if step.ended:
            if config.update_schedule == "episode":
                updates = len(self.episode.actions)  # one per step of the episode just ended
            self.episodes += 1
            self.obs, self.episode = _reset(self.env, None)
        else:
            self.obs = step.next_obs
        if self.step < config.start_steps or self.buffer.sampleable < config.batch_size:
            return 0
        if update:
            self.update(updates)
        return updates

    def update(self, times: int) -> None:
        """``times`` updates of this run's own agent, each on a batch sampled for it."""
        for _ in range(times):
            self.agent.update(self.sample())

    def sample(self) -> ReplayBatch:
        return self.buffer.sample(self.spec.td3.batch_size, self.agent.generator)


def _first_line(error: BaseException) -> str:
    return (str(error).strip().splitlines() or [type(error).__name__])[0]


def _verified_state(path: Path) -> dict[str, Any]:
    """``state.json`` of a checkpoint whose files all match their checksums."""
    try:
        sums = json.loads((path / CHECKSUMS).read_text())
        for name in ("state.safetensors", "state.json"):
            if sha256(path / name) != sums[name]:
                raise CheckpointError(f"{name} does not match its checksum (damaged or changed)")
        return json.loads((path / "state.json").read_text())
    except CheckpointError:
        raise
    except FileNotFoundError as error:
        raise CheckpointError(f"{Path(error.filename).name} is missing") from None
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise CheckpointError(f"not readable ({_first_line(error)})") from None


def _difference(identity: Any, spec: RunSpec) -> str:
    """What tells another run's checkpoint from this run: the first identity key that differs."""
    if not isinstance(identity, dict):
        return "its identity is not recorded"
    for key, value in spec.identity().items():
        if identity.get(key) != value:
            if key == "params":
                return "made with other params"
            if key == "embedding":
                return "made with another embedding"
            return f"{key} {identity.get(key)}, not {value}"
    return "made by another configuration"


def _write_curves(out: Path, run: _Run) -> None:
    write_text(out / "diagnostics.csv", _csv(run.diagnostics, DIAGNOSTIC_COLUMNS))
    write_text(out / "eval.csv", _csv(run.history))


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
    return train_group([spec], [out], embedding, device, progress, keep_checkpoint,
                       bad_checkpoint, notice)[0]


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
    ``out``, in one process: their environments stepped in turn, their updates as one
    (:class:`ede.group.GroupAgent`). Each member's outputs are those it gets alone. With
    ``td3.update_schedule: episode`` the members' episodes end together on tasks that never end
    early (all of the paper's), and their per-episode batches are one; where episodes end at
    different steps, the group dissolves and its members go on one by one, still exactly.
    CPU arithmetic flushes subnormal numbers to zero throughout (:func:`ede.nets.flush_denormals`).

    Each resumes from its ``out/checkpoint`` when there is one; members that resume from
    earlier steps than others first catch up alone. A checkpoint that cannot be used
    (:meth:`_Run.load`) is reported through ``notice`` and moved aside to
    ``out/checkpoint.bad-<time>``, and that run starts over; with ``bad_checkpoint="refuse"``
    it raises :class:`CheckpointError` instead, touching nothing.

    Returns:
        Each member's metrics, as written to its ``metrics.json``.

    Raises:
        CheckpointError: a bad checkpoint under "refuse".
        CheckpointWriteError: a checkpoint could not be written; the previous one is kept.
    """
    spec = specs[0]
    if spec.algo not in ("td3", "ede-td3"):
        raise ValueError(f"unknown algorithm {spec.algo!r}; expected td3 or ede-td3")
    if spec.algo == "ede-td3" and embedding is None:
        raise ValueError("ede-td3 needs the family's action embedding")
    alike = all(replace(s, seed=0) == replace(spec, seed=0) for s in specs)
    if not alike or len({s.seed for s in specs}) != len(specs):
        raise ValueError("a group's runs must differ in their seeds only")
    sessions = [_Session.start(s, out, embedding, device, bad_checkpoint, notice)
                for s, out in zip(specs, outs)]
    if progress is not None:
        progress(sum(session.run.step for session in sessions))
    ahead = max(session.run.step for session in sessions)
    for session in sessions:  # members resumed from earlier checkpoints catch up alone
        while session.run.step < ahead:
            session.run.env_step()
            session.after_step(progress)
    group = None
    if len({session.run.agent.updates for session in sessions}) > 1:  # dissolved before
        notice("the members have updated different numbers of times: they go on one by one")
    elif len(sessions) > 1:
        group = GroupAgent([s.run.agent for s in sessions])
    if group is not None:
        for j, session in enumerate(sessions):
            session.run.actor = _Member(group, j)
            session.group = group
    runs = [session.run for session in sessions]
    while runs[0].step < spec.budget:
        due = [run.env_step(update=group is None) for run in runs]
        if group is not None and len(set(due)) > 1:
            # Per-episode batches of episodes that ended at different steps (a task that can end
            # early): the members cannot update as one any more, so they go on one by one.
            notice("episodes of different lengths: the group's members go on one by one")
            _dissolve(group, sessions)
            group = None
            for run, updates in zip(runs, due):
                run.update(updates)
        elif group is not None:
            for _ in range(due[0]):
                group.update([run.sample() for run in runs])
        for session in sessions:
            session.after_step(progress)
    if group is not None:
        group.sync()
    return [session.finish(keep_checkpoint) for session in sessions]


def _dissolve(group: GroupAgent, sessions: list[_Session]) -> None:
    """Hand each member's state back to its own agent, which acts and updates from now on."""
    group.sync()
    for session in sessions:
        session.run.actor = session.run.agent
        session.group = None


@dataclass
class _Session:
    """One run of a group in this process: its run, outputs, and wall clock."""

    run: _Run
    out: Path
    resumed: bool
    started: float = field(default_factory=time.perf_counter)
    steps_at_start: int = 0
    wall_at_start: float = 0.0
    group: GroupAgent | None = None

    @classmethod
    def start(cls, spec: RunSpec, out: Path, embedding: ActionEmbedding | None,
              device: torch.device, bad_checkpoint: str, notice: Callable[[str], None]) -> _Session:
        out.mkdir(parents=True, exist_ok=True)
        checkpoint = out / "checkpoint"
        run = _Run(spec, embedding, device)
        try:
            resumed = run.load(checkpoint)
        except CheckpointError as error:
            if bad_checkpoint == "refuse":
                raise CheckpointError(f"{checkpoint}: {error}") from None
            aside = _move_aside(checkpoint)
            notice(f"{checkpoint}: {error}; moved aside to {aside.name}, starting over")
            run, resumed = _Run(spec, embedding, device), False
        session = cls(run, out, resumed, steps_at_start=run.step, wall_at_start=run.wall)
        if not run.history:
            run.evaluate()
            _write_curves(out, run)
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
            _write_curves(self.out, run)
        if run.step % config.checkpoint_every == 0 and run.step < run.spec.budget:
            self.clock()
            if self.group is not None:
                self.group.sync()
            checkpoint = self.out / "checkpoint"
            try:
                run.save(checkpoint)
            except OSError as error:
                raise CheckpointWriteError(f"{checkpoint}: not written ({error.strerror or error}); "
                                           "the previous checkpoint is kept") from None

    def finish(self, keep_checkpoint: bool) -> dict[str, Any]:
        """The run's final outputs; ``metrics.json`` last."""
        run, out, spec = self.run, self.out, self.run.spec
        self.clock()
        _write_curves(out, run)
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
        save_policy(out / "policy", run.agent, spec, run.adapter)
        write_json(out / "run.json", {**spec.identity(), "software": software_versions()})
        write_json(out / "metrics.json", metrics)  # last: a run with metrics.json is complete
        checkpoint = out / "checkpoint"
        if not keep_checkpoint:
            shutil.rmtree(checkpoint, ignore_errors=True)
        remove_stale_temporaries(checkpoint)  # a killed session's half-written checkpoint
        return metrics


def _move_aside(checkpoint: Path) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    aside = checkpoint.with_name(f"{checkpoint.name}.bad-{stamp}")
    n = 1
    while aside.exists():
        n += 1
        aside = checkpoint.with_name(f"{checkpoint.name}.bad-{stamp}-{n}")
    checkpoint.rename(aside)
    return aside


def save_policy(path: Path, agent: Agent, spec: RunSpec, adapter: ActionAdapter) -> None:
    """The final actor: ``policy.safetensors`` beside ``policy.json``."""

    def write(tmp: Path) -> None:
        state = {k: v.detach().cpu().contiguous() for k, v in agent.actor.state_dict().items()}
        save_file(state, tmp / "policy.safetensors")
        meta = {
            **spec.identity(),
            "k": adapter.k,
            "code_size": adapter.code_size,
            "code_low": adapter.code_low.tolist(),
            "code_high": adapter.code_high.tolist(),
            "hidden": spec.td3.hidden,
        }
        write_json(tmp / "policy.json", meta)

    write_atomically(path, write)
