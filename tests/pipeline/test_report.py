"""``ede-pipeline report``: every section, with one seed, missing runs and unequal lengths;
its inputs from its command line, and bad ones refused."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
import pytest
import torch
from click.testing import CliRunner, Result

from ede.config import (
    ALGO_LABELS,
    ALGOS,
    PAPER_ALGOS,
    Algo,
    DecoderConfig,
    EmbeddingConfig,
    load_params,
)
from ede.io.provenance import describe_software, software_versions
from ede.io.rollouts import Rollouts, write_store
from ede.method.embedding import train_decoder, train_encoder
from ede.run.artifacts import save_decoder, save_encoder
from ede.run.collect import collect
from ede.run.spec import RunSpec
from ede_pipeline import layout
from ede_pipeline.cli import main

TASKS = {"ede/ReacherVertical-v0": "reacher", "ede/Pusher-v0": "sevendof"}


def fake_run(
    root: Path, task: str, algo: Algo, seed: int, returns: list[float], every: int = 1000
) -> Path:
    """A finished run as ``train`` leaves it, of the params in ``root``: eval.csv (an evaluation
    every ``every`` steps), run.json and metrics.json."""
    out = root / "data/runs" / task / algo / f"seed{seed}"
    out.mkdir(parents=True)
    lines = ["step,episode,mean_return,std_return,wall_seconds"]
    lines += [f"{every * i},{10 * i},{r},1.0,{i}" for i, r in enumerate(returns)]
    (out / "eval.csv").write_text("\n".join(lines) + "\n")
    (out / "metrics.json").write_text(json.dumps({"final_return": returns[-1]}))
    params = load_params(root / "params.yaml")
    spec = RunSpec(task, algo, seed, params.runs.budgets[task], params.td3, params.ede_td3)
    software = {**software_versions(), "torch": "9.9"}
    (out / "run.json").write_text(json.dumps({**spec.identity(), "software": software}))
    if task.startswith("ede/"):  # training diagnostics, as train writes them
        lines = ["step,updates,critic_loss,actor_loss,mean_q"]
        lines += [f"{1000 * i},1000,{1.0 / i},{-r},{r}" for i, r in enumerate(returns[1:], start=1)]
        (out / "diagnostics.csv").write_text("\n".join(lines) + "\n")
    return out


def embedding(root: Path, family: str, env_id: str) -> None:
    """A family's rollouts and a small trained embedding, where the pipeline would put them."""
    torch.set_num_threads(1)
    store = root / layout.rollouts(family)
    write_store(
        store,
        collect(env_id, 2_000, 1, 0, workers=1),
        {
            "env_id": env_id,
            "family": family,
            "seed": 0,
            "num_envs": 1,
            "steps": 2000,
            "spaces": {},
            "params": {},
            "software": software_versions(),
        },
    )
    rollouts = Rollouts.open(store)
    small: dict[str, Any] = {"hidden": [32, 32], "epochs": 3, "lr": 1e-3}
    encoded = train_encoder(rollouts, EmbeddingConfig(**small))
    low, high = -np.ones(2), np.ones(2)
    decoded = train_decoder(rollouts, encoded, DecoderConfig(**small), 4, low, high)
    folder = root / layout.embedding(family)
    save_encoder(
        folder / "encoder",
        encoded,
        family=family,
        env_id=env_id,
        low=low,
        high=high,
        params={},
        data_fingerprint=rollouts.attrs["fingerprint"],
    )
    save_decoder(
        folder / "decoder",
        decoded.decoder,
        decoded.bound,
        encoder_path=folder / "encoder",
        params={},
    )


