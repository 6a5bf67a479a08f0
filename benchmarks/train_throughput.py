"""Training throughput of our TD3 (single runs, groups of seeds, eager and compiled) against SB3's.

    python benchmarks/train_throughput.py [--hidden 400,300] [--batch-size 100] [--device cpu|cuda]
                                          [--steps 5000] [--group-steps 3000] [--members 4,8]
                                          [--compile none,default]
    python benchmarks/train_throughput.py --precisions all|fp32,bf16-matmul,bf16
                                          [--hidden ...] [--batch-size ...] [--device ...]
                                          [--steps 5000] [--compile none,default]

Everything runs in one process with one torch thread, on gymnasium's ``Reacher-v5``, with the
per-step schedule of stable-baselines3 (SB3): 1,000 uniform random start steps, then one update
after every environment step (batch ``--batch-size``, ``--hidden`` networks, policy delay 2).
A rate is environment steps per second *after the start steps* (each of those steps with its
update; setup, start steps, evaluation and output writing are outside the clock), so runs of
different lengths compare. Every row is timed after an untimed warm-up run of its own (1,300
steps per run: imports, first calls, kernel choices; a compiled row compiles its update there,
afresh for its own shapes). The reference, SB3's TD3 on the same device, is measured in the same
run, and every figure is read as a ratio to it (or to our single run) — absolute rates depend on
the machine and on what else runs on it. ``--hidden 400,300 --batch-size 100`` (the default) is
the paper's TD3; ``--hidden 256,256 --batch-size 256`` is SB3's default.

The default invocation prints one table, one row each for:

* stable-baselines3's TD3: the reference (``x SB3`` 1.00);
* our TD3, one run (``ede.run.training.train_run``, an agent of M = 1), in each ``--compile`` mode
  (``td3.compile``: ``none`` eager; ``default`` the update compiled whole by ``torch.compile``;
  ``reduce-overhead`` that plus CUDA graphs, ``--device cuda`` only);
* our TD3, a group of M seeds 0..M-1 trained as one agent of M members
  (``ede.run.training.train_group``, what ``ede-pipeline train --seeds`` does) for each M of
  ``--members``, in each mode. ``steps/s`` is then the group's aggregate (M runs' steps), ``per
  run`` that / M, and ``x single`` the aggregate over the single run's rate in the same mode: on
  one core, what one process of M seeds buys against M single-run processes one after another.
  Groups run ``--group-steps`` steps per run (M x that environment steps; by default the start
  steps plus half of a single run's timed steps), fewer than single runs to keep the invocation
  short; the rates count only steps after the start steps, so the lengths do not bias the ratios.

With the defaults at the paper's size, a whole invocation takes about 12 minutes on one core of
our 2.1 GHz Xeon (single runs at about 90-130 steps/s), most of it the groups of 8 (16,000 timed
steps each) and compiling (about half a minute for each compiled row); ``--precisions all``
about as long.

An earlier commit is measured the same way by this script run in that commit's environment
(``--compile none``; its ``ede`` is imported): e.g. ``git worktree add /tmp/before HEAD~1``,
``make -C /tmp/before install``, then ``/tmp/before/.venv/bin/python
benchmarks/train_throughput.py --compile none`` from this checkout.

``--precisions`` measures instead our TD3 and our EDE-TD3 (with an embedding of Reacher-v5's
actions; its weights do not matter for speed) in each ``td3.precision`` given and each
``--compile`` mode, single runs against SB3's TD3, each row also as a ratio of EDE-TD3 to our TD3
of the same precision and mode. (The targets set at 256-256, batch 256, eager: our TD3 >= 1.5x
SB3, EDE-TD3 >= 0.9x our TD3.)

Both modes first print the machine. What ``bf16-matmul`` and ``bf16`` compute and buy depends on
the CPU, so this is the CPU model and its bf16-related flags, and for each precision measured the
error of a product against float64 (``ede.method.nets.product_error``) and the oneDNN kernel that
computed it (from ``ONEDNN_VERBOSE``; none means torch's own BLAS path); with ``--device cuda``
also the GPU. Read the ratios only for that machine. A row whose timed run still compiled
something (it should not) is marked: its rate is understated.
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

from ede.config import Algo, EdeTD3Config, Precision, TD3Config
from ede.io.rollouts import Whitening
from ede.method.embedding import ActionDecoder, ActionEmbedding, Encoder
from ede.method.nets import product_error
from ede.run.spec import RunSpec
from ede.run.training import train_group

TASK = "Reacher-v5"
PRECISIONS = list(get_args(Precision))
# td3.compile's modes; an earlier commit without it is eager ("none") only.
COMPILE_MODES = (
    list(get_args(TD3Config.model_fields["compile"].annotation))
    if "compile" in TD3Config.model_fields
    else ["none"]
)
START = 1_000  # uniform random start steps, no updates
WARMUP = START + 300  # steps per run of each row's untimed warm-up run


@dataclass(frozen=True)
class Setting:
    hidden: list[int]
    batch_size: int
    device: str


@dataclass(frozen=True)
class Timing:
    rate: float  # environment steps per second after the start steps, all members together
    compiled: int  # graphs compiled while timed (0 unless something recompiled)


def _sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def _graphs() -> int:
    from torch._dynamo.utils import counters

    return int(counters["stats"]["unique_graphs"])


def sb3(steps: int, setting: Setting) -> float:
    """SB3's TD3: steps/s from the end of its start steps to the end of its last update."""
    import gymnasium
    from stable_baselines3 import TD3
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.noise import NormalActionNoise

    class Clock(BaseCallback):
        started = 0.0

        def _on_step(self) -> bool:
            if self.num_timesteps == START:  # SB3 updates after steps > learning_starts
                _sync(setting.device)
                self.started = time.perf_counter()
            return True

    env = gymnasium.make(TASK)
    model = TD3(
        "MlpPolicy",
        env,
        learning_rate=1e-3,
        buffer_size=steps,
        learning_starts=START,
        batch_size=setting.batch_size,
        tau=0.005,
        gamma=0.99,
        train_freq=1,
        gradient_steps=1,
        action_noise=NormalActionNoise(np.zeros(2), 0.1 * np.ones(2)),
        policy_delay=2,
        policy_kwargs={"net_arch": setting.hidden},
        seed=0,
        device=setting.device,
        verbose=0,
    )
    clock = Clock()
    model.learn(total_timesteps=steps, callback=clock)
    _sync(setting.device)
    return (steps - START) / (time.perf_counter() - clock.started)


