"""TD3 and EDE-TD3: one agent, one replay buffer, one update.

TD3 (Fujimoto et al., 2018) is the special case k = 1 of EDE-TD3 (Section 3 of the paper): the
two differ only through an :class:`ActionAdapter` — the identity for TD3, the learned decoder for
EDE-TD3 — which fixes what the actor outputs (a raw action, or a whitened code z of k actions),
its bounds, and k.

Shapes: M members (the runs an agent trains at once; 1 for a run alone), B batch, K actions per
code (1 for TD3), A action size, C code size (A for TD3, D for EDE-TD3), O observation size.
Everything the update touches has the member axis first; each member computes what it computes
alone, bit for bit on CPU (:class:`ede.nets.StackedMLP`, :class:`MemberAdam`), from its own
random streams (:class:`Streams`).

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
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import NamedTuple, Protocol

import gymnasium
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ede.config import TD3Config
from ede.embedding import ActionEmbedding
from ede.nets import Layers, StackedMLP, flatten, gradients, matmul_precision

__all__ = [
    "ActionAdapter",
    "Actor",
    "Agent",
    "CodeExecutor",
    "CodeStep",
    "Critic",
    "MemberAdam",
    "EmbeddingAdapter",
    "IdentityAdapter",
    "ReplayBatch",
    "ReplayBuffer",
    "Streams",
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


# Random streams -------------------------------------------------------------------------------

# Each purpose's key in a member's seed sequence: a new purpose takes a new key and shifts none.
PURPOSES = {"weights": 0, "exploration": 1, "target_noise": 2, "replay": 3, "start_codes": 4}


class Streams:
    """One member's random streams: a generator per purpose, each seeded from (seed, purpose)
    by numpy's ``SeedSequence``, so that no stream depends on another member, another purpose,
    or how many of either there are. Initial weights are drawn on the CPU (the same weights on
    every device); the others live on the training device."""

    def __init__(self, seed: int, device: torch.device) -> None:
        for purpose, key in PURPOSES.items():
            state = np.random.SeedSequence(seed, spawn_key=(key,)).generate_state(2, np.uint32)
            where = torch.device("cpu") if purpose == "weights" else device
            generator = torch.Generator(device=where)
            generator.manual_seed(int(state[0]) | int(state[1]) << 32)
            setattr(self, purpose, generator)

    weights: torch.Generator
    exploration: torch.Generator
    target_noise: torch.Generator
    replay: torch.Generator
    start_codes: torch.Generator

    SAVED = ("exploration", "target_noise", "replay", "start_codes")  # what a checkpoint keeps


# Networks -------------------------------------------------------------------------------------


class Actor(nn.Module):
    """μ(s) of every member: a code inside [low, high] through a tanh."""

    def __init__(self, obs_size: int, low: torch.Tensor, high: torch.Tensor, hidden: list[int],
                 generators: Sequence[torch.Generator]) -> None:
        super().__init__()
        self.net = StackedMLP(obs_size, hidden, len(low), generators)
        self.register_buffer("centre", (high + low) / 2)
        self.register_buffer("half_range", (high - low) / 2)

    def forward(self, obs: torch.Tensor, layers: Layers | None = None) -> torch.Tensor:
        """``(M, B, O) -> (M, B, C)``, member m on its own batch."""
        return self.centre + self.half_range * torch.tanh(self.net(obs, layers, halves=True))

    def one(self, member: int, obs: torch.Tensor) -> torch.Tensor:
        """Member ``member`` alone: ``(B, O) -> (B, C)``."""
        return self.centre + self.half_range * torch.tanh(self.net.one(member, obs))

    def state_of(self, member: int) -> dict[str, torch.Tensor]:
        """One member's actor as the single-network ``Actor`` of ``policy.safetensors`` names it:
        ``net.0.weight``, ..., ``centre``, ``half_range``."""
        state = {f"net.{k}": v for k, v in self.net.state_of(self.net.flat[member]).items()}
        return state | {"centre": self.centre, "half_range": self.half_range}


def critic_repeat(setting: int | str, obs_size: int, pair_size: int) -> int:
    """How many times the critic sees (code, i): ``setting``, or for "auto" the authors' rule,
    max(1, ⌊0.5·O / pair size⌋) (their ``action_repeat``, docs/fidelity.md rows 7a–7b)."""
    if setting == "auto":
        return max(1, int(0.5 * obs_size // pair_size))
    return int(setting)


class Critic(nn.Module):
    """Twin Q(s, c, i) of every member: one stacked network of 2M rows, Q1 of every member
    then Q2, over (observation, then ``repeat`` copies of (code, i)).

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
        generators: Sequence[torch.Generator] = (),
    ) -> None:
        super().__init__()
        self.k, self.plan_step, self.members = k, plan_step, len(generators)
        step_size = 0 if k == 1 else (k if plan_step == "onehot" else 1)
        self.repeat = critic_repeat(repeat, obs_size, code_size + step_size)
        in_size = obs_size + self.repeat * (code_size + step_size)
        # Each member draws Q1's weights, then Q2's, from its own generator.
        self.net = StackedMLP(in_size, hidden, 1, [*generators, *generators])

    def inputs(self, obs: torch.Tensor, code: torch.Tensor, i: torch.Tensor) -> torch.Tensor:
        pair = [code]
        if self.k > 1 and self.plan_step == "onehot":
            pair.append(F.one_hot(i, self.k).to(obs.dtype))  # (..., B) -> (..., B, K)
        elif self.k > 1:
            pair.append(i.to(obs.dtype)[..., None])  # (..., B) -> (..., B, 1)
        return torch.cat([obs, *pair * self.repeat], dim=-1)

    def forward(self, obs: torch.Tensor, code: torch.Tensor, i: torch.Tensor,
                layers: Layers | None = None) -> torch.Tensor:
        """``(M, B, ·) -> (2, M, B)``: Q1 and Q2 of every member."""
        x = self.inputs(obs, code, i)
        q = self.net(torch.cat([x, x]), layers)  # (2M, B, 1): one product per layer for both
        return q.view(2, self.members, -1)

    def first(self, obs: torch.Tensor, code: torch.Tensor, i: torch.Tensor,
              flat: torch.Tensor) -> torch.Tensor:
        """Q1 alone, ``(M, B)``, with the weights ``flat`` (every row of the critic)."""
        q1 = self.net.layers(flat[:self.members])
        return self.net(self.inputs(obs, code, i), q1, halves=True).squeeze(-1)

    def state_of(self, member: int) -> dict[str, torch.Tensor]:
        """One member's twins as the single-run ``Critic`` named them (``q1.0.weight``, ...)."""
        rows = (member, self.members + member)
        return {f"q{j + 1}.{k}": v for j, row in enumerate(rows)
                for k, v in self.net.state_of(self.net.flat[row]).items()}


