"""Stage 4, ``ede-pipeline train``: one run of one task, algorithm and seed (TD3 or EDE-TD3, or
stable-baselines3's agents beside them: :mod:`ede.run.sb3`)."""

from __future__ import annotations

import functools
from collections.abc import Sequence
from contextlib import ExitStack
from itertools import pairwise
from pathlib import Path

import click
import numpy as np
import torch

from ede.config import ALGO_LABELS, ALGOS, EMBEDDED_ALGOS, SB3_ALGOS, SEED_RANGE, Params, is_seed
from ede.method.embedding import ActionEmbedding
from ede.method.nets import pick_device
from ede.method.td3 import Critic
from ede.run.artifacts import ArtifactError, load_action_embedding, params_mismatches
from ede.run.checkpoint import CheckpointError, CheckpointWriteError
from ede.run.embedded import EmbeddedActions
from ede.run.group import compiler_missing, env_workers
from ede.run.runs import RUN_KIND
from ede.run.sb3 import train_sb3
from ede.run.spec import RunSpec
from ede.run.training import Diverged, train_group
from ede.tasks import action_bounds, make
from ede_pipeline import layout
from ede_pipeline.common import (
    USABLE_SHARE,
    BadInput,
    Failed,
    available_memory,
    check_outputs,
    embedding_options,
    holding,
    in_units,
    params_option,
)
from ede_pipeline.progress import progress


@click.command()
@click.option("--task", required=True, help="A task of params.yaml's runs.tasks.")
@click.option(
    "--algo", required=True, help=f"One of {', '.join(ALGOS)} (params.yaml's runs.algos)."
)
@click.option(
    "--seed",
    "--seeds",
    "seeds",
    required=True,
    help="The run's seed (0 to 2**32 - 1), or several (0,1,2,3 or 0-3): the runs of one task and "
    "algorithm trained in one process, their updates batched (stable-baselines3's: one after "
    "another), each with the outputs it gets alone.",
)
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    help="Run directory; with several seeds, a pattern with {seed}  "
    "[default: data/runs/<task>/<algo>/seed<N>]",
)
@embedding_options
@click.option(
    "--keep-checkpoint",
    is_flag=True,
    help="Keep the checkpoint (replay buffer included) once the run is complete.",
)
@click.option(
    "--bad-checkpoint",
    type=click.Choice(["restart", "refuse"]),
    default="restart",
    show_default=True,
    help="A checkpoint that is damaged or another run's: move it aside to "
    "checkpoint.bad-<time> and start over, or refuse (exit 2) and touch nothing.",
)
@params_option
def train(
    params: Params,
    task: str,
    algo: str,
    seeds: str,
    out: Path | None,
    encoder: Path | None,
    decoder: Path | None,
    keep_checkpoint: bool,
    bad_checkpoint: str,
) -> None:
    """Stage 4: train one run, or the runs of several seeds in one process; each resumes from
    its checkpoint if one of the same run exists."""
    if algo not in ALGOS:
        raise BadInput(f"--algo {algo!r}: unknown; expected one of {', '.join(ALGOS)}")
    seed_list = parse_seeds(seeds)
    outs = run_dirs(task, algo, seed_list, out)
    if task not in params.runs.tasks:
        raise BadInput(
            f"--task {task!r}: not in params.yaml's runs.tasks ({', '.join(params.runs.all_tasks)})"
        )
    config = params.td3
    try:  # stable-baselines3's agents train on the CPU, one seed after another
        device = pick_device("cpu" if algo in SB3_ALGOS else config.device)
    except ValueError as error:
        raise BadInput(str(error)) from None
    if config.compile in ("default", "reduce-overhead") and algo not in SB3_ALGOS:
        if missing := compiler_missing(device):
            raise BadInput(
                f"td3.compile: {config.compile} needs {missing}, which this machine lacks; set "
                "td3.compile to auto (compiled where it can be) or none"
            )
    together = 1 if algo in SB3_ALGOS else len(seed_list)
    check_group_memory(params, task, algo, seeds, together, device)
    embedding: ActionEmbedding | None = None
    embedding_id, inputs = "", tuple[Path, ...]()
    if algo in EMBEDDED_ALGOS:
        embedding, embedding_id, inputs = family_embedding(
            params, task, algo, encoder, decoder, device
        )
    torch.set_num_threads(config.threads)
    budget = params.runs.budgets[task]
    specs = [
        RunSpec(task, algo, seed, budget, config, params.ede_td3, embedding_id)
        for seed in seed_list
    ]
    notice = functools.partial(click.echo, err=True)
    label = f"{algo} {task} seed{'s' if len(seed_list) > 1 else ''} {seeds}"
    for run_dir in outs:  # every run's, before the first lock is taken
        check_outputs((run_dir, RUN_KIND), inputs=inputs)
    try:
        with ExitStack() as locks:
            for run_dir in outs:
                locks.enter_context(holding((run_dir, RUN_KIND), inputs=inputs))
            with progress(budget * len(specs), label, resumable=True) as advance:
                if algo in SB3_ALGOS:
                    results = [
                        train_sb3(spec, run_dir, embedding, advance, keep_checkpoint,
                                  bad_checkpoint, notice)
                        for spec, run_dir in zip(specs, outs, strict=True)
                    ]  # fmt: skip
                else:
                    results = train_group(
                        specs, outs, embedding, device, advance, keep_checkpoint, bad_checkpoint,
                        notice,
                    )  # fmt: skip
    except CheckpointError as error:
        raise BadInput(f"{error} (--bad-checkpoint refuse)") from None
    except CheckpointWriteError as error:
        raise click.ClickException(str(error)) from None
    except Diverged as error:
        raise Failed(str(error)) from None
    for run_dir, metrics in zip(outs, results, strict=True):
        click.echo(
            f"{run_dir}: final return {metrics['final_return']:.2f}, best "
            f"{metrics['best_return']:.2f}, {metrics['steps_per_second'] or 0:.0f} steps/s"
        )


