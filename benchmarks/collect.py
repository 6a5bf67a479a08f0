"""Collector throughput against a plain single-env ``env.step`` loop, measured in the same run.

    python benchmarks/collect.py [--steps 100000] [--task ede/ReacherVertical-v0]

Prints steps per second of (a) a plain loop of ``env.step`` with uniform random actions and
resets, (b) ``collect`` + ``write_store`` of a store in one process (one worker), and (c) the
same with one worker per core; then each as a ratio per core to (a). Goal: (b) >= 0.8.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from ede.io.rollouts import write_store
from ede.run.collect import collect
from ede.tasks import action_bounds, make


def plain_loop(task: str, steps: int) -> float:
    env = make(task)
    rng = np.random.default_rng(0)
    low, high = action_bounds(env)
    env.reset(seed=0)
    start = time.perf_counter()
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(rng.uniform(low, high).astype(np.float32))
        if terminated or truncated:
            env.reset()
    return steps / (time.perf_counter() - start)


def collector(task: str, steps: int, num_envs: int, workers: int) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        arrays = collect(task, steps, num_envs, seed=0, workers=workers)
        write_store(Path(tmp) / "r.zarr", arrays, {"env_id": task, "family": "bench"})
        return steps / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=100_000)
    parser.add_argument("--task", default="ede/ReacherVertical-v0")
    args = parser.parse_args()
    cores = os.cpu_count() or 1

    plain = plain_loop(args.task, args.steps // 4)
    one = collector(args.task, args.steps, num_envs=1, workers=1)
    many = collector(args.task, args.steps, num_envs=cores, workers=cores)
    print(f"task {args.task}, {args.steps} steps, {cores} cores")
    print(f"plain env.step loop        {plain:9.0f} steps/s   1.00x")
    print(f"collect, 1 process         {one:9.0f} steps/s   {one / plain:.2f}x per core")
    print(
        f"collect, {cores} processes        {many:9.0f} steps/s   {many / cores / plain:.2f}x per core"
        f" ({many / plain:.2f}x total)"
    )


if __name__ == "__main__":
    main()