@pytest.fixture(scope="module")
def embeddings(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("embeddings")
    embedding(root, "point", "ede/Point-v0")
    embedding(root, "pointmass", "ede/PointMass-v0")
    return root


@pytest.fixture
def project(tmp_path: Path, write_params, monkeypatch: pytest.MonkeyPatch) -> Path:
    def edit(params: dict) -> None:
        params["runs"].update(
            tasks=TASKS,
            seeds=[0, 1, 2],
            budgets={"ede/ReacherVertical-v0": 2000, "ede/Pusher-v0": 2000},
        )
        params["report"].update(
            thresholds={"ede/ReacherVertical-v0": [-5.0, -3.0]}, bootstrap_samples=200
        )

    write_params(edit)
    monkeypatch.chdir(tmp_path)
    return tmp_path


def report(root: Path, *args: str) -> tuple[Result, str]:
    result = CliRunner().invoke(main, ["report", *args])
    assert result.exit_code == 0, result.output
    return result, (root / "data/report/index.html").read_text()


def test_every_section_with_runs_missing_and_one_cut_short(project: Path, embeddings: Path) -> None:
    shutil.copytree(embeddings / "data", project / "data")
    fake_run(project, "ede/ReacherVertical-v0", "td3", 0, [-20, -12, -8])
    fake_run(project, "ede/ReacherVertical-v0", "td3", 1, [-21, -10])  # ends before its budget
    fake_run(project, "ede/ReacherVertical-v0", "ede-td3", 0, [-20, -6, -4])
    fake_run(project, "ede/ReacherVertical-v0", "ede-td3", 1, [-19, -5, -3])
    fake_run(project, "ede/ReacherVertical-v0", "ede-td3", 2, [-18, -7, -2])
    _, page = report(project)
    for section in (
        "Learning curves",
        "reacher family",
        "sevendof family",
        "Figure 6",
        "R² =",
        "Figure 7",
        "of the arena",
        "Missing and excluded runs",
        "Provenance",
        "thresholds -5, -3",
        "steps to -5",
        "steps to -3",
    ):
        assert section in page, section
    for image in (
        "curves-reacher",
        "curves-sevendof",
        "diagnostics-reacher",
        "effect-space",
        "exploration",
        "performance-profile",
    ):
        assert f'id="{image}"' in page and (project / f"data/report/{image}.png").is_file()
    assert 'id="diagnostics-sevendof"' not in page  # no run of that family has diagnostics
    assert page.count("data:image/png;base64,") == 6  # self-contained
    # 12 runs expected (2 tasks x 2 algos x 3 seeds); 5 exist, one of them cut short.
    assert "7 of 12 runs have no results" in page
    assert (
        "1 finished runs are left out of the figures and tables:</p><ul><li>data/runs/ede/"
        "ReacherVertical-v0/td3/seed1/eval.csv: the last evaluation is at step 1000, not at "
        "the run&#x27;s budget 2000</li>"
    ) in page
    # provenance: each input's SHA-256 beside the versions that made it
    here = describe_software(software_versions())
    meta = json.loads((project / "data/families/point/embedding/encoder/meta.json").read_text())
    assert (
        f"<td>point encoder weights</td><td><code>{meta['weights_sha256']}</code></td><td>{here}</td>"
        in page
    )
    assert (
        f"<td>point rollouts</td><td><code>{meta['data_fingerprint']}</code></td><td>{here}</td>"
        in page
    )
    assert "reacher encoder weights" not in page  # every family in data/families: none there
    assert (
        "<td>4 training runs</td><td></td><td>" + here.replace(software_versions()["torch"], "9.9")
        in page
    )
    assert (
        "data/runs/ede/Pusher-v0/td3/seed0" in page
        and "data/runs/ede/ReacherVertical-v0/td3/seed2" in page
    )
    metrics = json.loads((project / "data/report-metrics.json").read_text())
    assert metrics["missing_runs"] == 7 and metrics["excluded_runs"] == 1
    # Across tasks: only ReacherVertical has runs of both, all 3 of EDE-TD3's seeds and TD3's
    # seed 0 (its seed 1 is left out above); every EDE-TD3 final return beats TD3's -8 there.
    across = metrics["across_tasks"]
    assert across["tasks"] == ["ede/ReacherVertical-v0"] and across["task_count"] == 1
    assert across["runs_per_task"] == {"ede-td3": 3, "td3": 1}
    assert across["final_return"]["probability_of_improvement"]["value"] == 1.0
    assert "P(EDE-TD3 &gt; TD3)" in page
    assert metrics["ede/ReacherVertical-v0"]["td3"] == {
        "final_return": -8.0,
        "auc": pytest.approx((-20 + -12) / 2 * 0.5 + (-12 + -8) / 2 * 0.5),
        "seeds": 1,
    }
    assert metrics["ede/ReacherVertical-v0"]["ede-td3"]["final_return"] == -3.0
    assert metrics["ede/Pusher-v0"]["td3"]["seeds"] == 0
    curve = (project / "data/report-curves/ede_ReacherVertical-v0.csv").read_text().splitlines()
    assert curve[0] == "step,td3,ede-td3" and curve[1] == "0,-20,-19"
    assert curve[3] == "2000,-8,-3"


def test_one_seed_and_no_pictures_where_the_params_name_no_family(
    project: Path, write_params
) -> None:
    def no_pictures(params: dict) -> None:
        params["runs"].update(
            tasks=TASKS, seeds=[0], budgets={"ede/ReacherVertical-v0": 2000, "ede/Pusher-v0": 2000}
        )
        params["report"].update(effect_space_family=None, exploration_family=None)

    write_params(no_pictures)
    fake_run(project, "ede/Pusher-v0", "ede-td3", 0, [-50, -40], every=2000)
    _, page = report(project)  # no embedding needed, none read
    assert "Not drawn: <code>report.effect_space_family</code> is null" in page
    assert "Not drawn: <code>report.exploration_family</code> is null" in page
    assert "EDE-TD3 (1 seeds)" not in page  # the legend is in the picture, not the text
    metrics = json.loads((project / "data/report-metrics.json").read_text())
    assert metrics["ede/Pusher-v0"]["ede-td3"] == {"final_return": -40.0, "auc": -45.0, "seeds": 1}
    assert "coverage" not in metrics and "effect_space_affine_r2" not in metrics


def test_the_inputs_are_the_command_lines_and_the_figures_families_the_params(
    project: Path, embeddings: Path, write_params
) -> None:
    """Runs, embeddings and rollouts from wherever the options say; Figure 6 from any family."""
    open_before = set(plt.get_fignums())  # tests run before in this process may leave some
    shutil.copytree(embeddings / "data", project / "elsewhere")
    fake_run(project, "ede/ReacherVertical-v0", "td3", 0, [-20, -12, -8])
    shutil.move(project / "data/runs", project / "elsewhere/runs")

    def swapped(params: dict) -> None:
        params["runs"].update(
            tasks=TASKS, seeds=[0], budgets={"ede/ReacherVertical-v0": 2000, "ede/Pusher-v0": 2000}
        )
        params["report"].update(effect_space_family="pointmass", exploration_family="pointmass")

    write_params(swapped)
    _, page = report(
        project,
        "--runs",
        "elsewhere/runs",
        "--embedding",
        "pointmass=elsewhere/families/pointmass/embedding",
        "--rollouts",
        "pointmass=elsewhere/families/pointmass/rollouts.zarr",
    )
    assert "random 4-step sequences on ede/PointMass-v0" in page and "Positions over ten" in page
    assert "pointmass rollouts" in page and "point encoder weights" not in page
    # Without --embedding, every family found in --families: both, in the provenance.
    _, page = report(project, "--runs", "elsewhere/runs", "--families", "elsewhere/families")
    assert "pointmass rollouts" in page and "point encoder weights" in page
    assert "<code>elsewhere/runs/ede/Pusher-v0/td3/seed0</code>" in page  # missing, by its path
    assert (
        set(plt.get_fignums()) <= open_before
    )  # every figure closed once drawn: two reports add none
    metrics = json.loads((project / "data/report-metrics.json").read_text())
    assert metrics["ede/ReacherVertical-v0"]["td3"]["seeds"] == 1


def bad(result: Result, message: str) -> None:
    assert result.exit_code == 2, result.output
    assert result.stderr.count("\n") == 1 and message in result.stderr, result.stderr
    assert "Traceback" not in result.output


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["--runs", "nowhere"],
            "--runs nowhere: no such directory; expected the folder of the runs",
        ),
        (["--embedding", "point=nowhere"], "--embedding point=nowhere: no such directory"),
        (
            ["--embedding", "data/families/point/embedding"],
            "--embedding 'data/families/point/embedding': expected FAMILY=PATH",
        ),
        (["--embedding", "moon=data/families/point/embedding"], "unknown family 'moon'"),
        (
            ["--embedding", "pointmass=data/families/pointmass/embedding"],
            "report.effect_space_family: point, but no --embedding point=DIR is given",
        ),
        (
            [
                "--embedding",
                "point=data/families/pointmass/embedding",
                "--embedding",
                "pointmass=data/families/pointmass/embedding",
            ],
            "the embedding of family pointmass, not point",
        ),
        (
            ["--rollouts", "point=data/families/pointmass/rollouts.zarr"],
            "but the point embedding was trained on",
        ),
        (
            ["--rollouts", "point=data/families/point/embedding"],
            "--rollouts point=data/families/point/embedding: no rollouts store here",
        ),
    ],
)
def test_bad_input_is_one_line_exit_2_and_writes_nothing(
    project: Path, embeddings: Path, args: list[str], message: str
) -> None:
    shutil.copytree(embeddings / "data", project / "data")
    fake_run(project, "ede/Pusher-v0", "td3", 0, [-50, -40], every=2000)
    bad(CliRunner().invoke(main, ["report", *args]), message)
    assert sorted(p.name for p in (project / "data").iterdir()) == ["families", "runs"]


