"""What one value of the params may be: the field types the sections are made of.

An algorithm, a seed, a name, a registered task id, a device, a count of threads, … : each a type
with its bound, checked by pydantic wherever a section holds one, so that a bad value is refused
naming its key before anything uses it. :class:`Section` is every section's base: strict, frozen,
no extra keys.
"""

from __future__ import annotations

import functools
import re
import typing
from collections.abc import Callable
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field
from pydantic.config import JsonDict

__all__ = [
    "ALGOS",
    "ALGO_LABELS",
    "EMBEDDED_ALGOS",
    "MAX_INT",
    "NAME_LENGTH",
    "NAME_RULE",
    "PAPER_ALGOS",
    "RAW_COUNTERPART",
    "RESULT_NEUTRAL",
    "SB3_ALGOS",
    "SEED_MAX",
    "SEED_RANGE",
    "Algo",
    "Device",
    "HiddenSizes",
    "Name",
    "PositiveInt",
    "Precision",
    "Repeat",
    "Returns",
    "Section",
    "Seed",
    "TaskId",
    "TaskName",
    "Threads",
    "is_seed",
    "name_problem",
    "result_neutral",
    "task_id_problem",
]

# The paper's two algorithms, ours, and stable-baselines3's agents beside them (docs/any-agent.md):
# its TD3 and SAC acting in the family's EDE space through ``ede.EmbeddedActions`` (a code every k
# steps, learning from k-step transitions), and its SAC on raw actions.
Algo = Literal["td3", "ede-td3", "sb3-td3-ede", "sb3-sac-ede", "sb3-sac"]
ALGOS: tuple[Algo, ...] = typing.get_args(Algo)
ALGO_LABELS: dict[str, str] = {  # the paper's two as the paper writes them
    "td3": "TD3",
    "ede-td3": "EDE-TD3",
    "sb3-td3-ede": "SB3 TD3 (EDE space)",
    "sb3-sac-ede": "SB3 SAC (EDE space)",
    "sb3-sac": "SB3 SAC",
}
PAPER_ALGOS: tuple[Algo, ...] = ("td3", "ede-td3")
"""The pair the paper compares, and params.yaml's default ``runs.algos``."""
RAW_COUNTERPART: dict[Algo, Algo] = {
    "ede-td3": "td3",
    "sb3-td3-ede": "td3",
    "sb3-sac-ede": "sb3-sac",
}
"""Each algorithm that acts in its family's EDE space, and the same learner on raw actions: what
the space is measured against. SB3's TD3 update is ours (``tests/ede/test_td3_reference.py``), so
TD3 is SB3's TD3's raw counterpart as it is EDE-TD3's."""
EMBEDDED_ALGOS: frozenset[Algo] = frozenset(RAW_COUNTERPART)
"""The algorithms that act in their family's embedding (and so need it, and record its checksum)."""
SB3_ALGOS: frozenset[Algo] = frozenset({"sb3-td3-ede", "sb3-sac-ede", "sb3-sac"})
"""The algorithms stable-baselines3 trains (:mod:`ede.run.sb3`): one run a process, never a group."""

# The mark of a setting that decides where or how fast a stage runs, never what it computes (a
# field's ``json_schema_extra``). :func:`result_neutral` reads it: run identities and the embedding
# artifacts' params check leave these keys out, and ``dvc.yaml`` tracks every key but these
# (``tests/pipeline/test_dvc.py`` holds it to them).
RESULT_NEUTRAL: JsonDict = {"result_neutral": True}

MAX_INT = 2**63 - 1
"""The largest integer parameter: NumPy's and torch's integers hold no more."""
PositiveInt = Annotated[int, Field(gt=0, le=MAX_INT)]

SEED_MAX = 2**32 - 1
"""The largest seed. NumPy's global generator, which the report seeds for rliable's bootstrap,
takes 32 bits; every other consumer takes more, with room for what is added to a seed: torch's
generators (64 bits) get ``seed + 1``, the environments' resets (any size) ``seed + i`` for
sub-environment ``i`` and ``1_000_003 × (seed + 1) + e`` for evaluation episode ``e``, and
``SeedSequence`` any size."""
SEED_RANGE = f"from 0 to {SEED_MAX}"


def is_seed(value: int) -> bool:
    """Whether every consumer of a seed accepts ``value`` (:data:`SEED_MAX`)."""
    return 0 <= value <= SEED_MAX


def _seed(value: int) -> int:
    if not is_seed(value):
        raise ValueError(f"expected a seed {SEED_RANGE} (2**32 - 1)")
    return value


Seed = Annotated[
    int,
    AfterValidator(_seed),
    Field(description="seed of every random number generator of a stage"),
]


