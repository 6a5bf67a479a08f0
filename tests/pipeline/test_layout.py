"""``dvc.yaml`` hands every stage the paths that ``ede_pipeline.layout`` builds: one layout."""

from __future__ import annotations

import shlex
from pathlib import Path

import yaml

from ede_pipeline import layout
from ede_pipeline.sweep.plan import train_command
from tests.support import REPO


def options(command: str, **values: str) -> dict[str, str]:
    """A stage's command, its ``${...}`` filled in, as ``{option: value}``."""
    for name, value in values.items():
        command = command.replace("${" + name + "}", value)
    words = shlex.split(command)
    return {
        w: words[i + 1] for i, w in enumerate(words) if w.startswith("--") and i + 1 < len(words)
    }


def test_every_stage_command_uses_the_layouts_paths() -> None:
    stages = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]
    family, task, algo, seed = "reacher", "ede/ReacherTurn-v0", "ede-td3", "3"
    code = options(stages["task_code"]["do"]["cmd"], key=family)
    assert code["--out"] == str(layout.code(family))
    source = "ede/ReacherVertical-v0"
    records = [
        d.replace("${key}", family).replace("${item.source}", source)
        for d in stages["collect"]["do"]["deps"]
    ]
    assert str(layout.task_code(family, source)) in records
    collect = options(stages["collect"]["do"]["cmd"], key=family)
    assert collect["--out"] == str(layout.rollouts(family))
    encoder = options(stages["pretrain_encoder"]["do"]["cmd"], key=family)
    assert (encoder["--rollouts"], encoder["--out"]) == (
        str(layout.rollouts(family)),
        str(layout.encoder(family)),
    )
    assert encoder["--metrics"].startswith(str(layout.embedding(family)) + "/")
    decoder = options(stages["pretrain_decoder"]["do"]["cmd"], key=family)
    assert (decoder["--encoder"], decoder["--out"]) == (
        str(layout.encoder(family)),
        str(layout.decoder(family)),
    )
    inputs = options(stages["task_inputs"]["do"]["cmd"], key=task, item=family)
    assert inputs["--out"] == str(layout.task_inputs(task))
    assert (inputs["--embedding"], inputs["--code"]) == (
        str(layout.embedding(family)),
        str(layout.code(family)),
    )
    train = options(
        stages["train"]["cmd"], **{"item.task": task, "item.algo": algo, "item.seed": seed}
    )
    # The sweep's command for a group of seeds is built from the layout: for one seed it is the stage's.
    filled = stages["train"]["cmd"]
    for name, value in {"item.task": task, "item.algo": algo, "item.seed": seed}.items():
        filled = filled.replace("${" + name + "}", value)
    assert shlex.split(filled) == train_command(task, algo, [int(seed)])
    assert train["--out"] == str(layout.run(task, algo, int(seed)))
    folder = layout.task_inputs(task)
    assert (train["--encoder"], train["--decoder"]) == (
        str(folder / layout.ENCODER),
        str(folder / layout.DECODER),
    )
    report = options(stages["report"]["cmd"])
    assert (report["--runs"], report["--out"], report["--metrics"], report["--curves"]) == (
        str(layout.RUNS),
        str(layout.REPORT),
        str(layout.REPORT_METRICS),
        str(layout.REPORT_CURVES),
    )


def test_the_report_reads_every_familys_folder_and_the_runs_and_depends_on_both() -> None:
    report = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]["report"]
    given = options(report["cmd"])
    assert (given["--families"], given["--runs"]) == (str(layout.FAMILIES), str(layout.RUNS))
    assert {str(layout.FAMILIES), str(layout.RUNS)} <= set(report["deps"])


def test_a_runs_inputs_are_its_tasks_folder_which_copies_its_familys() -> None:
    stages = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]
    family, task = (
        "${item}",
        "${key}",
    )  # task_inputs: one per task of runs.tasks, mapped to its family
    deps = stages["task_inputs"]["do"]["deps"]
    assert {
        str(layout.encoder(family)),
        str(layout.decoder(family)),
        str(layout.task_code(family, task)),
    } <= set(deps)
    assert stages["task_inputs"]["do"]["outs"] == [str(layout.task_inputs(task))]
    assert str(layout.task_inputs("${item.task}")) in stages["train"]["deps"]


def test_a_task_alone_is_a_family_named_after_it_that_params_accept(tmp_path: Path) -> None:
    from ede.config import load_params

    names = {
        t: layout.own_family(t)
        for t in ("HalfCheetah-v5", "ede/Pusher-v0", "Humanoid-v5", "ede/ReacherVertical-v0")
    }
    assert names == {
        "HalfCheetah-v5": "halfcheetah",
        "ede/Pusher-v0": "pusher",
        "Humanoid-v5": "humanoid",
        "ede/ReacherVertical-v0": "reachervertical",
    }
    params = yaml.safe_load((REPO / "params.yaml").read_text())  # a family key must be valid
    params["families"][names["HalfCheetah-v5"]] = {"source": "HalfCheetah-v5"}
    (path := tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    assert names["HalfCheetah-v5"] in load_params(path).families
    # Never a family already taken: gymnasium's Reacher is not of the paper's reacher family.
    assert layout.own_family("Reacher-v5", params["families"]) == "reacher-v5"
    assert layout.own_family("Hopper-v5", params["families"]) == "hopper"
    params["families"]["reacher-v5"] = {"source": "Reacher-v5"}
    path.write_text(yaml.safe_dump(params))
    assert "reacher-v5" in load_params(path).families
