"""What the report and the results page measure by running the environments themselves: the
reference returns of every task (uniform random actions', the normalised scores' 0, and zero
actions'), and the numbers of the paper's Figures 6 and 7 (:mod:`ede.analysis.figures` draws them)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import gymnasium
import numpy as np
import torch

from ede.method.adapters import EmbeddingAdapter, IdentityAdapter
from ede.method.embedding import ActionEmbedding
from ede.run.evaluation import evaluate
from ede.run.executor import CodeExecutor
from ede.run.vector import MemberEnvs
from ede.tasks import action_bounds, make, simulator


@dataclass
class EffectSpace:
    effects: np.ndarray  # (N, 2) s[t+k] - s[t]
    codes: np.ndarray  # (N, 2) whitened E(a)
    r_squared: float  # of the best affine map effect -> code
    k: int  # the sequences' length


def effect_space(
    embedding: ActionEmbedding,
    rng: np.random.Generator,
    sequences: int = 2000,
    env_id: str = "ede/Point-v0",
) -> EffectSpace:
    """Figure 6's numbers: the effects of random k-step sequences and their codes.

    Each sequence is stepped from a fresh reset of ``env_id``; its effect is the change of the
    first two state coordinates (the position). The affine fit z ≈ A·effect + b is reported as
    its R² over both code dimensions.
    """
    env = make(env_id)
    data = simulator(env).data  # the simulator's state: the same object through every reset
    k = embedding.k
    low, high = action_bounds(env)
    actions = rng.uniform(low, high, size=(sequences, k, len(low))).astype(np.float32)
    effects = np.zeros((sequences, 2))
    for n in range(sequences):
        env.reset(seed=int(rng.integers(2**31)))
        start = data.qpos[:2].copy()
        for action in actions[n]:
            env.step(action)
        effects[n] = data.qpos[:2] - start
    env.close()
    with torch.no_grad():
        codes = embedding.encode(torch.as_tensor(actions, device=embedding.device)).cpu().numpy()
    design = np.hstack([effects, np.ones((sequences, 1))])
    coefficients, *_ = np.linalg.lstsq(design, codes[:, :2], rcond=None)
    residual = codes[:, :2] - design @ coefficients
    r_squared = 1 - residual.var(axis=0).sum() / codes[:, :2].var(axis=0).sum()

    return EffectSpace(effects, codes, float(r_squared), k)


@dataclass
class Exploration:
    raw_positions: list[np.ndarray]  # per episode, (T, 2)
    ede_positions: list[np.ndarray]
    raw_coverage: float  # fraction of the arena's grid cells visited
    ede_coverage: float
    half_width: float  # of the arena, [−half_width, half_width]²


def _coverage(positions: list[np.ndarray], half_width: float, cells: int) -> float:
    xy = np.concatenate(positions)
    index = np.clip(((xy + half_width) / (2 * half_width) * cells).astype(int), 0, cells - 1)
    return len({(i, j) for i, j in index}) / cells**2


def exploration(
    embedding: ActionEmbedding,
    rng: np.random.Generator,
    episodes: int = 10,
    env_id: str = "ede/PointMass-v0",
    half_width: float = 1.0,
    cells: int = 20,
) -> Exploration:
    """Figure 7's numbers: positions over ``episodes`` episodes of uniform random raw actions, and of
    uniform random EDE codes (in [−bound, bound]^D) chosen every k steps and decoded — executed
    as training executes codes (:class:`ede.run.executor.CodeExecutor`; raw actions are codes with k = 1).

    Coverage is the fraction of a ``cells`` × ``cells`` grid over the arena
    ([−half_width, half_width]²) that the positions visit.
    """
    env = make(env_id)
    data = simulator(env).data  # the simulator's state: the same object through every reset
    low, high = action_bounds(env)
    seeds = rng.integers(2**31, size=episodes)
    device = embedding.device

    def uniform_action(obs: np.ndarray, _: np.ndarray) -> torch.Tensor:  # (1, O) -> (1, A)
        return torch.as_tensor(rng.uniform(low, high).astype(np.float32), device=device)[None]

    def uniform_code(obs: np.ndarray, _: np.ndarray) -> torch.Tensor:  # (1, O) -> (1, D)
        z = rng.uniform(-embedding.bound, embedding.bound, size=embedding.dim)  # (D,)
        return torch.as_tensor(z, dtype=torch.float32, device=device)[None]

    envs = MemberEnvs([lambda: env])  # the one environment, as training steps its members'
    one = np.ones(1, dtype=bool)

    def rollout(
        executor: CodeExecutor, policy: Callable[[np.ndarray, np.ndarray], torch.Tensor]
    ) -> list[np.ndarray]:  # per episode, (T, 2) positions
        return [
            np.array([data.qpos[:2].copy() for _ in executor.episodes(policy, 1, [seed], one)])
            for seed in seeds
        ]

    raw = rollout(CodeExecutor(envs, IdentityAdapter(low, high, device)), uniform_action)
    ede = rollout(CodeExecutor(envs, EmbeddingAdapter(embedding)), uniform_code)
    env.close()
    raw_cov, ede_cov = _coverage(raw, half_width, cells), _coverage(ede, half_width, cells)
    return Exploration(raw, ede, raw_cov, ede_cov, half_width)


ZERO_EPISODES = (
    100  # episodes behind a task's zero-action return (its standard error ~10 on Reacher's)
)


def random_policy_return(task: str, episodes: int, seed: int) -> float:
    """The mean return of uniform random actions on ``task`` over ``episodes`` episodes, episode e
    from ``reset(seed=seed + e)``: the low end of a task's normalised scores."""
    rng = np.random.default_rng(seed)
    return float(
        np.mean(
            _episode_returns(task, episodes, seed, lambda space: rng.uniform(space.low, space.high))
        )
    )


def zero_action_return(task: str, episodes: int, seed: int) -> tuple[float, float]:
    """The mean return, and its standard error, of the action nearest zero on ``task`` (idle
    actuators: on a task with an action penalty, the return of doing nothing) over ``episodes``
    episodes, episode e from ``reset(seed=seed + e)``. A policy below it has learned nothing the
    task rewards beyond sparing its actions."""
    returns = _episode_returns(
        task, episodes, seed, lambda space: np.clip(0.0, space.low, space.high)
    )
    return float(np.mean(returns)), float(np.std(returns, ddof=1) / np.sqrt(episodes))


def _episode_returns(
    task: str, episodes: int, seed: int, act: Callable[[gymnasium.spaces.Box], np.ndarray]
) -> np.ndarray:
    """Each episode's return on ``task`` with ``act(action_space)`` as the policy, by the
    evaluation's own loop (:func:`ede.run.evaluation.evaluate`)."""
    env = make(task)
    try:
        space = env.action_space
        assert isinstance(space, gymnasium.spaces.Box)
        adapter = IdentityAdapter(space.low, space.high, torch.device("cpu"))
        returns = evaluate(
            MemberEnvs([lambda: env]),
            lambda obs: torch.as_tensor(np.asarray(act(space), space.dtype))[None],
            adapter,
            episodes,
            [seed],
        )
        return returns[0]
    finally:
        env.close()
