"""TD3 and EDE-TD3: one agent, one replay buffer, one update.

TD3 (Fujimoto et al., 2018) is the special case k = 1 of EDE-TD3 (Section 3 of the paper): the
two differ only through an :class:`ActionAdapter` — the identity for TD3, the learned decoder for
EDE-TD3 — which fixes what the actor outputs (a raw action, or a whitened code z of k actions),
its bounds, and k.

Shapes: M members (the runs an agent trains at once; 1 for a run alone), B batch, K actions per
code (1 for TD3), A action size, C code size (A for TD3, D for EDE-TD3), O observation size.
:class:`TD3` is the update of one member; :class:`Agent` holds M members stacked
(:mod:`ede.method.ensemble`, the one module that knows their layout) and runs that update on all of
them at once, each computing what it computes alone, from its own random streams
(:class:`Streams`).

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

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple, Protocol

import numpy as np
import torch
import torch.nn.functional as F

from ede.config import TD3Config
from ede.method import ensemble
from ede.method.embedding import ActionEmbedding
from ede.method.ensemble import Params
from ede.method.nets import initial_mlp, matmul_precision, to_device

if TYPE_CHECKING:
    from ede.run.vector import MemberEnvs

__all__ = [
    "TD3",
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
        """(B, D) -> (B, K, A), each code alone (:func:`ede.method.ensemble.row_by_row`): a member's
        actions do not depend on how many members chose a code with it."""
        return ensemble.row_by_row(self.embedding.decode, codes)


class CodeStep(NamedTuple):
    """One environment step of every member's code (rows of members that sat it out: unused)."""

    code: torch.Tensor  # (M, C) the codes being executed
    i: np.ndarray  # (M,) steps of each executed before this one
    action: np.ndarray  # (M, A) each code's i-th action
    reward: np.ndarray  # (M,)
    next_obs: np.ndarray  # (M, O)
    terminated: np.ndarray  # (M,) bool
    truncated: np.ndarray  # (M,) bool

    @property
    def ended(self) -> np.ndarray:
        return self.terminated | self.truncated


class CodeExecutor:
    """Acts in M members' environments with codes (Section 3), one step of them at a time.

    For each member, when its i = 0 the policy chooses a code, which the adapter decodes into K
    actions; they are executed in order, one per step, and the next code is chosen after the K-th
    — or at the first step of the next episode, since an episode's end cuts the code short. Its
    state (each member's code, its actions, i) is part of a training run's checkpoint.

    A step is two calls, so that the caller can look at the codes before any environment moves
    (a code that is not finite stops its run there): :meth:`choose`, then :meth:`step`.
    """

    def __init__(self, envs: MemberEnvs, adapter: ActionAdapter) -> None:
        space = envs.vector.single_action_space
        self.envs, self.adapter, members = envs, adapter, envs.members
        self.code = torch.zeros(members, adapter.code_size, device=adapter.code_low.device)
        self.plan = np.zeros((members, adapter.k, *(space.shape or ())), dtype=space.dtype)
        self.i = np.zeros(members, dtype=np.int64)  # steps of each code executed
        self._rows = np.arange(members)

    def choose(
        self,
        obs: np.ndarray,
        policy: Callable[[np.ndarray, np.ndarray], torch.Tensor],
        members: np.ndarray,
    ) -> np.ndarray:
        """New codes for the members of ``members`` (``(M,)`` bool) at i = 0: rows of
        ``policy(obs, choosing)`` ``(M, O) -> (M, C)``. Returns ``choosing``."""
        choosing = members & (self.i == 0)
        if choosing.all():  # every member: the common case, without indexing
            self.code = policy(obs, choosing)  # (M, C)
            self.plan = self.adapter.decode(self.code).cpu().numpy()  # the group's one host copy
        elif choosing.any():
            rows = torch.as_tensor(np.flatnonzero(choosing), device=self.code.device)
            codes = policy(obs, choosing)[rows]  # (M, C) -> (N, C)
            self.code[rows] = codes
            plans = self.adapter.decode(codes)  # (N, C) -> (N, K, A)
            self.plan[choosing] = plans.cpu().numpy()  # the group's one copy to the host
        return choosing

    def step(self, members: np.ndarray) -> CodeStep:
        """One environment step of the members in ``members``, each with its code's next
        action."""
        i = self.i
        action = self.plan[self._rows, i]  # (M, K, A) -> (M, A)
        next_obs, reward, terminated, truncated = self.envs.step(action, members)
        if self.adapter.k > 1:  # (with k = 1 every step chooses: i stays 0)
            after = (i + 1) % self.adapter.k  # an episode's end cuts the code short: i = 0
            after[terminated | truncated] = 0
            self.i = np.where(members, after, i)
        return CodeStep(self.code.clone(), i, action, reward, next_obs, terminated, truncated)

    def episodes(
        self,
        policy: Callable[[np.ndarray, np.ndarray], torch.Tensor],
        episodes: int,
        seeds: Sequence[int],
        members: np.ndarray,
    ) -> Iterator[tuple[CodeStep, np.ndarray, np.ndarray]]:
        """``episodes`` episodes of each member of ``members``, one after another, episode e of
        member m from ``reset(seeds[m] + e)``; the members step together, each through its own
        episodes. Yields each step with the members that took it and the episode each is in."""
        members = np.asarray(members, dtype=bool)
        done = np.zeros(len(members), dtype=np.int64)  # episodes ended, per member
        seeds = [int(s) for s in seeds]
        obs = self.envs.reset(members, seeds)
        self.i[members] = 0
        while members.any():
            self.choose(obs, policy, members)
            step = self.step(members)
            yield step, members, done
            ended = step.ended  # (only members step)
            if ended.any():  # each starts its next (one done, an unused one: the vector wants it)
                done = done + ended
                members = members & (done < episodes)
                obs = self.envs.reset(ended, [s + int(e) for s, e in zip(seeds, done, strict=True)])
            else:
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


