"""TD3/EDE-TD3 internals: Equation 1 on hand-built replay data, the actor's gradient, targets,
and the executor of codes."""

from __future__ import annotations

import functools
from typing import Any, cast

import gymnasium
import numpy as np
import pytest
import torch

from ede.config import TD3Config
from ede.method.adapters import EmbeddingAdapter, IdentityAdapter
from ede.method.agent import Agent
from ede.method.embedding import ActionEmbedding
from ede.method.ensemble import Params
from ede.method.replay import ReplayBuffer
from ede.method.td3 import Critic, k_step_targets
from ede.run.executor import CodeExecutor
from ede.run.vector import MemberEnvs
from tests.support import add_step

GAMMA = 0.9
K, OBS, CODE = 4, 3, 2


class FixedAdapter:
    """A K-step adapter with a box of codes, enough for the agent's update (decode unused)."""

    k, code_size = K, CODE
    code_low = -torch.ones(CODE)
    code_high = torch.ones(CODE)
    noise_scale = torch.ones(CODE)
    target_noise_scale = 0.25
    clip_scale = torch.ones(CODE)
    plan_step = "onehot"

    def decode(self, codes: torch.Tensor) -> torch.Tensor:
        return codes[:, None].expand(-1, K, -1)


def agent_for(k_adapter, **overrides) -> Agent:
    config = TD3Config(hidden=[16, 16], policy_noise=0.0, discount=GAMMA, **overrides)
    return Agent(OBS, k_adapter, config, torch.device("cpu"), seeds=[0])


def filled_buffer(rewards, terminated=(), truncated=(), i=None) -> ReplayBuffer:
    """Steps t = 0..n-1 with obs[t] = next_obs[t-1] = (t, t, t) and codes (t, -t)/10."""
    n = len(rewards)
    buffer = ReplayBuffer(32, OBS, CODE, K, torch.device("cpu"))
    for t in range(n):
        add_step(
            buffer,
            0,
            obs=np.full(OBS, t, dtype=np.float32),
            code=torch.tensor([t / 10, -t / 10]),
            i=(t % K) if i is None else i[t],
            reward=rewards[t],
            next_obs=np.full(OBS, t + 1, dtype=np.float32),
            terminated=t in terminated,
            truncated=t in truncated,
        )
    return buffer


def batch_at(buffer: ReplayBuffer, index: int):
    """The batch of one sample (one member) at row ``index``."""
    return buffer.gather(torch.tensor([[index]]))


def target(agent: Agent, batch) -> torch.Tensor:
    """Equation 1 without target noise (the agents here have policy_noise 0)."""
    return agent.td3.target(
        agent.actor_target.params, agent.critic_target.params, batch, torch.zeros_like(batch.code)
    )


def q_min(agent: Agent, obs: torch.Tensor, code: torch.Tensor, i: int) -> float:
    q1, q2 = agent.td3.critic(
        agent.critic_target.params, obs[None, None], code[None, None], torch.tensor([[i]])
    )
    return torch.minimum(q1, q2).item()


def next_code(agent: Agent, obs: torch.Tensor) -> torch.Tensor:
    return agent.td3.clip(agent.td3.actor(agent.actor_target.params, obs[None, None]))[0, 0]


REWARDS = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.0]


def test_equation_1_at_i_0_sums_k_rewards_and_bootstraps_at_the_next_choice() -> None:
    agent = agent_for(FixedAdapter())
    buffer = filled_buffer(REWARDS)
    batch = batch_at(buffer, 4)  # i = 0: steps 4..7 remain, the next code is chosen at s_8
    s8 = torch.full((OBS,), 8.0)
    expected = sum(GAMMA**m * REWARDS[4 + m] for m in range(4))
    expected += GAMMA**4 * q_min(agent, s8, next_code(agent, s8), 0)
    assert target(agent, batch).item() == pytest.approx(expected, rel=1e-6)
    parts = k_step_targets(batch, GAMMA)
    assert parts.next_i.item() == 0 and not parts.keep_code.item()


def test_equation_1_at_i_3_has_one_step_left() -> None:
    agent = agent_for(FixedAdapter())
    buffer = filled_buffer(REWARDS)
    batch = batch_at(buffer, 3)  # i = 3: only r_3 remains, then s_4
    s4 = torch.full((OBS,), 4.0)
    expected = REWARDS[3] + GAMMA * q_min(agent, s4, next_code(agent, s4), 0)
    assert target(agent, batch).item() == pytest.approx(expected, rel=1e-6)


