"""``benchmarks/results.py``: docs/results.md's tables and figures, redrawn from per-run files."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from tests.support import REPO

SCRIPT = REPO / "benchmarks" / "results.py"
TASK = "ede/ReacherTurn-v0"
BUDGET = 20_000


def write_run(runs: Path, algo: str, seed: int, returns: np.ndarray, budget: int = BUDGET,
              task: str = TASK) -> None:
    folder = runs / task.split("/")[-1] / algo / f"seed{seed}"
    folder.mkdir(parents=True)
    steps = np.linspace(0, budget, len(returns))
    rows = [f"{int(s)},{i},{r},1.0,{i}" for i, (s, r) in enumerate(zip(steps, returns))]
    (folder / "eval.csv").write_text("step,episode,mean_return,std_return,wall_seconds\n"
                                     + "\n".join(rows) + "\n")
    made = {"task": task, "algo": algo, "seed": seed, "budget": budget}
    (folder / "run.json").write_text(json.dumps(made))
    (folder / "metrics.json").write_text(json.dumps({"final_return": float(returns[-1])}))


def results(runs: Path, figures: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), "--runs", str(runs), "--figures",
                           str(figures)], capture_output=True, text=True, cwd=REPO)


def test_tables_name_disjoint_bins_and_diverged_seeds(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    x = np.linspace(0, 1, 41)
    for seed in range(4):
        noise = np.random.default_rng(seed).normal(0, 5, (2, len(x)))
        write_run(runs, "ede-td3", seed, -200 + 150 * x + noise[0])  # learns steadily
        td3 = np.where(x < 0.5, -200 + 100 * x, -150 - 100 * (x - 0.5))  # falls after half
        write_run(runs, "td3", seed, td3 + noise[1])
    (runs / "ReacherTurn-v0" / "source.json").write_text(json.dumps({"commit": "0123456789ab"}))
    for algo in ("td3", "ede-td3"):  # a task still running: one seed of each so far
        write_run(runs, algo, 0, np.linspace(-200, -100, 41), task="ede/ReacherPush-v0")
    (runs / "ReacherPush-v0" / "source.json").write_text(json.dumps({"commit": "0123456789ab"}))

    done = results(runs, tmp_path / "figures")
    assert done.returncode == 0, done.stderr
    out = done.stdout
    assert "2.0% of the paper's 1,000,000; commit 0123456" in out
    assert "| EDE-TD3 | 0–3 |" in out and "| TD3 | 0–3 |" in out
    # The same start, then EDE-TD3 ahead by up to 125 with noise of 5: apart at the end only.
    above = out.split("EDE-TD3 above TD3 at ")[1].split("; below at ")
    assert above[0].endswith("–20K") and not above[0].startswith("1K")
    assert above[1].startswith("none.")
    assert out.count("| **yes** |") == 4  # every TD3 seed fell by more than half its gain
    turn = out.split("### ede/ReacherPush-v0")[0]
    assert "| EDE-TD3 | 0 | " in turn and turn.count("| no |") == 4
    assert (tmp_path / "figures" / "reacher.png").stat().st_size > 10_000
    # Across tasks (ReacherTurn's; ReacherPush waits for its seeds): every EDE-TD3 seed ends
    # above every TD3 seed, so P is 1 at both ends.
    across = out.split("### Across tasks: the reacher family")[1]
    assert "1 task (ede/ReacherTurn-v0); per task 4 of EDE-TD3 and 4 of TD3" in across
    assert "Not yet in these aggregates, with fewer runs of an algorithm than the others: " \
        "ede/ReacherPush-v0 (1 of 4)." in across
    final = across.split("| final return | ")[1].split(" |")
    assert final[0] == "1 [1, 1]" and float(final[1].split()[0]) > float(final[2].split()[0])
    assert (tmp_path / "figures" / "performance-profile.png").stat().st_size > 10_000


def test_runs_of_different_budgets_are_refused_by_name(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    write_run(runs, "td3", 0, np.zeros(21))
    write_run(runs, "td3", 1, np.zeros(21), budget=2 * BUDGET)
    done = results(runs, tmp_path / "figures")
    assert done.returncode == 1 and "runs of different budgets [20000, 40000]" in done.stderr
    assert "Traceback" not in done.stderr and not (tmp_path / "figures").exists()


def test_the_committed_runs_redraw(tmp_path: Path) -> None:
    done = results(REPO / "docs" / "results" / "runs", tmp_path)
    assert done.returncode == 0, done.stderr
    committed = {p.parent.parent.name for p in (REPO / "docs/results/runs").glob("*/*/seed*")}
    for task in committed:
        assert f"### ede/{task}\n" in done.stdout