def family_embedding(
    params: Params,
    task: str,
    algo: str,
    encoder: Path | None,
    decoder: Path | None,
    device: torch.device,
) -> tuple[ActionEmbedding, str, tuple[Path, ...]]:
    """The embedding ``algo`` acts in on ``task`` (its family's, or ``--encoder``/``--decoder``),
    checked against the task's family, the params and the task's action space; its checksum and
    its two folders (the run's inputs). Raises :class:`BadInput`, one line, where it cannot be."""
    family = params.runs.tasks[task]
    folder = layout.embedding(family)
    encoder, decoder = encoder or folder / "encoder", decoder or folder / "decoder"
    try:
        meta, embedding = load_action_embedding(encoder, decoder, device)
    except ArtifactError as error:
        raise BadInput(
            f"{error} ({ALGO_LABELS[algo]} on {task} needs the {family} family's embedding)"
        ) from None
    if meta.family != family:
        raise BadInput(
            f"{decoder}: the embedding of family {meta.family}, but {task} is in family {family}"
        )
    mismatches = params_mismatches(decoder, meta, params.embedding, params.decoder)
    if mismatches:
        raise BadInput("\n".join(mismatches))
    try:  # a decoder of another action space than the task's: one line naming both
        EmbeddedActions(make(task), embedding).close()
    except ArtifactError as error:
        raise BadInput(str(error).replace("the embedding", str(decoder), 1)) from None
    return embedding, meta.identity, (encoder, decoder)


MAX_GROUP = 4096  # seeds in one process: far more than a machine trains at once