# Networks: functions of one member's parameters ----------------------------------------------


class Actor:
    """μ(s): a code inside [low, high] through a tanh, ``(..., O) -> (..., C)``.

    Its parameters are an ``ede.method.nets.mlp``'s (``0.weight``, ``0.bias``, ...): one member's, or
    a stack of members' (:mod:`ede.method.ensemble`).
    """

    def __init__(
        self, obs_size: int, low: torch.Tensor, high: torch.Tensor, hidden: list[int]
    ) -> None:
        self.sizes = [obs_size, *hidden, len(low)]
        self.centre, self.half_range = (high + low) / 2, (high - low) / 2

    def initial(self, generator: torch.Generator) -> Params:
        return initial_mlp(self.sizes, generator)

    def __call__(self, params: Params, obs: torch.Tensor) -> torch.Tensor:
        return self.squash(ensemble.mlp(params, obs))

    def squash(self, raw: torch.Tensor) -> torch.Tensor:
        """The network's output into the box."""
        return self.centre + self.half_range * torch.tanh(raw)

    def export(self, params: Params) -> dict[str, torch.Tensor]:
        """One member's actor as ``policy.safetensors`` names it: ``net.0.weight``, ...,
        ``centre``, ``half_range``."""
        return {f"net.{k}": v for k, v in params.items()} | {
            "centre": self.centre,
            "half_range": self.half_range,
        }