# Names. A family's name, an experiment's and each part of a task id become path segments
# (data/families/NAME/, data/runs/TASK/, .dvc/tmp/experiments/NAME/), words of dvc.yaml's stage
# commands, DVC's stage names and param keys (`families.NAME`: a '.' there would be a key path's
# separator) and git refs (an experiment's). A name is therefore of the few characters all of these
# hold as they are: ASCII letters, digits, '-' and '_', the first a letter or digit (a word starting
# with '-' reads as an option); never a shell's metacharacter, a space, '/', '.' or '..'. Checked
# before anything uses it, so a name that reaches a path or a command is one of these.
NAME_LENGTH = 64
NAME_RULE = (
    f"1 to {NAME_LENGTH} ASCII letters, digits, '-' and '_', the first a letter or digit "
    '(docs/parameters.md, "Names")'
)
_NAME = re.compile(rf"[A-Za-z0-9][A-Za-z0-9_-]{{0,{NAME_LENGTH - 1}}}")


def name_problem(name: str) -> str | None:
    """Why ``name`` cannot name a family or an experiment (:data:`NAME_RULE`), or None."""
    return None if _NAME.fullmatch(name) else f"expected a name: {NAME_RULE}"


def task_id_problem(task: str) -> str | None:
    """Why ``task`` cannot be a task id, or None: a name, or a namespace and a name joined by one
    '/' (gymnasium's ``ede/ReacherVertical-v0``), each part as :func:`name_problem` says."""
    if all(_NAME.fullmatch(part) for part in task.split("/", 1)):
        return None
    return f"expected a task id: a name, or a namespace and a name joined by '/', each {NAME_RULE}"


def _check(problem: Callable[[str], str | None]) -> Callable[[str], str]:
    """A pydantic validator of a string that ``problem`` finds nothing wrong with."""

    def check(value: str) -> str:
        if (found := problem(value)) is not None:
            raise ValueError(found)
        return value

    return check


Name = Annotated[str, AfterValidator(_check(name_problem))]
TaskName = Annotated[str, AfterValidator(_check(task_id_problem))]


def _registered(task: str) -> str:
    if task not in _registered_task_ids():
        raise ValueError("a registered gymnasium task id (see `ede-pipeline envs`)")
    from ede.tasks import unusable

    reason = unusable(task)
    if reason is not None:
        raise ValueError(f"not usable: {reason}")
    return task


@functools.cache
def _registered_task_ids() -> frozenset[str]:
    import gymnasium

    import ede_envs

    ede_envs.register_envs()
    return frozenset(gymnasium.registry)


TaskId = Annotated[TaskName, AfterValidator(_registered)]
Device = Annotated[
    Literal["cpu", "cuda", "auto"],
    Field(description="where torch runs; auto: CUDA if present", json_schema_extra=RESULT_NEUTRAL),
]
Threads = Annotated[
    int,
    Field(
        gt=0,
        le=1024,  # torch takes a C int, and far fewer are of use
        description="torch threads on CPU: 1 is fastest for networks this small and "
        "lets stages and runs share the cores (more threads than cores slows everything)",
        json_schema_extra=RESULT_NEUTRAL,
    ),
]
Precision = Literal["fp32", "bf16-matmul", "bf16"]


def _repeat(value: Any) -> int | str:
    if value == "auto":
        return value
    if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
        raise ValueError("expected a positive integer or 'auto'")
    if value > MAX_INT:
        raise ValueError(f"expected at most {MAX_INT} (2**63 - 1)")
    return value


Repeat = Annotated[Any, AfterValidator(_repeat)]
HiddenSizes = Annotated[
    list[PositiveInt], Field(min_length=1, description="hidden layer widths of an MLP")
]


class Section(BaseModel):
    """The base of every section: no unknown key, no infinity or NaN, each value of its own type
    (strict), frozen."""

    # Infinities and NaN are not numbers a parameter can mean (and not valid JSON in run.json).
    # Strict: a value is what it says — true is no 1, "1" no number, 1 no string (an int is a
    # float, as YAML writes 1 for 1.0).
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, strict=True)


def result_neutral(section: type[BaseModel]) -> frozenset[str]:
    """The keys of ``section`` marked :data:`RESULT_NEUTRAL`: where or how fast it runs."""
    return frozenset(
        name
        for name, field in section.model_fields.items()
        if isinstance(field.json_schema_extra, dict)
        and field.json_schema_extra.get("result_neutral")
    )


def _returns(value: Any) -> Any:
    """A return, or a list of them, as a list (``report.thresholds``)."""
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    if number:
        return [value]
    if (
        not isinstance(value, list)
        or not value
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    ):
        raise ValueError("expected a return or a non-empty list of returns")
    return value


Returns = Annotated[list[float], BeforeValidator(_returns)]