def _embedding(device: str) -> ActionEmbedding:
    """An embedding of Reacher-v5's actions (k = 4, 2-dimensional codes), untrained."""
    torch.manual_seed(0)
    low, high = -np.ones(2), np.ones(2)
    return ActionEmbedding(
        Encoder(4, 2, 2, [400, 400]),
        ActionDecoder(2, 4, low, high, [400, 400]),
        Whitening(np.zeros(2), np.ones(2)),
        bound=3.0,
    ).to(device)


def ours(
    steps: int, setting: Setting, algo: Algo, precision: str, compile: str, members: int
) -> float:
    """Our ``algo``, ``members`` seeds as one group (one run if 1): aggregate steps/s from the
    end of the start steps (every member's) to the end of the last update."""
    config = TD3Config.model_validate(
        {
            "hidden": setting.hidden,
            "batch_size": setting.batch_size,
            "start_steps": START,
            "buffer_size": steps,
            "eval_every": 10**9,
            "eval_episodes": 1,
            "checkpoint_every": 10**9,
            "precision": precision,
            "device": setting.device,
            "update_schedule": "step",  # as SB3: train_freq=1
            # (no compile key when eager: the script then also runs on commits from
            # before td3.compile, to measure them the same way)
            **({} if compile == "none" else {"compile": compile}),
        }
    )
    embedding = _embedding(setting.device) if algo == "ede-td3" else None
    specs = [RunSpec(TASK, algo, seed, steps, config, EdeTD3Config()) for seed in range(members)]
    times: dict[int, float] = {}
    done = 0

    def progress(count: int) -> None:  # called with 1 after each member's step and updates
        nonlocal done
        done += count
        if done in (members * START, members * steps):
            _sync(setting.device)
            times[done] = time.perf_counter()

    with tempfile.TemporaryDirectory() as tmp:
        outs = [Path(tmp) / f"seed{spec.seed}" for spec in specs]
        train_group(specs, outs, embedding, torch.device(setting.device), progress)
    return members * (steps - START) / (times[members * steps] - times[members * START])


