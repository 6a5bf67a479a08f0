"""This checkout, and scratch copies of it to run ``dvc`` in without touching the real one.

The end-to-end tests and ``benchmarks/sweep.py`` need a repository in which DVC runs the pipeline
with params of their own: the checkout's files, committed or not yet added (never what git
ignores: no ``data/``, no ``.venv``), in a fresh git repository. Test support, so it lives here;
the sweep benchmark imports it from here too (it runs from the checkout), rather than keep a copy.

``REPO`` is this checkout, where the tests and the benchmarks run.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import gymnasium
import yaml

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent  # this environment's scripts: `dvc`, `ede-pipeline`


EnvT = TypeVar("EnvT", bound=gymnasium.Env)


def unwrapped(env: gymnasium.Env, kind: type[EnvT]) -> EnvT:
    """``env``'s innermost environment, checked to be a ``kind`` (its simulator, its fields)."""
    inner = env.unwrapped
    assert isinstance(inner, kind), f"{type(inner).__name__}, expected a {kind.__name__}"
    return inner


def tool_env() -> dict[str, str]:
    """This process's environment with :data:`BIN` first on ``PATH``: the stages call ``dvc`` and
    ``ede-pipeline`` by name, and must get this environment's."""
    return {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}"}


def scratch_copy(dest: Path, edit_params: Callable[[dict[str, Any]], None] | None = None) -> Path:
    """Copy the checkout's files to ``dest``, a fresh git repository with every file added.

    Args:
        dest: The new repository's folder (created; it should not exist or be empty).
        edit_params: Called on the copy's ``params.yaml`` as plain data, which is then written back.

    Returns:
        ``dest``.
    """
    files = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split("\0")
    for name in filter(None, files):
        if (REPO / name).is_file():  # a deleted file is still listed until its deletion is added
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / name, dest / name)
    if edit_params is not None:
        params = yaml.safe_load((dest / "params.yaml").read_text())
        edit_params(params)
        (dest / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    for command in (["git", "init", "-q"], ["git", "add", "-A"]):
        subprocess.run(command, cwd=dest, check=True)
    return dest


def run(
    copy: Path, *argv: str | Path, timeout: float | None = None
) -> subprocess.CompletedProcess[str]:
    """Run a command in ``copy`` with :func:`tool_env`; its output is captured as text."""
    return subprocess.run(
        [str(arg) for arg in argv],
        cwd=copy,
        env=tool_env(),
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def dvc(copy: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """``dvc ARGS`` in ``copy``, this environment's ``dvc``."""
    return run(copy, BIN / "dvc", *args)


# Names that are no names (docs/parameters.md, "Names"): each is a shell's words, another folder,
# an option, or more than one line wherever a family, task or experiment name goes.
HOSTILE_NAMES = [
    "pt;touch PWNED;echo",
    "$(touch PWNED)",
    "`touch PWNED`",
    "a'b",
    "..",
    ".",
    "../x",
    "a/b",
    "a.b",
    "my family",
    "",
    "x" * 65,
    "ünïcode",
    "-rf",
    "a\nb",
]

# A run's files that hold wall times, and run.json, which holds their SHA-256s.
WALL_TIMES = {"metrics.json", "eval.csv", "run.json"}


def untimed_run_json(path: Path) -> dict[str, Any]:
    """A run's ``run.json`` less the checksums of its files, which hold wall times."""
    record = json.loads(path.read_text())
    record.pop("sha256", None)
    return record


def train_record(copy: Path) -> dict[str, Any]:
    """What two trainings of the same runs on one machine agree on to the bit, from ``copy``'s
    ``dvc.lock``: each train stage's entry, the hashes of the files that hold wall times set
    aside, its ``eval.csv`` without the wall time (its last column) and its ``run.json``
    without the checksums."""
    lock = yaml.safe_load((copy / "dvc.lock").read_text())["stages"]
    entries = {name: entry for name, entry in lock.items() if name.startswith("train@")}
    returns, records = {}, {}
    for name, entry in entries.items():
        for out in entry["outs"]:
            if Path(out["path"]).name in WALL_TIMES:
                out.pop("md5"), out.pop("size")
            if Path(out["path"]).name == "eval.csv":
                lines = (copy / out["path"]).read_text().splitlines()
                returns[name] = [line.rsplit(",", 1)[0] for line in lines]
            if Path(out["path"]).name == "run.json":
                records[name] = untimed_run_json(copy / out["path"])
    return {"lock": entries, "returns": returns, "records": records}


def ok(result: subprocess.CompletedProcess[str]) -> str:
    """The output of a command that must have succeeded (stdout, then stderr); its end if not."""
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    return result.stdout + result.stderr


def one_task_upstream(dest: Path, shrink: Callable[[dict[str, Any]], None], task: str) -> Path:
    """A scratch copy at ``dest`` whose ``task``'s runs (1,000 steps, a checkpoint every 200:
    :func:`one_task_runs`) have their embedding made (``dvc repro task_inputs``) and no run yet."""
    copy = scratch_copy(dest, one_task_runs(shrink, task, steps=1_000, checkpoint_every=200))
    ok(dvc(copy, "repro", "task_inputs"))
    return copy


def one_task_runs(
    shrink: Callable[[dict[str, Any]], None], task: str, steps: int, checkpoint_every: int
) -> Callable[[dict[str, Any]], None]:
    """An edit of params for :func:`scratch_copy`: ``shrink``'s (e.g. the tiny pipeline), then the
    runs of ``task`` only, ``steps`` each with a checkpoint every ``checkpoint_every``: runs long
    enough to be caught between their first checkpoint and their end."""

    def edit(params: dict[str, Any]) -> None:
        shrink(params)
        params["td3"]["checkpoint_every"] = checkpoint_every
        params["runs"]["tasks"] = {task: params["runs"]["tasks"][task]}
        params["runs"]["budgets"] = {name: steps for name in params["runs"]["budgets"]}

    return edit


def add_step(
    buffer: Any,
    member: int,
    obs: Any,
    code: Any,
    i: int,
    reward: float,
    next_obs: Any,
    terminated: bool,
    truncated: bool,
) -> None:
    """One step of member ``member`` alone into an ``ede.method.replay.ReplayBuffer``, whose ``add`` takes
    a step of every member (rows of the others unused)."""
    import numpy as np
    import torch

    m = buffer.members
    rows = np.arange(m) == member

    def spread(value: Any, dtype: Any = None) -> np.ndarray:
        out = np.zeros((m, *np.shape(value)), dtype=dtype or np.asarray(value).dtype)
        out[member] = value
        return out

    codes = torch.zeros(m, *torch.as_tensor(code).shape)
    codes[member] = torch.as_tensor(code)
    buffer.add(
        rows,
        spread(obs, np.float64),
        codes,
        spread(i, np.int64),
        spread(reward, np.float64),
        spread(next_obs, np.float64),
        spread(terminated, bool),
        spread(truncated, bool),
    )


SEEDS, UPDATES = [3, 4], 12  # updated_agent's members, and its updates


def updated_agent(mode: str, device: str = "cpu", seeds: list[int] = SEEDS) -> tuple[Any, Any]:
    """An ``ede.method.agent.Agent`` of a member per seed (two: ``SEEDS``) at small sizes after
    ``UPDATES`` updates from its replay buffer of random steps, member 1 sitting every third out,
    its update compiled as ``td3.compile: mode`` says, and the buffer: the compiled update's tests
    compare these. Member 0's steps and updates are the same whatever the number of members."""
    import numpy as np
    import torch

    from ede.config import TD3Config
    from ede.method.adapters import IdentityAdapter
    from ede.method.agent import Agent
    from ede.method.replay import ReplayBuffer

    obs, act = 5, 2
    config = TD3Config.model_validate({"hidden": [32, 32], "batch_size": 16, "compile": mode})
    where = torch.device(device)
    agent = Agent(obs, IdentityAdapter(-np.ones(act), np.ones(act), where), config, where, seeds)
    buffer = ReplayBuffer(200, obs, act, 1, where, members=len(seeds))
    rng = np.random.default_rng(0)
    for member in range(len(seeds)):
        for t in range(100):
            add_step(
                buffer,
                member,
                rng.normal(size=obs),
                torch.as_tensor(rng.uniform(-1, 1, act)),
                0,
                float(rng.normal()),
                rng.normal(size=obs),
                t % 40 == 39,
                False,
            )
    for u in range(UPDATES):
        agent.update(buffer, np.array([True, u % 3 != 1])[: len(seeds)])  # member 1 sits some out
    return agent, buffer


def final_evaluation(run: Path, params: Path, episodes: int) -> list[float]:
    """The run's final evaluation (its ``episodes`` episodes, from their starts) replayed by its
    policy as ``ede-pipeline render`` rebuilds it (with ``params``), through
    :func:`ede.run.evaluation.evaluate` and without frames: each episode's return. Rendering,
    not playing, is what a video's episodes take time for."""
    from ede.analysis.policy import adapter_of, observation_size, policy_of, trained_embedding
    from ede.analysis.video import actor_of
    from ede.config import load_params
    from ede.run.evaluation import EVAL_SEED_OFFSET, evaluate
    from ede.run.vector import MemberEnvs
    from ede_pipeline import layout

    meta, tensors = policy_of(run)
    embedding = None
    if meta["algo"] == "ede-td3":
        where = layout.run_embedding(run, meta, load_params(params))
        embedding = trained_embedding(meta, *where)
    mu = actor_of(meta, tensors, observation_size(meta["task"]))
    envs = MemberEnvs.of_task(meta["task"], 1)
    start = EVAL_SEED_OFFSET * (int(meta["seed"]) + 1)
    adapter = adapter_of(meta, embedding)
    try:
        returns = evaluate(envs, lambda obs: mu(obs, obs), adapter, episodes, [start])
    finally:
        envs.vector.close()
    return [float(r) for r in returns[0]]
