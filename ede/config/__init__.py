"""The parameters of every stage: one pydantic model per section of ``params.yaml``.

``params.yaml`` is the single source of every number in the pipeline. :class:`Params` describes the
whole file (extra keys are refused everywhere); each stage validates all of it before doing any
work, so a typo fails fast with the key path named. Defaults live here and only here; the
committed ``params.yaml`` spells out the paper's configuration in full.
"""

from __future__ import annotations

import codecs
import collections
import functools
import json
import re
import typing
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic.config import JsonDict

from ede.errors import first_line

__all__ = [
    "ALGOS",
    "ALGO_LABELS",
    "MAX_INT",
    "NAME_RULE",
    "SEED_MAX",
    "SEED_RANGE",
    "Algo",
    "CollectConfig",
    "DecoderConfig",
    "EdeTD3Config",
    "EmbeddingConfig",
    "FamilyConfig",
    "Params",
    "ParamsError",
    "ReportConfig",
    "RunsConfig",
    "TD3Config",
    "episode_length",
    "is_seed",
    "load_params",
    "name_problem",
    "overridden",
    "result_neutral",
    "shown",
    "task_id_problem",
    "validate_params",
]

Algo = Literal["td3", "ede-td3"]
ALGOS: tuple[Algo, ...] = typing.get_args(Algo)
ALGO_LABELS: dict[str, str] = {"td3": "TD3", "ede-td3": "EDE-TD3"}  # as the paper writes them

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


class _Section(BaseModel):
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


class FamilyConfig(_Section):
    """Tasks that share one robot: the embedding is learned on ``source`` and used on all."""

    source: TaskId = Field(description="gymnasium id of the task the random-policy data comes from")
    targets: list[TaskId] = Field(default_factory=list, description="other tasks of the family")

    @property
    def tasks(self) -> list[str]:
        return [self.source, *self.targets]


class CollectConfig(_Section):
    """Stage 1: random actions on a family's source task (uniform, as the paper's)."""

    steps: PositiveInt = Field(100_000, description="environment steps to record")
    num_envs: PositiveInt | None = Field(
        None, description="parallel sub-environments; null means the number of cores"
    )
    seed: Seed = 0
    saturated_episodes: float = Field(
        0.0,
        ge=0,
        le=1,
        description="share of episodes whose actions are bang-bang (each "
        "component at its low or high bound, equally likely) instead of uniform; 0 is the "
        "paper's uniform random data (beyond the paper: docs/results/beyond-the-paper.md, "
        "HalfCheetah-v5)",
    )


class EmbeddingConfig(_Section):
    """Stage 2: the encoder E and predictor P (Section 2.2, Equation for L(θ_E, θ_P))."""

    k: PositiveInt = Field(4, description="actions per embedded sequence")
    dim: PositiveInt | None = Field(None, description="embedding size; null means the action size")
    beta: float = Field(1e-4, ge=0, description="weight of KL(E || N(0, I))")
    hidden: HiddenSizes = Field(default_factory=lambda: [400, 400])
    lr: float = Field(1e-4, gt=0)
    batch_size: PositiveInt = 128
    epochs: PositiveInt = Field(10, description="passes over the training windows")
    window_stride: PositiveInt = Field(
        1,
        description="training windows start every this many steps of an episode: 1 uses every "
        "window (overlapping); k gives non-overlapping windows, as the authors' code (which also "
        "collects 400K steps for its 100K windows: collect.steps 400000)",
    )
    predictor_state: bool = Field(
        True,
        description="whether P sees the state s_t; false feeds it a constant, as the "
        "authors' code does in effect (its delta-encoded first row is always zero), so P predicts "
        "the change from the code alone",
    )
    change_whitening: Literal["final", "all"] = Field(
        "final",
        description="moments that whiten P's target, the k-step change: its own "
        "('final'), or those of the changes after 0..k steps pooled, as the authors' code ('all': "
        "a smaller spread, so the target's variance exceeds 1; docs/fidelity.md, row 6a)",
    )
    holdout: float = Field(0.1, gt=0, lt=1, description="fraction of episodes never trained on")
    seed: Seed = 0
    device: Device = "cpu"
    threads: Threads = 1


