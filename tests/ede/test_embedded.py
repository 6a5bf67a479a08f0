"""A family's EDE space as a gymnasium wrapper (``ede.EmbeddedActions``): it acts as EDE-TD3's
executor acts, bit for bit, passes gymnasium's and stable-baselines3's checks, and an SB3 agent
learns in it unchanged."""

from __future__ import annotations

import re
import subprocess
import sys
import warnings
from collections.abc import Callable, Iterator
from typing import Any

import gymnasium
import numpy as np
import pytest
import torch

from ede.method.adapters import EmbeddingAdapter
from ede.method.embedding import ActionEmbedding
from ede.run.artifacts import ArtifactError, load_action_embedding
from ede.run.embedded import EmbeddedActions
from ede.run.executor import CodeExecutor
from ede.run.vector import MemberEnvs
from ede.tasks import make
from tests.support import REPO

# The Reacher family's published decoder (k = 4, D = 2, actions in [-1, 1]²).
PUBLISHED = REPO / "docs/results/clips/ede/ReacherVertical-v0/embedding/dd9075ddf328/decoder"
TASK = "ede/ReacherVertical-v0"


@pytest.fixture(autouse=True, scope="module")
def one_thread() -> Iterator[None]:
    """Small networks on one thread: on a busy machine more threads only wait for each other."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def embedding() -> ActionEmbedding:
    return load_action_embedding(None, PUBLISHED)[1]


class Counter(gymnasium.Env[np.ndarray, np.ndarray]):
    """Step t (from 1) observes t and rewards t; the episode ends at step ``length``."""

    observation_space = gymnasium.spaces.Box(0, np.inf, (1,))

    def __init__(self, length: int, truncate: bool = False, high: float = 1.0) -> None:
        self.action_space = gymnasium.spaces.Box(-high, high, (2,))
        self.length, self.truncate, self.t = length, truncate, 0

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self.t = 0
        return np.array([0.0], dtype=np.float32), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        self.t += 1
        over = self.t == self.length
        obs = np.array([self.t], dtype=np.float32)
        return obs, float(self.t), over and not self.truncate, over and self.truncate, {"t": self.t}


class Steps(gymnasium.Wrapper[Any, Any, Any, Any]):
    """Counts the task's steps."""

    steps = 0

    def step(self, action: Any) -> tuple[Any, Any, bool, bool, dict[str, Any]]:
        self.steps += 1
        return self.env.step(action)


def always(code: torch.Tensor) -> Callable[[np.ndarray, np.ndarray], torch.Tensor]:
    """The policy of one member that chooses ``code``, ``(M, O) -> (1, D)``."""
    return lambda _obs, _choosing: code[None]


def codes(embedding: ActionEmbedding, n: int, seed: int = 0) -> torch.Tensor:
    """``n`` codes ``(n, D)`` uniform in the embedding's box."""
    u = torch.rand(n, embedding.dim, generator=torch.Generator().manual_seed(seed))
    return (2 * u - 1) * embedding.bound


