"""The paper's method: the action embedding, the adapters, TD3 and its learner, the replay
buffer and the member axis. Nothing here steps an environment."""
