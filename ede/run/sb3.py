"""Stable-baselines3's agents as runs of the pipeline (``runs.algos``: sb3-td3-ede, sb3-sac-ede,
sb3-sac; docs/any-agent.md).

SB3's TD3 and SAC act in the family's EDE space through :class:`ede.run.embedded.EmbeddedActions`
(a code every k steps, one k-step transition a code: the naive agent EDE-TD3's every-step critic
is measured against), and SB3's SAC on raw actions. Each is a run like every other: its folder in
the format of :mod:`ede.run.runs`, evaluated as TD3 and EDE-TD3 are
(:func:`ede.run.evaluation.evaluate`, the same seeds and episodes), its steps counted in raw
environment steps. The loop is this module's, over SB3's own pieces (``_sample_action``,
``_store_transition``, ``train``), so that it evaluates and checkpoints at raw steps:

* a row of ``eval.csv`` at step B (each multiple of ``td3.eval_every``, and the budget) is the
  policy after the code that reaches or crosses B and the updates that code made due; the run's
  last code is cut at the budget (a truncation), so a run takes exactly its budget of raw steps;
* updates follow ``td3.update_schedule`` in raw steps, as EDE-TD3's: one per raw step a code ran
  (``step``: after each code, as many as its steps; ``episode``: at an episode's end, as many as
  its steps), none while ``td3.start_steps`` last or fewer transitions than a batch are stored;
* a checkpoint (after the code that reaches or crosses each multiple of ``td3.checkpoint_every``)
  holds no pickle: SB3's ``get_parameters`` and SAC's ``log_ent_coef`` as tensors beside their
  structure, the replay buffer's arrays, the counters, every random generator SB3 and the
  environment draw from, and the episode under way as its start and raw actions, replayed on
  resuming (:class:`ede.run.vector.Episode`). A run killed and resumed ends with the same
  ``eval.csv`` returns as an uninterrupted one on CPU.
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from importlib.metadata import version
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import torch
from stable_baselines3 import SAC, TD3
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.noise import NormalActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm

from ede.config import EMBEDDED_ALGOS, SB3_ALGOS
from ede.io.atomic import claim, remove_stale_temporaries
from ede.method.adapters import ActionAdapter, EmbeddingAdapter, IdentityAdapter
from ede.method.embedding import ActionEmbedding
from ede.run import sb3_state
from ede.run.checkpoint import CheckpointError
from ede.run.embedded import EmbeddedActions
from ede.run.evaluation import EVAL_SEED_OFFSET, evaluate
from ede.run.runs import POLICY, RUN_KIND, RUN_OWNS, write_curves, write_finished, write_policy
from ede.run.spec import RunSpec
from ede.run.training import Diverged, move_aside, run_metrics
from ede.run.vector import Episode, MemberEnvs
from ede.tasks import make

__all__ = ["train_sb3"]


def train_sb3(
    spec: RunSpec,
    out: Path,
    embedding: ActionEmbedding | None = None,
    progress: Callable[[int], None] | None = None,
    keep_checkpoint: bool = False,
    bad_checkpoint: str = "restart",
    notice: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Train ``spec``'s run (an algorithm of :data:`ede.config.SB3_ALGOS`) into ``out`` on CPU,
    resuming from ``out/checkpoint`` where there is one; a checkpoint that cannot be used is
    moved aside (``notice`` says so) or, with ``bad_checkpoint="refuse"``, refused.

    Returns:
        The metrics written to ``metrics.json``.

    Raises:
        CheckpointError: a bad checkpoint under "refuse".
        CheckpointWriteError: a checkpoint could not be written; the previous one is kept.
        Diverged: the actor, an update or an evaluation met numbers that are not finite; the
            last checkpoint is kept.
    """
    if spec.algo not in SB3_ALGOS:
        raise ValueError(f"{spec.algo!r} is not one of stable-baselines3's algorithms")
    if (spec.algo in EMBEDDED_ALGOS) != (embedding is not None):
        raise ValueError(f"{spec.algo} acts in the family's embedding: give it one, or none")
    claim(out, RUN_KIND, RUN_OWNS)
    path = out / "checkpoint"
    run = _Run(spec, embedding)
    try:
        run.resume(path)
    except CheckpointError as error:
        if bad_checkpoint == "refuse":
            run.close()
            raise CheckpointError(f"{path}: {error}") from None
        aside = move_aside(path)
        notice(f"{path}: {error}; moved aside to {aside.name}, starting over")
        run.close()  # its model may be half restored: a fresh one starts over
        run = _Run(spec, embedding)
    try:
        return run.train(out, progress, keep_checkpoint)
    finally:
        run.close()


