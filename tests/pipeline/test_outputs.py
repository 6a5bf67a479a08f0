"""Every stage checks, before it works, that it can write its outputs, lock, temporaries and
progress file: a place it cannot write is one line naming it, exit 2, and nothing written."""

from __future__ import annotations

import ast
import errno
import json
import os
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import yaml
from click.testing import CliRunner

from ede.io.atomic import unwritable
from ede_pipeline.cli import main
from tests.support import REPO

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
    params["runs"].update(
        tasks={"ede/Point-v0": "point"}, seeds=[0], budgets={"ede/Point-v0": 1000}
    )
    params["report"].update(effect_space_family=None, exploration_family=None)
    (root / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    cwd = os.getcwd()
    os.chdir(root)
    try:
        for command in (
            ["collect", "--family", "point"],
            ["pretrain", "encoder", "--family", "point"],
            ["pretrain", "decoder", "--family", "point"],
            ["task-code", "--family", "point"],
        ):
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
# Every stage that writes a folder, by the option that names it.
FOLDER_STAGES = {
    **STAGES,
    "report curves": ["report", "--out", "r", "--curves", "{out}"],
    "task-code": ["task-code", "--family", "point", "--out", "{out}"],
    "task-inputs": ["task-inputs", "--task", "ede/Point-v0", "--out", "{out}"],
}
PLACES = {
    "a file in the way": ("afile", "afile: a file is in the way; expected a directory there"),
    "a file among its parents": (
        "afile/out",
        "afile/out: cannot be created: afile is a file, not a directory",
    ),
    "a read-only location": (
        str(READ_ONLY / "out"),
        f"{READ_ONLY / 'out'}: cannot be written: /sys does not take new files",
    ),
}


@pytest.mark.parametrize("place", PLACES)
@pytest.mark.parametrize("stage", FOLDER_STAGES)
def test_an_output_that_cannot_be_written_is_refused_before_work(
    workdir: Path, stage: str, place: str
) -> None:
    out, message = PLACES[place]
    before = listing(workdir)
    result = CliRunner().invoke(main, [a.replace("{out}", out) for a in FOLDER_STAGES[stage]])
    assert result.exit_code == 2, result.output
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"Error: {message}"), result.stderr
    assert listing(workdir) == before


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["pretrain", "encoder", "--family", "point", "--out", "e", "--metrics", "afile/m.json"],
            "afile/m.json: cannot be created: afile is a file",
        ),
        (
            ["pretrain", "decoder", "--family", "point", "--out", "d", "--plots", "h.csv/x"],
            "h.csv/x: cannot be created",
        ),
        (["report", "--out", "r", "--curves", "afile"], "afile: a file is in the way"),
        (
            ["report", "--out", "r", "--metrics", str(READ_ONLY / "m.json")],
            "does not take new files",
        ),
    ],
)
def test_every_output_of_a_stage_is_checked_not_only_its_folder(
    workdir: Path, args: list[str], message: str
) -> None:
    (workdir / "h.csv").write_text("")
    before = listing(workdir)
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 2 and message in result.stderr, result.output
    assert len(result.stderr.splitlines()) == 1
    assert listing(workdir) == before


def test_an_unwritable_progress_file_is_named_by_its_variable(workdir: Path) -> None:
    before = listing(workdir)
    result = CliRunner(env={"EDE_PROGRESS": str(READ_ONLY / "progress.json")}).invoke(
        main, [*STAGES["collect"][:-2], "--out", "store"]
    )
    assert result.exit_code == 2
    assert result.stderr.startswith(
        f"Error: EDE_PROGRESS={READ_ONLY / 'progress.json'}: cannot be written"
    )
    assert listing(workdir) == before


def test_a_full_location_is_refused(workdir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def full(fd: int) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full)
    before = listing(workdir)
    result = CliRunner().invoke(main, [*STAGES["train"][:-1], "run"])
    assert result.exit_code == 2
    assert "run: cannot be written: . does not take data (No space left on device)" in result.stderr
    assert listing(workdir) == before


