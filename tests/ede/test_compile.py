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

import numpy as np
import pytest
import torch

from ede.config import TD3Config
from ede.td3 import Agent, IdentityAdapter, ReplayBuffer
from tests.support import add_step

pytestmark = pytest.mark.slow

OBS, ACT, SEEDS, UPDATES = 5, 2, [3, 4], 12
MEASURED: dict[str, Any] = {
    "rtol": 1e-6,
    "atol": 1e-7,
}  # weights within 3e-8, loss sums within 2e-6 of ~17
TOLERANCE: dict[str, Any] = {"rtol": 1e-5, "atol": 1e-6}


def labelled(where: str) -> Callable[[str], str]:
    """``assert_close``'s message: its own, after ``where``."""
    return lambda message: f"{where}: {message}"


def trained(mode: str) -> Agent:
    config = TD3Config.model_validate({"hidden": [32, 32], "batch_size": 16, "compile": mode})
    cpu = torch.device("cpu")
    agent = Agent(OBS, IdentityAdapter(-np.ones(ACT), np.ones(ACT), cpu), config, cpu, SEEDS)
    buffer = ReplayBuffer(200, OBS, ACT, 1, cpu, members=len(SEEDS))
    rng = np.random.default_rng(0)
    for member in range(len(SEEDS)):
        for t in range(100):
            add_step(
                buffer,
                member,
                rng.normal(size=OBS),
                torch.as_tensor(rng.uniform(-1, 1, ACT)),
                0,
                float(rng.normal()),
                rng.normal(size=OBS),
                t % 40 == 39,
                False,
            )
    for u in range(UPDATES):
        agent.update(buffer, np.array([True, u % 3 != 1]))  # member 1 sits some out
    return agent


def test_the_compiled_update_is_one_graph_and_computes_what_eager_computes() -> None:
    torch.set_num_threads(1)
    torch._dynamo.reset()
    eager, compiled = trained("none"), trained("default")
    for member in range(len(SEEDS)):
        mine, theirs = eager.state_dict(member), compiled.state_dict(member)
        for key, value in mine.items():
            if key.startswith("generator."):  # the same draws, outside the compiled function
                assert torch.equal(value, theirs[key]), key
            else:
                torch.testing.assert_close(
                    theirs[key],
                    value,
                    **TOLERANCE,
                    msg=labelled(f"member {member} {key}"),
                )
        assert int(theirs["updates"]) == UPDATES - (UPDATES // 3) * member