class DecoderConfig(_Section):
    """Stage 3: the decoder D, the minimum-norm one-sided inverse of E (Section 2.3)."""

    lam: float = Field(
        1e-4,
        ge=0,
        description="weight λ of the norm penalty: the sum over the batch and the k "
        "steps of ‖a‖, the authors' weighting (README, Stages 2 and 3)",
    )
    z_source: Literal["prior", "marginal"] = Field(
        "marginal",
        description="where training z are drawn: N(0, I) as the paper writes, or E's whitened "
        "marginal on the rollouts as the authors' code does",
    )
    output_range: Literal["bounds", "unit"] = Field(
        "bounds",
        description="how D's tanh becomes actions: mapped onto the action box "
        "('bounds'), or kept in [-1, 1] and clipped to the box as the authors' code ('unit': "
        "within ±1 on the 7-DoF family's ±2 box; docs/fidelity.md, row 11a)",
    )
    hidden: HiddenSizes = Field(default_factory=lambda: [400, 400])
    lr: float = Field(1e-4, gt=0)
    batch_size: PositiveInt = 128
    epochs: PositiveInt = Field(14, description="as many batches as the training windows fill")
    seed: Seed = 0
    device: Device = "cpu"
    threads: Threads = 1


class TD3Config(_Section):
    """TD3 as in its authors' reference code at the paper's time (Fujimoto et al., 2018)."""

    hidden: HiddenSizes = Field(default_factory=lambda: [400, 300])
    batch_size: PositiveInt = 100
    lr: float = Field(1e-3, gt=0, description="Adam learning rate of actor and critics")
    discount: float = Field(0.99, gt=0, le=1)
    tau: float = Field(0.005, gt=0, le=1, description="Polyak rate of the target networks")
    policy_noise: float = Field(0.2, ge=0, description="target smoothing noise std (noise_units)")
    noise_clip: float = Field(0.5, ge=0, description="clip of the target noise (noise_units)")
    policy_delay: PositiveInt = Field(2, description="critic updates per actor update")
    exploration_noise: float = Field(0.1, ge=0, description="behaviour noise std (noise_units)")
    noise_units: Literal["absolute", "range"] = Field(
        "absolute",
        description="TD3's noises in action units (sfujim's TD3, the authors' code) or "
        "× the half-range of the action box (range: stable-baselines3); the same on a ±1 box. "
        "EDE-TD3's are × its bound (ede_td3); docs/fidelity.md, row 8d",
    )
    critic_action_repeat: Repeat = Field(
        1,
        description="copies of (action or code, plan step) the critic sees; auto: the authors' "
        "max(1, ⌊0.5·obs size / their size⌋); 1: standard TD3 (stable-baselines3); docs/fidelity.md, "
        "rows 7a–7b",
    )
    start_steps: int = Field(
        0,
        ge=0,
        le=MAX_INT,
        description="uniform random steps before the policy acts and updates start; 0 (the "
        "authors' code): the actor plus exploration noise acts from the first step, and updates "
        "start as soon as a batch can be sampled",
    )
    update_schedule: Literal["step", "episode"] = Field(
        "episode",
        description="episode (the authors' code): at each episode's end as many "
        "updates as it had steps, the policy fixed while it collects; step: one update after "
        "every environment step (the paper's text, standard TD3). "
        "docs/fidelity.md, row 2: it moves TD3's result",
    )
    buffer_size: PositiveInt = 1_000_000
    eval_every: PositiveInt = Field(
        1_000, description="steps between evaluations (the authors' code)"
    )
    eval_episodes: PositiveInt = 10
    checkpoint_every: PositiveInt = Field(
        50_000, description="steps between a run's checkpoints", json_schema_extra=RESULT_NEUTRAL
    )
    precision: Precision = Field(
        "fp32",
        description="fp32; bf16-matmul: fp32 tensors, matrix products from bf16 inputs with fp32 "
        "accumulation (TF32 on CUDA); bf16: bf16 autocast (fp32 weights and optimiser state)",
    )
    device: Device = "cpu"
    threads: Threads = 1
    env_workers: Literal["auto", "yes", "no"] = Field(
        "auto",
        description="a group's environments in worker processes (gymnasium's AsyncVectorEnv, "
        "one per environment) or in the training process (SyncVectorEnv); auto: workers on a "
        "GPU machine for a group of several members, given at least 4 cores "
        '(docs/scaling.md, "Groups")',
        json_schema_extra=RESULT_NEUTRAL,
    )
    compile: Literal["none", "default", "reduce-overhead"] = Field(
        "none",
        description="how the update runs: eager (none), compiled whole with "
        "torch.compile (default), or compiled and captured as a CUDA graph on a GPU "
        '(reduce-overhead); leaves results alone beyond rounding (README, "Stage 4: train")',
        json_schema_extra=RESULT_NEUTRAL,
    )


