"""``ede-pipeline experiment``: the committed experiments, run by the sweep and recorded by DVC.

An experiment is a committed file, ``experiments/NAME.yaml``: the params sections with only the
keys it changes against ``params.yaml`` (``experiments/quick.yaml``, which ``make quick`` runs, among them), each key replacing its value
whole. ``experiment run NAME`` runs it in a working copy of its own,
``.dvc/tmp/experiments/NAME/`` (a git worktree sharing this checkout's DVC cache): this
checkout's files (the code that runs, committed or not), the experiment's params (its file
applied to the ``params.yaml`` of this checkout's commit: the workspace's, where an edit or
``dvc exp apply`` made it differ, is said in one line and not used unless
``--workspace-params`` asks for it), and its outputs, so that experiments neither touch this workspace nor each other, and a killed one
resumes there. Running it again brings the copy's code up to this checkout's, but not over
finished runs made with other code (DVC would run them again): that is refused unless
``--keep-code`` (finish with the copy's code and the params.yaml of its commit) or ``--update-code`` (run them again) says which.
Families that none of its tasks uses and no figure draws are left out, so it learns only the
embeddings it needs; an embedding another experiment already made with the same code and
params comes from DVC's run cache instead of being made again. The train stages run through
``ede-pipeline sweep`` (side by side, ``--jobs``, Ray when asked, each run resuming from its
checkpoint), the rest (the report) through ``dvc repro``, and ``dvc exp save`` records it as the
DVC experiment NAME: ``dvc exp show`` lists it with its metrics, ``dvc exp apply NAME`` brings it
into the workspace, ``dvc exp push`` shares it.

``experiment export NAME`` copies its finished runs' files into the published layout
(``docs/results/runs/<task>/<algo>/seed<N>/``, with a ``source.json`` per task naming the
experiment file and the commit, and the held-out metrics of the embedding its EDE-TD3 runs used;
an experiment adding seeds to a published task adds its part to that task's ``source.json``), from which ``ede-pipeline results`` draws the results page.

``experiment show`` prints DVC's experiments readably: ``dvc exp show`` puts every param, metric
and dependency hash of an experiment on one line, far wider than a terminal; this prints, per
experiment, a block — its name and commit, the params it changed against the commit it started
from, and per task the report's headline numbers for each algorithm (mean final return and area
under the curve, and the seeds that ran). It reads ``dvc exp show --json``, so it shows exactly
what DVC holds.

The package: :mod:`.workspace` (an experiment's file, params and working copy),
:mod:`.command` (``experiment list`` and ``experiment run``), :mod:`.export` (``experiment
export``; what it publishes, checked: :mod:`.export_plan`; the writing, all or nothing:
:mod:`.export_write`) and :mod:`.show` (``experiment show``).
"""
