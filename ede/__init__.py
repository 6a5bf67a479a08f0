"""The EDE method as a library: the embedding of action sequences (:mod:`ede.embedding`), TD3 and
EDE-TD3 (:mod:`ede.td3`, :mod:`ede.training`), and what the pipeline's stages share (params,
artifacts, rollouts, runs, statistics). ``ede_pipeline`` is the command line around it."""