def warm(
    learner: Callable[..., float],
    steps: int,
    setting: Setting,
    *args: object,
    compiled: bool = False,
) -> Timing:
    """``learner`` timed after an untimed short run of its own; a compiled one compiles afresh
    there (``torch._dynamo.reset``: no graphs of other shapes, no recompile limit reached)."""
    if compiled:
        torch._dynamo.reset()
    learner(WARMUP, setting, *args)
    graphs = _graphs()
    rate = learner(steps, setting, *args)
    return Timing(rate, _graphs() - graphs)


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
    code = f"import torch; torch.set_num_threads(1); from ede.method.nets import product_error; product_error({precision!r})"
    result = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        env={**os.environ, "ONEDNN_VERBOSE": "1"},
        check=True,
    )
    kernels = set()
    for line in result.stdout.splitlines():
        fields = line.split(",")
        if fields[0] == "onednn_verbose" and "exec" in fields:
            at = fields.index("exec")
            kernels.add(f"{fields[at + 2]}:{fields[at + 3]}")
    return ", ".join(sorted(kernels)) or "none (torch's BLAS path)"


def describe_machine(precisions: list[str], device: str = "cpu") -> None:
    model, flags = cpu_model()
    print(
        f"CPU: {model}; flags: {' '.join(flags) or '-'}; torch {torch.__version__}, "
        f"CPU capability {torch.backends.cpu.get_cpu_capability()}"
    )
    for precision in precisions:
        error = product_error(precision)
        kind = "fp32-accurate" if error < 1e-4 else "bf16-rounded inputs"
        print(
            f"  {precision:<12} product error {error:.1e} ({kind}); oneDNN: {onednn_kernels(precision)}"
        )
    if device == "cuda":
        print(f"GPU: {torch.cuda.get_device_name()}")


def _shape(setting: Setting) -> str:
    return (
        f"{TASK}, {setting.device}, 1 torch thread, {'-'.join(map(str, setting.hidden))} "
        f"networks, batch {setting.batch_size}, one update per step after {START:,} "
        f"uniform random start steps"
    )


def _mark(timing: Timing) -> str:
    if not timing.compiled:
        return ""
    return f"  (compiled {timing.compiled} graphs while timed: understated)"


def table(args: argparse.Namespace, setting: Setting) -> None:
    """SB3, our single runs and our groups, in each compile mode: one table."""
    describe_machine(["fp32"], setting.device)
    reference = warm(sb3, args.steps, setting)
    rows: list[tuple[str, str, int, Timing]] = []  # label, mode, M, timing
    single: dict[str, float] = {}
    for members in [1, *args.members]:
        for mode in args.compile:
            steps = args.steps if members == 1 else args.group_steps
            timing = warm(
                ours, steps, setting, "td3", "fp32", mode, members, compiled=mode != "none"
            )
            if members == 1:
                single[mode] = timing.rate
            rows.append(
                ("ours TD3, one run" if members == 1 else "ours TD3, group", mode, members, timing)
            )
    print(_shape(setting))
    print(
        f"Timed: the {args.steps - START:,} steps after the start steps of {args.steps:,}-step "
        f"single runs; groups run {args.group_steps:,} steps per run (M x {args.group_steps:,} "
        f"environment steps), timed over M x {args.group_steps - START:,}"
        + (
            " (fewer per run, to keep this short; the rates count only timed steps)"
            if args.group_steps < args.steps
            else ""
        )
        + f". Each row after an untimed {WARMUP:,}-step-per-run warm-up of its own."
    )
    print(
        f"{'':<22} {'compile':<16} {'M':>2} {'steps/s':>9} {'x SB3':>6} "
        f"{'per run':>9} {'x single':>8}"
    )
    print(f"{'stable-baselines3 TD3':<22} {'-':<16} {1:>2} {reference.rate:9.0f} {1:6.2f}")
    for label, mode, members, timing in rows:
        line = (
            f"{label:<22} {mode:<16} {members:>2} {timing.rate:9.0f} "
            f"{timing.rate / reference.rate:6.2f}"
        )
        if members > 1:
            line += f" {timing.rate / members:9.0f} {timing.rate / single[mode]:8.2f}"
        print(line + _mark(timing))
    print(
        "steps/s: all M runs together; per run: steps/s / M; x single: steps/s over the one "
        "run's in the same compile mode"
    )