def test_a_figures_family_must_be_a_family_of_the_params(project: Path, write_params) -> None:
    write_params(lambda params: params["report"].update(exploration_family="moon"))
    (project / "data/runs").mkdir(parents=True)
    bad(
        CliRunner().invoke(main, ["report"]),
        "report.exploration_family: got 'moon'; expected a family of `families`",
    )
    assert not (project / "data/report").exists()


@pytest.mark.skipif(shutil.which("chromium") is None, reason="Debian's chromium is not installed")
def test_the_page_opens_in_headless_chromium_with_its_figures(
    project: Path, embeddings: Path
) -> None:
    shutil.copytree(embeddings / "data", project / "data")
    fake_run(project, "ede/ReacherVertical-v0", "td3", 0, [-20, -12, -8])
    report(project)
    page = project / "data/report/index.html"
    shot = project / "shot.png"
    flags = [
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        f"--user-data-dir={project / 'chrome-profile'}",
    ]
    result = subprocess.run(
        ["chromium", *flags, f"--screenshot={shot}", "--window-size=1200,2400", page.as_uri()],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "HOME": str(project)},
    )
    assert result.returncode == 0, result.stderr
    assert shot.is_file() and shot.stat().st_size > 20_000
    dom = subprocess.run(
        ["chromium", *flags, "--dump-dom", page.as_uri()],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "HOME": str(project)},
    )
    assert (
        dom.returncode == 0 and dom.stdout.count("<img") == 5
    )  # curves x2, diagnostics, Figures 6 and 7


