"""The sweep's plan and progress: how many seeds share a process by default, and the one overall
line — stages, steps from the runs' progress files, rate and ETA."""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from ede.config import Params
from ede_pipeline.common import read_params
from ede_pipeline.progress import PROGRESS_ENV, progress, read_progress
from ede_pipeline.sweep.command import _tail
from ede_pipeline.sweep.execute import attempts_file, problem, progress_file, run_job
from ede_pipeline.sweep.plan import Job, RunId, default_group_size, group_jobs, train_command
from ede_pipeline.sweep.tally import Tally, job_steps

TASK = "ede/ReacherVertical-v0"


def job(tmp_path: Path, algo: str, seed: int, task: str = TASK) -> Job:
    command = shlex.join(train_command(task, algo, [seed]))
    return Job(
        f"train@{task}-{algo}-{seed}",
        [["/bin/sh", "-c", command]],
        str(tmp_path),
        {},
        str(tmp_path / f"{algo}-{seed}.log"),
        runs=(RunId(task, algo, seed),),
    )


def test_a_job_runs_its_tasks_budget_once_per_seed(tmp_path: Path) -> None:
    budgets = {TASK: 1000}
    jobs = [job(tmp_path, "td3", seed) for seed in range(3)]
    assert job_steps(jobs[0], budgets) == 1000
    [group] = group_jobs(jobs, 3)
    assert job_steps(group, budgets) == 3000
    report = Job("report", [["ede-pipeline", "report"]], str(tmp_path), {}, str(tmp_path / "r.log"))
    assert job_steps(report, budgets) == 0
    assert job_steps(job(tmp_path, "td3", 0, task="other/Task-v0"), budgets) == 0


def test_stable_baselines3_runs_are_never_grouped(tmp_path: Path) -> None:
    # nothing of theirs is batched: a group would only train its seeds one after another
    jobs = [job(tmp_path, algo, seed) for algo in ("td3", "sb3-sac-ede") for seed in range(3)]
    grouped = group_jobs(jobs, 3)
    assert sorted(len(j.runs) for j in grouped) == [1, 1, 1, 3]
    assert all(j.runs[0].algo == "sb3-sac-ede" for j in grouped if len(j.runs) == 1)


def test_the_overall_line_counts_steps_and_leaves_resumed_ones_out_of_the_rate(
    tmp_path: Path,
) -> None:
    jobs = [job(tmp_path, "td3", 0), job(tmp_path, "td3", 1)]
    other = Job("collect@reacher", [["true"]], str(tmp_path), {}, str(tmp_path / "c.log"))
    tally = Tally(3)
    tally.track([other], {TASK: 1000})
    tally.track(jobs, {TASK: 1000})  # a later wave's
    assert "0/3 stages, 0/2k steps (0%)" in tally.overall()
    # The first run resumed at step 400, then did 100 more; the sweep sees it first now.
    progress_file(jobs[0]).write_text('{"done": 500, "total": 1000, "start": 400}')
    # A stage that is not a run counts in its own units, which are not environment steps.
    progress_file(other).write_text('{"done": 3, "total": 5, "start": 0}')
    tally.start = time.perf_counter() - 10.0  # 10 s into the sweep: 100 new steps, 10 steps/s
    line = tally.overall()
    assert "0/3 stages, 500/2k steps (25%)" in line, line
    assert "10 steps/s" in line, line
    assert "ETA 2m30s" in line, line  # 1,500 steps left at 10 steps/s
    finished = tally.line("ok", jobs[0].stage, "1.0s", jobs[0].stage)
    assert finished.startswith("[1/3] ok") and "ETA" in finished, finished
    assert "1/3 stages, 1k/2k steps (50%)" in tally.overall()


def test_without_step_counts_the_eta_comes_from_finished_runs(tmp_path: Path) -> None:
    tally = Tally(3)
    tally.start = time.perf_counter() - 60.0
    line = tally.line("ok", "report", "60.0s")
    assert line.startswith("[1/3]") and "ETA 2m00s" in line, line


