"""Sweep wall time: four short train runs through ``dvc repro`` against ``ede-pipeline sweep --jobs 2``.

    python benchmarks/sweep.py [--steps 3000] [--jobs 2]

Two scratch copies of this repo (its files in a fresh git repository under a temporary folder,
made by ``tests.support.scratch_copy`` as the tests make theirs) with small params: one
reacher task, TD3 and EDE-TD3, two seeds — four runs of ``--steps`` environment steps each. The
embedding (collect, pretrain) is made once, untimed, and copied to both. Then, timed: ``dvc
repro train`` in one copy (one run at a time) and ``ede-pipeline sweep train --jobs
N`` in the other. Both include their own start-up and DVC's hashing and caching. Prints both wall
times and the ratio; goal: >= 1.8x with 2 jobs on 2 cores. Also checks that the two copies agree on
every run's returns.
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

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the checkout: its tests' support
from tests.support import BIN, run, scratch_copy

TASK = "ede/ReacherVertical-v0"


def small_params(steps: int) -> Callable[[dict[str, Any]], None]:
    """An edit of params.yaml: one reacher task, two seeds, runs of ``steps`` steps, small nets."""

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
            tasks={TASK: "reacher"},
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=3_000, help="environment steps per run")
    parser.add_argument("--jobs", type=int, default=2)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="ede-sweep-bench-") as tmp:
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
