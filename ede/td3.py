"""TD3 and EDE-TD3: one agent, one replay buffer, one update.

TD3 (Fujimoto et al., 2018) is the special case k = 1 of EDE-TD3 (Section 3 of the paper): the
two differ only through an :class:`ActionAdapter` — the identity for TD3, the learned decoder for
EDE-TD3 — which fixes what the actor outputs (a raw action, or a whitened code z of k actions),
its bounds, and k.

Shapes: B batch, K actions per code (1 for TD3), A action size, C code size (A for TD3, D for
EDE-TD3), O observation size.

The critic is Q(s, c, i) with i the number of steps of code c already executed, fed as a one-hot
of size K or as a scalar (absent when K = 1). Its target is Equation 1, batched over B and K::

    y = Σ_{m<n} γ^m r_{t+m} + γ^n (1 − terminal) min_j Q'_j(s_{t+n}, c', i')

where n ≤ K − i steps remain of the code, fewer if the episode ended first; c' = μ'(s_{t+n}) plus
clipped smoothing noise and i' = 0 where the next code is chosen; and where a time limit cut the
code short (truncated, not terminal), the code goes on: c' = c, i' = i + n. The actor follows
∇_c Q_1(s, c, 0) (Equation 2). A :class:`CodeExecutor` acts with codes in an environment: the
one place a code becomes K environment steps, for training, evaluation and the report alike.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import NamedTuple, Protocol

import gymnasium
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ede.config import TD3Config
from ede.embedding import ActionEmbedding
from ede.nets import initial_weights, matmul_precision, mlp

__all__ = [
    "ActionAdapter",
    "Actor",
    "Agent",
    "CodeExecutor",
    "CodeStep",
    "Critic",
    "EmbeddingAdapter",
    "IdentityAdapter",
    "ReplayBatch",
    "ReplayBuffer",
    "k_step_targets",
]


class ActionAdapter(Protocol):
    """What the actor's outputs mean: codes in a box, each decoded to K raw actions."""

    k: int
    code_size: int
    code_low: torch.Tensor  # (C,)
    code_high: torch.Tensor  # (C,)
    noise_scale: torch.Tensor  # (C,) the unit of exploration and target noise stds
    target_noise_scale: float  # target smoothing noise std, × noise_scale × this
    clip_scale: torch.Tensor  # (C,) the unit of the target noise clip
    plan_step: str  # how the critic sees i: "onehot" (size K) or "scalar" (the raw count)

    def decode(self, codes: torch.Tensor) -> torch.Tensor:
        """(B, C) -> (B, K, A) raw actions."""
        ...


class IdentityAdapter:
    """TD3: the code is the raw action, K = 1.

    ``noise_units``: "absolute" — noises in action units, whatever the box (sfujim's TD3 and the
    authors' code); "range" — × the half-range of the action box (stable-baselines3, which
    rescales actions to [−1, 1]). The two agree on a ±1 box.
    """

    k = 1
    target_noise_scale = 1.0
    plan_step = "onehot"  # unused: K = 1 has no plan step

    def __init__(
        self, low: np.ndarray, high: np.ndarray, device: torch.device, noise_units: str = "absolute"
    ) -> None:
        self.code_size = len(low)
        self.code_low = torch.as_tensor(low, dtype=torch.float32, device=device)
        self.code_high = torch.as_tensor(high, dtype=torch.float32, device=device)
        half_range = (self.code_high - self.code_low) / 2
        self.noise_scale = half_range if noise_units == "range" else torch.ones_like(half_range)
        self.clip_scale = self.noise_scale

    def decode(self, codes: torch.Tensor) -> torch.Tensor:
        return codes.unsqueeze(1)  # (B, A) -> (B, 1, A)


class EmbeddingAdapter:
    """EDE-TD3: the code is a whitened z in [−bound, bound]^D, decoded to K actions by D.

    Noise stds are × the bound (the authors' code); the target noise clip is in code units
    (``target_noise_clip="absolute"``, the authors' code) or × the bound × ``target_noise_scale``
    ("scaled").
    """

    def __init__(
        self,
        embedding: ActionEmbedding,
        bound_scale: float = 1.0,
        target_noise_scale: float = 1.0,
        target_noise_clip: str = "absolute",
        plan_step: str = "onehot",
    ) -> None:
        self.embedding = embedding
        self.target_noise_scale = target_noise_scale
        self.plan_step = plan_step
        self.k, self.code_size = embedding.k, embedding.dim
        bound = embedding.bound * bound_scale
        device = embedding.device
        self.code_low = torch.full((self.code_size,), -bound, device=device)
        self.code_high = torch.full((self.code_size,), bound, device=device)
        self.noise_scale = self.code_high
        ones = torch.ones_like(self.code_high)
        scaled = target_noise_clip == "scaled"
        self.clip_scale = bound * target_noise_scale * ones if scaled else ones

    @torch.no_grad()
    def decode(self, codes: torch.Tensor) -> torch.Tensor:
        return self.embedding.decode(codes)  # (B, D) -> (B, K, A)


