"""Damaged and foreign checkpoints, a full disk, two writers of one output: each ends in one clear
line or a correct recovery."""

from __future__ import annotations

import errno
import json
import shutil
import subprocess
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from ede.io.atomic import MARK, write_atomically
from ede.io.locks import lock_path
from ede_pipeline.cli import main
from tests.faults.conftest import TASK, Workdir, command

pytestmark = pytest.mark.slow


def train_args(out: Path, algo: str = "td3", seed: int = 0, *extra: str) -> list[str]:
    return [
        "train",
        "--task",
        TASK,
        "--algo",
        algo,
        "--seed",
        str(seed),
        "--out",
        str(out),
        "--encoder",
        "ref/embedding/encoder",
        "--decoder",
        "ref/embedding/decoder",
        *extra,
    ]


def returns(run: Path) -> list[str]:
    return [line.rsplit(",", 1)[0] for line in (run / "eval.csv").read_text().splitlines()]


@pytest.fixture(scope="module")
def good_checkpoint(workdir: Workdir, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A complete checkpoint of TD3 seed 0 (the last one, before the end of the budget)."""
    out = tmp_path_factory.mktemp("kept") / "run"
    result = workdir.run(*train_args(out, "td3", 0, "--keep-checkpoint"))
    assert result.returncode == 0, result.stderr
    return out / "checkpoint"


def truncate(checkpoint: Path) -> None:
    state = checkpoint / "state.safetensors"
    state.write_bytes(state.read_bytes()[: state.stat().st_size // 2])


def garble(checkpoint: Path) -> None:
    (checkpoint / "state.json").write_text('{"step": ')


def unsigned(checkpoint: Path) -> None:
    (checkpoint / "checksums.json").unlink()


DAMAGE = {
    "truncated": (truncate, "state.safetensors does not match its checksum"),
    "garbled": (garble, "state.json does not match its checksum"),
    "unsigned": (unsigned, "checksums.json is missing"),
}


def run_with(checkpoint: Path, out: Path) -> None:
    """A run folder ``out`` holding a copy of ``checkpoint``, as its run left it (with the mark
    that says a run wrote the folder)."""
    shutil.copytree(checkpoint, out / "checkpoint")
    shutil.copy(checkpoint.parent / MARK, out / MARK)


def damaged_run(good: Path, tmp_path: Path, damage: str) -> Path:
    out = tmp_path / "run"
    run_with(good, out)
    DAMAGE[damage][0](out / "checkpoint")
    return out


@pytest.mark.parametrize("damage", sorted(DAMAGE))
def test_a_damaged_checkpoint_is_moved_aside_and_the_run_starts_over(
    workdir: Workdir, good_checkpoint: Path, tmp_path: Path, damage: str
) -> None:
    out = damaged_run(good_checkpoint, tmp_path, damage)
    result = workdir.run(*train_args(out))
    assert result.returncode == 0, result.stderr
    notice = [line for line in result.stderr.splitlines() if "moved aside" in line]
    assert len(notice) == 1 and DAMAGE[damage][1] in notice[0], result.stderr
    assert "Traceback" not in result.stderr
    assert len(list(out.glob("checkpoint.bad-*"))) == 1
    assert json.loads((out / "metrics.json").read_text())["resumed_from_step"] is None
    assert returns(out) == returns(workdir.ref / "runs" / TASK / "td3" / "seed0")


@pytest.mark.parametrize("damage", sorted(DAMAGE))
def test_with_refuse_a_damaged_checkpoint_is_one_line_exit_2_and_left_alone(
    workdir: Workdir, good_checkpoint: Path, tmp_path: Path, damage: str
) -> None:
    out = damaged_run(good_checkpoint, tmp_path, damage)
    before = {p.name: p.read_bytes() for p in (out / "checkpoint").iterdir()}
    result = workdir.run(*train_args(out, "td3", 0, "--bad-checkpoint", "refuse"))
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and DAMAGE[damage][1] in lines[0] and "refuse" in lines[0], lines
    assert {p.name: p.read_bytes() for p in (out / "checkpoint").iterdir()} == before
    assert sorted(p.name for p in out.iterdir()) == [MARK, "checkpoint"]


def test_another_seeds_checkpoint_is_named_moved_aside_and_not_resumed(
    workdir: Workdir, good_checkpoint: Path, tmp_path: Path
) -> None:
    out = tmp_path / "run"
    run_with(good_checkpoint, out)
    result = workdir.run(*train_args(out, "td3", 1))
    assert result.returncode == 0, result.stderr
    assert "another run's: seed is 0, expected 1; moved aside to checkpoint.bad-" in result.stderr
    assert json.loads((out / "metrics.json").read_text())["resumed_from_step"] is None
    assert json.loads((out / "run.json").read_text())["seed"] == 1


def test_a_full_disk_keeps_the_previous_checkpoint_and_the_rerun_resumes_from_it(
    workdir: Workdir, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import ede.run.checkpoint

    real, calls = ede.run.checkpoint.save_tensors, []

    def fills_up(tensors, path, *args, **kwargs):
        calls.append(path)
        if len(calls) == 1:
            return real(tensors, path, *args, **kwargs)
        Path(path).write_bytes(b"\0" * 64)  # a partial write, then the disk is full
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.chdir(workdir.path)
    monkeypatch.setattr(ede.run.checkpoint, "save_tensors", fills_up)
    out = tmp_path / "run"
    result = CliRunner().invoke(main, train_args(out))
    assert result.exit_code == 1, result.output
    assert [line for line in result.stderr.splitlines() if "Error" in line] == [
        f"Error: {out / 'checkpoint'}: not written (No space left on device); "
        "the previous checkpoint is kept"
    ]
    state = json.loads((out / "checkpoint" / "state.json").read_text())
    assert state["step"] == 400 and not list(out.glob("checkpoint.tmp-*"))
    monkeypatch.undo()

    rerun = workdir.run(*train_args(out))
    assert rerun.returncode == 0, rerun.stderr
    assert json.loads((out / "metrics.json").read_text())["resumed_from_step"] == 400
    assert returns(out) == returns(workdir.ref / "runs" / TASK / "td3" / "seed0")


def test_a_second_writer_of_a_run_is_refused_with_the_holders_pid(
    workdir: Workdir, tmp_path: Path
) -> None:
    out = tmp_path / "run"
    first = subprocess.Popen(
        command(*train_args(out, "ede-td3")),
        cwd=workdir.path,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    lock = lock_path(out)
    while not (lock.exists() and lock.read_text().strip()) and first.poll() is None:
        time.sleep(0.05)
    second = workdir.run(*train_args(out, "ede-td3"))
    assert second.returncode == 2, second.stderr
    lines = second.stderr.strip().splitlines()
    assert len(lines) == 1 and f"being written by process {first.pid}" in lines[0], lines
    assert first.wait(timeout=600) == 0, first.stderr.read() if first.stderr else ""
    assert returns(out) == returns(workdir.ref / "runs" / TASK / "ede-td3" / "seed0")
    assert not lock.exists()


def test_a_writer_removes_only_temporaries_whose_writer_is_dead(tmp_path: Path) -> None:
    live = subprocess.Popen(["sleep", "60"])
    dead = subprocess.Popen(["true"])
    dead.wait()
    try:
        target = tmp_path / "out"
        for pid in (live.pid, dead.pid):
            (tmp_path / f"out.tmp-{pid}").mkdir()
        write_atomically(target, lambda tmp: (tmp / "file").write_text("whole"), "test output")
        assert (target / "file").read_text() == "whole"
        assert (tmp_path / f"out.tmp-{live.pid}").exists()
        assert not (tmp_path / f"out.tmp-{dead.pid}").exists()
    finally:
        live.kill()
        live.wait()
