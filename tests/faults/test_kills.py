"""SIGKILL at a random point of every stage, then a rerun: the outputs equal an uninterrupted run's.

Each stage runs as a real process writing under a fresh folder and is killed after a random
fraction of its uninterrupted wall time (process start included, so some kills land in imports,
some mid-work, some mid-write); whatever it left, its rerun must end with outputs equal to the
reference (``conftest.py``) and no temporary left behind. A kill that came after the stage
finished is still a valid case: the rerun then replaces complete outputs.
"""

from __future__ import annotations

import json
import random
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from ede.io.rollouts import Rollouts
from tests.faults.conftest import TASK, Workdir, command, stage_args

pytestmark = pytest.mark.slow


def kill_midway(work: Workdir, args: list[str], seconds: float) -> None:
    process = subprocess.Popen(
        command(*args),
        cwd=work.path,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    time.sleep(seconds)
    process.send_signal(signal.SIGKILL)
    process.wait()


def no_temporaries(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if ".tmp-" in p.name or p.name.endswith(".lock")]


def weights(folder: Path) -> bytes:
    return next(folder.glob("*.safetensors")).read_bytes()


def returns(run: Path) -> list[str]:
    return [line.rsplit(",", 1)[0] for line in (run / "eval.csv").read_text().splitlines()]


def same_outputs(name: str, out: Path, ref: Path) -> None:
    """The stage's outputs under ``out`` against the reference's (wall times aside)."""
    if name == "collect":
        a, b = Rollouts.open(out / "rollouts.zarr"), Rollouts.open(ref / "rollouts.zarr")
        assert a.attrs == b.attrs
        for key, value in a.arrays().items():
            np.testing.assert_array_equal(value, b.arrays()[key])
    elif name in ("encoder", "decoder"):
        assert weights(out / name) == weights(ref / "embedding" / name)
        assert json.loads((out / f"{name}.json").read_text()) == json.loads(
            (ref / "embedding" / f"{name}.json").read_text()
        )
    elif name == "train":
        reference = ref / "runs" / TASK / "ede-td3" / "seed0"
        assert returns(out / "run") == returns(reference)  # step, episode, mean and std
        assert (out / "run" / "diagnostics.csv").read_text() == (
            reference / "diagnostics.csv"
        ).read_text()
        assert (out / "run" / "policy" / "policy.safetensors").read_bytes() == (
            reference / "policy" / "policy.safetensors"
        ).read_bytes()
    elif name == "report":
        assert json.loads((out / "report.json").read_text()) == json.loads(
            (ref / "report.json").read_text()
        )
        for curve in (ref / "curves").iterdir():
            assert (out / "curves" / curve.name).read_text() == curve.read_text()
        assert (out / "report" / "index.html").is_file()


@pytest.mark.parametrize("name", ["collect", "encoder", "decoder", "train", "report"])
def test_a_stage_killed_at_a_random_point_reruns_to_the_uninterrupted_outputs(
    workdir: Workdir, tmp_path: Path, fault_seed: int, name: str
) -> None:
    fraction = random.Random(fault_seed).uniform(0.05, 0.95)
    where = f"EDE_FAULT_SEED={fault_seed}: killed after {fraction:.0%} of {name}"
    args = stage_args(name, tmp_path, workdir.ref)
    kill_midway(workdir, args, fraction * workdir.seconds[name])
    rerun = workdir.run(*args)
    assert rerun.returncode == 0, f"{where}: {rerun.stderr}"
    assert "Traceback" not in rerun.stderr, where
    same_outputs(name, tmp_path, workdir.ref)
    assert not no_temporaries(tmp_path), f"{where}: {no_temporaries(tmp_path)}"
