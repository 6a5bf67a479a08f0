"""Training throughput of our TD3 and EDE-TD3 against stable-baselines3's TD3, side by side, and
where one update's time goes against the machine's measured peak.

    python benchmarks/train_throughput.py [--hidden 400,300] [--batch-size 100] [--device cpu|cuda]
                                          [--steps 2500] [--rounds 5] [--algos td3,ede-td3]
                                          [--compile auto[,none,default]] [--precisions fp32[,...]|all]
                                          [--members 4,8] [--group-steps N] [--tiny]

Everything runs in one process with one torch thread, on gymnasium's ``Reacher-v5``, with the
per-step schedule of stable-baselines3 (SB3): 1,000 uniform random start steps, then one update
after every environment step (batch ``--batch-size``, ``--hidden`` networks, policy delay 2).
``--hidden 400,300 --batch-size 100`` (the default) is the paper's TD3; ``--hidden 256,256
--batch-size 256`` is SB3's default.

It prints three things.

**The machine**: the CPU model, its bf16-related flags, and for each precision measured the
error of a product against float64 (``ede.method.nets.product_error``) and the oneDNN kernel that
computed it (none means torch's own BLAS path); with ``--device cuda`` the GPU.

**One update** (CPU only), ours (each of ``--algos``, fp32, eager and — where ``--compile``
compiles here, as ``auto`` does with a C++ compiler — compiled) and SB3's ``TD3.train`` of one
gradient step, each on a replay buffer of random steps: its matrix-product FLOPs, counted from the
shapes of the products it ran (``2·b·m·k·n`` for a batch of b ``(m, k) @ (k, n)``, as
``torch.profiler`` records them; the elementwise work — Adam, ReLUs, the one-output layers'
products and sums — is left out, well under 1% of the FLOPs), its time (the median of
``UPDATE_REPEATS`` blocks of updates, unprofiled), the GFLOP/s that makes, and the machine's fp32
matrix-product peak, measured here: a 2048² ``torch.mm`` on one thread. Then the split of the
update's time: the products (their own time under the profiler), the optimiser (its steps,
timed by a clock around each in the unprofiled updates; the profiler would inflate SB3's ~100 small
operations a step; compiled, Adam is fused into the update's kernels, in the rest) and the rest
(the update's time less both: elementwise work, allocation, Python and dispatch; compiled, the
fused kernels and the compiled code's guard check and wrapper).

**Side by side** (``ROUNDS``): every arm — SB3's TD3 (the reference), our ``--algos`` in each
``--precisions`` and ``--compile`` setting, and groups of ``--members`` seeds — trains a run of
``--steps`` steps once a round, the arms in a rotated order, over ``--rounds`` rounds after an
untimed warm-up round (imports, first calls, kernel choices, compiling). A rate is environment
steps per second after the start steps (each with its update), all members together for a group;
each arm's ratio to SB3 is taken within a round, and the table gives the median ratio and its
min–max over the rounds. So load that drifts during the script moves both sides of a ratio alike:
read the ratios, not the rates. A group's ``x one run`` is its aggregate rate over our one run of
the same algorithm and setting in the same round (what one process of M seeds buys against M
processes one after another on one core). A row whose timed run compiled something (it should
not) is marked: its rate is understated.

``--compile auto`` (the default) measures what a user's default, ``td3.compile: auto``, does for a
run long enough to repay compiling (``ede.run.group.COMPILE_FROM_UPDATES`` updates; a paper run):
compiled where a C++ compiler is found, eager elsewhere — the script prints which; the
2,500-step runs timed here would otherwise stay eager. ``--compile auto,none`` adds the eager
update beside it.

With the defaults (5 rounds of 2,500-step runs: SB3, TD3, EDE-TD3) a whole invocation takes about
5 minutes on an idle core of our AVX-512 AMD EPYC (half a minute of compiling per compiled arm,
a few seconds where Inductor's on-disk cache holds it); ``--compile auto,none`` about half as long again. ``--tiny`` (16-16 networks,
batch 8, 100 start steps, runs of 150 steps, one round) checks in half a minute that it runs to
the end (``tests/test_benchmarks.py``).

An earlier commit is measured by this script run in that commit's environment (its ``ede`` is
imported; ``--compile none`` where it has no ``auto``): e.g. ``git worktree add /tmp/before HEAD~1``, ``make -C /tmp/before
install``, then ``/tmp/before/.venv/bin/python benchmarks/train_throughput.py`` from this
checkout.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, get_args

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
PRODUCTS = ("aten::mm", "aten::addmm", "aten::bmm", "aten::baddbmm")  # what FLOPs count
UPDATE_REPEATS, UPDATES = 7, 40  # blocks of updates timed, updates a block
PEAK_SIZE = 2048  # the peak's torch.mm: PEAK_SIZE² by PEAK_SIZE²


@dataclass(frozen=True)
class Setting:
    hidden: list[int]
    batch_size: int
    device: str
    start: int = 1_000  # uniform random start steps, no updates


@dataclass(frozen=True)
class Arm:
    """One learner of the side-by-side table: SB3's TD3 (``algo`` "sb3") or ours."""

    algo: str
    precision: str = "fp32"
    compile: str = "none"
    members: int = 1

    @property
    def label(self) -> str:
        if self.algo == "sb3":
            return "stable-baselines3 TD3"
        kind = "one run" if self.members == 1 else f"group of {self.members}"
        return f"ours {'TD3' if self.algo == 'td3' else 'EDE-TD3'}, {kind}"


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
            if self.num_timesteps == setting.start:  # SB3 updates after steps > learning_starts
                _sync(setting.device)
                self.started = time.perf_counter()
            return True

    env = gymnasium.make(TASK)
    model = TD3(
        "MlpPolicy",
        env,
        learning_rate=1e-3,
        buffer_size=steps,
        learning_starts=setting.start,
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
    return (steps - setting.start) / (time.perf_counter() - clock.started)


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


def _resolved(compile: str, device: str) -> str:
    """``td3.compile`` as a run long enough to repay compiling (a paper run) takes it here."""
    if compile != "auto":
        return compile
    from ede.run.group import COMPILE_FROM_UPDATES, compile_mode

    return compile_mode(compile, COMPILE_FROM_UPDATES, torch.device(device))


def ours(
    steps: int, setting: Setting, algo: Algo, precision: str, compile: str, members: int
) -> float:
    """Our ``algo``, ``members`` seeds as one group (one run if 1): aggregate steps/s from the
    end of the start steps (every member's) to the end of the last update."""
    config = TD3Config.model_validate(
        {
            "hidden": setting.hidden,
            "batch_size": setting.batch_size,
            "start_steps": setting.start,
            "buffer_size": steps,
            "eval_every": 10**9,
            "eval_episodes": 1,
            "checkpoint_every": 10**9,
            "precision": precision,
            "device": setting.device,
            "update_schedule": "step",  # as SB3: train_freq=1
            # (no compile key for eager on a commit from before td3.compile, so that the
            # script measures it the same way)
            **({"compile": compile} if "compile" in TD3Config.model_fields else {}),
        }
    )
    if compile == "auto":
        config = config.model_copy(update={"compile": _resolved(compile, setting.device)})
    embedding = _embedding(setting.device) if algo == "ede-td3" else None
    specs = [RunSpec(TASK, algo, seed, steps, config, EdeTD3Config()) for seed in range(members)]
    times: dict[int, float] = {}
    done = 0

    def progress(count: int) -> None:  # called with 1 after each member's step and updates
        nonlocal done
        done += count
        if done in (members * setting.start, members * steps):
            _sync(setting.device)
            times[done] = time.perf_counter()

    with tempfile.TemporaryDirectory() as tmp:
        outs = [Path(tmp) / f"seed{spec.seed}" for spec in specs]
        train_group(specs, outs, embedding, torch.device(setting.device), progress)
    return (
        members
        * (steps - setting.start)
        / (times[members * steps] - times[members * setting.start])
    )


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
        f"networks, batch {setting.batch_size}, one update per step after {setting.start:,} "
        f"uniform random start steps"
    )


