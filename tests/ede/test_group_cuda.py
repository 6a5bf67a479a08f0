"""A group on CUDA: each member trains as it trains alone on CUDA, within a bound.

Skipped without a CUDA device (CI has none). On the CPU a member's bits do not depend on how
many members share its agent (``tests/ede/test_group.py``); on CUDA, cuBLAS chooses its batched
kernels by the batch's size, so a member of four need not be bitwise the same run alone; the
bound below is provisional — set from the size of fp32 rounding, never measured on a GPU — and
this test is where a GPU run measures it (its failure message prints the divergence).
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from ede.config import EdeTD3Config, TD3Config
from ede.runs import RunSpec
from ede.training import train_group, train_run

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device"),
]

SEEDS = [0, 1, 2, 3]
CONFIG = TD3Config(
    hidden=[64, 64],
    batch_size=32,
    eval_every=100,
    eval_episodes=2,
    update_schedule="step",
    checkpoint_every=1000,
    device="cuda",
)
BOUND = 1e-3  # largest |difference| of a policy weight after 300 steps (provisional)


def spec(seed: int) -> RunSpec:
    return RunSpec("ede/Point-v0", "td3", seed, 300, CONFIG, EdeTD3Config())


def test_a_member_on_cuda_trains_as_it_trains_alone_within_the_bound(tmp_path: Path) -> None:
    cuda = torch.device("cuda")
    train_group([spec(s) for s in SEEDS], [tmp_path / f"group{s}" for s in SEEDS], device=cuda)
    train_run(spec(3), tmp_path / "alone", device=cuda)
    grouped = load_file(tmp_path / "group3" / "policy" / "policy.safetensors")
    alone = load_file(tmp_path / "alone" / "policy" / "policy.safetensors")
    divergence = max(float((grouped[k] - alone[k]).abs().max()) for k in alone)
    assert divergence <= BOUND, f"member 3 on CUDA differs from its run alone by {divergence:.3g}"
    other = load_file(tmp_path / "group0" / "policy" / "policy.safetensors")
    assert max(float((other[k] - alone[k]).abs().max()) for k in alone) > BOUND  # other runs
