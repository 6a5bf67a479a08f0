"""Aggregate training throughput on one GPU machine: P processes, each a group of M members.

    python benchmarks/gpu_throughput.py [--device cuda|cpu] [--tiny] [--plan 1x1,1x16,8x16]
                                        [--tasks ede/ReacherVertical-v0,ede/Pusher-v0]
                                        [--algos td3,ede-td3] [--steps 3000] [--minutes 7]

One command, one table: for each task and algorithm, each ``PxM`` of ``--plan`` — P processes
side by side, each training a group of M seeds through ``ede.run.training.train_group`` as
``ede-pipeline train --seeds`` does — and its aggregate rate: environment steps per second of all
P × M members together, timed in every process from its members' step 500 to their last
(compiling, setup, the first evaluation and the outputs outside the clock; the paper's evaluation,
10 episodes every 1,000 steps, inside). ``1x1`` is one run alone, the reference every row is read
against (``x alone``). Beside each row:

* ``update µs``: one batched update of M members (the paper's networks, batch 100) in this
  process, timed over 200 updates after 50 untimed ones, as ``td3.compile`` runs it;
* ``graph``: whether the update ran as a CUDA graph (``td3.compile: reduce-overhead`` and no
  CUDA-graph skip counted by Inductor), "-" on CPU;
* ``GPU busy``: the mean of ``nvidia-smi``'s utilisation, sampled every 0.2 s while the row ran.

The networks are the paper's (400-300, batch 100), the actor acts from the first step, each
member's update after each of its steps; EDE-TD3 acts through an untrained embedding (k = 4;
its weights do not matter for speed). Rows stop being started once ``--minutes`` have passed, so
the command ends within about a minute of it; a row not run says so. ``--tiny`` (tiny networks,
a few hundred steps, plan ``1x1,2x2``) is the form the test suite runs on CPU so that this script
cannot rot; its numbers mean nothing.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import shutil
import subprocess
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch

from ede.config import Algo

WARMUP = 500  # steps per member before the clock starts


@dataclass(frozen=True)
class Row:
    task: str
    algo: Algo
    processes: int
    members: int


def embedding(task: str, device: torch.device) -> Any:
    """An untrained embedding of ``task``'s actions, k = 4, codes the size of an action."""
    from ede.io.rollouts import Whitening
    from ede.method.embedding import ActionDecoder, ActionEmbedding, Encoder
    from ede.tasks import make

    env = make(task)
    low, high = env.action_space.low, env.action_space.high  # type: ignore[attr-defined]
    env.close()
    size = len(low)
    torch.manual_seed(0)
    return ActionEmbedding(
        Encoder(4, size, size, [400, 400]),
        ActionDecoder(size, 4, low, high, [400, 400]),
        Whitening(np.zeros(size), np.ones(size)),
        bound=3.0,
    ).to(device)


def config(device: str, tiny: bool, steps: int, compile: str) -> Any:
    from ede.config import TD3Config

    size = {"hidden": [16, 16], "batch_size": 8} if tiny else {}
    return TD3Config.model_validate(
        {
            **size,
            "start_steps": 0,
            "eval_every": 1_000,
            "eval_episodes": 10,
            "checkpoint_every": 10**9,
            "buffer_size": steps,
            "update_schedule": "step",
            "device": device,
            "compile": compile,
        }
    )


def group(args: tuple[Row, str, bool, int, str, int]) -> float:
    """One process's group: its members' environment steps per second, timed."""
    row, device, tiny, steps, compile, warmup = args
    from ede.config import EdeTD3Config
    from ede.run.spec import RunSpec
    from ede.run.training import train_group

    torch.set_num_threads(1)
    where = torch.device(device)
    td3 = config(device, tiny, steps, compile)
    specs = [RunSpec(row.task, row.algo, s, steps, td3, EdeTD3Config()) for s in range(row.members)]
    marks: dict[int, float] = {}
    done = [0]
    first, last = row.members * warmup, row.members * steps

    def progress(count: int) -> None:
        done[0] += count
        if done[0] in (first, last):
            if device == "cuda":
                torch.cuda.synchronize()
            marks[done[0]] = time.perf_counter()

    with tempfile.TemporaryDirectory() as tmp:
        outs = [Path(tmp) / f"seed{s.seed}" for s in specs]
        code = embedding(row.task, where) if row.algo == "ede-td3" else None
        train_group(specs, outs, code, where, progress)
    return (last - first) / (marks[last] - marks[first])


