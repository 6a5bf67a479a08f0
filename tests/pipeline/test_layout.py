"""``dvc.yaml`` hands every stage the paths that ``ede_pipeline.layout`` builds: one layout."""

from __future__ import annotations

import shlex

import yaml

from ede_pipeline import layout
from ede_pipeline.checkout import REPO


def options(command: str, **values: str) -> dict[str, str]:
    """A stage's command, its ``${...}`` filled in, as ``{option: value}``."""
    for name, value in values.items():
        command = command.replace("${" + name + "}", value)
    words = shlex.split(command)
    return {w: words[i + 1] for i, w in enumerate(words) if w.startswith("--") and i + 1 < len(words)}


def test_every_stage_command_uses_the_layouts_paths() -> None:
    stages = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]
    family, task, algo, seed = "reacher", "ede/ReacherTurn-v0", "ede-td3", "3"
    code = options(stages["task_code"]["do"]["cmd"], key=family)
    assert code["--out"] == str(layout.code(family))
    source = "ede/ReacherVertical-v0"
    records = [d.replace("${key}", family).replace("${item.source}", source)
               for d in stages["collect"]["do"]["deps"]]
    assert str(layout.task_code(family, source)) in records
    collect = options(stages["collect"]["do"]["cmd"], key=family)
    assert collect["--out"] == str(layout.rollouts(family))
    encoder = options(stages["pretrain_encoder"]["do"]["cmd"], key=family)
    assert (encoder["--rollouts"], encoder["--out"]) == (str(layout.rollouts(family)), str(layout.encoder(family)))
    assert encoder["--metrics"].startswith(str(layout.embedding(family)) + "/")
    decoder = options(stages["pretrain_decoder"]["do"]["cmd"], key=family)
    assert (decoder["--encoder"], decoder["--out"]) == (str(layout.encoder(family)), str(layout.decoder(family)))
    for stage in ("train_reacher", "train_sevendof"):
        fam = stage.removeprefix("train_")
        train = options(stages[stage]["cmd"], **{"item.task": task, "item.algo": algo, "item.seed": seed})
        assert train["--out"] == str(layout.run(task, algo, int(seed)))
        assert (train["--encoder"], train["--decoder"]) == (str(layout.encoder(fam)), str(layout.decoder(fam)))
    report = options(stages["report"]["cmd"])
    assert (report["--runs"], report["--out"], report["--metrics"], report["--curves"]) == (
        str(layout.RUNS), str(layout.REPORT), str(layout.REPORT_METRICS), str(layout.REPORT_CURVES))


def per_family(command: str, option: str) -> dict[str, str]:
    """The ``FAMILY=PATH`` values of a repeated option, as ``{family: path}``."""
    words = shlex.split(command)
    pairs = [words[i + 1].partition("=") for i, w in enumerate(words) if w == option]
    return {family: path for family, _, path in pairs}


def test_the_report_is_handed_every_familys_embedding_and_rollouts_and_depends_on_them() -> None:
    report = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]["report"]
    families = yaml.safe_load((REPO / "params.yaml").read_text())["families"]
    embeddings = per_family(report["cmd"], "--embedding")
    rollouts = per_family(report["cmd"], "--rollouts")
    assert embeddings == {family: str(layout.embedding(family)) for family in families}
    assert rollouts == {family: str(layout.rollouts(family)) for family in families}
    read = [options(report["cmd"])["--runs"], *rollouts.values()]
    read += [f"{folder}/{name}" for folder in embeddings.values()
             for name in (layout.ENCODER, layout.DECODER)]
    assert sorted(path for path in read if path not in report["deps"]) == []