# Replay ---------------------------------------------------------------------------------------


class ReplayBatch(NamedTuple):
    """Sampled steps of every member and, for each, the K steps from it on (the k-step target).

    Leading dimensions ``(M, B)``: member, sample.
    """

    obs: torch.Tensor  # (M, B, O)
    code: torch.Tensor  # (M, B, C)
    i: torch.Tensor  # (M, B) int64
    rewards: torch.Tensor  # (M, B, K): r_t ... r_{t+K-1}
    terminated: torch.Tensor  # (M, B, K) bool
    truncated: torch.Tensor  # (M, B, K) bool
    next_obs: torch.Tensor  # (M, B, K, O): s_{t+1} ... s_{t+K}


class ReplayBuffer:
    """Every member's steps, stored step-first: row t mod N of each field holds step t of every
    member (``(N, M, …)``), so members in step share one write head.

    Each step stores the code being executed and its index i. A sample's K-step future is read by
    index arithmetic (``idx[..., None] + arange(K)``), never by a Python loop; the newest K − 1
    steps are not sampled because their future is not written yet. ``count[m]`` is the number of
    steps member m has written: its head is ``count[m] mod N``.
    """

    FIELDS = ("obs", "next_obs", "code", "i", "reward", "terminated", "truncated")

    def __init__(self, capacity: int, obs_size: int, code_size: int, k: int,
                 device: torch.device, members: int = 1) -> None:
        self.capacity, self.k, self.device, self.members = capacity, k, device, members
        shape = (capacity, members)
        self.obs = torch.zeros((*shape, obs_size), device=device)
        self.next_obs = torch.zeros((*shape, obs_size), device=device)
        self.code = torch.zeros((*shape, code_size), device=device)
        self.i = torch.zeros(shape, dtype=torch.int64, device=device)
        self.reward = torch.zeros(shape, device=device)
        self.terminated = torch.zeros(shape, dtype=torch.bool, device=device)
        self.truncated = torch.zeros(shape, dtype=torch.bool, device=device)
        self.count = np.zeros(members, dtype=np.int64)

    def add(self, member: int, obs: np.ndarray, code: torch.Tensor, i: int, reward: float,
            next_obs: np.ndarray, terminated: bool, truncated: bool) -> None:
        row = int(self.count[member] % self.capacity)
        self.obs[row, member] = torch.as_tensor(obs, dtype=torch.float32)
        self.next_obs[row, member] = torch.as_tensor(next_obs, dtype=torch.float32)
        self.code[row, member] = code
        self.i[row, member] = i
        self.reward[row, member] = reward
        self.terminated[row, member] = terminated
        self.truncated[row, member] = truncated
        self.count[member] += 1

    def size(self, member: int) -> int:
        return int(min(self.count[member], self.capacity))

    def sampleable(self, member: int) -> int:
        return max(0, self.size(member) - (self.k - 1))

    def indices(self, batch_size: int,
                generators: Sequence[torch.Generator | None]) -> torch.Tensor:
        """``(M, B)`` rows to sample: member m's drawn from ``generators[m]``, uniform over its
        sampleable steps; a member given ``None`` draws nothing (it is not updated) and gets
        row 0."""
        rows = []
        for member, generator in enumerate(generators):
            if generator is None:
                rows.append(torch.zeros(batch_size, dtype=torch.int64, device=self.device))
                continue
            if self.sampleable(member) == 0:
                raise ValueError("the buffer holds no step whose K-step future is written")
            offset = torch.randint(self.sampleable(member), (batch_size,), generator=generator,
                                   device=generator.device)
            oldest = int(self.count[member]) - self.size(member)
            rows.append(((oldest + offset) % self.capacity).to(self.device))
        return torch.stack(rows)

    def gather(self, idx: torch.Tensor) -> ReplayBatch:
        """The batch at rows ``idx`` ``(M, B)``, every member from its own column."""
        member = torch.arange(self.members, device=self.device)[:, None]  # (M, 1)
        steps = (idx[..., None] + torch.arange(self.k, device=self.device)) % self.capacity
        return ReplayBatch(
            obs=self.obs[idx, member],
            code=self.code[idx, member],
            i=self.i[idx, member],
            rewards=self.reward[steps, member[..., None]],
            terminated=self.terminated[steps, member[..., None]],
            truncated=self.truncated[steps, member[..., None]],
            next_obs=self.next_obs[steps, member[..., None]],
        )

    def sample(self, batch_size: int, generators: Sequence[torch.Generator | None]) -> ReplayBatch:
        return self.gather(self.indices(batch_size, generators))

    def state_dict(self, member: int) -> dict[str, torch.Tensor]:
        """Member ``member``'s filled rows (row order) and its step count."""
        n = self.size(member)
        state = {name: getattr(self, name)[:n, member].cpu() for name in self.FIELDS}
        return state | {"count": torch.tensor(int(self.count[member]))}

    def load_state_dict(self, member: int, state: dict[str, torch.Tensor]) -> None:
        count = int(state["count"])
        n = min(count, self.capacity)
        for name in self.FIELDS:
            if state[name].shape[0] != n:
                raise ValueError(f"buffer.{name}: {state[name].shape[0]} rows, expected {n}")
            getattr(self, name)[:n, member] = state[name].to(self.device)
        self.count[member] = count


