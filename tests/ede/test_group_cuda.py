"""A group on CUDA: each member trains as it trains alone on CUDA, within a bound, and the update
runs as a CUDA graph.

Skipped without a CUDA device (CI has none). On the CPU a member's bits do not depend on how
many members share its agent (``tests/ede/test_group.py``); on CUDA, cuBLAS chooses its batched
kernels by the batch's size, so a member of four need not be bitwise the same run alone; the
bound below is provisional — set from the size of fp32 rounding, never measured on a GPU — and
this test is where a GPU run measures it (its failure message prints the divergence). The same
holds for ``CAPTURED_BOUND``, between the captured update and the eager one: set from the CPU's
compiled-against-eager tolerance (``tests/ede/test_compile.py``), not yet measured on a GPU.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import torch
from safetensors.torch import load_file

from ede.config import EdeTD3Config, TD3Config
from ede.run.spec import RunSpec
from ede.run.training import train_group, train_run
from tests.support import SEEDS as MEMBERS
from tests.support import updated_agent

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
# Captured against eager, 12 updates (provisional).
CAPTURED_BOUND: dict[str, Any] = {"rtol": 1e-5, "atol": 1e-6}


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


def test_the_update_is_captured_as_a_cuda_graph_and_computes_what_eager_computes() -> None:
    """``td3.compile: reduce-overhead``: Inductor captures the update (no skipped capture, a graph
    recorded), it computes what the eager update computes within ``CAPTURED_BOUND``, and updates
    queue on the GPU without the host waiting for them (no synchronising call)."""
    from torch._dynamo.utils import counters
    from torch._inductor.cudagraph_trees import get_manager

    torch._dynamo.reset()
    counters.clear()
    eager, _ = updated_agent("none", "cuda")
    captured, buffer = updated_agent("reduce-overhead", "cuda")
    assert counters["inductor"]["cudagraph_skips"] == 0, "Inductor skipped the capture"
    manager = get_manager(torch.cuda.current_device(), create_if_none_exists=False)
    assert manager is not None and any(manager.roots.values()), "no CUDA graph was recorded"
    for member in range(len(MEMBERS)):
        theirs = captured.state_dict(member)
        for key, value in eager.state_dict(member).items():
            if not key.startswith("generator."):
                torch.testing.assert_close(theirs[key], value, **CAPTURED_BOUND, msg=key)
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")  # a call that waits for the GPU raises
    try:
        for _ in range(5):
            captured.update(buffer)
    finally:
        torch.cuda.set_sync_debug_mode("default")
