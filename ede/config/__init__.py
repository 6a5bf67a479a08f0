"""The parameters of every stage: one pydantic model per section of ``params.yaml``.

``params.yaml`` is the single source of every number in the pipeline. :class:`Params` describes the
whole file (extra keys are refused everywhere); each stage validates all of it before doing any
work, so a typo fails fast with the key path named. Defaults live in the sections and only there;
the committed ``params.yaml`` spells out the paper's configuration in full.

In parts, each importing only those above it:

- :mod:`~ede.config.wording`: :class:`ParamsError` and how a problem is worded, one line each.
- :mod:`~ede.config.values`: what one value may be (algorithms, seeds, names, task ids, …).
- :mod:`~ede.config.schema`: the sections, one model each (what the method imports).
- :mod:`~ede.config.checks`: the checks between keys, some of which build the tasks' environments.
- :mod:`~ede.config.yaml`: reading a file: YAML 1.2, each key once, within bounds.
- :mod:`~ede.config.params`: :class:`Params`, the whole file, and reading, validating and
  overriding one.

Every name below is importable from ``ede.config`` itself.
"""

from __future__ import annotations

from ede.config.checks import episode_length
from ede.config.params import Params, load_params, overridden, validate_params
from ede.config.schema import (
    CollectConfig,
    DecoderConfig,
    EdeTD3Config,
    EmbeddingConfig,
    FamilyConfig,
    ReportConfig,
    RunsConfig,
    TD3Config,
)
from ede.config.values import (
    ALGO_LABELS,
    ALGOS,
    EMBEDDED_ALGOS,
    MAX_INT,
    NAME_LENGTH,
    NAME_RULE,
    PAPER_ALGOS,
    RAW_COUNTERPART,
    RESULT_NEUTRAL,
    SB3_ALGOS,
    SEED_MAX,
    SEED_RANGE,
    Algo,
    Device,
    HiddenSizes,
    Name,
    PositiveInt,
    Precision,
    Repeat,
    Returns,
    Seed,
    TaskId,
    TaskName,
    Threads,
    is_seed,
    name_problem,
    result_neutral,
    task_id_problem,
)
from ede.config.wording import ParamsError, shown
from ede.config.yaml import MAX_BYTES, MAX_DEPTH, MAX_VALUES, parse_yaml, read_yaml

__all__ = [
    "ALGOS",
    "ALGO_LABELS",
    "EMBEDDED_ALGOS",
    "MAX_BYTES",
    "MAX_DEPTH",
    "MAX_INT",
    "MAX_VALUES",
    "NAME_LENGTH",
    "NAME_RULE",
    "PAPER_ALGOS",
    "RAW_COUNTERPART",
    "RESULT_NEUTRAL",
    "SB3_ALGOS",
    "SEED_MAX",
    "SEED_RANGE",
    "Algo",
    "CollectConfig",
    "DecoderConfig",
    "Device",
    "EdeTD3Config",
    "EmbeddingConfig",
    "FamilyConfig",
    "HiddenSizes",
    "Name",
    "Params",
    "ParamsError",
    "PositiveInt",
    "Precision",
    "Repeat",
    "ReportConfig",
    "Returns",
    "RunsConfig",
    "Seed",
    "TD3Config",
    "TaskId",
    "TaskName",
    "Threads",
    "episode_length",
    "is_seed",
    "load_params",
    "name_problem",
    "overridden",
    "parse_yaml",
    "read_yaml",
    "result_neutral",
    "shown",
    "task_id_problem",
    "validate_params",
]
