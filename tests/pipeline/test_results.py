"""``ede-pipeline results``: docs/results.md's tables and figures, redrawn from per-run files."""

from __future__ import annotations

import json
import re
import shutil
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest
import torch
import yaml
from click.testing import CliRunner

from ede.analysis.results import arm
from ede.config import (
    ALGO_LABELS,
    ALGOS,
    EMBEDDED_ALGOS,
    Algo,
    EdeTD3Config,
    ReportConfig,
    TD3Config,
)
from ede.io.atomic import sha256
from ede.run.runs import PUBLISHED, write_curves, write_finished
from ede.run.spec import RunSpec
from ede_pipeline import layout
from ede_pipeline.cli import main
from ede_pipeline.published import read_folder
from tests.support import REPO

TASK = "ede/ReacherTurn-v0"
BUDGET = 20_000
# A task folder's source.json, unless a test writes its own: as those made before experiment files.
SOURCE = {"commit": "0123456789ab", "command": "experiment.py --seeds 0-3"}


EMBEDDING = "5e" * 32  # the decoder checksum an EDE-TD3 run's run.json names, unless told


def write_run(
    runs: Path,
    algo: str,
    seed: int,
    returns: np.ndarray,
    budget: int = BUDGET,
    task: str = TASK,
    machine: dict | None = None,
    embedding: str = EMBEDDING,
) -> None:
    """A finished run in the pipeline's layout (``runs/<task id>/<algo>/seed<N>/``), its run.json
    recording the SHA-256 of its files, as every run made since 2026-12 does (its wall times its
    own), and its seed named by its task's ``source.json`` (written where there is none yet)."""
    folder = layout.run(task, algo, seed, runs)
    folder.mkdir(parents=True)
    name_seed(runs, task, seed)
    steps = np.linspace(0, budget, len(returns))
    wall = zlib.crc32(f"{task} {algo} {seed}".encode()) / 1e6  # no two runs' curves one file
    rows = [
        f"{int(s)},{i},{r},1.0,{i + wall}"
        for i, (s, r) in enumerate(zip(steps, returns, strict=True))
    ]
    (folder / "eval.csv").write_text(
        "step,episode,mean_return,std_return,wall_seconds\n" + "\n".join(rows) + "\n"
    )
    (folder / "metrics.json").write_text(json.dumps({"final_return": float(returns[-1])}))
    (folder / "diagnostics.csv").write_text("step,updates,critic_loss,actor_loss,mean_q\n")
    made = {
        "task": task,
        "algo": algo,
        "seed": seed,
        "budget": budget,
        "embedding": embedding if algo in EMBEDDED_ALGOS else "",
        "sha256": {name: sha256(folder / name) for name in PUBLISHED if name != "run.json"},
    }
    if machine is not None:  # as run.json records it since 2026-12; the committed runs have none
        made["machine"] = machine
    (folder / "run.json").write_text(json.dumps(made))


def name_seed(runs: Path, task: str, seed: int) -> None:
    """``seed`` among those the task's ``source.json`` names (:data:`SOURCE`, where it has none
    yet; a list of parts is left as it is)."""
    path = layout.task_runs(task, runs) / "source.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    made = json.loads(path.read_text()) if path.is_file() else dict(SOURCE)
    if isinstance(made, dict):
        made["seeds"] = sorted({*made.get("seeds", []), seed})
        path.write_text(json.dumps(made))


class Done(NamedTuple):
    returncode: int
    stdout: str
    stderr: str


def write_source(runs: Path, task: str = TASK, **made: object) -> None:
    """``runs/<task>/source.json``: :data:`SOURCE` with ``made``'s keys, its seeds those of the
    runs there unless ``made`` names them."""
    folder = layout.task_runs(task, runs)
    seeds = sorted({int(run.name.removeprefix("seed")) for run in folder.glob("*/seed*")})
    (folder / "source.json").write_text(json.dumps({**SOURCE, "seeds": seeds, **made}))


BOOTSTRAP_SAMPLES = 200  # of params.yaml's 2,000: these tests check what the page says, and where


def results(runs: Path, figures: Path, *pages: Path) -> Done:
    """``ede-pipeline results`` on ``runs`` with the committed params at fewer bootstrap samples
    (written beside ``figures``), or, given ``pages``, filling them (their blocks name their runs);
    an exception other than click's exit is raised, not reported."""
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    params["report"]["bootstrap_samples"] = BOOTSTRAP_SAMPLES
    params_file = figures.parent / "params-results.yaml"
    params_file.write_text(yaml.safe_dump(params, sort_keys=False))
    where = [arg for page in pages for arg in ("--pages", str(page))] or [
        *("--runs", str(runs), "--figures", str(figures))
    ]
    done = CliRunner().invoke(main, ["results", *where, "--params", str(params_file)])
    if done.exception is not None and not isinstance(done.exception, SystemExit):
        raise done.exception
    return Done(done.exit_code, done.stdout, done.stderr)