def precisions(args: argparse.Namespace, setting: Setting) -> None:
    """SB3 against our TD3 and EDE-TD3, single runs, in each precision and compile mode."""
    chosen = PRECISIONS if args.precisions == ["all"] else args.precisions
    describe_machine(chosen, setting.device)
    reference = warm(sb3, args.steps, setting)
    rows = []
    for precision in chosen:
        for mode in args.compile:
            td3 = warm(
                ours, args.steps, setting, "td3", precision, mode, 1, compiled=mode != "none"
            )
            ede = warm(
                ours, args.steps, setting, "ede-td3", precision, mode, 1, compiled=mode != "none"
            )
            rows.append((precision, mode, td3, ede))
    print(_shape(setting))
    print(
        f"Timed: the {args.steps - START:,} steps after the start steps of {args.steps:,}-step "
        f"runs, each after an untimed {WARMUP:,}-step warm-up of its own."
    )
    print(
        f"{'':<22} {'precision':<12} {'compile':<16} {'steps/s':>9} {'x SB3':>6} {'x our TD3':>9}"
    )
    print(f"{'stable-baselines3 TD3':<22} {'-':<12} {'-':<16} {reference.rate:9.0f} {1:6.2f}")
    for precision, mode, td3, ede in rows:
        print(
            f"{'ours TD3':<22} {precision:<12} {mode:<16} {td3.rate:9.0f} "
            f"{td3.rate / reference.rate:6.2f}{_mark(td3)}"
        )
        print(
            f"{'ours EDE-TD3':<22} {precision:<12} {mode:<16} {ede.rate:9.0f} "
            f"{ede.rate / reference.rate:6.2f} {ede.rate / td3.rate:9.2f}{_mark(ede)}"
        )


def _list(kind: Callable[[str], object], choices: list[str] | None = None) -> Callable[[str], list]:
    def parse(text: str) -> list:
        items = [kind(item.strip()) for item in text.split(",") if item.strip()]
        bad = [item for item in items if choices is not None and item not in choices]
        if not items or bad:
            raise argparse.ArgumentTypeError(
                f"expected a comma-separated list{' of ' + ', '.join(choices) if choices else ''}"
            )
        return items

    return parse


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0],
        epilog="See the module docstring (top of this file) for what each row measures.",
    )
    parser.add_argument(
        "--hidden",
        type=_list(int),
        default=[400, 300],
        help="hidden widths, comma-separated (default 400,300: the paper's)",
    )
    parser.add_argument("--batch-size", type=int, default=100, help="default 100: the paper's")
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    parser.add_argument(
        "--steps",
        type=int,
        default=5_000,
        help=f"steps of a single run, the first {START:,} untimed (default 5000)",
    )
    parser.add_argument(
        "--group-steps",
        type=int,
        help=f"steps per run of a group, the first {START:,} untimed (default: "
        f"{START:,} plus half of --steps' timed steps, 3000 at --steps 5000)",
    )
    parser.add_argument(
        "--members",
        type=_list(int),
        default=[4, 8],
        help="group sizes, comma-separated (default 4,8)",
    )
    parser.add_argument(
        "--compile",
        type=_list(str, COMPILE_MODES),
        default=["none", "default"],
        help="td3.compile modes, comma-separated: none, default, reduce-overhead "
        "(CUDA only); default none,default",
    )
    parser.add_argument(
        "--precisions",
        type=_list(str, [*PRECISIONS, "all"]),
        help="measure our TD3 and EDE-TD3 in these td3.precision values "
        f"({', '.join(PRECISIONS)} or all) instead of the groups table "
        "(--members and --group-steps then unused)",
    )
    args = parser.parse_args()
    if args.group_steps is None:
        args.group_steps = START + (args.steps - START) // 2
    if args.steps <= START or args.group_steps <= START:
        parser.error(f"--steps and --group-steps must exceed the {START:,} start steps")
    if any(m < 2 for m in args.members):
        parser.error("--members: group sizes of 2 or more (the single run is always measured)")
    if args.device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda: no CUDA device here")
    if "reduce-overhead" in args.compile and args.device != "cuda":
        parser.error("--compile reduce-overhead: CUDA graphs, --device cuda only")
    torch.set_num_threads(1)
    setting = Setting(args.hidden, args.batch_size, args.device)
    if args.precisions:
        precisions(args, setting)
    else:
        table(args, setting)


if __name__ == "__main__":
    main()
