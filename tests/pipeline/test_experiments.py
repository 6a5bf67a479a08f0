"""``ede-pipeline experiment show``: DVC's experiments, each as a block that fits 80 columns."""

from __future__ import annotations

import json
import shutil
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml
from click.testing import CliRunner

from ede.config import Algo
from ede.io.atomic import sha256
from ede.run.runs import POLICY
from ede_pipeline.cli import main
from ede_pipeline.experiments.show import WIDTH, experiment_blocks
from tests.support import REPO, tool_env

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
    (root / "params.yaml").write_text(
        yaml.safe_dump({"td3": {"lr": 0.001, "batch_size": 100}, "runs": {"seeds": [0, 1]}})
    )
    (root / "stage.py").write_text(STAGE)
    (root / "dvc.yaml").write_text(
        yaml.safe_dump(
            {
                "stages": {
                    "report": {
                        "cmd": "python stage.py",
                        "deps": ["stage.py"],
                        "params": ["td3.lr", "td3.batch_size", "runs.seeds"],
                        "metrics": [
                            {"data/report-metrics.json": {"cache": False}},
                            {"data/other.json": {"cache": False}},
                        ],
                    }
                }
            }
        )
    )
    env = tool_env()
    subprocess.run(["dvc", "init", "-q"], cwd=root, check=True, env=env)
    git(root, "add", "-A")
    git(root, "commit", "-qm", "base")
    for name, overrides in [
        ("smaller-lr", ["td3.lr=0.0003"]),
        ("three-seeds", ["runs.seeds=[0,1,2]", "td3.batch_size=256"]),
    ]:
        sets = [arg for override in overrides for arg in ("-S", override)]
        args = ["dvc", "exp", "run", "--temp", "--name", name, *sets]
        subprocess.run(args, cwd=root, check=True, env=env, capture_output=True)
    return root


def test_each_experiment_shows_its_changes_and_returns_in_80_columns(
    repo: Path, monkeypatch
) -> None:
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
    def entry(rev: str, name: str | None, lr: float, metrics: dict, figure: str | None) -> dict:
        params = {"td3": {"lr": lr}, "report": {"effect_space_family": figure}}
        return {
            "rev": rev,
            "name": name,
            "error": None,
            "data": {"params": {"params.yaml": {"data": params}}, "metrics": metrics},
        }

    missing = {"data/report-metrics.json": {"error": {"type": "FileNotFoundError"}}}
    commit = entry("0123456789", "main", 0.001, missing, "point")
    commit["experiments"] = [{"revs": [entry("abc1234567", "no-report", 0.002, missing, None)]}]
    assert experiment_blocks([entry("workspace", None, 0.1, {}, "point"), commit]) == [
        "no-report  (abc1234, from main)",
        "  changed: td3.lr: 0.001 → 0.002; report.effect_space_family: point → null",
        "  no report yet",
    ]
    assert experiment_blocks([{**commit, "experiments": None}]) == []


def test_every_committed_experiment_is_valid_params_and_learns_only_what_it_uses(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from ede_pipeline.experiments.workspace import EXPERIMENTS, experiment_params
    from tests.support import REPO

    monkeypatch.chdir(REPO)
    names = sorted(p.stem for p in (REPO / EXPERIMENTS).glob("*.yaml"))
    assert "reacher-vertical" in names
    for name in names:
        params = experiment_params(name)
        families = set(params["runs"]["tasks"].values()) | {
            params["report"][k] for k in ("effect_space_family", "exploration_family")
        } - {None}
        assert set(params["families"]) == families, name
        first = (REPO / EXPERIMENTS / f"{name}.yaml").read_text().splitlines()[0]
        assert first.startswith("# "), f"{name}: its first line says what it is"


def test_every_published_run_was_made_with_its_experiments_params(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A task folder of docs/results/ whose source.json names an experiment file holds runs of
    exactly that file's params (its runs' run.json identities), so the file reproduces them;
    where its seeds came from several experiments, each part's seeds of that part's file."""
    from ede.config import Params
    from ede_pipeline.experiments.workspace import experiment_params
    from tests.support import REPO

    monkeypatch.chdir(REPO)
    checked = 0
    for source in sorted((REPO / "docs" / "results").rglob("source.json")):
        parts = json.loads(source.read_text())
        parts = parts if isinstance(parts, list) else [parts]
        named = {seed for made in parts for seed in made["seeds"]}
        ran = {json.loads(r.read_text())["seed"] for r in source.parent.glob("*/seed*/run.json")}
        assert ran <= named, (source, sorted(ran - named))  # every run is some part's
        for made in parts:
            if "experiment" not in made:
                continue
            params = Params.model_validate(experiment_params(Path(made["experiment"]).stem))
            assert made["seeds"] == params.runs.seeds, source
            checked += _check_runs(source.parent, params, made["seeds"])
    assert checked >= 80  # the 80 runs published when this test was written, and any since


def _check_runs(folder: Path, params, seeds: list[int]) -> int:
    """Each run of ``seeds`` in ``folder`` has the identity ``params`` give it; how many. An
    algorithm's folder that is a link (the published TD3 runs beside stable-baselines3's arms,
    docs/results/any-agent/) holds another experiment's runs, checked where they lie."""
    from ede.run.spec import RunSpec, identity_difference

    checked = 0
    for record in sorted(folder.glob("*/seed*/run.json")):
        if record.parent.parent.is_symlink():
            continue
        run = json.loads(record.read_text())
        if run["seed"] in seeds:
            spec = RunSpec(
                run["task"],
                run["algo"],
                run["seed"],
                params.runs.budgets[run["task"]],
                params.td3,
                params.ede_td3,
            )
            expected = {k: v for k, v in spec.identity().items() if k != "embedding"}
            assert identity_difference(run, expected) is None, (
                record,
                identity_difference(run, expected),
            )
            assert run["algo"] in params.runs.algos, record
            checked += 1
    return checked


