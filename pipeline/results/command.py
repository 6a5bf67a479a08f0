"""``ede-pipeline results``: the command (what it prints and draws: :mod:`ede_pipeline.results`)."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import NamedTuple

import click
import gymnasium
from matplotlib.figure import Figure

from ede.analysis.figures import learning_curves, performance_profile
from ede.analysis.probes import (
    ZERO_EPISODES,
    random_policy_return,
    zero_action_return,
)
from ede.analysis.results import RANDOM_EPISODES, across_tasks
from ede.analysis.stats import Band
from ede.analysis.video import VIDEO_KIND, write_video
from ede.config import PAPER_ALGOS, Params
from ede.io.atomic import write_text, writing_files
from ede.run.runs import Curve
from ede_pipeline import layout
from ede_pipeline.common import BadInput, hold, hold_outputs, params_option
from ede_pipeline.published import TaskRuns, read_ablations, read_runs
from ede_pipeline.results.clips import CLIP, clips, refused
from ede_pipeline.results.pages import fill_pages, read_pages
from ede_pipeline.results.sections import (
    Glance,
    Section,
    ablation_sections,
    across_section,
    at_a_glance,
    complete_tasks,
    task_section,
)

FIGURE_KIND = "results figure"  # what a figure's mark says drew it (ede.io.atomic.writing_files)


def references(tasks: list[str], params) -> dict[str, tuple[float, float, float]]:
    """Each task's reference returns: uniform random actions' (the low end of its normalised
    scores) and zero actions' with its standard error (ZERO_EPISODES episodes)."""
    found = {}
    for task in tasks:
        try:
            found[task] = (
                random_policy_return(task, RANDOM_EPISODES, params.report.seed),
                *zero_action_return(task, ZERO_EPISODES, params.report.seed),
            )
        except (gymnasium.error.Error, ValueError) as error:
            raise BadInput(
                f"{task}: cannot be made to measure its reference returns: {error}"
            ) from None
    return found


class Drawn(NamedTuple):
    """What the results of one runs folder are: its sections in order, and its figures by name."""

    sections: list[Section]
    figures: dict[str, Figure]

    def figure(self, name: str, made: Figure, figures: Path) -> None:
        """``made`` as figure ``name``, and a line where it stands saying where it goes (the
        folder ``figures``)."""
        self.figures[name] = made
        self.sections.append(Section(None, f"Figure: {figures / f'{name}.png'}\n"))


Curves = dict[tuple[str, str], list[Curve]]  # each (task, algorithm)'s runs


def draw(params: Params, runs: Path, bins: int, ablations: Path, figures: Path) -> Drawn:
    """Read and check the runs in ``runs`` (and the fidelity ablations in ``ablations``, where
    there are) and make every section and figure of their results: per family its tasks and its
    figure; the aggregates across tasks and the performance profile; the tasks at a glance; per
    ablation its sections and, run with several algorithms, its figure (``figures`` is where the
    sections say the figures go). Nothing is written."""
    families = read_runs(runs, params)
    found_ablations = read_ablations(ablations, runs) if ablations.is_dir() else []
    curves_of = {
        family: {(f.task, a): c for f in found for a, c in f.curves.items()}
        for family, found in families.items()
    }
    refs = references([f.task for found in families.values() for f in found], params)
    planned = {f.task: f.source.seeds for found in families.values() for f in found}
    drawn = Drawn([], {})
    glance = _families(drawn, families, curves_of, refs, bins, params, figures)
    _across_tasks(drawn, curves_of, refs, planned, params)
    if glance:
        drawn.sections.append(at_a_glance(glance, params.report.confidence))
    _ablations(drawn, found_ablations, bins, params, figures)
    return drawn


def _families(
    drawn: Drawn,
    families: dict[str, list[TaskRuns]],
    curves_of: dict[str, Curves],
    refs: dict[str, tuple[float, float, float]],
    bins: int,
    params: Params,
    figures: Path,
) -> list[Glance]:
    """Per family, each task's section and the family's figure, added to ``drawn``; the rows at
    a glance of its tasks with runs of both algorithms of a pair
    (:data:`ede.analysis.results.PAIRS`)."""
    glance = []
    for family, found in families.items():
        source = params.families[family].source if family in params.families else found[0].task
        bands: dict[tuple[str, str], Band] = {}
        for task_runs in found:
            section, task_bands, rows = task_section(
                task_runs,
                family,
                source,
                params.runs.budgets.get(task_runs.task),
                bins,
                refs[task_runs.task],
                params,
            )
            drawn.sections.append(section)
            glance += rows
            bands.update({(task_runs.task, a): band for a, band in task_bands.items()})
        made = learning_curves(
            family,
            [f.task for f in found],
            bands,
            {key: len(runs) for key, runs in curves_of[family].items()},
            params.report.confidence,
            {f.task: f.budget / bins for f in found},
        )
        drawn.figure(family, made, figures)
    return glance


