"""Stage 5, ``ede-pipeline report``: one self-contained HTML page of every result.

The package's parts, as the results pages' (:mod:`ede_pipeline.results`): :mod:`.inputs` reads
and checks the command line's inputs and the runs the params name; :mod:`.numbers` computes from
them, through the results model (:mod:`ede.analysis.results`) and the probes, each family's statistics,
the aggregates across tasks, Figures 6 and 7's data, the curves for ``dvc plots``, the DVC
metrics and the clips; :mod:`.sections` draws each section in HTML on the page (:mod:`.page`);
:mod:`.command` is the click command, which builds the page and writes its files.
"""