class EdeTD3Config(_Section):
    """What EDE-TD3 adds to TD3 (Section 3); every TD3 number is shared."""

    bound_scale: float = Field(
        1.0, gt=0, description="the actor's |z| bound, × the largest whitened |z| the decoder saw"
    )
    target_noise_scale: float = Field(
        0.25,
        gt=0,
        description="target smoothing noise std, × td3.policy_noise × the bound; "
        "0.25 = 1/k for k = 4, as the authors' code (one code moves the state k steps, so the "
        "same noise on it perturbs k actions)",
    )
    target_noise_clip: Literal["absolute", "scaled"] = Field(
        "absolute",
        description="absolute: the target noise is clipped at td3.noise_clip in code "
        "units (the authors' code); scaled: at td3.noise_clip × the bound × target_noise_scale "
        "(docs/fidelity.md, row 8a)",
    )
    plan_step_input: Literal["onehot", "scalar"] = Field(
        "onehot",
        description="how the critic sees i, the steps of the code already executed: a "
        "one-hot of size k, or the raw count as one input (the authors' code; docs/fidelity.md, "
        "row 7a)",
    )


class RunsConfig(_Section):
    """Stage 4: which runs make up the experiment."""

    tasks: dict[TaskId, Name] = Field(
        min_length=1,
        description="the tasks to train on, each with its family: the family whose "
        "embedding EDE-TD3 acts in there (its source, or a target it transfers to)",
    )
    algos: list[Algo] = Field(default_factory=lambda: list(ALGOS), min_length=1)
    seeds: list[Seed] = Field(min_length=1)
    budgets: dict[TaskId, PositiveInt] = Field(
        description="environment steps per task: every task of runs.tasks, and any other "
        "registered task (the budgets of the paper's tasks stay when an experiment trains fewer)"
    )

    @field_validator("tasks", mode="before")
    @classmethod
    def _task_to_family(cls, tasks: Any) -> Any:
        if isinstance(tasks, dict) and any(isinstance(v, list) for v in tasks.values()):
            raise ValueError(
                "runs.tasks: expected each task mapped to its family "
                "(`ede/ReacherTurn-v0: reacher`), not a family to a list of tasks "
                "(the format before dvc.yaml had one train stage for every family)"
            )
        return tasks

    @model_validator(mode="after")
    def _every_run_is_named_once(self) -> RunsConfig:
        problems = []
        missing = [task for task in self.all_tasks if task not in self.budgets]
        if missing:
            problems.append(f"runs.budgets: no budget for {', '.join(missing)}")
        if len(set(self.algos)) != len(self.algos):
            problems.append(
                f"runs.algos: {shown(self.algos)} repeats an algorithm; expected distinct "
                "algorithms"
            )
        if len(set(self.seeds)) != len(self.seeds):
            problems.append(
                f"runs.seeds: {shown(self.seeds)} repeats a seed; expected distinct seeds"
            )
        if problems:
            raise ValueError("\n".join(problems))
        return self

    @property
    def all_tasks(self) -> list[str]:
        return list(self.tasks)

    def by_family(self) -> dict[str, list[str]]:
        """The tasks to train on, grouped by family, in their order."""
        grouped: dict[str, list[str]] = {}
        for task, family in self.tasks.items():
            grouped.setdefault(family, []).append(task)
        return grouped

    @property
    def count(self) -> int:
        return len(self.all_tasks) * len(self.algos) * len(self.seeds)


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


