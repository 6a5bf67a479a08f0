"""Which embedding can express a saturating policy? Candidate embeddings, measured cheaply.

    python benchmarks/saturating_embeddings.py --policies DIR --out OUT [--experiment halfcheetah]
                                               [--episodes 5] [NAME ...]

TD3's gaits on HalfCheetah-v5 hold most motors at a bound, and run through the embedding learned
from uniform random actions they no longer run (``benchmarks/through_embedding.py``). Each
candidate below is a params setting of the collect and pretrain stages (on top of the
experiment's params, ``experiments/<experiment>.yaml``), made with the product's own stage
commands into ``OUT/<name>/families/<family>/`` — resumable: a candidate whose decoder metrics
exist is not made again. Each is then measured by what costs no RL run:

- the encoder's held-out prediction ratio (P's error over the mean change's; in brackets, a
  predictor given the raw k actions instead of the code: what the bottleneck loses), and KL;
- the decoder's held-out inverse error and the share of its decoded actions at a bound;
- TD3's final policies (``DIR/runs/<task>/td3/seed<N>/policy/``, as ``experiment run`` or
  ``train`` leave them) as is and through the candidate's embedding, from the starts of each
  run's last evaluation (:func:`through_embedding.episode`): how much of a saturating gait
  survives being chosen as an effect.

Prints one Markdown row a candidate. Pass NAMEs to make and measure only those.
"""

from __future__ import annotations

import argparse
import copy
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import yaml
from through_embedding import at_bound, episode, load_actor

from ede.run.artifacts import load_action_embedding
from ede.run.evaluation import EVAL_SEED_OFFSET
from ede.tasks import action_bounds, make, observation_size
from ede_pipeline.experiments.workspace import experiment_params

# name: the keys it changes against the experiment's params, and why it could help.
CANDIDATES: dict[str, dict[str, dict]] = {
    "default": {},  # uniform data, k·A actions summarised by A numbers, minimum-norm decoder
    "lam0": {"decoder": {"lam": 0.0}},  # no norm penalty: D free to reach the bounds
    "dim12": {"embedding": {"dim": 12}},  # twice the action size: less for D to choose
    "dim24": {"embedding": {"dim": 24}},  # k·A: no compression at all
    "sat25": {"collect": {"saturated_episodes": 0.25}},  # E also learns bang-bang effects
    "sat50": {"collect": {"saturated_episodes": 0.5}},
    "sat50-lam1e-6": {"collect": {"saturated_episodes": 0.5}, "decoder": {"lam": 1.0e-6}},
    "sat50-dim12": {"collect": {"saturated_episodes": 0.5}, "embedding": {"dim": 12}},
    "sat50-dim24": {"collect": {"saturated_episodes": 0.5}, "embedding": {"dim": 24}},
    "sat50-dim12-lam1e-6": {
        "collect": {"saturated_episodes": 0.5},
        "embedding": {"dim": 12},
        "decoder": {"lam": 1.0e-6},
    },
}


def make_embedding(name: str, base: dict, family: str, out: Path) -> Path:
    """The candidate's rollouts, encoder and decoder, by the stage commands; its folder."""
    root = out / name
    embedding = root / "families" / family / "embedding"
    if (embedding / "decoder_metrics.json").is_file():
        return root
    params = copy.deepcopy(base)
    for section, keys in CANDIDATES[name].items():
        params[section].update(keys)
    embedding.mkdir(parents=True, exist_ok=True)
    (root / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    rollouts = root / "families" / family / "rollouts.zarr"
    tool = [str(Path(sys.executable).parent / "ede-pipeline")]
    common = ["--family", family, "--params", str(root / "params.yaml")]
    for command in (
        ["collect", "--out", str(rollouts), "--workers", "1"],
        [
            "pretrain",
            "encoder",
            "--rollouts",
            str(rollouts),
            "--out",
            str(embedding / "encoder"),
            "--metrics",
            str(embedding / "encoder_metrics.json"),
            "--plots",
            str(embedding / "encoder_history.csv"),
        ],
        [
            "pretrain",
            "decoder",
            "--rollouts",
            str(rollouts),
            "--encoder",
            str(embedding / "encoder"),
            "--out",
            str(embedding / "decoder"),
            "--metrics",
            str(embedding / "decoder_metrics.json"),
            "--plots",
            str(embedding / "decoder_history.csv"),
        ],
    ):
        subprocess.run([*tool, *command, *common], check=True, stdout=subprocess.DEVNULL)
    return root


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--policies",
        type=Path,
        required=True,
        help="a train stage's data/ folder holding TD3's final policies",
    )
    parser.add_argument("--out", type=Path, required=True, help="where the candidates are made")
    parser.add_argument("--experiment", default="halfcheetah")
    parser.add_argument("--episodes", type=int, default=5)
    parser.add_argument("names", nargs="*", help=f"of: {', '.join(CANDIDATES)}")
    args = parser.parse_args()
    if unknown := [n for n in args.names if n not in CANDIDATES]:
        sys.exit(f"unknown candidates {unknown}; expected some of: {', '.join(CANDIDATES)}")
    base = experiment_params(args.experiment)
    ((task, family),) = base["runs"]["tasks"].items()
    runs = sorted(
        p.parent.parent
        for p in (args.policies / "runs" / task / "td3").glob("seed*/policy/policy.json")
    )
    if not runs:
        sys.exit(f"{args.policies}: no runs/{task}/td3/seed<N>/policy/ (a train stage's layout)")
    env = make(task)
    low, high = action_bounds(env)
    policies = []
    for run in runs:
        seed = json.loads((run / "run.json").read_text())["seed"]
        starts = [EVAL_SEED_OFFSET * (seed + 1) + e for e in range(args.episodes)]
        mu = load_actor(run / "policy", observation_size(env))
        as_is = np.mean([episode(env, mu, s, None)[0] for s in starts])
        policies.append((seed, mu, starts, as_is))
    print(
        f"{task}: TD3 seeds {', '.join(str(s) for s, *_ in policies)} as is: "
        + ", ".join(f"{r:.1f}" for *_, r in policies)
        + f" ({args.episodes} episodes each)\n"
    )
    print(
        "| candidate | prediction ratio (raw actions) | KL | inverse error | decoded at a bound "
        "| through the embedding, per TD3 seed (at a bound) |"
    )
    print("|---|---|---|---|---|---|")
    for name in args.names or CANDIDATES:
        embedding = make_embedding(name, base, family, args.out) / "families" / family / "embedding"
        e = json.loads((embedding / "encoder_metrics.json").read_text())
        d = json.loads((embedding / "decoder_metrics.json").read_text())
        _, through = load_action_embedding(embedding / "encoder", embedding / "decoder")
        cells = []
        for _, mu, starts, _ in policies:
            done = [episode(env, mu, s, through) for s in starts]
            acts = np.concatenate([a for _, a, _ in done])
            cells.append(
                f"{np.mean([r for r, _, _ in done]):.1f} ({at_bound(acts, low, high):.0%})"
            )
        print(
            f"| {name} | {e['prediction_ratio']:.3f} ({e['raw_prediction_ratio']:.3f}) "
            f"| {e['kl']:.1f} | {d['inverse_error']:.2g} | {d['at_bounds']:.1%} | "
            + "; ".join(cells)
            + " |",
            flush=True,
        )


if __name__ == "__main__":
    main()