def test_ede_hands_out_the_wrapper_on_first_use_only() -> None:
    code = (
        "import sys, ede, ede.config; heavy = ('torch', 'gymnasium')\n"
        "print(sorted(m for m in heavy if m in sys.modules))\n"
        "from ede import EmbeddedActions\n"
        "print(EmbeddedActions.__module__, sorted(m for m in heavy if m in sys.modules))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    assert done.stdout.split("\n")[:2] == ["[]", "ede.run.embedded ['gymnasium', 'torch']"]
    with pytest.raises(AttributeError, match="no attribute 'Embedded'"):
        import ede

        ede.Embedded  # noqa: B018


def test_the_action_space_is_the_box_ede_td3s_actor_acts_in(embedding: ActionEmbedding) -> None:
    env = EmbeddedActions(make(TASK), embedding, bound_scale=0.5)
    adapter = EmbeddingAdapter(embedding, bound_scale=0.5)
    space = env.action_space
    assert isinstance(space, gymnasium.spaces.Box) and space.dtype == np.float32
    assert space.shape == (embedding.dim,) and env.k == embedding.k == 4
    assert np.array_equal(space.low, adapter.code_low.numpy())
    assert np.array_equal(space.high, adapter.code_high.numpy())
    assert space.high[0] == np.float32(embedding.bound * 0.5)
    assert env.observation_space == env.env.observation_space


def test_a_code_is_the_actions_ede_td3s_executor_takes_for_it(embedding: ActionEmbedding) -> None:
    """The same task, seed and codes: the same actions, rewards and observations, bit for bit."""
    chosen = codes(embedding, 6)
    members = np.ones(1, dtype=bool)
    envs = MemberEnvs.of_task(TASK, 1)
    executor = CodeExecutor(envs, EmbeddingAdapter(embedding))
    obs = envs.reset(members, [7])
    theirs = []
    for code in chosen:
        executor.choose(obs, always(code), members)
        steps = [executor.step(members) for _ in range(embedding.k)]
        obs = steps[-1].next_obs
        actions = np.stack([s.action[0] for s in steps])
        theirs.append((actions, np.array([s.reward[0] for s in steps]), obs[0]))
    envs.close()

    env = EmbeddedActions(make(TASK), embedding)
    env.reset(seed=7)
    for code, (actions, rewards, last) in zip(chosen, theirs, strict=True):
        obs, reward, terminated, truncated, info = env.step(code.numpy())
        assert info["steps"] == embedding.k and not (terminated or truncated)
        assert np.array_equal(info["actions"], actions)
        assert np.array_equal(info["rewards"], rewards) and reward == rewards.sum()
        assert np.array_equal(obs, last)


@pytest.mark.parametrize("truncate", [False, True])
def test_an_episodes_end_cuts_the_code_short(embedding: ActionEmbedding, truncate: bool) -> None:
    env = EmbeddedActions(Counter(length=6, truncate=truncate), embedding)
    env.reset(seed=0)
    code = np.zeros(embedding.dim, dtype=np.float32)
    obs, reward, terminated, truncated, info = env.step(code)
    assert (info["steps"], reward, terminated, truncated) == (4, 1 + 2 + 3 + 4, False, False)
    obs, reward, terminated, truncated, info = env.step(code)
    assert info["steps"] == 2 and list(info["rewards"]) == [5.0, 6.0] and reward == 11.0
    assert (terminated, truncated) == (not truncate, truncate)
    assert obs[0] == 6 and info["t"] == 6 and len(info["actions"]) == 2  # the last step's info


def test_gamma_discounts_the_rewards_inside_a_code(embedding: ActionEmbedding) -> None:
    env = EmbeddedActions(Counter(length=6), embedding, gamma=0.5)
    env.reset(seed=0)
    code = np.zeros(embedding.dim, dtype=np.float32)
    assert env.step(code)[1] == 1 + 0.5 * 2 + 0.25 * 3 + 0.125 * 4
    assert env.step(code)[1] == 5 + 0.5 * 6  # the cut-short code: its own two steps
    undiscounted = EmbeddedActions(Counter(length=6), embedding, gamma=1.0)
    undiscounted.reset(seed=0)
    assert undiscounted.step(code)[1] == 10


@pytest.mark.parametrize("gamma", [0.0, -0.5, 1.01, float("nan")])
def test_a_gamma_outside_0_1_is_refused(embedding: ActionEmbedding, gamma: float) -> None:
    with pytest.raises(ValueError, match=r"^gamma = .*: expected a discount in \(0, 1\]"):
        EmbeddedActions(Counter(length=6), embedding, gamma=gamma)


def test_a_code_outside_the_box_is_clipped_into_it(embedding: ActionEmbedding) -> None:
    env = EmbeddedActions(make(TASK), embedding)
    b = embedding.bound
    outside = np.array([10 * b, -3 * b], dtype=np.float32)
    corner = np.array([b, -b], dtype=np.float32)
    acted = []
    for code in (outside, corner):
        env.reset(seed=0)
        acted.append(env.step(code)[4]["actions"])
    assert np.array_equal(acted[0], acted[1])
    unclipped = EmbeddingAdapter(embedding).decode(torch.as_tensor(outside)[None])[0].numpy()
    assert not np.array_equal(acted[0], unclipped)  # clipping is what made them equal


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_a_code_that_is_not_finite_is_refused_before_anything_steps(
    embedding: ActionEmbedding, bad: float
) -> None:
    task = Counter(length=6)
    env = EmbeddedActions(task, embedding)
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"^Counter: expected a finite action, got \[.*\]$"):
        env.step(np.array([bad, 0.0], dtype=np.float32))
    assert task.t == 0