# The update -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class TargetParts:
    """Equation 1 split into what the networks must evaluate and what they multiply."""

    returns: torch.Tensor  # (..., B) discounted rewards of the steps that remain
    discount: torch.Tensor  # (..., B) γ^n, zero where the episode terminated
    bootstrap_obs: torch.Tensor  # (..., B, O) s_{t+n}
    keep_code: torch.Tensor  # (..., B) bool: a time limit cut the code short, it goes on
    next_i: torch.Tensor  # (..., B) 0 where a new code is chosen, i + n where it goes on


def k_step_targets(batch: ReplayBatch, gamma: float) -> TargetParts:
    """The parts of Equation 1 that need no network, for a batch, all batched.

    n = the steps that remain of each sample's code (K − i), cut after the first step where the
    episode ended (terminated or truncated). Powers of γ come from a table of K + 1 entries,
    indexed: elementwise and the same for every member whatever their number.
    """
    k = batch.rewards.shape[-1]
    powers = gamma ** torch.arange(k + 1, dtype=batch.rewards.dtype, device=batch.rewards.device)
    m = torch.arange(k, device=batch.rewards.device)  # (K,)
    remaining = k - batch.i  # (..., B)
    ended = batch.terminated | batch.truncated  # (..., B, K)
    ended_before = ended.cumsum(dim=-1) > ended  # an earlier step ended the episode
    valid = (m < remaining[..., None]) & ~ended_before  # (..., B, K)
    n = valid.sum(dim=-1)  # (..., B), >= 1
    returns = (valid * powers[:k] * batch.rewards).sum(dim=-1)  # (..., B)
    last = (n - 1)[..., None]  # (..., B, 1)
    terminal = batch.terminated.gather(-1, last).squeeze(-1)
    cut_short = batch.truncated.gather(-1, last).squeeze(-1) & (n < remaining)
    bootstrap_obs = batch.next_obs.gather(
        -2, last[..., None].expand(*last.shape, batch.next_obs.shape[-1])
    ).squeeze(-2)  # (..., B, K, O) -> (..., B, O)
    discount = torch.where(terminal, 0.0, powers[n])
    next_i = torch.where(cut_short, batch.i + n, torch.zeros_like(n))
    return TargetParts(returns, discount, bootstrap_obs, cut_short, next_i)