def parse_seeds(text: str) -> list[int]:
    """``3``, ``0,1,2,3`` or ``0-3`` as a list of distinct seeds (:data:`ede.config.SEED_RANGE`),
    at most :data:`MAX_GROUP` of them."""
    try:
        if "-" in text.strip("-") and "," not in text:
            first, last = (int(part) for part in text.split("-"))
            ends = [first, last]
        else:
            ends = [int(part) for part in text.split(",")]
    except ValueError:
        raise BadInput(
            f"--seed {text!r}: expected a seed, a list (0,1,2) or a range (0-3)"
        ) from None
    if not all(map(is_seed, ends)):  # before a range is built: its ends may be anything
        raise BadInput(f"--seed {text}: expected distinct seeds {SEED_RANGE}")
    seeds = list(range(ends[0], ends[1] + 1)) if "-" in text else ends
    if not seeds or len(set(seeds)) != len(seeds):
        raise BadInput(
            f"--seed {text}: expected distinct seeds {SEED_RANGE}, a range's first "
            "no greater than its last"
        )
    if len(seeds) > MAX_GROUP:
        raise BadInput(
            f"--seed {text}: {len(seeds)} seeds; expected at most {MAX_GROUP} in one process"
        )
    return seeds


# float32 copies a group keeps of each network: weights, target, gradient and Adam's two moments
# (ede.method.ensemble.Adam: its fused step works in place).
NETWORK_COPIES = 5

# float32 values an update keeps per row of its batch and per unit of a network (the inputs,
# hidden and output widths of the actor and both critics): a forward's activations and their
# gradients. Measured (2026-12-07, CPU, hidden [400, 300], 4 members, batch 100 and 4,000, as
# tests/pipeline/test_train.py does): the tensors' peak grows by 2,600 floats a member's row,
# against 4,282 counted here; glibc's heap, which keeps some of what an update frees, made the
# peak resident size grow by 3,100 to 5,300 from run to run (USABLE_SHARE leaves room for it).
ACTIVATION_COPIES = 2

# Host memory each environment of a member holds (a member has two: training and evaluation,
# ede.run.group.Group): in this process, a MuJoCo model and its data, 0.6 to 0.9 MiB measured for
# ede/Point-v0, ede/Pusher-v0 and ede/Striker-v0; or, with td3.env_workers (AsyncVectorEnv), a
# worker process of its own that imports ede's tasks, gymnasium and MuJoCo, not torch
# (ede.run.vector imports none of the method): 35 to 39 MiB unique to it (USS; 70 MiB RSS, the
# rest shared with its forkserver) for each of the three, measured 2026-12-07 (164 MiB while the
# vector environments' module imported the checkpoint's, and so torch).
ENVS_PER_MEMBER = 2
ENV_BYTES = 2**20
WORKER_BYTES = 60 * 2**20

# A group may fill USABLE_SHARE of the free memory by group_memory's count: the rest is for what
# it leaves out. (A group estimated at 21.1 GiB, 201 TD3 runs of ede/ReacherVertical-v0 with 10^6
# steps of replay each, was killed for memory where 21.2 GiB were available.) Measured whole
# (2026-12-07, `train` of TD3 on ede/Point-v0, hidden [64, 64], batch 64, 2,000 steps, no
# workers): a peak RSS of 305 MiB for one seed and 322 MiB for eight, 2.4 MiB a member beyond the
# first against the 2.7 MiB counted; the first's 300 MiB are Python, torch and MuJoCo.


def group_memory(
    members: int,
    capacity: int,
    obs_size: int,
    code_size: int,
    networks: Sequence[Sequence[int]],
    batch_size: int = 0,
) -> int:
    """The bytes a group of ``members`` runs holds in its tensors while it trains, at least.

    Counts the replay buffer, ``capacity`` steps of each member as :class:`ede.method.replay.ReplayBuffer`
    stores them (two float32 observations of ``obs_size``, a float32 code of ``code_size``, an
    int64 plan step, a float32 reward, two bool flags), each member's ``networks``, given by
    their layer widths (a twin critic given twice), :data:`NETWORK_COPIES` times in float32, and
    an update's activations of ``batch_size`` rows through them (:data:`ACTIVATION_COPIES`).
    Not counted: the environments (:func:`environment_memory`), the embedding (one for the
    group, a few MB) and torch itself.
    """
    step = 4 * (2 * obs_size + code_size + 1) + 8 + 2
    weights = sum((n_in + 1) * n_out for widths in networks for n_in, n_out in pairwise(widths))
    units = sum(sum(widths) for widths in networks)
    activations = ACTIVATION_COPIES * 4 * batch_size * units
    return members * (capacity * step + NETWORK_COPIES * 4 * weights + activations)