def _edit_json(path: Path, change) -> None:
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def _rewrite(path: Path, old: str, new: str) -> None:
    path.write_text(path.read_text().replace(old, new, 1))


DAMAGE = {
    # what was done to td3 seed 1: (how, the reason named)
    "an EDE-TD3 run in a TD3 slot": (
        lambda run: _edit_json(run / "run.json", lambda d: d.update(algo="ede-td3")),
        'run.json: algo is "ede-td3", expected "td3"',
    ),
    "another budget's run": (
        lambda run: _edit_json(run / "run.json", lambda d: d.update(budget=6000)),
        "run.json: budget is 6000, expected 2000",
    ),
    "another seed's run": (
        lambda run: _edit_json(run / "run.json", lambda d: d.update(seed=0)),
        "run.json: seed is 0, expected 1",
    ),
    "other params": (
        lambda run: _edit_json(run / "run.json", lambda d: d["params"]["td3"].update(lr=0.01)),
        "run.json: made with td3.lr = 0.01, but the params say 0.001",
    ),
    "a garbled run.json": (
        lambda run: (run / "run.json").write_text('{"task": '),
        "run.json: not readable JSON",
    ),
    "no run.json": (lambda run: (run / "run.json").unlink(), "run.json: missing"),
    "an empty eval.csv": (
        lambda run: (run / "eval.csv").write_text(""),
        "eval.csv: no column step, mean_return; found none",
    ),
    "a header alone": (
        lambda run: (run / "eval.csv").write_text(
            "step,episode,mean_return,std_return,wall_seconds\n"
        ),
        "eval.csv: no rows",
    ),
    "a NaN return": (
        lambda run: _rewrite(run / "eval.csv", ",-12,", ",nan,"),
        "eval.csv: line 3, mean_return: nan, not a finite number",
    ),
    "text for a number": (
        lambda run: _rewrite(run / "eval.csv", ",-12,", ",abc,"),
        "eval.csv: line 3, mean_return: 'abc' is not a number",
    ),
    "a missing column": (
        lambda run: (run / "eval.csv").write_text("step,return\n0,-1\n2000,-2\n"),
        "eval.csv: no column mean_return; found step, return",
    ),
    "steps past the budget": (
        lambda run: _rewrite(run / "eval.csv", "\n2000,", "\n3000,"),
        "eval.csv: the last evaluation is at step 3000, not at the run's budget 2000",
    ),
    "steps out of order": (
        lambda run: _rewrite(run / "eval.csv", "\n1000,", "\n2500,"),
        "eval.csv: steps must start at 0 and rise; found [0, 2500, 2000]",
    ),
    "damaged diagnostics": (
        lambda run: _rewrite(run / "diagnostics.csv", "1000,1000,", "1000,x,"),
        "diagnostics.csv: line 2, updates: 'x' is not a number",
    ),
}