def update_us(row: Row, device: str, tiny: bool, compile: str) -> tuple[float, str]:
    """One batched update of ``row.members`` members, in µs, and whether a CUDA graph ran it."""
    from torch._dynamo.utils import counters

    from ede.method.adapters import EmbeddingAdapter, IdentityAdapter
    from ede.method.agent import Agent
    from ede.method.replay import ReplayBuffer
    from ede.tasks import make

    where = torch.device(device)
    env = make(row.task)
    low, high = env.action_space.low, env.action_space.high  # type: ignore[attr-defined]
    obs_size = int(np.prod(env.observation_space.shape))  # type: ignore[arg-type]
    env.close()
    if row.algo == "td3":
        adapter: Any = IdentityAdapter(low, high, where)
    else:
        adapter = EmbeddingAdapter(embedding(row.task, where))
    td3 = config(device, tiny, 1_000, compile)
    members = row.members
    agent = Agent(obs_size, adapter, td3, where, list(range(members)))
    buffer = ReplayBuffer(1_000, obs_size, adapter.code_size, adapter.k, where, members)
    every = np.ones(members, dtype=bool)
    rng = np.random.default_rng(0)
    for _ in range(1_000):
        buffer.add(
            every,
            rng.normal(size=(members, obs_size)),
            torch.as_tensor(rng.uniform(-1, 1, (members, adapter.code_size)), dtype=torch.float32),
            rng.integers(adapter.k, size=members),
            rng.normal(size=members),
            rng.normal(size=(members, obs_size)),
            np.zeros(members, dtype=bool),
            np.zeros(members, dtype=bool),
        )
    skips = counters["inductor"]["cudagraph_skips"]
    for _ in range(50):
        agent.update(buffer)
    if device == "cuda":
        torch.cuda.synchronize()
    started = time.perf_counter()
    for _ in range(200):
        agent.update(buffer)
    if device == "cuda":
        torch.cuda.synchronize()
    us = 1e6 * (time.perf_counter() - started) / 200
    captured = compile == "reduce-overhead" and counters["inductor"]["cudagraph_skips"] == skips
    return us, ("yes" if captured else "no") if device == "cuda" else "-"


class Busy:
    """The GPU's mean utilisation (``nvidia-smi``, sampled every 0.2 s) while the block runs."""

    def __init__(self, device: str) -> None:
        self.on = device == "cuda" and shutil.which("nvidia-smi") is not None
        self.samples: list[float] = []
        self.stop = threading.Event()

    def __enter__(self) -> Busy:
        if self.on:
            self.thread = threading.Thread(target=self.sample, daemon=True)
            self.thread.start()
        return self

    def sample(self) -> None:
        query = ["nvidia-smi", "--query-gpu=utilization.gpu", "--format=csv,noheader,nounits"]
        while not self.stop.wait(0.2):
            out = subprocess.run(query, capture_output=True, text=True, check=False).stdout
            if out.strip():
                self.samples.append(float(out.split()[0]))

    def __exit__(self, *exc: object) -> None:
        self.stop.set()

    def share(self) -> str:
        return f"{np.mean(self.samples):.0f}%" if self.samples else "-"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda", choices=["cuda", "cpu"])
    parser.add_argument("--tiny", action="store_true")
    parser.add_argument("--plan")
    parser.add_argument("--tasks", default="ede/ReacherVertical-v0,ede/Pusher-v0")
    parser.add_argument("--algos", default="td3,ede-td3")
    parser.add_argument("--steps", type=int)
    parser.add_argument("--compile", default=None, choices=["none", "default", "reduce-overhead"])
    parser.add_argument("--minutes", type=float, default=7.0)
    args = parser.parse_args()
    plan = args.plan or ("1x1,2x2" if args.tiny else "1x1,1x16,8x16")
    steps = args.steps or (200 if args.tiny else 3_000)
    warmup = min(WARMUP, steps // 2)
    compile = args.compile or ("reduce-overhead" if args.device == "cuda" else "none")
    started = time.perf_counter()
    torch.set_num_threads(1)
    gpu = torch.cuda.get_device_name() if args.device == "cuda" else "-"
    print(f"device {args.device} ({gpu}), {os.cpu_count()} cores, td3.compile {compile}")
    print(
        f"{'task':24} {'algo':8} {'PxM':>6} {'steps/s':>9} {'x alone':>8} "
        f"{'update µs':>10} {'graph':>6} {'GPU busy':>9}"
    )
    context = multiprocessing.get_context("spawn")
    for task in args.tasks.split(","):
        for algo in args.algos.split(","):
            alone = None
            for shape in plan.split(","):
                p, m = (int(n) for n in shape.split("x"))
                row = Row(task, cast(Algo, algo), p, m)
                name = f"{task:24} {algo:8} {shape:>6}"
                if time.perf_counter() - started > 60 * args.minutes:
                    print(f"{name} not run: --minutes {args.minutes} passed", flush=True)
                    continue
                job = (row, args.device, args.tiny, steps, compile, warmup)
                with Busy(args.device) as busy, context.Pool(p) as pool:
                    rate = sum(pool.map(group, [job] * p))
                us, graph = update_us(row, args.device, args.tiny, compile)
                alone = rate if (p, m) == (1, 1) else alone
                ratio = f"{rate / alone:>8.2f}" if alone else f"{'-':>8}"
                print(
                    f"{name} {rate:>9.0f} {ratio} {us:>10.0f} {graph:>6} {busy.share():>9}",
                    flush=True,
                )
    print(f"in {time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
