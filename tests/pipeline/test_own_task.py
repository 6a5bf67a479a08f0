"""A family added to ``params.yaml`` alone runs under ``dvc repro`` end to end (README, "Your own
task"): gymnasium's stock ``Hopper-v5`` (MuJoCo: the embedding's state is its physics; its
episodes end where it falls, so the report's clips are short) and
``Pendulum-v1`` (no MuJoCo: the state is the observation), with ``dvc.yaml`` as committed."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from ede.io.rollouts import Rollouts
from ede_pipeline import layout
from tests.support import REPO, dvc, scratch_copy

pytestmark = pytest.mark.slow

FAMILIES = {"hopper": "Hopper-v5", "pendulum": "Pendulum-v1"}


def own_families(
    tiny_pipeline: Callable[[dict[str, Any]], None],
) -> Callable[[dict[str, Any]], None]:
    def edit(params: dict[str, Any]) -> None:
        params["families"] = {family: {"source": task} for family, task in FAMILIES.items()}
        params["runs"]["tasks"] = {task: family for family, task in FAMILIES.items()}
        params["runs"]["budgets"] = {task: 200 for task in FAMILIES.values()}
        params["report"].update(effect_space_family=None, exploration_family=None)
        tiny_pipeline(params)
        params["collect"]["steps"] = 1_000  # an episode at Hopper-v5's limit, at the least

    return edit


def test_a_family_added_by_params_alone_runs_end_to_end(
    tmp_path: Path, tiny_pipeline: Callable[[dict[str, Any]], None]
) -> None:
    copy = scratch_copy(tmp_path / "repo", own_families(tiny_pipeline))
    assert (copy / "dvc.yaml").read_bytes() == (REPO / "dvc.yaml").read_bytes()
    result = dvc(copy, "repro")
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]

    for family, task in FAMILIES.items():
        store = Rollouts.open(copy / layout.rollouts(family), env_id=task)
        expected = "physics" if family == "hopper" else "observation"
        assert store.attrs["state_source"] == expected
        if expected == "observation":
            assert (store.state == store.obs).all()
        for algo in ("td3", "ede-td3"):
            run = copy / layout.run(task, algo, 0)
            metrics = json.loads((run / "metrics.json").read_text())
            assert math.isfinite(metrics["final_return"]), (task, algo, metrics)
            assert (run / "policy" / "policy.safetensors").is_file()
    page = (copy / "data/report/index.html").read_text()
    assert "hopper family" in page and "pendulum family" in page
    assert "None: every run the params name is here." in page
    status = dvc(copy, "status")
    assert "up to date" in status.stdout, status.stdout

    # Removing a family from the params is as simple: its stages are gone.
    params = yaml.safe_load((copy / "params.yaml").read_text())
    del params["families"]["hopper"], params["runs"]["tasks"]["Hopper-v5"]
    (copy / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    listed = dvc(copy, "stage", "list", "--name-only").stdout.split()
    assert not [name for name in listed if "hopper" in name.lower()], listed
    assert "train@Pendulum-v1-ede-td3-0" in listed
