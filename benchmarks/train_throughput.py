"""Training throughput: stable-baselines3's TD3 against our TD3 and EDE-TD3, same schedule.

    python benchmarks/train_throughput.py [--steps 6000] [--precision fp32|bf16-matmul|bf16|all]
                                          [--hidden 256,256] [--batch-size 256]

In one process and one torch thread, on gymnasium's ``Reacher-v5``: environment steps per second
with one update per step (batch 256, 256-256 networks, policy delay 2, 1,000 uniform random
start steps, then one update per step; each learner timed after an untimed warm-up run of its
own), for SB3's TD3 (the reference, measured in the same run), our TD3 and our EDE-TD3 (with an
embedding of Reacher-v5's actions; its weights do not matter for speed), in each ``td3.precision``.
Prints each and its ratio to SB3. Goals: our TD3 >= 1.5x SB3; EDE-TD3 >= 0.9x our TD3.
``--hidden 400,300 --batch-size 100`` measures the paper's TD3 configuration instead.

``--members N [--device cpu|cuda]`` measures groups instead (``ede-pipeline train --seeds``):
the aggregate environment steps per second of one process training N seeds of our TD3 together
(``ede.training.train_group``) against the same N runs trained one after another in this
process — the reference, measured in the same run; on one core that is what N single-run
processes give in aggregate.

What ``bf16-matmul`` and ``bf16`` compute and buy depends on the CPU, so the benchmark first
prints the machine: the CPU model and its bf16-related flags, and for each precision the error
of a product against float64 (``ede.nets.product_error``) and the oneDNN kernel that computed it
(from ``ONEDNN_VERBOSE``; none means torch's own BLAS path). Read its ratios only for that CPU.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import get_args

import numpy as np
import torch

from ede.config import EdeTD3Config, Precision, TD3Config
from ede.embedding import ActionDecoder, ActionEmbedding, Encoder
from ede.nets import product_error
from ede.rollouts import Whitening
from ede.training import RunSpec, train_group, train_run

TASK = "Reacher-v5"
PRECISIONS = list(get_args(Precision))
START = 1_000
WARMUP = START + 300


@dataclass(frozen=True)
class Shape:
    hidden: list[int]
    batch_size: int


def sb3(steps: int, shape: Shape) -> float:
    import gymnasium
    from stable_baselines3 import TD3
    from stable_baselines3.common.noise import NormalActionNoise

    env = gymnasium.make(TASK)
    model = TD3("MlpPolicy", env, learning_rate=1e-3, buffer_size=steps, learning_starts=START,
                batch_size=shape.batch_size, tau=0.005, gamma=0.99, train_freq=1, gradient_steps=1,
                action_noise=NormalActionNoise(np.zeros(2), 0.1 * np.ones(2)), policy_delay=2,
                policy_kwargs={"net_arch": shape.hidden}, seed=0, device="cpu", verbose=0)
    start = time.perf_counter()
    model.learn(total_timesteps=steps)
    return steps / (time.perf_counter() - start)


def ours(steps: int, shape: Shape, algo: str, precision: str) -> float:
    config = TD3Config(hidden=shape.hidden, batch_size=shape.batch_size, start_steps=START,
                       buffer_size=steps,
                       eval_every=10**9, eval_episodes=1, checkpoint_every=10**9,
                       precision=precision, update_schedule="step")  # as SB3: train_freq=1
    embedding = None
    if algo == "ede-td3":
        torch.manual_seed(0)
        low, high = -np.ones(2), np.ones(2)
        embedding = ActionEmbedding(Encoder(4, 2, 2, [400, 400]),
                                    ActionDecoder(2, 4, low, high, [400, 400]),
                                    Whitening(np.zeros(2), np.ones(2)), bound=3.0)
    spec = RunSpec(TASK, algo, 0, steps, config, EdeTD3Config())
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        train_run(spec, Path(tmp), embedding)
        return steps / (time.perf_counter() - start)


def runs(steps: int, shape: Shape, members: int, device: str, grouped: bool) -> float:
    """Aggregate steps/s of ``members`` TD3 runs, as one group or one after another."""
    config = TD3Config(hidden=shape.hidden, batch_size=shape.batch_size, start_steps=START,
                       buffer_size=steps, eval_every=10**9, eval_episodes=1,
                       checkpoint_every=10**9, device=device, update_schedule="step")
    specs = [RunSpec(TASK, "td3", seed, steps, config, EdeTD3Config()) for seed in range(members)]
    with tempfile.TemporaryDirectory() as tmp:
        outs = [Path(tmp) / f"seed{spec.seed}" for spec in specs]
        start = time.perf_counter()
        if grouped:
            train_group(specs, outs, device=torch.device(device))
        else:
            for spec, out in zip(specs, outs):
                train_run(spec, out, device=torch.device(device))
        return members * steps / (time.perf_counter() - start)


def warm(learner: Callable[..., float], steps: int, shape: Shape, *args: str) -> float:
    """Steps/s of ``learner`` after an untimed short run (imports, first calls, kernel choices)."""
    learner(WARMUP, shape, *args)
    return learner(steps, shape, *args)


def cpu_model() -> tuple[str, list[str]]:
    """The CPU's model name and which of the flags that decide bf16 paths it has."""
    model, flags = platform.processor() or platform.machine(), set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name":
                model = value.strip()
            elif key.strip() == "flags":
                flags = set(value.split())
                break
    except OSError:
        pass
    wanted = ["avx2", "avx512f", "avx512_bf16", "amx_bf16", "amx_tile"]
    return model, [flag for flag in wanted if flag in flags]