@pytest.mark.parametrize("case", DAMAGE)
def test_a_run_that_is_not_what_the_params_name_is_left_out_by_name(
    project: Path, case: str
) -> None:
    two_seeds_no_pictures(project, budget=2000)
    fake_run(project, "ede/ReacherVertical-v0", "td3", 0, [-20, -12, -8])
    damaged = fake_run(project, "ede/ReacherVertical-v0", "td3", 1, [-21, -12, -9])
    damage, reason = DAMAGE[case]
    damage(damaged)
    result, page = report(project)
    left_out = [line for line in result.stderr.splitlines() if line.startswith("left out: ")]
    assert len(left_out) == 1 and left_out[0].startswith(
        f"left out: {damaged.relative_to(project)}/"
    )
    assert reason in left_out[0], left_out[0]
    assert "Traceback" not in result.output
    assert "1 finished runs are left out of the figures and tables" in page
    metrics = json.loads((project / "data/report-metrics.json").read_text())
    assert metrics["excluded_runs"] == 1 and metrics["missing_runs"] == 6
    assert metrics["ede/ReacherVertical-v0"]["td3"]["seeds"] == 1  # seed 0's alone
    assert metrics["ede/ReacherVertical-v0"]["td3"]["final_return"] == -8.0


def two_seeds_no_pictures(root: Path, budget: int) -> None:
    """Params of seeds 0 and 1, ``budget`` steps on ReacherVertical, and no Figures 6 and 7."""
    import yaml

    from tests.support import REPO

    params = yaml.safe_load((REPO / "params.yaml").read_text())
    params["runs"].update(
        tasks=TASKS, seeds=[0, 1], budgets={"ede/ReacherVertical-v0": budget, "ede/Pusher-v0": 2000}
    )
    params["report"].update(effect_space_family=None, exploration_family=None)
    (root / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))


def test_a_seed_that_falls_and_stays_below_its_best_is_flagged(project: Path) -> None:
    two_seeds_no_pictures(project, budget=20_000)
    rises = list(np.linspace(-30, -10, 21))
    falls = list(np.linspace(-30, -10, 11)) + list(np.linspace(-14, -40, 10))
    fake_run(project, "ede/ReacherVertical-v0", "td3", 0, falls)
    fake_run(project, "ede/ReacherVertical-v0", "td3", 1, rises)
    fake_run(project, "ede/ReacherVertical-v0", "ede-td3", 0, rises)
    _, page = report(project)
    # The last quarter's 5 evaluations (16K to 20K) average -34.22; the best 5 before it, -14,
    # -12, -10, -14 and -16.9 (7K to 11K), -13.2.
    assert (
        "Fell and stayed below their best (diverged, in the paper's sense): TD3 seed 0 "
        "(best -13.2 over steps 7,000–11,000, last quarter -34.22)." in page
    )
    assert page.count("Fell and stayed below their best") == 1  # the others rise