def test_tables_name_the_bins_of_the_lead_and_the_seeds_that_diverged(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    x = np.linspace(0, 1, 41)
    for seed in range(4):
        noise = np.random.default_rng(seed).normal(0, 5, (2, len(x)))
        write_run(runs, "ede-td3", seed, -200 + 150 * x + noise[0])  # learns steadily
        td3 = np.where(x < 0.5, -200 + 100 * x, -150 - 100 * (x - 0.5))  # falls after half
        write_run(runs, "td3", seed, td3 + noise[1])
    for algo in ("td3", "ede-td3"):  # a task still running: one seed of each of its 4 so far
        write_run(runs, algo, 0, np.linspace(-200, -100, 41), task="ede/ReacherPush-v0")
    write_source(runs, "ede/ReacherPush-v0", seeds=[0, 1, 2, 3])

    done = results(runs, tmp_path / "figures")
    assert done.returncode == 0, done.stderr
    out = done.stdout
    assert "2.0% of the paper's 1,000,000; commit 0123456" in out
    assert "References: uniform random actions -2" in out and "zero actions -1" in out
    assert "| EDE-TD3 | 0–3 |" in out and "| TD3 | 0–3 |" in out
    # The same start, then EDE-TD3 ahead by up to 125 with noise of 5: its lead excludes 0 at
    # the end only.
    lead = out.split("EDE-TD3 − TD3 per bin, with its 95% bootstrap interval over seeds: ")[1]
    above, below = lead.split(".\n")[0].split(", below 0 in ")
    assert above.startswith("above 0 in ") and above.endswith("–20K)") and "(1K" not in above
    assert below == "none"
    overall = out.split("EDE-TD3 − TD3 overall: ")[1].split(" on the final return")[0]
    assert float(overall.split(" [")[1].split(",")[0]) > 0  # ahead at the end, interval and all
    # Every TD3 seed fell by more than half its gain, beyond its noise; no EDE-TD3 seed fell.
    verdicts = re.findall(r"^\| (TD3|EDE-TD3) \| \d \|.*\| (\S+) \| (\S+) \|$", out, re.M)
    assert verdicts[:8] == [("TD3", "**yes**", "**yes**")] * 4 + [("EDE-TD3", "no", "no")] * 4
    assert (
        "P(EDE-TD3 > TD3) over this task's seeds (rliable, as the aggregates across tasks): "
        "1 [1, 1] on the final return" in task_table(out, TASK)
    )
    turn = out.split("### ede/ReacherPush-v0")[0]
    assert "| EDE-TD3 | 0 | " in turn and turn.count("| no | no |") == 4
    # The last quarter's mean over seeds is the mean of the seed table's last column, and it
    # puts TD3's fall (to about -175) below EDE-TD3's climb (to about -70), intervals apart.
    late = turn.split("the asymptote, as far as this budget shows it): ")[1].split(".\n")[0]
    intervals = {
        name: tuple(map(float, numbers))
        for name, *numbers in re.findall(r"([A-Z0-9-]+) (\S+) \[(\S+), (\S+)\]", late)
    }
    for name in ("TD3", "EDE-TD3"):
        column = [
            float(row.split(" | ")[4])
            for row in turn.splitlines()
            if row.startswith(f"| {name} | ") and row.count(" | ") == 8
        ]
        assert len(column) == 4 and intervals[name][0] == pytest.approx(np.mean(column), abs=0.1)
    assert intervals["TD3"][2] < -150 < intervals["EDE-TD3"][1]
    assert (tmp_path / "figures" / "reacher.png").stat().st_size > 10_000
    # Across tasks (ReacherTurn's; ReacherPush waits for its seeds): every EDE-TD3 seed ends
    # above every TD3 seed, so P is 1 at both ends.
    across = out.split("### Across tasks: the reacher family")[1]
    assert "1 task (ede/ReacherTurn-v0); per task 4 of EDE-TD3 and 4 of TD3" in across
    assert (
        "Not yet in these aggregates, with runs of an algorithm still to finish: "
        "ede/ReacherPush-v0 (1 of its 4 seeds)." in across
    )
    final = across.split("| final return | ")[1].split(" |")
    assert final[0] == "1 [1, 1]" and float(final[1].split()[0]) > float(final[2].split()[0])
    assert (tmp_path / "figures" / "performance-profile.png").stat().st_size > 10_000


def test_runs_of_different_budgets_are_refused_by_name(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    write_run(runs, "td3", 0, np.zeros(21))
    write_run(runs, "td3", 1, np.zeros(21), budget=2 * BUDGET)
    done = results(runs, tmp_path / "figures")
    assert done.returncode == 2 and "runs of different budgets [20000, 40000]" in done.stderr
    assert "Traceback" not in done.stderr and not (tmp_path / "figures").exists()


def test_the_committed_pusher_runs_decline_alike_at_every_bin_width() -> None:
    # Pusher at 10⁶ steps, where the binned rule this one replaced flagged 0 to 3 of TD3's 4
    # seeds as the bins went from 20K to 100K steps.
    found = read_folder(REPO / "docs" / "results" / "1e6" / "runs", "ede/Pusher-v0")
    assert found is not None
    report = ReportConfig(bootstrap_samples=BOOTSTRAP_SAMPLES)
    verdicts = {
        width: {
            algo: [d and (d.declined, d.diverged) for d in arm(runs, [], width, report).divergence]
            for algo, runs in found.curves.items()
        }
        for width in (20_000, 25_000, 40_000, 50_000, 100_000)
    }
    assert all(each == verdicts[50_000] for each in verdicts.values())
    # Every TD3 seed fell (by 4.0 to 6.5), three beyond what their own noise reaches (seed 1's
    # 4.0 within its 6.1), none by half its gain; no EDE-TD3 seed fell.
    assert verdicts[50_000] == {
        "td3": [(True, False), (False, False), (True, False), (True, False)],
        "ede-td3": [(False, False)] * 4,
    }


def blocks(page: str) -> list[tuple[str, str, str]]:
    """A page's blocks: each one's runs folder, section heading and content."""
    return re.findall(r"<!-- results (\S+): (.*?) -->\n(.*?)<!-- /results -->\n", page, re.S)


def resampled(block: str) -> str:
    """A block with what its bootstrap's resamples decide blanked: each interval's ends, the bins
    where a lead's interval excludes 0 and how many there are, and how many resamples."""
    block = re.sub(r"\[[^\]]*\]", "[…]", block)
    block = re.sub(r"\d+ resamples", "… resamples", block)
    block = re.sub(
        r"^(.* per bin, with its \d+% bootstrap interval over seeds:).*$",
        r"\1 …",
        block,
        flags=re.M,
    )
    return re.sub(r"\| \d+, \d+ \(of \d+\) \|", "| … |", block)


NUMBER = r"-?\d+\.\d"  # a return, as a clip's block prints it


def played(block: str) -> tuple[str, list[float]]:
    """A clip's block: its words, and its returns apart. Its episodes are played again here, and a
    policy's actions take the last bits of this CPU's kernels, so a return may round the other way:
    the one step of 0.1 the block prints. Measured (2026-12-06, one AMD EPYC): every action of a
    clip's episode scaled by 1 + 1e-6·N(0, 1), a few float32 ulps, moved its return by under
    0.0001 on ReacherVertical, ReacherPush and Pusher, at most 0.0003 on Striker and 0.008 on
    ReacherTurn (TD3's; six draws a policy, seed 4's TD3 and EDE-TD3:
    `python benchmarks/clip_sensitivity.py`)."""
    return re.sub(NUMBER, "…", block), [float(n) for n in re.findall(NUMBER, block)]


@pytest.mark.slow
def test_the_committed_pages_redraw(tmp_path: Path) -> None:
    import imageio.v3 as iio

    # The pages, copied, beside the committed runs folders, linked where they lie in docs/.
    docs = tmp_path / "docs"
    for above in ("1e6", "any-agent"):
        (docs / "results" / above).mkdir(parents=True)
    shutil.copy(REPO / "docs" / "results.md", docs)
    for page in (REPO / "docs" / "results").glob("*.md"):
        shutil.copy(page, docs / "results")
    for folder in ("runs", "ablations", "1e6/runs", "any-agent/runs", "clips"):
        (docs / "results" / folder).symlink_to(REPO / "docs" / "results" / folder)
    done = results(tmp_path, tmp_path / "figures", docs / "results.md", docs / "results")
    assert done.returncode == 0, done.stderr
    pages = [docs / "results.md", *sorted((docs / "results").glob("*.md"))]
    for page in pages:
        committed = (REPO / page.relative_to(tmp_path)).read_text()
        redrawn = page.read_text()
        # The words around the blocks are the author's, and each block is the command's: the same
        # but for its resamples (drawn here at fewer than the committed params' 2,000), and for a
        # clip's returns, played again on this CPU (:func:`played`).
        assert re.split(r"<!-- results .*?<!-- /results -->\n", redrawn, flags=re.S) == re.split(
            r"<!-- results .*?<!-- /results -->\n", committed, flags=re.S
        )
        for (runs, heading, block), kept in zip(blocks(redrawn), blocks(committed), strict=True):
            if not heading.startswith("Clip: "):
                assert (runs, heading, resampled(block)) == (kept[0], kept[1], resampled(kept[2]))
                continue
            (words, returns), (kept_words, kept_returns) = played(block), played(kept[2])
            assert (runs, heading, words) == (kept[0], kept[1], kept_words), page.name
            assert np.allclose(returns, kept_returns, rtol=0, atol=0.1 + 1e-9), heading
    # Each clip a page links is drawn again as committed: its frames' count and size, and an
    # episode that moves.
    linked = {
        name for page in pages for name in re.findall(r"\]\((clip-\S+\.gif)\)", page.read_text())
    }
    assert linked, "no page shows a clip"
    for name in linked:
        clip = iio.imread(docs / "results" / name, index=None)
        assert clip.shape == iio.imread(REPO / "docs" / "results" / name, index=None).shape
        assert np.abs(clip[0].astype(int) - clip[-1].astype(int)).max() > 50, name
    # Every task with published runs has its section on a page, its runs folder's as it lies, and
    # every task with published policies its clip.
    placed = {(runs, heading) for page in pages for runs, heading, _ in blocks(page.read_text())}
    for folder in ("runs", "1e6/runs", "any-agent/runs", "clips"):
        made = REPO / "docs" / "results" / folder
        for record in made.rglob("seed*/run.json"):
            task = json.loads(record.read_text())["task"]
            if folder != "clips":
                assert (folder, task) in placed or (f"results/{folder}", task) in placed, task
            if (record.parent / "policy").is_dir():
                assert (folder, f"Clip: {task}") in placed, task


@pytest.mark.slow
def test_a_page_plays_only_the_clips_it_shows(tmp_path: Path) -> None:
    """A page showing one clip of a folder that holds several plays and writes that one alone:
    redrawing one page leaves the GIFs other pages link as they are (another CPU would draw
    them again at other last bits)."""
    clips = REPO / "docs" / "results" / "clips"
    assert len(list((clips / "ede").iterdir())) > 1  # the committed folder: more than one clip
    folder = tmp_path / "results"
    folder.mkdir()
    (folder / "clips").symlink_to(clips)
    page = folder / "page.md"
    page.write_text(
        "# One clip\n\n<!-- results clips: Clip: ede/ReacherVertical-v0 -->\n<!-- /results -->\n"
    )
    done = results(tmp_path, tmp_path / "figures", page)
    assert done.returncode == 0, done.stderr
    assert [p.name for p in folder.glob("*.gif")] == ["clip-ede_ReacherVertical-v0.gif"]
    assert "](clip-ede_ReacherVertical-v0.gif)" in page.read_text()


def task_table(out: str, task: str) -> str:
    """One task's section of the output."""
    return out.split(f"### {task}\n")[1].split("\n### ")[0]


def test_a_tasks_numbers_do_not_depend_on_the_other_tasks_present(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    for seed in range(8):  # enough for the bootstrap's percentiles not to fall on the same means
        for algo in ("td3", "ede-td3"):
            write_run(
                runs, algo, seed, np.random.default_rng([seed, len(algo)]).normal(-100, 20, 21)
            )
    alone = results(runs, tmp_path / "figures")
    assert alone.returncode == 0, alone.stderr
    # ReacherVertical comes first in params.yaml: its bootstraps run before ReacherTurn's; and
    # ReacherTurn gains a threshold, bootstrapped between its final returns and its bands.
    for seed in range(3):
        for algo in ("td3", "ede-td3"):
            write_run(
                runs,
                algo,
                seed,
                np.random.default_rng(seed + 7).normal(-20, 5, 21),
                budget=50_000,
                task="ede/ReacherVertical-v0",
            )
    write_source(runs, thresholds=[-110])
    beside = results(runs, tmp_path / "figures")
    assert beside.returncode == 0, beside.stderr
    assert beside.stdout.index("### ede/ReacherVertical-v0") < beside.stdout.index(
        "### ede/ReacherTurn-v0"
    )
    with_threshold = task_table(beside.stdout, "ede/ReacherTurn-v0")
    assert "| steps to reach -110 |" in with_threshold

    def first_columns(section: str) -> list[str]:  # every table cut to its first four columns
        return ["|".join(line.split("|")[:5]) for line in section.splitlines()]

    assert first_columns(with_threshold) == first_columns(
        task_table(alone.stdout, "ede/ReacherTurn-v0")
    )


def test_a_task_run_with_more_seeds_joins_the_aggregates_with_as_many_as_the_others(
    tmp_path: Path,
) -> None:
    runs = tmp_path / "runs"
    # Both finished; each ends above its random policy's return (-93 and -210).
    for task, seeds, start in (("ede/ReacherVertical-v0", 8, -60), (TASK, 4, -200)):
        for seed in range(seeds):
            write_run(runs, "td3", seed, np.linspace(start, start / 2 - seed, 21), task=task)
            write_run(runs, "ede-td3", seed, np.linspace(start, start / 4 - seed, 21), task=task)
        write_source(runs, task, seeds=list(range(seeds)))
    done = results(runs, tmp_path / "figures")
    assert done.returncode == 0, done.stderr
    across = done.stdout.split("### Across tasks: the reacher family")[1]
    assert (
        "2 tasks (ede/ReacherVertical-v0, ede/ReacherTurn-v0); per task 4 of EDE-TD3 and 4 "
        "of TD3" in across
    )
    assert (
        "Left out: ede/ReacherVertical-v0 EDE-TD3 seeds 4, 5, 6, 7; ede/ReacherVertical-v0 "
        "TD3 seeds 4, 5, 6, 7." in across
    )
    assert "Not yet in these aggregates" not in across
    assert "| final return | 1 [1, 1] |" in across  # every EDE-TD3 run ends above every TD3 run


def test_every_algorithm_of_a_task_has_its_row_and_ede_td3_is_set_against_each(
    tmp_path: Path,
) -> None:
    """stable-baselines3's agents beside the paper's pair: a row each, EDE-TD3 against each other
    algorithm, a table at a glance per algorithm naming the task without its runs; the pair's
    lines as they are without them, and the aggregates still EDE-TD3 against TD3."""
    x = np.linspace(0, 1, 21)
    gains = {"td3": 50, "ede-td3": 150, "sb3-td3-ede": 100, "sb3-sac": 0, "sb3-sac-ede": 200}
    for runs, algos in ((tmp_path / "pair", ("td3", "ede-td3")), (tmp_path / "arms", gains)):
        for seed in range(3):
            noise = np.random.default_rng(seed).normal(0, 2, len(x))
            for algo in algos:  # ReacherTurn: every algorithm; ReacherPush: the pair alone
                write_run(runs, algo, seed, -200 + gains[algo] * x + noise)
            for algo in ("td3", "ede-td3"):
                write_run(runs, algo, seed, -200 + gains[algo] * x, task="ede/ReacherPush-v0")
    pair = results(tmp_path / "pair", tmp_path / "pair-figures")
    arms = results(tmp_path / "arms", tmp_path / "arms-figures")
    assert pair.returncode == 0 and arms.returncode == 0, arms.stderr
    turn = task_table(arms.stdout, TASK)
    rows = [line.split(" | ")[0] for line in turn.splitlines() if " | 0–2 | " in line]
    assert rows == [f"| {ALGO_LABELS[a]}" for a in ALGOS]  # ALGOS' order, TD3's first
    for algo in (*ALGOS[2:], "td3"):
        label = ALGO_LABELS[algo]
        against = f"P(EDE-TD3 > {label}) over this task's seeds (rliable, as the aggregates"
        assert turn.count(against) == 1
        p = turn.split(against)[1].split(" on the final return")[0].removeprefix(" across tasks): ")
        # Every EDE-TD3 run ends above every run of TD3 and SB3's agents but SAC in the EDE space.
        assert p == ("0 [0, 0]" if algo == "sb3-sac-ede" else "1 [1, 1]"), label
        assert f"EDE-TD3 − {label} per bin, with its 95% bootstrap interval over seeds: " in turn
    # The pair's rows and the lines setting one against the other are as they are without the rest.

    def pairs(section: str) -> list[str]:
        return [
            line
            for line in section.splitlines()
            if line.startswith(("| TD3 |", "| EDE-TD3 |", "P(EDE-TD3 > TD3) "))
            or line.startswith("EDE-TD3 − TD3 ")
        ]

    assert len(pairs(turn)) == 11 and pairs(turn) == pairs(task_table(pair.stdout, TASK))
    push = "ede/ReacherPush-v0"
    assert section(arms.stdout, push) == section(pair.stdout, push)
    # At a glance: the pair's table as it is, then one per other algorithm, each naming the task
    # without its runs (and after them the EDE space's against raw actions, as the next test has).
    glance = section(arms.stdout, "The tasks at a glance")
    alone = section(pair.stdout, "The tasks at a glance")
    assert glance.startswith(alone)
    tables = glance.removeprefix(alone).strip("\n").split("\n\n")[: 2 * len(ALGOS[2:])]
    assert [table.split(" | ")[3] for table in tables[::2]] == [
        f"final return, {ALGO_LABELS[a]}" for a in ALGOS[2:]
    ]
    assert tables[1::2] == [
        f"No runs of {ALGO_LABELS[a]} on ede/ReacherPush-v0." for a in ALGOS[2:]
    ]
    assert "| ede/ReacherTurn-v0 | 20,000 (2.0% of the paper's) | 0–2 | " in tables[0]
    # The aggregates across tasks stay EDE-TD3 against TD3.
    assert section(arms.stdout, "Across tasks: the reacher family") == section(
        pair.stdout, "Across tasks: the reacher family"
    )


def test_each_algorithm_in_the_ede_space_is_set_against_the_same_learner_on_raw_actions(
    tmp_path: Path,
) -> None:
    """After EDE-TD3 against each other algorithm, SB3's TD3 in the EDE space against TD3 and
    SB3's SAC in the EDE space against SB3's SAC on raw actions: each pair's lines under its names,
    with the sign its runs have, and a table at a glance each, after a line saying what they are;
    a task with SB3's SAC in the EDE space and none on raw actions sets it against nothing, and
    under each table at a glance the tasks without it are named by what they have no runs of."""
    x = np.linspace(0, 1, 21)
    # The EDE space hurts SB3's TD3 (below TD3 at every step after the first) and helps its SAC.
    gains = {"td3": 100, "ede-td3": 150, "sb3-td3-ede": 20, "sb3-sac": 0, "sb3-sac-ede": 200}
    runs, push, vertical = tmp_path / "runs", "ede/ReacherPush-v0", "ede/ReacherVertical-v0"
    tasks = {  # ReacherTurn: every algorithm; ReacherPush: all but SB3's SAC; ReacherVertical: SAC's
        TASK: list(gains),
        push: [a for a in gains if a != "sb3-sac"],
        vertical: ["sb3-sac", "sb3-sac-ede"],
    }
    for seed in range(3):
        noise = np.random.default_rng(seed).normal(0, 2, len(x))
        for task, algos in tasks.items():
            for algo in algos:
                write_run(runs, algo, seed, -200 + gains[algo] * x + noise, task=task)
    done = results(runs, tmp_path / "figures")
    assert done.returncode == 0, done.stderr
    td3_space, sac_space, sac = (ALGO_LABELS[a] for a in ("sb3-td3-ede", "sb3-sac-ede", "sb3-sac"))

    def compared(section: str) -> dict[str, str]:  # P(… > …) per pair, as its line has it
        return {
            line.split(" over")[0]: line.split("tasks): ")[1]
            for line in section.splitlines()
            if line.startswith("P(")
        }

    turn = task_table(done.stdout, TASK)
    p_turn = compared(turn)
    assert list(p_turn) == [
        *(f"P(EDE-TD3 > {ALGO_LABELS[a]})" for a in ALGOS if a != "ede-td3"),
        f"P({td3_space} > TD3)",
        f"P({sac_space} > {sac})",
    ]
    every = "{0} on the final return and {0} on the area under the curve."
    assert p_turn[f"P({td3_space} > TD3)"] == every.format("0 [0, 0]")
    assert p_turn[f"P({sac_space} > {sac})"] == every.format("1 [1, 1]")
    for ours, theirs, side in ((td3_space, "TD3", "below"), (sac_space, sac, "above")):
        per_bin = f"{ours} − {theirs} per bin, with its 95% bootstrap interval over seeds: "
        (line,) = [line for line in turn.splitlines() if line.startswith(per_bin)]
        other = "above" if side == "below" else "below"
        assert f"{side} 0 in 20 of 20 bins (1K–20K)" in line and f"{other} 0 in none" in line
        assert f"{ours} − {theirs} overall: " in turn
    p_push = compared(task_table(done.stdout, push))
    assert list(p_push) == [
        *(f"P(EDE-TD3 > {ALGO_LABELS[a]})" for a in ("td3", "sb3-td3-ede", "sb3-sac-ede")),
        f"P({td3_space} > TD3)",
    ]
    assert f"{sac_space} − {sac}" not in task_table(done.stdout, push)
    assert list(compared(task_table(done.stdout, vertical))) == [f"P({sac_space} > {sac})"]
    # At a glance: after EDE-TD3's tables, a line and the EDE space's against raw actions; under
    # each, the tasks without its pair, by what they have no runs of.
    glance = section(done.stdout, "The tasks at a glance").rstrip("\n").split("\n\n")
    assert [part for part in glance if part.startswith("No runs")] == [
        f"No runs of EDE-TD3 or TD3 on {vertical}.",
        f"No runs of EDE-TD3 or {td3_space} on {vertical}.",
        f"No runs of EDE-TD3 on {vertical}.",
        f"No runs of EDE-TD3 on {vertical}.",
        f"No runs of {sac} on {push}.",
        f"No runs of {td3_space} or TD3 on {vertical}.",
        f"No runs of {sac} on {push}.",
    ]
    start = glance.index(
        "Each other algorithm in the EDE space against the same learner on raw actions: a bin "
        "counts where the interval of its lead (its mean minus the learner's) lies above 0, or "
        "below."
    )
    td3_table, _, sac_table, _ = glance[start + 1 :]
    assert f"| final return, TD3 | final return, {td3_space} | P({td3_space} > TD3), " in td3_table
    assert f"| final return, {sac} | final return, {sac_space} | P({sac_space} > {sac}), " in (
        sac_table
    )
    for table, p, drawn in (
        (td3_table, "0 [0, 0]", [TASK, push]),
        (sac_table, "1 [1, 1]", [vertical, TASK]),
    ):
        rows = table.splitlines()[2:]
        assert [row.split(" | ")[0] for row in rows] == [f"| {t}" for t in drawn]
        assert all(row.split(" | ")[5:7] == [p, p] for row in rows)


def test_a_task_beyond_the_paper_is_its_own_family_with_its_thresholds(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    x = np.linspace(0, 1, 21)
    for seed in range(3):
        write_run(runs, "ede-td3", seed, -1200 + 1100 * np.sqrt(x) + seed, task="Pendulum-v1")
        write_run(runs, "td3", seed, -1200 + 1100 * x + seed, task="Pendulum-v1")
    write_source(runs, "Pendulum-v1", thresholds=[-600, -50])
    for algo in ("td3", "ede-td3"):  # and a task of the paper's, beside it
        for seed in range(3):
            write_run(runs, algo, seed, np.linspace(-200, -100 - 20 * (algo == "ede-td3"), 21))

    done = results(runs, tmp_path / "figures")
    assert done.returncode == 0, done.stderr
    table = task_table(done.stdout, "Pendulum-v1")
    assert (
        "pendulum family, its own (beyond the paper). 20,000 steps a run; commit 0123456" in table
    )
    assert "| steps to reach -600 | steps to reach -50 |" in table
    # EDE-TD3 passes -600 at x = 0.3 (6,000 steps), TD3 at x = 0.55 (11,000): the same for every
    # seed, so the intervals are points; neither reaches -50.
    rows = {line.split(" | ")[0]: line for line in table.splitlines() if " | 0–2 | " in line}
    assert rows["| EDE-TD3"].endswith("| 6,000 [6,000, 6,000] | never [never, never] |")
    assert rows["| TD3"].endswith("| 11,000 [11,000, 11,000] | never [never, never] |")
    assert (tmp_path / "figures" / "pendulum.png").stat().st_size > 10_000
    assert "### Across tasks: the pendulum family" in done.stdout
    every = done.stdout.split("### Across tasks: every task")[1]
    assert "2 tasks (ede/ReacherTurn-v0, Pendulum-v1)" in every


def test_an_ablation_is_set_against_the_defaults_runs_of_the_same_seeds(tmp_path: Path) -> None:
    runs, ablations = tmp_path / "runs", tmp_path / "ablations"
    x = np.linspace(0, 1, 21)
    for seed in range(4):  # the default: seeds 0-3, each ending at -100 - 10 * seed
        write_run(runs, "ede-td3", seed, -200 + (100 - 10 * seed) * x)
        write_run(runs, "td3", seed, -200 + 50 * x)
    for seed in (0, 1):  # the variant: seeds 0 and 1 of EDE-TD3, learning twice as fast
        write_run(ablations / "fast", "ede-td3", seed, -200 + 150 * np.sqrt(x) + seed)
    write_source(
        ablations / "fast",
        commit="fedcba987654",
        command="experiment.py --variant fast:x=1",
        thresholds=[-150],
    )
    embedding = layout.published_embedding(TASK, EMBEDDING, ablations / "fast")
    embedding.mkdir(parents=True)
    (embedding / "encoder_metrics.json").write_text(
        json.dumps({"prediction_ratio": 0.7021, "kl": 7.94})
    )
    for algo in ("td3", "ede-td3"):  # a variant of both algorithms, drawn as a family is
        write_run(ablations / "both", algo, 0, -200 + 20 * x)
    write_source(ablations / "both", commit="0")

    done = results(runs, tmp_path / "figures")
    assert (tmp_path / "figures" / "ablation-both.png").stat().st_size > 10_000
    assert not (tmp_path / "figures" / "ablation-fast.png").exists()  # EDE-TD3 alone: no figure
    assert done.returncode == 0, done.stderr
    section = done.stdout.split("### fast: ede/ReacherTurn-v0, EDE-TD3\n")[1]
    assert (
        "20,000 steps a run, seeds 0, 1 of each; the variant's command `experiment.py --variant fast:x=1`"
        in section
    )
    rows = {
        line.split(" | ")[0]: line.split(" | ")
        for line in section.splitlines()
        if line.startswith("| ")
    }
    # The default's seeds 0 and 1 only (-100 and -110): not seeds 2 and 3 (-120, -130).
    assert rows["| default"][1] == "0123456; —" and rows["| default"][2].startswith("-105 [")
    assert rows["| fast"][1] == "fedcba9; prediction ratio 0.702, KL 7.9 nats"
    assert rows["| fast"][2].startswith("-49.5 [")
    # -150 first reached at x = 0.15 by the variant (3,000 steps), at x = 0.5 and 0.6 by the default.
    assert rows["| fast"][4] == "3,000 [3,000, 3,000] |" and rows["| default"][4].startswith(
        "11,000 ["
    )
    assert "### fast: ede/ReacherTurn-v0, TD3" not in done.stdout  # the variant ran no TD3
    assert (
        "fast − the default per bin, with its 95% bootstrap interval over seeds: above 0 in 20 of "
        "20 bins (1K–20K), below 0 in none." in section
    )


def test_a_source_written_by_experiment_export_names_its_file_and_commits(tmp_path: Path) -> None:
    runs, ablations = tmp_path / "runs", tmp_path / "ablations"
    for algo in ("td3", "ede-td3"):
        write_run(runs, algo, 0, np.linspace(-200, -100, 21))
        write_run(ablations / "fast", algo, 0, np.linspace(-200, -90, 21))
    # As `ede-pipeline experiment export` writes it, of runs made at two commits.
    made = {
        "experiment": "experiments/turn.yaml",
        "commit": ["0123456789ab", "fedcba987654"],
        "seeds": [0],
    }
    (layout.task_runs(TASK, runs) / "source.json").write_text(json.dumps(made))
    variant = {"experiment": "experiments/fast.yaml", "commit": "fedcba987654", "seeds": [0]}
    (layout.task_runs(TASK, ablations / "fast") / "source.json").write_text(json.dumps(variant))
    done = results(runs, tmp_path / "figures")
    assert done.returncode == 0, done.stderr
    assert (
        "2.0% of the paper's 1,000,000; experiment `experiments/turn.yaml`, commits 0123456, "
        "fedcba9; curves binned per 1,000 steps."
    ) in task_table(done.stdout, TASK)
    section = done.stdout.split("### fast: ede/ReacherTurn-v0, TD3\n")[1]
    assert "seeds 0 of each; the variant's experiment `experiments/fast.yaml`; curves" in section
    rows = {
        line.split(" | ")[0]: line.split(" | ")
        for line in section.splitlines()
        if line.startswith("| ")
    }
    assert rows["| default"][1] == "0123456, fedcba9; —" and rows["| fast"][1] == "fedcba9; —"


def test_a_task_whose_seeds_came_from_two_experiments_names_each_and_its_embedding(
    tmp_path: Path,
) -> None:
    """Seeds added by a second experiment (``experiment export`` merges its part into the task's
    source.json): the task names which seeds each part made, and the held-out figures of each
    embedding its EDE-TD3 seeds used, found by the checksum their run.json names."""
    runs = tmp_path / "runs"
    other = "a1" * 32
    for seed in range(4):
        write_run(runs, "td3", seed, np.linspace(-200, -100, 21))
        write_run(
            runs,
            "ede-td3",
            seed,
            np.linspace(-200, -90, 21),
            embedding=EMBEDDING if seed < 2 else other,
        )
    parts = [
        {
            "experiment": "experiments/turn.yaml",
            "commit": "0123456789ab",
            "seeds": [0, 1],
            "thresholds": [-150],
        },
        {
            "command": "experiment.py --seeds 2-3",
            "commit": "fedcba987654",
            "seeds": [2, 3],
            "thresholds": [-120, -150],
        },
    ]
    (layout.task_runs(TASK, runs) / "source.json").write_text(json.dumps(parts))
    for checksum, ratio in ((EMBEDDING, 0.125), (other, 0.25)):
        kept = layout.published_embedding(TASK, checksum, runs)
        kept.mkdir(parents=True)
        (kept / "encoder_metrics.json").write_text(
            json.dumps({"prediction_ratio": ratio, "kl": 8.0})
        )
    done = results(runs, tmp_path / "figures")
    assert done.returncode == 0, done.stderr
    table = task_table(done.stdout, TASK)
    assert (
        "seeds 0, 1 by experiment `experiments/turn.yaml`, commit 0123456; seeds 2, 3 by "
        "commit fedcba9; curves binned"
    ) in table
    assert (
        "Its embedding, held out: seeds 0, 1: prediction ratio 0.125, KL 8.0 nats; seeds 2, 3: "
        "prediction ratio 0.250, KL 8.0 nats."
    ) in table
    header = next(line for line in table.splitlines() if line.startswith("| algorithm"))
    assert header.count("reach -150 |") == 1 and "reach -120 |" in header  # each part's, once


def test_each_task_names_the_cpus_that_made_its_runs(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    xeon = {
        "cpu": "Intel(R) Xeon(R) Processor",
        "instruction_sets": ["avx2", "avx512f"],
        "torch_cpu_capability": "AVX512",
        "torch_threads": 1,
        "gpu": None,
    }
    write_run(runs, "td3", 0, np.linspace(-200, -100, 21), machine=xeon)
    write_run(runs, "td3", 1, np.linspace(-200, -100, 21), machine=xeon)
    write_run(
        runs,
        "ede-td3",
        0,
        np.linspace(-200, -90, 21),
        machine={**xeon, "cpu": "AMD EPYC 7B13", "instruction_sets": []},
    )
    write_run(runs, "ede-td3", 1, np.linspace(-200, -90, 21))  # made before run.json named it
    done = results(runs, tmp_path / "figures")
    assert done.returncode == 0, done.stderr
    table = task_table(done.stdout, TASK)
    assert (
        "\nRuns made on: Intel(R) Xeon(R) Processor (avx2, avx512f): 2; AMD EPYC 7B13 (none of "
        "avx2, avx512f, avx512_bf16, amx_tile, amx_bf16): 1; CPU unrecorded: 1.\n" in table
    )
    # After the line naming the commit, before the table.
    assert (
        table.index("commit 0123456") < table.index("Runs made on") < table.index("| algorithm |")
    )


def test_an_ablation_without_the_defaults_seeds_is_refused_by_name(tmp_path: Path) -> None:
    runs, ablations = tmp_path / "runs", tmp_path / "ablations"
    write_run(runs, "ede-td3", 0, np.zeros(21))
    write_run(ablations / "fast", "ede-td3", 3, np.zeros(21))
    write_source(ablations / "fast", commit="0")
    done = results(runs, tmp_path / "figures")
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert "the default's runs of seeds [3] are not all in" in done.stderr
    assert not (tmp_path / "figures").exists()  # refused before the default's figure is drawn


def test_a_task_alone_never_joins_a_family_of_the_papers_and_one_seed_claims_no_interval(
    tmp_path: Path,
) -> None:
    runs = tmp_path / "runs"
    for algo in ("td3", "ede-td3"):  # gymnasium's Reacher-v5 would be family "reacher"
        write_run(runs, algo, 0, np.linspace(-50, -5 - 5 * (algo == "td3"), 21), task="Reacher-v5")
    done = results(runs, tmp_path / "figures")
    assert done.returncode == 0, done.stderr
    assert "reacher-v5 family, its own (beyond the paper)" in done.stdout
    assert (tmp_path / "figures" / "reacher-v5.png").is_file()
    assert not (tmp_path / "figures" / "reacher.png").exists()
    assert "per bin, with its" not in done.stdout  # one seed each: no interval of the lead


def bad_input_cases() -> dict[str, tuple]:
    """Each case: what to break in a folder of good runs, and the line expected."""

    def source(value: object) -> Callable[[Path], object]:
        return lambda runs: (layout.task_runs(TASK, runs) / "source.json").write_text(
            json.dumps(value)
        )

    def embedding(runs: Path) -> None:
        kept = layout.published_embedding(TASK, EMBEDDING, runs)
        kept.mkdir(parents=True)
        (kept / "encoder_metrics.json").write_text("{}")

    def unknown_task(runs: Path) -> None:
        for algo in ("td3", "ede-td3"):
            write_run(runs, algo, 0, np.zeros(21), task="HalfCheetah-v99")

    def machine(runs: Path) -> None:
        made = layout.run(TASK, "td3", 0, runs) / "run.json"
        made.write_text(json.dumps({**json.loads(made.read_text()), "machine": "a laptop"}))

    def unknown_algorithm(runs: Path) -> None:  # SB3's TD3 in the EDE space, misnamed
        shutil.copytree(
            layout.run(TASK, "td3", 0, runs).parent, layout.task_runs(TASK, runs) / "sb3-td3"
        )

    def misplaced(runs: Path) -> None:  # beside its own folder, under another task's name
        shutil.copytree(layout.task_runs(TASK, runs), runs / "ede" / "ReacherTurn-v1")

    return {
        "machine": (
            machine,
            "run.json: 'machine' is 'a laptop'; expected its 'cpu' and 'instruction_sets'",
        ),
        "no commit": (
            source({"command": "experiment.py"}),
            "source.json: expected JSON naming the 'commit'",
        ),
        "no commits": (
            source({"commit": [], "experiment": "experiments/a.yaml"}),
            "source.json: expected JSON naming the 'commit' that made the runs beside it "
            "(a string, or a list of them)",
        ),
        "no maker": (
            source({"commit": "0123456"}),
            "source.json: expected the 'experiment' file (or the 'command') that made",
        ),
        "experiment": (
            source(
                {
                    "commit": ["0123456"],
                    "experiment": ["experiments/a.yaml"],
                    "command": "experiment.py",
                }
            ),
            "source.json: expected the 'experiment' file (or the 'command') that made",
        ),
        "thresholds": (
            source({**SOURCE, "thresholds": "150"}),
            "source.json: 'thresholds' is '150'; expected a list of returns",
        ),
        "seeds": (
            source({**SOURCE, "seeds": [0, -1]}),
            "source.json: 'seeds' is [0, -1]; expected a list of seeds (whole numbers >= 0)",
        ),
        "seed twice": (
            source([{**SOURCE, "seeds": [0, 1]}, {**SOURCE, "seeds": [1, 2]}]),
            "source.json: seeds [1] are named by two of its parts; expected each seed made by one",
        ),
        "no parts": (source([]), "source.json: an empty list; expected what made the runs"),
        "embedding": (embedding, f"embedding/{EMBEDDING[:12]}: expected pretrain's metrics"),
        "unknown task": (
            unknown_task,
            "HalfCheetah-v99: cannot be made to measure its reference returns",
        ),
        "unknown algorithm": (
            unknown_algorithm,
            "ReacherTurn-v0/sb3-td3: runs of no algorithm known here; expected a folder per "
            "algorithm, named one of td3, ede-td3, sb3-td3-ede, sb3-sac-ede, sb3-sac",
        ),
        "misplaced": (
            misplaced,
            "ReacherTurn-v1: its runs are of ede/ReacherTurn-v0; keep them in ",
        ),
    }


@pytest.mark.parametrize("case", list(bad_input_cases()))
def test_bad_input_is_one_line_exit_2_and_nothing_drawn(tmp_path: Path, case: str) -> None:
    runs = tmp_path / "runs"
    for algo in ("td3", "ede-td3"):
        write_run(runs, algo, 0, np.linspace(-200, -100, 21))
    breaks, expected = bad_input_cases()[case]
    breaks(runs)
    done = results(runs, tmp_path / "figures")
    assert done.returncode == 2 and expected in done.stderr, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and not (tmp_path / "figures").exists()


def test_a_task_folder_whose_runs_name_another_task_is_refused_in_one_line(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    for algo in ("td3", "ede-td3"):
        write_run(runs, algo, 0, np.linspace(-200, -100, 21))
    # As they were kept before a task's folder took its full id.
    shutil.move(layout.task_runs(TASK, runs), runs / "ReacherTurn-v0")
    done = results(runs, tmp_path / "figures")
    assert done.returncode == 2 and done.stderr == (
        f"Error: {runs / 'ReacherTurn-v0'}: its runs are of ede/ReacherTurn-v0; keep them in "
        f"{runs / 'ede' / 'ReacherTurn-v0'}/\n"
    )
    assert not (tmp_path / "figures").exists()


def test_the_transfer_tasks_have_an_aggregate_of_their_own(tmp_path: Path) -> None:
    """The transfer claim's aggregate: the families' target tasks alone (not their sources)."""
    runs = tmp_path / "runs"
    for task, start in (
        ("ede/ReacherVertical-v0", -60),
        (TASK, -200),
        ("ede/ReacherPush-v0", -220),
    ):
        for seed in range(2):
            write_run(runs, "td3", seed, np.linspace(start, start / 2 - seed, 21), task=task)
            write_run(runs, "ede-td3", seed, np.linspace(start, start / 4 - seed, 21), task=task)
        write_source(runs, task, seeds=[0, 1])
    done = results(runs, tmp_path / "figures")
    assert done.returncode == 0, done.stderr
    transfer = done.stdout.split("### Across tasks: the transfer tasks")[1].split("###")[0]
    assert "2 tasks (ede/ReacherTurn-v0, ede/ReacherPush-v0);" in transfer
    assert "ede/ReacherVertical-v0" not in transfer


def test_one_transfer_task_has_no_transfer_aggregate(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    for task in ("ede/ReacherVertical-v0", TASK):
        for seed in range(2):
            for algo in ("td3", "ede-td3"):
                write_run(runs, algo, seed, np.linspace(-200, -100 - seed, 21), task=task)
        write_source(runs, task, seeds=[0, 1])
    done = results(runs, tmp_path / "figures")
    assert done.returncode == 0, done.stderr
    assert "### Across tasks: the reacher family" in done.stdout
    assert "the transfer tasks" not in done.stdout


# Runs that are not the task's: each refused in one line naming it, exit 2, nothing drawn -------


def finished_run(
    runs: Path,
    algo: Algo,
    seed: int,
    td3: TD3Config | None = None,
    ede_td3: EdeTD3Config | None = None,
) -> Path:
    """A run of :data:`TASK` as ``train`` finishes it (:func:`ede.run.runs.write_finished`: its
    run.json records its params and the SHA-256 of its files), with a published copy's files
    (no policy), and its task's ``source.json`` where it has none yet."""
    folder = layout.run(TASK, algo, seed, runs)
    name_seed(runs, TASK, seed)
    history = [
        {
            "step": step,
            "episode": i,
            "mean_return": -200.0 + 5 * i + seed,
            "std_return": 1.0,
            "wall_seconds": i + (algo == "ede-td3") / 2,  # each run's own
        }
        for i, step in enumerate(range(0, BUDGET + 1, BUDGET // 20))
    ]
    diagnostics = [
        {"step": 1_000, "updates": 1_000, "critic_loss": 0.5, "actor_loss": 1.0, "mean_q": -1.0}
    ]
    write_curves(folder, history, diagnostics)
    spec = RunSpec(
        TASK,
        algo,
        seed,
        BUDGET,
        td3 or TD3Config(),
        ede_td3 or EdeTD3Config(),
        EMBEDDING if algo == "ede-td3" else "",
    )
    write_finished(folder, spec, {"final_return": history[-1]["mean_return"]}, torch.device("cpu"))
    return folder


def four_runs(
    runs: Path, td3: TD3Config | None = None, ede_td3: EdeTD3Config | None = None
) -> None:
    """Seeds 0 and 1 of each algorithm, each seed 1 made with ``td3`` and ``ede_td3``."""
    algos: tuple[Algo, ...] = ("td3", "ede-td3")
    for algo in algos:
        finished_run(runs, algo, 0)
        finished_run(runs, algo, 1, td3, ede_td3)


def refused(tmp_path: Path, runs: Path, line: str) -> None:
    """``results`` on ``runs`` exits 2 with ``Error: line`` alone, and prints and draws nothing."""
    done = results(runs, tmp_path / "figures")
    assert (done.returncode, done.stderr) == (2, f"Error: {line}\n")
    assert done.stdout == "" and not (tmp_path / "figures").exists()


def test_runs_as_train_finishes_them_are_read_with_their_checksums(tmp_path: Path) -> None:
    """The control of the refusals below: the same runs, whole, are drawn; a key that leaves a
    result alone (as an older run.json records td3.device) and EDE-TD3's params on a TD3 run
    do not set runs apart."""
    runs = tmp_path / "runs"
    four_runs(runs)
    td3 = layout.run(TASK, "td3", 1, runs) / "run.json"
    made = json.loads(td3.read_text())
    made["params"]["td3"]["device"] = "cuda"
    made["params"]["ede_td3"]["bound_scale"] = 2.0  # TD3 runs train without it
    td3.write_text(json.dumps(made))
    done = results(runs, tmp_path / "figures")
    assert done.returncode == 0, done.stderr
    assert "| TD3 | 0, 1 |" in done.stdout and "| EDE-TD3 | 0, 1 |" in done.stdout
    assert (tmp_path / "figures" / "reacher.png").is_file()


@pytest.mark.parametrize("name", ["seed00", "seed01", "seed-1", "seedx", "seed 1", "Seed2", "2"])
def test_a_seed_folder_not_named_seed_n_is_refused(tmp_path: Path, name: str) -> None:
    """A copy of td3/seed0 named seed00 once counted seed 0 twice ("3 of TD3"), exit 0."""
    runs = tmp_path / "runs"
    four_runs(runs)
    copy = layout.run(TASK, "td3", 0, runs).parent / name
    shutil.copytree(layout.run(TASK, "td3", 0, runs), copy)
    refused(
        tmp_path,
        runs,
        f"{copy}: not a run's folder name; expected seed<N>, N a whole number >= 0 without "
        "leading zeros (seed0, seed12)",
    )


def test_the_same_seed_twice_is_refused(tmp_path: Path) -> None:
    """A copy of td3/seed0 as td3/seed2: its run.json names seed 0 (ede.run.runs.read_run)."""
    runs = tmp_path / "runs"
    four_runs(runs)
    copy = layout.run(TASK, "td3", 2, runs)
    shutil.copytree(layout.run(TASK, "td3", 0, runs), copy)
    refused(tmp_path, runs, f"{copy / 'run.json'}: seed is 0, expected 2")


def test_a_run_copied_as_another_seed_is_refused_whatever_its_run_json_says(
    tmp_path: Path,
) -> None:
    """The copy of td3/seed0 as td3/seed2, its run.json saying seed 2 and source.json naming it,
    was once averaged as a third seed: its files are seed 0's, byte for byte."""
    runs = tmp_path / "runs"
    four_runs(runs)
    original, copy = (layout.run(TASK, "td3", seed, runs) for seed in (0, 2))
    shutil.copytree(original, copy)
    made = json.loads((copy / "run.json").read_text())
    (copy / "run.json").write_text(json.dumps({**made, "seed": 2}))
    name_seed(runs, TASK, 2)
    refused(
        tmp_path,
        runs,
        f"{copy}: the same run as {original} (their eval.csv's SHA-256 are both "
        f"{sha256(original / 'eval.csv')[:12]}…); a run is published once, in the folder of its "
        "own seed",
    )


@pytest.mark.parametrize("where", ["another task", "an ablation"])
def test_a_run_copied_as_another_tasks_or_a_variants_is_refused(tmp_path: Path, where: str) -> None:
    """td3/seed0 copied to another task's folder (its run.json saying that task), or to an
    ablation's variant, where it would stand for what it is not."""
    runs = tmp_path / "runs"
    four_runs(runs)
    original = layout.run(TASK, "td3", 0, runs)
    other = "ede/ReacherPush-v0" if where == "another task" else TASK
    root = runs if where == "another task" else tmp_path / "ablations" / "copied"
    copy = layout.run(other, "td3", 0, root)
    shutil.copytree(original, copy)
    made = json.loads((copy / "run.json").read_text())
    (copy / "run.json").write_text(json.dumps({**made, "task": other}))
    name_seed(root, other, 0)
    refused(
        tmp_path,
        runs,
        f"{copy}: the same run as {original} (their eval.csv's SHA-256 are both "
        f"{sha256(original / 'eval.csv')[:12]}…); a run is published once, in the folder of its "
        "own seed",
    )


def test_a_run_of_a_seed_source_json_does_not_name_is_refused(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    four_runs(runs)
    write_source(runs, seeds=[0])
    refused(
        tmp_path,
        runs,
        f"{layout.run(TASK, 'td3', 1, runs)}: a run of seed 1, which "
        f"{layout.task_runs(TASK, runs) / 'source.json'} does not name (it names 0); a task's "
        "runs are the seeds its experiments made, as each export names them",
    )


@pytest.mark.parametrize(
    ("sha256s", "line"),
    [
        (None, "'sha256' is not a SHA-256 by file name"),
        ({}, "'sha256' records no SHA-256 of eval.csv, diagnostics.csv, metrics.json"),
        ("eval.csv", "'sha256' records no SHA-256 of eval.csv"),
        ("removed", "records no 'sha256' of the run's files"),
    ],
)
def test_a_run_whose_checksums_are_turned_off_is_refused(
    tmp_path: Path, sha256s: object, line: str
) -> None:
    """Its run.json's sha256 set null or empty, an entry or the key removed: a run made since
    run.json recorded checksums is not one of the runs published before (ede/run/early_runs.py)."""
    runs = tmp_path / "runs"
    four_runs(runs)
    record = layout.run(TASK, "td3", 1, runs) / "run.json"
    made = json.loads(record.read_text())
    if sha256s == "removed":
        del made["sha256"]
    elif sha256s == "eval.csv":
        del made["sha256"]["eval.csv"]
    else:
        made["sha256"] = sha256s
    record.write_text(json.dumps(made))
    done = results(runs, tmp_path / "figures")
    assert done.returncode == 2 and done.stderr.startswith(f"Error: {record}: {line}")
    assert done.stderr.count("\n") == 1 and done.stdout == ""
    assert not (tmp_path / "figures").exists()


@pytest.mark.parametrize(
    ("params", "algo", "difference"),
    [
        ({"td3": TD3Config(lr=0.002)}, "td3", "td3.lr = 0.002, but {seed0} was made with 0.001"),
        (
            {"td3": TD3Config(update_schedule="step")},
            "td3",
            'td3.update_schedule = "step", but {seed0} was made with "episode"',
        ),
        (
            {"ede_td3": EdeTD3Config(bound_scale=2.0)},
            "ede-td3",
            "ede_td3.bound_scale = 2.0, but {seed0} was made with 1.0",
        ),
    ],
)
def test_a_run_made_with_other_params_than_its_tasks_others_is_refused(
    tmp_path: Path, params: dict, algo: Algo, difference: str
) -> None:
    """Each seed 1 made with ``params``: the first found, ``algo``'s, is refused against its
    algorithm's seed 0 (td3's params are both algorithms', ede_td3's EDE-TD3's)."""
    runs = tmp_path / "runs"
    four_runs(runs, **params)
    refused(
        tmp_path,
        runs,
        f"{layout.run(TASK, algo, 1, runs) / 'run.json'}: made with "
        f"{difference.format(seed0=layout.run(TASK, algo, 0, runs))}; a task's runs share every "
        "param that changes a result",
    )


def test_a_td3_run_against_an_ede_td3_run_of_other_td3_params_is_refused(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    finished_run(runs, "td3", 0)
    finished_run(runs, "ede-td3", 0, td3=TD3Config(tau=0.01))
    refused(
        tmp_path,
        runs,
        f"{layout.run(TASK, 'ede-td3', 0, runs) / 'run.json'}: made with td3.tau = 0.01, but "
        f"{layout.run(TASK, 'td3', 0, runs)} was made with 0.005; a task's runs share every "
        "param that changes a result",
    )


@pytest.mark.parametrize("name", ["eval.csv", "diagnostics.csv", "metrics.json"])
def test_a_file_other_than_its_run_wrote_is_refused_by_name(tmp_path: Path, name: str) -> None:
    runs = tmp_path / "runs"
    four_runs(runs)
    path = layout.run(TASK, "ede-td3", 1, runs) / name
    recorded = json.loads((path.parent / "run.json").read_text())["sha256"][name]
    text = path.read_text()
    last = max(i for i, c in enumerate(text) if c.isdigit())  # its last number's last digit
    path.write_text(text[:last] + ("2" if text[last] == "1" else "1") + text[last + 1 :])
    refused(
        tmp_path,
        runs,
        f"{path}: not the file its run wrote (SHA-256 {sha256(path)[:12]}…, run.json records "
        f"{recorded[:12]}…)",
    )


def test_a_file_whose_checksum_its_run_records_is_refused_where_missing(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    four_runs(runs)
    path = layout.run(TASK, "td3", 1, runs) / "diagnostics.csv"
    path.unlink()
    refused(tmp_path, runs, f"{path}: missing, though run.json records its SHA-256")


def test_a_figure_is_drawn_only_over_a_figure_results_drew(tmp_path: Path) -> None:
    """The figures folder may hold other files: a figure is drawn where nothing is or over the
    figure this command drew there (its mark), never over a user's file of the same name."""
    runs = tmp_path / "runs"
    for seed in range(2):
        for algo in ("td3", "ede-td3"):
            write_run(runs, algo, seed, np.linspace(-200, -100, 41))
    figures = tmp_path / "figures"
    first = results(runs, figures)
    assert first.returncode == 0, first.stderr
    again = results(runs, figures)  # its own figures: drawn over
    assert again.returncode == 0, again.stderr
    drawn = sorted(p.name for p in figures.glob("*.png"))
    mine = figures / drawn[0]
    mine.write_bytes(b"a user's picture")
    refused = results(runs, figures)
    assert refused.returncode == 2
    assert refused.stderr.splitlines() == [
        f"Error: {mine}: a file a results figure writer did not write there, or one changed "
        "since; expected a new path or that writer's own file: move it, or choose another place"
    ]
    assert mine.read_bytes() == b"a user's picture" and refused.stdout == ""


def section(out: str, heading: str) -> str:
    """The Markdown under a section's heading in the printed results, as a page's block holds it."""
    found = out.split(f"### {heading}\n\n")[1].split("\n### ")[0].split("\nFigure: ")[0]
    return found.rstrip("\n") + "\n"


PAGE = """# ReacherTurn, as an author writes it

Words of the author, kept.
<!-- results runs: ede/ReacherTurn-v0 -->
a stale table
<!-- /results -->
More words.

<!-- results runs: The tasks at a glance -->
<!-- /results -->
"""


def test_pages_fill_their_blocks_and_keep_the_authors_words(tmp_path: Path) -> None:
    runs = tmp_path / "pages" / "runs"
    for seed in range(4):
        # TD3 climbs halfway, then falls below where it started: its seeds diverge.
        write_run(runs, "td3", seed, np.r_[np.linspace(-180, -80, 11), np.full(10, -190)] - seed)
        # EDE-TD3 is above TD3 in the last bins only (its start is below TD3's).
        write_run(runs, "ede-td3", seed, np.linspace(-200, -60, 21) - seed)
    printed = results(runs, tmp_path / "printed")
    assert printed.returncode == 0, printed.stderr
    page = tmp_path / "pages" / "turn.md"
    page.write_text(PAGE)

    filled = results(runs, tmp_path / "figures", tmp_path / "pages")
    assert filled.returncode == 0, filled.stderr
    assert filled.stdout == f"Filled: {page}\n"
    text = page.read_text()
    words = re.split(r"<!-- results .*? -->\n.*?<!-- /results -->\n", text, flags=re.S)
    assert words == re.split(r"<!-- results .*? -->\n.*?<!-- /results -->\n", PAGE, flags=re.S)
    blocks = re.findall(r"<!-- results runs: (.*?) -->\n(.*?)\n<!-- /results -->", text, re.S)
    assert blocks == [(heading, section(printed.stdout, heading)) for heading, _ in blocks]
    # The runs' figure goes to the folder above them, as `--figures` defaults to for docs/results.
    assert (tmp_path / "pages" / "reacher.png").stat().st_size > 10_000
    # The glance row: the task's own final returns, its bins and TD3's seeds that declined and
    # diverged.
    row = blocks[1][1].splitlines()[-1].split(" | ")
    task = section(printed.stdout, TASK)
    assert row[:3] == ["| ede/ReacherTurn-v0", "20,000 (2.0% of the paper's)", "0–3"]
    assert row[3] == task.split("| TD3 | 0–3 | ")[1].split(" |")[0]
    assert row[4] == task.split("| EDE-TD3 | 0–3 | ")[1].split(" |")[0]
    assert f"{row[5]} on the final return and {row[6]} on the area under the curve" in task
    above, below = (int(n) for n in row[7].removesuffix(" (of 20)").split(", "))
    assert above > 0 and below > 0  # EDE-TD3 starts below TD3 and ends above
    diverged = re.findall(r"\| TD3 \| \d \|.*\| \*\*yes\*\* \| \*\*yes\*\* \|", task)
    assert row[8] == f"{len(diverged)}, {len(diverged)} (of 4) |" and diverged

    again = results(runs, tmp_path / "figures", page)
    assert again.returncode == 0 and again.stdout == "" and page.read_text() == text


@pytest.mark.parametrize(
    ("page", "said"),
    [
        (
            PAGE.replace("ReacherTurn-v0 -->", "Reacher-v9 -->"),
            "runs has no section 'ede/Reacher-v9' (its sections: 'ede/ReacherTurn-v0'",
        ),
        (PAGE.replace("a stale table\n<!-- /results -->\n", ""), "line 4: its block has no"),
        (PAGE + "<!-- /results -->\n", "line 11: <!-- /results --> closes no block"),
        (PAGE.replace("results runs:", "results elsewhere:"), "no runs folder"),
    ],
)
def test_a_page_whose_blocks_cannot_be_filled_is_one_line_and_left_alone(
    tmp_path: Path, page: str, said: str
) -> None:
    runs = tmp_path / "pages" / "runs"
    for seed in range(2):
        for algo in ("td3", "ede-td3"):
            write_run(runs, algo, seed, np.linspace(-200, -100 - seed, 21))
    (tmp_path / "pages" / "turn.md").write_text(page)
    done = results(runs, tmp_path / "figures", tmp_path / "pages" / "turn.md")
    assert done.returncode == 2 and said in done.stderr, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and "Traceback" not in done.stderr
    assert (tmp_path / "pages" / "turn.md").read_text() == page
    assert not (tmp_path / "pages" / "reacher.png").exists()


def test_pages_take_their_runs_from_their_blocks_alone(tmp_path: Path) -> None:
    page = tmp_path / "turn.md"
    page.write_text(PAGE)
    done = CliRunner().invoke(main, ["results", "--pages", str(page), "--runs", str(tmp_path)])
    assert done.exit_code == 2 and "leave out --runs, --figures and --ablations" in done.stderr
    assert page.read_text() == PAGE
