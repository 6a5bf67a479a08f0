"""Every stage checks, before it works, that it can write its outputs, lock, temporaries and
progress file: a place it cannot write is one line naming it, exit 2, and nothing written."""

from __future__ import annotations

import errno
import os
import shutil
from pathlib import Path

import pytest
import yaml
from click.testing import CliRunner

from ede.atomic import unwritable
from tests.support import REPO
from ede_pipeline.cli import main

# /sys takes no new file, even from root (sysfs): a read-only location on every Linux machine.
READ_ONLY = Path("/sys/ede-test-output")


@pytest.fixture(scope="module")
def project(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Tiny params with the point family's rollouts and embedding."""
    root = tmp_path_factory.mktemp("outputs")
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    params["collect"].update(steps=2_000, num_envs=1)
    for section in ("embedding", "decoder"):
        params[section].update(hidden=[16], epochs=1)
    params["runs"].update(tasks={"ede/Point-v0": "point"}, seeds=[0], budgets={"ede/Point-v0": 1000})
    params["report"].update(effect_space_family=None, exploration_family=None)
    (root / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    cwd = os.getcwd()
    os.chdir(root)
    try:
        for command in (["collect", "--family", "point"], ["pretrain", "encoder", "--family", "point"],
                        ["pretrain", "decoder", "--family", "point"]):
            result = CliRunner().invoke(main, command)
            assert result.exit_code == 0, result.output
    finally:
        os.chdir(cwd)
    return root


@pytest.fixture
def workdir(project: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    shutil.copytree(project, tmp_path / "p")
    monkeypatch.chdir(tmp_path / "p")
    (tmp_path / "p" / "afile").write_text("in the way\n")
    return tmp_path / "p"


def listing(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


STAGES = {
    "collect": ["collect", "--family", "point", "--out", "{out}"],
    "encoder": ["pretrain", "encoder", "--family", "point", "--out", "{out}"],
    "decoder": ["pretrain", "decoder", "--family", "point", "--out", "{out}"],
    "train": ["train", "--task", "ede/Point-v0", "--algo", "td3", "--seed", "0", "--out", "{out}"],
    "report": ["report", "--out", "{out}"],
}
PLACES = {
    "a file in the way": ("afile", "afile: a file is in the way; expected a directory there"),
    "a file among its parents": ("afile/out", "afile/out: cannot be created: afile is a file, "
                                 "not a directory"),
    "a read-only location": (str(READ_ONLY / "out"), f"{READ_ONLY / 'out'}: cannot be written: "
                             "/sys does not take new files"),
}


@pytest.mark.parametrize("place", PLACES)
@pytest.mark.parametrize("stage", STAGES)
def test_an_output_that_cannot_be_written_is_refused_before_work(workdir: Path, stage: str,
                                                                 place: str) -> None:
    out, message = PLACES[place]
    before = listing(workdir)
    result = CliRunner().invoke(main, [a.replace("{out}", out) for a in STAGES[stage]])
    assert result.exit_code == 2, result.output
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"Error: {message}"), result.stderr
    assert listing(workdir) == before


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["pretrain", "encoder", "--family", "point", "--out", "e", "--metrics", "afile/m.json"],
         "afile/m.json: cannot be created: afile is a file"),
        (["pretrain", "decoder", "--family", "point", "--out", "d", "--plots", "h.csv/x"],
         "h.csv/x: cannot be created"),
        (["report", "--out", "r", "--curves", "afile"], "afile: a file is in the way"),
        (["report", "--out", "r", "--metrics", str(READ_ONLY / "m.json")], "does not take new files"),
    ],
)
def test_every_output_of_a_stage_is_checked_not_only_its_folder(workdir: Path, args: list[str],
                                                                 message: str) -> None:
    (workdir / "h.csv").write_text("")
    before = listing(workdir)
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 2 and message in result.stderr, result.output
    assert len(result.stderr.splitlines()) == 1
    assert listing(workdir) == before


def test_an_unwritable_progress_file_is_named_by_its_variable(workdir: Path) -> None:
    before = listing(workdir)
    result = CliRunner(env={"EDE_PROGRESS": str(READ_ONLY / "progress.json")}).invoke(
        main, STAGES["collect"][:-2] + ["--out", "store"])
    assert result.exit_code == 2
    assert result.stderr.startswith(f"Error: EDE_PROGRESS={READ_ONLY / 'progress.json'}: cannot be "
                                    "written")
    assert listing(workdir) == before


def test_a_full_location_is_refused(workdir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def full(fd: int) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full)
    before = listing(workdir)
    result = CliRunner().invoke(main, STAGES["train"][:-1] + ["run"])
    assert result.exit_code == 2
    assert "run: cannot be written: . does not take data (No space left on device)" in result.stderr
    assert listing(workdir) == before


def test_several_seeds_are_all_checked_before_any_lock(workdir: Path) -> None:
    (workdir / "runs").mkdir()
    (workdir / "runs" / "seed2").write_text("in the way\n")
    before = listing(workdir)
    result = CliRunner().invoke(main, ["train", "--task", "ede/Point-v0", "--algo", "td3", "--seed",
                                       "0-2", "--out", "runs/seed{seed}"])
    assert result.exit_code == 2 and "runs/seed2: a file is in the way" in result.stderr
    assert listing(workdir) == before  # no lock of seed 0 or 1 left behind


def test_unwritable_says_nothing_where_all_is_well_and_leaves_nothing(tmp_path: Path) -> None:
    assert unwritable(tmp_path / "a" / "b", directory=True) is None
    assert unwritable(tmp_path / "m.json", directory=False) is None
    (tmp_path / "d").mkdir()
    assert unwritable(tmp_path / "d", directory=False) == (
        f"{tmp_path / 'd'}: a directory is in the way; expected a file there, or nothing")
    assert listing(tmp_path) == ["d"]


def test_a_sweeps_log_folder_is_checked_before_anything_runs(tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    shutil.copy(REPO / "params.yaml", tmp_path)
    shutil.copy(REPO / "dvc.yaml", tmp_path)
    (tmp_path / "afile").write_text("")
    monkeypatch.chdir(tmp_path)
    before = listing(tmp_path)
    result = CliRunner().invoke(main, ["sweep", "--logs", "afile/logs"])
    assert result.exit_code == 2
    assert result.stderr == "Error: --logs afile/logs: cannot be created: afile is a file, not a directory\n"
    assert listing(tmp_path) == before
