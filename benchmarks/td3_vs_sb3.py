"""Learning curves: our TD3 against stable-baselines3's TD3, same settings, same evaluation.

    python benchmarks/td3_vs_sb3.py run --learner ours|sb3 --seeds 0-7 [--steps 30000] --out DIR
    python benchmarks/td3_vs_sb3.py summarise --out DIR
    python benchmarks/td3_vs_sb3.py untrained [--seeds 0-39]

On gymnasium's ``Reacher-v5`` at the paper's TD3 settings (400-300 networks, batch 100, lr 1e-3,
gamma 0.99, tau 0.005, target noise 0.2 clipped at 0.5, policy delay 2, exploration noise 0.1,
1,000 uniform random start steps, then one update per environment step), each learner trains one
run per seed on one torch thread. Both are evaluated by the same protocol: every 1,000 steps, 10
deterministic episodes whose starts are the ones our runs use for that seed (``reset(seed=b + e)``
with ``b = EVAL_SEED_OFFSET * (seed + 1)``), so evaluation starts cannot separate the two.

Each finished (learner, seed) writes ``DIR/<learner>-seed<N>.json`` (runs already there are
skipped, so a killed batch resumes by seed); ``summarise`` prints the mean curve of each learner
with its 95% percentile bootstrap band over seeds, and at which evaluations our mean lies outside
stable-baselines3's band; then the area under each learner's curve, and the difference ours − SB3
of the means, over the run and per evaluation, with bootstrap intervals. The area is given twice:
over the run, and from the first evaluation after an update on, since the first two evaluations
(steps 0 and 1,000) score the untrained policy, whose return varies from seed to seed with its
initial weights alone (standard deviation about 21 over seeds); ``untrained`` measures that
distribution for both learners over many seeds (both initialise as ``nn.Linear`` does, from
different random streams).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import gymnasium
import numpy as np
import torch

from ede.analysis.stats import bootstrap_mean
from ede.config import EdeTD3Config, TD3Config
from ede.method.adapters import IdentityAdapter
from ede.method.agent import Agent
from ede.run.evaluation import EVAL_SEED_OFFSET, evaluate
from ede.run.runs import area_under_curve
from ede.run.spec import RunSpec
from ede.run.training import train_run
from ede.run.vector import MemberEnvs
from ede.tasks import action_bounds, observation_size

TASK = "Reacher-v5"
START = 1_000
EVAL_EVERY = 1_000
EVAL_EPISODES = 10


def evaluate_sb3(model, seed: int) -> float:
    env = gymnasium.make(TASK)
    base = EVAL_SEED_OFFSET * (seed + 1)
    returns = []
    for e in range(EVAL_EPISODES):
        obs, _ = env.reset(seed=base + e)
        done, total = False, 0.0
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, reward, terminated, truncated, _ = env.step(action)
            total += float(reward)
            done = terminated or truncated
        returns.append(total)
    return float(np.mean(returns))


def sb3_model(seed: int):
    from stable_baselines3 import TD3
    from stable_baselines3.common.noise import NormalActionNoise

    return TD3(
        "MlpPolicy",
        gymnasium.make(TASK),
        learning_rate=1e-3,
        buffer_size=1_000_000,
        learning_starts=START,
        batch_size=100,
        tau=0.005,
        gamma=0.99,
        train_freq=1,
        gradient_steps=1,
        action_noise=NormalActionNoise(np.zeros(2), 0.1 * np.ones(2)),
        policy_delay=2,
        target_policy_noise=0.2,
        target_noise_clip=0.5,
        policy_kwargs={"net_arch": [400, 300]},
        seed=seed,
        device="cpu",
        verbose=0,
    )


def ours_config() -> TD3Config:
    return TD3Config(
        hidden=[400, 300],
        batch_size=100,
        start_steps=START,
        eval_every=EVAL_EVERY,
        eval_episodes=EVAL_EPISODES,
        checkpoint_every=5_000,
        update_schedule="step",
        compile="none",  # eager, as the published comparison ran
    )  # SB3 updates after every step (train_freq=1)


def run_sb3(seed: int, steps: int) -> list[tuple[int, float]]:
    from stable_baselines3.common.callbacks import BaseCallback

    model = sb3_model(seed)
    curve = [(0, evaluate_sb3(model, seed))]

    class Evaluate(BaseCallback):
        def _on_step(self) -> bool:
            if self.num_timesteps % EVAL_EVERY == 0:
                curve.append((self.num_timesteps, evaluate_sb3(self.model, seed)))
            return True

    model.learn(total_timesteps=steps, callback=Evaluate())
    return curve


def run_ours(seed: int, steps: int, out: Path) -> list[tuple[int, float]]:
    spec = RunSpec(TASK, "td3", seed, steps, ours_config(), EdeTD3Config())
    train_run(spec, out / f"ours-seed{seed}-run", None)
    lines = (out / f"ours-seed{seed}-run" / "eval.csv").read_text().splitlines()[1:]
    return [(int(float(line.split(",")[0])), float(line.split(",")[2])) for line in lines]


def untrained(seeds: list[int], confidence: float = 0.95) -> None:
    """The evaluation return of each learner's untrained policy (its step-0 evaluation), over
    many seeds: both initialise as ``nn.Linear`` does, from different random streams, so the two
    should be samples of one distribution."""
    env = gymnasium.make(TASK)
    adapter = IdentityAdapter(*action_bounds(env), torch.device("cpu"))
    obs_size = observation_size(env)
    scores: dict[str, list[float]] = {"sb3": [], "ours": []}
    for seed in seeds:
        scores["sb3"].append(evaluate_sb3(sb3_model(seed), seed))
        agent = Agent(obs_size, adapter, ours_config(), torch.device("cpu"), [seed])
        returns = evaluate(
            MemberEnvs([lambda: env]),
            agent.act,
            adapter,
            EVAL_EPISODES,
            [EVAL_SEED_OFFSET * (seed + 1)],
        )
        scores["ours"].append(float(returns.mean()))
    rng = np.random.default_rng(0)
    for name, values in scores.items():
        print(
            f"untrained policy, {name} ({len(seeds)} seeds): "
            f"{bootstrap_mean(np.array(values), confidence, 2_000, rng)}, "
            f"standard deviation over seeds {np.std(values, ddof=1):.2f}"
        )


def summarise(out: Path, confidence: float = 0.95) -> None:
    curves = {}
    for learner in ("sb3", "ours"):
        runs = [json.loads(p.read_text()) for p in sorted(out.glob(f"{learner}-seed*.json"))]
        if runs:
            curves[learner] = ({row[0] for run in runs for row in run["curve"]}, runs)
    rng = np.random.default_rng(0)
    steps = sorted(set.intersection(*(s for s, _ in curves.values())))
    print(f"{TASK}: mean evaluation return over seeds [{100 * confidence:.0f}% bootstrap band]")
    print(
        "step    "
        + "".join(f"{name} ({len(runs)} seeds)".ljust(34) for name, (_, runs) in curves.items())
    )
    outside = []
    for step in steps:
        cells, bands = [], {}
        for name, (_, runs) in curves.items():
            values = np.array([dict(map(tuple, run["curve"]))[step] for run in runs])
            band = bootstrap_mean(values, confidence, 2_000, rng)
            bands[name] = (band.mean, band)
            cells.append(f"{values.mean():8.2f} [{band.low:7.2f}, {band.high:7.2f}]".ljust(34))
        print(f"{step:<8d}" + "".join(cells))
        if "ours" in bands and "sb3" in bands:
            mean, (low, high) = bands["ours"][0], (bands["sb3"][1].low, bands["sb3"][1].high)
            if not low - 1e-9 <= mean <= high + 1e-9:
                outside.append((step, "above" if mean > high else "below"))
    print(
        f"our mean outside stable-baselines3's band at {len(outside)} of {len(steps)} evaluations:",
        ", ".join(f"{s} ({side})" for s, side in outside) or "none",
    )
    if {"ours", "sb3"} <= curves.keys():
        difference(curves, steps, confidence, rng)


def difference(
    curves: dict,
    steps: list[int],
    confidence: float,
    rng: np.random.Generator,
    samples: int = 2_000,
) -> None:
    """Ours minus SB3: the area under the curve (mean return over the run) of each, and per
    evaluation and over the run the difference of the means with a bootstrap interval that
    resamples each learner's seeds independently."""
    values = {
        name: np.array([[dict(map(tuple, run["curve"]))[step] for step in steps] for run in runs])
        for name, (_, runs) in curves.items()
    }  # (seeds, evaluations)
    tail = (1 - confidence) / 2
    learning = np.array(steps) > START  # from the first evaluation after an update on
    for label, kept in (
        ("over the run", slice(None)),
        (f"from {steps[int(np.argmax(learning))]:,} steps on (trained policies)", learning),
    ):
        part = np.array(steps)[kept]
        auc = {
            name: np.array([area_under_curve(part, row[kept]) for row in v])
            for name, v in values.items()
        }
        for name in ("sb3", "ours"):
            print(
                f"area under the curve {label}, {name}: "
                f"{bootstrap_mean(auc[name], confidence, samples, rng)}"
            )
        aucs = {
            name: a[rng.integers(len(a), size=(samples, len(a)))].mean(axis=1)
            for name, a in auc.items()
        }
        low, high = np.quantile(aucs["ours"] - aucs["sb3"], [tail, 1 - tail])
        print(
            f"area under the curve {label}, ours - sb3: "
            f"{auc['ours'].mean() - auc['sb3'].mean():+.2f} [{low:+.2f}, {high:+.2f}]"
        )
    draws = {
        name: v[rng.integers(len(v), size=(samples, len(v)))].mean(axis=1)
        for name, v in values.items()
    }  # (samples, evaluations)
    gaps = draws["ours"] - draws["sb3"]
    lows, highs = np.quantile(gaps, [tail, 1 - tail], axis=0)
    means = values["ours"].mean(axis=0) - values["sb3"].mean(axis=0)
    print("difference of the means per evaluation, ours - sb3 [interval]:")
    for step, mean, lo, hi in zip(steps, means, lows, highs, strict=True):
        print(f"  {step:<8d}{mean:+6.2f} [{lo:+6.2f}, {hi:+6.2f}]")
    apart = [
        (step, "above" if lo > 0 else "below")
        for step, lo, hi in zip(steps, lows, highs, strict=True)
        if lo > 0 or hi < 0
    ]
    print(
        f"difference of the means excludes 0 at {len(apart)} of {len(steps)} evaluations:",
        ", ".join(f"{s} ({side})" for s, side in apart) or "none",
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run")
    run.add_argument("--learner", choices=["ours", "sb3"], required=True)
    run.add_argument("--seeds", default="0-7", help="e.g. 0-7 or 0,2,5")
    run.add_argument("--steps", type=int, default=30_000)
    run.add_argument("--out", type=Path, required=True)
    show = sub.add_parser("summarise")
    show.add_argument("--out", type=Path, required=True)
    init = sub.add_parser("untrained", help="the untrained policies' returns over many seeds")
    init.add_argument("--seeds", default="0-39")
    args = parser.parse_args()
    if args.command == "summarise":
        summarise(args.out)
        return
    torch.set_num_threads(1)
    first, _, last = args.seeds.partition("-")
    seeds = (
        list(range(int(first), int(last) + 1)) if last else [int(s) for s in args.seeds.split(",")]
    )
    if args.command == "untrained":
        untrained(seeds)
        return
    args.out.mkdir(parents=True, exist_ok=True)
    for seed in seeds:
        result = args.out / f"{args.learner}-seed{seed}.json"
        if result.exists():
            continue
        start = time.perf_counter()
        curve = (
            run_sb3(seed, args.steps)
            if args.learner == "sb3"
            else run_ours(seed, args.steps, args.out)
        )
        result.write_text(
            json.dumps(
                {
                    "learner": args.learner,
                    "seed": seed,
                    "steps": args.steps,
                    "seconds": time.perf_counter() - start,
                    "curve": curve,
                }
            )
        )
        print(
            f"{args.learner} seed {seed}: final {curve[-1][1]:.2f} in {time.perf_counter() - start:.0f}s",
            flush=True,
        )


if __name__ == "__main__":
    main()