def _aggregated(curves_of: dict[str, Curves], params: Params) -> list[tuple[str, Curves]]:
    """The sets of runs aggregated across tasks, each with its title: each family's; the
    paper's tasks, where other families' are beside them; the transfer tasks; every task, where
    there is more than one family."""
    everything = {key: c for curves in curves_of.values() for key, c in curves.items()}
    sets = [(f"the {family} family", curves) for family, curves in curves_of.items()]
    paper = [family for family in curves_of if family in params.families]
    if len(curves_of) > len(paper) > 1:  # and the tasks beyond, in "every task"
        sets.append(("the paper's tasks", {k: c for f in paper for k, c in curves_of[f].items()}))
    # The transfer claim's own aggregate: the tasks an embedding learned elsewhere acts in.
    targets = {t for f in paper for t in params.families[f].targets}
    transfer = {k: c for f in paper for k, c in curves_of[f].items() if k[0] in targets}
    if len({task for task, _ in transfer}) > 1:
        sets.append(("the transfer tasks", transfer))
    return sets + [("every task", everything)] * (len(curves_of) > 1)


def _across_tasks(
    drawn: Drawn,
    curves_of: dict[str, Curves],
    refs: dict[str, tuple[float, float, float]],
    planned: dict[str, list[int]],
    params: Params,
) -> None:
    """Each set's aggregates across tasks (:func:`_aggregated`: of its tasks with every planned
    run of both algorithms finished) and the performance profile of every task's, added to
    ``drawn``."""
    report = params.report
    both = {
        task
        for curves in curves_of.values()
        for (task, _) in curves
        if all((task, a) in curves for a in PAPER_ALGOS)
    }
    lows = {task: refs[task][0] for task in both}
    for title, curves in _aggregated(curves_of, params):
        tasks, waiting = complete_tasks(curves, both, planned)
        aggregates = across_tasks(
            curves,
            {t: lows[t] for t in tasks},
            report.confidence,
            report.bootstrap_samples,
            report.seed,
        )
        if aggregates is not None:
            drawn.sections.append(across_section(title, aggregates, params, waiting))
            if title == "every task" or len(curves_of) == 1:
                profile = aggregates.profile
                drawn.figures["performance-profile"] = performance_profile(
                    profile, len(aggregates.tasks), aggregates.runs
                )


def _ablations(
    drawn: Drawn,
    found: list[tuple[str, TaskRuns, TaskRuns]],
    bins: int,
    params: Params,
    figures: Path,
) -> None:
    """Per fidelity ablation its sections, and the figure of each variant run with several
    algorithms, added to ``drawn``."""
    kept: dict[str, list[tuple[TaskRuns, dict[str, Band]]]] = {}
    for variant, ours, theirs in found:
        sections, variant_bands = ablation_sections(variant, ours, theirs, bins, params)
        drawn.sections.extend(sections)
        if len(ours.curves) > 1:  # several algorithms: drawn as a family is
            kept.setdefault(variant, []).append((ours, variant_bands))
    for variant, variant_runs in kept.items():
        made = learning_curves(
            variant,
            [k.task for k, _ in variant_runs],
            {(k.task, a): band for k, bands in variant_runs for a, band in bands.items()},
            {(k.task, a): len(c) for k, _ in variant_runs for a, c in k.curves.items()},
            params.report.confidence,
            {k.task: k.budget / bins for k, _ in variant_runs},
            title=f"the {variant} variant (a fidelity ablation)",
        )
        drawn.figure(f"ablation-{variant}", made, figures)


def save_figures(figures: Path, drawn: dict[str, Figure]) -> None:
    """Each figure to ``<figures>/<name>.png``, marked as this command's."""
    for name, made in drawn.items():
        figures.mkdir(parents=True, exist_ok=True)
        with writing_files([(figures / f"{name}.png", FIGURE_KIND)]):
            made.savefig(figures / f"{name}.png", dpi=120)


def check_figures(figures: Path, names: Iterable[str], inputs: tuple[Path, ...]) -> None:
    """Each figure a new file or one this command drew, before any is drawn; held until the
    command ends."""
    hold_outputs(
        (None, FIGURE_KIND),
        files=tuple((figures / f"{name}.png", FIGURE_KIND) for name in names),
        inputs=inputs,
    )


