"""The update compiled whole (``td3.compile: default``, ``torch.compile(fullgraph=True)``) on CPU:
it compiles as one graph — no host synchronisation, no Python loop over members, nothing
Dynamo cannot trace — and computes what the eager update computes, within rounding.

The compiled update runs other kernels than the eager one (Inductor's generated loops for the
elementwise work: Adam, Polyak, the losses), so the comparison has a tolerance. Measured, torch
2.13 CPU, on an Intel Xeon (the previous design) and an AMD EPYC (this one): after 12 updates of
two members (a masked one among them) every weight, moment and diagnostic sum agreed within
``MEASURED`` and not exactly; ``TOLERANCE`` leaves 10x.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest
import torch

from tests.support import SEEDS, UPDATES, updated_agent

pytestmark = pytest.mark.slow

MEASURED: dict[str, Any] = {
    "rtol": 1e-6,
    "atol": 1e-7,
}  # moments within 1e-7, loss sums within 2e-6 of ~17
TOLERANCE: dict[str, Any] = {"rtol": 1e-5, "atol": 1e-6}
# A weight: Adam steps it by lr·g/(|g| + ε) for a gradient g below its ε (1e-8), so a rounding
# difference of 5e-11 in such a gradient moves the weight by lr·5e-11/ε = 5e-6. Measured (the
# stack's products on transposed activations, AMD EPYC): one weight of 2048, member 1's
# critic.2.weight, 4.6e-6 apart, every other weight within 2e-7, its moments within 1e-8.
WEIGHTS: dict[str, Any] = {"rtol": 1e-5, "atol": 5e-5}


def labelled(where: str) -> Callable[[str], str]:
    """``assert_close``'s message: its own, after ``where``."""
    return lambda message: f"{where}: {message}"


def test_the_compiled_update_is_one_graph_and_computes_what_eager_computes() -> None:
    torch.set_num_threads(1)
    torch._dynamo.reset()
    (eager, _), (compiled, _) = updated_agent("none"), updated_agent("default")
    for member in range(len(SEEDS)):
        mine, theirs = eager.state_dict(member), compiled.state_dict(member)
        for key, value in mine.items():
            if key.startswith("generator."):  # the same draws, outside the compiled function
                assert torch.equal(value, theirs[key]), key
            else:
                weight = key.split(".")[0] in ("actor", "critic", "actor_target", "critic_target")
                torch.testing.assert_close(
                    theirs[key],
                    value,
                    **(WEIGHTS if weight else TOLERANCE),
                    msg=labelled(f"member {member} {key}"),
                )
        assert int(theirs["updates"]) == UPDATES - (UPDATES // 3) * member


def test_the_compiled_update_writes_only_static_inputs_so_a_cuda_graph_can_capture_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``td3.compile: reduce-overhead`` captures the update as a CUDA graph only where every input
    it writes in place is static (``torch.compile`` marks a module's buffers so: the networks,
    Adam's moments, the loss sums); a mutated input that is not static makes Inductor skip the
    capture ("mutated inputs"). Checked here on the CPU, where the same graphs are compiled, from
    what Inductor records of each graph: the inputs it mutates and those it takes as static. The
    capture itself is tested on CUDA (``tests/ede/test_group_cuda.py``)."""
    import inspect

    import torch._functorch.config
    import torch._inductor.config
    from torch._inductor.output_code import CompiledFxGraph

    graphs: list[tuple[list[int], list[int]]] = []
    made = CompiledFxGraph.__init__
    signature = inspect.signature(made)

    def recording(self: CompiledFxGraph, *args: Any, **kwargs: Any) -> None:
        made(self, *args, **kwargs)
        static = signature.bind(self, *args, **kwargs).arguments["static_input_idxs"]
        graphs.append((sorted(self.mutated_input_idxs), sorted(static)))

    monkeypatch.setattr(CompiledFxGraph, "__init__", recording)
    torch.set_num_threads(1)
    torch._dynamo.reset()
    with (
        torch._inductor.config.patch(fx_graph_cache=False),  # each graph compiled, not loaded
        torch._functorch.config.patch(enable_autograd_cache=False),
    ):
        updated_agent("reduce-overhead")
    assert len(graphs) >= 2  # the update with an actor step and without
    for mutated, static in graphs:
        assert mutated, "the update writes its state in place"
        assert set(mutated) <= set(static), f"mutated inputs {mutated}, static {static}"