class ReportConfig(_Section):
    """Stage 5: the report's statistics, and the families of its two pictures."""

    confidence: float = Field(0.95, gt=0, lt=1)
    # At most 10^5 resamples: rliable draws them one by one (a second or so a curve at 10^5); the
    # interval's Monte Carlo error, already well under its width at 2,000, falls as 1/√samples.
    bootstrap_samples: int = Field(2_000, gt=0, le=100_000)
    thresholds: dict[TaskName, Returns] = Field(
        default_factory=dict,
        description="per task, a return that counts as solved, or a list of "
        "them: the report gives the steps each run takes to reach each",
    )
    seed: Seed = 0
    bin_steps: PositiveInt | None = Field(
        2_500,
        description="average each run's evaluations in bins of this many steps before the "
        "mean over seeds, as the authors' figures (2,500 for ReacherVertical); null: a twentieth "
        "of each task's budget (the bins of its divergence check too). "
        "The report's curve CSVs (DVC plots) keep every evaluation",
    )
    effect_space_family: Name | None = Field(
        "point",
        description="a family of `families` whose embedding is drawn beside the effect "
        "space on its source task (Figure 6; the task's first two qpos are its position); null: "
        "no Figure 6",
    )
    exploration_family: Name | None = Field(
        "pointmass",
        description="a family of `families` whose embedding explores its source task "
        "against uniform random actions (Figure 7; the first two qpos are a position in "
        "[-1, 1]²); null: no Figure 7",
    )
    videos: bool = Field(
        True,
        description="per task, one episode of TD3 beside EDE-TD3 of the same seed (the median "
        "seed by EDE-TD3's final return), played from their final policies (`ede-pipeline "
        "render`); needs offscreen GL (MUJOCO_GL=egl or osmesa)",
    )


