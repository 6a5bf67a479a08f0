"""``ede-pipeline sweep``: the out-of-date stages of ``dvc.yaml``, run in parallel, recorded by DVC.

``dvc repro`` runs one stage at a time, and two ``dvc repro`` processes in one checkout race on the
repository's lock. A sweep takes that lock once, as ``dvc repro`` does, and inside it:

1. puts the stages (by default every stage of ``dvc.yaml``; with targets, those and what they
   depend on) in waves: a stage in the wave after that of its last dependency (task code, collect,
   encoder, decoder, task inputs, the runs, the report), so that the stages of a wave — the
   families side by side, then the runs — can run at once;
2. asks DVC which stages are out of date (``Stage.changed``, what ``dvc status`` reports), with
   everything downstream of them; at its wave's turn each is asked again (what it depends on may
   have come out as before: then it is up to date, as ``dvc repro`` finds it), and the sweep does
   what ``dvc repro`` does before the command — removes the stage's outputs (never a run's
   ``checkpoint/``, which is not one) and restores the stage from DVC's run cache if this very
   run (command, dependencies, params) was recorded before;
3. with ``--group-size N`` (by default every seed on CUDA; on CPU as many as leave every job a
   process: ``default_group_size``), gathers the train runs of
   one task and algorithm into processes of up to N (``ede-pipeline train --seeds``: their
   updates batched, each run's outputs those it gets alone), then
   runs the wave's commands in parallel — threads each waiting on one child process
   (``--executor local``), or one Ray task each (``--executor ray``);
4. records each stage as it finishes, exactly as ``dvc repro`` would: the stage's dependencies and
   outputs hashed, the outputs committed to DVC's cache and the run cache, its ``dvc.lock`` entry
   written. A following ``dvc repro`` or ``dvc status`` sees it as up to date.

A stage that fails (non-zero exit, a killed process) is reported with the path of its log and
recorded nowhere, and the stages that depend on it are not run; the others are recorded all the
same, and the sweep exits 1. Its checkpoint
stays, so the next ``sweep`` (or ``dvc repro``) runs only what is still out of date and resumes
that run where it stopped. On Ray, a run lost with its worker or node is not a failure: Ray
starts it again (``--retries`` times at most) on the nodes there are, and it resumes from its
checkpoint within this sweep.

On Ray, every node runs the command in this very checkout, which must be at the same path on every
node (a shared filesystem); only this process touches DVC. A cluster without a shared filesystem
runs each stage as a batch job instead (``scripts/batch-job.sh``: pull, run, push; README.md).

A ``dvc.yaml`` or ``dvc.lock`` that DVC cannot read (not YAML, not what DVC expects, empty, a
folder) is one line naming it and how to mend it, exit code 2, before anything runs.

The package, one job a module: :mod:`.plan` (what to run: the pipeline DVC reads, the runs,
their commands, groups),
:mod:`.stages` (DVC: which stages, their waves, which are out of date, recording),
:mod:`.execute` (running a job's commands; the local executor), :mod:`.on_ray` (the Ray
executor and its address check), :mod:`.tally` (progress) and :mod:`.command` (the CLI).
"""
