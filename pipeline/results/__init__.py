"""``ede-pipeline results``: the measured results of docs/results.md and its pages, redrawn from
the per-run files committed beside them.

    ede-pipeline results [--runs docs/results/runs] [--figures docs/results] [--bins 20]
                         [--ablations docs/results/ablations] [--params params.yaml]
    ede-pipeline results --pages docs/results.md --pages docs/results [--bins 20] [--params ...]

The package's parts: :mod:`.sections` renders each section in Markdown, :mod:`.pages` fills the
pages' blocks with them, :mod:`.command` reads the runs, draws the figures and writes. With
``--pages``, each block of a page names a runs folder (relative to the page) and a section's
heading, and the command fills it with that section instead of printing (:mod:`.pages`); each runs
folder's fidelity ablations are ``ablations/`` beside it, and its figures go to the folder above it.

``--runs`` holds one folder per finished run, ``<task>/<algorithm>/seed<N>/`` with its
``eval.csv``, ``run.json`` and ``metrics.json`` (as ``ede-pipeline train`` writes them), laid out as
the pipeline's runs (:func:`ede_pipeline.layout.run`: the task by its full id, so
``ede/ReacherTurn-v0``'s runs are in ``ede/ReacherTurn-v0/``), and in each task's folder a
``source.json`` naming what made its runs (one JSON object, or a list of them, one per experiment,
where its seeds came from several): the commit (``"commit"``, a string, or a list where its
runs were made at several) and the experiment file (``"experiment": "experiments/NAME.yaml"``,
as ``ede-pipeline experiment export`` writes it) or, in files written before experiments were
files, the command (``"command"``); and, optionally, the returns whose first crossing to report
(``"thresholds": [500, 1000]``) and the seeds it runs (``"seeds": [0, 1, 2, 3]``). A task's folder is any folder there holding
a ``source.json`` and runs; its path must be the task its runs name. The tasks are those of the
committed ``params.yaml``'s families, then every other task with a folder there, each its own
family named after it (as an experiment file runs a task ``params.yaml`` does not
train on; never one of ``params.yaml``'s families, whose name it then takes whole). For each
family with runs, this draws its figure (``<figures>/<family>.png``: each task's mean return over
seeds with its bootstrap band, evaluations averaged in ``--bins`` bins of a run's budget, as the
report draws them) and prints, per task, in Markdown:

- the budget a run, as a fraction of the paper's (``runs.budgets``; none beyond the paper), the
  seeds, the experiment file where ``source.json`` names one and the commits (7 characters), per
  part where there are several, and the held-out figures of each embedding the EDE-TD3 runs used
  (``<task>/embedding/<checksum>/``, :func:`ede_pipeline.layout.published_embedding`);
- the CPUs that made its runs (each one's model and instruction sets, as its ``run.json``'s
  ``machine`` records them, and how many runs it made; "CPU unrecorded" for runs made before);
- two reference returns: uniform random actions' (the normalised scores' 0, as the report's) and
  zero actions' over ``ZERO_EPISODES`` episodes with its standard error (doing nothing: on a task
  that penalises actions, a policy must beat it to have learned what the task rewards);
- final return, area under the curve and the steps to reach each threshold per algorithm (the
  paper's TD3 and EDE-TD3, and each of stable-baselines3's agents with runs there), with
  bootstrap intervals over seeds;
- EDE-TD3 against each other algorithm there, TD3 first: its lead (EDE-TD3's mean minus the
  other's) with its bootstrap interval, the bins where that lies above 0 and below 0, and overall
  on the final return and the area (with two seeds or more of each), and rliable's probability that
  an EDE-TD3 run beats one of the other's, over all the task's seeds, on the final return and on
  the area;
- then the same of each other algorithm in the EDE space against the same learner on raw actions,
  where both have runs there (:data:`ede.config.RAW_COUNTERPART`: SB3's TD3 against TD3, SB3's
  SAC against SB3's SAC): does the space help it as it helps TD3;
- each algorithm's mean over seeds of a seed's last quarter of evaluations, with its bootstrap
  interval (the asymptote, as far as the budget shows it);
- per seed, whether it declined and whether it diverged (:func:`ede.analysis.stats.divergence`:
  its last quarter's mean below its best as long window before by more than a plateau with the
  run's own noise, as correlated as its evaluations are, falls in 95% of simulated runs; and by
  more than half of what it had gained, where that gain is more than noise);

and, per family, over the paper's tasks (where they span two families and there are tasks beyond
them), over the transfer tasks (the families' targets, where there are two or more: the
transfer claim's own aggregate) and over every task with runs of TD3 and EDE-TD3, the report's
aggregates across tasks (rliable: the probability that
EDE-TD3 beats TD3 and each one's interquartile mean of normalised scores, over final returns and
areas, with stratified bootstrap intervals), drawing the performance profile of all of them to
``<figures>/performance-profile.png``. A task with a seed of its ``source.json`` not yet
finished by an algorithm (an experiment still running) waits, named, rather than cutting every
task's seeds to its count; tasks run with more seeds than others (ReacherVertical's 8) give the
aggregates each task's lowest seeds, as many as the fewest, and the rest are named. The tasks at
a glance: a table per pair set against each other (EDE-TD3 against TD3 first, then EDE-TD3
against each other algorithm, then each in the EDE space against its raw counterpart), naming the
tasks without runs of one of its pair, by what they lack.

``--ablations`` holds the fidelity ablations' runs the same way, one folder per variant
(``<variant>/<task>/<algorithm>/seed<N>/``, ``source.json`` per task, and where kept the variant's
embedding metrics in ``<task>/embedding/<checksum>/``): each is printed, with its experiment file or command,
against the default's runs of the same task, algorithm and seeds in ``--runs``, with the variant's lead over the default per bin and overall; a
variant run with several algorithms is drawn as a family is, to ``<figures>/ablation-<variant>.png``.

The confidence, the bootstrap's resamples and its seed are the report's (``report`` in
``params.yaml``), and every statistic's bootstrap (an interval, a band of the figure) starts afresh
from that seed, so a number depends on its own runs alone: the same on every machine, whatever
other tasks, algorithms or thresholds are beside it. Bad input (a run, ``source.json``, an
embedding's metrics, a task's folder not at its task's path, an ablation without its default) is
one line and exit code 2 (:class:`ede_pipeline.common.BadInput`), before anything is written. A
run is bad where its folder is not named ``seed<N>`` (a copy ``seed00`` beside ``seed0`` would
count seed 0 twice), its ``run.json`` names another task, algorithm or seed than its folder, a
file of it is not the one its ``run.json`` records the SHA-256 of (a ``run.json`` that records
none is one of the runs published before checksums, :mod:`ede.run.early_runs`, byte for byte), its
seed is not one ``source.json`` names, its files are another run's (a copy under another folder,
task or variant, whatever its ``run.json`` says; :func:`ede.run.runs.same_files`), or it was made with
other params than its task's other runs (those of both algorithms, and of EDE-TD3's between its
runs; :func:`ede.run.spec.unshared_params`).
"""