class Params(_Section):
    """The whole of ``params.yaml``.

    Beyond each key's own constraint, keys must agree: tasks sit in their families, each once, and
    the numbers leave every stage something to do (a run reaches its first update and more than its
    first and last evaluation; the rollouts fill a batch of windows) and fit the families'
    episodes (each sub-environment's share of the rollouts holds one).
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
        problems = self._placement_problems() + self._scale_problems()
        if problems:
            raise ValueError("\n".join(problems))
        return self

    def _placement_problems(self) -> list[str]:
        """Tasks in their families, each once; the report's families among ``families``."""
        problems = []
        for task, family in self.runs.tasks.items():
            if family not in self.families:
                problems.append(
                    f"runs.tasks.{task}: got {family!r}; expected a family of "
                    f"`families` ({_listed(self.families)})"
                )
            elif task not in self.families[family].tasks:
                problems.append(
                    f"runs.tasks.{task}: not a task of the {family} family "
                    f"({_listed(self.families[family].tasks)})"
                )
        for task in self.report.thresholds:
            if task not in self.runs.all_tasks:
                problems.append(f"report.thresholds.{task}: not a task of runs.tasks")
        for key in ("effect_space_family", "exploration_family"):
            named = getattr(self.report, key)
            if named is not None and named not in self.families:
                problems.append(
                    f"report.{key}: got {named!r}; expected a family of `families` "
                    f"({_listed(self.families)}) or null"
                )
        in_families: dict[str, list[str]] = {}  # each task, the families it is in
        for name, config in self.families.items():
            counts = collections.Counter(config.tasks)
            repeated = [task for task in config.targets if counts[task] > 1]
            if repeated:
                problems.append(
                    f"families.{name}.targets: {', '.join(dict.fromkeys(repeated))} "
                    "given twice in the family (its source counts); expected each "
                    "task once"
                )
            for task in counts:
                in_families.setdefault(task, []).append(name)
        for task, names in in_families.items():
            if len(names) > 1:
                problems.append(f"families: {task} in {_both(names)}; expected in one family")
        problems += self._action_space_problems()
        return problems

    def _action_space_problems(self) -> list[str]:
        """A family shares one embedding, so its tasks must share one action space."""
        from ede.tasks import action_box, unusable

        problems = []
        for name, family in self.families.items():
            if any(unusable(task) for task in family.tasks):
                continue  # each such task is refused by name already
            source = action_box(family.source)
            for target in family.targets:
                if action_box(target) != source:
                    problems.append(
                        f"families.{name}.targets: {target}'s actions are not "
                        f"{family.source}'s (a family shares one action space, "
                        "and so one embedding)"
                    )
        return problems

    def _episode_problems(self) -> list[str]:
        """Rollouts hold a window of k actions, and are whole episodes, one per sub-environment
        at least.

        ``collect`` splits ``collect.steps`` among its sub-environments, and each records whole
        episodes until it has its share: at least one episode, whatever its share. So each share
        must hold an episode of the longest source (its time limit), or the store holds far more
        steps than asked for (2,000 sub-environments of 2,000 steps: 200,000). A source without a
        time limit bounds nothing; each sub-environment still needs a step.
        """
        collect, k = self.collect, self.embedding.k
        envs = collect.num_envs or 1  # null: one per core, which only the stage knows
        lengths = {
            name: length
            for name, family in self.families.items()
            if (length := episode_length(family.source)) is not None
        }
        problems = []
        if collect.steps < k:
            problems.append(
                f"collect.steps: got {collect.steps}; expected at least embedding.k "
                f"({k}): no window of k actions fits in the rollouts"
            )
        if not lengths:
            if envs > collect.steps:
                problems.append(
                    f"collect.num_envs: got {envs}; expected at most collect.steps "
                    f"({collect.steps}): each sub-environment records an equal share "
                    "of the steps, so some would record none"
                )
            return problems
        longest = max(lengths, key=lengths.__getitem__)
        length = lengths[longest]
        episode = (
            f"{length}, the episode length of {self.families[longest].source} "
            f"(families.{longest}.source)"
        )
        recorded = f"record about {envs * length} steps, not {collect.steps}"
        if collect.steps < length:
            problems.append(
                f"collect.steps: got {collect.steps}; expected at least {episode}: "
                "collect records whole episodes, at least one per sub-environment, "
                f"so it would {recorded}"
            )
        elif envs * length > collect.steps:
            problems.append(
                f"collect.num_envs: got {envs}; expected at most "
                f"{collect.steps // length} = collect.steps {collect.steps} // "
                f"{episode}: each sub-environment records whole episodes, at least "
                f"one, so {envs} of them would {recorded}"
            )
        return problems

    def _scale_problems(self) -> list[str]:
        """Numbers valid one by one that together leave a stage nothing to do."""
        collect, embedding, td3 = self.collect, self.embedding, self.td3
        problems = self._episode_problems()
        # A loose bound: rollouts end in whole episodes and windows must stay inside one.
        windows = collect.steps * (1 - embedding.holdout)
        bound = f"collect.steps {collect.steps} × (1 - embedding.holdout {embedding.holdout})"
        for key, batch_size, stride in (
            ("embedding", embedding.batch_size, embedding.window_stride),
            ("decoder", self.decoder.batch_size, 1),  # D learns on every training window
        ):
            if windows / stride < batch_size:
                of = f" / embedding.window_stride {stride}" if key == "embedding" else ""
                problems.append(
                    f"{key}.batch_size: got {batch_size}; expected at most "
                    f"{int(windows / stride)} = {bound}{of}, the most training "
                    "windows the rollouts can give: every epoch would be one "
                    "partial batch"
                )
        # EDE-TD3 samples k-step sequences: n stored steps hold n - (k - 1) of them.
        extra = embedding.k - 1 if "ede-td3" in self.runs.algos else 0
        batch = f"td3.batch_size {td3.batch_size}" + (
            f" + embedding.k {embedding.k} - 1 (ede-td3's k-step samples)" if extra else ""
        )
        if td3.buffer_size < td3.batch_size + extra:
            problems.append(
                f"td3.buffer_size: got {td3.buffer_size}; expected at least "
                f"{td3.batch_size + extra} = {batch}: no batch could ever be sampled"
            )
        first_update = max(td3.start_steps, td3.batch_size + extra)
        for task in self.runs.all_tasks:
            budget = self.runs.budgets[task]
            if budget < first_update:
                problems.append(
                    f"runs.budgets.{task}: got {budget}; expected at least "
                    f"{first_update} = max(td3.start_steps {td3.start_steps}, "
                    f"{batch}), the step of the first update: the run would never "
                    "update"
                )
            if budget < td3.eval_every:
                problems.append(
                    f"runs.budgets.{task}: got {budget}; expected at least "
                    f"td3.eval_every ({td3.eval_every}): the run would have only "
                    "its initial and final evaluations"
                )
        return problems