def test_several_seeds_are_all_checked_before_any_lock(workdir: Path) -> None:
    (workdir / "runs").mkdir()
    (workdir / "runs" / "seed2").write_text("in the way\n")
    before = listing(workdir)
    result = CliRunner().invoke(
        main,
        [
            "train",
            "--task",
            "ede/Point-v0",
            "--algo",
            "td3",
            "--seed",
            "0-2",
            "--out",
            "runs/seed{seed}",
        ],
    )
    assert result.exit_code == 2 and "runs/seed2: a file is in the way" in result.stderr
    assert listing(workdir) == before  # no lock of seed 0 or 1 left behind


def test_unwritable_says_nothing_where_all_is_well_and_leaves_nothing(tmp_path: Path) -> None:
    assert unwritable(tmp_path / "a" / "b", directory=True) is None
    assert unwritable(tmp_path / "m.json", directory=False) is None
    (tmp_path / "d").mkdir()
    assert unwritable(tmp_path / "d", directory=False) == (
        f"{tmp_path / 'd'}: a directory is in the way; expected a file there, or nothing"
    )
    assert listing(tmp_path) == ["d"]


def test_a_sweeps_log_folder_is_checked_before_anything_runs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    shutil.copy(REPO / "params.yaml", tmp_path)
    shutil.copy(REPO / "dvc.yaml", tmp_path)
    (tmp_path / "afile").write_text("")
    monkeypatch.chdir(tmp_path)
    before = listing(tmp_path)
    result = CliRunner().invoke(main, ["sweep", "--logs", "afile/logs"])
    assert result.exit_code == 2
    assert (
        result.stderr
        == "Error: --logs afile/logs: cannot be created: afile is a file, not a directory\n"
    )
    assert listing(tmp_path) == before


# ---------------------------------------------------------------------------------------------
# Nothing lost: a stage replaces or writes into a folder only where it wrote it itself.

ROLLOUTS = "data/families/point/rollouts.zarr"
ENCODER = "data/families/point/embedding/encoder"


