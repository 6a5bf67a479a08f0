"""One task's experiment outside DVC: variants of params, both algorithms, many seeds, a table.

    python benchmarks/experiment.py --out DIR [--task ede/ReacherVertical-v0] [--seeds 0-7]
        [--algos td3,ede-td3] [--jobs 2] [--variant NAME:key=value,key=value ...] [--budget N]
        [--thresholds -15,-10] [--summarise]

Each variant is the committed ``params.yaml`` restricted to the task's family and the task, with
its overrides applied (dotted keys, YAML values: ``embedding.predictor_state=false``); no
variant means the committed params alone (``default``). For each variant, in ``DIR/<variant>/``:
the family's rollouts and embedding (``ede-pipeline collect`` and ``pretrain``, skipped when
present), then one ``ede-pipeline train`` per algorithm and seed, ``--jobs`` at a time, each a
separate process that resumes from its checkpoint when the batch is run again; finished runs are
kept. Then, per variant and algorithm, over seeds with 95% bootstrap intervals: final return,
area under the curve, steps to -15 and -10, and the binned mean curve (``report.bin_steps``).

A task the committed params do not train on (``--task HalfCheetah-v5 --budget 100000
--thresholds ''``) becomes a family of its own, its embedding learned on its own random data (README,
"Your own task").

The paper's ReacherVertical experiment at the committed defaults is
``--out DIR --seeds 0-7``; the embedding-recipe ablation of docs/fidelity.md (rows 4 and 5) is
``--algos ede-td3 --seeds 0-3 --variant state: --variant constant:embedding.predictor_state=false
--variant windows400k:collect.steps=400000,embedding.window_stride=4``.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import yaml

from ede.config import load_params
from ede.report import curve_band, summarise_task
from ede.runs import RunRejected, read_run
from ede_pipeline import layout

REPO = Path(__file__).resolve().parents[1]
THRESHOLDS = (-15.0, -10.0)


def variant_params(task: str, overrides: str, budget: int | None = None) -> dict:
    """The committed params for ``task`` alone; a task they do not train on becomes its own
    family (its embedding learned on its own random data), with ``budget`` steps a run."""
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    if task in params["runs"]["tasks"]:
        family = params["runs"]["tasks"][task]
        params["families"] = {family: params["families"][family]}
    else:
        if budget is None:
            raise SystemExit(f"--task {task}: not in params.yaml's runs.tasks; give --budget")
        family = layout.own_family(task, params["families"])
        params["families"] = {family: {"source": task}}
    params["runs"]["tasks"] = {task: family}
    params["runs"]["budgets"] = {task: budget or params["runs"]["budgets"][task]}
    for figure in ("effect_space_family", "exploration_family"):  # other families' figures
        if params["report"].get(figure) != family:
            params["report"][figure] = None
    for assignment in filter(None, overrides.split(",")):
        key, _, value = assignment.partition("=")
        *path, last = key.split(".")
        section = params
        for part in path:
            section = section[part]
        section[last] = yaml.safe_load(value)
    return params


def ede_pipeline(workdir: Path, *args: str) -> None:
    log = workdir / "log.txt"
    with open(log, "a") as handle:
        result = subprocess.run([sys.executable, "-m", "ede_pipeline", *args], cwd=workdir,
                                stdout=handle, stderr=subprocess.STDOUT)
    if result.returncode:
        raise SystemExit(f"{workdir}: ede-pipeline {' '.join(args)} failed; see {log}")


def prepare(workdir: Path, task: str, overrides: str, budget: int | None) -> str:
    """The variant's params file, rollouts and embedding; returns the family."""
    workdir.mkdir(parents=True, exist_ok=True)
    params = variant_params(task, overrides, budget)
    (workdir / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    load_params(workdir / "params.yaml")  # a bad override stops here, with its key named
    family = next(iter(params["families"]))
    rollouts, embedding = layout.rollouts(family), layout.embedding(family)
    if not (workdir / rollouts).exists():
        ede_pipeline(workdir, "collect", "--family", family, "--out", str(rollouts))
    for part in ("encoder", "decoder"):
        if not (workdir / embedding / part / "meta.json").exists():
            extra = ["--encoder", str(embedding / "encoder")] if part == "decoder" else []
            ede_pipeline(workdir, "pretrain", part, "--family", family,
                         "--rollouts", str(rollouts), *extra, "--out", str(embedding / part),
                         "--metrics", str(embedding / f"{part}_metrics.json"),
                         "--plots", str(embedding / f"{part}_history.csv"))
    return family


def run_dir(workdir: Path, task: str, algo: str, seed: int) -> Path:
    return workdir / layout.run(task, algo, seed)


def train(workdir: Path, family: str, task: str, algo: str, seed: int) -> None:
    out = run_dir(workdir, task, algo, seed)
    if (out / "metrics.json").exists():
        return
    ede_pipeline(workdir, "train", "--task", task, "--algo", algo, "--seed", str(seed),
                 "--out", str(out.relative_to(workdir)),
                 "--encoder", str(layout.encoder(family)), "--decoder", str(layout.decoder(family)))
    print(f"{workdir.name}: {algo} seed {seed} done", flush=True)


def summarise(workdir: Path, task: str, algos: list[str], seeds: list[int],
              thresholds: tuple[float, ...] = THRESHOLDS) -> None:
    params = load_params(workdir / "params.yaml")
    rng = np.random.default_rng(0)
    print(f"\n== {workdir.name}")
    bands = {}
    for algo in algos:
        curves = []
        for seed in seeds:
            try:
                record = read_run(run_dir(workdir, task, algo, seed),
                                  {"task": task, "algo": algo, "seed": seed})
            except RunRejected as error:
                print(f"left out: {error}")
                continue
            if record is not None:
                curves.append(record.curve)
        if not curves:
            continue
        rows = [summarise_task(task, algo, curves, [], t, 0.95, 2_000, rng)
                for t in thresholds or (None,)]
        print(f"{algo:8s} seeds {len(curves)}: final {rows[0].final}; AUC {rows[0].auc}"
              + "".join(f"; to {t:g}: {r.to_threshold.steps()}" for t, r in zip(thresholds, rows)))
        bands[algo] = curve_band(curves, 0.95, 2_000, rng, params.report.bin_steps)
    if bands:
        steps = next(iter(bands.values()))[0]
        print("bin end  " + "".join(f"{a:>28s}" for a in bands))
        for j, step in enumerate(steps):
            print(f"{int(step):7d}  " + "".join(
                f"{b[1][j]:9.2f} [{b[2][j]:7.2f}, {b[3][j]:7.2f}]" for b in bands.values()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--task", default="ede/ReacherVertical-v0")
    parser.add_argument("--algos", default="td3,ede-td3")
    parser.add_argument("--seeds", default="0-7", help="e.g. 0-7 or 0,2,5")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--variant", action="append", default=[], help="NAME:key=value,...")
    parser.add_argument("--budget", type=int, help="steps a run [default: params.yaml's]; "
                        "required for a task params.yaml does not train on (its own family)")
    parser.add_argument("--thresholds", default="-15,-10",
                        help="returns to report the steps to reach ('' for none)")
    parser.add_argument("--summarise", action="store_true", help="only print the tables")
    args = parser.parse_args()
    first, _, last = args.seeds.partition("-")
    seeds = list(range(int(first), int(last) + 1)) if last else [int(s) for s in args.seeds.split(",")]
    algos = args.algos.split(",")
    variants = [v.partition(":")[::2] for v in args.variant] or [("default", "")]
    if not args.summarise:
        for name, overrides in variants:
            family = prepare(args.out / name, args.task, overrides, args.budget)
            # Interleaved so that a batch cut short holds both algorithms for the same seeds.
            jobs = [(name, algo, seed) for seed in seeds for algo in algos]
            with ThreadPoolExecutor(args.jobs) as pool:
                for result in [pool.submit(train, args.out / n, family, args.task, a, s) for n, a, s in jobs]:
                    result.result()
    thresholds = tuple(float(t) for t in filter(None, args.thresholds.split(",")))
    for name, _ in variants:
        summarise(args.out / name, args.task, algos, seeds, thresholds)


if __name__ == "__main__":
    main()