def onednn_kernels(precision: str) -> str:
    """The oneDNN kernels of one product under ``precision``, from a fresh interpreter."""
    code = f"import torch; torch.set_num_threads(1); from ede.nets import product_error; product_error({precision!r})"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            env={**os.environ, "ONEDNN_VERBOSE": "1"}, check=True)
    kernels = set()
    for line in result.stdout.splitlines():
        fields = line.split(",")
        if fields[0] == "onednn_verbose" and "exec" in fields:
            at = fields.index("exec")
            kernels.add(f"{fields[at + 2]}:{fields[at + 3]}")
    return ", ".join(sorted(kernels)) or "none (torch's BLAS path)"


def describe_machine(precisions: list[str]) -> None:
    model, flags = cpu_model()
    print(f"CPU: {model}; flags: {' '.join(flags) or '-'}; torch {torch.__version__}, "
          f"CPU capability {torch.backends.cpu.get_cpu_capability()}")
    for precision in precisions:
        error = product_error(precision)
        kind = "fp32-accurate" if error < 1e-4 else "bf16-rounded inputs"
        print(f"  {precision:<12} product error {error:.1e} ({kind}); oneDNN: {onednn_kernels(precision)}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=6_000)
    parser.add_argument("--precision", choices=[*PRECISIONS, "all"], default="all")
    parser.add_argument("--hidden", default="256,256", help="hidden widths, comma-separated")
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--members", type=int, help="measure a group of this many seeds")
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    args = parser.parse_args()
    shape = Shape([int(width) for width in args.hidden.split(",")], args.batch_size)
    torch.set_num_threads(1)
    if args.members:
        describe_machine(["fp32"])
        alone = warm(runs, args.steps, shape, args.members, args.device, False)
        grouped = warm(runs, args.steps, shape, args.members, args.device, True)
        print(f"{TASK}, {args.steps} steps per run, {args.members} seeds of TD3, {args.device}, "
              f"1 thread, batch {shape.batch_size}, {'-'.join(map(str, shape.hidden))} networks")
        print(f"{args.members} runs one after another  {alone:7.0f} steps/s aggregate   1.00x")
        print(f"{args.members} runs as one group       {grouped:7.0f} steps/s aggregate   "
              f"{grouped / alone:.2f}x")
        return
    precisions = PRECISIONS if args.precision == "all" else [args.precision]
    describe_machine(precisions)
    reference = warm(sb3, args.steps, shape)
    print(f"{TASK}, {args.steps} steps, 1 thread, batch {shape.batch_size}, "
          f"{'-'.join(map(str, shape.hidden))} networks")
    print(f"stable-baselines3 TD3        {reference:7.0f} steps/s   1.00x")
    for precision in precisions:
        td3 = warm(ours, args.steps, shape, "td3", precision)
        ede = warm(ours, args.steps, shape, "ede-td3", precision)
        print(f"ours TD3, {precision:<12}     {td3:7.0f} steps/s   {td3 / reference:.2f}x")
        print(f"ours EDE-TD3, {precision:<12} {ede:7.0f} steps/s   {ede / reference:.2f}x"
              f"  ({ede / td3:.2f}x our TD3)")


if __name__ == "__main__":
    main()
