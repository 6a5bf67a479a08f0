"""How far a results page's clip moves on another CPU: the bound the redraw test allows its returns.

    python benchmarks/clip_sensitivity.py [--runs DIR]... [--draws 6] [--scale 1e-6]

A clip plays a published seed's TD3 and EDE-TD3 policies for the first episode of their runs' final
evaluations (``ede-pipeline results``' ``Clip:`` blocks; published in ``docs/results/clips``, and
ReacherPush's among its runs in ``docs/results/runs``, the two folders ``--runs`` defaults to), and
the block prints each episode's return to 0.1. Played again on another CPU, the policies' actions
take that CPU's kernels' last bits. This plays each clip's episodes again with every action scaled
by ``1 + scale·N(0, 1)`` (1e-6: a few float32 ulps), ``--draws`` times a policy, and prints how far
each return moved: what ``tests/pipeline/test_results.py``'s ``played`` tolerance has to hold. Needs
offscreen GL, as the clips do (``MUJOCO_GL=egl``).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np
import torch

from ede.analysis.policy import adapter_of, trained_embedding
from ede.analysis.video import frames_of
from ede.config import PAPER_ALGOS, load_params
from ede.run.runs import POLICY, read_policy
from ede_pipeline import layout
from ede_pipeline.published import published_runs, task_folders


def returns(run: Path, scales: list[float], rng: np.random.Generator) -> list[float]:
    """The return of the first episode of ``run``'s final evaluation, as ``ede-pipeline render``
    plays it (:func:`ede.analysis.video.frames_of`), once per scale, each action scaled by
    ``1 + scale·N(0, 1)``."""
    meta, tensors = read_policy(run)
    params = load_params("params.yaml")
    embedding = None
    if meta["algo"] != "td3":
        embedding = trained_embedding(meta, *layout.run_embedding(run, meta, params))
    adapter = adapter_of(meta, embedding)
    decode = adapter.decode
    made = []
    for scale in scales:

        def jittered(codes: torch.Tensor, scale: float = scale) -> torch.Tensor:
            actions = decode(codes)
            noise = torch.from_numpy(rng.standard_normal(tuple(actions.shape)))
            return actions * (1 + scale * noise.to(actions.dtype))

        setattr(adapter, "decode", jittered)  # noqa: B010 (a method replaced on this one instance)
        frames, played = frames_of(meta, tensors, adapter, 1, shrink=2)
        for _ in frames:  # each frame played and dropped: the episode's return is known after
            pass
        made.append(played[0])
    return made


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=Path, action="append", help="repeatable")
    parser.add_argument("--draws", type=int, default=6)
    parser.add_argument("--scale", type=float, default=1e-6)
    args = parser.parse_args()
    os.environ.setdefault("MUJOCO_GL", "egl")
    rng = np.random.default_rng(0)
    print(f"{'task':<24} {'algo':<8} {'return':>10} {'largest move':>13}")
    folders = args.runs or [layout.RESULTS / "clips", layout.RESULTS / "runs"]
    for folder, task in [(runs, task) for runs in folders for task in task_folders(runs)]:
        kept = {
            (record.made["algo"], record.curve.seed): run
            for run, record in published_runs(folder, task)
            if (run / POLICY).is_dir()
        }
        seeds = sorted({seed for _, seed in kept})
        if not seeds:
            continue
        for algo in PAPER_ALGOS:
            run = kept[(algo, seeds[0])]
            exact, *jittered = returns(run, [0.0] + [args.scale] * args.draws, rng)
            moved = max(abs(ret - exact) for ret in jittered)
            print(f"{task:<24} {algo:<8} {exact:>10.4f} {moved:>13.5f}")


if __name__ == "__main__":
    main()