def peak_gflops(device: str) -> float:
    """The machine's fp32 matrix-product peak on one thread: the best of a few 2048² ``torch.mm``."""
    a, b = (torch.randn(PEAK_SIZE, PEAK_SIZE, device=device) for _ in range(2))
    best = float("inf")
    for _ in range(6):
        _sync(device)
        began = time.perf_counter()
        torch.mm(a, b)
        _sync(device)
        best = min(best, time.perf_counter() - began)
    return 2 * PEAK_SIZE**3 / best / 1e9


@dataclass(frozen=True)
class Update:
    """One update's cost: matrix-product FLOPs, seconds, and seconds in products and optimiser
    (None where it is fused into a compiled update)."""

    flops: float
    seconds: float
    products: float
    optimiser: float | None


def _flops(name: str, shapes: list[list[int]]) -> float:
    """2·b·m·k·n of product ``name``'s recorded input shapes: its two factors, after the bias for
    addmm and baddbmm (a compiled update's products also record their ``out``, last)."""
    first = 1 if name in ("aten::addmm", "aten::baddbmm") else 0
    left, right = shapes[first : first + 2]
    return 2.0 * float(np.prod(left)) * right[-1]


class Clocked:
    """An update and the seconds its optimiser steps took: each ``step`` of ``optimisers`` wrapped
    in a clock."""

    def __init__(self, update: Callable[[], object], optimisers: list[Any]) -> None:
        self.update, self.seconds = update, 0.0
        for optimiser in optimisers:
            optimiser.step = self._clocked(optimiser.step)

    def _clocked(self, step: Callable[..., Any]) -> Callable[..., Any]:
        def clocked(*args: Any, **kwargs: Any) -> Any:
            began = time.perf_counter()
            result = step(*args, **kwargs)
            self.seconds += time.perf_counter() - began
            return result

        return clocked


