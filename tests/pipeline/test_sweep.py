"""``ede-pipeline sweep`` records exactly what ``dvc repro`` would, in parallel, run by run.

Scratch copies of the repo with tiny params and four train runs (one task, both algorithms, two
seeds): ``dvc repro train`` in one copy is the reference; the sweeps in others must leave
the same ``dvc.lock`` entries and the same returns. Runs are deterministic on CPU; only the wall
times they write (``eval.csv``'s ``wall_seconds``, ``metrics.json``'s speed) differ, so the hashes
of those two files are compared by content minus the times instead.
"""

from __future__ import annotations

import contextlib
import csv
import json
import shlex
import shutil
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from ede.config import load_params
from ede.io.locks import exclusive
from ede_pipeline.sweep.plan import (
    Job,
    RunId,
    group_jobs,
    seed_by_seed,
    train_command,
    train_runs,
)
from tests.support import BIN, WALL_TIMES, dvc, run, scratch_copy, untimed_run_json

pytestmark = pytest.mark.slow

TASK = "ede/ReacherVertical-v0"
STAGES = [f"train@{TASK}-{algo}-{seed}" for algo in ("td3", "ede-td3") for seed in (0, 1)]
BROKEN = "train@ede/ReacherVertical-v0-td3-1"
BROKEN_RUN = f"data/runs/{TASK}/td3/seed1"
HELD = "being written by process"  # what the held run's command says
UNTIMED = WALL_TIMES  # the run's files that hold wall times, and run.json their checksums


def ok(result: subprocess.CompletedProcess[str]) -> str:
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    return result.stdout + result.stderr