def test_an_episode_that_terminates_inside_the_code_is_cut_without_bootstrap() -> None:
    agent = agent_for(FixedAdapter())
    # Terminates after step 5; step 6 starts a new episode (i = 0 there).
    buffer = filled_buffer(REWARDS, terminated={5}, i=[0, 1, 2, 3, 0, 1, 0, 1, 2, 3, 0, 1])
    batch = batch_at(buffer, 4)
    expected = REWARDS[4] + GAMMA * REWARDS[5]  # r_6, r_7 belong to the next episode
    assert target(agent, batch).item() == pytest.approx(expected, rel=1e-6)
    assert k_step_targets(batch, GAMMA).discount.item() == 0.0


def test_a_time_limit_inside_the_code_bootstraps_with_the_code_going_on() -> None:
    agent = agent_for(FixedAdapter())
    buffer = filled_buffer(REWARDS, truncated={5}, i=[0, 1, 2, 3, 0, 1, 0, 1, 2, 3, 0, 1])
    batch = batch_at(buffer, 4)  # code of step 4 ran 2 of its 4 steps when time ran out
    s6, code = torch.full((OBS,), 6.0), buffer.code[4, 0]
    expected = REWARDS[4] + GAMMA * REWARDS[5] + GAMMA**2 * q_min(agent, s6, code, 2)
    assert target(agent, batch).item() == pytest.approx(expected, rel=1e-6)
    parts = k_step_targets(batch, GAMMA)
    assert parts.keep_code.item() and parts.next_i.item() == 2


def test_a_time_limit_at_the_codes_last_step_chooses_a_new_code() -> None:
    agent = agent_for(FixedAdapter())
    buffer = filled_buffer(REWARDS, truncated={7})
    batch = batch_at(buffer, 4)
    s8 = torch.full((OBS,), 8.0)
    expected = sum(GAMMA**m * REWARDS[4 + m] for m in range(4))
    expected += GAMMA**4 * q_min(agent, s8, next_code(agent, s8), 0)
    assert target(agent, batch).item() == pytest.approx(expected, rel=1e-6)


def test_with_k_1_the_target_is_td3s() -> None:
    adapter = IdentityAdapter(-np.ones(CODE), np.ones(CODE), torch.device("cpu"))
    agent = agent_for(adapter)
    buffer = ReplayBuffer(8, OBS, CODE, 1, torch.device("cpu"))
    for t in range(4):
        add_step(
            buffer,
            0,
            np.full(OBS, t, dtype=np.float32),
            torch.zeros(CODE),
            0,
            float(t),
            np.full(OBS, t + 1, dtype=np.float32),
            t == 2,
            False,
        )
    batch = buffer.sample(64, [torch.Generator().manual_seed(1)])
    targets = target(agent, batch)
    for obs, y, reward in zip(batch.obs[0], targets[0], batch.rewards[0, :, 0], strict=True):
        t = int(obs[0].item())
        s1 = torch.full((OBS,), t + 1.0)
        bootstrap = 0.0 if t == 2 else GAMMA * q_min(agent, s1, next_code(agent, s1), 0)
        assert y.item() == pytest.approx(reward.item() + bootstrap, rel=1e-6)


def test_the_newest_k_minus_1_steps_are_never_sampled() -> None:
    buffer = filled_buffer(REWARDS[:6])
    batch = buffer.sample(500, [torch.Generator().manual_seed(0)])
    assert set(batch.obs[0, :, 0].long().tolist()) == {0, 1, 2}


def test_the_actor_learns_only_through_the_critic_at_i_0(monkeypatch: pytest.MonkeyPatch) -> None:
    agent = agent_for(FixedAdapter(), policy_delay=1)
    buffer = filled_buffer(REWARDS)
    seen_i = []
    original = type(agent.td3.critic).q1

    def spy(self, params, obs, code, i):
        seen_i.append(i.clone())
        return original(self, params, obs, code, i)

    monkeypatch.setattr(type(agent.td3.critic), "q1", spy)
    critic_after_its_step = {}

    def snapshot(*args, **kwargs):
        out = step(*args, **kwargs)
        critic_after_its_step["flat"] = agent.critic.flat.clone()
        return out

    step = agent.critic_adam.step
    monkeypatch.setattr(agent.critic_adam, "step", snapshot)
    actor_before = agent.actor.flat.clone()
    agent.update(buffer)
    assert len(seen_i) == 1 and torch.all(seen_i[0] == 0)
    assert not torch.equal(actor_before, agent.actor.flat)
    assert torch.equal(
        agent.critic.flat, critic_after_its_step["flat"]
    )  # the actor step left Q alone