def environment_memory(members: int, workers: bool) -> int:
    """The host's bytes a group's environments hold: :data:`ENVS_PER_MEMBER` a member, each in
    this process or, with ``workers``, in a worker process of its own."""
    return members * ENVS_PER_MEMBER * (WORKER_BYTES if workers else ENV_BYTES)


def check_group_memory(
    params: Params, task: str, algo: str, seeds: str, members: int, device: torch.device
) -> None:
    """Refuse a group whose memory is more than :data:`USABLE_SHARE` of the memory free where
    it goes, before any work: its tensors (:func:`group_memory`) where they go (the GPU's, or
    the host's available memory), its environments (:func:`environment_memory`) on the host.

    Raises:
        BadInput: naming the seeds, the estimate, what is free and how many seeds would fit.
    """
    env = make(task)  # its spaces size a step and the networks
    obs_size = int(np.prod(env.observation_space.shape or ()))
    action_size = action_bounds(env)[0].size
    env.close()
    td3 = params.td3
    if algo not in EMBEDDED_ALGOS:
        code_size, k, plan_step = action_size, 1, "onehot"
    else:
        code_size = params.embedding.dim or action_size
        k, plan_step = params.embedding.k, params.ede_td3.plan_step_input
    actor = [obs_size, *td3.hidden, code_size]
    critic = Critic(obs_size, code_size, k, td3.hidden, plan_step, td3.critic_action_repeat).sizes
    capacity = min(td3.buffer_size, params.runs.budgets[task])  # as ede.run.group sizes it
    workers = env_workers(td3.env_workers, members, device)  # as ede.run.group chooses
    tensors = group_memory(
        1, capacity, obs_size, code_size, [actor, critic, critic], td3.batch_size
    )
    hosted = environment_memory(1, workers)
    everything = "replay buffers, networks, activations and environments"
    if device.type == "cuda":  # the tensors on the GPU, the environments on the host
        places = [
            (tensors, "replay buffers, networks and activations", device),
            (hosted, "environments", torch.device("cpu")),
        ]
    else:
        places = [(tensors + hosted, everything, device)]
    for one, what, where in places:
        free, there = free_memory(where)
        need, usable = members * one, int(USABLE_SHARE * free)
        if need <= usable:
            continue
        fits = usable // one
        if fits:
            advice = f"train at most {fits} seed{'s' if fits > 1 else ''} per process"
        elif workers and what == "environments":
            advice = "not one run fits: set td3.env_workers to no"
        else:
            advice = "not one run fits: lower td3.buffer_size or the task's budget"
        raise BadInput(
            f"--seed {seeds}: {algo} on {task} for {members} seed{'s' if members > 1 else ''} "
            f"in one process needs about {in_units(need)} ({what}), more than "
            f"{USABLE_SHARE:.0%} of the {in_units(free)} {there}; {advice}"
        )


def free_memory(device: torch.device) -> tuple[int, str]:
    """The bytes free where a group's tensors go, and where that is, in words: the GPU's free
    memory, or the host's available memory (what it can use without swapping)."""
    if device.type == "cuda":
        return torch.cuda.mem_get_info(device)[0], f"free on {device}"
    return available_memory(), "of memory available"


def run_dirs(task: str, algo: str, seeds: list[int], out: Path | None) -> list[Path]:
    """Each seed's run directory: ``--out`` (a pattern with ``{seed}`` for several) or the
    layout's."""
    if out is None:
        return [layout.run(task, algo, seed) for seed in seeds]
    if len(seeds) == 1:
        return [out]
    if "{seed}" not in str(out):
        raise BadInput(
            f"--out {out}: several seeds need a pattern with {{seed}}, e.g. runs/seed{{seed}}"
        )
    return [Path(str(out).replace("{seed}", str(seed))) for seed in seeds]