def finished_workspace(
    root: Path,
    name: str,
    seeds: list[int],
    algos: list[Algo],
    tasks: tuple[str, ...] = ("ede/ReacherVertical-v0",),
    finished: tuple[str, ...] = ("ede/ReacherVertical-v0",),
    embedding: str = "e0" * 32,
    td3: dict[str, Any] | None = None,
    policies: bool = False,
) -> Path:
    """``experiments/NAME.yaml`` and its working copy as ``experiment run`` leaves it: the runs
    of ``seeds`` finished on the ``finished`` tasks (none yet on the rest of ``tasks``), their
    EDE-TD3 runs made with the embedding of checksum ``embedding``, whose metrics are the reacher
    family's, and the params.yaml's td3 keys changed as ``td3`` says; with ``policies``, each
    run's policy/ (its policy.safetensors ``<algo> <seed>``), marked as a run writes it."""
    import torch

    from ede.config import load_params
    from ede.io.atomic import write_atomically
    from ede.run.runs import write_curves, write_finished
    from ede.run.spec import RunSpec
    from ede_pipeline import layout
    from tests.support import REPO

    (root / "experiments").mkdir(exist_ok=True)
    (root / "experiments" / f"{name}.yaml").write_text(f"# {name}\n")
    workspace = root / ".dvc" / "tmp" / "experiments" / name
    workspace.mkdir(parents=True)
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    params["runs"].update(tasks={task: "reacher" for task in tasks}, algos=algos, seeds=seeds)
    params["runs"]["budgets"] = {task: params["runs"]["budgets"][task] for task in tasks}
    params["report"]["thresholds"] = {"ede/ReacherVertical-v0": [-15, -10]}
    params["td3"].update(td3 or {})
    (workspace / "params.yaml").write_text(yaml.safe_dump(params))
    loaded = load_params(workspace / "params.yaml")
    metrics = workspace / layout.embedding("reacher")
    metrics.mkdir(parents=True)
    for part in ("encoder", "decoder"):
        (metrics / f"{part}_metrics.json").write_text(json.dumps({"of": [part, embedding]}))
    for task, algo, seed in ((t, a, s) for t in finished for a in algos for s in seeds):
        out = workspace / layout.run(task, algo, seed)
        out.mkdir(parents=True)
        budget = loaded.runs.budgets[task]
        write_curves(
            out,
            [
                {
                    "step": s,
                    "episode": 0,
                    "mean_return": -9.0,
                    "std_return": 0.0,
                    "wall_seconds": s + seed + (algo == "ede-td3") / 2,  # each run's own
                }
                for s in (0, budget)
            ],
            [],
        )
        spec = RunSpec(
            task,
            algo,
            seed,
            budget,
            loaded.td3,
            loaded.ede_td3,
            embedding if algo == "ede-td3" else "",
        )
        if policies:
            write_atomically(out / POLICY, policy_of(f"{algo} {seed}"), "policy")
        write_finished(out, spec, {"final_return": -9.0}, torch.device("cpu"))
    return workspace


def policy_of(text: str) -> Callable[[Path], object]:
    """What writes a policy/ holding ``text`` as its policy.safetensors (for ``write_atomically``)."""
    return lambda tmp: (tmp / "policy.safetensors").write_text(text)


def export(name: str) -> Any:
    return CliRunner().invoke(main, ["experiment", "export", name, "--to", "published"])