def test_actor_updates_wait_for_the_policy_delay_and_targets_move_by_tau() -> None:
    agent = agent_for(FixedAdapter(), policy_delay=2, tau=0.25)
    buffer = filled_buffer(REWARDS)
    actor_before, target_before = agent.actor.flat.clone(), agent.critic_target.flat.clone()
    agent.update(buffer)  # update 1: critic only
    assert torch.equal(actor_before, agent.actor.flat)
    assert torch.equal(target_before, agent.critic_target.flat)
    agent.update(buffer)  # update 2: actor, targets
    torch.testing.assert_close(
        agent.critic_target.flat, 0.75 * target_before + 0.25 * agent.critic.flat
    )
    assert not torch.equal(agent.critic_target.flat, target_before)


class BoxEmbedding:
    """What EmbeddingAdapter reads of an embedding: k, dim, the bound, the device."""

    k, dim, device = K, CODE, torch.device("cpu")

    def __init__(self, bound: float) -> None:
        self.bound = bound


def largest_target_noise(adapter, noise_clip: float = 0.5, **overrides) -> float:
    """The largest |c' − μ'(s')| over a batch, with a target noise std far above its clip."""
    config = TD3Config(hidden=[16, 16], policy_noise=1e3, noise_clip=noise_clip, **overrides)
    agent = Agent(OBS, adapter, config, torch.device("cpu"), seeds=[0])
    buffer = filled_buffer(REWARDS) if adapter.k == K else filled_buffer_k1()
    seen = []
    critic = agent.td3.critic

    def spy(params: Params, obs: torch.Tensor, code: torch.Tensor, i: torch.Tensor) -> Any:
        seen.append((obs, code))
        return critic(params, obs, code, i)

    agent.td3.critic = spy  # type: ignore[assignment]  # the critic, watched
    batch = buffer.sample(64, [torch.Generator().manual_seed(0)])
    noise = torch.randn(batch.code.shape, generator=torch.Generator().manual_seed(1))
    agent.td3.target(agent.actor_target.params, agent.critic_target.params, batch, noise)
    obs, code = seen[0]
    return (
        (code - agent.td3.clip(agent.td3.actor(agent.actor_target.params, obs))).abs().max().item()
    )


def filled_buffer_k1() -> ReplayBuffer:
    buffer = ReplayBuffer(32, OBS, CODE, 1, torch.device("cpu"))
    for t in range(8):
        add_step(
            buffer,
            0,
            np.full(OBS, t, dtype=np.float32),
            torch.zeros(CODE),
            0,
            0.0,
            np.full(OBS, t + 1, dtype=np.float32),
            False,
            False,
        )
    return buffer


@pytest.mark.parametrize(("clip", "expected"), [("absolute", 0.5), ("scaled", 0.5 * 3.8 * 0.25)])
def test_ede_target_noise_is_clipped_in_code_units_or_scaled_by_the_bound(clip, expected) -> None:
    # The bound 3.8 (ReacherVertical's): the authors' clip is td3.noise_clip = 0.5 in whitened-z
    # units; "scaled" multiplies it by the bound and target_noise_scale (0.475).
    embedding = cast(ActionEmbedding, BoxEmbedding(3.8))  # a stand-in with what the adapter reads
    adapter = EmbeddingAdapter(embedding, target_noise_scale=0.25, target_noise_clip=clip)
    assert largest_target_noise(adapter) == pytest.approx(expected, abs=1e-5)