def measure_update(clocked: Clocked, compiled: bool = False) -> Update:
    """An update (warmed up) timed with its optimiser steps (none clocked where ``compiled``),
    then profiled for its products."""
    from torch.profiler import ProfilerActivity, profile

    blocks, clocked.seconds = [], 0.0
    for _ in range(UPDATE_REPEATS):
        began = time.perf_counter()
        for _ in range(UPDATES):
            clocked.update()
        blocks.append((time.perf_counter() - began) / UPDATES)
    optimiser = clocked.seconds / (UPDATE_REPEATS * UPDATES)
    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as profiled:
        for _ in range(UPDATES):
            clocked.update()
    products = [e for e in profiled.events() if e.name in PRODUCTS]
    return Update(
        flops=sum(_flops(e.name, e.input_shapes) for e in products) / UPDATES,
        seconds=statistics.median(blocks),
        products=sum(e.self_cpu_time_total for e in products) / 1e6 / UPDATES,
        optimiser=None if compiled else optimiser,
    )


def sb3_update(setting: Setting) -> Clocked:
    """SB3's ``TD3.train`` of one gradient step, after its start steps filled its buffer."""
    import gymnasium
    from stable_baselines3 import TD3

    model = TD3(
        "MlpPolicy",
        gymnasium.make(TASK),
        learning_rate=1e-3,
        learning_starts=setting.start,
        batch_size=setting.batch_size,
        policy_kwargs={"net_arch": setting.hidden},
        seed=0,
        device=setting.device,
    )
    model.learn(total_timesteps=setting.start + 10)
    return Clocked(
        lambda: model.train(gradient_steps=1, batch_size=setting.batch_size),
        [model.actor.optimizer, model.critic.optimizer],
    )


def ours_update(setting: Setting, algo: str, compile: str = "none") -> Clocked:
    """Our agent's update (fp32, ``td3.compile`` ``compile``) on a buffer of random steps; eager,
    its Adam steps clocked (compiled, they are fused into the update: not clocked)."""
    import gymnasium

    from ede.method.adapters import EmbeddingAdapter, IdentityAdapter
    from ede.method.agent import Agent
    from ede.method.replay import ReplayBuffer

    device = torch.device(setting.device)
    env = gymnasium.make(TASK)
    low, high = env.action_space.low, env.action_space.high  # type: ignore[attr-defined]
    obs_size = int(np.prod(env.observation_space.shape))  # type: ignore[arg-type]
    adapter: Any = (
        IdentityAdapter(low, high, device)
        if algo == "td3"
        else EmbeddingAdapter(_embedding(setting.device))
    )
    config = TD3Config.model_validate(  # no compile key for eager, as ours() (an earlier commit)
        {
            "hidden": setting.hidden,
            "batch_size": setting.batch_size,
            **({"compile": compile} if compile != "none" else {}),
        }
    )
    agent = Agent(obs_size, adapter, config, device)
    buffer = ReplayBuffer(setting.start, obs_size, adapter.code_size, adapter.k, device)
    rng, one = np.random.default_rng(0), np.ones(1, dtype=bool)
    for _ in range(setting.start):
        code = torch.as_tensor(rng.uniform(-1, 1, (1, adapter.code_size)), dtype=torch.float32)
        obs, reward, next_obs = (
            rng.normal(size=(1, obs_size)),
            rng.normal(size=1),
            rng.normal(size=(1, obs_size)),
        )
        no = np.zeros(1, dtype=bool)
        buffer.add(one, obs, code, rng.integers(adapter.k, size=1), reward, next_obs, no, no)
    optimisers = [agent.critic_adam, agent.actor_adam] if compile == "none" else []
    return Clocked(lambda: agent.update(buffer), optimisers)


