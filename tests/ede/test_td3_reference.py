"""Our TD3 update pinned to a peer: stable-baselines3's ``TD3.train`` on the same everything.

At k = 1 (the identity adapter) an :class:`ede.method.agent.Agent` (one member) must be TD3: given the
same initial weights, the same replay batches and the same target-smoothing noise, several
updates — critic steps, delayed actor steps and target moves — must leave the same gradients and
weights as stable-baselines3's. The two run different kernels for the products — ours batched
over the member axis, the actor's batch in two halves; SB3's ``nn.Linear`` — which round
differently in the last bits, hence a tolerance (the Adam arithmetic is torch's own, in the same
order). Over these 8 updates every weight and gradient agreed within ``MEASURED`` and not
exactly (AMD EPYC, torch 2.13 CPU); ``TOLERANCE`` leaves 10x.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium
import numpy as np
import pytest
import torch

from ede.config import TD3Config
from ede.method.adapters import IdentityAdapter
from ede.method.agent import Agent
from ede.method.ensemble import Params
from ede.method.replay import ReplayBatch
from ede.tasks import action_bounds, observation_size

sb3 = pytest.importorskip("stable_baselines3")  # a dev dependency: present wherever tests run
# after the skip above, as its imports need stable-baselines3
from stable_baselines3.common.logger import configure  # noqa: E402
from stable_baselines3.common.type_aliases import ReplayBufferSamples  # noqa: E402

HIDDEN, BATCH, UPDATES, SEED = [64, 48], 32, 8, 3
MEASURED: dict[str, Any] = {"rtol": 1e-6, "atol": 1e-7}
TOLERANCE: dict[str, Any] = {"rtol": 1e-5, "atol": 1e-6}


class FixedBatches:
    """Stands in for SB3's replay buffer: hands out the batches we prepared, in order."""

    def __init__(self, batches: list[ReplayBufferSamples]) -> None:
        self.batches = iter(batches)

    def sample(self, batch_size: int, env: object = None) -> ReplayBufferSamples:
        return next(self.batches)


def labelled(where: str) -> Callable[[str], str]:
    """``assert_close``'s message: its own, after ``where``."""
    return lambda message: f"{where}: {message}"


def linears(module: torch.nn.Module) -> list[torch.nn.Linear]:
    return [m for m in module.modules() if isinstance(m, torch.nn.Linear)]


def copy_weights(source: torch.nn.Module, target: Params, twin: int | None = None) -> None:
    """An SB3 network's weights into one member's parameters (of twin ``twin`` of a critic)."""
    with torch.no_grad():
        for j, layer in enumerate(linears(source)):
            for name in ("weight", "bias"):
                ours = target[f"{2 * j}.{name}"]
                (ours if twin is None else ours[twin]).copy_(getattr(layer, name))


def assert_same(
    ours: Params, theirs: torch.nn.Module, what: str, twin: int | None = None, grads: bool = False
) -> None:
    """One member's parameters (or gradients; of twin ``twin``) against an SB3 network's."""
    for j, layer in enumerate(linears(theirs)):
        for name in ("weight", "bias"):
            x = ours[f"{2 * j}.{name}"]
            x = x if twin is None else x[twin]
            y = getattr(layer, name).grad if grads else getattr(layer, name)
            torch.testing.assert_close(x, y, **TOLERANCE, msg=labelled(f"{what} layer {j} {name}"))


