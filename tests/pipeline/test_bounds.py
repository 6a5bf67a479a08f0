"""Inputs that scale a command's work are bounded before any work: one line naming the option or
key, the value and the limit, exit code 2, in seconds. (``render --episodes``:
tests/pipeline/test_render.py; a group's memory: tests/pipeline/test_train.py.)"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import pytest
from click.testing import CliRunner

from ede_pipeline.cli import main
from ede_pipeline.results.command import MAX_BINS


def test_results_bins_beyond_a_runs_evaluations_are_refused(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    start = time.perf_counter()
    done = CliRunner().invoke(main, ["results", "--bins", "1000000000"])
    assert time.perf_counter() - start < 30
    assert done.exit_code == 2, done.output
    assert f"'--bins': 1000000000 is not in the range 1<=x<={MAX_BINS}" in done.output
    assert list(tmp_path.iterdir()) == []


def test_bootstrap_resamples_beyond_the_bound_are_refused_by_validate(
    write_params: Callable[..., Path],
) -> None:
    path = write_params(lambda params: params["report"].update(bootstrap_samples=10**9))
    start = time.perf_counter()
    done = CliRunner().invoke(main, ["validate", "--params", str(path)])
    assert time.perf_counter() - start < 30
    assert done.exit_code == 2, done.output
    assert done.output == (
        f"Error: {path}: report.bootstrap_samples: got 1000000000; expected less than or "
        "equal to 100000\n"
    )


@pytest.mark.parametrize("samples", [1, 100_000])
def test_bootstrap_resamples_within_the_bound_validate(
    write_params: Callable[..., Path], samples: int
) -> None:
    path = write_params(lambda params: params["report"].update(bootstrap_samples=samples))
    assert CliRunner().invoke(main, ["validate", "--params", str(path)]).exit_code == 0


def test_more_collected_steps_than_memory_holds_are_refused_before_any_work(
    write_params: Callable[..., Path], tmp_path: Path, monkeypatch
) -> None:
    path = write_params(lambda params: params["collect"].update(steps=10**11))
    monkeypatch.chdir(tmp_path)
    start = time.perf_counter()
    done = CliRunner().invoke(
        main, ["collect", "--family", "point", "--params", str(path), "--out", "r.zarr"]
    )
    assert time.perf_counter() - start < 30
    assert done.exit_code == 2, done.output
    assert done.output.count("\n") == 1, done.output
    assert done.output.startswith(
        "Error: collect.steps: 100,000,000,000 steps of ede/Point-v0 need about "
    )
    assert "of memory (collected whole, " in done.output and " available; at most " in done.output
    assert [p.name for p in tmp_path.iterdir()] == [path.name]