@functools.cache
def episode_length(task: str) -> int | None:
    """The most steps an episode of a registered ``task`` lasts (its time limit), if it has one."""
    import gymnasium

    return gymnasium.spec(task).max_episode_steps


@functools.cache
def _registered_task_ids() -> frozenset[str]:
    import gymnasium

    import ede_envs

    ede_envs.register_envs()
    return frozenset(gymnasium.registry)


class ParamsError(ValueError):
    """A params file that cannot be used; ``problems`` holds one line per problem."""

    def __init__(self, path: Path, problems: list[str]) -> None:
        self.path = path
        self.problems = problems
        super().__init__("\n".join(f"{path}: {problem}" for problem in problems))


# What a params or experiment file may hold, bounded so that reading a bad one ends in a line at
# once (the committed params.yaml: 6 kB, 4 levels deep, about 250 values): its size, read before
# anything is parsed; how deep it nests (PyYAML composes recursively: a file nested 100,000 levels
# would end in a RecursionError); how many values it holds once its aliases are expanded (nine
# aliases of nine aliases of … of a list, "billion laughs", are a few lines that validation would
# walk for hours); and how long an integer is (Python converts no more than 4,300 digits; the
# schema bounds each integer parameter by :data:`MAX_INT`, naming its key).
MAX_BYTES = 1 << 18
MAX_DEPTH = 32
MAX_VALUES = 10_000
_INT_CHARS = 100  # an integer's longest spelling read at all: 2**63 has 19 digits (64 in binary)


class _Refused(yaml.MarkedYAMLError):
    """What the loader refuses in YAML it can read: a key given twice, too deep a nesting, too
    many values, too large an integer."""


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing a key given twice in one mapping (PyYAML keeps the last,
    silently; DVC refuses such a file) and what exceeds the bounds above."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0  # how many nodes the node being composed is inside
        self._values = 0  # how many values composed so far, each alias counted as what it names
        self._sizes: dict[int, int] = {}  # the values of each node counted (_expanded_size)

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node | None:
        if self._depth == MAX_DEPTH:
            raise _Refused(
                problem=f"nested more than {MAX_DEPTH} levels deep; params nest 4",
                problem_mark=self.peek_event().start_mark,
            )
        alias = self.check_event(yaml.AliasEvent)
        self._depth += 1
        try:
            node = super().compose_node(parent, index)
        finally:
            self._depth -= 1
        if node is None:
            return node
        self._values += _expanded_size(node, self._sizes) if alias else 1  # children counted
        if self._values > MAX_VALUES:
            raise _Refused(
                problem=f"more than {MAX_VALUES} values (each alias, *name, counted as what it "
                "names); params hold about 250",
                problem_mark=node.start_mark,
            )
        return node

    def construct_yaml_int(self, node: yaml.ScalarNode) -> int:
        spelled = self.construct_scalar(node)
        if len(spelled) > _INT_CHARS:  # checked by key once read; this long, it is not read
            raise _Refused(
                problem=f"an integer of {len(spelled)} characters ({spelled[:12]}…); no "
                f"parameter takes more than 2**63 - 1 (19 digits)",
                problem_mark=node.start_mark,
            )
        return super().construct_yaml_int(node)

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        first: dict[Any, yaml.Mark] = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                mark = first.setdefault(key, key_node.start_mark)
            except TypeError:  # an unhashable key: the base class says so
                break
            if mark is not key_node.start_mark:
                again = key_node.start_mark.line
                where = (
                    f"on line {again + 1}"
                    if again == mark.line
                    else f"on lines {mark.line + 1} and {again + 1}"
                )
                raise _Refused(
                    problem=f"key {shown(key)} given twice, {where}; give it once",
                    problem_mark=key_node.start_mark,
                )
        return super().construct_mapping(node, deep=deep)


_UniqueKeyLoader.add_constructor("tag:yaml.org,2002:int", _UniqueKeyLoader.construct_yaml_int)