def sweep(copy: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return run(copy, BIN / "ede-pipeline", "sweep", *args, timeout=600)


@pytest.fixture(scope="module")
def upstream(
    tmp_path_factory: pytest.TempPathFactory, tiny_pipeline: Callable[[dict[str, Any]], None]
) -> Path:
    """A copy with tiny params and runs of one reacher task, whose embedding is made (collect,
    pretrain), and no run yet."""

    def one_task(params: dict[str, Any]) -> None:
        tiny_pipeline(params)
        params["runs"]["tasks"] = {TASK: "reacher"}
        params["runs"]["seeds"] = [0, 1]

    copy = scratch_copy(tmp_path_factory.mktemp("upstream") / "repo", one_task)
    ok(dvc(copy, "repro", "task_inputs"))
    return copy


@pytest.fixture(scope="module")
def reference(upstream: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """What ``dvc repro`` of the four train stages records, one at a time."""
    copy = tmp_path_factory.mktemp("reference") / "repo"
    shutil.copytree(upstream, copy, symlinks=True)
    ok(dvc(copy, "repro", "train"))
    return record_of(copy)


@pytest.fixture
def copy_of_upstream(upstream: Path, tmp_path: Path) -> Path:
    copy = tmp_path / "repo"
    shutil.copytree(upstream, copy, symlinks=True)
    return copy


def record_of(copy: Path, stages: list[str] = STAGES) -> dict[str, Any]:
    """Per stage: its dvc.lock entry (untimed files' hashes set aside) and its returns."""
    lock = yaml.safe_load((copy / "dvc.lock").read_text())["stages"]
    record = {}
    for stage in stages:
        entry = lock[stage]
        for out in entry["outs"]:
            if Path(out["path"]).name in UNTIMED:
                assert (copy / out["path"]).is_file(), out["path"]
                out.pop("md5"), out.pop("size")
        run = copy / next(Path(out["path"]).parent for out in entry["outs"])
        with (run / "eval.csv").open() as file:
            returns = [(row["step"], row["mean_return"]) for row in csv.DictReader(file)]
        metrics = json.loads((run / "metrics.json").read_text())
        record[stage] = {
            "lock": entry,
            "returns": returns,
            "final": metrics["final_return"],
            "run": untimed_run_json(run / "run.json"),
        }
    return record


def assert_up_to_date(copy: Path) -> None:
    status = ok(dvc(copy, "status", "train"))
    assert "up to date" in status, status


def test_sweep_with_two_jobs_records_what_dvc_repro_records(
    copy_of_upstream: Path, reference: dict[str, Any]
) -> None:
    copy = copy_of_upstream
    # An upstream stage out of date (its output gone): the sweep brings it back first (from the run
    # cache: this very run was made before); the task's inputs, made from it, come out as before.
    shutil.rmtree(copy / "data/families/reacher/embedding/decoder")
    out = ok(sweep(copy, "train", "--jobs", "2", "--group-size", "1"))
    assert "6 of 9 stages out of date" in out, out  # of the runs and the five stages before them
    first = next(line for line in out.splitlines() if line.startswith("[1/6]"))
    assert "cached pretrain_decoder@reacher  restored from the run cache" in first, out
    assert "up to date: its inputs came out as before" in out, out
    assert out.count(" ok ") == 5 and "[6/6]" in out and "ETA" in out, out
    overall = [line for line in out.splitlines() if line.startswith("sweep: 6/6 stages")]
    assert overall and "/s" in overall[-1] and "(100%)" in overall[-1], out
    assert record_of(copy) == reference
    assert not (copy / f"data/runs/{TASK}/td3/seed0/checkpoint").exists()
    assert_up_to_date(copy)


def test_sweep_in_groups_of_seeds_records_what_dvc_repro_records(
    copy_of_upstream: Path, reference: dict[str, Any]
) -> None:
    copy = copy_of_upstream
    out = ok(sweep(copy, "train", "--jobs", "2", "--group-size", "2"))
    assert out.count("(one process for 2)") == 4 and "[4/4]" in out, out
    assert record_of(copy) == reference
    assert_up_to_date(copy)


REPORT = Job("report", [["ede-pipeline", "report"]], "/repo", {}, "/logs/report.log")  # no run


def job(algo: str, seed: int) -> Job:
    """A train stage's job as the sweep makes it, its command through a shell as DVC runs it."""
    words = train_command(TASK, algo, [seed])
    return Job(
        f"train@{TASK}-{algo}-{seed}",
        [["/bin/sh", "-c", shlex.join(words)]],
        "/repo",
        {"A": "1"},
        f"/logs/{algo}-{seed}.log",
        runs=(RunId(TASK, algo, seed),),
    )


def test_jobs_of_one_task_and_algorithm_are_grouped_by_seed() -> None:
    jobs = [job("td3", 0), job("ede-td3", 1), job("td3", 2), job("td3", 1), REPORT]
    grouped = group_jobs(jobs, 2)
    assert [j.stage for j in grouped] == [
        "report",
        f"train@{TASK}-td3-0 + train@{TASK}-td3-1",
        f"train@{TASK}-td3-2",
        f"train@{TASK}-ede-td3-1",
    ]
    shell, flag, command = grouped[1].argvs[0]
    assert (shell, flag, grouped[1].env) == ("/bin/sh", "-c", {"A": "1"})
    words = shlex.split(command)
    assert words[words.index("--seed") + 1] == "0,1"
    assert words[words.index("--out") + 1] == f"data/runs/{TASK}/td3/seed{{seed}}"
    assert grouped[1].members == (f"train@{TASK}-td3-0", f"train@{TASK}-td3-1")
    assert grouped[1].runs == (RunId(TASK, "td3", 0), RunId(TASK, "td3", 1))
    assert group_jobs(jobs, 1) == jobs


def test_runs_start_seed_by_seed_so_a_stopped_sweep_leaves_both_algorithms_at_its_seeds() -> None:
    in_dvc_order = [job(algo, seed) for algo in ("td3", "ede-td3") for seed in (0, 1, 2, 3)]
    order = [j.stage for j in seed_by_seed([*in_dvc_order, REPORT])]
    assert order == ["report"] + [
        f"train@{TASK}-{algo}-{seed}" for seed in (0, 1, 2, 3) for algo in ("td3", "ede-td3")
    ]
    groups = seed_by_seed(group_jobs(in_dvc_order, 2))  # the order the sweep submits them in
    assert [[run.seed for run in g.runs] for g in groups] == [[0, 1], [0, 1], [2, 3], [2, 3]]
    assert [g.runs[0].algo for g in groups] == ["td3", "ede-td3", "td3", "ede-td3"]


def test_a_stages_run_is_known_from_the_params_as_dvc_names_it(write_params) -> None:
    params = load_params(write_params())
    runs = train_runs(params)
    assert len(runs) == params.runs.count
    assert runs["train@ede/ReacherTurn-v0-ede-td3-3"] == RunId("ede/ReacherTurn-v0", "ede-td3", 3)


def break_one_run(copy: Path) -> contextlib.AbstractContextManager[None]:
    """The run's output held by this process (another writer, for the run's command): that run's
    command fails, for real, while the block lasts."""
    return exclusive(copy / BROKEN_RUN)


def test_a_failed_run_is_reported_and_the_others_recorded_then_resumed(
    copy_of_upstream: Path, reference: dict[str, Any]
) -> None:
    copy = copy_of_upstream
    with break_one_run(copy):
        failed = sweep(copy, "train", "--jobs", "2", "--group-size", "1")
    out = failed.stdout + failed.stderr
    assert failed.returncode == 1, out
    log = copy / ".dvc/tmp/sweep" / (BROKEN.replace("/", "_").replace("@", "__") + ".log")
    assert f"FAILED {BROKEN}" in out and f"log: {log}" in out, out
    assert "ede-pipeline train" in log.read_text() and HELD in log.read_text()
    assert "3 recorded, 1 failed" in out, out
    others = [stage for stage in STAGES if stage != BROKEN]
    lock = yaml.safe_load((copy / "dvc.lock").read_text())["stages"]
    assert BROKEN not in lock
    assert record_of(copy, others) == {stage: reference[stage] for stage in others}

    again = ok(sweep(copy, "train", "--jobs", "2", "--group-size", "1"))
    assert "1 of 9 stages out of date" in again and f"ok     {BROKEN}" in again, again
    assert record_of(copy) == reference
    assert_up_to_date(copy)


@pytest.fixture
def ray_cluster() -> Iterator[str]:
    """A Ray cluster on this machine only, two CPUs (two runs at once); its address."""
    import ray  # part of the dev extra: a missing Ray fails this test rather than skipping it

    context = ray.init(
        num_cpus=2,
        include_dashboard=False,
        _node_ip_address="127.0.0.1",
        log_to_driver=False,
        configure_logging=False,
    )
    try:
        yield context.address_info["gcs_address"]  # type: ignore[attr-defined]  # a RayContext
    finally:
        ray.shutdown()


def test_sweep_on_a_ray_cluster_records_what_dvc_repro_records(
    copy_of_upstream: Path, reference: dict[str, Any], ray_cluster: str
) -> None:
    copy = copy_of_upstream
    with break_one_run(copy):
        failed = sweep(copy, "train", "--executor", "ray", "--address", ray_cluster)
    out = failed.stdout + failed.stderr
    assert failed.returncode == 1 and f"FAILED {BROKEN}" in out, out
    assert "3 recorded, 1 failed" in out and "[4/4]" in out, out
    others = [stage for stage in STAGES if stage != BROKEN]
    assert record_of(copy, others) == {stage: reference[stage] for stage in others}
    log = copy / ".dvc/tmp/sweep" / (BROKEN.replace("/", "_").replace("@", "__") + ".log")
    assert HELD in log.read_text()


def test_a_sweep_writes_into_its_own_logs_folder_again_and_never_beside_a_users_file(
    repo_copy: Path,
) -> None:
    """A folder given as ``--logs`` is marked as the sweep's, owning every file a sweep writes
    there: each job's log, attempts and progress file, and what the writers of these put beside
    them (a temporary, a lock, a mark), so that the next sweep writes there again; a user's file
    put there is never written beside."""
    copy, logs = repo_copy, repo_copy / "logs"
    ok(sweep(copy, "collect@point", "--logs", "logs"))
    written = {path.name for path in logs.iterdir()}
    assert {"collect__point.log", "collect__point.progress"} <= written, written
    # What a writer killed midway leaves beside its file, and what marks and locks a file.
    for name in (
        "collect__point.progress.tmp-4194304",
        ".collect__point.progress.ede-output.json",
        ".collect__point.progress.ede-output.json.tmp-4194304",
        ".collect__point.progress.lock",
    ):
        (logs / name).touch()  # where the sweep wrote none itself

    # Out of date again, a run not made before (not in the run cache): it writes there again.
    params = yaml.safe_load((copy / "params.yaml").read_text())
    params["collect"]["steps"] += 1
    (copy / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    again = ok(sweep(copy, "collect@point", "--logs", "logs"))
    assert "1 of 2 stages out of date" in again and "ok     collect@point" in again, again

    shutil.rmtree(copy / "data/families/point/rollouts.zarr")
    (logs / "notes.txt").write_text("mine")
    before = {path.name: path.read_bytes() for path in logs.iterdir()}
    refused = sweep(copy, "collect@point", "--logs", "logs")
    assert refused.returncode == 2, refused.stderr
    assert refused.stderr == (
        f"Error: --logs {Path('logs')}: holds notes.txt beside the folder of sweep logs written "
        "there; move it out first\n"
    )
    assert {path.name: path.read_bytes() for path in logs.iterdir()} == before


@pytest.mark.parametrize(
    ("name", "damaged", "said"),
    [
        (
            "dvc.lock",
            'schema: "2.0"\nstages:\n  collect@point: 5\n',
            "dvc.lock: not what DVC expects: stages.collect@point",
        ),
        ("dvc.yaml", "stages:\n  a:\n    cmd: x\n    deps: [5\n", "dvc.yaml: not YAML (line 5"),
    ],
)
def test_a_damaged_dvc_file_is_one_line_before_anything_runs(
    repo_copy: Path, name: str, damaged: str, said: str
) -> None:
    (repo_copy / name).write_text(damaged)
    for targets in ((), ("task_code@point",)):
        result = sweep(repo_copy, *targets)
        assert result.returncode == 2, result.stderr
        [line] = result.stderr.splitlines()
        assert line.startswith("Error: ") and said in line, line
    assert not (repo_copy / "data").exists()


def test_the_default_logs_folder_given_by_name_is_the_default(repo_copy: Path) -> None:
    """``--logs .dvc/tmp/sweep`` is the default folder, DVC's scratch, where earlier sweeps left
    their logs unmarked: written into as the default is, not refused as a user's folder."""
    earlier = repo_copy / ".dvc/tmp/sweep/task_code__point.log"
    earlier.parent.mkdir(parents=True)
    earlier.write_text("an earlier sweep's log\n")
    out = ok(sweep(repo_copy, "task_code@point", "--logs", "./.dvc/tmp/sweep"))
    assert "ok     task_code@point" in out, out
    assert "ede-pipeline task-code" in earlier.read_text()  # this sweep's log now
