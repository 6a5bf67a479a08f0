"""The benchmarks that must not rot run here in their smallest form: they run to the end and
print the table they promise."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support import REPO

pytestmark = pytest.mark.slow


def table(benchmark: str, *args: str) -> list[list[str]]:
    """The rows of the table ``benchmarks/BENCHMARK`` prints (one per task's line), run to its
    end."""
    command = [sys.executable, str(REPO / "benchmarks" / benchmark), *args]
    done = subprocess.run(command, capture_output=True, text=True, check=False, timeout=600)
    assert done.returncode == 0, done.stderr
    return [line.split() for line in done.stdout.splitlines() if line.startswith("ede/")]


def test_gpu_throughput_runs_on_cpu_in_its_tiny_form() -> None:
    rows = table(
        "gpu_throughput.py", "--device", "cpu", "--tiny", "--tasks", "ede/ReacherVertical-v0"
    )
    assert [(row[1], row[2]) for row in rows] == [
        ("td3", "1x1"),
        ("td3", "2x2"),
        ("ede-td3", "1x1"),
        ("ede-td3", "2x2"),
    ]
    for row in rows:
        rate, ratio, update_us = float(row[3]), row[4], float(row[5])
        assert rate > 0 and update_us > 0, row
        assert float(ratio) > 0 and (ratio == "1.00" or row[2] != "1x1"), row  # against alone
        assert row[6:] == ["-", "-"], row  # no CUDA graph, no GPU to be busy on CPU


def test_train_throughput_runs_side_by_side_in_its_tiny_form() -> None:
    # The default arm, td3.compile auto, with no compiler to be found: eager, as it says (with one
    # it would compile each arm first, a minute on CI's cold cache).
    command = [sys.executable, str(REPO / "benchmarks/train_throughput.py"), "--tiny"]
    done = subprocess.run(
        command,
        capture_output=True,
        text=True,
        check=False,
        timeout=600,
        env={**os.environ, "CXX": "/nonexistent/c++"},
    )
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert (
        "td3.compile auto (the default) runs as a run of 25,000 updates or more takes it here: "
        "none (a C++ compiler (/nonexistent/c++, or $CXX) not found)"
    ) in lines
    learners = ["stable-baselines3 TD3", "ours TD3", "ours EDE-TD3"]
    # One update of each: FLOPs, time, GFLOP/s, share of the measured peak, and the split.
    peak = float(next(line for line in lines if "peak" in line).split("peak ")[1].split()[0])
    assert peak > 0
    for name in learners:
        row = next(line for line in lines if line.startswith(f"{name} ")).split()[-7:]
        mflop, ms, gflops = (float(x) for x in row[:3])
        assert mflop > 0 and ms > 0 and gflops == pytest.approx(mflop / ms, abs=0.1), row
        assert abs(int(row[3].rstrip("%")) - 100 * gflops / peak) <= 1, row
        products, optimiser, rest = (float(x.rstrip("%")) for x in row[4:])
        assert products > 0 and optimiser > 0 and abs(products + optimiser + rest - 100) <= 2, row
    # Side by side: each arm's ratio to SB3 within its rounds (one round here).
    rows = {
        line.split(",")[0] if line.startswith("ours") else "stable-baselines3 TD3": line.split()
        for line in lines
        if "(" in line and "–" in line and line.startswith(("stable", "ours"))
    }
    assert rows["stable-baselines3 TD3"][-2:] == ["1.00", "(1.00–1.00)"]
    for name in ("ours TD3", "ours EDE-TD3"):
        ratio, spread = float(rows[name][-2]), rows[name][-1]
        assert ratio > 0 and spread == f"({ratio:.2f}–{ratio:.2f})", rows[name]


def test_train_throughputs_compiled_update_runs_the_eager_ones_products(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The one-update table's compiled row (where ``--compile`` compiles here): the same matrix
    products as the eager update, counted from the profiled shapes, and Adam fused into it, so
    not clocked."""
    import importlib.util

    import torch

    spec = importlib.util.spec_from_file_location(
        "train_throughput", REPO / "benchmarks/train_throughput.py"
    )
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, bench)  # its dataclasses look themselves up
    spec.loader.exec_module(bench)
    setting = bench.Setting([16, 16], 8, "cpu", start=100)
    try:
        measured = {}
        for mode in ("none", "default"):
            clocked = bench.ours_update(setting, "ede-td3", mode)
            for _ in range(4):  # compiled: both graphs (with and without the actor's step)
                clocked.update()
            measured[mode] = bench.measure_update(clocked, compiled=mode != "none")
    finally:
        torch._dynamo.reset()
    eager, compiled = measured["none"], measured["default"]
    assert compiled.flops == eager.flops > 0, (compiled, eager)
    assert eager.optimiser is not None and eager.optimiser > 0 and compiled.optimiser is None
    assert 0 < compiled.products < compiled.seconds, compiled


def test_clip_sensitivity_plays_a_published_clip_again(tmp_path: Path) -> None:
    import shutil

    task = "ede/ReacherVertical-v0"
    shutil.copytree(REPO / "docs/results/clips" / task, tmp_path / task)
    rows = table("clip_sensitivity.py", "--runs", str(tmp_path), "--draws", "1")
    assert [row[:2] for row in rows] == [[task, "td3"], [task, "ede-td3"]]
    page = (REPO / "docs/results/reacher-vertical.md").read_text()
    shown = page.split("This episode's return: ")[1]  # "-9.9 (TD3) and -6.0 (EDE-TD3); …"
    printed = [float(shown.split(" (TD3) and ")[0]), float(shown.split(" and ")[1].split(" ")[0])]
    for row, on_page in zip(rows, printed, strict=True):
        assert abs(float(row[2]) - on_page) <= 0.05 + 0.1, (row, on_page)  # the page's rounding
        assert 0 <= float(row[3]) < 0.1, row  # a few ulps move the return less than 0.1
