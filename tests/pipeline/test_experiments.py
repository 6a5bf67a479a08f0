"""``ede-pipeline experiment show``: DVC's experiments, each as a block that fits 80 columns."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
import yaml
from click.testing import CliRunner

from tests.support import tool_env
from ede_pipeline.cli import main
from ede_pipeline.experiments import WIDTH, experiment_blocks

TASK = "ede/ReacherVertical-v0"

# A stage that writes the report's metrics in the report's layout from two params, and a second
# metrics file, so that DVC prefixes metric columns with their file as it does in dvc.yaml.
STAGE = """
import json, yaml
p = yaml.safe_load(open("params.yaml"))
lr, seeds = p["td3"]["lr"], p["runs"]["seeds"]
metrics = {
    "ede/ReacherVertical-v0": {
        "td3": {"final_return": -1000 * lr, "auc": -2000 * lr, "seeds": len(seeds)},
        "ede-td3": {"final_return": -500 * lr, "auc": -1500 * lr, "seeds": len(seeds)},
    },
    "missing_runs": 0,
    "across_tasks": {"tasks": ["ede/ReacherVertical-v0"], "task_count": 1,
                     "runs_per_task": {"ede-td3": len(seeds), "td3": len(seeds)},
                     "final_return": {"probability_of_improvement":
                                      {"value": 0.75, "low": 0.5, "high": 1.0}},
                     "auc": {"probability_of_improvement": {"value": 0.5, "low": 0.25, "high": 0.75}}},
}
json.dump(metrics, open("data/report-metrics.json", "w"))
json.dump({"r2": 0.5}, open("data/other.json", "w"))
"""


def git(repo: Path, *args: str) -> None:
    subprocess.run(["git", *args], cwd=repo, check=True, capture_output=True)


@pytest.fixture(scope="module")
def repo(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("experiments")
    git(root, "init", "-q")
    git(root, "config", "user.email", "test@example.org")
    git(root, "config", "user.name", "test")
    (root / "data").mkdir()
    (root / "data" / ".gitkeep").write_text("")
    (root / "params.yaml").write_text(yaml.safe_dump(
        {"td3": {"lr": 0.001, "batch_size": 100}, "runs": {"seeds": [0, 1]}}))
    (root / "stage.py").write_text(STAGE)
    (root / "dvc.yaml").write_text(yaml.safe_dump({"stages": {"report": {
        "cmd": "python stage.py",
        "deps": ["stage.py"],
        "params": ["td3.lr", "td3.batch_size", "runs.seeds"],
        "metrics": [{"data/report-metrics.json": {"cache": False}},
                    {"data/other.json": {"cache": False}}],
    }}}))
    env = tool_env()
    subprocess.run(["dvc", "init", "-q"], cwd=root, check=True, env=env)
    git(root, "add", "-A")
    git(root, "commit", "-qm", "base")
    for name, overrides in [("smaller-lr", ["td3.lr=0.0003"]),
                            ("three-seeds", ["runs.seeds=[0,1,2]", "td3.batch_size=256"])]:
        sets = [arg for override in overrides for arg in ("-S", override)]
        args = ["dvc", "exp", "run", "--temp", "--name", name, *sets]
        subprocess.run(args, cwd=root, check=True, env=env, capture_output=True)
    return root


def test_each_experiment_shows_its_changes_and_returns_in_80_columns(repo: Path,
                                                                     monkeypatch) -> None:
    monkeypatch.chdir(repo)
    result = CliRunner().invoke(main, ["experiment", "show"])
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert all(len(line) <= WIDTH for line in lines), [line for line in lines if len(line) > WIDTH]
    blocks = {block.splitlines()[0].split()[0]: block for block in result.output.split("\n\n")}
    assert set(blocks) == {"smaller-lr", "three-seeds"}

    smaller = blocks["smaller-lr"]
    assert "td3.lr: 0.001 → 0.0003" in smaller and "batch_size" not in smaller
    row = next(line for line in smaller.splitlines() if TASK in line).split()
    # final and AUC of TD3, then of EDE-TD3, then the seeds of each
    assert row[1:] == ["-0.30", "-0.60", "-0.15", "-0.45", "2/2"]
    assert "  P(EDE-TD3 > TD3), 1 task: final 0.75 [0.50, 1.00]; AUC 0.50 [0.25, 0.75]" in smaller

    three = blocks["three-seeds"]
    assert "td3.batch_size: 100 → 256" in three and "runs.seeds: [0, 1] → [0, 1, 2]" in three
    assert next(line for line in three.splitlines() if TASK in line).split()[-1] == "3/3"


def test_an_experiment_without_a_report_says_so() -> None:
    def entry(rev: str, name: str, lr: float, metrics: dict) -> dict:
        return {"rev": rev, "name": name, "error": None, "data": {
            "params": {"params.yaml": {"data": {"td3": {"lr": lr}}}}, "metrics": metrics}}

    missing = {"data/report-metrics.json": {"error": {"type": "FileNotFoundError"}}}
    commit = entry("0123456789", "main", 0.001, missing)
    commit["experiments"] = [{"revs": [entry("abc1234567", "no-report", 0.002, missing)]}]
    assert experiment_blocks([entry("workspace", None, 0.1, {}), commit]) == [
        "no-report  (abc1234, from main)", "  changed: td3.lr: 0.001 → 0.002", "  no report yet",
    ]
    assert experiment_blocks([{**commit, "experiments": None}]) == []


def test_every_committed_experiment_is_valid_params_and_learns_only_what_it_uses(
    monkeypatch: pytest.MonkeyPatch
) -> None:
    from ede_pipeline.experiments import EXPERIMENTS, experiment_params
    from tests.support import REPO

    monkeypatch.chdir(REPO)
    names = sorted(p.stem for p in (REPO / EXPERIMENTS).glob("*.yaml"))
    assert "reacher-vertical" in names
    for name in names:
        params = experiment_params(name)
        families = set(params["runs"]["tasks"].values()) | {
            params["report"][k] for k in ("effect_space_family", "exploration_family")} - {None}
        assert set(params["families"]) == families, name
        first = (REPO / EXPERIMENTS / f"{name}.yaml").read_text().splitlines()[0]
        assert first.startswith("# "), f"{name}: its first line says what it is"


def test_every_published_run_was_made_with_its_experiments_params(
    monkeypatch: pytest.MonkeyPatch
) -> None:
    """A task folder of docs/results/ whose source.json names an experiment file holds runs of
    exactly that file's params (its runs' run.json identities), so the file reproduces them."""
    from ede.config import Params
    from ede.runs import RunSpec, identity_difference
    from ede_pipeline.experiments import experiment_params
    from tests.support import REPO

    monkeypatch.chdir(REPO)
    checked = 0
    for source in sorted((REPO / "docs" / "results").rglob("source.json")):
        made = json.loads(source.read_text())
        if "experiment" not in made:
            continue
        params = Params.model_validate(experiment_params(Path(made["experiment"]).stem))
        assert made["seeds"] == params.runs.seeds, source
        for record in sorted(source.parent.glob("*/seed*/run.json")):
            run = json.loads(record.read_text())
            spec = RunSpec(run["task"], run["algo"], run["seed"], params.runs.budgets[run["task"]],
                           params.td3, params.ede_td3)
            expected = {k: v for k, v in spec.identity().items() if k != "embedding"}
            assert identity_difference(run, expected) is None, (record, identity_difference(run, expected))
            assert run["algo"] in params.runs.algos and run["seed"] in params.runs.seeds, record
            checked += 1
    assert checked >= 80  # the 80 runs published when this test was written, and any since


def test_export_publishes_the_finished_runs_of_each_task_and_skips_a_task_with_none(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import torch

    from ede.config import load_params
    from ede.runs import RunSpec, write_curves, write_finished
    from ede_pipeline import layout
    from tests.support import REPO

    monkeypatch.chdir(tmp_path)
    (tmp_path / "experiments").mkdir()
    (tmp_path / "experiments" / "two-tasks.yaml").write_text("# two tasks\n")
    workspace = tmp_path / ".dvc" / "tmp" / "experiments" / "two-tasks"
    workspace.mkdir(parents=True)
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    params["runs"].update(tasks={"ede/ReacherVertical-v0": "reacher", "ede/ReacherTurn-v0": "reacher"},
                          algos=["td3"], seeds=[0, 1])
    params["report"]["thresholds"] = {"ede/ReacherVertical-v0": [-15, -10]}
    (workspace / "params.yaml").write_text(yaml.safe_dump(params))
    loaded = load_params(workspace / "params.yaml")
    budget = loaded.runs.budgets["ede/ReacherVertical-v0"]
    for seed in (0, 1):  # ReacherVertical's two runs finished; ReacherTurn's none
        out = workspace / layout.run("ede/ReacherVertical-v0", "td3", seed)
        out.mkdir(parents=True)
        write_curves(out, [{"step": s, "episode": 0, "mean_return": -9.0, "std_return": 0.0,
                            "wall_seconds": 0.0} for s in (0, budget)], [])
        spec = RunSpec("ede/ReacherVertical-v0", "td3", seed, budget, loaded.td3, loaded.ede_td3)
        write_finished(out, spec, {"final_return": -9.0}, torch.device("cpu"))
    result = CliRunner().invoke(main, ["experiment", "export", "two-tasks", "--to", "published"])
    assert result.exit_code == 0, result.output
    assert "ede/ReacherTurn-v0: no run finished yet; nothing exported" in result.stderr
    source = json.loads((tmp_path / "published/ede/ReacherVertical-v0/source.json").read_text())
    assert source["experiment"] == "experiments/two-tasks.yaml" and source["seeds"] == [0, 1]
    assert source["thresholds"] == [-15, -10]
    assert sorted(p.name for p in (tmp_path / "published/ede/ReacherVertical-v0/td3").iterdir()) \
        == ["seed0", "seed1"]
    assert not (tmp_path / "published/ede/ReacherTurn-v0").exists()
