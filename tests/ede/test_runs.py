"""A run's folder (ede.runs): written, read back, checked against the run it must be; and what
run.json records of the code and the machine (ede.provenance)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
import torch

from ede import provenance
from ede.config import EdeTD3Config, TD3Config
from ede.runs import (
    RunRejected,
    RunSpec,
    identity_difference,
    read_run,
    write_curves,
    write_finished,
)

SPEC = RunSpec("ede/Point-v0", "td3", 3, 2_000, TD3Config(), EdeTD3Config())


def finished(out: Path, spec: RunSpec = SPEC) -> None:
    history = [
        {
            "step": s,
            "episode": s // 100,
            "mean_return": -50.0 + s / 100,
            "std_return": 1.0,
            "wall_seconds": s / 1e3,
        }
        for s in (0, 1_000, 2_000)
    ]
    write_curves(
        out,
        history,
        [{"step": 1_000, "updates": 900, "critic_loss": 0.5, "actor_loss": 2.0, "mean_q": -2.0}],
    )
    write_finished(out, spec, {"final_return": -30.0}, torch.device("cpu"))


def test_a_finished_run_reads_back_as_written(tmp_path: Path) -> None:
    finished(tmp_path)
    run = read_run(tmp_path, SPEC.identity())
    assert run is not None
    assert run.curve.seed == 3
    assert run.curve.steps.tolist() == [0, 1_000, 2_000]
    assert run.curve.returns.tolist() == [-50.0, -40.0, -30.0]
    assert run.diagnostics is not None and run.diagnostics["critic_loss"].tolist() == [0.5]
    assert run.made["seed"] == 3 and run.software == provenance.software_versions()


def test_a_run_without_metrics_is_not_finished(tmp_path: Path) -> None:
    finished(tmp_path)
    (tmp_path / "metrics.json").unlink()
    assert read_run(tmp_path, SPEC.identity()) is None


def test_another_runs_folder_is_rejected_naming_the_first_difference(tmp_path: Path) -> None:
    finished(tmp_path)
    other = RunSpec("ede/Point-v0", "td3", 3, 2_000, TD3Config(tau=0.01), EdeTD3Config())
    with pytest.raises(
        RunRejected,
        match=r"run.json: made with td3.tau = 0.005, but the params "
        r"say 0.01$",
    ):
        read_run(tmp_path, other.identity())
    with pytest.raises(RunRejected, match=r"run.json: seed is 3, expected 4$"):
        read_run(tmp_path, {"seed": 4})


def test_identity_difference_names_one_key_in_words() -> None:
    identity = SPEC.identity()
    assert identity_difference(identity, identity) is None
    assert identity_difference(None, identity) == "its identity is not recorded"
    assert identity_difference(identity, {"algo": "ede-td3"}) == 'algo is "td3", expected "ede-td3"'
    assert (identity_difference(identity, {"embedding": "abc"}) or "").startswith(
        "made with another embedding"
    )
    other = RunSpec("ede/Point-v0", "td3", 3, 2_000, TD3Config(hidden=[64]), EdeTD3Config())
    assert identity_difference(identity, other.identity()) == (
        "made with td3.hidden = [400, 300], but the params say [64]"
    )


def test_run_json_names_the_code_and_the_machine(tmp_path: Path) -> None:
    provenance.code_version.cache_clear()  # read once a process: the checkout's HEAD of now
    finished(tmp_path)
    made = json.loads((tmp_path / "run.json").read_text())
    root = Path(provenance.__file__).resolve().parents[1]
    head = subprocess.run(
        ["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, check=True
    ).stdout.strip()
    assert made["code"]["commit"] == head
    assert isinstance(made["code"]["modified"], bool)
    machine = made["machine"]
    assert machine["cpu"] and set(machine["instruction_sets"]) <= set(provenance.INSTRUCTION_SETS)
    assert machine["torch_cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    assert machine["torch_threads"] == torch.get_num_threads() and machine["gpu"] is None


def test_outside_a_checkout_the_commit_comes_from_the_build(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def no_git(*args: object, **kwargs: object) -> None:
        raise FileNotFoundError("git")

    monkeypatch.setattr(subprocess, "run", no_git)
    monkeypatch.setenv(provenance.COMMIT_ENV, "f" * 40)
    assert provenance.code_version.__wrapped__() == {"commit": "f" * 40, "modified": None}
    monkeypatch.delenv(provenance.COMMIT_ENV)
    assert provenance.code_version.__wrapped__() == {"commit": None, "modified": None}