def test_every_algorithm_the_params_name_has_its_row_and_ede_td3_is_set_against_each(
    project: Path, write_params
) -> None:
    def every_algorithm(params: dict, algos: tuple[str, ...] = ALGOS) -> None:
        params["runs"].update(
            tasks=TASKS,
            algos=list(algos),
            seeds=[0, 1, 2],
            budgets={"ede/ReacherVertical-v0": 2000, "ede/Pusher-v0": 2000},
        )
        params["report"].update(
            effect_space_family=None, exploration_family=None, bootstrap_samples=200
        )

    write_params(every_algorithm)
    ends: dict[Algo, int] = {
        "td3": -8,
        "ede-td3": -4,
        "sb3-td3-ede": -6,
        "sb3-sac": -2,
    }  # SB3's SAC in EDE: none
    for algo, end in ends.items():
        for seed in range(3):
            fake_run(project, "ede/ReacherVertical-v0", algo, seed, [-20, -12, end - 0.1 * seed])
    _, page = report(project)
    table = page.split("<h4>ede/ReacherVertical-v0")[1].split("<h4>")[0]
    rows = [row.split("</td>")[0] for row in table.split("<tr><td>")[1:]]
    assert rows[: len(ALGOS)] == [ALGO_LABELS[a] for a in ALGOS]  # a row each, TD3's first
    assert 'SB3 SAC (EDE space)</td><td><span class="missing">missing</span>' in table
    against = table.split("<th>EDE-TD3 against</th>")[1].split("</table>")[0]
    compared = {row.split("</td>")[0]: row for row in against.split("<tr><td>")[1:]}
    assert list(compared) == ["TD3", "SB3 TD3 (EDE space)", "SB3 SAC"]  # those with runs
    for label, p in (
        ("TD3", "1 [1, 1]"),
        ("SB3 TD3 (EDE space)", "1 [1, 1]"),
        ("SB3 SAC", "0 [0, 0]"),
    ):
        assert compared[label].startswith(f"{label}</td><td>{p}</td><td>{p}</td>"), label
    assert page.count("<th>EDE-TD3 against</th>") == 1  # Pusher has no runs to set against
    # Then SB3's TD3 in the EDE space against TD3 on raw actions; its SAC there has no runs.
    space = table.split("<th>SB3 TD3 (EDE space) against</th>")[1].split("</table>")[0]
    (row,) = space.split("<tr><td>")[1:]
    assert row == "TD3</td><td>1 [1, 1]</td><td>1 [1, 1]</td><td>1, 0 (of 1)</td></tr>"
    assert "<th>SB3 SAC (EDE space) against</th>" not in page
    # The aggregates across tasks stay EDE-TD3 against TD3, the profile of those two.
    assert "<th>P(EDE-TD3 &gt; TD3)</th>" in page and 'id="performance-profile"' in page
    # The paper's pair alone: its report as it was, no table setting one against the other.
    write_params(lambda params: every_algorithm(params, PAPER_ALGOS))
    _, pair = report(project)
    assert "<th>EDE-TD3 against</th>" not in pair and "<td>SB3" not in pair


def test_a_tasks_intervals_do_not_depend_on_the_runs_of_tasks_before_it(
    project: Path, write_params
) -> None:
    def eight_seeds(params: dict) -> None:  # 8 seeds: percentiles that resampling noise moves
        params["runs"].update(
            tasks=TASKS,
            seeds=list(range(8)),
            budgets={"ede/ReacherVertical-v0": 2000, "ede/Pusher-v0": 2000},
        )
        params["report"].update(effect_space_family=None, exploration_family=None)

    def pusher_table(page: str) -> str:
        return page.split("<h4>ede/Pusher-v0")[1].split("</table>")[0]

    write_params(eight_seeds)
    for seed in range(8):
        for algo in ("td3", "ede-td3"):
            noise = np.random.default_rng([seed, len(algo)]).normal(0, 5, 3)
            fake_run(project, "ede/Pusher-v0", algo, seed, list(-50 + noise))
    _, alone = report(project)
    for seed in range(8):  # ReacherVertical's runs come first in the params: bootstrapped before
        for algo in PAPER_ALGOS:
            noise = np.random.default_rng([seed, 9]).normal(0, 3, 3)
            fake_run(project, "ede/ReacherVertical-v0", algo, seed, list(-20 + noise))
    _, beside = report(project)
    assert "<h4>ede/ReacherVertical-v0" in beside and "[" in pusher_table(alone)
    assert pusher_table(beside) == pusher_table(alone)


def with_policy(run: Path, algo: Algo, seed: int, embedding: Any, identity: str) -> None:
    """A final policy in ``run`` as train writes it: an untrained actor of the seed's weights,
    acting in the action box (TD3) or in the embedding's code box (EDE-TD3)."""
    from ede.method.td3 import Actor
    from ede.run.runs import write_policy
    from ede.tasks import action_bounds, make

    env = make("ede/Point-v0")
    low, high = action_bounds(env)
    if algo == "ede-td3":
        low, high = (
            -embedding.bound * np.ones(embedding.dim),
            embedding.bound * np.ones(embedding.dim),
        )
    obs_size = int(np.prod(env.observation_space.shape or ()))
    actor = Actor(obs_size, torch.tensor(low), torch.tensor(high), [32, 32])
    weights = actor.initial(torch.Generator().manual_seed(seed))
    meta = {
        "task": "ede/Point-v0",
        "algo": algo,
        "seed": seed,
        "embedding": identity if algo == "ede-td3" else "",
        "params": {"ede_td3": {"bound_scale": 1.0}},
        "k": embedding.k if algo == "ede-td3" else 1,
        "code_size": len(low),
        "code_low": [float(x) for x in low],
        "code_high": [float(x) for x in high],
        "hidden": [32, 32],
    }
    write_policy(run / "policy", actor.export(weights), meta)


