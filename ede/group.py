"""Several runs of one task and algorithm updated as one: :class:`GroupAgent`.

The members are ordinary :class:`ede.td3.Agent` objects — built as a run alone builds them, so
with the same initial weights, generators and counters — whose networks and Adam states are
stacked into :class:`ede.members.StackedMLP` and :class:`ede.members.MemberAdam` for the update.
A group update is TD3's update (``Agent._update``) for every member at once: each member samples
from its own buffer with its own generator, draws its own target noise, and gets exactly the
numbers it would get alone (``tests/ede/test_group.py``). The member agents stay the record of
each run: :meth:`GroupAgent.sync` writes the stacked weights and Adam states back into them, so
a member's checkpoint and policy are those of a single run and either can resume the other.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ede.members import MemberAdam, StackedMLP
from ede.nets import matmul_precision
from ede.td3 import Agent, ReplayBatch, k_step_targets, polyak

__all__ = ["GroupAgent"]


def _linear_params(stacked: StackedMLP) -> list[torch.Tensor]:
    """Weights and biases interleaved as ``nn.Sequential.parameters()`` lists them."""
    return [t for pair in zip(stacked.weights, stacked.biases) for t in pair]


def _forward_member(stacked: StackedMLP, j: int, x: torch.Tensor) -> torch.Tensor:
    """Member j's network on ``x`` as its own ``nn.Linear`` layers compute it."""
    last = len(stacked.weights) - 1
    for i, (w, b) in enumerate(zip(stacked.weights, stacked.biases)):
        x = F.linear(x, w[j], b[j])
        if i < last:
            x = torch.relu_(x)
    return x


