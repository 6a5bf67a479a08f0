"""The checks between keys of the params: what each key allows alone, several may still contradict.

Tasks sit in their families, each once, and a family's tasks share one action space; the numbers
leave every stage something to do (a run reaches its first update and more than its first and
last evaluation; the rollouts fill a batch of windows) and fit the families' episodes (each
sub-environment's share of the rollouts holds one). Some of these build the tasks' environments
to read their action spaces and time limits. Each check returns one line per problem, naming the
keys and values.
"""

from __future__ import annotations

import collections
import functools
from collections.abc import Mapping

from ede.config.schema import (
    CollectConfig,
    DecoderConfig,
    EmbeddingConfig,
    FamilyConfig,
    ReportConfig,
    RunsConfig,
    TD3Config,
)
from ede.config.values import EMBEDDED_ALGOS, SB3_ALGOS
from ede.config.wording import both, listed

__all__ = [
    "action_space_problems",
    "episode_length",
    "episode_problems",
    "placement_problems",
    "scale_problems",
]


def placement_problems(
    families: Mapping[str, FamilyConfig], runs: RunsConfig, report: ReportConfig
) -> list[str]:
    """Tasks in their families, each once; the report's families among ``families``."""
    problems = []
    for task, family in runs.tasks.items():
        if family not in families:
            problems.append(
                f"runs.tasks.{task}: got {family!r}; expected a family of "
                f"`families` ({listed(families)})"
            )
        elif task not in families[family].tasks:
            problems.append(
                f"runs.tasks.{task}: not a task of the {family} family "
                f"({listed(families[family].tasks)})"
            )
    for task in report.thresholds:
        if task not in runs.all_tasks:
            problems.append(f"report.thresholds.{task}: not a task of runs.tasks")
    for key in ("effect_space_family", "exploration_family"):
        named = getattr(report, key)
        if named is not None and named not in families:
            problems.append(
                f"report.{key}: got {named!r}; expected a family of `families` "
                f"({listed(families)}) or null"
            )
    in_families: dict[str, list[str]] = {}  # each task, the families it is in
    for name, config in families.items():
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
            problems.append(f"families: {task} in {both(names)}; expected in one family")
    return problems


def action_space_problems(families: Mapping[str, FamilyConfig]) -> list[str]:
    """A family shares one embedding, so its tasks must share one action space."""
    from ede.tasks import action_box, unusable

    problems = []
    for name, family in families.items():
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


def episode_problems(
    families: Mapping[str, FamilyConfig], collect: CollectConfig, k: int
) -> list[str]:
    """Rollouts hold a window of ``k`` actions, and are whole episodes, one per sub-environment
    at least.

    ``collect`` splits ``collect.steps`` among its sub-environments, and each records whole
    episodes until it has its share: at least one episode, whatever its share. So each share
    must hold an episode of the longest source (its time limit), or the store holds far more
    steps than asked for (2,000 sub-environments of 2,000 steps: 200,000). A source without a
    time limit bounds nothing; each sub-environment still needs a step.
    """
    envs = collect.num_envs or 1  # null: one per core, which only the stage knows
    lengths = {
        name: length
        for name, family in families.items()
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
        f"{length}, the episode length of {families[longest].source} (families.{longest}.source)"
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


def scale_problems(
    collect: CollectConfig,
    embedding: EmbeddingConfig,
    decoder: DecoderConfig,
    td3: TD3Config,
    runs: RunsConfig,
) -> list[str]:
    """Numbers valid one by one that together leave a stage nothing to do."""
    problems = []
    # A loose bound: rollouts end in whole episodes and windows must stay inside one.
    windows = collect.steps * (1 - embedding.holdout)
    bound = f"collect.steps {collect.steps} × (1 - embedding.holdout {embedding.holdout})"
    for key, batch_size, stride in (
        ("embedding", embedding.batch_size, embedding.window_stride),
        ("decoder", decoder.batch_size, 1),  # D learns on every training window
    ):
        if windows / stride < batch_size:
            of = f" / embedding.window_stride {stride}" if key == "embedding" else ""
            problems.append(
                f"{key}.batch_size: got {batch_size}; expected at most "
                f"{int(windows / stride)} = {bound}{of}, the most training "
                "windows the rollouts can give: every epoch would be one "
                "partial batch"
            )
    # EDE-TD3 samples k-step sequences: n stored steps hold n - (k - 1) of them. (The agents of
    # stable-baselines3 sample single transitions, a code's in the EDE space: batch_size of them.)
    extra = embedding.k - 1 if "ede-td3" in runs.algos else 0
    batch = f"td3.batch_size {td3.batch_size}" + (
        f" + embedding.k {embedding.k} - 1 (ede-td3's k-step samples)" if extra else ""
    )
    if td3.buffer_size < td3.batch_size + extra:
        problems.append(
            f"td3.buffer_size: got {td3.buffer_size}; expected at least "
            f"{td3.batch_size + extra} = {batch}: no batch could ever be sampled"
        )
    first_update = max(td3.start_steps, td3.batch_size + extra)
    for task in runs.all_tasks:
        budget = runs.budgets[task]
        if budget < first_update:
            problems.append(
                f"runs.budgets.{task}: got {budget}; expected at least "
                f"{first_update} = max(td3.start_steps {td3.start_steps}, "
                f"{batch}), the step of the first update: the run would never "
                "update"
            )
        coded = sorted(set(runs.algos) & EMBEDDED_ALGOS & SB3_ALGOS)
        if coded and budget < td3.batch_size * embedding.k:
            problems.append(
                f"runs.budgets.{task}: got {budget}; expected at least "
                f"{td3.batch_size * embedding.k} = td3.batch_size {td3.batch_size} × "
                f"embedding.k {embedding.k}: {', '.join(coded)} store one transition a code "
                "and would never update"
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