def updates(args: argparse.Namespace, setting: Setting) -> None:
    """One update of SB3's TD3 and of each of ours (eager, and compiled where ``--compile``
    compiles here): FLOPs, time, GFLOP/s against the peak, and where the time goes."""
    compiled = sorted({_resolved(mode, setting.device) for mode in args.compile} - {"none"})
    learners = {"stable-baselines3 TD3": sb3_update(setting)} | {
        f"ours {'TD3' if algo == 'td3' else 'EDE-TD3'}{'' if mode == 'none' else ', compiled'}": (
            ours_update(setting, algo, mode)
        )
        for algo in args.algos
        for mode in ["none", *compiled]
    }
    for clocked in learners.values():  # first calls, kernel choices, compiling
        for _ in range(20):
            clocked.update()
    peak = peak_gflops(setting.device)
    measured = {
        name: measure_update(clocked, compiled=name.endswith(", compiled"))
        for name, clocked in learners.items()
    }
    print(
        f"One update ({'-'.join(map(str, setting.hidden))}, batch {setting.batch_size}, "
        f"fp32; the actor every 2nd): fp32 matrix-product peak {peak:.0f} GFLOP/s "
        f"({PEAK_SIZE}² torch.mm, one thread)"
    )
    print(
        f"{'':<32} {'MFLOP':>7} {'ms':>6} {'GFLOP/s':>8} {'of peak':>7}   "
        f"{'products':>8} {'optimiser':>9} {'rest':>6}"
    )
    for name, u in measured.items():
        rest = u.seconds - u.products - (u.optimiser or 0.0)
        shares = [
            None if part is None else 100 * part / u.seconds
            for part in (u.products, u.optimiser, rest)
        ]
        print(
            f"{name:<32} {u.flops / 1e6:7.2f} {u.seconds * 1e3:6.2f} {u.flops / u.seconds / 1e9:8.1f} "
            f"{100 * u.flops / u.seconds / 1e9 / peak:6.0f}%   "
            + " ".join(
                f"{share:8.0f}%" if share is not None else f"{'fused':>9}" for share in shares
            )
        )
    print(
        "MFLOP: matrix products per update, from their shapes; products: their own time under "
        "the profiler; optimiser: Adam's steps, by a clock (compiled: fused, in the rest); rest: the "
        "update's time less both (elementwise work, allocation, Python and dispatch; compiled: "
        "the fused kernels, the compiled code's guards and wrapper). At the peak, the products alone would take "
        + ", ".join(f"{u.flops / peak / 1e6:.2f} ms ({name})" for name, u in measured.items())
        + "."
    )


