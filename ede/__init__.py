"""The EDE method as a library: the embedding of action sequences (:mod:`ede.method.embedding`), TD3 and
EDE-TD3 (:mod:`ede.method.td3`, :mod:`ede.run.training`), and what the pipeline's stages share (params,
artifacts, rollouts, runs, statistics). ``ede_pipeline`` is the command line around it."""