def _rows(tensors: list[torch.Tensor]) -> list[torch.Tensor]:
    """Every row of every stacked tensor, as a tensor of its own."""
    return [t[r] for t in tensors for r in range(t.shape[0])]


def _step_rows(params: list[torch.Tensor], steps: torch.Tensor) -> list[torch.Tensor]:
    """The step count of each row of :func:`_rows` ``(params)``: its member's."""
    return [steps[r % steps.shape[0]] for t in params for r in range(t.shape[0])]


def _adam_rows(params: list[torch.Tensor], grads: list[torch.Tensor],
               exp_avgs: list[torch.Tensor], exp_avg_sqs: list[torch.Tensor],
               steps: torch.Tensor, mask: torch.Tensor | None, lr: float, beta1: float,
               beta2: float, eps: float,
               rows: tuple[list[torch.Tensor], ...] | None = None) -> None:
    """torch's fused Adam kernel on each row of each stacked tensor in ``params`` as a tensor of
    its own, with the step count of the row's member (row r of a tensor belongs to member
    r mod M); members where ``mask`` is false keep everything bit for bit. ``rows``: the rows of
    ``params``, ``exp_avgs`` and ``exp_avg_sqs`` and their step counts, if already listed."""
    members = steps.shape[0]
    if mask is not None:
        kept = [t.clone() for t in (*params, *exp_avgs, *exp_avg_sqs)]
        steps.add_(mask.to(steps.dtype))
    else:
        steps.add_(1)
    if rows is None:
        rows = (_rows(params), _rows(exp_avgs), _rows(exp_avg_sqs), _step_rows(params, steps))
    param_rows, avg_rows, sq_rows, step_rows = rows
    torch._fused_adam_(
        param_rows, _rows(grads), avg_rows, sq_rows, [], step_rows,
        lr=lr, beta1=beta1, beta2=beta2, weight_decay=0.0, eps=eps, amsgrad=False,
        maximize=False,
    )
    if mask is not None:
        for tensor, old in zip((*params, *exp_avgs, *exp_avg_sqs), kept):
            keep = ~mask.repeat(tensor.shape[0] // members).view(-1, *[1] * (tensor.dim() - 1))
            torch.where(keep, old, tensor, out=tensor)


@torch.library.custom_op("ede::member_adam_", mutates_args=("param", "exp_avg", "exp_avg_sq",
                                                            "steps"))
def _member_adam(param: torch.Tensor, grad: torch.Tensor, exp_avg: torch.Tensor,
                 exp_avg_sq: torch.Tensor, steps: torch.Tensor, mask: torch.Tensor | None,
                 lr: float, beta1: float, beta2: float, eps: float) -> None:
    """:func:`_adam_rows` on whole flat tensors, as an operator of its own: what a compiled
    update calls (``torch.compile`` cannot trace the fused kernel on views of a parameter, and
    keeps an operator whole)."""
    _adam_rows([param], [grad], [exp_avg], [exp_avg_sq], steps, mask, lr, beta1, beta2, eps)


@_member_adam.register_fake
def _(param, grad, exp_avg, exp_avg_sq, steps, mask, lr, beta1, beta2, eps) -> None:  # noqa: ANN001
    return None


class MemberAdam:
    """Adam with a step count per member, on a :class:`ede.nets.StackedMLP`'s parameter, whose
    rows belong to members.

    The parameter is ``(R·M, N)``: row r belongs to member r mod M (R = 2 for the twin critics).
    Each layer of each row is stepped by torch's fused Adam kernel as a tensor of its own, so a
    member gets the same bits whatever M is (the kernel splits a tensor into vector and scalar
    parts by its size), in eager mode; compiled, each row is one tensor. torch's optimisers keep
    one step count per tensor and step every tensor they hold; here a member masked out of a
    step keeps its weights, moments and step count bit for bit.
    """

    def __init__(self, net: StackedMLP, members: int, lr: float,
                 betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8) -> None:
        self.net, self.param, self.members = net, net.flat, members
        self.lr, self.betas, self.eps = lr, betas, eps
        self.exp_avg = torch.zeros_like(self.param, memory_format=torch.contiguous_format)
        self.exp_avg_sq = torch.zeros_like(self.exp_avg)
        self.steps = torch.zeros(members, device=self.param.device)  # per member
        # Each layer's views of the weights and moments, and their rows with their step counts,
        # listed once (they stay valid: every change is in place).
        self._views = [_tensors(net.layers(t)) for t in
                       (self.param.detach(), self.exp_avg, self.exp_avg_sq)]
        self._rows = (*map(_rows, self._views), _step_rows(self._views[0], self.steps))

    def rows(self, per_member: torch.Tensor) -> torch.Tensor:
        """``(M,)`` -> ``(R·M, 1)``, each row its member's value."""
        return per_member.repeat(self.param.shape[0] // self.members)[:, None]

    def step(self, grads: list[torch.Tensor], mask: torch.Tensor | None = None) -> None:
        """One Adam step for every member, or for those where ``mask`` (``(M,)`` bool) is true;
        ``grads``: the gradient of each layer's weight and bias (``StackedMLP.layers``)."""
        hyper = (self.lr, *self.betas, self.eps)
        if torch.compiler.is_compiling():
            _member_adam(self.param.detach(), flatten(grads, self.param.shape[1]), self.exp_avg,
                         self.exp_avg_sq, self.steps, mask, *hyper)
            return
        params, exp_avgs, exp_avg_sqs = self._views
        # The fused kernel reads a tensor's memory in order: a weight's gradient from a batched
        # product comes transposed in memory.
        grads = [g.contiguous() for g in grads]
        _adam_rows(params, grads, exp_avgs, exp_avg_sqs, self.steps, mask, *hyper,
                   rows=self._rows)

    def state_of(self, member: int) -> dict[str, torch.Tensor]:
        rows = list(range(member, self.param.shape[0], self.members))
        return {"exp_avg": self.exp_avg[rows], "exp_avg_sq": self.exp_avg_sq[rows],
                "step": self.steps[member]}

    def load_state_of(self, member: int, state: dict[str, torch.Tensor]) -> None:
        rows = list(range(member, self.param.shape[0], self.members))
        self.exp_avg[rows] = state["exp_avg"].to(self.exp_avg.device)
        self.exp_avg_sq[rows] = state["exp_avg_sq"].to(self.exp_avg.device)
        self.steps[member] = state["step"].to(self.steps.device)


def polyak(target: torch.Tensor, source: torch.Tensor, tau: float,
           mask: torch.Tensor | None = None) -> None:
    """target ← (1 − τ) target + τ source, in place, for every row or the rows where ``mask``
    (``(rows, 1)`` bool) is true."""
    with torch.no_grad():
        if mask is None:
            target.lerp_(source, tau)
        else:
            target.copy_(torch.where(mask, target.lerp(source, tau), target))


def _tensors(layers: Layers) -> list[torch.Tensor]:
    return [t.detach() for layer in layers for t in layer]


def _layers(tensors: list[torch.Tensor]) -> Layers:
    return list(zip(tensors[::2], tensors[1::2]))


class Agent:
    """The TD3 learner of M members over any :class:`ActionAdapter` (TD3: identity, EDE-TD3: the
    decoder). A single run is M = 1; member m is the run of seed ``seeds[m]``.

    Every network holds its members on a leading axis (:class:`ede.nets.StackedMLP`); an update
    is one function of tensors (:meth:`step`) for every member at once, each on its own batch
    and target noise, drawn from its own generators (:meth:`draw`), each with the gradient it
    would get alone (losses are means over B, summed over members). Members not due an update
    are masked: they keep their weights and optimiser states.
    """

    def __init__(
        self,
        obs_size: int,
        adapter: ActionAdapter,
        config: TD3Config,
        device: torch.device,
        seeds: Sequence[int] = (0,),
    ) -> None:
        self.adapter, self.config, self.device = adapter, config, device
        self.members = len(seeds)
        self.streams = [Streams(seed, device) for seed in seeds]
        low, high = adapter.code_low.cpu(), adapter.code_high.cpu()
        self.scale = adapter.noise_scale  # (C,) the unit of the noise stds
        self.target_scale = self.scale * adapter.target_noise_scale
        weights = [s.weights for s in self.streams]
        self.actor = Actor(obs_size, low, high, config.hidden, weights).to(device)
        self.critic = Critic(obs_size, adapter.code_size, adapter.k, config.hidden,
                             adapter.plan_step, config.critic_action_repeat, weights).to(device)
        self.actor_target = copy.deepcopy(self.actor).requires_grad_(False)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.actor_optimizer = MemberAdam(self.actor.net, self.members, config.lr)
        self.critic_optimizer = MemberAdam(self.critic.net, self.members, config.lr)
        self.updates = np.zeros(self.members, dtype=np.int64)  # critic steps, per member
        self.autocast = config.precision == "bf16"
        # Sums per member since the last take_diagnostics(), kept on the device so that no
        # update waits for the host: critic loss, critic steps, actor loss (−mean Q(s, μ(s), 0)),
        # actor steps.
        self.loss_sums = torch.zeros(4, self.members, device=device)
        self._step = self._step_eager if config.compile == "none" else torch.compile(
            self._step_eager, fullgraph=True,
            mode=None if config.compile == "default" else config.compile)

    def clip(self, codes: torch.Tensor) -> torch.Tensor:
        return codes.clamp(self.adapter.code_low, self.adapter.code_high)

    # Acting, one member at a time ----------------------------------------------------------

    @torch.no_grad()
    def act(self, member: int, obs: np.ndarray, explore: bool) -> torch.Tensor:
        """Member ``member``'s code for one observation: μ(s), plus exploration noise from its
        own stream when ``explore``."""
        x = torch.as_tensor(obs, dtype=torch.float32, device=self.device)[None]
        code = self.actor.one(member, x)[0]
        if explore:
            noise = torch.randn(code.shape, generator=self.streams[member].exploration,
                                device=self.device)
            code = self.clip(code + noise * self.config.exploration_noise * self.scale)
        return code

    def random_code(self, member: int) -> torch.Tensor:
        """A code uniform in the box: the start-steps behaviour."""
        low, high = self.adapter.code_low, self.adapter.code_high
        u = torch.rand(low.shape, generator=self.streams[member].start_codes, device=self.device)
        return low + u * (high - low)

    # Updating, every member at once ----------------------------------------------------------

    def draw(self, buffer: ReplayBuffer, due: np.ndarray) -> tuple[ReplayBatch, torch.Tensor]:
        """The random part of an update: each due member's batch and target noise, drawn from
        its own generators (members not due draw nothing)."""
        c = self.config
        replay = [s.replay if d else None for s, d in zip(self.streams, due)]
        batch = buffer.sample(c.batch_size, replay)
        shape = (c.batch_size, self.adapter.code_size)
        noise = torch.stack([
            torch.randn(shape, generator=s.target_noise, device=self.device) if d
            else torch.zeros(shape, device=self.device)
            for s, d in zip(self.streams, due)
        ])
        return batch, noise

    def update(self, buffer: ReplayBuffer, due: np.ndarray | None = None) -> None:
        """One TD3 update of the members where ``due`` (``(M,)`` bool; every member by default):
        a critic step, and every ``policy_delay`` of a member's critic steps an actor step and
        target moves. Its matrix products follow ``td3.precision``."""
        due = np.ones(self.members, dtype=bool) if due is None else np.asarray(due, dtype=bool)
        batch, noise = self.draw(buffer, due)
        self.step(batch, noise, due)

    def step(self, batch: ReplayBatch, noise: torch.Tensor, due: np.ndarray) -> None:
        """:meth:`update` on a drawn batch and raw (unit) target noise ``(M, B, C)``."""
        actor_due = due & ((self.updates + 1) % self.config.policy_delay == 0)
        self.updates += due
        masks = torch.as_tensor(np.stack([due, actor_due]), device=self.device)
        with matmul_precision(self.config.precision):
            self._step(batch, noise, masks, bool(actor_due.any()), not due.all(),
                       not actor_due.all())

    def _autocast(self) -> torch.autocast:
        return torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.autocast)

    def target(self, batch: ReplayBatch, noise: torch.Tensor) -> torch.Tensor:
        """Equation 1 with TD3's clipped double-Q and target policy smoothing, ``(M, B)``;
        ``noise`` is unit normal ``(M, B, C)``."""
        c = self.config
        parts = k_step_targets(batch, c.discount)
        with torch.no_grad(), self._autocast():
            noise = noise * c.policy_noise * self.target_scale
            clip = c.noise_clip * self.adapter.clip_scale
            noise = torch.maximum(torch.minimum(noise, clip), -clip)
            chosen = self.clip(self.actor_target(parts.bootstrap_obs) + noise)
            next_code = torch.where(parts.keep_code[..., None], batch.code, chosen)
            q = self.critic_target(parts.bootstrap_obs, next_code, parts.next_i)
            return parts.returns + parts.discount * q.amin(0).float()

    def _critic_losses(self, params: list[torch.Tensor], batch: ReplayBatch,
                       target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        with self._autocast():
            q = self.critic(batch.obs, batch.code, batch.i, _layers(params)).float()  # (2, M, B)
        losses = ((q - target) ** 2).mean(-1).sum(0)  # (M,): each member's two MSEs
        return losses.sum(), losses

    def _actor_losses(self, params: list[torch.Tensor], obs: torch.Tensor,
                      critic: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        # The actor follows ∇_c Q_1(s, c, 0) (Equation 2); Q's weights are constants here.
        with self._autocast():
            codes = self.actor(obs, _layers(params))
            start = torch.zeros(obs.shape[:2], dtype=torch.int64, device=obs.device)
            losses = -self.critic.first(obs, codes, start, critic).float().mean(-1)  # (M,)
        return losses.sum(), losses

    def _step_eager(self, batch: ReplayBatch, noise: torch.Tensor, masks: torch.Tensor,
                    actor: bool, critic_masked: bool, actor_masked: bool) -> None:
        """The update as one function of tensors (no host synchronisation): what
        ``td3.compile`` compiles. ``masks``: ``(2, M)`` bool, the members due a critic step
        and an actor step; the flags say, from the host, whether any actor step is due and
        whether either mask leaves a member out."""
        c, due, actor_due = self.config, masks[0], masks[1]
        target = self.target(batch, noise)
        # Gradients by layer: of views of the flat rows (a gradient of the flat parameter itself
        # would be scattered layer by layer into zeros).
        critic, policy = self.critic.net, self.actor.net
        grads, losses = gradients(self._critic_losses, _tensors(critic.layers(critic.flat)),
                                  batch, target)
        self.critic_optimizer.step(grads, due if critic_masked else None)
        self.loss_sums[0] += torch.where(due, losses, 0.0)
        self.loss_sums[1] += due
        if not actor:
            return
        grads, losses = gradients(self._actor_losses, _tensors(policy.layers(policy.flat)),
                                  batch.obs, critic.flat.detach())
        self.actor_optimizer.step(grads, actor_due if actor_masked else None)
        self.loss_sums[2] += torch.where(actor_due, losses, 0.0)
        self.loss_sums[3] += actor_due
        mask = None if not actor_masked else actor_due
        polyak(self.critic_target.net.flat, self.critic.net.flat, c.tau,
               None if mask is None else self.critic_optimizer.rows(mask))
        polyak(self.actor_target.net.flat, self.actor.net.flat, c.tau,
               None if mask is None else self.actor_optimizer.rows(mask))

    def take_diagnostics(self, member: int) -> dict[str, float]:
        """Member ``member``'s means over its updates since its last call (one host
        synchronisation), then its sums reset.

        Returns:
            ``updates`` (critic steps), ``critic_loss``, ``actor_loss`` and ``mean_q``, the mean
            of Q_1(s, μ(s), 0) over the actor steps' batches (NaN where there was no step).
        """
        critic, critic_steps, actor, actor_steps = self.loss_sums[:, member].tolist()
        self.loss_sums[:, member] = 0
        nan = float("nan")
        return {
            "updates": int(critic_steps),
            "critic_loss": critic / critic_steps if critic_steps else nan,
            "actor_loss": actor / actor_steps if actor_steps else nan,
            "mean_q": -actor / actor_steps if actor_steps else nan,
        }

    def non_finite(self) -> dict[int, str]:
        """The members whose losses since their last :meth:`take_diagnostics` are not finite
        (one host synchronisation), each with the quantity: the critic's loss, or the actor's
        (minus its Q value)."""
        finite = torch.isfinite(self.loss_sums[[0, 2]]).tolist()  # (2, M)
        names = ("the critic's loss", "the actor's loss (its Q value)")
        return {m: names[0] if not finite[0][m] else names[1]
                for m in range(self.members) if not (finite[0][m] and finite[1][m])}

    # State, one member at a time ---------------------------------------------------------------

    def state_dict(self, member: int) -> dict[str, torch.Tensor]:
        """Member ``member``'s learner state, as a run alone holds it (``docs/``: checkpoint
        format): each network's row(s) of flat weights, each optimiser's moments and step,
        its counters, diagnostics sums and generator states."""
        rows = [member, self.members + member]
        state = {
            "actor": self.actor.net.flat[member],
            "actor_target": self.actor_target.net.flat[member],
            "critic": self.critic.net.flat[rows],
            "critic_target": self.critic_target.net.flat[rows],
            "updates": torch.tensor(int(self.updates[member])),
            "loss_sums": self.loss_sums[:, member],
        }
        for name, optimizer in (("actor_optimizer", self.actor_optimizer),
                                ("critic_optimizer", self.critic_optimizer)):
            state |= {f"{name}.{k}": v for k, v in optimizer.state_of(member).items()}
        for purpose in Streams.SAVED:
            state[f"generator.{purpose}"] = getattr(self.streams[member], purpose).get_state()
        return {k: v.detach().cpu().clone() for k, v in state.items()}

    @torch.no_grad()
    def load_state_dict(self, member: int, state: dict[str, torch.Tensor]) -> None:
        """Member ``member`` continues from ``state`` (:meth:`state_dict`'s, from any M)."""
        rows = [member, self.members + member]
        for name, module in (("actor", self.actor), ("actor_target", self.actor_target)):
            module.net.flat[member] = state[name].to(self.device)
        for name, module in (("critic", self.critic), ("critic_target", self.critic_target)):
            module.net.flat[rows] = state[name].to(self.device)
        self.updates[member] = int(state["updates"])
        self.loss_sums[:, member] = state["loss_sums"].to(self.device)
        for name, optimizer in (("actor_optimizer", self.actor_optimizer),
                                ("critic_optimizer", self.critic_optimizer)):
            optimizer.load_state_of(member, {k: state[f"{name}.{k}"]
                                             for k in ("exp_avg", "exp_avg_sq", "step")})
        for purpose in Streams.SAVED:
            getattr(self.streams[member], purpose).set_state(state[f"generator.{purpose}"])
