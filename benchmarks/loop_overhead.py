"""The training loop's own cost per member-step — everything but ``env.step`` and the update —
of a group of M members, against an earlier commit measured in the same run.

    python benchmarks/loop_overhead.py [--members 1,16,64] [--steps 2000] [--algos td3,ede-td3]
                                       [--before DIR] [--whole]

A group of M seeds of the paper's networks (400-300, batch 100) trains ``--steps`` steps per
member on ``ede/ReacherVertical-v0`` through ``ede.run.training.train_group``, as the pipeline trains
it: the actor (plus its exploration noise) acts from the first step, the paper's evaluation
(10 episodes every 1,000 steps) included, the CPU and one torch thread. Two things are taken out
of the clock, so that what is left is the loop's own work — acting, decoding, the replay
buffer's writes, the bookkeeping of episodes, evaluation's acting:

* the update: ``Agent.update`` does nothing (an update's cost is ``train_throughput.py``'s);
* the environment: every call of the task's ``step`` is timed and its time subtracted.

``µs`` is then (wall − env.step) / (M × steps), timed from each member's step 100 to its last
(setup, the first and the last evaluation and the outputs outside the clock): per training step
of a member, its share of the evaluations between included; ``env share`` the wall's share in
``env.step``; and ``x before`` the earlier commit's figure over this checkout's. EDE-TD3 acts through an untrained
embedding (k = 4; its weights do not matter for speed).

``--whole`` leaves the update on and prints each group's aggregate steps per second instead: what
a whole run (or group) gains or loses, the loop's cost beside the update's.

``--before DIR``: an earlier commit's checkout, e.g. ``git worktree add /tmp/before HEAD~1``;
its ``ede`` is imported in a child process (``PYTHONPATH=DIR``) with this environment's
packages, and measured by this same script. With the defaults about 4 minutes on one core for
this checkout, and as long again for each commit before a batched loop.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch
from gpu_throughput import embedding  # this folder's: an untrained embedding of a task

from ede.config import Algo

TASK = "ede/ReacherVertical-v0"
WARMUP = 100  # steps per member before the clock starts: first calls, the first evaluation


def measure(algo: Algo, members: int, steps: int, whole: bool = False) -> dict[str, float]:
    """One group's loop cost: µs per member-step, the share of the wall in ``env.step``, and
    the group's aggregate steps per second (with ``whole``, the update on: a whole run's)."""
    from ede.config import EdeTD3Config, TD3Config
    from ede.method.agent import Agent
    from ede.run.spec import RunSpec
    from ede.run.training import train_group
    from ede.tasks import make

    env_class = type(make(TASK).unwrapped)
    step, spent = env_class.step, [0.0]

    def timed(self: Any, action: np.ndarray) -> Any:
        started = time.perf_counter()
        result = step(self, action)
        spent[0] += time.perf_counter() - started
        return result

    config = TD3Config(
        start_steps=0, eval_every=1_000, eval_episodes=10, checkpoint_every=10**9, buffer_size=steps
    )
    specs = [RunSpec(TASK, algo, seed, steps, config, EdeTD3Config()) for seed in range(members)]
    update, marks, done = Agent.update, {}, [0]
    first, last = members * WARMUP, members * steps

    def progress(count: int) -> None:  # the clock: from the warm-up's end to the last step's
        done[0] += count
        if done[0] in (first, last):
            marks[done[0]] = (time.perf_counter(), spent[0])

    setattr(env_class, "step", timed)  # noqa: B010 (a method replaced for the measurement)
    if not whole:
        setattr(Agent, "update", lambda self, buffer, due=None: None)  # noqa: B010
    try:
        with tempfile.TemporaryDirectory() as tmp:
            outs = [Path(tmp) / f"seed{spec.seed}" for spec in specs]
            code = embedding(TASK, torch.device("cpu")) if algo == "ede-td3" else None
            train_group(specs, outs, code, progress=progress)
    finally:
        setattr(env_class, "step", step)  # noqa: B010
        setattr(Agent, "update", update)  # noqa: B010
    wall, env = (marks[last][j] - marks[first][j] for j in (0, 1))
    rate = (last - first) / wall
    return {"us": 1e6 * (wall - env) / (last - first), "env_share": env / wall, "rate": rate}


def child(before: Path, algo: str, members: int, steps: int, whole: bool) -> dict[str, float]:
    """:func:`measure` with the ``ede`` of the checkout at ``before``."""
    environment = {**os.environ, "PYTHONPATH": str(before)}
    command = [sys.executable, __file__, "--measure", algo, str(members), str(steps)]
    command += ["--whole"] if whole else []
    output = subprocess.run(command, env=environment, check=True, capture_output=True, text=True)
    return json.loads(output.stdout.splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--members", default="1,16,64")
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--algos", default="td3,ede-td3")
    parser.add_argument("--before", type=Path)
    parser.add_argument("--whole", action="store_true", help="the update on: whole runs' rates")
    parser.add_argument("--measure", nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.measure:  # a child: one measurement, as JSON
        algo, members, steps = args.measure
        print(json.dumps(measure(cast(Algo, algo), int(members), int(steps), args.whole)))
        return
    import ede

    print(f"this checkout: {Path(ede.__file__).parent.parent}; before: {args.before or '-'}")
    figure, unit = ("rate", "steps/s") if args.whole else ("us", "µs")
    print(f"{'algo':8} {'M':>4} {unit:>8} {'env share':>10} {'before':>10} {'x before':>9}")
    for algo in args.algos.split(","):
        for members in (int(m) for m in args.members.split(",")):
            now = measure(cast(Algo, algo), members, args.steps, args.whole)
            then = (
                child(args.before, algo, members, args.steps, args.whole) if args.before else None
            )
            line = f"{algo:8} {members:>4} {now[figure]:>8.1f} {now['env_share']:>10.0%}"
            if then:  # x before: how many times faster than before
                ratio = now["rate"] / then["rate"] if args.whole else then["us"] / now["us"]
                line += f" {then[figure]:>10.1f} {ratio:>9.2f}"
            print(line, flush=True)


if __name__ == "__main__":
    main()