def side_by_side(args: argparse.Namespace, setting: Setting, arms: list[Arm]) -> None:
    """Every arm once a round, in a rotated order; ratios to SB3 within each round."""

    def run(arm: Arm, steps: int) -> float:
        if arm.algo == "sb3":
            return sb3(steps, setting)
        algo: Algo = "td3" if arm.algo == "td3" else "ede-td3"
        return ours(steps, setting, algo, arm.precision, arm.compile, arm.members)

    def steps(arm: Arm) -> int:
        return args.steps if arm.members == 1 else args.group_steps

    if any(arm.compile != "none" for arm in arms):
        torch._dynamo.reset()
    if any(arm.compile == "auto" for arm in arms):
        from ede.run.group import COMPILE_FROM_UPDATES, compiler_missing

        mode = _resolved("auto", setting.device)
        print(
            f"td3.compile auto (the default) runs as a run of {COMPILE_FROM_UPDATES:,} updates or "
            f"more takes it here: {mode}"
            + (
                f" ({compiler_missing(torch.device(setting.device))} not found)"
                if mode == "none"
                else ""
            )
        )
    for arm in arms:  # the warm-up round: compiles, first calls, kernel choices
        run(arm, min(setting.start + 300, steps(arm)))
    rates: dict[Arm, list[float]] = {arm: [] for arm in arms}
    compiled: dict[Arm, int] = dict.fromkeys(arms, 0)
    for r in range(args.rounds):
        for arm in arms[r % len(arms) :] + arms[: r % len(arms)]:
            graphs = _graphs()
            rates[arm].append(run(arm, steps(arm)))
            compiled[arm] += _graphs() - graphs
    reference = rates[arms[0]]
    print(_shape(setting))
    print(
        f"Side by side: {args.rounds} rounds, each arm once a round in a rotated order, after an "
        f"untimed warm-up round; runs of {args.steps:,} steps"
        + (f" (groups {args.group_steps:,} a run)" if args.group_steps != args.steps else "")
        + f", timed after the {setting.start:,} start steps. Ratios within a round: median (min–max)."
    )
    print(
        f"{'':<26} {'precision':<11} {'compile':<9} {'steps/s':>8} {'x SB3':>6} {'(min–max)':>12} "
        f"{'x one run':>9}"
    )
    for arm in arms:
        ratios = [rate / ref for rate, ref in zip(rates[arm], reference, strict=True)]
        line = (
            f"{arm.label:<26} {arm.precision if arm.algo != 'sb3' else '-':<11} "
            f"{arm.compile if arm.algo != 'sb3' else '-':<9} {statistics.median(rates[arm]):8.0f} "
            f"{statistics.median(ratios):6.2f} {f'({min(ratios):.2f}–{max(ratios):.2f})':>12}"
        )
        if arm.members > 1:
            single = rates[Arm(arm.algo, arm.precision, arm.compile)]
            line += (
                f" {statistics.median(g / s for g, s in zip(rates[arm], single, strict=True)):9.2f}"
            )
        if compiled[arm]:
            line += f"  (compiled {compiled[arm]} graphs while timed: understated)"
        print(line)
    print("steps/s: the median over rounds, all members together for a group")


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
        epilog="See the module docstring (top of this file) for what each part measures.",
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
        "--steps", type=int, default=2_500, help="steps of a run, the first 1,000 untimed"
    )
    parser.add_argument("--rounds", type=int, default=5, help="timed rounds (default 5)")
    parser.add_argument(
        "--algos",
        type=_list(str, ["td3", "ede-td3"]),
        default=["td3", "ede-td3"],
        help="ours, comma-separated (default td3,ede-td3)",
    )
    parser.add_argument(
        "--compile",
        type=_list(str, COMPILE_MODES),
        default=["auto" if "auto" in COMPILE_MODES else "none"],
        help="td3.compile modes, comma-separated: auto (as a run long enough to repay "
        "compiling takes it: compiled where a compiler is), none, default, reduce-overhead "
        "(CUDA only); default auto; an earlier commit without td3.compile: none",
    )
    parser.add_argument(
        "--precisions",
        type=_list(str, [*PRECISIONS, "all"]),
        default=["fp32"],
        help=f"td3.precision values ({', '.join(PRECISIONS)} or all; default fp32)",
    )
    parser.add_argument(
        "--members",
        type=_list(int),
        default=[],
        help="group sizes of 2 or more, comma-separated (default none: one run alone)",
    )
    parser.add_argument(
        "--group-steps", type=int, help="steps per run of a group (default --steps)"
    )
    parser.add_argument(
        "--tiny", action="store_true", help="16-16 networks, batch 8, runs of 150 steps, one round"
    )
    args = parser.parse_args()
    start = 1_000
    if args.tiny:
        args.hidden, args.batch_size, args.steps, args.rounds, start = [16, 16], 8, 150, 1, 100
    args.group_steps = args.group_steps or args.steps
    if min(args.steps, args.group_steps) <= start:
        parser.error(f"--steps and --group-steps must exceed the {start:,} start steps")
    if any(m < 2 for m in args.members):
        parser.error("--members: group sizes of 2 or more (the single run is always measured)")
    if args.device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda: no CUDA device here")
    if "reduce-overhead" in args.compile and args.device != "cuda":
        parser.error("--compile reduce-overhead: CUDA graphs, --device cuda only")
    torch.set_num_threads(1)
    setting = Setting(args.hidden, args.batch_size, args.device, start)
    precisions = PRECISIONS if args.precisions == ["all"] else args.precisions
    describe_machine(precisions, setting.device)
    if setting.device == "cpu":
        updates(args, setting)
    arms = [Arm("sb3")] + [
        Arm(algo, precision, mode, members)
        for members in [1, *args.members]
        for algo in args.algos
        for precision in precisions
        for mode in args.compile
    ]
    side_by_side(args, setting, arms)


if __name__ == "__main__":
    main()