def test_a_stage_publishes_its_progress_where_the_sweep_asks(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "run.progress"
    monkeypatch.setenv(PROGRESS_ENV, str(path))
    with progress(10, "steps", resumable=True) as advance:
        advance(2)  # the first count: what it had done before (resumed)
        assert read_progress(path) == (2, 10, 2)  # the first update is written at once
        advance(1)
        advance(7)
    assert read_progress(path) == (10, 10, 2)  # and the last whatever the time
    with progress(10, "epochs", unit="epoch") as advance:  # a stage that starts afresh
        advance(3)
    assert read_progress(path) == (3, 10, 0)
    assert read_progress(tmp_path / "none") is None
    # No temporaries and no lock: the file and its mark as a progress writer's (ede.io.atomic).
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == [".run.progress.ede-output.json", "run.progress"]


def test_a_stage_goes_on_when_its_progress_file_can_no_longer_be_written(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The progress file is for display: a write that fails midway (the disk filled) is said
    once and the file left as it was, never the stage's failure."""
    path = tmp_path / "run.progress"
    monkeypatch.setenv(PROGRESS_ENV, str(path))
    with progress(10, "steps") as advance:
        advance(2)
        monkeypatch.setattr(
            "ede_pipeline.progress.write_json",
            lambda *_: (_ for _ in ()).throw(OSError(28, "No space left on device")),
        )
        advance(8)
    assert read_progress(path) == (2, 10, 0)
    said = [line for line in capsys.readouterr().err.splitlines() if PROGRESS_ENV in line]
    assert said == [
        f"{PROGRESS_ENV}={path}: no longer kept up to date ([Errno 28] No space left on device)"
    ]


def test_the_overall_line_lives_on_a_terminal_and_ends_in_a_log(tmp_path: Path) -> None:
    """Without a terminal the line is printed at every further tenth of the steps, and last."""
    script = f"""
import time
from pathlib import Path
from ede_pipeline.sweep.execute import progress_file
from ede_pipeline.sweep.plan import Job, RunId
from ede_pipeline.sweep.tally import Tally
Tally.POLL = 0.05
job = Job(
    "t", [["ede-pipeline", "train"]], ".", {{}}, r"{tmp_path}/t.log", runs=(RunId("{TASK}", "td3", 0),)
)
tally = Tally(1)
tally.track([job], {{"{TASK}": 100}})
with tally.watch():
    for done in (10, 55, 100):
        progress_file(job).write_text('{{"done": %d, "total": 100, "start": 0}}' % done)
        time.sleep(0.3)
"""
    result = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        env={**os.environ},
        timeout=60,
        check=True,
    )
    lines = [line for line in result.stderr.splitlines() if line.startswith("sweep:")]
    assert [line.split(" steps ")[0].split(", ")[-1] for line in lines] == [
        "10/100",
        "55/100",
        "100/100",
        "100/100",
    ], result.stderr


def paper_params(**td3: str) -> Params:
    """The committed params (8 seeds), td3 as told."""
    params = read_params(Path(__file__).resolve().parents[2] / "params.yaml")
    return params.model_copy(update={"td3": params.td3.model_copy(update=td3)})


def test_on_cpu_seeds_share_a_process_while_every_job_still_gets_one() -> None:
    params = paper_params()  # 8 seeds
    seeds = len(params.runs.seeds)
    assert default_group_size(params, runs=80, workers=2) == seeds  # 40 runs a core: all 8 seeds
    assert default_group_size(params, runs=80, workers=16) == 5  # 16 processes of up to 5
    assert default_group_size(params, runs=4, workers=2) == 2
    assert default_group_size(params, runs=3, workers=16) == 1  # fewer runs than cores: alone
    assert default_group_size(params, runs=80, workers=None) == 1  # Ray, its size unknown


def test_every_schedule_and_precision_groups_alike() -> None:  # one agent: a group is any run
    assert default_group_size(paper_params(update_schedule="episode"), 80, 2) == 8
    assert default_group_size(paper_params(precision="bf16"), 80, 2) == 8


def test_the_overall_line_is_read_while_the_next_wave_is_tracked(tmp_path: Path) -> None:
    """The progress thread reads the tally (its jobs' progress and attempts files) while the
    sweep tracks a wave's jobs: neither sees the other's work half done. (A job added while the
    jobs were counted once ended `make quick`'s progress thread: "dictionary changed size during
    iteration".)"""
    jobs = [job(tmp_path, "td3", seed) for seed in range(300)]
    for each in jobs:
        progress_file(each).write_text('{"done": 10, "total": 1000, "start": 0}')
    tally = Tally(len(jobs))
    tally.track(jobs[:100], {TASK: 1000})
    reading, stop, failures = threading.Event(), threading.Event(), []

    def read() -> None:  # as the progress thread does, with a much shorter pause
        try:
            while True:
                tally.overall(), tally.retries()
                reading.set()
                if stop.wait(0.001):
                    return
        except Exception as error:  # the failure, for the assert below
            failures.append(error)

    reader = threading.Thread(target=read)
    reader.start()
    try:
        assert reading.wait(timeout=60)  # the reader at work before the next wave's jobs come
        for each in jobs[100:]:  # the next wave's, one by one
            tally.track([each], {TASK: 1000})
            time.sleep(0.001)
    finally:
        stop.set()
        reader.join()
    assert failures == [], failures
    assert "0/300 stages, 3k/300k steps (1%)" in tally.overall()


def test_damaged_progress_and_attempts_files_leave_the_overall_line_going(tmp_path: Path) -> None:
    """A progress file that holds no counts that make sense (an infinite count, JSON nested past
    Python's limit, a negative count, bytes that are not text) is read as none yet; an attempts
    file that cannot be read, as no attempt: the line goes on, and says the rest."""
    jobs = [job(tmp_path, "td3", seed) for seed in range(5)]
    damaged = [
        b'{"done": 1e400, "total": 1000, "start": 0}',
        b"[" * 100_000,
        b'{"done": -5, "total": 1000, "start": 0}',
        b"\xff\xfe\x00",
    ]
    for each, content in zip(jobs, damaged, strict=False):
        progress_file(each).write_bytes(content)
    progress_file(jobs[4]).write_text('{"done": 500, "total": 1000, "start": 0}')
    attempts_file(jobs[0]).mkdir()  # a folder where the file goes
    tally = Tally(5)
    tally.track(jobs, {TASK: 1000})
    assert "0/5 stages, 500/5k steps (10%)" in tally.overall()
    assert tally.retries() == 0


def test_a_job_that_cannot_write_its_log_fails_in_one_line(tmp_path: Path) -> None:
    """The logs folder removed and a file put in its place while the sweep runs, or a shell that
    is not there: the job is not run, and its outcome says why, as any failed job's does."""
    (tmp_path / "logs").write_text("not a folder")
    outcome = run_job(
        Job("report", [["true"]], str(tmp_path), {}, str(tmp_path / "logs" / "report.log"))
    )
    assert outcome.returncode is None and outcome.attempts == 1
    assert problem(outcome) == f"could not run ({tmp_path}/logs/report.progress: Not a directory)"
    no_shell = Job(
        "report", [["/no/such/shell", "-c", "true"]], str(tmp_path), {}, str(tmp_path / "r.log")
    )
    assert problem(run_job(no_shell)) == "could not run (/no/such/shell: No such file or directory)"


def test_an_error_in_the_overall_line_ends_the_line_not_the_sweep(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def broken(self: Tally) -> None:
        raise RuntimeError("a bug")

    monkeypatch.setattr(Tally, "POLL", 0.01)
    monkeypatch.setattr(Tally, "tick", broken)
    tally = Tally(1)
    with tally.watch():
        time.sleep(0.2)
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err, out + err
    assert out.count("the overall line stops here (RuntimeError: a bug)") == 1, out
    assert err.startswith("sweep: 0/1 stages"), err  # the last line all the same


def test_a_failed_jobs_log_is_shown_whatever_bytes_it_holds_or_if_it_is_gone(
    tmp_path: Path,
) -> None:
    log = tmp_path / "t.log"
    log.write_bytes(b"$ ede-pipeline train\nbinary \xff\xfe output\nError: it failed\n")
    assert (
        _tail(log)
        == "    | $ ede-pipeline train\n    | binary \ufffd\ufffd output\n    | Error: it failed"
    )
    assert _tail(tmp_path / "removed.log") == ""
