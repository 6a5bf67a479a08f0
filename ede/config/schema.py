"""The sections of ``params.yaml``: one pydantic model each, with every default.

Each stage and the library take the sections they use (the method :class:`TD3Config` and
:class:`EdeTD3Config`, the embedding :class:`EmbeddingConfig` and :class:`DecoderConfig`); the
whole file, :class:`ede.config.params.Params`, is these sections and the checks between their keys.
Defaults live here and only here; the committed ``params.yaml`` spells out the paper's
configuration in full.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field, field_validator, model_validator

from ede.config.values import (
    MAX_INT,
    PAPER_ALGOS,
    RESULT_NEUTRAL,
    Algo,
    Device,
    HiddenSizes,
    Name,
    PositiveInt,
    Precision,
    Repeat,
    Returns,
    Section,
    Seed,
    TaskId,
    TaskName,
    Threads,
)
from ede.config.wording import shown

__all__ = [
    "CollectConfig",
    "DecoderConfig",
    "EdeTD3Config",
    "EmbeddingConfig",
    "FamilyConfig",
    "ReportConfig",
    "RunsConfig",
    "TD3Config",
]


class FamilyConfig(Section):
    """Tasks that share one robot: the embedding is learned on ``source`` and used on all."""

    source: TaskId = Field(description="gymnasium id of the task the random-policy data comes from")
    targets: list[TaskId] = Field(default_factory=list, description="other tasks of the family")

    @property
    def tasks(self) -> list[str]:
        return [self.source, *self.targets]


class CollectConfig(Section):
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


class EmbeddingConfig(Section):
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


class DecoderConfig(Section):
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


class TD3Config(Section):
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
    compile: Literal["auto", "none", "default", "reduce-overhead"] = Field(
        "auto",
        description="how the update runs: eager (none), compiled whole with "
        "torch.compile (default), or compiled and captured as a CUDA graph on a GPU "
        "(reduce-overhead); auto: default for a run of 25,000 updates or more where a C++ "
        "compiler (CPU) or Triton (GPU) is present, else none; leaves results alone beyond "
        'rounding (docs/performance.md, "compiled updates")',
        json_schema_extra=RESULT_NEUTRAL,
    )


class EdeTD3Config(Section):
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


class RunsConfig(Section):
    """Stage 4: which runs make up the experiment."""

    tasks: dict[TaskId, Name] = Field(
        min_length=1,
        description="the tasks to train on, each with its family: the family whose "
        "embedding EDE-TD3 acts in there (its source, or a target it transfers to)",
    )
    algos: list[Algo] = Field(default_factory=lambda: list(PAPER_ALGOS), min_length=1)
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


class ReportConfig(Section):
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
        "of each task's budget (the bins of EDE-TD3's lead over each other algorithm too). "
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