def test_k1_updates_equal_stable_baselines3_td3() -> None:
    env = gymnasium.make("Reacher-v5")
    low, high = action_bounds(env)
    obs_size, act_size = observation_size(env), len(low)
    config = TD3Config(hidden=HIDDEN, batch_size=BATCH)
    torch.set_num_threads(1)
    theirs = sb3.TD3(
        "MlpPolicy",
        env,
        learning_rate=config.lr,
        batch_size=BATCH,
        tau=config.tau,
        gamma=config.discount,
        policy_delay=config.policy_delay,
        target_policy_noise=config.policy_noise,
        target_noise_clip=config.noise_clip,
        policy_kwargs={"net_arch": HIDDEN},
        seed=SEED,
        device="cpu",
    )
    theirs.set_logger(configure(None, []))
    adapter = IdentityAdapter(low, high, torch.device("cpu"))
    ours = Agent(obs_size, adapter, config, torch.device("cpu"), seeds=[SEED])
    # Same weights everywhere: SB3's critic is q_networks[0] and [1], our twins 0 and 1.
    copy_weights(theirs.actor.mu, ours.actor.member(0))
    copy_weights(theirs.actor_target.mu, ours.actor_target.member(0))
    for j in range(2):
        copy_weights(theirs.critic.q_networks[j], ours.critic.member(0), j)
        copy_weights(theirs.critic_target.q_networks[j], ours.critic_target.member(0), j)
    grads: dict[str, Params] = {}  # the gradient each optimiser was handed, by parameter
    for name in ("actor", "critic"):
        adam = getattr(ours, f"{name}_adam")
        step = adam.step

        def spy(grad: torch.Tensor, *args: Any, name: str = name, step=step, adam=adam) -> None:
            grads[name] = adam.stack.views(grad[0])  # then the step itself
            step(grad, *args)

        adam.step = spy

    rng = np.random.default_rng(0)
    ours_batches, their_batches = [], []
    for _ in range(UPDATES):
        obs = torch.as_tensor(rng.normal(size=(BATCH, obs_size)), dtype=torch.float32)
        actions = torch.as_tensor(rng.uniform(-1, 1, size=(BATCH, act_size)), dtype=torch.float32)
        rewards = torch.as_tensor(rng.normal(size=(BATCH, 1)), dtype=torch.float32)
        terminated = torch.as_tensor(rng.random((BATCH, 1)) < 0.2)
        next_obs = torch.as_tensor(rng.normal(size=(BATCH, obs_size)), dtype=torch.float32)
        batch = ReplayBatch(
            obs,
            actions,
            torch.zeros(BATCH, dtype=torch.int64),
            rewards,
            terminated,
            torch.zeros_like(terminated),
            next_obs[:, None],
        )
        ours_batches.append(ReplayBatch(*(t[None] for t in batch)))  # one member
        their_batches.append(
            ReplayBufferSamples(obs, actions, next_obs, terminated.float(), rewards)
        )
    theirs.replay_buffer = FixedBatches(their_batches)

    for step, batch in enumerate(ours_batches, start=1):
        # The same target-smoothing noise: both draw one (B, A) standard normal per update, SB3's
        # from torch's global generator; ours is handed the same draw.
        torch.manual_seed(100 + step)
        noise = torch.randn(1, BATCH, act_size)
        torch.manual_seed(100 + step)
        ours.step(batch, noise, np.ones(1, dtype=bool))
        theirs.train(gradient_steps=1, batch_size=BATCH)
        actor_step = step % config.policy_delay == 0
        for j in range(2):
            if (
                not actor_step
            ):  # SB3's actor loss adds into the critic's gradients; ours spares them
                assert_same(
                    grads["critic"],
                    theirs.critic.q_networks[j],
                    f"update {step} critic {j} grad",
                    j,
                    grads=True,
                )
            assert_same(
                ours.critic.member(0), theirs.critic.q_networks[j], f"update {step} critic {j}", j
            )
            assert_same(
                ours.critic_target.member(0),
                theirs.critic_target.q_networks[j],
                f"update {step} target {j}",
                j,
            )
        assert_same(ours.actor.member(0), theirs.actor.mu, f"update {step} actor")
        assert_same(
            ours.actor_target.member(0), theirs.actor_target.mu, f"update {step} actor target"
        )
        if actor_step:  # its gradients too
            assert_same(grads["actor"], theirs.actor.mu, f"update {step} actor grad", grads=True)
    # The updates did move the weights (the comparison above is not between untouched copies).
    first = ours.actor.member(0)["0.weight"]
    assert not torch.equal(
        first,
        linears(
            sb3.TD3(
                "MlpPolicy", env, policy_kwargs={"net_arch": HIDDEN}, seed=SEED, device="cpu"
            ).actor.mu
        )[0].weight,
    )
