"""TD3 and EDE-TD3, the paper's update: the actor, the twin critic, Equation 1 and the losses.

TD3 (Fujimoto et al., 2018) is the special case k = 1 of EDE-TD3 (Section 3 of the paper): the
two differ only through an :class:`ActionAdapter` — the identity for TD3, the learned decoder for
EDE-TD3 — which fixes what the actor outputs (a raw action, or a whitened code z of k actions),
its bounds, and k.

Shapes: M members (the runs an agent trains at once; 1 for a run alone), B batch, K actions per
code (1 for TD3), A action size, C code size (A for TD3, D for EDE-TD3), O observation size.
:class:`TD3` is the update of one member, as functions of its parameters and batch.

The critic is Q(s, c, i) with i the number of steps of code c already executed, fed as a one-hot
of size K or as a scalar (absent when K = 1). Its target is Equation 1, batched over B and K::

    y = Σ_{m<n} γ^m r_{t+m} + γ^n (1 − terminal) min_j Q'_j(s_{t+n}, c', i')

where n ≤ K − i steps remain of the code, fewer if the episode ended first; c' = μ'(s_{t+n}) plus
clipped smoothing noise and i' = 0 where the next code is chosen; and where a time limit cut the
code short (truncated, not terminal), the code goes on: c' = c, i' = i + n. The actor follows
∇_c Q_1(s, c, 0) (Equation 2).

Where the rest lives:

- the adapters (identity for TD3, the decoder for EDE-TD3): :mod:`ede.method.adapters`;
- the member axis (M runs stacked on a leading axis, the batched MLP): :mod:`ede.method.ensemble`;
- the optimiser: Adam over the stacked members (:class:`ede.method.ensemble.Adam`), stepped in
  :meth:`ede.method.agent.Agent.step`;
- the learner that owns the networks, their targets, the optimisers and the random streams, and
  runs this update on every member at once: :class:`ede.method.agent.Agent`;
- the replay buffer and its k-step batches: :mod:`ede.method.replay`;
- the loop (acting with codes, evaluating, checkpoints): :mod:`ede.run.executor` and
  :mod:`ede.run.training`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ede.config.schema import TD3Config
from ede.method import ensemble
from ede.method.adapters import ActionAdapter
from ede.method.ensemble import Params
from ede.method.nets import initial_mlp
from ede.method.replay import ReplayBatch

__all__ = ["TD3", "Actor", "Critic", "TargetParts", "critic_repeat", "k_step_targets"]


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