def test_a_decoder_of_another_action_space_is_refused_naming_both(
    embedding: ActionEmbedding,
) -> None:
    with pytest.raises(ArtifactError) as refused:
        EmbeddedActions.load(make("ede/Pusher-v0"), PUBLISHED)
    line = str(refused.value)
    assert "\n" not in line and line.startswith(f"{PUBLISHED}: decodes into actions in [[-1, -1]")
    assert "but ede/Pusher-v0 acts in [[-2, -2, -2, -2, -2, -2, -2]" in line
    assert issubclass(ArtifactError, ValueError)  # the pipeline's bad input: exit 2
    with pytest.raises(ArtifactError, match=r"^the embedding: .* but Counter acts in \[\[-2, -2\]"):
        EmbeddedActions(Counter(length=6, high=2.0), embedding)


def test_a_published_decoder_loads_in_one_line(embedding: ActionEmbedding) -> None:
    env = EmbeddedActions.load(make(TASK), PUBLISHED, gamma=0.99)
    assert env.gamma == 0.99 and env.k == 4
    z = codes(embedding, 3)
    assert torch.equal(env.embedding.decode(z), embedding.decode(z))


def test_it_passes_gymnasiums_and_stable_baselines3s_checks(embedding: ActionEmbedding) -> None:
    from gymnasium.utils.env_checker import check_env as gymnasium_check
    from stable_baselines3.common.env_checker import check_env as sb3_check

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        gymnasium_check(EmbeddedActions(make(TASK), embedding), skip_render_check=True)
        sb3_check(EmbeddedActions(make(TASK), embedding))
    # Both ask for a [-1, 1] box (SB3's agents rescale any bounded box, as they do here) and warn
    # of the task's own unbounded observations; gymnasium's asks for the unwrapped task, where the
    # wrapper is what is checked.
    expected = ("symmetric and normalized", "is infinity", "is -infinity", "unwrapped version")
    unexpected = [w.message for w in caught if not any(e in str(w.message) for e in expected)]
    assert unexpected == [] and len(caught) >= 2


@pytest.mark.parametrize("algorithm", ["SAC", "TD3"])
def test_a_stable_baselines3_agent_learns_in_it_unchanged(
    embedding: ActionEmbedding, algorithm: str
) -> None:
    import stable_baselines3

    task = Steps(make(TASK))
    env = EmbeddedActions(task, embedding, gamma=0.99)
    agent = getattr(stable_baselines3, algorithm)(
        "MlpPolicy",
        env,
        gamma=0.99**env.k,
        learning_starts=50,
        batch_size=32,
        policy_kwargs={"net_arch": [16, 16]},
        seed=0,
        device="cpu",
    )
    before = [p.clone() for p in agent.actor.parameters()]
    agent.learn(total_timesteps=200)
    assert agent.num_timesteps == 200 and agent.replay_buffer.size() == 200
    assert task.steps == 200 * env.k  # no episode cut a code short: 100 steps are 25 codes
    assert any(not torch.equal(a, b) for a, b in zip(before, agent.actor.parameters(), strict=True))


def test_the_recipe_on_any_agent_md_runs(monkeypatch: pytest.MonkeyPatch) -> None:
    """docs/any-agent.md's code, as a user copies it, at a budget of 150 codes; the README shows
    the same lines."""
    page = (REPO / "docs" / "any-agent.md").read_text()
    blocks = re.findall(r"^```python\n(.*?)^```", page, re.S | re.M)
    readme = (REPO / "README.md").read_text()
    assert blocks[0] in re.findall(r"^```python\n(.*?)^```", readme, re.S | re.M)
    recipe, count = re.subn(r"total_timesteps=[^)]*", "total_timesteps=150", blocks[0])
    assert count == 1 and len(recipe.strip().splitlines()) <= 12
    monkeypatch.chdir(REPO)
    scope: dict[str, Any] = {}
    exec(compile(recipe, "docs/any-agent.md", "exec"), scope)
    assert isinstance(scope["env"], EmbeddedActions) and scope["model"].num_timesteps == 150