class CodeStep(NamedTuple):
    """One environment step of a code."""

    code: torch.Tensor  # (C,) the code being executed
    i: int  # steps of it executed before this one
    action: np.ndarray  # (A,) its i-th action
    reward: float
    next_obs: np.ndarray
    terminated: bool
    truncated: bool

    @property
    def ended(self) -> bool:
        return self.terminated or self.truncated


class CodeExecutor:
    """Acts in an environment with codes (Section 3), one step at a time.

    When i = 0 the policy chooses a code, which the adapter decodes into K actions; they are
    executed in order, one per step, and the next code is chosen after the K-th — or at the first
    step of the next episode, since an episode's end cuts the code short. Its state (the code, its
    actions, i) is part of a training run's checkpoint.
    """

    def __init__(self, env: gymnasium.Env, adapter: ActionAdapter) -> None:
        space = env.action_space
        self.env, self.adapter = env, adapter
        self.code = torch.zeros(adapter.code_size, device=adapter.code_low.device)  # (C,)
        self.plan = np.zeros((adapter.k, *space.shape), dtype=space.dtype)  # (K, A)
        self.i = 0  # steps of the code executed

    def step(self, obs: np.ndarray, policy: Callable[[np.ndarray], torch.Tensor]) -> CodeStep:
        """One environment step from ``obs``; ``policy(obs)`` gives a new code when i = 0."""
        i = self.i
        if i == 0:
            self.code = policy(obs)  # (C,)
            self.plan = self.adapter.decode(self.code[None])[0].cpu().numpy()  # (1, C) -> (K, A)
        action = self.plan[i]
        next_obs, reward, terminated, truncated, _ = self.env.step(action)
        self.i = 0 if terminated or truncated else (i + 1) % self.adapter.k
        return CodeStep(self.code, i, action, float(reward), next_obs, bool(terminated),
                        bool(truncated))

    def episode(
        self, obs: np.ndarray, policy: Callable[[np.ndarray], torch.Tensor]
    ) -> Iterator[CodeStep]:
        """Steps from ``obs`` (just after a reset) until the episode ends."""
        while True:
            step = self.step(obs, policy)
            yield step
            if step.ended:
                return
            obs = step.next_obs


class Actor(nn.Module):
    """μ(s): a code inside [low, high] through a tanh."""

    def __init__(self, obs_size: int, low: torch.Tensor, high: torch.Tensor, hidden: list[int]):
        super().__init__()
        self.net = mlp(obs_size, hidden, len(low))
        self.register_buffer("centre", (high + low) / 2)
        self.register_buffer("half_range", (high - low) / 2)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.centre + self.half_range * torch.tanh(self.net(obs))  # (B, O) -> (B, C)