def _expanded_size(node: yaml.Node, sizes: dict[int, int]) -> int:
    """How many values ``node`` holds, itself included, each alias counted as what it names
    (``sizes``: those of the nodes counted so far, so that each is counted once)."""
    if id(node) not in sizes:
        children: list[yaml.Node] = []
        if isinstance(node, yaml.SequenceNode):
            children = node.value
        elif isinstance(node, yaml.MappingNode):
            children = [child for pair in node.value for child in pair]
        sizes[id(node)] = 1 + sum(_expanded_size(child, sizes) for child in children)
    return sizes[id(node)]


# Floats of YAML 1.2 that PyYAML (YAML 1.1) reads as strings: an exponent after no dot, or without
# a sign (1e-4, 1.0e4). DVC writes YAML 1.2: `dvc exp run -S embedding.beta=0.00001` leaves
# `beta: 1e-05` in params.yaml.
_UniqueKeyLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+.0123456789"),
)


def read_yaml(path: Path) -> Any:
    """A YAML file's content, each key of a mapping given once, within the bounds above.

    Raises:
        ParamsError: one line saying where the file cannot be read, and why.
    """
    try:
        with path.open("rb") as handle:
            data = handle.read(MAX_BYTES + 1)
    except FileNotFoundError:
        raise ParamsError(path, ["no such file"]) from None
    except IsADirectoryError:
        raise ParamsError(path, ["a directory; expected a YAML file"]) from None
    except OSError as error:
        raise ParamsError(path, [f"not readable ({first_line(error)})"]) from None
    if len(data) > MAX_BYTES:
        raise ParamsError(path, [_TOO_LARGE])
    return parse_yaml(_utf8(data, path), path)


_TOO_LARGE = (
    f"larger than {MAX_BYTES >> 10} KiB; expected a file of a few kilobytes, as params.yaml"
)


def _utf8(data: bytes, path: Path) -> str:
    """A file's bytes as UTF-8 text (YAML's and DVC's encoding), or one line saying why not."""
    if data.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):  # UTF-32's LE mark too
        problem = "UTF-16 or UTF-32 text (it starts with their byte order mark)"
        raise ParamsError(path, [f"{problem}; expected UTF-8: save it as UTF-8"])
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as error:
        line = data[: error.start].count(b"\n") + 1
        problem = f"not UTF-8 text (byte {data[error.start]:#04x} on line {line})"
        raise ParamsError(path, [f"{problem}; expected UTF-8: save it as UTF-8"]) from None


def parse_yaml(text: str, path: Path) -> Any:
    """YAML text's content, each key of a mapping given once, within the bounds above; ``path``
    names it in errors.

    Raises:
        ParamsError: one line saying where the text cannot be read, and why.
    """
    if len(text) > MAX_BYTES:
        raise ParamsError(path, [_TOO_LARGE])
    try:
        return yaml.load(text, Loader=_UniqueKeyLoader)
    except _Refused as error:
        where = f"line {error.problem_mark.line + 1}: " if error.problem_mark else ""
        raise ParamsError(path, [f"{where}{error.problem}"]) from None
    except yaml.YAMLError as error:
        raise ParamsError(path, [_describe_yaml_error(error, text)]) from None


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
        found = _found(changes)
        expected = "sections of the params with the keys to change"
        raise ParamsError(overrides, [f"{found}; expected {expected}, as experiments/quick.yaml"])
    merged = dict(params)
    for section, values in changes.items():
        if not isinstance(merged.get(section), dict):
            known = ", ".join(key for key, value in params.items() if isinstance(value, dict))
            raise ParamsError(
                overrides, [f"{_key(section)}: not a section of the params ({known})"]
            )
        if not isinstance(values, dict):
            raise ParamsError(overrides, [f"{_key(section)}: {_found(values)}; expected its keys"])
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
            path, [f"{_found(raw)}; expected a mapping of sections (families, runs, …)"]
        )
    try:
        return Params.model_validate(raw)
    except ValidationError as error:
        problems = [line for e in error.errors() for line in _describe(e).splitlines()]
        raise ParamsError(path, problems) from None


