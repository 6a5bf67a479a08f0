"""``ede-pipeline train``: learning, exact resume after SIGKILL, outputs and bad input."""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner, Result

from ede.io.provenance import code_version, machine, software_versions
from ede.run.evaluation import EVAL_SEED_OFFSET
from ede.tasks import make
from ede_pipeline.cli import main
from ede_pipeline.progress import PROGRESS_ENV, read_progress
from tests.support import REPO, final_evaluation

BUDGET = 3_000


def tiny(params: dict) -> None:
    params["collect"].update(steps=4_000, num_envs=1)
    for section in ("embedding", "decoder"):
        params[section].update(hidden=[64, 64], epochs=10, lr=1e-3)
    params["td3"].update(
        hidden=[64, 64],
        batch_size=64,
        start_steps=500,
        eval_every=500,
        eval_episodes=5,
        checkpoint_every=400,
    )
    params["runs"].update(
        tasks={"ede/Point-v0": "point", "ede/ReacherVertical-v0": "reacher"},
        seeds=[0],
        budgets={"ede/Point-v0": BUDGET, "ede/ReacherVertical-v0": 600},
    )


def run(*args: str) -> Result:
    return CliRunner().invoke(main, list(args))


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A working directory with tiny params and the point family's embedding."""
    import yaml

    from tests.support import REPO

    path = tmp_path_factory.mktemp("train")
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    tiny(params)
    (path / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    cwd = os.getcwd()
    os.chdir(path)
    try:
        for command in (
            ["collect", "--family", "point"],
            ["pretrain", "encoder", "--family", "point"],
            ["pretrain", "decoder", "--family", "point"],
        ):
            result = run(*command)
            assert result.exit_code == 0, result.output
    finally:
        os.chdir(cwd)
    return path


@pytest.fixture
def in_workdir(workdir: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.chdir(workdir)
    return workdir


def returns_of(path: Path) -> list[float]:
    with open(path / "eval.csv") as handle:
        return [float(row["mean_return"]) for row in csv.DictReader(handle)]


def random_policy_return(episodes: int = 5) -> float:
    env = make("ede/Point-v0")
    rng = np.random.default_rng(0)
    total = 0.0
    for e in range(episodes):
        env.reset(seed=EVAL_SEED_OFFSET + e)
        done = False
        while not done:
            _, reward, terminated, truncated, _ = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
            total += float(reward)
            done = terminated or truncated
    return total / episodes


@pytest.mark.parametrize("algo", ["td3", "ede-td3"])
def test_both_algorithms_clearly_beat_a_random_policy(in_workdir: Path, algo: str) -> None:
    code_version.cache_clear()  # read once a process: the checkout's HEAD of now
    result = run("train", "--task", "ede/Point-v0", "--algo", algo, "--seed", "0")
    assert result.exit_code == 0, result.output
    out = in_workdir / "data/runs/ede/Point-v0" / algo / "seed0"
    returns = returns_of(out)
    assert len(returns) == BUDGET // 500 + 1
    random_return = random_policy_return()
    # Random wandering scores about -130 here; reaching the goal and staying scores about -15.
    assert max(returns[-2:]) > 0.5 * random_return, (returns, random_return)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["final_return"] == returns[-1] and metrics["best_return"] == max(returns)
    assert "params" not in metrics  # the run's numbers only; what made it is run.json
    made = json.loads((out / "run.json").read_text())
    assert made["algo"] == algo and made["seed"] == 0 and made["budget"] == BUDGET
    assert made["software"] == software_versions()
    head = subprocess.run(
        ["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True, text=True, check=True
    ).stdout.strip()
    assert made["code"]["commit"] == head and isinstance(made["code"]["modified"], bool)
    assert made["machine"]["cpu"] == machine()["cpu"]
    assert made["machine"]["instruction_sets"] == machine()["instruction_sets"]
    assert made["update"] == "eager"  # td3.compile auto: 2,500 updates do not repay compiling
    assert "threads" not in made["params"]["td3"] and made["params"]["td3"]["tau"] == 0.005
    assert metrics["steps_per_second"] > 0
    policy = json.loads((out / "policy/policy.json").read_text())
    assert policy["k"] == (4 if algo == "ede-td3" else 1)
    assert not (out / "checkpoint").exists()  # removed once the run is complete


@pytest.fixture(params=["fp32", "bf16-matmul"])
def precision(request: pytest.FixtureRequest, in_workdir: Path) -> Iterator[str]:
    """The work directory's params with ``td3.precision`` set, restored afterwards."""
    params = in_workdir / "params.yaml"
    text = params.read_text()
    assert "precision: fp32" in text
    params.write_text(text.replace("precision: fp32", f"precision: {request.param}"))
    yield request.param
    params.write_text(text)


def test_a_run_killed_midway_resumes_to_the_same_returns(
    in_workdir: Path, precision: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    reference = in_workdir / f"reference-{precision}"
    result = run(
        "train",
        "--task",
        "ede/Point-v0",
        "--algo",
        "ede-td3",
        "--seed",
        "1",
        "--out",
        str(reference),
    )
    assert result.exit_code == 0, result.output

    killed = in_workdir / f"killed-{precision}"
    command = [
        sys.executable,
        "-m",
        "ede_pipeline",
        "train",
        "--task",
        "ede/Point-v0",
        "--algo",
        "ede-td3",
        "--seed",
        "1",
        "--out",
        str(killed),
    ]
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    # No short deadline: on a loaded machine the first checkpoint can take minutes to come.
    while not (killed / "checkpoint/state.json").exists() and process.poll() is None:
        time.sleep(0.05)
    time.sleep(0.7)  # somewhere after the first checkpoint, mid-way between two
    process.send_signal(signal.SIGKILL)
    process.wait()
    assert not (killed / "metrics.json").exists(), "the run finished before it was killed"
    state = json.loads((killed / "checkpoint/state.json").read_text())
    assert 0 < state["step"] < BUDGET

    published = in_workdir / f"resumed-{precision}.progress"  # where a sweep would read it
    monkeypatch.setenv(PROGRESS_ENV, str(published))
    resumed = run(
        "train", "--task", "ede/Point-v0", "--algo", "ede-td3", "--seed", "1", "--out", str(killed)
    )
    assert resumed.exit_code == 0, resumed.output
    assert read_progress(published) == (BUDGET, BUDGET, state["step"])  # its steps before: start
    assert returns_of(killed) == returns_of(reference)
    # and the training diagnostics, interval by interval, to the bit
    assert (killed / "diagnostics.csv").read_text() == (reference / "diagnostics.csv").read_text()
    assert len((reference / "diagnostics.csv").read_text().splitlines()) > 2
    metrics = json.loads((killed / "metrics.json").read_text())
    assert metrics["resumed_from_step"] == state["step"]
    # Its rate over the whole run: both sessions' walls (the first's as its checkpoint carried
    # it), at least the wall its last evaluation recorded; a run never resumed has one rate.
    whole = BUDGET / metrics["whole_run_steps_per_second"]
    session = (BUDGET - state["step"]) / metrics["steps_per_second"]
    assert state["wall_seconds"] > 0 and whole == pytest.approx(state["wall_seconds"] + session)
    with open(killed / "eval.csv", newline="") as handle:
        assert whole >= float(list(csv.DictReader(handle))[-1]["wall_seconds"]) - 0.001
    alone = json.loads((reference / "metrics.json").read_text())
    assert alone["whole_run_steps_per_second"] == alone["steps_per_second"]
    assert json.loads((killed / "run.json").read_text())["params"]["td3"]["precision"] == precision


def test_a_checkpoint_of_other_params_is_moved_aside_not_resumed(in_workdir: Path) -> None:
    out = in_workdir / "other"
    assert (
        run(
            "train",
            "--task",
            "ede/ReacherVertical-v0",
            "--algo",
            "td3",
            "--seed",
            "0",
            "--out",
            str(out),
            "--keep-checkpoint",
        ).exit_code
        == 0
    )
    params = in_workdir / "params.yaml"
    text = params.read_text()
    params.write_text(text.replace("discount: 0.99", "discount: 0.98"))
    try:
        result = run(
            "train",
            "--task",
            "ede/ReacherVertical-v0",
            "--algo",
            "td3",
            "--seed",
            "0",
            "--out",
            str(out),
        )
    finally:
        params.write_text(text)
    assert result.exit_code == 0
    assert json.loads((out / "metrics.json").read_text())["resumed_from_step"] is None
    assert (
        "another run's: made with td3.discount = 0.99, but the params say 0.98; moved aside to checkpoint.bad-"
        in result.stderr
    )
    assert len(list(out.glob("checkpoint.bad-*/state.json"))) == 1


def bad(result: Result, message: str) -> None:
    assert result.exit_code == 2, result.output
    assert result.stderr.count("\n") == 1 and message in result.stderr, result.stderr
    assert "Traceback" not in result.output


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--task", "ede/Nope-v0", "--algo", "td3", "--seed", "0"], "--task 'ede/Nope-v0': not in"),
        (["--task", "ede/Point-v0", "--algo", "ddpg", "--seed", "0"], "--algo 'ddpg': unknown"),
        (["--task", "ede/Point-v0", "--algo", "td3", "--seed", "-3"], "--seed -3: expected"),
        (["--task", "ede/Point-v0", "--algo", "td3", "--seeds", "1,1"], "expected distinct seeds"),
        (
            ["--task", "ede/Point-v0", "--algo", "td3", "--seeds", "a-b"],
            "expected a seed, a list (0,1,2) or a range (0-3)",
        ),
        (
            ["--task", "ede/Point-v0", "--algo", "td3", "--seeds", "0-1"],
            "several seeds need a pattern with {seed}",
        ),
        (
            ["--task", "ede/ReacherVertical-v0", "--algo", "ede-td3", "--seed", "0"],
            "needs the reacher family's embedding",
        ),
        (
            [
                "--task",
                "ede/ReacherVertical-v0",
                "--algo",
                "ede-td3",
                "--seed",
                "0",
                "--encoder",
                "data/families/point/embedding/encoder",
                "--decoder",
                "data/families/point/embedding/decoder",
            ],
            "the embedding of family point, but ede/ReacherVertical-v0 is in family reacher",
        ),
    ],
)
def test_bad_train_input_is_one_line_exit_2_and_writes_nothing(
    in_workdir: Path, args: list[str], message: str
) -> None:
    out = in_workdir / "bad-run"
    bad(run("train", *args, "--out", str(out)), message)
    assert not out.exists()


def test_a_compiled_update_asked_for_where_no_compiler_is_is_refused_in_one_line(
    in_workdir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    params = in_workdir / "params.yaml"
    text = params.read_text()
    assert "  compile: auto" in text
    params.write_text(text.replace("  compile: auto", "  compile: default"))
    monkeypatch.setenv("CXX", "/nonexistent/c++")
    out = in_workdir / "no-compiler"
    try:
        result = run(
            "train", "--task", "ede/Point-v0", "--algo", "td3", "--seed", "0", "--out", str(out)
        )
    finally:
        params.write_text(text)
    bad(
        result,
        "td3.compile: default needs a C++ compiler (/nonexistent/c++, or $CXX), which this "
        "machine lacks; set td3.compile to auto (compiled where it can be) or none",
    )
    assert not out.exists()


@pytest.mark.parametrize(
    "command",
    [
        ["train", "--task", "ede/Point-v0", "--algo", "ede-td3", "--seed", "0", "--out", "k2-run"],
        ["pretrain", "decoder", "--family", "point", "--out", "k2-decoder"],
    ],
)
def test_an_embedding_made_with_other_params_is_refused_by_name(
    in_workdir: Path, command: list[str]
) -> None:
    import yaml

    params = yaml.safe_load((in_workdir / "params.yaml").read_text())
    params["embedding"]["k"] = 2
    (in_workdir / "params-k2.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    bad(
        run(*command, "--params", "params-k2.yaml"),
        "made with embedding.k = 4, but params.yaml has embedding.k = 2",
    )
    assert not (in_workdir / command[command.index("--out") + 1]).exists()


def test_several_seeds_train_in_one_process_each_as_it_trains_alone(in_workdir: Path) -> None:
    task = ["--task", "ede/ReacherVertical-v0", "--algo", "td3"]  # per-episode batches
    group = run("train", *task, "--seeds", "0-1", "--out", "group/seed{seed}")
    assert group.exit_code == 0, group.output
    alone = run("train", *task, "--seed", "1", "--out", "alone1")
    assert alone.exit_code == 0, alone.output
    assert [
        line.rsplit(",", 1)[0]
        for line in (in_workdir / "group/seed1/eval.csv").read_text().splitlines()
    ] == [
        line.rsplit(",", 1)[0] for line in (in_workdir / "alone1/eval.csv").read_text().splitlines()
    ]
    assert (in_workdir / "group/seed0/metrics.json").is_file()


@pytest.mark.parametrize("algo", ["td3", "ede-td3"])
def test_a_run_that_diverges_fails_in_one_line_without_metrics(in_workdir: Path, algo: str) -> None:
    import yaml

    params = yaml.safe_load((in_workdir / "params.yaml").read_text())
    params["td3"]["lr"] = 1.0e30
    (in_workdir / "params-lr.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    out = in_workdir / f"diverging-{algo}"
    result = run(
        "train",
        "--task",
        "ede/Point-v0",
        "--algo",
        algo,
        "--seed",
        "0",
        "--out",
        str(out),
        "--params",
        "params-lr.yaml",
    )
    assert result.exit_code == 1 and result.exception is not None  # click's exit, no traceback
    lines = [line for line in result.stderr.splitlines() if line.startswith("Error: ")]
    assert len(lines) == 1, result.stderr  # beside the progress line
    assert lines[0].startswith(f"Error: ede/Point-v0 {algo} seed 0: diverged at step 50")  # 500-599
    assert lines[0].endswith(f"its last checkpoint, {out / 'checkpoint'}, is at step 400")
    assert "Traceback" not in result.output
    assert not (out / "metrics.json").exists()


def test_through_embedding_rebuilds_the_final_actor_and_runs_it_through_the_embedding(
    in_workdir: Path,
) -> None:
    """benchmarks/through_embedding.py: its actor, rebuilt from policy/, replays the run's own
    last evaluation; through the point embedding it still acts; bad --data is one line, exit 2."""
    from tests.support import REPO

    if not (in_workdir / "data/runs/ede/Point-v0/td3/seed0/metrics.json").exists():
        assert run("train", "--task", "ede/Point-v0", "--algo", "td3", "--seed", "0").exit_code == 0
    script = [
        sys.executable,
        str(REPO / "benchmarks/through_embedding.py"),
        "--task",
        "ede/Point-v0",
        "--family",
        "point",
        "--episodes",
        "5",
    ]
    done = subprocess.run([*script, "--data", "data"], capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    line = done.stdout.splitlines()[-1]
    as_is, last, through = (
        float(line.split(word)[1].split()[0].rstrip(";,"))
        for word in ("as is", "last evaluation", "through the embedding")
    )
    # Training evaluates the stacked actor, the script a plain nn.Sequential: other kernels, the
    # same weights; on a point mass over 100 steps their returns agree far inside 0.01.
    assert abs(as_is - last) < 0.01, line
    assert np.isfinite(through) and "of its codes clipped to the box" in line
    missing = subprocess.run(
        [*script, "--data", "nowhere"], capture_output=True, text=True, check=False
    )
    assert missing.returncode == 2 and missing.stderr.count("\n") == 1, missing.stderr
    assert "nowhere: expected families/point/embedding/" in missing.stderr
    assert "Traceback" not in missing.stderr


def test_a_groups_memory_estimate_is_what_its_replay_buffer_and_networks_hold() -> None:
    import torch

    from ede.config import TD3Config
    from ede.method.adapters import IdentityAdapter
    from ede.method.agent import Agent
    from ede.method.replay import ReplayBuffer
    from ede_pipeline.train import group_memory

    obs, code, members, capacity, cpu = 7, 3, 5, 300, torch.device("cpu")
    buffer = ReplayBuffer(capacity, obs, code, 4, cpu, members)
    stored = sum(getattr(buffer, name).nbytes for name in ReplayBuffer.FIELDS)
    assert group_memory(members, capacity, obs, code, []) == stored  # the buffer: exactly

    config = TD3Config.model_validate({"hidden": [64, 64]})
    adapter = IdentityAdapter(-np.ones(code), np.ones(code), cpu)
    agent = Agent(obs, adapter, config, cpu, seeds=range(members))
    stacks = [agent.actor, agent.actor_target, agent.critic, agent.critic_target]
    parts = [*stacks, agent.actor_adam, agent.critic_adam]  # an Adam holds its stack too: once
    held = stored + sum({t.data_ptr(): t.nbytes for p in parts for t in p.buffers()}.values())
    critic = agent.td3.critic.sizes
    estimate = group_memory(members, capacity, obs, code, [agent.td3.actor.sizes, critic, critic])
    # At least what the group holds, and at most a quarter more: the estimate counts a gradient of
    # each network too, which lives only during an update (5 copies against 4 held), and not the
    # padding of a network's row to 32 floats (here under 1%).
    assert held <= estimate <= 1.25 * held, (held, estimate)


class _Trained(Exception):
    """Raised in place of training: the command got past every check."""


def _no_training(*args: object, **kwargs: object) -> list:
    raise _Trained


def test_a_group_too_big_for_the_memory_is_refused_in_one_line_before_any_work(
    write_params, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def huge(params: dict) -> None:  # 4096 runs of 10M steps: over 2 TB of replay buffers
        params["td3"]["buffer_size"] = 10_000_000
        params["runs"].update(tasks={"ede/Point-v0": "point"}, budgets={"ede/Point-v0": 10**7})

    path = write_params(huge)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("ede_pipeline.train.train_group", _no_training)
    start = time.perf_counter()
    result = run(
        "train", "--params", str(path), "--task", "ede/Point-v0", "--algo", "td3",
        "--seeds", "0-4095", "--out", "runs/seed{seed}",
    )  # fmt: skip
    assert time.perf_counter() - start < 30
    bad(result, "--seed 0-4095: td3 on ede/Point-v0 for 4096 seeds in one process needs about ")
    assert (
        "(replay buffers, networks, activations and environments), more than 80% of the "
        in result.stderr
    )
    assert "GiB of memory available; train at most " in result.stderr
    assert [p.name for p in tmp_path.iterdir()] == [path.name]


@pytest.mark.parametrize(
    ("algo", "free", "message"),
    [
        ("td3", 10**15, None),
        (
            "td3",
            5 * 2**20,
            "more than 80% of the 5.0 MiB of memory; train at most 1 seed per process",
        ),
        (
            "ede-td3",
            3 * 2**20,
            "more than 80% of the 3.0 MiB of memory; not one run fits: lower td3.buffer_size",
        ),
    ],
)
def test_a_group_is_refused_only_when_its_estimate_exceeds_the_free_memory(
    write_params,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    algo: str,
    free: int,
    message: str | None,
) -> None:
    path = write_params(tiny)  # runs of 3,000 steps: about 2.7 MiB each, 2 of them environments
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("ede_pipeline.train.train_group", _no_training)
    monkeypatch.setattr("ede_pipeline.train.free_memory", lambda device: (free, "of memory"))
    result = run(
        "train", "--params", str(path), "--task", "ede/Point-v0", "--algo", algo,
        "--seeds", "0,1", "--out", "runs/seed{seed}",
    )  # fmt: skip
    if message is None:
        assert isinstance(result.exception, _Trained), result.output
    else:
        bad(result, f"--seed 0,1: {algo} on ede/Point-v0 for 2 seeds in one process needs about ")
        assert message in result.stderr
        assert [p.name for p in tmp_path.iterdir()] == [path.name]


def test_a_groups_memory_is_compared_with_the_memory_where_its_tensors_go(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import psutil
    import torch

    from ede_pipeline.train import free_memory

    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device: (123, 456))
    assert free_memory(torch.device("cuda:0")) == (123, "free on cuda:0")
    free, where = free_memory(torch.device("cpu"))
    assert where == "of memory available"
    assert abs(free - psutil.virtual_memory().available) < 2**30  # read again: it moves a little


# What a group's updates add to the memory of a process that holds its agent and replay buffer:
# the peak resident size while they run (Linux's VmHWM, reset just before them by writing 5 to
# /proc/self/clear_refs) less the resident size before, so that the peak of the imports, which a
# machine's libraries set and which may be the higher, does not hide it. glibc's allocator runs
# with a fixed mmap threshold: by default it raises the threshold as large blocks are freed and
# then keeps what the next ones free in its heap, so the same updates peaked 195 to 333 MB from
# run to run; with every block above 64 KiB a mapping of its own, returned when freed, the peak is
# the tensors' own: 161 MB on every run, with MKL, oneDNN and ATen held to AVX2 or SSE4.2 alike.
PEAK = """
import re, sys
from pathlib import Path
import numpy as np, torch
from ede.config import TD3Config
from ede.method.agent import Agent
from ede.method.adapters import IdentityAdapter
from ede.method.replay import ReplayBuffer
torch.set_num_threads(1)
members, batch, obs, code, cpu = 4, int(sys.argv[1]), 11, 2, torch.device("cpu")
config = TD3Config.model_validate({"hidden": [400, 300], "batch_size": batch})
agent = Agent(obs, IdentityAdapter(-np.ones(code), np.ones(code), cpu), config, cpu, range(members))
buffer = ReplayBuffer(4_000, obs, code, 1, cpu, members)
every, rows = np.ones(members, bool), np.zeros((members, obs), np.float32)
zeros = np.zeros(members)
for _ in range(4_000):
    buffer.add(every, rows, torch.zeros(members, code), zeros.astype(np.int64), zeros, rows,
               zeros.astype(bool), zeros.astype(bool))
def status(key):
    return int(re.search(rf"{key}:\\s+(\\d+) kB", Path("/proc/self/status").read_text())[1]) * 1024
before = status("VmRSS")
Path("/proc/self/clear_refs").write_text("5")
for _ in range(3):
    agent.update(buffer)
print(status("VmHWM") - before)
"""


def test_a_groups_estimate_bounds_what_an_updates_activations_add() -> None:
    from ede.method.td3 import Critic
    from ede_pipeline.train import group_memory

    def peak(batch: int) -> int:
        done = subprocess.run(
            [sys.executable, "-c", PEAK, str(batch)],
            env={**os.environ, "MALLOC_MMAP_THRESHOLD_": str(64 * 1024)},
            capture_output=True,
            text=True,
            check=True,
        )
        return int(done.stdout)

    critic = Critic(11, 2, 1, [400, 300], "onehot", 1).sizes
    networks = [[11, 400, 300, 2], critic, critic]

    def estimate(batch: int) -> int:
        return group_memory(4, 4_000, 11, 2, networks, batch)

    measured, counted = peak(4_000) - peak(100), estimate(4_000) - estimate(100)
    # Counted: at least what the update adds, and not more than three times it.
    assert measured <= counted <= 3 * measured, (measured, counted)


def test_a_groups_environments_are_counted_as_they_are_held() -> None:
    """With workers, each environment is a process: its own memory (USS) is what the estimate
    counts, at most, and not far below."""
    import psutil
    from gymnasium.vector import AsyncVectorEnv

    from ede.run.vector import MemberEnvs
    from ede_pipeline.train import ENVS_PER_MEMBER, WORKER_BYTES, environment_memory

    assert environment_memory(3, workers=True) == 3 * ENVS_PER_MEMBER * WORKER_BYTES
    envs = MemberEnvs.of_task("ede/Pusher-v0", 2, workers=True)
    try:
        envs.reset(np.ones(2, dtype=bool), [0, 1])
        assert isinstance(envs.vector, AsyncVectorEnv)
        own = [psutil.Process(p.pid).memory_full_info().uss for p in envs.vector.processes]
    finally:
        envs.close()
    assert len(own) == 2 and all(WORKER_BYTES / 2 < uss <= WORKER_BYTES for uss in own), own


def test_a_gpu_groups_environments_are_weighed_against_the_hosts_memory(
    write_params, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import torch

    def workers(params: dict) -> None:
        tiny(params)
        params["td3"].update(env_workers="yes", device="cuda")

    path = write_params(workers)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("ede_pipeline.train.train_group", _no_training)
    monkeypatch.setattr("ede_pipeline.train.pick_device", lambda setting: torch.device("cuda"))
    memory = {"cuda": (10**15, "free on cuda"), "cpu": (2 * 2**30, "of memory available")}
    monkeypatch.setattr("ede_pipeline.train.free_memory", lambda device: memory[device.type])
    result = run(
        "train", "--params", str(path), "--task", "ede/Point-v0", "--algo", "td3",
        "--seeds", "0-31", "--out", "runs/seed{seed}",
    )  # fmt: skip
    bad(result, "--seed 0-31: td3 on ede/Point-v0 for 32 seeds in one process needs about 3.8 GiB ")
    assert (
        "(environments), more than 80% of the 2.0 GiB of memory available; train at most 13 "
        in (result.stderr)
    )
    assert [p.name for p in tmp_path.iterdir()] == [path.name]


def trained(workdir: Path, algo: str) -> Path:
    """The Point run of ``algo``, seed 0, trained here unless an earlier test did."""
    out = workdir / "data/runs/ede/Point-v0" / algo / "seed0"
    if not (out / "metrics.json").exists():
        done = run("train", "--task", "ede/Point-v0", "--algo", algo, "--seed", "0")
        assert done.exit_code == 0, done.output
    return out


@pytest.mark.parametrize("algo", ["td3", "ede-td3"])
def test_render_plays_the_final_policy_as_its_last_evaluation(in_workdir: Path, algo: str) -> None:
    import imageio.v3 as iio

    out = trained(in_workdir, algo)
    done = run("render", str(out), "--out", f"videos/{algo}.mp4")
    assert done.exit_code == 0, done.output
    video = iio.imread(in_workdir / f"videos/{algo}.mp4", plugin="FFMPEG", index=None)
    assert video.shape == (100, 480, 480, 3)  # an episode of ede/Point-v0's 100 steps
    scene = video[:, 16:-24].astype(np.int16)  # between the code mark and the written line
    assert scene[0].std() > 10  # not blank
    assert np.abs(scene[0] - scene[50]).max() > 50  # the point has moved
    # EDE-TD3's frames carry a bar along the top where each code starts (every 4 steps): the
    # mark's orange there, the scene's own colours on the steps between (compression: within 40).
    top = video[:12, :4].reshape(12, -1, 3).mean(axis=1)
    marked = np.abs(top - np.array([255, 196, 0])).max(axis=1) < 40
    assert list(marked) == ([True, False, False, False] * 3 if algo == "ede-td3" else [False] * 12)
    # Episodes one after another, at half size: the GIF (every other frame; a quarter of the
    # full size's rendering).
    small = run("render", str(out), "--episodes", "2", "--out", f"videos/{algo}.gif")
    assert small.exit_code == 0, small.output
    clip = iio.imread(in_workdir / f"videos/{algo}.gif", index=None)[..., :3]
    assert clip.shape[:3] == (2 * 50, 240, 240)
    # The same starts as the run's final evaluation: the same returns as its first 2 episodes,
    # from the actor rebuilt out of policy/ (other kernels than training's stacked one: within
    # 0.01), at either size. Rendering, not playing, is what takes time: the 5 are replayed
    # without frames.
    evaluation = final_evaluation(out, in_workdir / "params.yaml", 5)
    assert abs(np.mean(evaluation) - returns_of(out)[-1]) < 0.01, (evaluation, returns_of(out))
    for played_, episodes in ((done, 1), (small, 2)):
        text = played_.output.split("; returns ")[1].split(" (mean")[0]
        played = [float(r) for r in text.split(", ")]
        assert np.allclose(played, evaluation[:episodes], rtol=0, atol=0.01), (text, evaluation)
    # One palette for the whole GIF keeps the mark's orange (every other GIF frame starts a code).
    top = clip[:6, :2].reshape(6, -1, 3).mean(axis=1)
    marked = np.abs(top - np.array([255, 196, 0])).max(axis=1) < 40
    assert list(marked) == ([True, False] * 3 if algo == "ede-td3" else [False] * 6)


def test_render_refuses_what_it_cannot_play_in_one_line_and_writes_nothing(
    in_workdir: Path, tmp_path: Path
) -> None:
    import shutil

    out = trained(in_workdir, "td3")
    published = tmp_path / "published"  # a run as docs/results/runs keeps it: no policy
    shutil.copytree(out, published, ignore=shutil.ignore_patterns("policy"))
    damaged = tmp_path / "damaged"
    shutil.copytree(out, damaged)
    (damaged / "policy/policy.safetensors").write_bytes(b"\0" * 64)
    elsewhere = tmp_path / "elsewhere"  # its policy names a task that cannot be made
    shutil.copytree(out, elsewhere)
    (elsewhere / "run.json").unlink()  # (so that no checksum stops it first)
    policy = json.loads((elsewhere / "policy/policy.json").read_text())
    (elsewhere / "policy/policy.json").write_text(json.dumps({**policy, "task": "Nowhere-v0"}))
    ede = trained(in_workdir, "ede-td3")
    cases = [
        ([str(published)], "no final policy (policy.safetensors and policy.json missing)"),
        ([str(damaged)], "policy.safetensors: not the file its run wrote"),
        ([str(elsewhere)], "Nowhere-v0: cannot be made to render"),
        ([str(out), "--out", "videos/x.avi"], "expected a file ending in .mp4 or .gif"),
        ([str(ede), "--decoder", "nowhere"], "nowhere"),
    ]
    for args, said in cases:
        done = run("render", *args, "--out", "videos/bad.mp4") if "--out" not in args else None
        done = done or run("render", *args)
        assert done.exit_code == 2, (args, done.output)
        assert said in done.output and done.output.count("\n") == 1, done.output
    assert (
        not (in_workdir / "videos/bad.mp4").exists() and not (in_workdir / "videos/x.avi").exists()
    )
    no_gl = subprocess.run(
        [
            sys.executable,
            "-m",
            "ede_pipeline",
            "render",
            str(out),
            "--out",
            str(tmp_path / "x.mp4"),
        ],
        env={**os.environ, "MUJOCO_GL": "disable"},
        cwd=in_workdir,
        capture_output=True,
        text=True,
        check=False,
    )
    assert no_gl.returncode == 1 and no_gl.stderr.count("\n") == 1, no_gl.stderr
    assert "MUJOCO_GL=disable: videos render offscreen" in no_gl.stderr
    assert not (tmp_path / "x.mp4").exists()


# Stable-baselines3's arms (ede/run/sb3.py) -------------------------------------------------------

SB3_BUDGET = 600
SB3 = ["sb3-td3-ede", "sb3-sac-ede", "sb3-sac"]


@pytest.fixture
def sb3_params(in_workdir: Path) -> Iterator[str]:
    """The work directory's params with networks and evaluations small enough for SB3's arms on
    ede/Point-v0 at a budget of 600 steps; torch on one thread (on a busy machine more threads
    only wait for each other)."""
    import torch
    import yaml

    params = yaml.safe_load((in_workdir / "params.yaml").read_text())
    params["td3"].update(
        hidden=[16, 16], batch_size=16, start_steps=40, eval_every=200, eval_episodes=2,
        checkpoint_every=200, update_schedule="step",
    )  # fmt: skip
    params["runs"]["budgets"]["ede/Point-v0"] = SB3_BUDGET
    params["runs"]["algos"] = ["td3", "ede-td3", *SB3]
    (in_workdir / "params-sb3.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield "params-sb3.yaml"
    torch.set_num_threads(threads)


def sb3_train(params: str, algo: str, out: Path, *more: str) -> Result:
    task = ["--task", "ede/Point-v0", "--algo", algo, "--seed", "0"]
    return run("train", *task, "--out", str(out), "--params", params, *more)


@pytest.mark.parametrize("algo", SB3)
def test_a_stable_baselines3_arm_trains_into_a_complete_run_folder(
    in_workdir: Path, sb3_params: str, algo: str
) -> None:
    from ede.run.artifacts import load_action_embedding
    from ede.run.runs import read_policy, read_run

    out = in_workdir / f"sb3/{algo}"
    result = sb3_train(sb3_params, algo, out)
    assert result.exit_code == 0, result.output
    made = json.loads((out / "run.json").read_text())
    meta, _ = load_action_embedding(None, in_workdir / "data/families/point/embedding/decoder")
    embedding = meta.identity if algo != "sb3-sac" else ""
    run_ = read_run(out, {"algo": algo, "budget": SB3_BUDGET, "embedding": embedding})
    assert run_ is not None  # finished, its checksums and eval.csv's steps as every run's
    # raw environment steps, never codes: the same rows as TD3's and EDE-TD3's
    assert list(run_.curve.steps) == [0, 200, 400, 600]
    assert made["software"]["stable-baselines3"] and made["machine"]["cpu"] == machine()["cpu"]
    policy, tensors = read_policy(out)
    assert policy["k"] == (1 if algo == "sb3-sac" else 4) and tensors
    diagnostics = run_.diagnostics
    assert diagnostics is not None and diagnostics["updates"].sum() > 0
    assert not (out / "checkpoint").exists()
    video = in_workdir / f"sb3-{algo}.gif"
    bad(run("render", str(out), "--out", str(video)), "not stable-baselines3's actors")
    assert not video.exists()


def test_an_ede_space_arm_makes_one_update_per_raw_step(in_workdir: Path, sb3_params: str) -> None:
    import yaml

    from ede.config import Params
    from ede.run.artifacts import load_action_embedding
    from ede.run.sb3 import _Run
    from ede.run.spec import RunSpec

    params = Params.model_validate(yaml.safe_load((in_workdir / sb3_params).read_text()))
    _, embedding = load_action_embedding(None, in_workdir / "data/families/point/embedding/decoder")
    spec = RunSpec("ede/Point-v0", "sb3-sac-ede", 0, SB3_BUDGET, params.td3, params.ede_td3)
    run_ = _Run(spec, embedding)
    try:
        counted = []
        while run_.steps.steps < 300:
            steps, updates = run_.steps.steps, run_.model._n_updates
            run_._code()
            counted.append((run_.steps.steps - steps, run_.model._n_updates - updates))
    finally:
        run_.close()
    learning = [pair for pair in counted if pair[1]]
    assert len(learning) > 10 and all(ran == updates for ran, updates in learning)
    assert {ran for ran, _ in counted} >= {4}  # a code is k = 4 raw steps


@pytest.mark.parametrize("algo", SB3)
def test_a_stable_baselines3_run_killed_midway_resumes_to_the_same_returns(
    in_workdir: Path, sb3_params: str, algo: str
) -> None:
    reference = in_workdir / f"sb3-reference/{algo}"
    assert sb3_train(sb3_params, algo, reference).exit_code == 0
    killed = in_workdir / f"sb3-killed/{algo}"
    command = [sys.executable, "-m", "ede_pipeline", "train", "--task", "ede/Point-v0",
               "--algo", algo, "--seed", "0", "--out", str(killed), "--params", sb3_params]  # fmt: skip
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    while not (killed / "checkpoint/state.json").exists() and process.poll() is None:
        time.sleep(0.02)
    process.send_signal(signal.SIGKILL)
    process.wait()
    assert not (killed / "metrics.json").exists(), "the run finished before it was killed"
    step = json.loads((killed / "checkpoint/state.json").read_text())["step"]
    assert 0 < step < SB3_BUDGET
    resumed = sb3_train(sb3_params, algo, killed)
    assert resumed.exit_code == 0, resumed.output
    assert returns_of(killed) == returns_of(reference)
    assert (killed / "diagnostics.csv").read_text() == (reference / "diagnostics.csv").read_text()
    assert json.loads((killed / "metrics.json").read_text())["resumed_from_step"] == step


def test_a_damaged_or_other_stable_baselines3_checkpoint_is_refused_or_moved_aside(
    in_workdir: Path, sb3_params: str
) -> None:
    out = in_workdir / "sb3-damaged"
    assert sb3_train(sb3_params, "sb3-sac", out, "--keep-checkpoint").exit_code == 0
    (out / "metrics.json").unlink()  # as if killed after its last checkpoint
    tensors = out / "checkpoint/state.safetensors"
    data = bytearray(tensors.read_bytes())
    data[-1] ^= 1
    tensors.write_bytes(bytes(data))
    eval_csv = (out / "eval.csv").read_text()
    bad(
        sb3_train(sb3_params, "sb3-sac", out, "--bad-checkpoint", "refuse"),
        "state.safetensors does not match its checksum (damaged or changed) (--bad-checkpoint refuse)",
    )
    assert (out / "eval.csv").read_text() == eval_csv and not (out / "metrics.json").exists()
    restarted = sb3_train(sb3_params, "sb3-sac", out)
    assert restarted.exit_code == 0, restarted.output
    assert "moved aside to checkpoint.bad-" in restarted.stderr
    assert json.loads((out / "metrics.json").read_text())["resumed_from_step"] is None
    # a checkpoint of another arm's run is another run's
    other = in_workdir / "sb3-other"
    assert sb3_train(sb3_params, "sb3-sac-ede", other, "--keep-checkpoint").exit_code == 0
    (out / "metrics.json").unlink()
    shutil.rmtree(out / "checkpoint", ignore_errors=True)
    shutil.copytree(other / "checkpoint", out / "checkpoint")
    bad(sb3_train(sb3_params, "sb3-sac", out, "--bad-checkpoint", "refuse"), "another run's")


def test_an_sb3_arm_refuses_an_embedding_of_other_params(in_workdir: Path, sb3_params: str) -> None:
    import yaml

    params = yaml.safe_load((in_workdir / sb3_params).read_text())
    params["embedding"]["k"] = 2
    (in_workdir / "params-sb3-k2.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    out = in_workdir / "sb3-k2"
    bad(
        sb3_train("params-sb3-k2.yaml", "sb3-td3-ede", out),
        "made with embedding.k = 4, but params.yaml has embedding.k = 2",
    )
    assert not out.exists()


def test_several_seeds_of_an_sb3_arm_train_one_after_another_each_as_alone(
    in_workdir: Path, sb3_params: str
) -> None:
    task = ["--task", "ede/Point-v0", "--algo", "sb3-td3-ede", "--params", sb3_params]
    group = run("train", *task, "--seeds", "1-2", "--out", "sb3-seeds/seed{seed}")
    assert group.exit_code == 0, group.output
    alone = run("train", *task, "--seed", "2", "--out", "sb3-seeds/alone")
    assert alone.exit_code == 0, alone.output
    assert returns_of(in_workdir / "sb3-seeds/seed2") == returns_of(in_workdir / "sb3-seeds/alone")
    assert returns_of(in_workdir / "sb3-seeds/seed1") != returns_of(in_workdir / "sb3-seeds/alone")


@pytest.mark.parametrize("algo", ["sb3-td3-ede", "sb3-sac"])
def test_an_sb3_run_that_diverges_fails_in_one_line_without_metrics(
    in_workdir: Path, sb3_params: str, algo: str
) -> None:
    import yaml

    params = yaml.safe_load((in_workdir / sb3_params).read_text())
    params["td3"]["lr"] = 1.0e30
    (in_workdir / "params-sb3-lr.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    out = in_workdir / f"sb3-diverging-{algo}"
    result = sb3_train("params-sb3-lr.yaml", algo, out)
    assert result.exit_code == 1 and result.exception is not None  # click's exit, no traceback
    lines = [line for line in result.stderr.splitlines() if line.startswith("Error: ")]
    assert len(lines) == 1, repr(result.exception)  # beside the progress line
    assert lines[0].startswith(f"Error: ede/Point-v0 {algo} seed 0: diverged at step"), lines
    assert "Traceback" not in result.output
    assert not (out / "metrics.json").exists()
