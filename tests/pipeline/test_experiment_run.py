"""``ede-pipeline experiment run/export``: a committed experiment file run by the sweep in its own
working copy, killed and resumed, recorded by DVC, its finished runs exported."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import yaml

from tests.faults.conftest import tiny
from tests.support import BIN, dvc, final_evaluation, ok, run, scratch_copy, tool_env

pytestmark = pytest.mark.slow

TASK = "ede/Point-v0"
EXPERIMENT = (
    "# Point at two seeds, TD3 only: a tiny experiment.\nruns:\n  algos: [td3]\n  seeds: [0, 1]\n"
)


def commit(repo: Path) -> None:
    for command in (
        ["git", "add", "-A"],
        [
            "git",
            "-c",
            "user.email=t@example.org",
            "-c",
            "user.name=t",
            "commit",
            "-qm",
            "experiments",
        ],
    ):
        subprocess.run(command, cwd=repo, check=True, capture_output=True)


@pytest.fixture(scope="module")
def repo(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A checkout at the tiny point pipeline (1,200 steps a run, a checkpoint every 400) with
    two experiments: ``two-seeds``, and ``two-seeds-lr`` (another td3.lr: new runs, the same
    family's embedding)."""
    copy = scratch_copy(tmp_path_factory.mktemp("experiment") / "repo", tiny)
    (copy / "experiments").mkdir(exist_ok=True)
    (copy / "experiments" / "two-seeds.yaml").write_text(EXPERIMENT)
    (copy / "experiments" / "two-seeds-lr.yaml").write_text(EXPERIMENT + "td3:\n  lr: 0.002\n")
    (copy / "experiments" / "bad.yaml").write_text("td3:\n  batch_size: 0\n")
    for name in ("x..y", "my exp"):  # no names (a path, a git ref, a shell word)
        (copy / "experiments" / f"{name}.yaml").write_text(EXPERIMENT)
    commit(copy)
    return copy


