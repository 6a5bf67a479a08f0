"""``ede-pipeline``: the pipeline's stages as click commands (collect, pretrain, train, report),
the sweep that runs them in parallel and the committed experiments, over the :mod:`ede` library."""
