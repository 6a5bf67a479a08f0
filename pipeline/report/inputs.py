"""What the report reads: its inputs as its command line names them, checked before anything is
written (:func:`read_inputs`), and the runs the params name (:func:`read_runs`)."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ede.config import EMBEDDED_ALGOS, Algo, Params
from ede.method.embedding import ActionEmbedding
from ede.run.artifacts import ArtifactError, load_action_embedding
from ede.run.runs import Curve, RunRejected, read_run
from ede.run.spec import RunSpec
from ede_pipeline import layout
from ede_pipeline.common import BadInput

FIGURE_FAMILIES = {"effect_space_family": "Figure 6", "exploration_family": "Figure 7"}

Key = tuple[str, str]  # a task and an algorithm


@dataclass(frozen=True)
class Inputs:
    """What the report reads, as its command line names it, checked."""

    runs: Path  # the folder of every run: <task>/<algo>/seed<N>/
    embeddings: dict[str, Path]  # per family, the folder of its encoder and decoder
    loaded: dict[str, ActionEmbedding]
    rollouts: dict[str, dict[str, Any]]  # per family, the store's attributes
    embedding_ids: dict[str, str]  # per family, its decoder's identity, which EDE-TD3 runs record


@dataclass
class Runs:
    """The runs the params name, as the report found them, per task and algorithm in the params'
    order (family by family)."""

    curves: dict[Key, list[Curve]] = field(default_factory=dict)  # of the runs averaged
    missing: dict[Key, list[int]] = field(default_factory=dict)  # the seeds not averaged
    diagnostics: dict[Key, list[dict[str, np.ndarray]]] = field(default_factory=dict)
    software: list[dict[str, Any] | None] = field(default_factory=list)  # of each run averaged
    absent: list[str] = field(default_factory=list)  # the folders of runs with no results
    excluded: list[str] = field(default_factory=list)  # a line per finished run left out, and why


def _by_family(
    option: str,
    values: tuple[str, ...],
    params: Params,
    default: Callable[[str], Path],
    default_families: list[str],
) -> dict[str, Path]:
    """The ``FAMILY=PATH`` values of a repeatable option; none given, ``default_families`` at
    their ``default`` paths."""
    if not values:
        return {family: default(family) for family in default_families}
    found: dict[str, Path] = {}
    for value in values:
        family, equals, path = value.partition("=")
        if not (family and equals and path):
            raise BadInput(
                f"{option} {value!r}: expected FAMILY=PATH, e.g. {option} point={default('point')}"
            )
        if family not in params.families:
            raise BadInput(
                f"{option} {value!r}: unknown family {family!r}; params.yaml's families "
                f"are {', '.join(params.families)}"
            )
        if family in found:
            raise BadInput(f"{option} {value!r}: the {family} family is given twice")
        found[family] = Path(path)
    return found


def _store_attributes(store: Path) -> dict[str, Any]:
    """A Zarr v3 store's attributes, read from its header alone; empty if there is none."""
    try:
        return json.loads((store / "zarr.json").read_text()).get("attributes", {})
    except (OSError, ValueError, AttributeError):
        return {}


def read_inputs(
    params: Params,
    runs: Path,
    embeddings: tuple[str, ...],
    rollouts: tuple[str, ...],
    families: Path = layout.FAMILIES,
) -> Inputs:
    """Check every input before anything is written.

    Without ``--embedding``, every family of the params whose embedding is in ``families`` (and
    the pictured ones, which must be); without ``--rollouts``, those families' stores there.

    Raises:
        BadInput: naming the option (or params key) and what it expects.
    """
    if not runs.is_dir():
        raise BadInput(
            f"--runs {runs}: no such directory; expected the folder of the runs "
            "(<task>/<algo>/seed<N>/, written by `ede-pipeline train`)"
        )
    figures = {key: getattr(params.report, key) for key in FIGURE_FAMILIES}
    pictured = list(dict.fromkeys(family for family in figures.values() if family is not None))
    found = [
        family
        for family in params.families
        if family in pictured or layout.embedding(family, families).is_dir()
    ]
    folders = _by_family(
        "--embedding", embeddings, params, lambda family: layout.embedding(family, families), found
    )
    stores = _by_family(
        "--rollouts",
        rollouts,
        params,
        lambda family: layout.rollouts(family, families),
        list(folders),
    )
    loaded, embedding_ids, trained_on = _embeddings(folders)
    for key, family in figures.items():
        if family is not None and family not in folders:
            raise BadInput(
                f"report.{key}: {family}, but no --embedding {family}=DIR is given; "
                f"{FIGURE_FAMILIES[key]} needs that family's embedding"
            )
    return Inputs(runs, folders, loaded, _stores(stores, trained_on), embedding_ids)