def test_export_publishes_the_finished_runs_of_each_task_and_skips_a_task_with_none(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    finished_workspace(
        tmp_path,
        "two-tasks",
        [0, 1],
        ["td3"],
        tasks=("ede/ReacherVertical-v0", "ede/ReacherTurn-v0"),
    )
    result = export("two-tasks")
    assert result.exit_code == 0, result.output
    assert "ede/ReacherTurn-v0: no run finished yet; nothing exported" in result.stderr
    source = json.loads((tmp_path / "published/ede/ReacherVertical-v0/source.json").read_text())
    assert source["experiment"] == "experiments/two-tasks.yaml" and source["seeds"] == [0, 1]
    assert source["thresholds"] == [-15, -10]
    assert sorted(
        p.name for p in (tmp_path / "published/ede/ReacherVertical-v0/td3").iterdir()
    ) == ["seed0", "seed1"]
    assert not (tmp_path / "published/ede/ReacherVertical-v0/embedding").exists()  # no EDE-TD3
    assert not (tmp_path / "published/ede/ReacherTurn-v0").exists()


def test_an_experiment_adding_seeds_exports_beside_the_published_ones(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Seeds 0–1 from one experiment, 2–3 from another with its own embedding: one task folder,
    its source.json a part per experiment, each embedding's metrics under its checksum; the
    second exported again replaces its own part; an experiment of seeds already published is
    refused with one line, and nothing is written."""
    from ede_pipeline import layout
    from ede_pipeline.published import read_source

    monkeypatch.chdir(tmp_path)
    task, first, second = "ede/ReacherVertical-v0", "a0" * 32, "b1" * 32
    finished_workspace(tmp_path, "first", [0, 1], ["td3", "ede-td3"], embedding=first)
    finished_workspace(tmp_path, "more", [2, 3], ["td3", "ede-td3"], embedding=second)
    finished_workspace(tmp_path, "again", [1, 2], ["td3", "ede-td3"])
    for name in ("first", "more", "more"):
        result = export(name)
        assert result.exit_code == 0, result.output
    folder = layout.task_runs(task, Path("published"))
    parts = json.loads((folder / "source.json").read_text())
    assert [(p["experiment"], p["seeds"]) for p in parts] == [
        ("experiments/first.yaml", [0, 1]),
        ("experiments/more.yaml", [2, 3]),
    ]
    assert read_source(folder).seeds == [0, 1, 2, 3]
    assert sorted(p.name for p in (folder / "ede-td3").iterdir()) == [f"seed{s}" for s in range(4)]
    for checksum in (first, second):
        kept = layout.published_embedding(task, checksum, Path("published"))
        assert json.loads((kept / "decoder_metrics.json").read_text()) == {
            "of": ["decoder", checksum]
        }
    before = {p: p.read_bytes() for p in Path("published").rglob("*") if p.is_file()}
    result = export("again")
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert result.stderr.strip().endswith(
        "source.json: seeds [1] are already published by "
        "experiment `experiments/first.yaml`; an experiment "
        "adds seeds the task has not"
    )
    assert {p: p.read_bytes() for p in Path("published").rglob("*") if p.is_file()} == before


def test_an_export_names_the_commits_of_runs_an_earlier_export_published(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Seed 0 exported, then gone from the working copy (made again at another commit): the
    next export keeps seed 0's files and names its commit beside the one seed 1 was made at."""
    import shutil

    from ede_pipeline import layout

    monkeypatch.chdir(tmp_path)
    workspace = finished_workspace(tmp_path, "later", [0, 1], ["td3"])
    assert export("later").exit_code == 0
    published = layout.run(TASK, "td3", 0, Path("published")) / "run.json"
    earlier = json.loads(published.read_text())
    now = earlier["code"]["commit"]
    earlier["code"]["commit"] = "e" * 40
    published.write_text(json.dumps(earlier))
    shutil.rmtree(workspace / layout.run(TASK, "td3", 0))
    result = export("later")
    assert result.exit_code == 0, result.output
    source = json.loads((layout.task_runs(TASK, Path("published")) / "source.json").read_text())
    assert source["commit"] == sorted(["e" * 40, now])
    assert json.loads(published.read_text()) == earlier


def test_an_experiment_made_again_exports_without_its_earlier_embedding(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An experiment exported, then made again with its family's embedding (another machine's
    kernels, say) and exported over its runs: the earlier embedding's folder, which no run names
    now, goes; another experiment's embedding, which its seeds still name, stays."""
    from ede_pipeline import layout

    monkeypatch.chdir(tmp_path)
    earlier, again, other = "a0" * 32, "b1" * 32, "c2" * 32
    finished_workspace(tmp_path, "beside", [2], ["td3", "ede-td3"], embedding=other)
    assert export("beside").exit_code == 0
    workspace = finished_workspace(tmp_path, "clip", [0], ["td3", "ede-td3"], embedding=earlier)
    assert export("clip").exit_code == 0
    shutil.rmtree(workspace)
    finished_workspace(tmp_path, "clip", [0], ["td3", "ede-td3"], embedding=again)
    result = export("clip")
    assert result.exit_code == 0, result.output
    kept = layout.task_runs(TASK, Path("published")) / layout.PUBLISHED_EMBEDDINGS
    assert sorted(p.name for p in kept.iterdir()) == [again[:12], other[:12]]
    assert f"{kept / earlier[:12]}: removed" in result.stderr


def test_an_experiment_made_again_exports_without_the_policy_its_runs_no_longer_record(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Exported with --policies, then made again (here keeping no policy) and exported without:
    the earlier run's policy, which the new run.json does not record, goes, so that the folder
    reads as ``results`` reads it."""
    from ede_pipeline import layout
    from ede_pipeline.published import published_runs

    monkeypatch.chdir(tmp_path)
    workspace = finished_workspace(tmp_path, "clip", [0], ["td3"], policies=True)
    args = ["experiment", "export", "clip", "--to", "published"]
    assert CliRunner().invoke(main, [*args, "--policies"]).exit_code == 0
    policy = layout.run(TASK, "td3", 0, Path("published")) / POLICY
    assert policy.is_dir()
    shutil.rmtree(workspace)
    finished_workspace(tmp_path, "clip", [0], ["td3"])
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    assert f"{policy}: removed (not the policy of the run exported over it)" in result.stderr
    assert not policy.exists() and len(published_runs(Path("published"), TASK)) == 1


def test_an_export_publishes_the_policies_of_the_seeds_it_is_given(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--policies 1`` publishes seed 1's two policies and the decoder its EDE-TD3 policy acts
    through, and no other run's policy; an export without --policies leaves them; ``--policies``
    alone publishes every run's; a narrower one takes away those it no longer plays. A seed the
    experiment has not, a value that is no seed, a seed whose runs have not finished, and a
    decoder that is not the one the runs trained with: one line each, nothing written."""
    from ede.run.artifacts import ActionSpaceMeta, DecoderMeta, WhiteningMeta
    from ede_pipeline import layout

    decoder_meta = DecoderMeta(
        software={}, weights_sha256="0" * 64, meta_sha256="1" * 64, family="reacher", k=4, dim=2,
        action_space=ActionSpaceMeta(low=[-1.0], high=[1.0]), hidden=[8], bound=1.0,
        code_whitening=WhiteningMeta(mean=[0.0, 0.0], std=[1.0, 1.0]), params={},
        data_fingerprint="data", encoder_sha256="2" * 64,
    )  # fmt: skip
    monkeypatch.chdir(tmp_path)
    workspace = finished_workspace(
        tmp_path, "pair", [0, 1], ["td3", "ede-td3"], embedding=decoder_meta.identity, policies=True
    )
    decoder = workspace / layout.embedding("reacher") / layout.DECODER
    decoder.mkdir()
    (decoder / "meta.json").write_text(decoder_meta.model_dump_json())
    out = Path("published")
    kept = layout.published_embedding(TASK, decoder_meta.identity, out) / layout.DECODER

    def export_pair(*policies: str) -> dict[tuple[str, int], str]:
        """The export, and the policies published after it."""
        result = CliRunner().invoke(
            main, ["experiment", "export", "pair", "--to", str(out), *policies]
        )
        assert result.exit_code == 0, result.output
        return {
            (algo, seed): (file / "policy.safetensors").read_text()
            for algo, seed in ((a, s) for a in ("td3", "ede-td3") for s in (0, 1))
            if (file := layout.run(TASK, algo, seed, out) / POLICY).is_dir()
        }

    def refused(policies: str, line: str) -> None:
        before = published()
        result = CliRunner().invoke(
            main, ["experiment", "export", "pair", "--to", str(out), "--policies", policies]
        )
        assert (result.exit_code, result.stderr) == (2, f"Error: {line}\n"), result.output
        assert published() == before

    assert export_pair() == {} and not kept.exists()
    assert export_pair("--policies", "1") == {("td3", 1): "td3 1", ("ede-td3", 1): "ede-td3 1"}
    assert (kept / "meta.json").read_text() == decoder_meta.model_dump_json()
    assert len(export_pair()) == 2  # without --policies, the published ones stay
    assert len(export_pair("--policies")) == 4
    refused("1,7", "--policies: seeds [7] are not among experiment pair's [0, 1]")
    refused("pair", "--policies 'pair': expected seeds of experiment pair (4 or 4,6), or "
                    "nothing for all of them; give --policies after NAME")  # fmt: skip
    made_again = decoder_meta.model_copy(update={"weights_sha256": "3" * 64})
    (decoder / "meta.json").write_text(made_again.model_dump_json())  # the family's, made again
    run = workspace.relative_to(tmp_path) / layout.run(TASK, "ede-td3", 1)
    refused("1", f"{decoder.relative_to(tmp_path)}: not the embedding {run} trained with (its "
                 f"checksum {made_again.identity[:12]}…, the run's {decoder_meta.identity[:12]}…): "
                 "its family's embedding was made again since; run the experiment again to "
                 "publish it")  # fmt: skip
    (decoder / "meta.json").write_text(decoder_meta.model_dump_json())
    assert export_pair("--policies", "0") == {("td3", 0): "td3 0", ("ede-td3", 0): "ede-td3 0"}
    shutil.rmtree(workspace / layout.run(TASK, "ede-td3", 1))  # a run not finished yet
    refused("1", f"--policies: {TASK} seed 1 has no finished EDE-TD3 run yet; publish its "
                 "policies once its runs have finished")  # fmt: skip


def test_an_experiments_tools_run_the_code_of_its_working_copy(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    """The sweep, DVC and the runs they start import the working copy's packages, not this
    checkout's (edited meanwhile), and run.json names the copy's commit; its params.yaml,
    changed by the experiment, does not count as modified code."""
    import shutil

    from ede_pipeline.experiments.workspace import run_tool
    from tests.support import REPO

    workspace = tmp_path / "copy"
    for folder in ("ede", "pipeline", "envs"):
        shutil.copytree(
            REPO / folder, workspace / folder, ignore=shutil.ignore_patterns("__pycache__")
        )
    (workspace / "params.yaml").write_text("td3: {lr: 0.001}\n")
    for args in (
        ["init", "-q"],
        ["add", "-A"],
        ["-c", "user.email=t@example.org", "-c", "user.name=t", "commit", "-qm", "copy"],
    ):
        git(workspace, *args)
    head = subprocess.run(
        ["git", "rev-parse", "HEAD"], cwd=workspace, capture_output=True, text=True, check=True
    ).stdout.strip()
    (workspace / "params.yaml").write_text("td3: {lr: 0.0003}\n")  # the experiment's params
    monkeypatch.chdir(REPO)  # where `experiment run` runs: pyproject.toml names the packages
    show = (
        "import json, ede, ede_envs, ede_pipeline; from ede.io.provenance import code_version; "
        "print(json.dumps([[m.__file__ for m in (ede, ede_envs, ede_pipeline)], code_version()]))"
    )
    capfd.readouterr()
    assert run_tool(workspace, "python", "-c", show) == 0
    files, code = json.loads(capfd.readouterr().out.strip().splitlines()[-1])
    assert [Path(f).resolve().parent for f in files] == [
        (workspace / folder).resolve() for folder in ("ede", "envs", "pipeline")
    ]
    assert code == {"commit": head, "modified": False}
    (workspace / "ede" / "method" / "nets.py").write_text("# edited\n", encoding="utf-8")
    assert run_tool(workspace, "python", "-c", show) == 0
    assert json.loads(capfd.readouterr().out.strip().splitlines()[-1])[1]["modified"] is True


def test_a_working_copy_keeps_its_record_of_finished_runs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Bringing a working copy up to this checkout keeps its ``dvc.lock`` (which DVC's autostage
    has added to the copy's git index) and its outputs, and takes this checkout's files, a file
    deleted here included."""
    from ede_pipeline.experiments.workspace import prepare_workspace

    git(tmp_path, "init", "-q")
    subprocess.run(["dvc", "init", "-q"], cwd=tmp_path, check=True, env=tool_env())
    (tmp_path / "code.py").write_text("v = 1\n")
    (tmp_path / "gone.py").write_text("v = 0\n")
    git(tmp_path, "add", "-A")
    git(tmp_path, "-c", "user.email=t@example.org", "-c", "user.name=t", "commit", "-qm", "base")
    monkeypatch.chdir(tmp_path)
    workspace = prepare_workspace("x", {"td3": {"lr": 0.001}})
    records = "schema: '2.0'\nstages:\n  train:\n    cmd: python code.py\n"
    (workspace / "dvc.lock").write_text(records)
    git(workspace, "add", "dvc.lock")  # as `dvc repro` does with core.autostage
    (workspace / "data" / "run.csv").write_text("step\n")
    (tmp_path / "code.py").write_text("v = 2\n")
    (tmp_path / "gone.py").unlink()

    assert prepare_workspace("x", {"td3": {"lr": 0.0003}}) == workspace
    assert (workspace / "dvc.lock").read_text() == records
    assert (workspace / "data" / "run.csv").read_text() == "step\n"
    assert (workspace / "code.py").read_text() == "v = 2\n"
    assert not (workspace / "gone.py").exists()
    assert "lr: 0.0003" in (workspace / "params.yaml").read_text()


# What an export must refuse, in one line, writing nothing ---------------------------------------

PUBLISHED_TASK = Path("published") / TASK  # layout.task_runs(TASK, Path("published"))


def published() -> dict[Path, bytes]:
    return {p: p.read_bytes() for p in Path("published").rglob("*") if p.is_file()}


def refused(name: str, line: str) -> None:
    """``experiment export NAME`` exits 2 with ``Error: line`` alone and writes nothing."""
    before = published()
    result = export(name)
    assert (result.exit_code, result.stderr) == (2, f"Error: {line}\n"), result.output
    assert published() == before


def another_number(path: Path) -> None:
    """The last digit of ``path`` changed: a CSV or JSON file still reads, to another number."""
    text = path.read_text()
    last = max(i for i, c in enumerate(text) if c.isdigit())
    path.write_text(text[:last] + ("2" if text[last] == "1" else "1") + text[last + 1 :])


@pytest.fixture
def first_published(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Seed 0 of TD3 exported from experiment ``first`` to ``published/``, and experiment
    ``more``'s seed 1 finished, to export beside it; in ``tmp_path``, the working directory."""
    monkeypatch.chdir(tmp_path)
    finished_workspace(tmp_path, "first", [0], ["td3"])
    finished_workspace(tmp_path, "more", [1], ["td3"])
    assert export("first").exit_code == 0
    return tmp_path


@pytest.mark.parametrize("name", ["seed00", "seed-1", "seedx", "seed 1"])
def test_an_export_beside_a_seed_folder_not_named_seed_n_is_refused(
    first_published: Path, name: str
) -> None:
    shutil.copytree(PUBLISHED_TASK / "td3" / "seed0", PUBLISHED_TASK / "td3" / name)
    refused(
        "more",
        f"{PUBLISHED_TASK / 'td3' / name}: not a run's folder name; expected seed<N>, N a whole "
        "number >= 0 without leading zeros (seed0, seed12)",
    )


def test_an_export_beside_a_seed_published_twice_is_refused(first_published: Path) -> None:
    """A copy of seed 0 as seed 2: its run.json names seed 0."""
    shutil.copytree(PUBLISHED_TASK / "td3" / "seed0", PUBLISHED_TASK / "td3" / "seed2")
    refused("more", f"{PUBLISHED_TASK / 'td3' / 'seed2' / 'run.json'}: seed is 0, expected 2")


@pytest.mark.parametrize("name", ["first", "more"])
def test_an_export_beside_seeds_source_json_does_not_name_is_refused(
    first_published: Path, name: str
) -> None:
    """A task's source.json from before parts named their seeds: the runs of seed 0 there are
    no experiment's, neither the one that would replace them nor one beside them."""
    (PUBLISHED_TASK / "source.json").write_text(
        json.dumps({"commit": "0" * 40, "command": "experiment.py --seeds 0"})
    )
    refused(
        name,
        f"{PUBLISHED_TASK / 'td3' / 'seed0'}: a run of seed 0, which "
        f"{PUBLISHED_TASK / 'source.json'} does not name (it names none); a task's runs are the "
        "seeds its experiments made, as each export names them",
    )


def test_an_export_of_runs_made_with_other_params_than_the_published_is_refused(
    first_published: Path,
) -> None:
    """td3.lr set apart; td3.threads, which leaves results alone, does not."""
    finished_workspace(first_published, "faster", [1], ["td3"], td3={"lr": 0.002})
    finished_workspace(first_published, "threads", [2], ["td3"], td3={"threads": 2})
    lr = yaml.safe_load((REPO / "params.yaml").read_text())["td3"]["lr"]
    run = Path(".dvc/tmp/experiments/faster/data/runs") / TASK / "td3" / "seed1"
    refused(
        "faster",
        f"{run / 'run.json'}: made with td3.lr = 0.002, but {PUBLISHED_TASK / 'td3' / 'seed0'} "
        f"was made with {json.dumps(lr)}; a task's runs share every param that changes a result",
    )
    assert export("threads").exit_code == 0


def test_an_export_beside_a_published_file_its_run_did_not_write_is_refused(
    first_published: Path,
) -> None:
    path = PUBLISHED_TASK / "td3" / "seed0" / "eval.csv"
    recorded = json.loads((path.parent / "run.json").read_text())["sha256"]["eval.csv"]
    another_number(path)
    refused(
        "more",
        f"{path}: not the file its run wrote (SHA-256 {sha256(path)[:12]}…, run.json records "
        f"{recorded[:12]}…)",
    )


def test_an_export_of_a_file_its_run_did_not_write_is_refused(first_published: Path) -> None:
    path = Path(".dvc/tmp/experiments/more/data/runs") / TASK / "td3" / "seed1" / "metrics.json"
    recorded = json.loads((path.parent / "run.json").read_text())["sha256"]["metrics.json"]
    another_number(path)
    refused(
        "more",
        f"{path}: not the file its run wrote (SHA-256 {sha256(path)[:12]}…, run.json records "
        f"{recorded[:12]}…)",
    )


def test_an_export_refuses_to_remove_a_folder_among_the_embeddings_it_did_not_write(
    first_published: Path,
) -> None:
    """The issue's example: a user's folder beside the published embeddings, which no run acts
    through, was removed as an export's; and an export's own, with a user's file added."""
    from ede_pipeline import layout

    kept = PUBLISHED_TASK / layout.PUBLISHED_EMBEDDINGS
    (kept / "my-notes").mkdir(parents=True)
    (kept / "my-notes" / "NOTES.txt").write_text("mine\n")
    line = (
        "no published run acts through it, but no export wrote it (it holds what an export's "
        f"mark does not own); an export removes only its own: move it out of {kept}"
    )
    refused("more", f"{kept / 'my-notes'}: {line}")
    (kept / "my-notes" / "NOTES.txt").unlink()
    result = export("more")  # an empty folder holds nothing of anyone's
    assert result.exit_code == 0, result.output
    finished_workspace(first_published, "ede", [2], ["ede-td3"], embedding="a0" * 32)
    assert export("ede").exit_code == 0
    shutil.rmtree(Path(".dvc/tmp/experiments/ede"))  # made again with another embedding
    finished_workspace(first_published, "ede", [2], ["ede-td3"], embedding="b1" * 32)
    (kept / ("a0" * 6) / "NOTES.txt").write_text("mine\n")
    refused("ede", f"{kept / ('a0' * 6)}: {line}")


@pytest.mark.parametrize(
    ("to", "line"),
    [
        (".", ".: the working directory; expected a folder of the output's own, e.g. one inside it"),
        ("..", "..: the working directory or a folder above it; expected a folder of the output's "
               "own, e.g. one inside it"),
        ("notes.txt", "notes.txt: a file is in the way; expected a directory there, or nothing"),
        (".dvc/tmp/experiments/more/data", ".dvc/tmp/experiments/more/data: lies inside the "
                                           "stage's input .dvc/tmp/experiments/more; expected a "
                                           "place apart from it"),
    ],
)  # fmt: skip
def test_an_export_to_the_working_directory_its_input_or_a_file_is_refused(
    first_published: Path, to: str, line: str
) -> None:
    (first_published / "notes.txt").write_text("mine\n")
    before = {p: p.read_bytes() for p in first_published.rglob("*") if p.is_file()}
    result = CliRunner().invoke(main, ["experiment", "export", "more", "--to", to])
    assert (result.exit_code, result.stderr) == (2, f"Error: {line}\n"), result.output
    assert {p: p.read_bytes() for p in first_published.rglob("*") if p.is_file()} == before


def test_an_export_refuses_what_is_in_the_way_of_what_it_writes(first_published: Path) -> None:
    """A file where a folder of the task goes, a folder where its source.json goes, and a seed
    folder of the user's where a run goes: one line each, nothing written."""
    algo = PUBLISHED_TASK / "td3"
    (PUBLISHED_TASK / "source.json").rename("source.json")
    (PUBLISHED_TASK / "source.json").mkdir()
    refused("more", f"{PUBLISHED_TASK / 'source.json'}: a folder is in the way; expected a file "
                    "there, or nothing")  # fmt: skip
    (PUBLISHED_TASK / "source.json").rmdir()
    Path("source.json").rename(PUBLISHED_TASK / "source.json")
    (algo / "seed1").mkdir()
    (algo / "seed1" / "NOTES.txt").write_text("mine\n")
    refused("more", f"{algo / 'seed1'}: holds NOTES.txt, and no finished run an export "
                    "published; move them out first")  # fmt: skip
    shutil.rmtree(algo / "seed1")
    (algo / "seed1").write_text("mine\n")
    refused("more", f"{algo / 'seed1'}: a file is in the way; expected a folder there, or nothing")


@pytest.mark.parametrize("link", ["seed folder", "task folder"])
def test_an_export_never_writes_through_a_link_in_a_published_folder(
    first_published: Path, link: str
) -> None:
    """A seed folder, or the folder above a task's, that leads outside the published folder."""
    elsewhere = first_published / "elsewhere"
    linked = PUBLISHED_TASK / "td3" / "seed1" if link == "seed folder" else PUBLISHED_TASK.parent
    if link == "task folder":
        shutil.move(linked, elsewhere)
    else:
        elsewhere.mkdir()
    linked.symlink_to(elsewhere)
    refused(
        "more",
        f"{linked}: a symbolic link (to {elsewhere}); a published folder holds its own files, so "
        "that an export writes nothing outside it: put what it names there instead",
    )
    assert sorted(p.name for p in elsewhere.rglob("*")) == (
        [] if link == "seed folder" else sorted(p.name for p in elsewhere.rglob("*"))
    )


def test_an_export_refuses_to_remove_a_policy_it_did_not_write(first_published: Path) -> None:
    finished_workspace(first_published, "pair", [0, 1], ["td3"], policies=True)
    (PUBLISHED_TASK / "source.json").unlink()
    shutil.rmtree(PUBLISHED_TASK / "td3")
    assert export("pair").exit_code == 0
    policy = PUBLISHED_TASK / "td3" / "seed0" / POLICY
    policy.mkdir()
    (policy / "NOTES.txt").write_text("mine\n")
    before = published()
    result = CliRunner().invoke(
        main, ["experiment", "export", "pair", "--to", "published", "--policies", "1"]
    )
    assert (result.exit_code, result.stderr) == (
        2,
        f"Error: {policy}: holds NOTES.txt, which no export wrote there (no "
        ".ede-output.json of one); move it out first\n",
    ), result.output
    assert published() == before


def test_an_export_waits_for_no_other_export_to_the_same_place(first_published: Path) -> None:
    from ede.io.locks import exclusive

    with exclusive(Path("published")):
        before = published()
        result = export("more")
        assert result.exit_code == 2 and "published: being written by process" in result.stderr
        assert published() == before


def test_an_export_that_fails_midway_leaves_the_published_folder_as_it_was(
    first_published: Path,
) -> None:
    """A full disk (each write past RLIMIT_FSIZE fails, as one on a full disk does): one line,
    exit 1, no traceback, and the published folder as it was, with no temporary left."""
    import sys

    from tests.pipeline.test_outputs import LIMITED

    finished_workspace(first_published, "both", [0, 1], ["td3"], policies=True)
    (PUBLISHED_TASK / "source.json").unlink()
    shutil.rmtree(PUBLISHED_TASK / "td3")
    assert export("both").exit_code == 0
    before = {p: p.read_bytes() for p in first_published.rglob("*") if p.is_file()}
    names = sorted(p.relative_to(first_published) for p in first_published.rglob("*"))
    done = subprocess.run(
        [sys.executable, "-c", LIMITED.format(limit=1_000), "experiment", "export", "both",
         "--to", "published", "--policies"],
        capture_output=True, text=True, timeout=600, env=tool_env(),
    )  # fmt: skip
    assert (done.returncode, done.stderr) == (
        1,
        "Error: published: nothing exported (File too large); it is as it was\n",
    ), done.stderr
    assert {p: p.read_bytes() for p in first_published.rglob("*") if p.is_file()} == before
    assert sorted(p.relative_to(first_published) for p in first_published.rglob("*")) == names


def test_an_export_puts_back_what_an_export_killed_midway_left(first_published: Path) -> None:
    """Killed between taking a task's folder away and putting its new one in its place: the old
    folder goes back before the next export, which then writes beside it; a killed export's
    half-built folders go."""
    killed = Path("published/.export.tmp-4194304")
    aside = killed / "old" / TASK
    aside.parent.mkdir(parents=True)
    PUBLISHED_TASK.rename(aside)
    (killed / "new" / TASK).mkdir(parents=True)
    result = export("more")
    assert result.exit_code == 0, result.output
    assert not killed.exists()
    assert sorted(p.name for p in (PUBLISHED_TASK / "td3").iterdir()) == ["seed0", "seed1"]
    parts = json.loads((PUBLISHED_TASK / "source.json").read_text())
    assert [(p["experiment"], p["seeds"]) for p in parts] == [
        ("experiments/first.yaml", [0]),
        ("experiments/more.yaml", [1]),
    ]


def test_an_export_of_a_run_copied_from_a_published_one_is_refused(first_published: Path) -> None:
    """Experiment ``more``'s seed 1 replaced by a copy of the published seed 0, its run.json
    saying seed 1: the same run, whatever its folder and run.json say."""
    run = Path(".dvc/tmp/experiments/more/data/runs") / TASK / "td3" / "seed1"
    shutil.rmtree(run)
    shutil.copytree(PUBLISHED_TASK / "td3" / "seed0", run)
    made = json.loads((run / "run.json").read_text())
    (run / "run.json").write_text(json.dumps({**made, "seed": 1}))
    refused(
        "more",
        f"{run}: the same run as {PUBLISHED_TASK / 'td3' / 'seed0'} (their eval.csv's SHA-256 "
        f"are both {sha256(run / 'eval.csv')[:12]}…); a run is published once, in the folder of "
        "its own seed",
    )