class GroupAgent:
    """M member agents (same adapter, same config, their own seeds) updated together."""

    def __init__(self, agents: Sequence[Agent]) -> None:
        self.agents = list(agents)
        first = self.agents[0]
        if first.autocast:
            raise ValueError("td3.precision bf16 is not supported in a group; use fp32 or bf16-matmul")
        self.config, self.adapter, self.device = first.config, first.adapter, first.device
        self.members = len(self.agents)
        self.centre, self.half_range = first.actor.centre, first.actor.half_range
        self.critic_inputs = first.critic._inputs  # the same encoding of (s, c, i) for all

        def stack(get: str) -> StackedMLP:
            modules: list[nn.Module] = list(self.agents)  # type: ignore[arg-type]
            for part in get.split("."):
                modules = [getattr(m, part) for m in modules]
            return StackedMLP(modules).to(self.device)

        self.actor, self.actor_target = stack("actor.net"), stack("actor_target.net")
        self.q1, self.q2 = stack("critic.q1"), stack("critic.q2")
        self.q1_target, self.q2_target = stack("critic_target.q1"), stack("critic_target.q2")
        for target in (self.actor_target, self.q1_target, self.q2_target):
            target.requires_grad_(False)
        self._critic_params = _linear_params(self.q1) + _linear_params(self.q2)
        self._actor_params = _linear_params(self.actor)
        self.critic_optimizer = MemberAdam(self._critic_params, lr=self.config.lr)
        self.actor_optimizer = MemberAdam(self._actor_params, lr=self.config.lr)
        self._load_optimizer(self.critic_optimizer, "critic_optimizer")
        self._load_optimizer(self.actor_optimizer, "actor_optimizer")
        self._polyak_pairs = [
            (_linear_params(self.q1_target) + _linear_params(self.q2_target), self._critic_params),
            (_linear_params(self.actor_target), self._actor_params),
        ]

    # Acting, member by member ---------------------------------------------------------------

    def actor_of(self, j: int, obs: torch.Tensor) -> torch.Tensor:
        return self.centre + self.half_range * torch.tanh(_forward_member(self.actor, j, obs))

    @torch.no_grad()
    def act(self, j: int, obs: np.ndarray, explore: bool) -> torch.Tensor:
        """Member j's code for one observation, as ``Agent.act`` computes it alone."""
        agent = self.agents[j]
        x = torch.as_tensor(obs, dtype=torch.float32, device=self.device)[None]
        code = self.actor_of(j, x)[0]
        if explore:
            noise = agent._noise(code.shape, self.config.exploration_noise, agent.scale)
            code = agent.clip(code + noise)
        return code

    # The update --------------------------------------------------------------------------------

    def _stacked_actor(self, net: StackedMLP, obs: torch.Tensor) -> torch.Tensor:
        return self.centre + self.half_range * torch.tanh(net(obs))

    def update(self, batches: Sequence[ReplayBatch]) -> None:
        """One TD3 update of every member on its own batch (``Agent.update``, batched)."""
        with matmul_precision(self.config.precision):
            self._update(batches)

    def _update(self, batches: Sequence[ReplayBatch]) -> None:
        c, agents = self.config, self.agents
        parts = [k_step_targets(batch, c.discount) for batch in batches]
        with torch.no_grad():
            noise = torch.stack([
                agent._noise(batch.code.shape, c.policy_noise, agent.target_scale)
                for agent, batch in zip(agents, batches)
            ])  # each member's own draw, in its own order
            clip = c.noise_clip * self.adapter.clip_scale
            noise = torch.maximum(torch.minimum(noise, clip), -clip)
            bootstrap = torch.stack([p.bootstrap_obs for p in parts])
            chosen = self._stacked_actor(self.actor_target, bootstrap) + noise
            chosen = chosen.clamp(self.adapter.code_low, self.adapter.code_high)
            keep = torch.stack([p.keep_code for p in parts])[..., None]
            codes = torch.stack([b.code for b in batches])
            next_code = torch.where(keep, codes, chosen)
            x = self.critic_inputs(bootstrap, next_code, torch.stack([p.next_i for p in parts]))
            q = torch.minimum(self.q1_target(x).squeeze(-1), self.q2_target(x).squeeze(-1))
            returns = torch.stack([p.returns for p in parts])
            discount = torch.stack([p.discount for p in parts])
            target = returns + discount * q  # (M, B)
        obs = torch.stack([b.obs for b in batches])
        x = self.critic_inputs(obs, codes, torch.stack([b.i for b in batches]))
        q1, q2 = self.q1(x).squeeze(-1), self.q2(x).squeeze(-1)
        losses = [F.mse_loss(q1[j], target[j]) + F.mse_loss(q2[j], target[j])
                  for j in range(self.members)]
        for p in self._critic_params:
            p.grad = None
        torch.stack(losses).sum().backward()
        self.critic_optimizer.step()
        for agent, loss in zip(agents, losses):
            agent.loss_sums[0] += loss.detach()
            agent.loss_sums[1] += 1
            agent.updates += 1
        if agents[0].updates % c.policy_delay:
            return
        for p in self._critic_params:
            p.requires_grad_(False)
        start = torch.zeros_like(torch.stack([b.i for b in batches]))
        x = self.critic_inputs(obs, self._stacked_actor(self.actor, obs), start)
        q_first = self.q1(x).squeeze(-1)
        actor_losses = [-q_first[j].mean() for j in range(self.members)]
        for p in self._actor_params:
            p.grad = None
        torch.stack(actor_losses).sum().backward()
        self.actor_optimizer.step()
        for p in self._critic_params:
            p.requires_grad_(True)
        for agent, loss in zip(agents, actor_losses):
            agent.loss_sums[2] += loss.detach()
            agent.loss_sums[3] += 1
        for target, source in self._polyak_pairs:
            polyak(target, source, c.tau)

    # The member agents as the record -------------------------------------------------------

    def _load_optimizer(self, optimizer: MemberAdam, name: str) -> None:
        """The members' Adam states (all at one step count) into the stacked optimiser."""
        states = [getattr(agent, name).state_dict()["state"] for agent in self.agents]
        if not states[0]:
            return
        steps = {float(state[0]["step"]) for state in states}
        if len(steps) != 1:
            raise ValueError(f"members at different optimiser steps {sorted(steps)}")
        optimizer.step_count.fill_(steps.pop())
        for i, (avg, avg_sq) in enumerate(zip(optimizer.exp_avg, optimizer.exp_avg_sq)):
            for j, state in enumerate(states):
                avg[j].copy_(state[i]["exp_avg"])
                avg_sq[j].copy_(state[i]["exp_avg_sq"])

    @torch.no_grad()
    def sync(self) -> None:
        """Write every member's weights and Adam state back into its own agent."""
        for j, agent in enumerate(self.agents):
            pairs: list[tuple[StackedMLP, nn.Module]] = [
                (self.actor, agent.actor.net), (self.actor_target, agent.actor_target.net),
                (self.q1, agent.critic.q1), (self.q2, agent.critic.q2),
                (self.q1_target, agent.critic_target.q1), (self.q2_target, agent.critic_target.q2),
            ]
            for stacked, module in pairs:
                for mine, theirs in zip(_linear_params(stacked), module.parameters()):
                    theirs.copy_(mine[j])
            for optimizer, torch_optimizer in ((self.critic_optimizer, agent.critic_optimizer),
                                               (self.actor_optimizer, agent.actor_optimizer)):
                if not int(optimizer.step_count):
                    continue
                for i, p in enumerate(torch_optimizer.param_groups[0]["params"]):
                    torch_optimizer.state[p] = {
                        "step": optimizer.step_count.clone(),
                        "exp_avg": optimizer.exp_avg[i][j].clone(),
                        "exp_avg_sq": optimizer.exp_avg_sq[i][j].clone(),
                    }
