"""Subnormal numbers in a long run's optimiser state, and what flushing them to zero buys.

    python benchmarks/subnormals.py [--task HalfCheetah-v5] [--steps 50000] [--updates 1000]

Trains our TD3 at the paper's size (400-300, batch 100, one update per step, one thread) on
``--task`` for ``--steps`` environment steps with flushing off — torch's default, and how
training ran before ``ede.method.nets.flush_denormals`` — so that the Adam first moments of weights
that get no gradient sink into fp32's subnormal range. Then it prints the share of each
optimiser's first and second moments that are subnormal and, from copies of that one state on
the same ``--updates`` batches, the update rate with flushing off (the reference) and on (as
training now runs), best of three alternating rounds, as a ratio. The training phase itself
slows as the subnormals appear: ``--steps 50000`` takes about ten minutes on one core.
"""

from __future__ import annotations

import argparse
import copy
import time
from contextlib import nullcontext

import numpy as np
import torch

from ede.config import EdeTD3Config, TD3Config
from ede.method.agent import Agent
from ede.method.ensemble import Adam
from ede.method.nets import flush_denormals
from ede.method.replay import ReplayBatch
from ede.run.group import Group
from ede.run.spec import RunSpec

SMALLEST_NORMAL = torch.finfo(torch.float32).tiny


def subnormal_share(optimizer: Adam, moment: str) -> float:
    values = getattr(optimizer, moment).abs()
    return ((values > 0) & (values < SMALLEST_NORMAL)).float().mean().item()


def updates_per_second(
    agent: Agent, batches: list[tuple[ReplayBatch, torch.Tensor]], flush: bool
) -> float:
    agent = copy.deepcopy(agent)
    due = np.ones(1, dtype=bool)
    with flush_denormals() if flush else nullcontext():
        start = time.perf_counter()
        for batch, noise in batches:
            agent.step(batch, noise, due)
    return len(batches) / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="HalfCheetah-v5")
    parser.add_argument("--steps", type=int, default=50_000, help="training steps before measuring")
    parser.add_argument("--updates", type=int, default=1_000, help="updates timed per round")
    args = parser.parse_args()
    torch.set_num_threads(1)
    config = TD3Config(
        hidden=[400, 300],
        batch_size=100,
        update_schedule="step",
        buffer_size=args.steps,
        compile="none",  # the eager update's slow path is what this measures
    )
    group = Group(
        [RunSpec(args.task, "td3", 0, args.steps, config, EdeTD3Config())],
        None,
        torch.device("cpu"),
    )
    start = time.perf_counter()
    while group.advance():
        pass
    print(
        f"{args.task}: {args.steps} steps of TD3 (400-300, batch 100) without flushing in "
        f"{time.perf_counter() - start:.0f} s"
    )
    agent = group.agent
    for name, optimizer in (("critic", agent.critic_adam), ("actor", agent.actor_adam)):
        print(
            f"  {name} Adam moments subnormal: first {subnormal_share(optimizer, 'exp_avg'):.1%}, "
            f"second {subnormal_share(optimizer, 'exp_avg_sq'):.1%}"
        )
    everyone = np.ones(1, dtype=bool)
    batches = [agent.draw(group.buffer, everyone) for _ in range(args.updates)]
    rates: dict[bool, list[float]] = {False: [], True: []}
    for _ in range(3):
        for flush in (False, True):
            rates[flush].append(updates_per_second(agent, batches, flush))
    off, on = max(rates[False]), max(rates[True])
    print(f"updates, subnormals kept      {off:7.1f} /s   1.00x")
    print(f"updates, subnormals flushed   {on:7.1f} /s   {on / off:.2f}x")


if __name__ == "__main__":
    main()
