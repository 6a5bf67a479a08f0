"""The fault-injection suite's shared state: one working directory of tiny params, each stage's
uninterrupted outputs in it (the reference every faulted run must end equal to), and the timing
that places the kills."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

from tests.support import REPO

TASK = "ede/Point-v0"
BUDGET = 1_200


def tiny(params: dict) -> None:
    """The point family alone, at a size every stage finishes in seconds."""
    params["families"] = {"point": params["families"]["point"]}
    params["collect"].update(steps=4_000, num_envs=1)
    for section in ("embedding", "decoder"):
        params[section].update(hidden=[64, 64], epochs=6, lr=1e-3)
    params["td3"].update(
        hidden=[64, 64],
        batch_size=64,
        start_steps=0,
        eval_every=500,
        eval_episodes=3,
        checkpoint_every=400,
    )
    params["runs"].update(
        tasks={TASK: "point"}, algos=["td3", "ede-td3"], seeds=[0], budgets={TASK: BUDGET}
    )
    params["report"].update(
        bootstrap_samples=100, effect_space_family="point", exploration_family=None
    )


def stage_args(name: str, out: Path, ref: Path) -> list[str]:
    """The ``ede-pipeline`` arguments of a stage writing under ``out``, reading ``ref``'s inputs."""
    embedding = ref / "embedding"
    return {
        "collect": ["collect", "--family", "point", "--out", str(out / "rollouts.zarr")],
        "encoder": [
            "pretrain",
            "encoder",
            "--family",
            "point",
            "--rollouts",
            str(ref / "rollouts.zarr"),
            "--out",
            str(out / "encoder"),
            "--metrics",
            str(out / "encoder.json"),
            "--plots",
            str(out / "encoder.csv"),
        ],
        "decoder": [
            "pretrain",
            "decoder",
            "--family",
            "point",
            "--rollouts",
            str(ref / "rollouts.zarr"),
            "--encoder",
            str(embedding / "encoder"),
            "--out",
            str(out / "decoder"),
            "--metrics",
            str(out / "decoder.json"),
            "--plots",
            str(out / "decoder.csv"),
        ],
        "train": [
            "train",
            "--task",
            TASK,
            "--algo",
            "ede-td3",
            "--seed",
            "0",
            "--out",
            str(out / "run"),
            "--encoder",
            str(embedding / "encoder"),
            "--decoder",
            str(embedding / "decoder"),
        ],
        "report": [
            "report",
            "--runs",
            str(ref / "runs"),
            "--embedding",
            f"point={embedding}",
            "--rollouts",
            f"point={ref / 'rollouts.zarr'}",
            "--out",
            str(out / "report"),
            "--metrics",
            str(out / "report.json"),
            "--curves",
            str(out / "curves"),
        ],
    }[name]


def command(*args: str) -> list[str]:
    return [sys.executable, "-m", "ede_pipeline", *args]


@dataclass
class Workdir:
    """The directory the stages run in (its ``params.yaml``), and the reference outputs."""

    path: Path
    ref: Path
    seconds: dict[str, float]  # each stage's uninterrupted wall time, process start included

    def run(self, *args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            command(*args), cwd=self.path, capture_output=True, text=True, timeout=600
        )


def build_workdir(path: Path) -> None:
    """Tiny params in ``path`` and each stage's uninterrupted outputs under ``path / "ref"``; each
    stage's wall time in ``seconds.json``."""
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    tiny(params)
    (path / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    ref = path / "ref"
    work = Workdir(path, ref, {})
    embedding = ref / "embedding"
    for name, out in [("collect", ref), ("encoder", embedding), ("decoder", embedding)]:
        start = time.perf_counter()
        result = work.run(*stage_args(name, out, ref))
        assert result.returncode == 0, result.stderr
        work.seconds[name] = time.perf_counter() - start
    for algo in ("td3", "ede-td3"):
        start = time.perf_counter()
        run_dir = ref / "runs" / TASK / algo / "seed0"
        args = stage_args("train", ref, ref)
        args[args.index("--algo") + 1], args[args.index("--out") + 1] = algo, str(run_dir)
        result = work.run(*args)
        assert result.returncode == 0, result.stderr
        work.seconds["train"] = time.perf_counter() - start
    start = time.perf_counter()
    result = work.run(*stage_args("report", ref, ref))
    assert result.returncode == 0, result.stderr
    work.seconds["report"] = time.perf_counter() - start
    (path / "seconds.json").write_text(json.dumps(work.seconds))


@pytest.fixture(scope="session")
def workdir(built_once: Callable[[str, Callable[[Path], None]], Path]) -> Workdir:
    """The workdir, built once for the session whatever the workers; its tests only read it."""
    path = built_once("faults", build_workdir)
    return Workdir(path, path / "ref", json.loads((path / "seconds.json").read_text()))


@pytest.fixture
def fault_seed() -> int:
    """A fresh seed for the random kill points, shown in every failure to replay it
    (``EDE_FAULT_SEED=<n> pytest tests/faults``)."""
    return int(os.environ.get("EDE_FAULT_SEED", int.from_bytes(os.urandom(4), "little")))