class _Steps(gymnasium.Wrapper):
    """The task as the agent's environment sees it: counts the run's raw steps, keeps the
    episode under way (its start and actions, :class:`Episode`), and truncates the step that
    reaches the run's budget (``info["budget"]``), so that the last code stops there."""

    def __init__(self, env: gymnasium.Env, budget: int) -> None:
        super().__init__(env)
        self.budget, self.steps, self.episode = budget, 0, Episode({})

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> Any:
        rng = self.env.unwrapped.np_random.bit_generator.state
        self.episode = Episode({"seed": seed} if seed is not None else {"rng": rng})
        return self.env.reset(seed=seed, options=options)

    def step(self, action: Any) -> tuple[Any, Any, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.steps += 1
        self.episode.actions.append(np.array(action))
        self.episode.ret += float(reward)
        if self.steps >= self.budget and not (terminated or truncated):
            truncated, info = True, {**info, "budget": True}
        return obs, reward, terminated, truncated, info


class _Run:
    """One SB3 run in this process: its agent, environments, counters and history."""

    def __init__(self, spec: RunSpec, embedding: ActionEmbedding | None) -> None:
        self.spec, td3 = spec, spec.td3
        self.steps = _Steps(make(spec.task), spec.budget)
        self.env: gymnasium.Env = self.steps
        self.adapter: ActionAdapter
        if embedding is not None:
            ede = spec.ede_td3
            wrapped = EmbeddedActions(self.steps, embedding, td3.discount, ede.bound_scale)
            self.env, self.k = wrapped, wrapped.k
            self.adapter = EmbeddingAdapter(
                embedding, ede.bound_scale, ede.target_noise_scale, ede.target_noise_clip
            )
        else:
            space = self.steps.action_space
            assert isinstance(space, gymnasium.spaces.Box)  # ede.tasks.unusable refuses others
            self.adapter, self.k = IdentityAdapter(space.low, space.high, torch.device("cpu")), 1
        self.model = _model(spec, self.env, self.adapter, self.k)
        self.model.set_logger(Logger(folder=None, output_formats=[]))
        obs, _ = self.env.reset(seed=spec.seed)  # later episodes: from the env's own generator
        self.model._last_obs = obs[None]
        self.eval_envs = MemberEnvs.of_task(spec.task, 1)
        self.episodes, self.wall, self.resumed_from = 0, 0.0, 0
        self.history: list[dict[str, float]] = []
        self.diagnostics: list[dict[str, float]] = []
        self.sums = {"updates": 0.0, "critic": 0.0, "actor": 0.0, "actor_updates": 0.0}

    def close(self) -> None:
        self.env.close()
        self.eval_envs.close()

    def train(
        self, out: Path, progress: Callable[[int], None] | None, keep_checkpoint: bool
    ) -> dict[str, Any]:
        """Step codes until the budget, evaluating and checkpointing at raw steps; the outputs."""
        spec, td3, started = self.spec, self.spec.td3, time.perf_counter()
        wall_at_start, start = self.wall, self.steps.steps
        if progress is not None:
            progress(start)
        if not self.history:
            self._evaluate(0)
            write_curves(out, self.history, self.diagnostics)
        while (before := self.steps.steps) < spec.budget:
            self._code()
            now = self.steps.steps
            if progress is not None:
                progress(now - before)
            self.wall = wall_at_start + time.perf_counter() - started
            due = _crossed(before, now, td3.eval_every)
            due += [now] if now == spec.budget and now not in due else []
            for boundary in due:
                self._evaluate(boundary)
            if due:
                write_curves(out, self.history, self.diagnostics)
            if now < spec.budget and _crossed(before, now, td3.checkpoint_every):
                self.save(out / "checkpoint")
        now = self.steps.steps
        self.wall = wall_at_start + time.perf_counter() - started
        seconds = time.perf_counter() - started
        metrics = run_metrics(
            self.history, self.episodes, now, now - start, seconds, self.wall,
            start if self.resumed_from else None,
        )  # fmt: skip
        actor = self.model.actor.state_dict()
        write_policy(out / POLICY, actor, self._policy_meta())
        sb3 = {"stable-baselines3": version("stable-baselines3")}
        write_finished(out, spec, metrics, torch.device("cpu"), sb3)
        if not keep_checkpoint:
            shutil.rmtree(out / "checkpoint", ignore_errors=True)
        remove_stale_temporaries(out / "checkpoint")
        return metrics

    def _code(self) -> None:
        """One step of the agent (a code, or a raw action), stored, and the updates it makes due."""
        model, td3 = self.model, self.spec.td3
        warm = self.steps.steps < td3.start_steps  # uniform codes for the start steps
        actor = f"the actor's {'code' if self.spec.algo in EMBEDDED_ALGOS else 'action'}"
        with self._finite(self.steps.steps + 1, actor):
            action, buffer_action = model._sample_action(
                model.num_timesteps + 1 if warm else 0, model.action_noise
            )
        if not np.isfinite(action).all():  # the wrapper and the tasks refuse such actions
            self._diverged(self.steps.steps + 1, actor)
        obs, reward, terminated, truncated, info = self.env.step(action[0])
        model.num_timesteps += 1
        ran = int(info.get("steps", 1))
        done = terminated or truncated
        episode_steps = len(self.steps.episode.actions)
        new_obs = obs
        if done:
            model._episode_num += 1
            if not info.get("budget"):
                self.episodes += 1
            if self.steps.steps < self.spec.budget:
                new_obs, _ = self.env.reset()
        timeout = truncated and not terminated
        infos = [{"terminal_observation": obs, "TimeLimit.truncated": timeout} if done else {}]
        assert model.replay_buffer is not None
        model._store_transition(
            model.replay_buffer, buffer_action, new_obs[None],
            np.array([reward], dtype=np.float32), np.array([done]), infos,
        )  # fmt: skip
        if td3.update_schedule == "step":
            self._update(ran)
        elif done and not info.get("budget"):
            self._update(episode_steps)

    def _update(self, steps: int) -> None:
        """``steps`` gradient updates, one per raw step (none before the start steps end or a
        batch can be drawn); their losses into the diagnostics' sums."""
        model, td3 = self.model, self.spec.td3
        buffer = model.replay_buffer
        assert buffer is not None
        if self.steps.steps < td3.start_steps or buffer.size() < td3.batch_size or not steps:
            return
        with self._finite(self.steps.steps, "an update's numbers"):
            model.train(gradient_steps=steps, batch_size=td3.batch_size)
        values = model.logger.name_to_value
        self.sums["updates"] += steps
        self.sums["critic"] += steps * values["train/critic_loss"]
        if "train/actor_loss" in values:
            self.sums["actor"] += steps * values["train/actor_loss"]
            self.sums["actor_updates"] += steps
        model.logger.dump()  # clears what it recorded

    def _evaluate(self, step: int) -> None:
        """The deterministic policy's ``td3.eval_episodes`` episodes, as every run's: a row of
        ``eval.csv`` at ``step``, and of ``diagnostics.csv`` if it has updated since."""
        spec, model = self.spec, self.model

        def policy(obs: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(model.predict(obs, deterministic=True)[0], dtype=torch.float32)

        seeds = [EVAL_SEED_OFFSET * (spec.seed + 1)]
        with self._finite(step, "the evaluation's actor"):
            episodes = spec.td3.eval_episodes
            returns = evaluate(self.eval_envs, policy, self.adapter, episodes, seeds)[0]
        if not np.isfinite(returns).all():
            self._diverged(step, "the evaluation's return")
        self.history.append(
            {
                "step": step,
                "episode": self.episodes,
                "mean_return": float(returns.mean()),
                "std_return": float(returns.std()),
                "wall_seconds": round(self.wall, 3),
            }
        )
        sums = self.sums
        if sums["updates"]:
            actor = sums["actor"] / sums["actor_updates"] if sums["actor_updates"] else np.nan
            self.diagnostics.append(
                {
                    "step": step,
                    "updates": int(sums["updates"]),
                    "critic_loss": sums["critic"] / sums["updates"],
                    "actor_loss": actor,
                    "mean_q": np.nan,  # SB3 does not report it
                }
            )
            self.sums = dict.fromkeys(sums, 0.0)

    @contextmanager
    def _finite(self, step: int, quantity: str) -> Iterator[None]:
        """Stop the run where SB3 meets numbers that are not finite: torch's distributions
        (SAC's) refuse them with a ValueError."""
        try:
            yield
        except ValueError as error:
            if "invalid values" not in str(error):
                raise
            self._diverged(step, quantity)

    def _diverged(self, step: int, quantity: str) -> None:
        """Stop the run: its numbers are no longer finite (its last checkpoint is kept)."""
        spec = self.spec
        raise Diverged(
            f"{spec.task} {spec.algo} seed {spec.seed}: diverged at step {step}: {quantity} is "
            "not finite; stopped there, no metrics.json written"
        )

    def _policy_meta(self) -> dict[str, Any]:
        adapter = self.adapter
        return {
            **self.spec.identity(),
            "k": self.k,
            "code_size": adapter.code_size,
            "code_low": adapter.code_low.tolist(),
            "code_high": adapter.code_high.tolist(),
            "hidden": self.spec.td3.hidden,
            "format": f"stable-baselines3 {version('stable-baselines3')} "
            f"{type(self.model).__name__} actor (model.actor.state_dict())",
        }

    # Checkpoints ---------------------------------------------------------------------------

    def save(self, path: Path) -> None:
        """This run's checkpoint (:mod:`ede.run.sb3_state`), no pickle in it."""
        run = {
            "episodes": self.episodes,
            "history": self.history,
            "diagnostics": self.diagnostics,
            "sums": self.sums,
            "wall_seconds": self.wall,
        }
        sb3_state.write(path, self.spec, self.model, self.steps.steps, self.steps.episode, run)

    def resume(self, path: Path) -> None:
        """Continue from the checkpoint at ``path`` (none: start afresh).

        Raises:
            CheckpointError: it cannot be used (damaged, another run's, another format, not
                restorable); the caller starts the run over with a fresh :class:`_Run`.
        """
        if not path.exists():
            return
        state, tensors = sb3_state.read(path, self.spec)
        episode, run = sb3_state.restore(state, tensors, self.model, self.steps.env)
        self.steps.episode, self.steps.steps = episode, int(state["step"])
        self.episodes, self.wall, self.sums = run["episodes"], run["wall_seconds"], run["sums"]
        self.history, self.diagnostics = run["history"], run["diagnostics"]
        self.resumed_from = self.steps.steps


def _model(spec: RunSpec, env: gymnasium.Env, adapter: ActionAdapter, k: int) -> OffPolicyAlgorithm:
    """SB3's agent with the paper's networks and learning rates (docs/any-agent.md's table): in
    the EDE space its discount is γ^k (the wrapper's rewards are discounted sums), TD3's noises
    in SB3's [-1, 1] units are EDE-TD3's in code units over the bound."""
    td3 = spec.td3
    common: dict[str, Any] = {
        "learning_rate": td3.lr,
        "buffer_size": min(td3.buffer_size, spec.budget),
        "learning_starts": 0,  # this module's loop decides (td3.start_steps, in raw steps)
        "batch_size": td3.batch_size,
        "tau": td3.tau,
        "gamma": td3.discount**k,
        "policy_kwargs": {"net_arch": list(td3.hidden)},
        "seed": spec.seed,
        "device": "cpu",
    }
    if spec.algo == "sb3-td3-ede":
        half = float(adapter.code_high[0])  # SB3's [-1, 1] is the code box [-b, b]
        size = adapter.code_size
        noise = td3.exploration_noise * float(adapter.noise_scale[0]) / half
        return TD3(
            "MlpPolicy", env, **common,
            action_noise=NormalActionNoise(np.zeros(size), np.full(size, noise)),
            policy_delay=td3.policy_delay,
            target_policy_noise=td3.policy_noise * adapter.target_noise_scale
            * float(adapter.noise_scale[0]) / half,
            target_noise_clip=td3.noise_clip * float(adapter.clip_scale[0]) / half,
        )  # fmt: skip
    return SAC("MlpPolicy", env, **common)


def _crossed(before: int, now: int, every: int) -> list[int]:
    """The multiples of ``every`` in (before, now]."""
    return list(range((before // every + 1) * every, now + 1, every))