def contents(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` with its bytes: what a stage must leave as it was."""
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


def refused(
    args: list[str], workdir: Path, *message: str, env: dict[str, str] | None = None
) -> None:
    before = contents(workdir)
    result = CliRunner(env=env).invoke(main, args)
    assert result.exit_code == 2, result.output
    assert len(result.stderr.splitlines()) == 1 and result.exception is not None, result.stderr
    assert all(part in result.stderr for part in message), result.stderr
    assert contents(workdir) == before


def run(stage: str, out: str) -> list[str]:
    return [a.replace("{out}", out) for a in FOLDER_STAGES[stage]]


@pytest.mark.parametrize("stage", FOLDER_STAGES)
def test_no_stage_deletes_a_folder_of_a_users_files(workdir: Path, stage: str) -> None:
    """The issue's example for every stage: --out names a folder holding a copy of the family's
    rollouts and a user's notes; both stay, byte for byte."""
    shutil.copytree(ROLLOUTS, "mine/rollouts.zarr")
    (workdir / "mine" / "NOTES.txt").write_text("a week of thoughts\n")
    refused(
        run(stage, "mine"),
        workdir,
        "mine: holds NOTES.txt, rollouts.zarr, which no ede stage wrote there",
    )


@pytest.mark.parametrize("stage", FOLDER_STAGES)
@pytest.mark.parametrize("place", [".", "..", "../.."])
def test_no_stage_writes_over_the_working_directory_or_above(
    workdir: Path, stage: str, place: str
) -> None:
    refused(run(stage, place), workdir, "the working directory")


@pytest.mark.parametrize("stage", ["collect", "encoder", "decoder", "task-code", "task-inputs"])
def test_a_stage_replaces_its_own_output_and_nothing_beside_it(workdir: Path, stage: str) -> None:
    first = CliRunner().invoke(main, run(stage, "out"))
    assert first.exit_code == 0, first.output
    again = CliRunner().invoke(main, run(stage, "out"))  # its own: replaced
    assert again.exit_code == 0, again.output
    (workdir / "out" / "NOTES.txt").write_text("mine\n")
    refused(run(stage, "out"), workdir, "out: holds NOTES.txt beside the")


def test_a_training_run_resumes_in_its_own_folder_but_keeps_off_a_users_file(workdir: Path) -> None:
    args = run("train", "run")
    assert CliRunner().invoke(main, args).exit_code == 0
    assert CliRunner().invoke(main, args).exit_code == 0
    (workdir / "run" / "NOTES.txt").write_text("mine\n")
    refused(args, workdir, "run: holds NOTES.txt beside the training run")


@pytest.mark.parametrize(
    ("stage", "other", "kinds"),
    [
        ("encoder", "data/families/point/embedding/decoder", "holds a decoder, not an encoder"),
        ("decoder", "records", "holds a folder of task records, not a decoder"),
        ("collect", ENCODER, "holds an encoder, not a rollouts store"),
        ("report", "records", "holds a folder of task records, not a report"),
        ("train", ROLLOUTS, "holds a rollouts store, not a training run"),
    ],
)
def test_a_stage_never_replaces_another_stages_output(
    workdir: Path, stage: str, other: str, kinds: str
) -> None:
    assert CliRunner().invoke(main, run("task-code", "records")).exit_code == 0
    refused(run(stage, other), workdir, kinds)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["pretrain", "encoder", "--family", "point", "--out", "data/families/point"],
            f"data/families/point: holds the stage's input {ROLLOUTS}",
        ),
        (
            [
                "pretrain",
                "encoder",
                "--family",
                "point",
                "--out",
                "e",
                "--metrics",
                f"{ROLLOUTS}/zarr.json",
            ],
            f"{ROLLOUTS}/zarr.json: lies inside the stage's input {ROLLOUTS}",
        ),
        (
            [
                "pretrain",
                "decoder",
                "--family",
                "point",
                "--out",
                "d",
                "--plots",
                f"{ENCODER}/meta.json",
            ],
            f"lies inside the stage's input {ENCODER}",
        ),
        (["report", "--out", "r", "--curves", "data"], "data: holds the stage's input data/runs"),
        (
            ["report", "--out", "r", "--metrics", "data/runs/m.json"],
            "data/runs/m.json: lies inside the stage's input data/runs",
        ),
        (
            ["task-inputs", "--task", "ede/Point-v0", "--out", "data/families/point/embedding"],
            "data/families/point/embedding: is the stage's input data/families/point/embedding",
        ),
    ],
)
def test_no_output_is_holds_or_lies_inside_an_input(
    workdir: Path, args: list[str], message: str
) -> None:
    (workdir / "data" / "runs").mkdir(exist_ok=True)
    (workdir / "data" / "families" / "point" / "code").mkdir(exist_ok=True)
    refused(args, workdir, message)


def test_ede_td3_refuses_a_run_folder_inside_its_embedding(workdir: Path) -> None:
    refused(
        [
            "train",
            "--task",
            "ede/Point-v0",
            "--algo",
            "ede-td3",
            "--seed",
            "0",
            "--out",
            f"{ENCODER}/run",
        ],
        workdir,
        f"{ENCODER}/run: lies inside the stage's input {ENCODER}",
    )


def test_the_library_refuses_too(tmp_path: Path) -> None:
    """``write_atomically`` itself keeps off what it did not write, for code that calls it."""
    from ede.io.atomic import NotOurs, write_atomically

    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "NOTES.txt").write_text("mine\n")
    with pytest.raises(NotOurs, match=r"holds NOTES\.txt, which no ede stage wrote there"):
        write_atomically(tmp_path / "mine", lambda t: (t / "x").write_text("x"), "thing")
    assert listing(tmp_path) == ["mine", "mine/NOTES.txt"]


# A write that fails midway: each process limits the size of a file it writes (RLIMIT_FSIZE), so
# a write past the limit fails with EFBIG, as one on a full disk fails with ENOSPC.
LIMITED = """
import resource, signal, sys
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit}))
from ede_pipeline.cli import main
sys.argv = ["ede-pipeline", *sys.argv[1:]]
main()
"""


@pytest.mark.parametrize(
    ("args", "limit", "out"),
    [
        (["collect", "--family", "point", "--out", "r.zarr"], 2_000, "r.zarr"),
        (["pretrain", "encoder", "--family", "point", "--out", "e"], 2_000, "e"),
        (["report", "--runs", "empty", "--out", "r"], 2_000, "r"),
    ],
)
def test_a_write_that_fails_midway_is_one_line_and_leaves_nothing(
    workdir: Path,
    args: list[str],
    limit: int,
    out: str,
) -> None:
    import subprocess
    import sys

    (workdir / "empty").mkdir()
    before = listing(workdir)
    result = subprocess.run(
        [sys.executable, "-c", LIMITED.format(limit=limit), *args],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 1, result.stderr
    errors = [line for line in result.stderr.splitlines() if line.startswith("Error:")]
    assert errors == [
        line
        for line in result.stderr.splitlines()
        if "Traceback" in line or line.startswith("Error:")
    ], result.stderr  # no traceback
    assert (
        len(errors) == 1 and f"{out}" in errors[0] and "not written (File too large)" in errors[0]
    )
    left = sorted(set(listing(workdir)) - set(before))
    assert left == [], left  # no temporary, no lock, no half an output


# ---------------------------------------------------------------------------------------------
# One rule for every place a command writes, whatever option names it and however it is named.

# Every option of a command that names a path, by the command's words: what it writes, or that it
# only reads. A new path option must be added to one of them, and every writing one is then held
# to the rule below (the command's other required arguments beside it).
WRITES = {
    ("collect", "--out"): ["collect", "--family", "point"],
    ("pretrain encoder", "--out"): ["pretrain", "encoder", "--family", "point"],
    ("pretrain encoder", "--metrics"): ["pretrain", "encoder", "--family", "point"],
    ("pretrain encoder", "--plots"): ["pretrain", "encoder", "--family", "point"],
    ("pretrain decoder", "--out"): ["pretrain", "decoder", "--family", "point"],
    ("pretrain decoder", "--metrics"): ["pretrain", "decoder", "--family", "point"],
    ("pretrain decoder", "--plots"): ["pretrain", "decoder", "--family", "point"],
    ("report", "--out"): ["report"],
    ("report", "--metrics"): ["report"],
    ("report", "--curves"): ["report"],
    ("results", "--figures"): ["results"],
    ("results", "--pages"): ["results"],  # the pages it fills in place
    ("render", "--out"): ["render", "a-run"],
    ("experiment export", "--to"): ["experiment", "export", "two"],
    ("sweep", "--logs"): ["sweep"],
    ("task-code", "--out"): ["task-code", "--family", "point"],
    ("task-inputs", "--out"): ["task-inputs", "--task", "ede/Point-v0"],
    ("train", "--out"): ["train", "--task", "ede/Point-v0", "--algo", "td3", "--seed", "0"],
}
READS = {
    ("inspect", "--rollouts"),
    ("pretrain encoder", "--rollouts"),
    ("pretrain decoder", "--rollouts"),
    ("pretrain decoder", "--encoder"),
    ("report", "--runs"),
    ("report", "--families"),
    ("results", "--runs"),
    ("results", "--ablations"),
    ("task-inputs", "--embedding"),
    ("task-inputs", "--code"),
    ("train", "--encoder"),
    ("train", "--decoder"),
    ("render", "run"),
    ("render", "--encoder"),
    ("render", "--decoder"),
    *((command, "--params") for command in (
        "collect", "envs", "inspect", "pretrain decoder", "pretrain encoder", "render", "report",
        "results", "task-code", "task-inputs", "train", "validate",
    )),
}  # fmt: skip


def path_options() -> set[tuple[str, str]]:
    """Every (command, option) of ``ede-pipeline`` whose value is a path."""
    import click

    found = set()

    def walk(command: click.Command, words: tuple[str, ...], context: click.Context) -> None:
        if isinstance(command, click.Group):
            for name in command.list_commands(context):
                sub = command.get_command(context, name)
                assert sub is not None
                walk(sub, (*words, name), context)
            return
        for param in command.params:
            if isinstance(param.type, click.Path):
                found.add((" ".join(words), param.opts[0] if param.opts else str(param.name)))

    walk(main, (), click.Context(main))
    return found


def test_every_path_option_is_known_as_one_that_writes_or_one_that_reads() -> None:
    assert path_options() == set(WRITES) | READS


@pytest.mark.parametrize("link", [False, True], ids=["named", "through a link"])
@pytest.mark.parametrize("option", WRITES, ids=" ".join)
def test_no_option_writes_over_the_params_file(
    workdir: Path, option: tuple[str, str], link: bool
) -> None:
    """The issue's example, ``report --metrics params.yaml``, for every writing option: the
    params file (or a link to it) is refused in one line before any work, and kept."""
    target = "params.yaml"
    (workdir / "dvc.yaml").write_text("stages: {}\n")  # the sweep runs in a DVC project only
    if link:
        (workdir / "link.yaml").symlink_to("params.yaml")
        target = "link.yaml"
    before = contents(workdir)
    result = CliRunner().invoke(main, [*WRITES[option], option[1], target])
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output and target in result.stderr, result.stderr
    assert contents(workdir) == before


FILE_OUTPUTS = {
    "encoder metrics": ["pretrain", "encoder", "--family", "point", "--out", "e", "--metrics"],
    "decoder history": ["pretrain", "decoder", "--family", "point", "--out", "d", "--plots"],
    "report metrics": ["report", "--runs", "empty", "--out", "r", "--metrics"],
}


@pytest.mark.parametrize("output", FILE_OUTPUTS)
def test_a_file_output_replaces_only_the_file_it_wrote(workdir: Path, output: str) -> None:
    """A file option may name a new path or the file the same kind of writer wrote there; a
    user's file, or the stage's own file edited since, is kept and refused in one line."""
    (workdir / "empty").mkdir()
    args = [*FILE_OUTPUTS[output], "out.file"]
    (workdir / "out.file").write_text("a user's numbers\n")
    refused(args, workdir, "out.file: a file", "did not write there")
    (workdir / "out.file").unlink()
    assert CliRunner().invoke(main, args).exit_code == 0
    again = CliRunner().invoke(main, args)  # its own file: replaced
    assert again.exit_code == 0, again.output
    with (workdir / "out.file").open("a") as file:
        file.write("edited by hand\n")
    refused(args, workdir, "out.file: a file", "or one changed since")


def test_a_link_to_a_folder_is_written_through_and_stays_a_link(workdir: Path) -> None:
    """``--out L`` with L a link to an empty folder: the output is written where L leads, L is
    still the link; a link to a folder of a user's files is refused as that folder is."""
    (workdir / "target").mkdir()
    (workdir / "L").symlink_to("target")
    done = CliRunner().invoke(main, run("task-code", "L"))
    assert done.exit_code == 0, done.output
    assert (workdir / "L").is_symlink() and (workdir / "target" / "ede" / "Point-v0.json").is_file()
    assert not [p for p in workdir.iterdir() if ".tmp-" in p.name]
    again = CliRunner().invoke(main, run("task-code", "L"))  # its own, through the link
    assert again.exit_code == 0, again.output
    (workdir / "mine").mkdir()
    (workdir / "mine" / "NOTES.txt").write_text("mine\n")
    (workdir / "M").symlink_to("mine")
    refused(run("task-code", "M"), workdir, "M: holds NOTES.txt, which no ede stage wrote")


def test_two_names_of_one_output_share_its_lock(workdir: Path) -> None:
    from ede.io.locks import exclusive

    (workdir / "out").mkdir()
    (workdir / "L").symlink_to("out")
    with exclusive(workdir / "out"):
        refused(run("task-code", "L"), workdir, "being written by process")


@pytest.mark.parametrize("length", [250, 247, 244])
def test_a_name_too_long_for_the_filesystem_is_refused_before_work(
    workdir: Path, length: int
) -> None:
    """Names near the filesystem's 255 bytes: the output's temporary (``.tmp-<pid>``) and lock
    (``.<name>.lock``) beside it must fit too, so longer ones are refused before any work."""
    refused(run("task-code", "x" * length), workdir, "bytes; at most 238 fit here")
    fits = CliRunner().invoke(main, run("task-code", "y" * 238))
    assert fits.exit_code == 0, fits.output


def test_a_file_output_whose_writer_was_killed_before_marking_it_is_still_its_own(
    workdir: Path,
) -> None:
    """A stage marks each file output before it writes it: killed between the write and the
    final mark, the file it left is its own, and the rerun replaces it."""
    import subprocess
    import sys

    from ede.io.atomic import file_problem

    (workdir / "empty").mkdir()
    args = [*FILE_OUTPUTS["report metrics"], "out.file"]
    assert CliRunner().invoke(main, args).exit_code == 0
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], text=True,
                          capture_output=True, check=True)  # fmt: skip
    mark = json.loads((workdir / ".out.file.ede-output.json").read_text())
    mark.update(sha256=None, writer=int(gone.stdout))  # a writer that died before its mark
    (workdir / ".out.file.ede-output.json").write_text(json.dumps(mark))
    (workdir / "out.file").write_text("half of what it meant to write")
    assert file_problem(workdir / "out.file", "report metrics") is None
    again = CliRunner().invoke(main, args)
    assert again.exit_code == 0, again.output
    assert json.loads((workdir / ".out.file.ede-output.json").read_text())["sha256"] is not None


# ---------------------------------------------------------------------------------------------
# Every door, not only the options: the environment variables that name paths.

# Every environment variable the code reads, by what it names: a path a command writes, a path it
# only reads (or runs), or no path. A new one must be added to one of them (the test below finds
# each read in ede/, pipeline/ and envs/), and every written one is then held to the rule below.
ENV_WRITES = {"EDE_PROGRESS"}
ENV_READS = {"RAY_TLS_SERVER_CERT", "RAY_TLS_SERVER_KEY", "RAY_TLS_CA_CERT", "SHELL", "PATH",
             "PYTHONPATH",
             "CC", "CXX"}  # the compilers torch.compile runs (ede.run.group.compiler_missing)  # fmt: skip
ENV_NOT_PATHS = {"EDE_COMMIT", "EDE_PARENT", "MUJOCO_GL", "RAY_ADDRESS", "RAY_USE_TLS"}
# Reads whose name is a loop's variable, not a constant: the names it takes, by its module.
ENV_LOOPS = {
    "ede_pipeline.sweep.on_ray": lambda module: {*module.RAY_TLS.values(), module.RAY_TLS_CA}
}


def environment_variables() -> set[str]:
    """Every variable that ``os.environ.get/pop/setdefault``, ``os.environ[...]`` or
    ``os.getenv`` reads in the project's packages, each name resolved to its value."""
    import importlib

    packages = {"ede": "ede", "pipeline": "ede_pipeline", "envs": "ede_envs"}
    found: set[str] = set()
    for folder, package in packages.items():
        for source in sorted((REPO / folder).rglob("*.py")):
            parts = source.relative_to(REPO / folder).with_suffix("").parts
            name = ".".join((package, *parts)).removesuffix(".__init__")
            for node in ast.walk(ast.parse(source.read_text())):
                read = _environment_read(node)
                if read is None:
                    continue
                where = f"{source}:{read.lineno}"
                if isinstance(read, ast.Constant) and isinstance(read.value, str):
                    found.add(read.value)
                    continue
                assert isinstance(read, ast.Name), f"{where}: name the variable by a constant"
                module = importlib.import_module(name)
                value = getattr(module, read.id, None)
                if isinstance(value, str):
                    found.add(value)
                else:
                    assert name in ENV_LOOPS, f"{where}: add the names it takes to ENV_LOOPS"
                    found |= ENV_LOOPS[name](module)
    return found


def _environment_read(node: ast.AST) -> ast.expr | None:
    """The name argument of an environment read, or None where ``node`` is none."""

    def environ(value: ast.expr) -> bool:
        return (
            isinstance(value, ast.Attribute)
            and value.attr == "environ"
            and isinstance(value.value, ast.Name)
            and value.value.id == "os"
        )

    if isinstance(node, ast.Subscript) and environ(node.value):
        return node.slice
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.args:
        method = node.func
        if (method.attr in ("get", "pop", "setdefault") and environ(method.value)) or (
            method.attr == "getenv"
            and isinstance(method.value, ast.Name)
            and method.value.id == "os"
        ):
            return node.args[0]
    return None


def test_every_environment_variable_is_known_as_a_path_written_read_or_none() -> None:
    assert environment_variables() == ENV_WRITES | ENV_READS | ENV_NOT_PATHS


# The commands that publish their progress to the file EDE_PROGRESS names (ede_pipeline.progress).
PUBLISHERS = {
    "collect": ["collect", "--family", "point", "--out", "c2.zarr"],
    "pretrain encoder": ["pretrain", "encoder", "--family", "point", "--out", "e"],
    "pretrain decoder": ["pretrain", "decoder", "--family", "point", "--out", "d"],
    "train": [*STAGES["train"][:-1], "run"],
}
# Where EDE_PROGRESS may not lead, and what the one line may say (a file of the rollouts store is
# the input of some commands, and a file no progress writer wrote for the others).
PROGRESS_PLACES = {
    "the params file": ("params.yaml", "is the stage's input params.yaml"),
    "a link to the params file": ("link.yaml", "is the stage's input params.yaml"),
    "a user's file": ("afile", "afile: a file a progress writer did not write there"),
    "a file of the rollouts store": (
        f"{ROLLOUTS}/zarr.json",
        "a file a progress writer did not write there",
        f"lies inside the stage's input {ROLLOUTS}",
    ),
    "a folder": ("data", "data: a directory is in the way; expected a file"),
    "the working directory": (".", ".: a directory is in the way"),
}


@pytest.mark.parametrize("place", PROGRESS_PLACES)
@pytest.mark.parametrize("command", PUBLISHERS)
def test_the_progress_file_is_held_to_the_rule_of_every_output(
    workdir: Path, command: str, place: str
) -> None:
    """The issue's example, ``EDE_PROGRESS=params.yaml ede-pipeline collect --family point
    --out c2.zarr``, for every command that publishes and every place that is not its own: one
    line naming the variable, exit 2, every file kept byte for byte."""
    (workdir / "link.yaml").symlink_to("params.yaml")
    value, *messages = PROGRESS_PLACES[place]
    before = contents(workdir)
    result = CliRunner(env={"EDE_PROGRESS": value}).invoke(main, PUBLISHERS[command])
    assert result.exit_code == 2, result.output
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"Error: EDE_PROGRESS={value}: "), lines
    assert any(message in lines[0] for message in messages), lines
    assert contents(workdir) == before


@pytest.mark.parametrize(
    ("args", "value", "message"),
    [
        (
            ["pretrain", "encoder", "--family", "point", "--out", "e"],
            f"{ROLLOUTS}/new.json",
            f"lies inside the stage's input {ROLLOUTS}",
        ),
        (
            ["pretrain", "decoder", "--family", "point", "--out", "d"],
            f"{ENCODER}/progress.json",
            f"lies inside the stage's input {ENCODER}",
        ),
        (PUBLISHERS["collect"], "c2.zarr/progress.json", "lies inside the stage's output c2.zarr"),
        (
            ["pretrain", "encoder", "--family", "point", "--out", "e", "--metrics", "m.json"],
            "m.json",
            "is the stage's output m.json",
        ),
        (PUBLISHERS["train"], "run/progress.json", "lies inside the stage's output run"),
    ],
)
def test_the_progress_file_is_apart_from_the_stages_inputs_and_outputs(
    workdir: Path, args: list[str], value: str, message: str
) -> None:
    refused(args, workdir, f"Error: EDE_PROGRESS={value}: {message}", env={"EDE_PROGRESS": value})


def test_outputs_of_one_stage_are_apart_from_each_other(workdir: Path) -> None:
    (workdir / "empty").mkdir()
    refused(
        ["report", "--runs", "empty", "--out", "r", "--metrics", "r/m.json"],
        workdir,
        "r: holds the stage's output r/m.json",
    )
    refused(
        [*FILE_OUTPUTS["encoder metrics"], "h.csv", "--plots", "h.csv"],
        workdir,
        "h.csv: is the stage's output h.csv",
    )


def test_the_progress_file_is_the_stages_own_and_replaced_only_as_such(workdir: Path) -> None:
    """A progress file is marked as a progress writer's: the next stage given it replaces it,
    a file edited since is kept; nothing but it and its mark is left beside it."""
    env = {"EDE_PROGRESS": "progress/p.json"}
    args = PUBLISHERS["pretrain encoder"]
    first = CliRunner(env=env).invoke(main, args)
    assert first.exit_code == 0, first.output
    assert json.loads((workdir / "progress" / "p.json").read_text())["done"] == 1
    assert sorted(p.name for p in (workdir / "progress").iterdir()) == [
        ".p.json.ede-output.json",
        "p.json",
    ]  # no lock left
    again = CliRunner(env=env).invoke(main, PUBLISHERS["pretrain decoder"])
    assert again.exit_code == 0, again.output
    (workdir / "progress" / "p.json").write_text("{}\n")
    refused(args, workdir, "progress/p.json: a file a progress writer did not write", env=env)


# ---------------------------------------------------------------------------------------------
# One writer per output: each file output is locked as a folder is.

HOLDER = """
import sys
from ede.io.locks import exclusive
with exclusive(sys.argv[1]):
    print("held", flush=True)
    sys.stdin.read()
"""


@pytest.fixture
def held(workdir: Path) -> Iterator[Callable[[str], int]]:
    """``held(path)``: the lock of ``path`` taken by another process, until the test ends; its
    PID."""
    import subprocess
    import sys

    holders: list[subprocess.Popen[str]] = []

    def hold(path: str) -> int:
        holder = subprocess.Popen(
            [sys.executable, "-c", HOLDER, path],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        holders.append(holder)
        assert holder.stdout is not None and holder.stdout.readline() == "held\n"
        return holder.pid

    yield hold
    for holder in holders:
        holder.communicate("", timeout=60)


@pytest.mark.parametrize(
    ("args", "output"),
    [
        (["report", "--runs", "empty", "--out", "r2", "--metrics", "m.json"], "m.json"),
        (["report", "--runs", "empty", "--out", "r2", "--curves", "c"], "c"),
        ([*FILE_OUTPUTS["encoder metrics"], "m.json"], "m.json"),
        ([*FILE_OUTPUTS["decoder history"], "h.csv"], "h.csv"),
        (["render", "a-run", "--out", "v.mp4"], "v.mp4"),
        ([*PUBLISHERS["collect"]], "EDE_PROGRESS=p.json"),
    ],
)
def test_a_second_writer_of_a_file_output_is_refused_with_the_holders_pid(
    workdir: Path, held: Callable[[str], int], args: list[str], output: str
) -> None:
    """The issue's example: two ``report`` given one ``--metrics`` at once; the second is one
    line naming the first, exit 2, and the first's file is as it wrote it."""
    (workdir / "empty").mkdir()
    holder = held(output.removeprefix("EDE_PROGRESS="))
    refused(
        args, workdir, f"Error: {output}: being written by process {holder}",
        env={"EDE_PROGRESS": "p.json", "MUJOCO_GL": "egl"},
    )  # fmt: skip


def test_a_file_output_another_writer_is_writing_is_refused_naming_it(
    workdir: Path, held: Callable[[str], int]
) -> None:
    """Two ``report`` given one ``--metrics`` file that an earlier report wrote: while the first
    writes it (its lock held, its mark naming it), the second says so in one line."""
    (workdir / "empty").mkdir()
    args = [*FILE_OUTPUTS["report metrics"], "m.json"]
    assert CliRunner().invoke(main, args).exit_code == 0
    holder = held("m.json")
    mark = {"kind": "report metrics", "sha256": None, "writer": holder}  # as writing_files does
    (workdir / ".m.json.ede-output.json").write_text(json.dumps(mark))
    refused(args, workdir, f"Error: m.json: being written by process {holder}; wait for it")


def test_a_runs_names_cannot_lead_its_video_out_of_the_videos_folder(workdir: Path) -> None:
    """``render RUN`` puts the video where the run's policy names its task and algorithm
    (``data/videos/<task>/<algo>/``): names that climb out of it are refused before any work
    (a task must be registered and an algorithm ours: the policy's check ends them, and render's
    own check of the path stays behind it)."""
    import torch
    from safetensors.torch import save_file

    policy = workdir / "a-run" / "policy"
    policy.mkdir(parents=True)
    save_file({"w": torch.zeros(1)}, policy / "policy.safetensors")
    meta = {"task": "../../../../../elsewhere", "algo": "td3", "seed": 0, "hidden": [16],
            "k": 1, "code_size": 1, "code_low": [0.0], "code_high": [1.0]}  # fmt: skip
    (policy / "policy.json").write_text(json.dumps(meta))
    refused(
        ["render", "a-run"], workdir, "../../../../../elsewhere: cannot be made to render",
        env={"MUJOCO_GL": "egl"},
    )  # fmt: skip
    assert not (workdir.parent / "elsewhere").exists()