def point_runs(project: Path, embeddings: Path, write_params, **report: Any) -> None:
    """Params of ede/Point-v0 alone, seeds 0-2, its family's embedding, and each run finished
    with a final policy; EDE-TD3's final returns make seed 2 the median."""
    from ede.run.artifacts import load_action_embedding

    def point(params: dict) -> None:
        params["runs"].update(tasks={"ede/Point-v0": "point"}, seeds=[0, 1, 2])
        params["runs"]["budgets"] = {"ede/Point-v0": 2000}
        params["report"].update(bootstrap_samples=200, **report)

    write_params(point)
    if (project / "data").exists():
        return
    shutil.copytree(embeddings / "data", project / "data")
    found, embedding = load_action_embedding(
        project / layout.encoder("point"), project / layout.decoder("point")
    )
    finals = {0: -30.0, 1: -10.0, 2: -20.0}
    for seed, final in finals.items():
        for algo in PAPER_ALGOS:
            run = fake_run(project, "ede/Point-v0", algo, seed, [-50, -40, final])
            identity = found.identity if algo == "ede-td3" else ""
            _edit_json(run / "run.json", lambda made, i=identity: made.update(embedding=i))
            with_policy(run, algo, seed, embedding, found.identity)


def test_each_task_shows_td3_beside_ede_td3_of_its_median_seed(
    project: Path, embeddings: Path, write_params
) -> None:
    import imageio.v3 as iio

    point_runs(project, embeddings, write_params)
    _, page = report(project)
    assert page.count("<video") == 1 and "<h4>ede/Point-v0, seed 2</h4>" in page
    video = iio.imread(project / "data/report/clip-ede_Point-v0.mp4", plugin="FFMPEG", index=None)
    assert video.shape == (100, 240, 480, 3)  # one 100-step episode of each, at half size
    # TD3 on the left, EDE-TD3 on the right: its bar where each of its codes starts, every k steps.
    top = video[:, :3].astype(float)
    mark = np.abs(top - np.array([255, 196, 0])).max(axis=-1) < 40  # (frames, 3 rows, 480)
    right = mark[:, :, 240:].mean(axis=(1, 2)) > 0.9
    assert list(right[:8]) == [True, False, False, False] * 2 and not mark[:, :, :240].any()

    point_runs(project, embeddings, write_params, videos=False)
    _, page = report(project)
    assert "Not drawn: <code>report.videos</code> is false." in page and "<video" not in page


@pytest.mark.skipif(shutil.which("chromium") is None, reason="Debian's chromium is not installed")
def test_a_clip_plays_in_headless_chromium(project: Path, embeddings: Path, write_params) -> None:
    point_runs(project, embeddings, write_params)
    _, page = report(project)
    tag = page[page.index("<video") : page.index("</video>") + len("</video>")]
    alone = project / "clip.html"  # the page's clip alone, so that the window shows it
    alone.write_text(
        f"<!DOCTYPE html><html><body style='margin:0;background:#fff'>{tag}</body></html>"
    )
    shot = project / "clip.png"
    result = subprocess.run(
        [
            "chromium",
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--no-first-run",
            f"--user-data-dir={project / 'chrome-profile'}",
            "--virtual-time-budget=3000",  # time for the clip to load and show a frame
            "--window-size=480,240",
            f"--screenshot={shot}",
            alone.as_uri(),
        ],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "HOME": str(project)},
    )
    assert result.returncode == 0, result.stderr
    import imageio.v3 as iio

    pixels = iio.imread(shot)[..., :3].astype(float)
    # A decoded frame: the scene's colours; a clip the browser cannot play leaves the page white.
    assert pixels.std() > 20 and pixels.mean() < 200, (pixels.std(), pixels.mean())