def _embeddings(
    folders: dict[str, Path],
) -> tuple[dict[str, ActionEmbedding], dict[str, str], dict[str, str]]:
    """Per family, its embedding from its folder, its decoder's identity, and the fingerprint of
    the rollouts it learned from.

    Raises:
        BadInput: naming the ``--embedding`` and what it expects.
    """
    loaded: dict[str, ActionEmbedding] = {}
    embedding_ids: dict[str, str] = {}
    trained_on: dict[str, str] = {}
    for family, folder in folders.items():
        given = f"--embedding {family}={folder}"
        if not folder.is_dir():
            raise BadInput(
                f"{given}: no such directory; expected the {family} family's embedding "
                f"folder ({layout.ENCODER}/ and {layout.DECODER}/, from `ede-pipeline "
                "pretrain`)"
            )
        try:
            meta, loaded[family] = load_action_embedding(
                folder / layout.ENCODER, folder / layout.DECODER
            )
        except ArtifactError as error:
            raise BadInput(f"{given}: {error}") from None
        if meta.family != family:
            raise BadInput(f"{given}: the embedding of family {meta.family}, not {family}")
        trained_on[family] = meta.data_fingerprint
        embedding_ids[family] = meta.identity
    return loaded, embedding_ids, trained_on


def _stores(stores: dict[str, Path], trained_on: dict[str, str]) -> dict[str, dict[str, Any]]:
    """Per family, its rollouts store's attributes, the store the family's embedding (where
    given) learned from.

    Raises:
        BadInput: naming the ``--rollouts`` and what it expects.
    """
    attributes: dict[str, dict[str, Any]] = {}
    for family, store in stores.items():
        given = f"--rollouts {family}={store}"
        attrs = _store_attributes(store)
        if "fingerprint" not in attrs:
            raise BadInput(
                f"{given}: no rollouts store here; expected the Zarr store that "
                "`ede-pipeline collect` writes"
            )
        if trained_on.get(family, attrs["fingerprint"]) != attrs["fingerprint"]:
            raise BadInput(
                f"{given}: rollouts {attrs['fingerprint'][:12]}, but the {family} "
                f"embedding was trained on {trained_on[family][:12]}"
            )
        attributes[family] = attrs
    return attributes


def read_runs(params: Params, inputs: Inputs) -> Runs:
    """Every run the params name, read (:func:`ede.run.runs.read_run`) against what it must be
    (:func:`_expected`): a run that is not, or is damaged, is excluded and named."""
    runs = Runs()
    for tasks in params.runs.by_family().values():
        for task in tasks:
            for algo in params.runs.algos:
                found, missing = [], []
                for seed in params.runs.seeds:
                    run = layout.run(task, algo, seed, inputs.runs)
                    try:
                        record = read_run(run, _expected(params, inputs, task, algo, seed))
                    except RunRejected as error:
                        record = None
                        runs.excluded.append(str(error))
                    else:
                        if record is None:
                            runs.absent.append(str(run))
                    if record is None:
                        missing.append(seed)
                        continue
                    found.append(record.curve)
                    runs.software.append(record.software)
                    if record.diagnostics is not None:
                        runs.diagnostics.setdefault((task, algo), []).append(record.diagnostics)
                runs.curves[(task, algo)] = found
                runs.missing[(task, algo)] = missing
    return runs


def _expected(params: Params, inputs: Inputs, task: str, algo: Algo, seed: int) -> dict[str, Any]:
    """What a run's ``run.json`` must say: the run the params name, with the family's embedding
    where it acts in it (:data:`ede.config.EMBEDDED_ALGOS`) and the report was given it."""
    embedding = inputs.embedding_ids.get(params.runs.tasks[task]) if algo in EMBEDDED_ALGOS else ""
    expected = RunSpec(
        task, algo, seed, params.runs.budgets[task], params.td3, params.ede_td3, embedding or ""
    ).identity()
    if embedding is None:
        del expected["embedding"]  # not given to the report: nothing to check it against
    return expected
