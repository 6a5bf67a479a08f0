"""Sweep wall time: the stages of two families, and four short train runs, through ``dvc repro``
against ``ede-pipeline sweep --jobs 2``.

    python benchmarks/sweep.py [--steps 3000] [--jobs 2]

Scratch copies of this repo (its files in a fresh git repository under a temporary folder, made by
``tests.support.scratch_copy`` as the tests make theirs) with small params. First the families:
two tasks of two families (ReacherVertical, Pusher), their task code, collect, encoder, decoder and
task-input stages, timed as ``dvc repro task_inputs`` (one stage at a time) and as ``ede-pipeline
sweep task_inputs --jobs N`` (in waves, the two families side by side); the two copies must record
the same outputs. Then the runs: one reacher task, TD3 and EDE-TD3, two seeds — four runs of
``--steps`` environment steps each; the embedding is made once, untimed, and copied to both; timed
``dvc repro train`` in one copy and ``ede-pipeline sweep train --jobs N`` in the other, which must
agree on every run's returns. Each time includes the commands' start-up and DVC's hashing and
caching. Prints the wall times and ratios; goal for the runs: >= 1.8x with 2 jobs on 2 cores.
"""

from __future__ import annotations

import argparse
import csv
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the checkout: its tests' support
from tests.support import BIN, run, scratch_copy

TASK = "ede/ReacherVertical-v0"
FAMILIES = {TASK: "reacher", "ede/Pusher-v0": "sevendof"}  # a task of each of two families


def small_params(
    steps: int, tasks: dict[str, str] | None = None
) -> Callable[[dict[str, Any]], None]:
    """An edit of params.yaml: one reacher task (or ``tasks``), two seeds, runs of ``steps``
    steps, small nets."""

    def edit(params: dict[str, Any]) -> None:
        params["collect"].update(steps=2_000, num_envs=1)
        small = {"hidden": [64, 64], "epochs": 1, "batch_size": 64}
        params["embedding"].update(small)
        params["decoder"].update(small)
        params["td3"].update(
            hidden=[64, 64],
            start_steps=500,
            eval_every=steps // 4,
            eval_episodes=2,
            checkpoint_every=10 * steps,
        )
        params["runs"].update(
            tasks=tasks or {TASK: "reacher"},
            seeds=[0, 1],
            budgets={task: steps for task in params["runs"]["budgets"]},
        )

    return edit


def timed(copy: Path, *argv: str | Path) -> float:
    start = time.perf_counter()
    result = run(copy, *argv)
    seconds = time.perf_counter() - start
    if result.returncode != 0:
        command = " ".join(map(str, argv))
        sys.exit(f"{command} failed:\n{result.stdout[-3000:]}{result.stderr[-3000:]}")
    return seconds


def returns(copy: Path) -> dict[str, list[str]]:
    found = {}
    for path in sorted((copy / "data/runs").rglob("eval.csv")):
        with path.open() as file:
            found[str(path.relative_to(copy))] = [
                row["mean_return"] for row in csv.DictReader(file)
            ]
    return found


def recorded_outputs(copy: Path) -> dict[str, list[str]]:
    """Each stage's output hashes, as ``dvc.lock`` records them."""
    lock = yaml.safe_load((copy / "dvc.lock").read_text())["stages"]
    return {stage: [out["md5"] for out in entry["outs"]] for stage, entry in lock.items()}


def families(tmp: Path, steps: int, jobs: int) -> tuple[float, float]:
    """The families' stages, one at a time against in waves: the two wall times."""
    base = tmp / "families"
    scratch_copy(base, small_params(steps, FAMILIES))
    repro, swept = tmp / "families-repro", tmp / "families-sweep"
    shutil.copytree(base, repro, symlinks=True)
    shutil.copytree(base, swept, symlinks=True)
    sequential = timed(repro, BIN / "dvc", "repro", "task_inputs")
    parallel = timed(swept, BIN / "ede-pipeline", "sweep", "task_inputs", "--jobs", str(jobs))
    made = recorded_outputs(swept)
    if made != recorded_outputs(repro) or len(made) != 4 * len(set(FAMILIES.values())) + 2:
        sys.exit("the sweep's outputs of the families differ from dvc repro's")
    return sequential, parallel


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=3_000, help="environment steps per run")
    parser.add_argument("--jobs", type=int, default=2)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="ede-sweep-bench-") as tmp:
        upstream, waves = families(Path(tmp), args.steps, args.jobs)
        base = Path(tmp) / "base"
        scratch_copy(base, small_params(args.steps))
        timed(base, BIN / "dvc", "repro", "task_inputs")
        repro, swept = Path(tmp) / "repro", Path(tmp) / "sweep"
        shutil.copytree(base, repro, symlinks=True)
        shutil.copytree(base, swept, symlinks=True)
        sequential = timed(repro, BIN / "dvc", "repro", "train")
        parallel = timed(swept, BIN / "ede-pipeline", "sweep", "train", "--jobs", str(args.jobs))
        if returns(repro) != returns(swept) or len(returns(swept)) != 4:
            sys.exit("the sweep's returns differ from dvc repro's")
    print(f"the stages of two families ({', '.join(FAMILIES.values())}), {os.cpu_count()} cores")
    print(f"dvc repro task_inputs        {upstream:7.1f} s   1.00x")
    print(
        f"ede-pipeline sweep --jobs {args.jobs}           {waves:7.1f} s   {upstream / waves:.2f}x"
    )
    print(
        f"4 train runs of {args.steps} steps ({TASK}, td3 and ede-td3, seeds 0 and 1), "
        f"{os.cpu_count()} cores"
    )
    print(f"dvc repro train              {sequential:7.1f} s   1.00x")
    print(
        f"ede-pipeline sweep --jobs {args.jobs}           {parallel:7.1f} s   "
        f"{sequential / parallel:.2f}x"
    )


if __name__ == "__main__":
    main()
