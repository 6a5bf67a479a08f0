"""Can a family's embedding express the policies TD3 finds? TD3's final policies run through it.

    python benchmarks/through_embedding.py --data DIR --task HalfCheetah-v5 [--episodes 10]

``DIR`` holds a ``train`` stage's layout (``runs/<task>/td3/seed<N>/policy/`` and
``families/<family>/embedding/``), as ``ede-pipeline experiment run NAME`` leaves it in
``.dvc/tmp/experiments/NAME/data``. Each TD3 run's final actor μ is evaluated twice from the starts its own
final evaluation used (``ede.run.evaluation``: episode e of seed s resets with
``EVAL_SEED_OFFSET·(s+1) + e``):

- *as is*: μ(s) at every step — the run's last evaluation, again (printed beside it: a check that
  the actor was rebuilt right);
- *through the embedding*: every k steps, the k actions μ would take next (played out on a copy
  of the simulator's state) are replaced by D(clip(E(those k actions))), the sequence an EDE-TD3
  policy would execute for the code nearest that effect, and those are executed.

If the second return is far below the first, the behaviour TD3 learned lies outside what the
embedding can express, and EDE-TD3 on that task is capped below TD3 whatever its training does.
Both lines give the fraction of executed action components within 1% of a bound (bang-bang
control shows as a fraction near 1). The look-ahead restores the simulator's ``qpos`` and ``qvel``:
it fits tasks whose whole state they are (gymnasium's locomotion tasks, ``ede/ReacherVertical-v0``,
``ede/Point-v0``), not those that keep more of it in Python.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path
from typing import cast

import gymnasium
import numpy as np
import torch
from gymnasium.envs.mujoco.mujoco_env import MujocoEnv

from ede.analysis.video import actor_of
from ede.method.embedding import ActionEmbedding
from ede.run.artifacts import load_action_embedding
from ede.run.evaluation import EVAL_SEED_OFFSET
from ede.run.runs import read_policy
from ede.tasks import action_bounds, make, observation_size
from ede_pipeline import layout


def load_actor(run: Path, obs_size: int):
    """μ of a run's final policy (:func:`ede.run.runs.read_policy`): obs (O,) -> action (A,)."""
    meta, tensors = read_policy(run)
    batched = actor_of(meta, tensors, obs_size)  # (M, O) -> (M, A)

    def mu(obs: np.ndarray) -> np.ndarray:
        return batched(obs[None], np.ones(1, bool))[0].numpy()

    return mu


def episode(
    env: gymnasium.Env, mu, seed: int, embedding: ActionEmbedding | None
) -> tuple[float, np.ndarray, list[bool]]:
    """One episode's return and executed actions, and per window whether its code lay outside
    the box EDE-TD3 acts in (clipped); through ``embedding`` when one is given."""
    sim = cast(MujocoEnv, env.unwrapped)  # the simulator itself, to play ahead and rewind
    obs, _ = env.reset(seed=seed)
    total, executed, clipped, done = 0.0, [], [], False
    while not done:
        if embedding is None:
            plan = mu(obs)[None]
        else:  # μ's next k actions, played out on the simulator alone (no time limit counted)
            qpos, qvel, ahead, window = sim.data.qpos.copy(), sim.data.qvel.copy(), obs, []
            for _ in range(embedding.k):
                window.append(mu(ahead))
                ahead, *_ = sim.step(window[-1])
            sim.set_state(qpos, qvel)
            with torch.no_grad():
                z = embedding.encode(torch.as_tensor(np.array(window))[None])
                clipped.append(bool((z.abs() > embedding.bound).any()))
                plan = embedding.decode(z.clamp(-embedding.bound, embedding.bound))[0].numpy()
        for action in plan:
            obs, reward, terminated, truncated, _ = env.step(action)
            total += float(reward)
            executed.append(action)
            if terminated or truncated:
                done = True
                break
    return total, np.array(executed), clipped


def at_bound(actions: np.ndarray, low: np.ndarray, high: np.ndarray) -> float:
    margin = 0.01 * (high - low) / 2
    return float(np.mean((actions <= low + margin) | (actions >= high - margin)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="a train stage's data/ folder")
    parser.add_argument("--task", required=True)
    parser.add_argument("--family", help="whose embedding [default: the task's own family]")
    parser.add_argument("--episodes", type=int, default=10)
    args = parser.parse_args()
    family = args.family or layout.own_family(args.task, {})
    found = args.data / "families" / family / "embedding"
    runs = sorted(
        p.parent.parent
        for p in (args.data / "runs" / args.task / "td3").glob("seed*/policy/policy.json")
    )
    if not (found / "decoder").is_dir() or not runs:
        print(
            f"{args.data}: expected families/{family}/embedding/ and runs/{args.task}/td3/"
            "seed<N>/policy/ (a train stage's layout)",
            file=sys.stderr,
        )
        sys.exit(2)
    _, embedding = load_action_embedding(found / "encoder", found / "decoder")
    env = make(args.task)
    low, high = action_bounds(env)
    print(
        f"{args.task}: TD3's final policies as is and through {family}'s embedding "
        f"(k={embedding.k}, {embedding.dim} dimensions, |z| <= {embedding.bound:.3g}); "
        f"{args.episodes} episodes each"
    )
    for run in runs:
        seed = json.loads((run / "run.json").read_text())["seed"]
        with (run / "eval.csv").open() as f:
            last = float(list(csv.DictReader(f))[-1]["mean_return"])
        mu = load_actor(run, observation_size(env))
        starts = [EVAL_SEED_OFFSET * (seed + 1) + e for e in range(args.episodes)]
        line = []
        for through in (None, embedding):
            done = [episode(env, mu, s, through) for s in starts]
            acts = np.concatenate([a for _, a, _ in done])
            line.append(
                f"{np.mean([r for r, _, _ in done]):9.1f} ({at_bound(acts, low, high):.0%} at a bound)"
            )
        clipped = np.mean([c for _, _, cs in done for c in cs])
        print(
            f"seed {seed}: as is {line[0]}, the run's last evaluation {last:.1f}; "
            f"through the embedding {line[1]}, {clipped:.0%} of its codes clipped to the box"
        )


if __name__ == "__main__":
    main()
