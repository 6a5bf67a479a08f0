"""Where every output of the pipeline lives under ``data/``: the one place paths are built.

``dvc.yaml`` writes the same paths into each stage's command (``tests/pipeline/test_layout.py``
holds the two together); the commands use these as the defaults of their path options.
"""

from __future__ import annotations

from pathlib import Path

__all__ = [
    "DATA",
    "REPORT",
    "REPORT_CURVES",
    "REPORT_METRICS",
    "RUNS",
    "decoder",
    "embedding",
    "encoder",
    "rollouts",
    "run",
]

DATA = Path("data")
RUNS = DATA / "runs"
REPORT = DATA / "report"
REPORT_METRICS = DATA / "report-metrics.json"
REPORT_CURVES = DATA / "report-curves"


def rollouts(family: str) -> Path:
    """The family's random-policy rollouts (Zarr store)."""
    return DATA / family / "rollouts.zarr"


def embedding(family: str) -> Path:
    """The folder of the family's encoder and decoder artifacts, metrics and histories."""
    return DATA / family / "embedding"


def encoder(family: str) -> Path:
    return embedding(family) / "encoder"


def decoder(family: str) -> Path:
    return embedding(family) / "decoder"


def run(task: str, algo: str, seed: int) -> Path:
    """One training run's directory."""
    return RUNS / task / algo / f"seed{seed}"
