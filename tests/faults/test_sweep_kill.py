"""A sweep killed at a random point (the whole process group: the sweep and its runs, as when a
node is lost), then run again: ``dvc.lock`` and the runs' returns equal those of ``dvc repro``."""

from __future__ import annotations

import os
import random
import shutil
import signal
import subprocess
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.support import BIN, dvc, scratch_copy, tool_env

pytestmark = pytest.mark.slow

TASK = "ede/ReacherVertical-v0"
TIMED = {"metrics.json", "eval.csv"}  # a run's files that hold wall times


def two_runs(tiny_pipeline: Callable[[dict[str, Any]], None]) -> Callable[[dict[str, Any]], None]:
    """One reacher task, both algorithms, one seed, long enough to be killed mid-run."""

    def edit(params: dict[str, Any]) -> None:
        tiny_pipeline(params)
        params["td3"]["checkpoint_every"] = 200
        params["runs"]["tasks"] = {TASK: "reacher"}
        params["runs"]["budgets"] = {task: 1_000 for task in params["runs"]["budgets"]}

    return edit


def ok(result: subprocess.CompletedProcess[str]) -> str:
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    return result.stdout + result.stderr


def record(copy: Path) -> dict[str, Any]:
    """Each train stage's dvc.lock entry (the timed files' hashes set aside) and returns."""
    lock = yaml.safe_load((copy / "dvc.lock").read_text())["stages"]
    entries = {name: entry for name, entry in lock.items() if name.startswith("train@")}
    returns = {}
    for name, entry in entries.items():
        for out in entry["outs"]:
            if Path(out["path"]).name in TIMED:
                out.pop("md5"), out.pop("size")
            if Path(out["path"]).name == "eval.csv":
                lines = (copy / out["path"]).read_text().splitlines()
                returns[name] = [line.rsplit(",", 1)[0] for line in lines]
    return {"lock": entries, "returns": returns}


@pytest.fixture(scope="module")
def upstream(tmp_path_factory: pytest.TempPathFactory,
             tiny_pipeline: Callable[[dict[str, Any]], None]) -> Path:
    copy = scratch_copy(tmp_path_factory.mktemp("sweep-kill") / "upstream",
                        two_runs(tiny_pipeline))
    ok(dvc(copy, "repro", "task_inputs"))
    return copy


def test_a_killed_sweep_resumes_to_what_dvc_repro_records(
    upstream: Path, tmp_path: Path, fault_seed: int
) -> None:
    reference = tmp_path / "reference"
    shutil.copytree(upstream, reference, symlinks=True)
    start = time.perf_counter()
    ok(dvc(reference, "repro", "train"))
    seconds = time.perf_counter() - start

    copy = tmp_path / "swept"
    shutil.copytree(upstream, copy, symlinks=True)
    fraction = random.Random(fault_seed).uniform(0.2, 0.9)
    where = f"EDE_FAULT_SEED={fault_seed}: killed after {fraction:.0%} of the sweep"
    sweep = [str(BIN / "ede-pipeline"), "sweep", "train", "--jobs", "2"]
    process = subprocess.Popen(sweep, cwd=copy, env=tool_env(), stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL, start_new_session=True)
    time.sleep(fraction * seconds)
    os.killpg(process.pid, signal.SIGKILL)
    process.wait()

    again = subprocess.run(sweep, cwd=copy, env=tool_env(), capture_output=True, text=True,
                           timeout=600)
    assert again.returncode == 0, f"{where}: {again.stdout[-2000:]}{again.stderr[-2000:]}"
    assert record(copy) == record(reference), where
    assert "up to date" in ok(dvc(copy, "status", "train")), where