def experiment(repo: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return run(repo, BIN / "ede-pipeline", "experiment", *args, timeout=900)


def two_seeds_made(repo: Path) -> Path:
    """The ``two-seeds`` experiment's working copy, its runs finished: by a test before on this
    worker (the repository is the module's), or run here."""
    workspace = repo / ".dvc" / "tmp" / "experiments" / "two-seeds"
    runs = workspace / "data" / "runs" / TASK / "td3"
    if not all((runs / f"seed{seed}" / "metrics.json").exists() for seed in (0, 1)):
        ok(experiment(repo, "run", "two-seeds", "--jobs", "2"))
    return workspace


@pytest.mark.parametrize(
    ("args", "line"),
    [
        (["run", "bad"], "experiments/bad.yaml: td3.batch_size: "),
        (
            ["run", "nothing"],
            "experiment 'nothing': no experiments/nothing.yaml; the experiments "
            "are: ablation-epochs6, ablation-step, ",
        ),
        (["run", "two-seeds", "--jobs", "0"], "sweep options: Invalid value for '-j' / '--jobs'"),
        (
            ["run", "two-seeds", "--jobs", "2", "train@ede/Point-v0-td3-1"],
            "experiment two-seeds: stages (train@ede/Point-v0-td3-1) are not taken: an "
            "experiment runs all of experiments/two-seeds.yaml's runs",
        ),
        (["export", "two-seeds-lr"], "experiment two-seeds-lr: not run here yet"),
        (["run", "x..y"], "experiment 'x..y': expected a name: 1 to 64 ASCII letters"),
        (["run", "my exp"], "experiment 'my exp': expected a name: 1 to 64 ASCII letters"),
        (
            ["run", "two-seeds-lr", "--workspace-params", "--keep-code"],
            "--workspace-params and --keep-code: the code the working copy keeps runs with the "
            "params.yaml of its own commit",
        ),
    ],
)
def test_bad_input_is_one_line_and_makes_nothing(repo: Path, args: list[str], line: str) -> None:
    before = sorted(p.name for p in (repo / ".dvc").iterdir())
    result = experiment(repo, *args)
    assert result.returncode == 2, result.stderr
    assert result.stderr.startswith(f"Error: {line}"), result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert not (repo / ".dvc" / "tmp" / "experiments" / args[1]).exists()
    assert sorted(p.name for p in (repo / ".dvc").iterdir()) == before


def test_a_params_yaml_never_committed_is_one_line(tmp_path: Path) -> None:
    """An experiment's file is applied to the committed params.yaml: where there is none (no
    commit yet), one line says so and what to do, and nothing is made."""
    repo = scratch_copy(tmp_path / "repo", tiny)  # every file added, none committed
    result = experiment(repo, "run", "quick")
    assert result.returncode == 2, result.stderr
    assert result.stderr.startswith("Error: HEAD:params.yaml: fatal: "), result.stderr
    assert "; commit params.yaml (an experiment applies its file to the committed one), or " in (
        result.stderr
    )
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert not (repo / ".dvc" / "tmp").exists()


def test_a_killed_experiment_resumes_is_recorded_and_exports_its_runs(repo: Path) -> None:
    workspace = repo / ".dvc" / "tmp" / "experiments" / "two-seeds"
    command = [str(BIN / "ede-pipeline"), "experiment", "run", "two-seeds", "--jobs", "2"]
    process = subprocess.Popen(
        command,
        cwd=repo,
        env=tool_env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    runs = workspace / "data" / "runs" / TASK / "td3"
    deadline = time.monotonic() + 600
    while not list(runs.glob("seed*/checkpoint/state.json")):  # killed between checkpoints
        assert process.poll() is None and time.monotonic() < deadline, "no checkpoint was written"
        time.sleep(0.2)
    os.killpg(process.pid, signal.SIGKILL)
    process.wait()
    assert not list(runs.glob("seed*/metrics.json")), "both runs finished before the kill"

    ok(experiment(repo, "run", "two-seeds", "--jobs", "2"))
    resumed = [
        json.loads((runs / f"seed{s}" / "metrics.json").read_text())["resumed_from_step"]
        for s in (0, 1)
    ]
    assert any(step is not None and step > 0 for step in resumed), resumed
    # The workspace keeps this checkout's params and code; the experiment's changes on top.
    params = yaml.safe_load((workspace / "params.yaml").read_text())
    assert params["runs"]["seeds"] == [0, 1] and params["runs"]["algos"] == ["td3"]
    assert (workspace / "ede" / "method" / "td3.py").read_bytes() == (
        repo / "ede" / "method" / "td3.py"
    ).read_bytes()

    listed = dvc(repo, "exp", "show", "--json")
    assert listed.returncode == 0, listed.stderr
    shown = json.loads(listed.stdout)
    saved = {
        rev.get("name"): rev
        for commit_ in shown
        for exp in commit_.get("experiments") or []
        for rev in exp.get("revs") or []
    }
    assert "two-seeds" in saved
    metrics = saved["two-seeds"]["data"]["metrics"]["data/report-metrics.json"]["data"]
    assert metrics[TASK]["td3"]["seeds"] == 2

    out = repo / "published"
    ok(experiment(repo, "export", "two-seeds", "--to", str(out)))
    for seed in (0, 1):
        for name in ("eval.csv", "diagnostics.csv", "run.json", "metrics.json"):
            published = out / TASK / "td3" / f"seed{seed}" / name
            assert published.read_bytes() == (runs / f"seed{seed}" / name).read_bytes()
        assert not (out / TASK / "td3" / f"seed{seed}" / "policy").exists()
    source = json.loads((out / TASK / "source.json").read_text())
    made = json.loads((runs / "seed0" / "run.json").read_text())
    assert source == {
        "experiment": "experiments/two-seeds.yaml",
        "commit": made["code"]["commit"],
        "seeds": [0, 1],
    }

    drawn = ok(
        run(
            repo,
            BIN / "ede-pipeline",
            "results",
            "--runs",
            out,
            "--figures",
            repo / "figures",
            timeout=600,
        )
    )
    assert f"### {TASK}" in drawn and "experiment `experiments/two-seeds.yaml`" in drawn
    assert f"{made['machine']['cpu']} (" in drawn and ": 2" in drawn  # the CPU of both runs
    assert (repo / "figures" / "point.png").is_file()


def test_an_experiment_runs_the_commits_params_whatever_the_workspaces_hold(repo: Path) -> None:
    """The README's path, `make quick` then `dvc exp apply quick` then another experiment, leaves
    other params in the workspace's params.yaml: an experiment applies its file to the commit's
    params.yaml all the same, says in one line that the workspace's differs and is not used, and
    `experiment show` shows it changed what its file changes, against that commit."""
    two_seeds_made(repo)
    params = repo / "params.yaml"
    committed = params.read_text()
    edited = yaml.safe_load(committed)
    edited["td3"].update(lr=0.005, hidden=[32, 32])  # as `dvc exp apply` of another leaves it
    params.write_text(yaml.safe_dump(edited))
    try:
        again = experiment(repo, "run", "two-seeds", "--jobs", "2")
    finally:
        params.write_text(committed)
    ok(again)
    said = [line for line in again.stderr.splitlines() if "params.yaml" in line]
    assert said == [
        "experiment two-seeds: this checkout's params.yaml differs from its commit's (td3.hidden, "
        "td3.lr) and is not used: the experiment runs with the commit's (--workspace-params: "
        "with this one)"
    ], said
    assert re.search(r"sweep: 0 of \d+ stages out of date", again.stderr), again.stderr[-3000:]
    workspace = repo / ".dvc" / "tmp" / "experiments" / "two-seeds"
    ran = (workspace / "params.yaml").read_text()
    assert ran.startswith("# experiments/two-seeds.yaml applied to its commit's params.yaml")
    assert yaml.safe_load(ran)["td3"] == yaml.safe_load(committed)["td3"]
    blocks = ok(experiment(repo, "show")).split("\n\n")
    (shown,) = [block for block in blocks if block.startswith("two-seeds  (")]
    assert "runs.seeds: " in shown and "td3." not in shown, shown


def test_experiments_of_one_family_share_its_embedding(repo: Path) -> None:
    store = repo.parent / "ede-store"  # .dvc/config's remote, ../ede-store from the checkout
    two_seeds_made(repo)  # run again, it runs nothing, and pushes
    first = ok(experiment(repo, "run", "two-seeds", "--jobs", "2", "--push"))
    assert "Running stage" not in first
    assert len([p for p in store.rglob("*") if p.is_file()]) > 10  # its outputs, in the store
    second = ok(experiment(repo, "run", "two-seeds-lr", "--jobs", "2"))
    for stage in ("collect@point", "pretrain_encoder@point", "pretrain_decoder@point"):
        assert f"Running stage '{stage}'" not in second, second[-3000:]
    workspace = repo / ".dvc" / "tmp" / "experiments" / "two-seeds-lr"
    run_json = json.loads((workspace / "data/runs" / TASK / "td3/seed1/run.json").read_text())
    assert run_json["params"]["td3"]["lr"] == 0.002


def test_a_changed_code_keeps_finished_runs_unless_told(repo: Path) -> None:
    """Running an experiment again after its runs' code changed is refused while runs have
    finished (DVC would run them again); --keep-code finishes it with the code they were made
    with and the params of that code's commit (a key added here since is one that code does not
    know), --update-code runs them again with the checkout's (and --workspace-params with the
    workspace's uncommitted params)."""
    (repo / "experiments" / "one-seed.yaml").write_text(
        "# Point at one seed, TD3 only.\nruns:\n  algos: [td3]\n  seeds: [0]\n"
    )
    commit(repo)
    ok(experiment(repo, "run", "one-seed", "--jobs", "1"))
    workspace = repo / ".dvc" / "tmp" / "experiments" / "one-seed"
    finished = workspace / "data" / "runs" / TASK / "td3" / "seed0"
    made = (finished / "metrics.json").read_bytes()
    code, params = repo / "ede" / "method" / "td3.py", repo / "params.yaml"
    original, committed = code.read_bytes(), params.read_text()
    try:  # the module's checkout, as the tests after this one on its worker expect it
        _change_code_then_run(repo, workspace, finished, made)
    finally:
        code.write_bytes(original)
        params.write_text(committed)


def _change_code_then_run(repo: Path, workspace: Path, finished: Path, made: bytes) -> None:
    code = repo / "ede" / "method" / "td3.py"
    original = code.read_bytes()
    code.write_bytes(original + b"\n# edited after the run\n")  # not committed: it counts
    params = repo / "params.yaml"
    base = yaml.safe_load(params.read_text())
    params.write_text(yaml.safe_dump({**base, "td3": {**base["td3"], "lr": 0.005}}))

    refused = experiment(repo, "run", "one-seed", "--jobs", "1")
    assert refused.returncode == 2, refused.stderr
    assert refused.stderr.startswith(
        "Error: experiment one-seed: code its finished runs depend on changed here "
        "(ede/method/td3.py), and DVC would run them (1) again; --keep-code "
    ), refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1, refused.stderr
    assert (workspace / "ede" / "method" / "td3.py").read_bytes() == original
    assert (finished / "metrics.json").read_bytes() == made

    kept = ok(experiment(repo, "run", "one-seed", "--keep-code", "--jobs", "1"))
    assert re.search(r"sweep: 0 of \d+ stages out of date", kept), kept[-3000:]
    assert "this checkout's params.yaml differs from its commit's (td3.lr) and is not used" in kept
    assert (workspace / "ede" / "method" / "td3.py").read_bytes() == original
    assert (finished / "metrics.json").read_bytes() == made

    again = ok(
        experiment(repo, "run", "one-seed", "--update-code", "--workspace-params", "--jobs", "1")
    )
    assert "is not used" not in again
    # The run, and the report made from it.
    assert re.search(r"sweep: 2 of \d+ stages out of date", again), again[-3000:]
    assert (workspace / "ede" / "method" / "td3.py").read_bytes() == code.read_bytes()
    assert json.loads((finished / "run.json").read_text())["params"]["td3"]["lr"] == 0.005
    assert json.loads((finished / "run.json").read_text())["code"]["modified"] is True


def test_one_experiment_runs_once_at_a_time(repo: Path) -> None:
    """A second ``experiment run`` of an experiment that runs is refused in one line before it
    touches the working copy (it once rewrote it and left its dvc.lock empty)."""
    from ede.io.locks import exclusive

    workspace = repo / ".dvc" / "tmp" / "experiments" / "two-seeds"
    before = sorted(str(p) for p in workspace.parent.rglob("*")) if workspace.exists() else []
    with exclusive(workspace):  # as a first run holds it
        second = experiment(repo, "run", "two-seeds", "--jobs", "1")
    assert second.returncode == 2, second.stderr
    lines = second.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: experiment two-seeds: "), lines
    assert "being written by process" in lines[0]
    after = sorted(str(p) for p in workspace.parent.rglob("*")) if workspace.exists() else []
    assert [p for p in after if not p.endswith(".two-seeds.lock")] == before


def _entry_replaced(lock: Path) -> None:
    records = yaml.safe_load(lock.read_text())
    records["stages"]["collect@point"] = 5
    lock.write_text(yaml.safe_dump(records))


@pytest.mark.parametrize(
    ("damage", "problem"),
    [
        (lambda lock: lock.write_text(""), "empty"),  # a kill while DVC wrote it
        (
            _entry_replaced,
            "not what DVC expects: stages.collect@point: expected a dictionary",
        ),
    ],
    ids=["empty", "an entry replaced"],
)
def test_a_damaged_dvc_lock_in_the_working_copy_is_removed_and_the_runs_restored(
    repo: Path, damage, problem: str
) -> None:
    """A working copy's dvc.lock DVC cannot read (a kill while DVC wrote it can leave it empty;
    an entry of it replaced) is said in one line and removed by the next run, and DVC restores
    the finished runs from its run cache."""
    workspace = two_seeds_made(repo)
    finished = workspace / "data" / "runs" / TASK / "td3" / "seed1" / "metrics.json"
    made = finished.read_bytes()
    damage(workspace / "dvc.lock")
    again = experiment(repo, "run", "two-seeds", "--jobs", "2")
    assert again.returncode == 0, again.stderr[-3000:]
    said = [line for line in again.stderr.splitlines() if "dvc.lock" in line]
    assert said == [
        f"experiment two-seeds: its working copy's dvc.lock was damaged ({problem}) and is "
        "removed; DVC restores the finished runs from its run cache"
    ], said
    assert "Traceback" not in again.stderr
    assert "Running stage" not in again.stdout + again.stderr  # restored, not trained again
    assert finished.read_bytes() == made


@pytest.mark.parametrize(
    ("name", "content", "line"),
    [
        ("dvc.yaml", "stages: {{{\n", "dvc.yaml: not YAML (line 2: "),
        ("dvc.yaml", "stages: 5\n", "dvc.yaml: not what DVC expects: stages: expected a "),
        ("dvc.yaml", "", "dvc.yaml: no stages; mend it ("),
        ("dvc.yaml", None, "dvc.yaml: not a file; mend it ("),
        (
            "dvc.lock",
            "schema: '2.0'\nstages:\n  collect@point: 5\n",
            "dvc.lock: not what DVC expects: stages.collect@point: expected a dictionary; "
            "remove it: DVC then restores",
        ),
    ],
    ids=["not YAML", "a wrong type", "empty", "a folder", "an entry of dvc.lock replaced"],
)
def test_a_damaged_dvc_yaml_or_dvc_lock_here_is_one_line_and_makes_nothing(
    repo: Path, name: str, content: str | None, line: str
) -> None:
    """The checkout's dvc.yaml or dvc.lock that DVC cannot read: one line naming it and how to
    mend it, before the experiment's working copy is made; the file is left as it is."""
    (repo / "experiments" / "untouched.yaml").write_text(EXPERIMENT)
    damaged = repo / name
    kept = damaged.read_bytes() if damaged.is_file() else None
    damaged.unlink(missing_ok=True)
    try:
        if content is None:
            damaged.mkdir()
        else:
            damaged.write_text(content)
        refused = experiment(repo, "run", "untouched", "--jobs", "1")
        assert content is None or damaged.read_text() == content
    finally:
        if damaged.is_dir():
            shutil.rmtree(damaged)
        damaged.unlink(missing_ok=True)
        if kept is not None:
            damaged.write_bytes(kept)
        (repo / "experiments" / "untouched.yaml").unlink()
    assert refused.returncode == 2, refused.stderr
    assert refused.stderr.startswith(f"Error: {line}"), refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1, refused.stderr
    assert not (repo / ".dvc" / "tmp" / "experiments" / "untouched").exists()


def test_make_quick_runs_the_quick_look_as_an_experiment_with_no_warning(tmp_path: Path) -> None:
    """A newcomer's first command on a fresh clone: `make quick` runs experiments/quick.yaml (here
    at the tiny point pipeline's size) through `experiment run`, saved as the DVC experiment
    `quick` that `experiment show` lists and `dvc exp apply quick` brings into the workspace, and
    prints no warning a newcomer cannot act on (`dvc exp run --temp` once printed 140, one per
    output dvc.lock names that a fresh clone's cache lacks)."""
    repo = scratch_copy(tmp_path / "repo", tiny)
    (repo / "experiments" / "quick.yaml").write_text("# The quick look, tiny.\ntd3:\n  lr: 0.002\n")
    commit(repo)
    installed = BIN.parent  # the suite's environment: `make` finds it installed
    made = ok(run(repo, "make", "quick", f"VENV={installed}", timeout=900))
    warned = [line for line in made.splitlines() if "warn" in line.lower()]
    assert warned == [], warned[:5]
    # No traceback either (the sweep's progress thread once printed one): neither its header
    # nor an exception's line.
    assert "Traceback (most recent call last)" not in made, made[-3000:]
    raised = re.findall(r"^\s*(?:\w+\.)*\w+(?:Error|Exception)\b.*$", made, re.MULTILINE)
    assert raised == [], raised[:5]
    assert "experiment run quick --update-code" in made  # one way to run an experiment
    for algo in ("td3", "ede-td3"):
        assert (repo / ".dvc/tmp/experiments/quick/data/runs" / TASK / algo / "seed0").is_dir()

    assert "quick  (" in ok(experiment(repo, "show"))
    assert not (repo / "data" / "report" / "index.html").exists()
    ok(dvc(repo, "exp", "apply", "quick"))
    assert (repo / "data" / "report" / "index.html").is_file()
    assert yaml.safe_load((repo / "params.yaml").read_text())["td3"]["lr"] == 0.002
    # The README's next step, an experiment run with the quick look's params in the workspace:
    # it runs the commit's, and says so.
    again = ok(run(repo, "make", "quick", f"VENV={installed}", timeout=900))
    assert "this checkout's params.yaml differs from its commit's (td3.lr) and is not used" in again
    assert re.search(r"sweep: 0 of \d+ stages out of date", again), again[-3000:]


def test_an_export_with_policies_publishes_what_render_plays(repo: Path) -> None:
    """`experiment export --policies` publishes each run's final policy, and the decoder (not
    the encoder) its EDE-TD3 runs act through; `render` plays a published EDE-TD3 run from what
    is published beside it alone, as the run's final evaluation played it."""
    (repo / "experiments" / "both.yaml").write_text(
        "# Point at one seed, both algorithms.\nruns:\n  seeds: [0]\n"
    )
    commit(repo)
    ok(experiment(repo, "run", "both", "--jobs", "2"))
    out = repo / "clips"
    ok(experiment(repo, "export", "both", "--to", str(out), "--policies"))
    for algo in ("td3", "ede-td3"):
        assert (out / TASK / algo / "seed0" / "policy" / "policy.safetensors").is_file()
    published = out / TASK / "ede-td3" / "seed0"
    made = json.loads((published / "run.json").read_text())
    kept = out / TASK / "embedding" / made["embedding"][:12]
    assert (kept / "decoder" / "weights.safetensors").is_file() and not (kept / "encoder").exists()
    assert not (repo / "data" / "families").exists()  # no pipeline embedding to fall back on

    played = ok(run(repo, BIN / "ede-pipeline", "render", published,
                    "--out", repo / "clip.gif", timeout=300))  # fmt: skip
    # Its first episode as the run's final evaluation played it (3 episodes, replayed without
    # frames: their mean the one recorded), as in test_train.py's render test.
    evaluation = final_evaluation(published, repo / "params.yaml", 3)
    last = (published / "eval.csv").read_text().strip().splitlines()[-1].split(",")
    assert abs(np.mean(evaluation) - float(last[2])) < 0.01, (evaluation, last)
    first = float(played.split("; returns ")[1].split(" (mean")[0])
    assert abs(first - evaluation[0]) < 0.01, (played, evaluation)

    # A results page's clip of the folder: TD3 beside EDE-TD3, a GIF beside the page.
    page = repo / "clips.md"
    page.write_text(f"# Clips\n\n<!-- results clips: Clip: {TASK} -->\n<!-- /results -->\nEnd.\n")
    ok(run(repo, BIN / "ede-pipeline", "results", "--pages", page, timeout=300))
    text = page.read_text()
    gif = repo / f"clip-{TASK.replace('/', '_')}.gif"
    assert f"![{TASK}: TD3 (left) beside EDE-TD3 (right), seed 0]({gif.name})" in text
    finals = [
        float((out / TASK / algo / "seed0" / "eval.csv").read_text().split()[-1].split(",")[2])
        for algo in ("td3", "ede-td3")
    ]
    assert f"the final evaluation's mean: {finals[0]:.1f} and {finals[1]:.1f}." in text
    assert text.startswith("# Clips\n\n") and text.endswith("<!-- /results -->\nEnd.\n")
    clip = iio.imread(gif, index=None)
    assert clip.shape[:3] == (50, 240, 480)  # 100 steps, every other frame; two half-size halves
    assert np.abs(clip[0].astype(int) - clip[-1].astype(int)).max() > 50  # the points moved
