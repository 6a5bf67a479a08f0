"""The whole of ``params.yaml``: :class:`Params`, and reading, validating and overriding a file.

Each stage validates all of the file before doing any work (extra keys are refused everywhere), so
a typo fails fast with the key path named; a bad file is one :class:`ParamsError`, a line per
problem.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import Field, ValidationError, model_validator

from ede.config.checks import (
    action_space_problems,
    episode_problems,
    placement_problems,
    scale_problems,
)
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
from ede.config.values import Name, Section
from ede.config.wording import ParamsError, found, key_name, validation_problem
from ede.config.yaml import read_yaml

__all__ = ["Params", "load_params", "overridden", "validate_params"]


class Params(Section):
    """The whole of ``params.yaml``.

    Beyond each key's own constraint, keys must agree (:mod:`ede.config.checks`): tasks sit in
    their families, each once, and the numbers leave every stage something to do (a run reaches
    its first update and more than its first and last evaluation; the rollouts fill a batch of
    windows) and fit the families' episodes (each sub-environment's share of the rollouts holds
    one).
    """

    families: dict[Name, FamilyConfig] = Field(min_length=1)
    collect: CollectConfig = CollectConfig()
    embedding: EmbeddingConfig = EmbeddingConfig()
    decoder: DecoderConfig = DecoderConfig()
    td3: TD3Config = TD3Config()
    ede_td3: EdeTD3Config = EdeTD3Config()
    runs: RunsConfig
    report: ReportConfig = ReportConfig()

    @model_validator(mode="after")
    def _keys_agree(self) -> Params:
        problems = [
            *placement_problems(self.families, self.runs, self.report),
            *action_space_problems(self.families),
            *episode_problems(self.families, self.collect, self.embedding.k),
            *scale_problems(self.collect, self.embedding, self.decoder, self.td3, self.runs),
        ]
        if problems:
            raise ValueError("\n".join(problems))
        return self


def load_params(path: str | Path) -> Params:
    """Read and validate a params file.

    Raises:
        ParamsError: naming each bad key, its value and what is expected.
    """
    path = Path(path)
    return validate_params(read_yaml(path), path)


def overridden(params: dict[str, Any], overrides: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """``params`` (a params file's content) with the file ``overrides`` applied, and the overrides.

    An overrides file (an experiment of ``experiments/``, ``quick.yaml`` among them) holds sections
    of the params with only the keys to change; each key given replaces that key's value whole
    (a mapping such as ``runs.budgets`` included), and every other key keeps its value.

    Raises:
        ParamsError: the file cannot be read, is not sections of keys, or its result is not
            valid params (naming ``overrides`` and the key).
    """
    changes = read_yaml(overrides)
    if not isinstance(changes, dict) or not changes:
        held = found(changes)
        expected = "sections of the params with the keys to change"
        raise ParamsError(overrides, [f"{held}; expected {expected}, as experiments/quick.yaml"])
    merged = dict(params)
    for section, values in changes.items():
        if not isinstance(merged.get(section), dict):
            known = ", ".join(key for key, value in params.items() if isinstance(value, dict))
            raise ParamsError(
                overrides, [f"{key_name(section)}: not a section of the params ({known})"]
            )
        if not isinstance(values, dict):
            raise ParamsError(
                overrides, [f"{key_name(section)}: {found(values)}; expected its keys"]
            )
        merged[section] = {**merged[section], **values}
    validate_params(merged, overrides)
    return merged, changes


def validate_params(raw: Any, path: Path) -> Params:
    """Validate a params file's content, as plain data (``experiment run`` merges an experiment's overrides into it).

    Raises:
        ParamsError: naming ``path``, and each bad key, its value and what is expected.
    """
    if not isinstance(raw, dict) or not raw:
        raise ParamsError(
            path, [f"{found(raw)}; expected a mapping of sections (families, runs, …)"]
        )
    try:
        return Params.model_validate(raw)
    except ValidationError as error:
        problems = [line for e in error.errors() for line in validation_problem(e).splitlines()]
        raise ParamsError(path, problems) from None
