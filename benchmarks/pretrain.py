"""Encoder and decoder training at the paper's settings on one core, with their quality.

    python benchmarks/pretrain.py [--family reacher] [--params params.yaml] [--threads 1]

Collects the family's rollouts (params' ``collect`` section), trains E and P then D with the
params' ``embedding`` and ``decoder`` sections, and prints the wall time of each against a
reference measured in the same run (one epoch of plain Adam steps on an MLP of the same size, fed
the same batches, so the ratio shows what the training loop adds), with the held-out metrics.
Goals: both stages under 2 minutes together; prediction ratio to the mean-change baseline < 0.2.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from ede.config import load_params
from ede.io.rollouts import Rollouts, write_store
from ede.method.embedding import train_decoder, train_encoder
from ede.method.nets import mlp
from ede.run.collect import collect


def reference_epoch(rollouts: Rollouts, k: int, hidden: list[int], batch_size: int) -> float:
    """Seconds for one pass of a bare MLP regression over the same windows."""
    state, actions, later = rollouts.windows(rollouts.window_starts(k), k)
    x = torch.as_tensor(
        np.concatenate([state, actions.reshape(len(state), -1)], 1), dtype=torch.float32
    )
    y = torch.as_tensor(later - state, dtype=torch.float32)
    net = mlp(x.shape[1], hidden, y.shape[1], torch.nn.SELU)
    optimizer = torch.optim.Adam(net.parameters(), lr=1e-4)
    start = time.perf_counter()
    for batch in torch.randperm(len(x)).split(batch_size):
        loss = (net(x[batch]) - y[batch]).pow(2).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--family", default="reacher")
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    params = load_params(args.params)
    source = params.families[args.family].source

    with tempfile.TemporaryDirectory() as tmp:
        arrays = collect(source, params.collect.steps, 2, params.collect.seed)
        attrs = {"env_id": source, "family": args.family}
        write_store(
            Path(tmp) / "r.zarr",
            arrays,
            attrs | {"seed": 0, "num_envs": 2, "steps": 0, "spaces": {}, "params": {}},
        )
        rollouts = Rollouts.open(Path(tmp) / "r.zarr")
    k = params.embedding.k
    reference = reference_epoch(rollouts, k, params.embedding.hidden, params.embedding.batch_size)

    start = time.perf_counter()
    encoded = train_encoder(rollouts, params.embedding)
    encoder_s = time.perf_counter() - start
    low = rollouts.action.min(axis=0).round()
    high = rollouts.action.max(axis=0).round()
    start = time.perf_counter()
    decoded = train_decoder(rollouts, encoded, params.decoder, k, low, high)
    decoder_s = time.perf_counter() - start

    e, d = encoded.metrics, decoded.metrics
    print(f"{args.family} ({source}), {len(rollouts)} steps, {args.threads} thread(s)")
    print(f"reference: one epoch of a bare MLP  {reference:7.1f} s")
    print(
        f"encoder + predictor ({params.embedding.epochs} epochs)  {encoder_s:7.1f} s  "
        f"= {encoder_s / reference / params.embedding.epochs:.2f}x the reference per epoch"
    )
    print(
        f"decoder ({params.decoder.epochs} epochs)             {decoder_s:7.1f} s  "
        f"= {decoder_s / reference / params.decoder.epochs:.2f}x the reference per epoch"
    )
    print(f"total                             {encoder_s + decoder_s:7.1f} s (goal < 120 s)")
    print(
        f"held-out prediction MSE {e['prediction_mse']:.4f}, mean-change baseline "
        f"{e['mean_change_mse']:.4f}: ratio {e['prediction_ratio']:.3f} (goal < 0.2)"
    )
    print(f"raw k actions, no bottleneck: ratio {e['raw_prediction_ratio']:.3f}; KL {e['kl']:.2f}")
    print(
        f"decoder inverse error {d['inverse_error']:.4f} of the code variance; "
        f"{100 * d['at_bounds']:.1f}% of actions at a bound; |z| bound {d['bound']:.2f}"
    )


if __name__ == "__main__":
    main()
