"""Names are names: a family, task or experiment name that is no name (docs/parameters.md,
"Names") is refused in one line before anything runs, and ``dvc.yaml``'s commands hold whatever
value DVC fills in as one shell word, so that even a name that got past the params runs nothing.

The issue's example: a family named ``pt;touch PWNED;echo`` passed ``validate``, and
``ede-pipeline sweep 'task_code*'`` then ran ``touch PWNED``.
"""

from __future__ import annotations

import codecs
import shlex
import subprocess
from pathlib import Path
from typing import Any

import pytest
import yaml
from click.testing import CliRunner

from ede_pipeline.cli import main
from ede_pipeline.sweep.stages import stage_argvs
from tests.support import BIN, HOSTILE_NAMES, run, scratch_copy

# Everything a shell acts on, in one name: DVC fills it in, the command must take it as one word.
SHELL_WORDS = "pt;touch PWNED;echo $(touch PWNED) `touch PWNED` & x | y > PWNED {a,b} * ~"


@pytest.fixture(scope="module")
def copy(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A scratch copy of the repository (a git repository with ``.dvc/``, its files committed:
    an experiment applies its file to the committed params.yaml), nothing made."""
    copy = scratch_copy(tmp_path_factory.mktemp("names") / "repo")
    identity = ("-c", "user.email=t@example.org", "-c", "user.name=t")
    run(copy, "git", *identity, "commit", "-qm", "the checkout")
    return copy


def family_named(params: dict[str, Any], name: str) -> None:
    """The point family renamed to ``name`` (no figure draws it: one place names it)."""
    params["families"][name] = params["families"].pop("point")
    params["report"]["effect_space_family"] = None


def write(path: Path, edit: Any, name: str) -> None:
    params = yaml.safe_load((path.parent / "params.yaml").read_text())
    edit(params, name)
    path.write_text(yaml.safe_dump(params, sort_keys=False, allow_unicode=True))


def made(copy: Path) -> list[str]:
    """What git sees in ``copy`` beyond its committed files, ignored files included."""
    listed = run(copy, "git", "status", "--porcelain", "--ignored", "--untracked-files=all")
    return sorted(line for line in listed.stdout.splitlines() if "params.yaml" not in line)


@pytest.mark.parametrize("name", HOSTILE_NAMES, ids=repr)
def test_validate_sweep_and_collect_refuse_a_name_that_is_no_name_in_one_line(
    copy: Path, name: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(copy)
    before = made(copy)
    write(copy / "params.yaml", family_named, name)
    try:
        for argv in (["validate"], ["sweep", "task_code*"], ["collect", "--family", name]):
            result = CliRunner().invoke(main, argv)
            assert result.exit_code == 2, (argv, result.output)
            (line,) = result.stderr.splitlines()
            assert line.startswith("Error: params.yaml: families."), line
            assert "expected a name: 1 to 64 ASCII letters" in line
        assert not list(copy.rglob("PWNED")) and made(copy) == before
    finally:
        run(copy, "git", "checkout", "params.yaml")


def test_the_issues_sweep_runs_nothing(copy: Path) -> None:
    """As a user runs it: a separate process, the stage commands through the shell."""
    write(copy / "params.yaml", family_named, "pt;touch PWNED;echo")
    before = made(copy)
    try:
        result = run(copy, BIN / "ede-pipeline", "sweep", "task_code*", timeout=300)
    finally:
        run(copy, "git", "checkout", "params.yaml")
    assert result.returncode == 2, result.stderr
    assert len(result.stderr.splitlines()) == 1, result.stderr
    assert not list(copy.rglob("PWNED")) and made(copy) == before


@pytest.mark.parametrize(
    ("args", "line"),
    [
        (["run", "a;touch PWNED"], "Error: experiment 'a;touch PWNED': expected a name"),
        (["run", "../params"], "Error: experiment '../params': expected a name"),
        (["run", "-rf", "--jobs", "1"], "Error: experiment '-rf': expected a name"),
        (["export", ".."], "Error: experiment '..': expected a name"),
        (["export", "x" * 300], "Error: experiment 'xxxxxxxx"),
    ],
)
def test_an_experiment_name_that_is_no_name_is_one_line(
    copy: Path, args: list[str], line: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(copy)
    before = made(copy)
    result = CliRunner().invoke(main, ["experiment", *args])
    assert result.exit_code == 2, result.output
    assert result.stderr.startswith(line) and len(result.stderr.splitlines()) == 1, result.stderr
    assert "expected a name: 1 to 64 ASCII letters" in result.stderr
    assert not list(copy.rglob("PWNED")) and made(copy) == before


@pytest.mark.parametrize(
    ("content", "problem"),
    [
        (codecs.BOM_UTF16_LE + "td3:\n  lr: 1\n".encode("utf-16-le"), "UTF-16 or UTF-32 text"),
        (
            b"a: &a [1, 1, 1, 1]\n"
            + b"".join(
                f"{n}: &{n} [*{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}]\n".encode()
                for p, n in zip("abcde", "bcdef", strict=True)
            ),
            "line 4: more than 10000 values",
        ),
        (b"", "empty; expected sections of the params"),
        (None, "a directory; expected a YAML file"),
    ],
    ids=["UTF-16", "aliases", "empty", "a directory"],
)
def test_a_bad_experiment_file_is_one_line_naming_it(
    copy: Path, content: bytes | None, problem: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(copy)
    before = made(copy)
    path = copy / "experiments" / "bad.yaml"
    if content is None:
        path.mkdir()
    else:
        path.write_bytes(content)
    try:
        result = CliRunner().invoke(main, ["experiment", "run", "bad"])
        after = made(copy)
    finally:
        if path.is_dir():
            path.rmdir()
        else:
            path.unlink()
    assert result.exit_code == 2, result.output
    assert result.stderr.startswith(f"Error: experiments/bad.yaml: {problem}"), result.stderr
    assert len(result.stderr.splitlines()) == 1, result.stderr
    assert [line for line in after if "bad.yaml" not in line] == before


def test_every_value_in_a_stage_command_is_one_shell_word(tmp_path: Path) -> None:
    """Past the params' check (written here without it), a family and a task named with every
    character a shell acts on reach each command as one argument, and the shell runs nothing
    else: each stage's command runs as DVC runs it, with an ``ede-pipeline`` that prints its
    arguments. (A name with ``'`` would end the quoting: the params refuse it.)"""
    from dvc.repo import Repo

    copy = scratch_copy(tmp_path / "repo")
    task = f"ede/{SHELL_WORDS}"

    def hostile(params: dict[str, Any], name: str) -> None:
        family_named(params, name)
        params["runs"]["tasks"] = {task: name}
        params["runs"]["seeds"] = [0]

    write(copy / "params.yaml", hostile, SHELL_WORDS)
    fake = tmp_path / "bin"
    fake.mkdir()
    (fake / "ede-pipeline").write_text('#!/bin/sh\nprintf "%s\\0" "$@"\n')
    (fake / "ede-pipeline").chmod(0o755)
    with Repo(str(copy)) as repo:
        stages = [s for s in repo.stage.collect() if SHELL_WORDS in s.name]
        assert {s.name.partition("@")[0] for s in stages} == {
            "task_code",
            "collect",
            "pretrain_encoder",
            "pretrain_decoder",
            "task_inputs",
            "train",
        }
        for stage in stages:
            for argv in stage_argvs(stage):
                done = subprocess.run(
                    argv,
                    cwd=copy,
                    env={"PATH": f"{fake}:/usr/bin:/bin"},
                    capture_output=True,
                    check=True,
                )
                words = done.stdout.decode().split("\0")[:-1]
                assert words == shlex.split(argv[-1])[1:], stage.name  # as written
                named = {words[i + 1] for i, w in enumerate(words) if w in ("--family", "--task")}
                assert named <= {SHELL_WORDS, task} and named, (stage.name, words)
                assert not done.stderr, (stage.name, done.stderr)
    assert not list(copy.rglob("PWNED")) and not list(tmp_path.glob("*PWNED*"))
