"""A sweep killed at a random point (the whole process group: the sweep and its runs, as when a
node is lost), then run again: ``dvc.lock`` and the runs' returns equal those of ``dvc repro``."""

from __future__ import annotations

import os
import random
import shutil
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest

from tests.support import BIN, dvc, ok, tool_env, train_record

pytestmark = pytest.mark.slow


def test_a_killed_sweep_resumes_to_what_dvc_repro_records(
    reacher_upstream: Path,
    reacher_reference: tuple[dict[str, Any], float],
    tmp_path: Path,
    fault_seed: int,
) -> None:
    reference, seconds = reacher_reference
    copy = tmp_path / "swept"
    shutil.copytree(reacher_upstream, copy, symlinks=True)
    fraction = random.Random(fault_seed).uniform(0.2, 0.9)
    where = f"EDE_FAULT_SEED={fault_seed}: killed after {fraction:.0%} of the sweep"
    sweep = [str(BIN / "ede-pipeline"), "sweep", "train", "--jobs", "2"]
    process = subprocess.Popen(
        sweep,
        cwd=copy,
        env=tool_env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    time.sleep(fraction * seconds)
    os.killpg(process.pid, signal.SIGKILL)
    process.wait()

    again = subprocess.run(
        sweep, cwd=copy, env=tool_env(), capture_output=True, text=True, timeout=600
    )
    assert again.returncode == 0, f"{where}: {again.stdout[-2000:]}{again.stderr[-2000:]}"
    assert train_record(copy) == reference, where
    assert "up to date" in ok(dvc(copy, "status", "train")), where