@pytest.mark.parametrize(("units", "expected"), [("absolute", 0.5), ("range", 1.0)])
def test_td3_noise_is_absolute_or_relative_to_the_action_box(units, expected) -> None:
    # A ±2 box, as Pusher's: absolute noises are in action units (sfujim, the authors' code);
    # "range" multiplies them by the half-range 2 (stable-baselines3).
    adapter = IdentityAdapter(-2 * np.ones(CODE), 2 * np.ones(CODE), torch.device("cpu"), units)
    assert largest_target_noise(adapter) == pytest.approx(expected, abs=1e-5)
    config = TD3Config(hidden=[16, 16], exploration_noise=0.1)
    agent = Agent(OBS, adapter, config, torch.device("cpu"), seeds=[0])
    obs, one = np.zeros((1, OBS), dtype=np.float32), np.ones(1, dtype=bool)
    mean = agent.act(obs)
    noise = torch.stack([agent.behave(obs, one, ~one) - mean for _ in range(4000)])
    assert noise.std().item() == pytest.approx(0.1 * expected / 0.5, rel=0.05)


def test_critic_sees_the_plan_step_as_a_one_hot_or_a_scalar() -> None:
    obs, code, i = torch.zeros(3, OBS), torch.ones(3, CODE), torch.tensor([0, 2, 3])
    onehot = Critic(OBS, CODE, K, [8], "onehot").inputs(obs, code, i)
    scalar = Critic(OBS, CODE, K, [8], "scalar").inputs(obs, code, i)
    assert onehot[:, OBS + CODE :].tolist() == torch.eye(K)[i].tolist()
    assert scalar[:, OBS + CODE :].tolist() == [[0.0], [2.0], [3.0]]


@pytest.mark.parametrize(
    ("obs_size", "code_size", "k", "plan_step", "repeat", "copies"),
    [
        (10, 2, 1, "onehot", "auto", 2),  # TD3 on ReacherVertical: ⌊5 / 2⌋, as the authors' code
        (10, 2, 4, "scalar", "auto", 1),  # EDE-TD3 there: ⌊5 / 3⌋
        (14, 2, 4, "scalar", "auto", 2),  # ReacherPush (the authors' 14 entries): ⌊7 / 3⌋
        (23, 7, 1, "onehot", "auto", 1),  # Pusher: ⌊11.5 / 7⌋
        (10, 2, 1, "onehot", 3, 3),  # a number is taken as it is
    ],
)
def test_critic_repeats_its_action_input_as_asked(
    obs_size, code_size, k, plan_step, repeat, copies
) -> None:
    critic = Critic(obs_size, code_size, k, [8], plan_step, repeat)
    step_size = 0 if k == 1 else (k if plan_step == "onehot" else 1)
    assert critic.sizes[0] == obs_size + copies * (code_size + step_size)
    obs, code = torch.randn(2, obs_size), torch.randn(2, code_size)
    x = critic.inputs(obs, code, torch.tensor([0, k - 1]))
    pair = x[:, obs_size:].reshape(2, copies, -1)
    assert torch.equal(pair, pair[:, :1].expand_as(pair)) and torch.equal(
        pair[:, 0, :code_size], code
    )


# The executor of codes ----------------------------------------------------------------------


class StepEnv(gymnasium.Env):
    """Observes the step within the episode; the episode ends after ``length`` steps."""

    observation_space = gymnasium.spaces.Box(0, np.inf, (1,))
    action_space = gymnasium.spaces.Box(-np.inf, np.inf, (CODE,))

    def __init__(self, length: int, truncate: bool = False) -> None:
        self.length, self.truncate = length, truncate
        self.t = 0
        self.actions: list[np.ndarray] = []

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.array([0.0]), {}

    def step(self, action):
        self.actions.append(np.array(action))
        self.t += 1
        over = self.t == self.length
        return (
            np.array([float(self.t)]),
            1.0,
            over and not self.truncate,
            over and self.truncate,
            {},
        )


class StepAdapter(FixedAdapter):
    """Decodes code c into K actions: action m is 10 c + m."""

    def decode(self, codes: torch.Tensor) -> torch.Tensor:
        return 10 * codes[:, None] + torch.arange(K, dtype=codes.dtype)[None, :, None]


class CountingPolicy:
    """The n-th code chosen for a member is (n, -n); records the observation it was chosen at.
    Batched as the executor calls it: ``(M, O) -> (M, C)``, one count per member."""

    def __init__(self, members: int = 1) -> None:
        self.chosen_at: list[list[float]] = [[] for _ in range(members)]

    def __call__(self, obs: np.ndarray, choosing: np.ndarray) -> torch.Tensor:
        codes = torch.zeros(len(obs), CODE)
        for m in np.flatnonzero(choosing):
            n = len(self.chosen_at[m])
            self.chosen_at[m].append(float(obs[m, 0]))
            codes[m] = torch.tensor([float(n), float(-n)])
        return codes