# The most bins a run's budget is cut into: each bin is bootstrapped, so time grows with them, and
# a bin averages the evaluations in it: a run of our longest budgets (10^6 steps, an evaluation
# every 1,000) holds 1,000, so more bins than that would leave some empty.
MAX_BINS = 1_000


@click.command()
@click.option(
    "--runs",
    type=click.Path(file_okay=False, path_type=Path),
    help="The published runs: a folder per task, as `ede-pipeline experiment export` writes them  "
    f"[default: {layout.RESULTS_RUNS}]",
)
@click.option(
    "--figures",
    type=click.Path(file_okay=False, path_type=Path),
    help=f"Where the figures go  [default: {layout.RESULTS}]",
)
@click.option(
    "--bins",
    type=click.IntRange(min=1, max=MAX_BINS),
    default=20,
    show_default=True,
    help="Bins per run's budget.",
)
@click.option(
    "--ablations",
    type=click.Path(file_okay=False, path_type=Path),
    help="One folder per variant, each compared with the default's runs in --runs  "
    "[default: 'ablations' beside --runs]",
)
@click.option(
    "--pages",
    type=click.Path(exists=True, path_type=Path),
    multiple=True,
    help="Markdown pages (or folders of them) whose marked blocks to fill with the sections they "
    "name, from the runs folder each names, instead of printing; each runs folder's figures, "
    "and its clips where its policies are published (`Clip: <task>` blocks), go to the folder "
    "above it. Repeatable.",
)
@params_option
def results(
    params: Params,
    runs: Path | None,
    figures: Path | None,
    bins: int,
    ablations: Path | None,
    pages: tuple[Path, ...],
) -> None:
    """Print docs/results.md's tables (Markdown) and draw its figures from the published runs, or
    fill the results pages' generated blocks with them (--pages).

    Per task: budget, seeds, experiment and commits, the CPUs of its runs, reference returns,
    final return, area and steps to each threshold with bootstrap intervals, EDE-TD3's lead over
    each other algorithm per bin and overall, the probability of improvement, and which seeds
    declined and diverged;
    per family, its figure and the aggregates across tasks; the tasks at a glance; per fidelity
    ablation, its runs against the default's. Every statistic is the report's (params' `report`).
    Bad input is one line, exit 2, before anything is written.
    """
    if pages:
        if runs or figures or ablations:
            raise BadInput(
                "--pages: its blocks name their runs folders; leave out --runs, --figures and "
                "--ablations"
            )
        found = read_pages(pages)
        folders = list(dict.fromkeys(block.runs for block in found.blocks))
        named = {(b.runs, b.heading.startswith(CLIP)) for b in found.blocks}
        made = {
            folder: draw(params, folder, bins, folder.parent / "ablations", folder.parent)
            for folder in folders
            if (folder, False) in named
        }
        shown: dict[Path, set[str]] = {}  # the clips the pages show; the others' GIFs stay
        for block in found.blocks:
            if block.heading.startswith(CLIP):
                shown.setdefault(block.runs, set()).add(block.heading.removeprefix(CLIP))
        with refused():
            played = {folder: clips(folder, params, tasks) for folder, tasks in shown.items()}
        for folder, drawn in made.items():
            check_figures(folder.parent, drawn.figures, (folder,))
        for folder, each in played.items():
            for clip in each:
                hold_outputs((None, VIDEO_KIND), files=((clip.gif, VIDEO_KIND),), inputs=(folder,))
        sections = {
            folder: [
                *(made[folder].sections if folder in made else []),
                *(clip.section for clip in played.get(folder, [])),
            ]
            for folder in folders
        }
        filled = fill_pages(found, sections)
        hold(*filled)  # one writer per page, as per figure
        for folder, drawn in made.items():  # figures and clips first: a page filled is complete
            save_figures(folder.parent, drawn.figures)
        for clip in (clip for each in played.values() for clip in each):
            with refused():
                write_video(clip.gif, clip.frames, clip.fps)
        for page, text in filled.items():
            write_text(page, text)
            click.echo(f"Filled: {page}")
        return
    runs = runs or layout.RESULTS_RUNS
    figures = figures or layout.RESULTS
    ablations = ablations or runs.parent / "ablations"
    drawn = draw(params, runs, bins, ablations, figures)
    check_figures(figures, drawn.figures, (runs, ablations))
    # Every input is read and checked: from here on, print and draw.
    for section in drawn.sections:
        click.echo(section.text)
    save_figures(figures, drawn.figures)
