"""The ``ede-pipeline`` commands that every stage shares: validate and envs."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

import ede_envs
from ede_pipeline.cli import main
from tests.support import REPO


def test_validate_accepts_the_committed_params() -> None:
    result = CliRunner().invoke(main, ["validate", "--params", str(REPO / "params.yaml")])
    assert result.exit_code == 0, result.output
    assert "80 runs" in result.output  # 5 tasks x 2 algorithms x 8 seeds


def test_validate_refuses_a_bad_file_with_one_line_per_problem_and_exit_2(write_params) -> None:
    def bad(p: dict) -> None:
        p["embedding"]["k"] = 0
        p["collect"]["stepz"] = 10

    path = write_params(bad)
    result = CliRunner().invoke(main, ["validate", "--params", str(path)])
    assert result.exit_code == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 2, lines
    assert any("embedding.k: got 0" in line for line in lines)
    assert any("collect.stepz: unknown key" in line for line in lines)
    assert "Traceback" not in result.output and result.stdout == ""


def test_validate_names_a_missing_file(tmp_path) -> None:
    result = CliRunner().invoke(main, ["validate", "--params", str(tmp_path / "nope.yaml")])
    assert result.exit_code == 2
    assert "nope.yaml: no such file" in result.stderr


def test_envs_lists_every_task_with_its_family_and_shapes() -> None:
    result = CliRunner().invoke(main, ["envs"])
    assert result.exit_code == 0, result.output
    lines = result.output.strip().splitlines()
    assert lines[0].split()[:3] == ["task", "family", "role"]
    rows = {line.split()[0]: line.split() for line in lines[1:]}
    assert set(rows) == set(ede_envs.TASKS)
    assert rows["ede/Pusher-v0"][1:3] == ["sevendof", "source"]
    assert rows["ede/Pusher-v0"][3] == "(23,)" and rows["ede/Pusher-v0"][4] == "Box[-2,2]^7"
    assert rows["ede/Striker-v0"][4] == rows["ede/Pusher-v0"][4]
    assert rows["ede/ReacherTurn-v0"][4] == "Box[-1,1]^2"
    assert all(row[-1] == "100" for row in rows.values())


def bad_experiment(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, text: str):
    """``experiment run bad`` in a folder holding the committed params (committed there: an
    experiment applies its file to the commit's) and ``experiments/bad.yaml`` with ``text``:
    refused before anything is made."""
    (tmp_path / "experiments").mkdir()
    (tmp_path / "experiments" / "bad.yaml").write_text(text)
    (tmp_path / "params.yaml").write_bytes((REPO / "params.yaml").read_bytes())
    for git in (["init", "-q"], ["add", "params.yaml"], ["commit", "-qm", "params"]):
        subprocess.run(["git", "-c", "user.email=t@example.org", "-c", "user.name=t", *git],
                       cwd=tmp_path, check=True)  # fmt: skip
    (tmp_path / "dvc.yaml").write_text("stages: {}\n")
    (tmp_path / ".dvc").mkdir()
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(main, ["experiment", "run", "bad"])
    assert sorted(p.name for p in (tmp_path / ".dvc").iterdir()) == []  # nothing made
    return result


@pytest.mark.parametrize(
    ("text", "line"),
    [
        ("td3:\n  lr: 0.001\n  lr: 5.0\n", "line 3: key 'lr' given twice, on lines 2 and 3"),
        ("td3:\n  noise_clip: .inf\n", "td3.noise_clip"),
        ("- td3\n", "a list, not a mapping; expected sections of the params"),
    ],
)
def test_an_experiment_file_that_means_two_things_is_refused(
    tmp_path, monkeypatch, text, line
) -> None:
    result = bad_experiment(tmp_path, monkeypatch, text)
    assert result.exit_code == 2 and line in result.stderr and result.stdout == ""
    assert len(result.stderr.strip().splitlines()) == 1


def test_make_quick_runs_the_quick_experiment_as_every_experiment_runs() -> None:
    """`make quick` is `experiment run quick` (tested end to end in test_experiment_run.py)."""
    shown = subprocess.run(
        ["make", "-n", "quick", "STAMP=/dev/null"], cwd=REPO, capture_output=True, text=True
    )
    assert shown.returncode == 0, shown.stderr
    assert "ede-pipeline experiment run quick --update-code" in shown.stdout
    assert (REPO / "experiments" / "quick.yaml").is_file()


def pipeline(*args: str, **env: str) -> subprocess.CompletedProcess:
    """``python -m ede_pipeline`` in a fresh process: MuJoCo reads MUJOCO_GL when first imported."""
    return subprocess.run(
        [sys.executable, "-m", "ede_pipeline", *args],
        capture_output=True,
        text=True,
        env={**os.environ, **env},
        cwd=REPO,
        timeout=600,
    )


def test_an_invalid_mujoco_gl_is_one_line_naming_what_works_here() -> None:
    result = pipeline("validate", MUJOCO_GL="foo")
    assert result.returncode == 2 and result.stdout == ""
    assert result.stderr.startswith(
        "Error: MUJOCO_GL=foo: MuJoCo cannot start with it (invalid "
        "value for environment variable MUJOCO_GL: foo); this machine "
        "supports "
    ), result.stderr
    assert result.stderr.endswith(
        ", disable, or leave it unset (render, report and results then take egl; no other "
        "command renders)\n"
    )
    assert len(result.stderr.splitlines()) == 1


def test_no_stage_needs_rendering() -> None:
    result = pipeline("validate", MUJOCO_GL="disable")
    assert result.returncode == 0 and result.stdout.startswith("ok: "), result.stderr


def test_a_stage_imports_only_what_it_runs() -> None:
    """Each stage is a process of its own: the dispatcher loads a stage's command, and so its
    dependencies, only when that stage runs."""
    code = (
        "import sys\n"
        "from ede_pipeline.cli import main\n"
        "main(['collect', '--help'], standalone_mode=False)\n"
        "heavy = ('torch', 'matplotlib', 'dvc', 'rliable', 'ede_pipeline.train')\n"
        "print(sorted(m for m in heavy if m in sys.modules))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=os.environ, check=False
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines()[-1] == "[]"