def critic_repeat(setting: int | str, obs_size: int, pair_size: int) -> int:
    """How many times the critic sees (code, i): ``setting``, or for "auto" the authors' rule,
    max(1, ⌊0.5·O / pair size⌋) (their ``action_repeat``, docs/fidelity.md rows 7a–7b)."""
    if setting == "auto":
        return max(1, int(0.5 * obs_size // pair_size))
    return int(setting)


class Critic:
    """Twin Q(s, c, i) over (observation, then ``repeat`` copies of (code, i)), ``(..., B)`` each.

    i is a one-hot of size K (``plan_step="onehot"``) or the raw count as one input ("scalar", the
    authors' code); it is absent when K = 1. The twins are one ``ede.method.nets.mlp``'s parameters
    with a twin axis first (``0.weight`` ``(2, out, in)``: Q1's, then Q2's), evaluated together.
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
        self.k, self.plan_step = k, plan_step
        step_size = 0 if k == 1 else (k if plan_step == "onehot" else 1)
        self.repeat = critic_repeat(repeat, obs_size, code_size + step_size)
        self.sizes = [obs_size + self.repeat * (code_size + step_size), *hidden, 1]

    def initial(self, generator: torch.Generator) -> Params:
        q1, q2 = (initial_mlp(self.sizes, generator) for _ in range(2))  # Q1 drawn first
        return {name: torch.stack([q1[name], q2[name]]) for name in q1}

    def inputs(self, obs: torch.Tensor, code: torch.Tensor, i: torch.Tensor) -> torch.Tensor:
        pair = [code]
        if self.k > 1 and self.plan_step == "onehot":
            pair.append(F.one_hot(i, self.k).to(obs.dtype))  # (..., B) -> (..., B, K)
        elif self.k > 1:
            pair.append(i.to(obs.dtype)[..., None])  # (..., B) -> (..., B, 1)
        return torch.cat([obs, *pair * self.repeat], dim=-1)

    def __call__(
        self, params: Params, obs: torch.Tensor, code: torch.Tensor, i: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Q1 and Q2."""
        x = self.inputs(obs, code, i)
        q = ensemble.mlp(params, torch.stack([x, x], dim=-3))  # (..., B, in) -> (..., 2, B, 1)
        return q[..., 0, :, 0], q[..., 1, :, 0]

    def q1(
        self, params: Params, obs: torch.Tensor, code: torch.Tensor, i: torch.Tensor
    ) -> torch.Tensor:
        """Q1 alone."""
        # The twin axis is a weight's third dimension from the end, a bias's second.
        first = {k: v.select(-3 if k.endswith("weight") else -2, 0) for k, v in params.items()}
        return ensemble.mlp(first, self.inputs(obs, code, i)).squeeze(-1)  # (..., B, 1) -> (..., B)


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

    def __init__(
        self,
        capacity: int,
        obs_size: int,
        code_size: int,
        k: int,
        device: torch.device,
        members: int = 1,
    ) -> None:
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

    def add(
        self,
        members: np.ndarray,
        obs: np.ndarray,
        code: torch.Tensor,
        i: np.ndarray,
        reward: np.ndarray,
        next_obs: np.ndarray,
        terminated: np.ndarray,
        truncated: np.ndarray,
    ) -> None:
        """One step of each member in ``members`` (``(M,)`` bool), from its rows of the others
        (``(M, ...)``): one write per field for the group, each member at its own head."""
        which = np.flatnonzero(members)
        values = {
            "obs": obs,
            "next_obs": next_obs,
            "code": code,
            "i": i,
            "reward": reward,
            "terminated": terminated,
            "truncated": truncated,
        }
        heads = self.count[which] % self.capacity
        if len(which) == self.members and (heads == heads[0]).all():  # in step: one row
            for name, value in values.items():
                row = getattr(self, name)[int(heads[0])]
                row.copy_(value if isinstance(value, torch.Tensor) else torch.from_numpy(value))
        else:
            rows = torch.as_tensor(heads, device=self.device)
            cols = torch.as_tensor(which, device=self.device)
            for name, value in values.items():
                field = getattr(self, name)
                field[rows, cols] = torch.as_tensor(value, dtype=field.dtype, device=self.device)[
                    cols
                ]
        self.count[which] += 1

    def size(self, member: int) -> int:
        return int(min(self.count[member], self.capacity))

    def sampleable(self, member: int) -> int:
        return max(0, self.size(member) - (self.k - 1))

    def indices(
        self, batch_size: int, generators: Sequence[torch.Generator | None]
    ) -> torch.Tensor:
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
            offset = torch.randint(
                self.sampleable(member), (batch_size,), generator=generator, device=generator.device
            )
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


class TD3:
    """TD3's update (Fujimoto et al., 2018) for one member, over an :class:`ActionAdapter`: the
    target, the critic's loss and the actor's, as functions of the member's parameters and batch.

    Nothing here knows about members: every operation acts on trailing dimensions, so
    :mod:`ede.method.ensemble` runs the same functions on M members stacked on a leading axis.
    """

    def __init__(
        self, actor: Actor, critic: Critic, adapter: ActionAdapter, config: TD3Config
    ) -> None:
        self.actor, self.critic, self.adapter, self.config = actor, critic, adapter, config
        self.autocast = config.precision == "bf16"

    def clip(self, codes: torch.Tensor) -> torch.Tensor:
        return codes.clamp(self.adapter.code_low, self.adapter.code_high)

    def _autocast(self, device: torch.device) -> torch.autocast:
        return torch.autocast(device.type, dtype=torch.bfloat16, enabled=self.autocast)

    @torch.no_grad()
    def target(
        self, actor_target: Params, critic_target: Params, batch: ReplayBatch, noise: torch.Tensor
    ) -> torch.Tensor:
        """Equation 1 with clipped double-Q and target policy smoothing, ``(B,)``; ``noise``: a
        unit normal draw ``(B, C)``."""
        c, adapter = self.config, self.adapter
        parts = k_step_targets(batch, c.discount)
        with self._autocast(batch.obs.device):
            clip = c.noise_clip * adapter.clip_scale
            noise = noise * c.policy_noise * adapter.noise_scale * adapter.target_noise_scale
            noise = torch.maximum(torch.minimum(noise, clip), -clip)
            chosen = self.clip(self.actor(actor_target, parts.bootstrap_obs) + noise)
            # Where a time limit cut the code short, the code goes on (c' = c).
            next_code = torch.where(parts.keep_code[..., None], batch.code, chosen)
            q1, q2 = self.critic(critic_target, parts.bootstrap_obs, next_code, parts.next_i)
            return parts.returns + parts.discount * torch.minimum(q1, q2).float()

    def critic_loss(self, critic: Params, batch: ReplayBatch, y: torch.Tensor) -> torch.Tensor:
        """Both twins' mean squared error to the target ``y``, summed."""
        with self._autocast(batch.obs.device):
            q1, q2 = self.critic(critic, batch.obs, batch.code, batch.i)
        return ((q1.float() - y) ** 2).mean(-1) + ((q2.float() - y) ** 2).mean(-1)

    def actor_loss(self, actor: Params, critic: Params, obs: torch.Tensor) -> torch.Tensor:
        """−Q_1(s, μ(s), 0): the actor follows ∇_c Q_1(s, c, 0) (Equation 2), Q fixed."""
        with self._autocast(obs.device):
            start = torch.zeros(obs.shape[:-1], dtype=torch.int64, device=obs.device)
            q1 = self.critic.q1(critic, obs, self.actor(actor, obs), start)
        return -q1.float().mean(-1)


class Agent:
    """The TD3 learner of M members over any :class:`ActionAdapter` (TD3: identity, EDE-TD3: the
    decoder). A single run is M = 1; member m is the run of seed ``seeds[m]``.

    Its networks and optimiser states hold the members stacked (:mod:`ede.method.ensemble`); an update
    runs :class:`TD3`'s functions on every member at once, each on its own batch and target
    noise drawn from its own generators (:meth:`draw`). Members not due an update keep their
    weights and optimiser states.
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
        actor = Actor(obs_size, adapter.code_low, adapter.code_high, config.hidden)
        critic = Critic(
            obs_size,
            adapter.code_size,
            adapter.k,
            config.hidden,
            adapter.plan_step,
            config.critic_action_repeat,
        )
        self.td3 = TD3(actor, critic, adapter, config)
        # Each member draws its actor's initial weights, then its critic's, from its own stream.
        initial = [(actor.initial(s.weights), critic.initial(s.weights)) for s in self.streams]
        self.actor = ensemble.Stack([a for a, _ in initial], device)
        self.critic = ensemble.Stack([c for _, c in initial], device, networks=2)  # the twins
        self.actor_target, self.critic_target = self.actor.clone(), self.critic.clone()
        self._acting = ensemble.one_row_layers(self.actor.params)  # views of the live weights
        self.actor_adam = ensemble.Adam(self.actor, config.lr)
        self.critic_adam = ensemble.Adam(self.critic, config.lr)
        # Each member's critic steps: the one count of its updates (its actor steps follow).
        self.updates = np.zeros(self.members, dtype=np.int64)
        # Sums per member since the last take_diagnostics(), kept on the device so that no
        # update waits for the host: critic loss, critic steps, actor loss (−mean Q(s, μ(s), 0)),
        # actor steps. A module's buffer, as the networks are (ensemble.Stack says why).
        self._sums = torch.nn.Module()
        self._sums.register_buffer("losses", torch.zeros(4, self.members, device=device))
        self._update = (
            self._update_eager
            if config.compile == "none"
            else torch.compile(
                self._update_eager,
                fullgraph=True,
                mode=None if config.compile == "default" else config.compile,
            )
        )

    @property
    def loss_sums(self) -> torch.Tensor:
        """``(4, M)``: each member's sums since its last :meth:`take_diagnostics`."""
        return self._sums.get_buffer("losses")

    # Acting, every member at once ----------------------------------------------------------

    @torch.no_grad()
    def act(self, obs: np.ndarray) -> torch.Tensor:
        """μ(s) of every member for its observation, ``(M, O) -> (M, C)``: one forward of the
        stacked actor."""
        x = torch.as_tensor(obs, dtype=torch.float32, device=self.device)[:, None]  # (M, 1, O)
        raw = ensemble.one_row_each(self._acting, x)  # (M, 1, O) -> (M, 1, C)
        return self.td3.actor.squash(raw[:, 0])

    @torch.no_grad()
    def behave(self, obs: np.ndarray, members: np.ndarray, uniform: np.ndarray) -> torch.Tensor:
        """The codes training acts with, ``(M, C)``, for the members of ``members``: uniform in
        the box where ``uniform`` (the start steps), else μ(s) plus exploration noise; every
        draw from the member's own stream (rows of other members: unused)."""
        low, high, scale = self.adapter.code_low, self.adapter.code_high, self.adapter.noise_scale
        draw = self._draw
        if (members & ~uniform).all():  # every member explores: the common case, in one piece
            noise = torch.stack([draw(torch.randn, m, "exploration") for m in range(self.members)])
            return self.td3.clip(self.act(obs) + noise * self.config.exploration_noise * scale)
        codes = low.repeat(len(obs), 1)  # (M, C)
        explore, start = members & ~uniform, members & uniform
        if start.any():
            rows = np.flatnonzero(start)
            u = torch.stack([draw(torch.rand, int(m), "start_codes") for m in rows])
            codes[rows] = low + u * (high - low)
        if explore.any():
            rows = np.flatnonzero(explore)
            noise = torch.stack([draw(torch.randn, int(m), "exploration") for m in rows])
            mean = self.act(obs)[rows]  # (N, C)
            codes[rows] = self.td3.clip(mean + noise * self.config.exploration_noise * scale)
        return codes

    def _draw(self, sample: Callable[..., torch.Tensor], member: int, purpose: str) -> torch.Tensor:
        """One code's worth ``(C,)`` of ``sample`` from member ``member``'s stream ``purpose``."""
        generator = getattr(self.streams[member], purpose)
        return sample(self.adapter.code_size, generator=generator, device=self.device)

    def policy(self, member: int) -> dict[str, torch.Tensor]:
        """Member ``member``'s actor as ``policy.safetensors`` holds it."""
        return self.td3.actor.export(self.actor.member(member))

    # Updating, every member at once ----------------------------------------------------------

    def draw(self, buffer: ReplayBuffer, due: np.ndarray) -> tuple[ReplayBatch, torch.Tensor]:
        """The random part of an update: each due member's batch and target noise, drawn from
        its own generators (members not due draw nothing)."""
        c = self.config
        replay = [s.replay if d else None for s, d in zip(self.streams, due, strict=True)]
        batch = buffer.sample(c.batch_size, replay)
        shape = (c.batch_size, self.adapter.code_size)
        noise = torch.stack(
            [
                torch.randn(shape, generator=s.target_noise, device=self.device)
                if d
                else torch.zeros(shape, device=self.device)
                for s, d in zip(self.streams, due, strict=True)
            ]
        )
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
        delay = self.config.policy_delay
        actor_due = due & ((self.updates + 1) % delay == 0)
        self.updates += due
        corrections = torch.stack(
            [
                self.critic_adam.corrections(self.updates, self.device),
                self.actor_adam.corrections(self.updates // delay, self.device),
            ]
        )
        masks = to_device(np.stack([due, actor_due]), self.device)
        with matmul_precision(self.config.precision):
            self._update(
                batch,
                noise,
                masks,
                corrections,
                bool(actor_due.any()),
                not due.all(),
                not actor_due.all(),
            )

    def _update_eager(
        self,
        batch: ReplayBatch,
        noise: torch.Tensor,
        masks: torch.Tensor,
        corrections: torch.Tensor,
        actor: bool,
        critic_masked: bool,
        actor_masked: bool,
    ) -> None:
        """The update as one function of tensors (no host synchronisation): what
        ``td3.compile`` compiles. ``masks``: ``(2, M)`` bool, the members due a critic step and
        an actor step; ``corrections``: ``(2, 2, M)``, each optimiser's :meth:`Adam.corrections`;
        the flags say, from the host, whether any actor step is due and whether either mask
        leaves a member out."""
        td3, due, actor_due = self.td3, masks[0], masks[1]
        y = td3.target(self.actor_target.params, self.critic_target.params, batch, noise)
        grad, losses = ensemble.grad(td3.critic_loss, self.critic, batch, y)
        self.critic_adam.step(grad, corrections[0], due if critic_masked else None)
        self.loss_sums[0] += torch.where(due, losses, 0.0)
        self.loss_sums[1] += due
        if not actor:
            return
        grad, losses = ensemble.grad(td3.actor_loss, self.actor, self.critic.params, batch.obs)
        mask = actor_due if actor_masked else None
        self.actor_adam.step(grad, corrections[1], mask)
        self.loss_sums[2] += torch.where(actor_due, losses, 0.0)
        self.loss_sums[3] += actor_due
        self.critic_target.polyak(self.critic, self.config.tau, mask)
        self.actor_target.polyak(self.actor, self.config.tau, mask)

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
        return {
            m: names[0] if not finite[0][m] else names[1]
            for m in range(self.members)
            if not (finite[0][m] and finite[1][m])
        }

    # State, one member at a time ---------------------------------------------------------------

    def _member(self, member: int) -> dict[str, Params]:
        """Member ``member``'s networks and optimiser moments (views), by checkpoint prefix."""
        state = {
            "actor": self.actor.member(member),
            "actor_target": self.actor_target.member(member),
            "critic": self.critic.member(member),
            "critic_target": self.critic_target.member(member),
        }
        for name, adam in (("actor_adam", self.actor_adam), ("critic_adam", self.critic_adam)):
            state |= {f"{name}.{moment}": views for moment, views in adam.member(member).items()}
        return state

    def state_dict(self, member: int) -> dict[str, torch.Tensor]:
        """Member ``member``'s learner state, as a run alone holds it (``ede/run/checkpoint.py``):
        each network's parameters (``actor.0.weight``, ``critic.0.weight`` (Q1's and Q2's), ...),
        each optimiser's moments (``actor_adam.exp_avg.0.weight``, ...), its update count,
        diagnostics sums and generator states."""
        state = {
            f"{prefix}.{k}": v
            for prefix, params in self._member(member).items()
            for k, v in params.items()
        }
        state["updates"] = torch.tensor(int(self.updates[member]))
        state["loss_sums"] = self.loss_sums[:, member]
        for purpose in Streams.SAVED:
            state[f"generator.{purpose}"] = getattr(self.streams[member], purpose).get_state()
        return {k: v.detach().cpu().clone() for k, v in state.items()}

    @torch.no_grad()
    def load_state_dict(self, member: int, state: dict[str, torch.Tensor]) -> None:
        """Member ``member`` continues from ``state`` (:meth:`state_dict`'s, from any M)."""
        for prefix, params in self._member(member).items():
            for k, v in params.items():
                v.copy_(state[f"{prefix}.{k}"])
        self.updates[member] = int(state["updates"])
        self.loss_sums[:, member] = state["loss_sums"].to(self.device)
        for purpose in Streams.SAVED:
            getattr(self.streams[member], purpose).set_state(state[f"generator.{purpose}"])
