"""The benchmarks that must not rot run here in their smallest form: they run to the end and
print the table they promise."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.support import REPO

pytestmark = pytest.mark.slow


def test_gpu_throughput_runs_on_cpu_in_its_tiny_form() -> None:
    command = [
        sys.executable,
        str(REPO / "benchmarks/gpu_throughput.py"),
        *("--device", "cpu", "--tiny", "--tasks", "ede/ReacherVertical-v0"),
    ]
    done = subprocess.run(command, capture_output=True, text=True, check=False, timeout=600)
    assert done.returncode == 0, done.stderr
    rows = [line.split() for line in done.stdout.splitlines() if line.startswith("ede/")]
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
