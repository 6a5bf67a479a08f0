"""Where every output of the pipeline lives under ``data/``, and the published runs under
``docs/results/``: the one place paths are built.

``dvc.yaml`` writes the same paths into each stage's command (``tests/pipeline/test_layout.py``
holds the two together); the commands use these as the defaults of their path options.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ede.config import Params

__all__ = [
    "DATA",
    "DECODER",
    "ENCODER",
    "FAMILIES",
    "PUBLISHED_EMBEDDINGS",
    "REPORT",
    "REPORT_CURVES",
    "REPORT_METRICS",
    "RESULTS",
    "RESULTS_RUNS",
    "RUNS",
    "VIDEOS",
    "code",
    "decoder",
    "embedding",
    "embedding_beside",
    "encoder",
    "own_family",
    "published_embedding",
    "rollouts",
    "run",
    "run_embedding",
    "task_code",
    "task_inputs",
    "task_runs",
    "video",
]

DATA = Path("data")
FAMILIES = DATA / "families"  # one folder per family: what its stages write
TASKS = DATA / "tasks"  # one folder per task trained on: what its runs read from its family
RUNS = DATA / "runs"
REPORT = DATA / "report"
REPORT_METRICS = DATA / "report-metrics.json"
REPORT_CURVES = DATA / "report-curves"
VIDEOS = DATA / "videos"  # `ede-pipeline render`'s videos, laid out as RUNS
ENCODER, DECODER = "encoder", "decoder"  # the two artifacts in an embedding's folder
PUBLISHED_EMBEDDINGS = "embedding"  # a published task folder's embeddings, one folder each
RESULTS = Path("docs") / "results"  # the results page's figures (`ede-pipeline results`)
RESULTS_RUNS = RESULTS / "runs"  # the published runs, laid out as RUNS (`experiment export`)


def code(family: str, families: Path = FAMILIES) -> Path:
    """The folder of the family's task records (``ede-pipeline task-code``)."""
    return families / family / "code"


def task_code(family: str, task: str) -> Path:
    """What defines ``task``: its registration and the checksums of the files it runs."""
    return code(family) / f"{task}.json"


def rollouts(family: str, families: Path = FAMILIES) -> Path:
    """The family's random-policy rollouts (Zarr store)."""
    return families / family / "rollouts.zarr"


def embedding(family: str, families: Path = FAMILIES) -> Path:
    """The folder of the family's encoder and decoder artifacts, metrics and histories."""
    return families / family / "embedding"


def encoder(family: str) -> Path:
    return embedding(family) / ENCODER


def decoder(family: str) -> Path:
    return embedding(family) / DECODER


def own_family(task: str, taken: Collection[str] = ()) -> str:
    """The name of the family a task forms alone, its embedding learned on its own random data:
    ``HalfCheetah-v5`` is ``halfcheetah``, ``ede/Pusher-v0`` is ``pusher``. Never one of the
    ``taken`` families (params.yaml's): there, ``Reacher-v5`` is ``reacher-v5``, not ``reacher``."""
    name = "".join(c for c in task.split("/")[-1].split("-v")[0].lower() if c.isalnum())
    return task.split("/")[-1].lower() if name in taken else name


def task_inputs(task: str) -> Path:
    """A task's copy of its family's encoder and decoder and its own code record
    (``ede-pipeline task-inputs``), which its runs read."""
    return TASKS / task


def task_runs(task: str, runs: Path = RUNS) -> Path:
    """The folder of one task's runs, named by its full id: ``ede/ReacherTurn-v0`` is
    ``ede/ReacherTurn-v0/``. Published, it holds the task's ``source.json`` beside them."""
    return runs / task


def run(task: str, algo: str, seed: int, runs: Path = RUNS) -> Path:
    """One training run's directory in the folder of all runs."""
    return task_runs(task, runs) / algo / f"seed{seed}"


def video(task: str, algo: str, seed: int, videos: Path = VIDEOS) -> Path:
    """A run's video (``ede-pipeline render``), laid out as its run's folder."""
    return videos / task / algo / f"seed{seed}.mp4"


def published_embedding(task: str, checksum: str, runs: Path = RESULTS_RUNS) -> Path:
    """Published, the held-out metrics of an embedding a task's EDE-TD3 runs used, named by the
    first 12 characters of its decoder's checksum (the ``embedding`` their ``run.json`` names),
    so that each run finds its own where a task's seeds came from several experiments."""
    return task_runs(task, runs) / PUBLISHED_EMBEDDINGS / checksum[:12]


def embedding_beside(run: Path, checksum: str) -> Path:
    """A published run's embedding (:func:`published_embedding`), from the run's own folder
    (``<task folder>/<algo>/seed<N>``)."""
    return run.parent.parent / PUBLISHED_EMBEDDINGS / checksum[:12]


def run_embedding(
    run: Path,
    meta: Mapping[str, Any],
    params: Params,
    encoder: Path | None = None,
    decoder: Path | None = None,
) -> tuple[Path | None, Path]:
    """Where the embedding an EDE-TD3 run (its policy's ``meta``) acts through is, as its
    encoder (None: the decoder alone) and decoder: the ones ``encoder`` and ``decoder`` name;
    else, for a published run, the decoder published beside it (``experiment export
    --policies``; a policy acts through the decoder alone); else its family's in the pipeline's
    data (:func:`ede.analysis.video.trained_embedding` reads it)."""
    task = meta["task"]
    beside = embedding_beside(run, str(meta.get("embedding"))) / DECODER
    if encoder is None and decoder is None and beside.is_dir():
        return None, beside
    family = params.runs.tasks.get(task) or own_family(task, params.families)
    folder = embedding(family)
    return encoder or folder / ENCODER, decoder or folder / DECODER