def _describe(error: Any) -> str:
    loc = error["loc"][:-1] if error["loc"][-1:] == ("[key]",) else error["loc"]  # a bad key
    where = ".".join(_key(part) for part in loc) or "(top level)"
    message = error["msg"].removeprefix("Value error, ")
    if error["type"] == "extra_forbidden":
        return f"{where}: unknown key"
    if error["type"] == "missing":
        return f"{where}: missing; this key is required"
    if error["type"] == "value_error" and isinstance(error.get("input"), dict):
        return message  # cross-key checks name their own keys, one line per problem
    if error["type"] in _EXPECTED:  # a value of another type: say which, in YAML's words
        value = error.get("input")
        kind = "" if value is None else f", {_KINDS.get(type(value), 'a ' + type(value).__name__)}"
        return f"{where}: got {shown(value)}{kind}; expected {_EXPECTED[error['type']]}"
    if message.startswith("Input should be "):
        message = "expected " + message.removeprefix("Input should be ")
    elif message.startswith("a registered"):
        message = "expected " + message
    return f"{where}: got {shown(error.get('input'))}; {message}"


# A YAML value's type, and what each of pydantic's errors for a value of another type expects.
_KINDS = {
    bool: "a boolean",
    int: "an integer",
    float: "a number",
    str: "a string",
    list: "a list",
    dict: "a mapping",
}
_EXPECTED = {
    "bool_type": "true or false",
    "int_type": "an integer",
    "float_type": "a number",
    "string_type": "a string",
    "list_type": "a list",
    "dict_type": "a mapping",
    "model_type": "a mapping",
}


def _key(part: str | int) -> str:
    """A key of a key path as written, or quoted and escaped where it is no plain key (a space, a
    line break, a name too long): a problem stays one line."""
    text = str(part)
    return text if _PLAIN_KEY.fullmatch(text) else shown(text)


_PLAIN_KEY = re.compile(r"[A-Za-z0-9_./-]{1,100}")


def _both(names: list[str]) -> str:
    """``both a and b``, ``a, b, c``, or ``a, b, c and 7 more``."""
    return f"both {names[0]} and {names[1]}" if len(names) == 2 else _listed(names, most=3)


def _listed(names: Iterable[str], most: int = 8) -> str:
    """``a, b, c``, each once; past ``most`` of them, the first ``most`` and how many more (a
    problem stays a line however many families the params hold)."""
    distinct = list(dict.fromkeys(names))
    if len(distinct) <= most:
        return ", ".join(distinct)
    return f"{', '.join(distinct[:most])} and {len(distinct) - most} more"


def _found(content: Any) -> str:
    """What a file or section holds instead of the mapping expected, in YAML's words."""
    if content is None or content == {}:
        return "empty"
    return f"{_KINDS.get(type(content), 'a ' + type(content).__name__)}, not a mapping"


def shown(value: Any) -> str:
    """A value as one short line: its repr (JSON's null, true, false), cut at 60 characters."""
    text = json.dumps(value) if value is None or isinstance(value, bool) else repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _describe_yaml_error(error: yaml.YAMLError, text: str) -> str:
    """One line: where (1-based, as editors count), what PyYAML says, and the line's text.

    A problem found at the end of the stream (an unclosed bracket or quote) is placed where its
    context began, the line to fix, rather than past the last line.
    """
    if isinstance(error, yaml.reader.ReaderError):  # a character YAML refuses (a NUL byte)
        number = text.count("\n", 0, error.position) + 1
        return f"line {number}: not readable YAML ({first_line(error)})"
    if not (isinstance(error, yaml.MarkedYAMLError) and error.problem_mark and error.problem):
        return f"not readable YAML ({first_line(error)})"
    mark, problem = error.problem_mark, error.problem
    context, context_mark = error.context, error.context_mark
    if context_mark is not None and not text[mark.index :].strip():  # at the end of the stream
        mark = context_mark
    if context and context_mark is not None and context_mark.index != mark.index:
        context += f" from line {context_mark.line + 1}, column {context_mark.column + 1}"
    lines = text.splitlines()
    line = lines[mark.line] if mark.line < len(lines) else ""
    shown = line if len(line) <= 100 else line[:97] + "..."
    return (
        f"line {mark.line + 1}, column {mark.column + 1}: not readable YAML: {problem}"
        + (f" ({context})" if context else "")
        + f"; the line reads: {json.dumps(shown, ensure_ascii=False)}"
    )
