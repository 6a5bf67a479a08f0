"""The update compiled whole (``td3.compile: default``, ``torch.compile(fullgraph=True)``) on CPU:
it compiles as one graph — no host synchronisation, no Python loop over members, nothing
Dynamo cannot trace — and computes what the eager update computes, within rounding.

The compiled update runs other kernels than the eager one (Inductor's generated loops for the
elementwise work: Adam, Polyak, the losses), so the comparison has a tolerance. Measured, torch
2.13 CPU, on an Intel Xeon (the previous design) and an AMD EPYC (this one): after 12 updates of
two members (a masked one among them) every weight, moment and diagnostic sum agreed within
``MEASURED`` and not exactly; ``TOLERANCE`` leaves 10x.

Compiling on the CPU needs what Inductor needs: a C++ compiler and Python's C headers (our
machines and CI have both; ``ede.run.group.compiler_missing`` names what is missing). The last
tests check ``td3.compile: auto``, the default, which compiles a long run's update where they are
and falls back to eager where compiling fails.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import torch

from ede.config import EdeTD3Config, TD3Config
from ede.run import group
from ede.run.group import COMPILE_FROM_UPDATES, compile_mode, compiler_missing
from ede.run.spec import RunSpec
from ede.run.training import train_run
from tests.support import REPO, SEEDS, UPDATES, updated_agent

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


def test_a_compiled_member_computes_alone_what_it_computes_in_a_group() -> None:
    """The CPU contract holds compiled too: a member alone and beside a member that sits some
    updates out ends with the same weights, moments and sums, bit for bit (Inductor's loops over
    a member's row do not depend on how many rows there are; measured too at the paper's sizes,
    one member against three, on our AVX-512 AMD EPYC; this test checks it on every CI machine)."""
    torch.set_num_threads(1)
    (group, _), (alone, _) = updated_agent("default"), updated_agent("default", seeds=SEEDS[:1])
    assert group.compiled and alone.compiled
    mine, theirs = alone.state_dict(0), group.state_dict(0)
    for key, value in mine.items():
        assert torch.equal(value, theirs[key]), key


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


# `td3.compile: auto`, the default ----------------------------------------------------------------


def test_auto_compiles_a_run_long_enough_to_repay_it_where_a_compiler_is(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    cpu = torch.device("cpu")
    monkeypatch.setenv("CXX", sys.executable)  # a program that exists stands for the compiler
    assert compiler_missing(cpu) is None
    assert compile_mode("auto", COMPILE_FROM_UPDATES, cpu) == "default"
    assert compile_mode("auto", COMPILE_FROM_UPDATES - 1, cpu) == "none"
    monkeypatch.setenv("CXX", "/nonexistent/c++")
    assert compiler_missing(cpu) == "a C++ compiler (/nonexistent/c++, or $CXX)"
    assert compile_mode("auto", 10**6, cpu) == "none"
    for setting in ("none", "default", "reduce-overhead"):  # a setting is taken as it is
        assert compile_mode(setting, 10, cpu) == setting


FALLBACK = """
import json, sys, torch
from ede.method import agent
from tests.support import updated_agent
told, made = [], agent.Agent.__init__
agent.Agent.__init__ = lambda self, *a, **k: made(self, *a, **k, fallback=told.append)
compiled, _ = updated_agent("default")
agent.Agent.__init__ = made
eager, _ = updated_agent("none")
same = all(
    torch.equal(value, eager.state_dict(m)[key])
    for m in range(2) for key, value in compiled.state_dict(m).items()
)
print(json.dumps({"told": told, "compiled": compiled.compiled, "same": same}))
"""


def test_an_update_that_fails_to_compile_runs_eager_after_one_line(tmp_path: Path) -> None:
    """A compiler that is there but fails (``/bin/false`` as Inductor's ``$CXX``): under
    ``auto`` the agent says so in one line and its updates are the eager ones, bit for bit —
    the failed compile touched nothing. A process of its own: Inductor reads ``$CXX`` once."""
    done = subprocess.run(
        [sys.executable, "-c", FALLBACK],
        capture_output=True,
        text=True,
        cwd=REPO,
        env={**os.environ, "CXX": "/bin/false", "TORCHINDUCTOR_CACHE_DIR": str(tmp_path)},
        check=True,
    )
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert len(result["told"]) == 1, result
    assert result["told"][0].startswith("td3.compile auto: compiling the update failed (")
    assert "C++ compiler" in result["told"][0], result["told"][0]  # the cause, not a wrapper
    assert "\n" not in result["told"][0] and result["told"][0].endswith("); it runs eager")
    assert result["compiled"] is False and result["same"] is True


def test_a_run_under_auto_compiles_when_long_enough_and_records_how_it_updated(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    config = TD3Config(hidden=[16, 16], batch_size=8, start_steps=100, eval_every=200)
    spec = RunSpec("ede/Point-v0", "td3", 0, 300, config, EdeTD3Config())
    told: list[str] = []
    train_run(spec, tmp_path / "short", notice=told.append)  # 200 updates: eager
    monkeypatch.setattr(group, "COMPILE_FROM_UPDATES", 200)
    torch._dynamo.reset()
    train_run(spec, tmp_path / "long", notice=told.append)
    updates = {
        run: json.loads((tmp_path / run / "run.json").read_text())["update"]
        for run in ("short", "long")
    }
    assert updates == {"short": "eager", "long": "compiled"} and told == []
    monkeypatch.setenv("CXX", "/nonexistent/c++")  # no compiler: eager, said in one line
    train_run(spec, tmp_path / "none", notice=told.append)
    assert json.loads((tmp_path / "none" / "run.json").read_text())["update"] == "eager"
    assert told == [
        "td3.compile auto: a C++ compiler (/nonexistent/c++, or $CXX) not found, so the updates "
        "run eager, slower (docs/performance.md)"
    ]
