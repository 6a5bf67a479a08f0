"""The results pages' clips: per task of a runs folder whose policies are published (``ede-pipeline
experiment export --policies``), TD3 beside EDE-TD3 of one seed, one episode each from the same
start, as a GIF and the section a page's block takes by the heading ``Clip: <task>``.

The GIF goes where the folder's figures go, the folder above it (``docs/results/clips/`` →
``docs/results/clip-ede_ReacherPush-v0.gif``), and the section links it from there: the pages
that name the folder lie there too.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ede.analysis.policy import PolicyRejected, policy_of, trained_embedding
from ede.analysis.video import NoOffscreenGL, fps_of, side_by_side
from ede.config import ALGO_LABELS, PAPER_ALGOS, Params
from ede.io.atomic import NotWritten
from ede.run.runs import POLICY
from ede_pipeline import layout
from ede_pipeline.common import BadInput, Failed
from ede_pipeline.published import Source, published_runs, read_source, task_folders
from ede_pipeline.results.sections import Section

CLIP = "Clip: "  # a clip's heading: CLIP + its task


class Clip(NamedTuple):
    """One task's clip: its section, and the GIF it links, to be written."""

    section: Section
    gif: Path
    frames: list[np.ndarray]
    fps: float


@contextmanager
def refused() -> Iterator[None]:
    """The video library's refusals as the command's: a policy it cannot play is bad input (one
    line, exit 2); no offscreen GL, or a clip the disk cannot hold, one line, exit 1."""
    try:
        yield
    except PolicyRejected as error:
        raise BadInput(str(error)) from None
    except NoOffscreenGL as error:
        raise Failed(str(error)) from None
    except NotWritten as error:
        raise Failed(error.strerror or str(error)) from None


def clip_name(task: str) -> str:
    return f"clip-{task.replace('/', '_')}.gif"


def clips(runs: Path, params: Params, tasks: set[str]) -> list[Clip]:
    """Each of ``tasks`` (the clips the pages show) under ``runs`` with a seed whose TD3 and
    EDE-TD3 policies are both kept: the clip of its lowest such seed, the episode its final
    evaluation played first."""
    os.environ.setdefault("MUJOCO_GL", "egl")  # read as the first environment renders
    made = []
    for task in (task for task in task_folders(runs) if task in tasks):
        kept: dict[int, dict[str, Path]] = {}
        finals = {}  # each run's final evaluation's mean return, by (algorithm, seed)
        for run, record in published_runs(runs, task):
            algo, seed = record.made["algo"], record.curve.seed
            finals[(algo, seed)] = float(record.curve.returns[-1])
            if (run / POLICY).is_dir():
                kept.setdefault(seed, {})[algo] = run
        seeds = sorted(seed for seed, algos in kept.items() if set(PAPER_ALGOS) <= set(algos))
        if not seeds:
            continue
        seed = seeds[0]
        pair = [kept[seed][algo] for algo in PAPER_ALGOS]
        meta, _ = policy_of(kept[seed]["ede-td3"])
        embedding = trained_embedding(meta, *layout.run_embedding(pair[1], meta, params))
        played, returns = side_by_side(pair, (embedding, meta["embedding"]))
        frames = list(played)  # one episode each (the returns are known once it is played)
        gif = runs.parent / clip_name(task)
        folder = layout.task_runs(task, Path(runs.name)).as_posix()  # from a page in runs.parent
        source = read_source(layout.task_runs(task, runs))  # the part that made this seed's runs
        made_by = Source([part for part in source.parts if seed in part.seeds] or source.parts)
        labels = [ALGO_LABELS[algo] for algo in PAPER_ALGOS]
        text = (
            f"### {CLIP}{task}\n\n"
            f"![{task}: {labels[0]} (left) beside {labels[1]} (right), seed {seed}]"
            f"({clip_name(task)})\n\n"
            f"Seed {seed}'s final policies, each playing the first episode of its run's final "
            "evaluation; an orange bar marks each step where EDE-TD3 chooses a code. This "
            f"episode's return: {returns[0]:.1f} ({labels[0]}) and {returns[1]:.1f} "
            f"({labels[1]}); the final evaluation's mean: "
            f"{finals[(PAPER_ALGOS[0], seed)]:.1f} and {finals[(PAPER_ALGOS[1], seed)]:.1f}. Made by "
            f"{made_by.made_at()}; [`{folder}`]({folder}) "
            "holds the runs and their policies.\n"
        )
        made.append(Clip(Section(CLIP + task, text), gif, frames, fps_of(task)))
    return made