def executor_of(*envs: StepEnv, adapter=None) -> CodeExecutor:
    """An executor over ``envs``, one member each."""
    return CodeExecutor(
        MemberEnvs([functools.partial(lambda e: e, env) for env in envs]), adapter or StepAdapter()
    )


ONE = np.ones(1, dtype=bool)


def test_a_codes_k_actions_are_executed_in_order_and_the_next_code_is_chosen_at_i_0() -> None:
    env, policy = StepEnv(length=100), CountingPolicy()
    executor = executor_of(env)
    obs = executor.envs.reset(ONE, [0])
    steps = []
    for _ in range(2 * K + 1):
        executor.choose(obs, policy, ONE)
        steps.append(executor.step(ONE))
        obs = steps[-1].next_obs
    assert [int(step.i[0]) for step in steps] == [0, 1, 2, 3, 0, 1, 2, 3, 0]
    assert policy.chosen_at == [[0.0, 4.0, 8.0]]  # at i = 0 only
    expected = [[10 * n + m, -10 * n + m] for n in range(3) for m in range(K)][: 2 * K + 1]
    assert np.array_equal(np.array(env.actions), expected)
    assert [step.code[0].tolist() for step in steps[K : 2 * K]] == [[1.0, -1.0]] * K
    assert executor.i.tolist() == [1]


@pytest.mark.parametrize("truncate", [False, True])
def test_an_episode_end_inside_a_code_cuts_it_and_the_next_episode_chooses_anew(
    truncate: bool,
) -> None:
    env, policy = StepEnv(length=K + 2, truncate=truncate), CountingPolicy()
    executor = executor_of(env)
    steps = [step for step, _, _ in executor.episodes(policy, 2, [0], ONE)]
    first = steps[: K + 2]
    assert [bool(step.ended[0]) for step in first] == [False] * (K + 1) + [True]
    assert [int(step.i[0]) for step in first] == [0, 1, 2, 3, 0, 1]  # the second code cut after 2
    assert (first[-1].truncated[0], first[-1].terminated[0]) == (truncate, not truncate)
    second = steps[K + 2]
    assert second.i[0] == 0 and second.code[0].tolist() == [2.0, -2.0]  # a new code, not the rest
    assert policy.chosen_at[0][:3] == [0.0, float(K), 0.0]
    assert np.array_equal(env.actions[K + 2], [20.0, -20.0])


def test_with_k_1_every_step_chooses_a_code_that_is_the_action() -> None:
    env, policy = StepEnv(length=3), CountingPolicy()
    adapter = IdentityAdapter(-np.ones(CODE), np.ones(CODE), torch.device("cpu"))
    steps = list(executor_of(env, adapter=adapter).episodes(policy, 1, [0], ONE))
    assert [int(step.i[0]) for step, _, _ in steps] == [0, 0, 0]
    assert policy.chosen_at == [[0.0, 1.0, 2.0]]
    assert np.array_equal(np.array(env.actions), [[0, 0], [1, -1], [2, -2]])


def test_members_step_together_each_through_its_own_episodes_as_alone() -> None:
    """Two members whose episodes end at different steps: each member's actions and codes are
    those it gets alone, and a member whose episodes are done sits the other's steps out."""
    short, long = StepEnv(length=3), StepEnv(length=K + 3)
    policy = CountingPolicy(members=2)
    episodes = list(executor_of(short, long).episodes(policy, 2, [0, 0], np.ones(2, bool)))
    assert len(episodes) == 2 * (K + 3)  # the longer member's two episodes
    assert len(short.actions) == 2 * 3  # the shorter one stepped its own two and then sat out
    alone = [StepEnv(length=3), StepEnv(length=K + 3)]
    for member, env in enumerate(alone):
        lone = CountingPolicy()
        list(executor_of(env).episodes(lone, 2, [0], ONE))
        assert policy.chosen_at[member] == lone.chosen_at[0]
    assert np.array_equal(short.actions, alone[0].actions)
    assert np.array_equal(long.actions, alone[1].actions)