def critic_repeat(setting: int | str, obs_size: int, pair_size: int) -> int:
    """How many times the critic sees (code, i): ``setting``, or for "auto" the authors' rule,
    max(1, ⌊0.5·O / pair size⌋) (their ``action_repeat``, docs/fidelity.md rows 7a–7b)."""
    if setting == "auto":
        return max(1, int(0.5 * obs_size // pair_size))
    return int(setting)


class Critic(nn.Module):
    """Twin Q(s, c, i): two MLPs over (observation, then ``repeat`` copies of (code, i)).

    i is a one-hot of size K (``plan_step="onehot"``) or the raw count as one input ("scalar", the
    authors' code); it is absent when K = 1.
    """

    def __init__(
        self,
        obs_size: int,
        code_size: int,
        k: int,
        hidden: list[int],
        plan_step: str = "onehot",
        repeat: int | str = 1,
    ) -> None:
        super().__init__()
        self.k, self.plan_step = k, plan_step
        step_size = 0 if k == 1 else (k if plan_step == "onehot" else 1)
        self.repeat = critic_repeat(repeat, obs_size, code_size + step_size)
        in_size = obs_size + self.repeat * (code_size + step_size)
        self.q1 = mlp(in_size, hidden, 1)
        self.q2 = mlp(in_size, hidden, 1)

    def _inputs(self, obs: torch.Tensor, code: torch.Tensor, i: torch.Tensor) -> torch.Tensor:
        pair = [code]
        if self.k > 1 and self.plan_step == "onehot":
            pair.append(F.one_hot(i, self.k).to(obs.dtype))  # (B,) -> (B, K)
        elif self.k > 1:
            pair.append(i.to(obs.dtype)[..., None])  # (B,) -> (B, 1)
        return torch.cat([obs, *pair * self.repeat], dim=-1)

    def forward(
        self, obs: torch.Tensor, code: torch.Tensor, i: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        x = self._inputs(obs, code, i)
        return self.q1(x).squeeze(-1), self.q2(x).squeeze(-1)  # (B,), (B,)

    def first(self, obs: torch.Tensor, code: torch.Tensor, i: torch.Tensor) -> torch.Tensor:
        return self.q1(self._inputs(obs, code, i)).squeeze(-1)


class ReplayBatch(NamedTuple):
    """Sampled steps and, for each, the K steps from it on (for the k-step target)."""

    obs: torch.Tensor  # (B, O)
    code: torch.Tensor  # (B, C)
    i: torch.Tensor  # (B,) int64
    rewards: torch.Tensor  # (B, K): r_t ... r_{t+K-1}
    terminated: torch.Tensor  # (B, K) bool
    truncated: torch.Tensor  # (B, K) bool
    next_obs: torch.Tensor  # (B, K, O): s_{t+1} ... s_{t+K}


class ReplayBuffer:
    """A circular buffer of steps; samples come with the K steps that follow them.

    Each step stores the code being executed and its index i. A sample's K-step future is read by
    index arithmetic (``idx[:, None] + arange(K)``), never by a Python loop; the newest K − 1 steps
    are not sampled because their future is not written yet.
    """

    def __init__(
        self, capacity: int, obs_size: int, code_size: int, k: int, device: torch.device
    ) -> None:
        self.capacity, self.k, self.device = capacity, k, device
        self.obs = torch.zeros((capacity, obs_size), device=device)
        self.next_obs = torch.zeros((capacity, obs_size), device=device)
        self.code = torch.zeros((capacity, code_size), device=device)
        self.i = torch.zeros(capacity, dtype=torch.int64, device=device)
        self.reward = torch.zeros(capacity, device=device)
        self.terminated = torch.zeros(capacity, dtype=torch.bool, device=device)
        self.truncated = torch.zeros(capacity, dtype=torch.bool, device=device)
        self.head = 0  # where the next step goes
        self.size = 0

    FIELDS = ("obs", "next_obs", "code", "i", "reward", "terminated", "truncated")

    def add(
        self,
        obs: np.ndarray,
        code: torch.Tensor,
        i: int,
        reward: float,
        next_obs: np.ndarray,
        terminated: bool,
        truncated: bool,
    ) -> None:
        h = self.head
        self.obs[h] = torch.as_tensor(obs, dtype=torch.float32)
        self.next_obs[h] = torch.as_tensor(next_obs, dtype=torch.float32)
        self.code[h] = code
        self.i[h] = i
        self.reward[h] = reward
        self.terminated[h] = terminated
        self.truncated[h] = truncated
        self.head = (h + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    @property
    def sampleable(self) -> int:
        return max(0, self.size - (self.k - 1))

    def sample(self, batch_size: int, generator: torch.Generator) -> ReplayBatch:
        if self.sampleable == 0:
            raise ValueError("the buffer holds no step whose K-step future is written")
        offset = torch.randint(
            self.sampleable, (batch_size,), generator=generator, device=generator.device
        )
        oldest = self.head - self.size  # the oldest step, mod capacity
        idx = ((oldest + offset) % self.capacity).to(self.device)  # (B,)
        steps = (idx[:, None] + torch.arange(self.k, device=self.device)) % self.capacity  # (B, K)
        return ReplayBatch(
            obs=self.obs[idx],
            code=self.code[idx],
            i=self.i[idx],
            rewards=self.reward[steps],
            terminated=self.terminated[steps],
            truncated=self.truncated[steps],
            next_obs=self.next_obs[steps],
        )

    def state(self) -> tuple[dict[str, torch.Tensor], dict[str, int]]:
        """Tensors and counters to checkpoint (only the filled part)."""
        n = self.size
        tensors = {name: getattr(self, name)[:n].cpu() for name in self.FIELDS}
        return tensors, {"head": self.head, "size": self.size}

    def load(self, tensors: dict[str, torch.Tensor], counters: dict[str, int]) -> None:
        n = counters["size"]
        for name in self.FIELDS:
            getattr(self, name)[:n] = tensors[name].to(self.device)
        self.head, self.size = counters["head"], n


@dataclass(frozen=True)
class TargetParts:
    """Equation 1 split into what the networks must evaluate and what they multiply."""

    returns: torch.Tensor  # (B,) discounted rewards of the steps that remain
    discount: torch.Tensor  # (B,) γ^n, zero where the episode terminated
    bootstrap_obs: torch.Tensor  # (B, O) s_{t+n}
    keep_code: torch.Tensor  # (B,) bool: a time limit cut the code short, it goes on
    next_i: torch.Tensor  # (B,) 0 where a new code is chosen, i + n where it goes on


def k_step_targets(batch: ReplayBatch, gamma: float) -> TargetParts:
    """The parts of Equation 1 that need no network, for a batch, all batched.

    n = the steps that remain of each sample's code (K − i), cut after the first step where the
    episode ended (terminated or truncated).
    """
    k = batch.rewards.shape[1]
    m = torch.arange(k, dtype=batch.rewards.dtype, device=batch.rewards.device)  # (K,)
    remaining = k - batch.i  # (B,)
    ended = batch.terminated | batch.truncated  # (B, K)
    ended_before = ended.cumsum(dim=1) > ended  # an earlier step ended the episode
    valid = (m < remaining[:, None]) & ~ended_before  # (B, K)
    n = valid.sum(dim=1)  # (B,), >= 1
    returns = (valid * gamma**m * batch.rewards).sum(dim=1)  # (B,)
    last = (n - 1)[:, None]  # (B, 1)
    terminal = batch.terminated.gather(1, last).squeeze(1)  # (B,)
    cut_short = batch.truncated.gather(1, last).squeeze(1) & (n < remaining)
    bootstrap_obs = batch.next_obs.gather(
        1, last[:, :, None].expand(-1, 1, batch.next_obs.shape[2])
    ).squeeze(1)  # (B, K, O) -> (B, O)
    discount = torch.where(terminal, 0.0, gamma**n)
    next_i = torch.where(cut_short, batch.i + n, torch.zeros_like(n))
    return TargetParts(returns, discount, bootstrap_obs, cut_short, next_i)


def polyak(target: list[torch.Tensor], source: list[torch.Tensor], tau: float) -> None:
    """target ← (1 − τ) target + τ source, in place, tensor by tensor."""
    with torch.no_grad():
        torch._foreach_lerp_(target, source, tau)


def _clear_grads(params: list[torch.Tensor]) -> None:
    """``optimizer.zero_grad(set_to_none=True)`` without its per-call bookkeeping."""
    for p in params:
        p.grad = None


class Agent:
    """The TD3 learner over any :class:`ActionAdapter` (TD3: identity, EDE-TD3: the decoder)."""

    def __init__(
        self,
        obs_size: int,
        adapter: ActionAdapter,
        config: TD3Config,
        device: torch.device,
        seed: int,
    ) -> None:
        self.adapter, self.config, self.device = adapter, config, device
        low, high = adapter.code_low, adapter.code_high
        self.scale = adapter.noise_scale  # (C,) the unit of the noise stds
        self.target_scale = self.scale * adapter.target_noise_scale
        with initial_weights(seed):
            self.actor = Actor(obs_size, low, high, config.hidden).to(device)
            self.critic = Critic(
                obs_size, adapter.code_size, adapter.k, config.hidden, adapter.plan_step,
                config.critic_action_repeat,
            ).to(device)
        self.actor_target = copy.deepcopy(self.actor).requires_grad_(False)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        # One fused kernel per step instead of a Python loop over tensors: a third of an update's
        # time on CPU for networks this small.
        self.actor_optimizer = torch.optim.Adam(self.actor.parameters(), lr=config.lr, fused=True)
        self.critic_optimizer = torch.optim.Adam(self.critic.parameters(), lr=config.lr, fused=True)
        self.generator = torch.Generator(device=device).manual_seed(seed)
        self.updates = 0
        # Listed once: walking the module trees every update costs more than the moves themselves.
        self._critic_params = list(self.critic.parameters())
        self._actor_params = list(self.actor.parameters())
        self._polyak_pairs = [
            (list(self.critic_target.parameters()), self._critic_params),
            (list(self.actor_target.parameters()), self._actor_params),
        ]
        self.autocast = config.precision == "bf16"
        # Sums since the last take_diagnostics(), kept on the device so that no update waits for
        # the host: critic loss, critic steps, actor loss (−mean Q(s, μ(s), 0)), actor steps.
        self.loss_sums = torch.zeros(4, device=device)

    def _noise(self, shape: torch.Size, std: float, scale: torch.Tensor) -> torch.Tensor:
        return torch.randn(shape, generator=self.generator, device=self.device) * std * scale

    def clip(self, codes: torch.Tensor) -> torch.Tensor:
        return codes.clamp(self.adapter.code_low, self.adapter.code_high)

    @torch.no_grad()
    def act(self, obs: np.ndarray, explore: bool) -> torch.Tensor:
        """The code for one observation: μ(s), plus exploration noise when ``explore``."""
        c = self.config
        code = self.actor(torch.as_tensor(obs, dtype=torch.float32, device=self.device)[None])[0]
        if explore:
            code = self.clip(code + self._noise(code.shape, c.exploration_noise, self.scale))
        return code

    def random_code(self) -> torch.Tensor:
        """A code uniform in the box: the start-steps behaviour."""
        low, high = self.adapter.code_low, self.adapter.code_high
        u = torch.rand(low.shape, generator=self.generator, device=self.device)
        return low + u * (high - low)

    def _autocast(self) -> torch.autocast:
        return torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.autocast)

    def target(self, batch: ReplayBatch) -> torch.Tensor:
        """Equation 1 with TD3's clipped double-Q and target policy smoothing."""
        c = self.config
        parts = k_step_targets(batch, c.discount)
        with torch.no_grad(), self._autocast():
            noise = self._noise(batch.code.shape, c.policy_noise, self.target_scale)
            clip = c.noise_clip * self.adapter.clip_scale
            noise = torch.maximum(torch.minimum(noise, clip), -clip)
            chosen = self.clip(self.actor_target(parts.bootstrap_obs) + noise)
            next_code = torch.where(parts.keep_code[:, None], batch.code, chosen)
            q1, q2 = self.critic_target(parts.bootstrap_obs, next_code, parts.next_i)
            return parts.returns + parts.discount * torch.minimum(q1, q2).float()

    def update(self, batch: ReplayBatch) -> None:
        """One critic step, and every ``policy_delay`` steps an actor step and target moves.

        Its matrix products follow ``td3.precision`` (see :func:`ede.nets.matmul_precision`).
        """
        with matmul_precision(self.config.precision):
            return self._update(batch)

    def _update(self, batch: ReplayBatch) -> None:
        c = self.config
        target = self.target(batch)
        with self._autocast():
            q1, q2 = self.critic(batch.obs, batch.code, batch.i)
            critic_loss = F.mse_loss(q1.float(), target) + F.mse_loss(q2.float(), target)
        _clear_grads(self._critic_params)
        critic_loss.backward()
        self.critic_optimizer.step()
        self.loss_sums[0] += critic_loss.detach()
        self.loss_sums[1] += 1
        self.updates += 1
        if self.updates % c.policy_delay:
            return
        # The actor follows ∇_c Q_1(s, c, 0) (Equation 2); Q's own weights get no gradient here,
        # which also spares the backward pass their weight products.
        for p in self._critic_params:
            p.requires_grad_(False)
        with self._autocast():
            start = torch.zeros_like(batch.i)  # a new code is chosen: i = 0
            actor_loss = -self.critic.first(batch.obs, self.actor(batch.obs), start).float().mean()
        _clear_grads(self._actor_params)
        actor_loss.backward()
        self.actor_optimizer.step()
        for p in self._critic_params:
            p.requires_grad_(True)
        self.loss_sums[2] += actor_loss.detach()
        self.loss_sums[3] += 1
        for target, source in self._polyak_pairs:
            polyak(target, source, c.tau)

    def take_diagnostics(self) -> dict[str, float]:
        """Means over the updates since the last call (one host synchronisation), then reset.

        Returns:
            ``updates`` (critic steps), ``critic_loss``, ``actor_loss`` and ``mean_q``, the mean
            of Q_1(s, μ(s), 0) over the actor steps' batches (NaN where there was no step).
        """
        critic, critic_steps, actor, actor_steps = self.loss_sums.tolist()
        self.loss_sums.zero_()
        nan = float("nan")
        return {
            "updates": int(critic_steps),
            "critic_loss": critic / critic_steps if critic_steps else nan,
            "actor_loss": actor / actor_steps if actor_steps else nan,
            "mean_q": -actor / actor_steps if actor_steps else nan,
        }

    # Checkpoints -------------------------------------------------------------------------

    def modules(self) -> dict[str, nn.Module]:
        return {
            "actor": self.actor,
            "critic": self.critic,
            "actor_target": self.actor_target,
            "critic_target": self.critic_target,
        }

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return {"actor_optimizer": self.actor_optimizer, "critic_optimizer": self.critic_optimizer}
