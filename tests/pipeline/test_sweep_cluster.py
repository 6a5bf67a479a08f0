"""``sweep --executor ray`` on a real multi-node Ray cluster on this machine.

A head and worker nodes, each a Ray node of its own (``ray.cluster_utils.Cluster``: a raylet and
its workers per node, one GCS), and a sweep of two short runs (one reacher task, both algorithms,
1,000 steps, a checkpoint every 200) as the user starts it, in a subprocess joining the cluster:

- two worker nodes, a run on each; one node lost after its run's first checkpoint: Ray starts
  that run again on the node that remains (once its own run is done), it resumes from its
  checkpoint, and the sweep ends with both runs recorded and one retry counted — no second sweep;
- one worker node, and a run waiting for a CPU: a node that joins while the sweep runs takes it;
  then the sweep process is killed mid-run and started again, and it resumes what was left;

and in each case the runs' records (``dvc.lock`` entries and returns, wall times set aside) equal
those of ``dvc repro`` on this machine: on CPU a resumed run ends as an uninterrupted one.
The executor alone, on the same cluster, shows that only a lost run is started again: a command
that fails is reported once, as it ended.

A node is lost as a machine is: its raylet and every process under it (the workers, the runs'
commands) killed at once. SIGKILL of the raylet alone leaves its workers running: they finish the
task in hand and hand its result back, and nothing is lost.

The head runs no task (``num_cpus=0``), so each run lands on a worker node chosen by the test; the
GCS checks the nodes' health every half second (Ray's default: every 3 s, 5 missed), so a lost
node is known in about a second. The head also serves Ray Client (``ray://``), which the address
check must accept as it accepts the GCS.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import psutil
import pytest

from ede_pipeline import layout
from ede_pipeline.sweep.on_ray import RayExecutor, check_ray_address
from ede_pipeline.sweep.plan import Job
from tests.support import BIN, dvc, ok, tool_env, train_record

pytestmark = pytest.mark.slow

TASK = "ede/ReacherVertical-v0"
ALGOS = ("td3", "ede-td3")
STAGES = {algo: f"train@{TASK}-{algo}-0" for algo in ALGOS}
LOGS = Path(".dvc/tmp/sweep")  # the sweep's default --logs
WAIT = 120.0  # seconds any one awaited event may take before the test fails


@pytest.fixture(scope="module")
def undisturbed(reacher_reference: tuple[dict[str, Any], float]) -> dict[str, Any]:
    """The record of the same runs that nothing disturbs (``dvc repro``, one at a time, which a
    local sweep records too: tests/pipeline/test_sweep.py)."""
    return reacher_reference[0]


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture(scope="module")
def cluster() -> Iterator[Any]:
    """A head node with no CPU for tasks, serving Ray Client on ``cluster.client_port``.

    ``Cluster`` writes its address where ``ray.init()`` on this machine looks for a cluster to
    join (``/tmp/ray/ray_current_cluster``); the other tests start Ray instances of their own, so
    it writes nothing there (and so removes nothing there when it ends).
    """
    import ray._common.utils
    import ray._private.utils
    from ray.cluster_utils import Cluster

    client_port = free_port()
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(ray._private.utils, "write_ray_address", lambda *args, **kwargs: None)
        patch.setattr(ray._common.utils, "reset_ray_address", lambda *args, **kwargs: None)
        head = Cluster(
            initialize_head=True,
            head_node_args={
                "num_cpus": 0,
                "include_dashboard": False,
                "ray_client_server_port": client_port,
                "_system_config": {
                    "health_check_period_ms": 500,
                    "health_check_failure_threshold": 2,
                },
            },
        )
        head.client_port = client_port  # type: ignore[attr-defined]  # where tests find it
        try:
            yield head
        finally:
            head.shutdown()


@pytest.fixture
def add_node(cluster: Any) -> Iterator[Callable[[int], Any]]:
    """``add_node(cpus)``: a worker node joins the cluster; it leaves when the test ends."""
    nodes = []

    def add(cpus: int) -> Any:
        nodes.append(cluster.add_node(num_cpus=cpus))
        return nodes[-1]

    yield add
    for node in nodes:
        cluster.remove_node(node, allow_graceful=False)


def lose(node: Any) -> None:
    """The node gone as a machine goes: its raylet and every process under it, SIGKILL at once."""
    raylet = psutil.Process(node.all_processes["raylet"][0].process.pid)
    processes = [raylet, *raylet.children(recursive=True)]
    for process in processes:
        process.kill()
    psutil.wait_procs(processes, timeout=WAIT)


def wait_for(what: str, condition: Callable[[], bool]) -> None:
    deadline = time.monotonic() + WAIT
    while not condition():
        assert time.monotonic() < deadline, f"not within {WAIT:g} s: {what}"
        time.sleep(0.1)


def attempts(copy: Path, algo: str) -> list[str]:
    """Where each attempt of the run ran, as the sweep's attempts file says (a line each)."""
    name = (
        STAGES[algo].replace("/", "_").replace("@", "__")
    )  # the log's name, as the sweep makes it
    path = copy / LOGS / f"{name}.attempts"
    return path.read_text().splitlines() if path.is_file() else []


def on(node: Any) -> str:
    return f"Ray node {node.node_id}"


def checkpointed(copy: Path, algo: str) -> bool:
    return (copy / layout.run(TASK, algo, 0) / "checkpoint").is_dir()


def resumed_from(copy: Path, algo: str) -> int | None:
    """The step the run's last session started from (None: it ran from the start)."""
    return json.loads((copy / layout.run(TASK, algo, 0) / "metrics.json").read_text())[
        "resumed_from_step"
    ]


def start_sweep(copy: Path, cluster: Any, output: Path) -> subprocess.Popen[bytes]:
    with output.open("ab") as out:
        return subprocess.Popen(
            [
                BIN / "ede-pipeline",
                "sweep",
                "train",
                "--executor",
                "ray",
                "--address",
                cluster.address,
            ],
            cwd=copy,
            env=tool_env(),
            stdout=out,
            stderr=subprocess.STDOUT,
        )


def finished(sweep: subprocess.Popen[bytes], output: Path) -> str:
    try:
        sweep.wait(timeout=600)
    finally:
        if sweep.poll() is None:
            sweep.kill()
    text = output.read_text()
    assert sweep.returncode == 0, text[-4000:]
    return text


@pytest.fixture
def copy_of_upstream(reacher_upstream: Path, tmp_path: Path) -> Path:
    copy = tmp_path / "repo"
    shutil.copytree(reacher_upstream, copy, symlinks=True)
    return copy


def test_a_lost_node_costs_only_time(
    cluster: Any,
    add_node: Callable[[int], Any],
    copy_of_upstream: Path,
    undisturbed: dict[str, Any],
    tmp_path: Path,
) -> None:
    copy, output = copy_of_upstream, tmp_path / "sweep.out"
    nodes = [add_node(1), add_node(1)]  # a run on each
    sweep = start_sweep(copy, cluster, output)
    try:
        wait_for(
            "a run on each node",
            lambda: (
                sorted(line for algo in ALGOS for line in attempts(copy, algo))
                == sorted(map(on, nodes))
            ),
        )
        lost = next(algo for algo in ALGOS if attempts(copy, algo) == [on(nodes[0])])
        other = next(algo for algo in ALGOS if algo != lost)
        wait_for("the run on the first node writes a checkpoint", lambda: checkpointed(copy, lost))
        lose(nodes[0])
        out = finished(sweep, output)
    finally:
        if sweep.poll() is None:
            sweep.kill()

    # Started again on the node that remains, once that node's own run was done; resumed.
    assert attempts(copy, lost) == [on(nodes[0]), on(nodes[1])], out
    assert attempts(copy, other) == [on(nodes[1])], out
    assert (resumed_from(copy, lost) or 0) >= 200, "the lost run did not resume from its checkpoint"
    assert resumed_from(copy, other) is None
    assert (
        f"ok     {STAGES[lost]}" in out and "(attempt 2: 1 lost with a Ray worker or node)" in out
    )
    assert "sweep: 2 recorded, 0 failed" in out, out
    assert "sweep: 2/2 stages, 1 retry, " in out, out
    assert train_record(copy) == undisturbed
    assert "up to date" in ok(dvc(copy, "status", "train"))


def test_a_node_that_joins_is_used_and_a_killed_sweep_resumes(
    cluster: Any,
    add_node: Callable[[int], Any],
    copy_of_upstream: Path,
    undisturbed: dict[str, Any],
    tmp_path: Path,
) -> None:
    copy, output = copy_of_upstream, tmp_path / "sweep.out"
    first = add_node(1)  # one run at a time: the other waits for a node
    sweep = start_sweep(copy, cluster, output)
    try:
        wait_for(
            "a run starts on the first node",
            lambda: any(attempts(copy, algo) == [on(first)] for algo in ALGOS),
        )
        waiting = next(algo for algo in ALGOS if not attempts(copy, algo))
        joined = add_node(1)
        wait_for(
            "the waiting run starts on the node that joined",
            lambda: attempts(copy, waiting) == [on(joined)],
        )
        wait_for("it writes a checkpoint", lambda: checkpointed(copy, waiting))
        os.kill(sweep.pid, signal.SIGKILL)  # the sweep only: the runs are Ray's, on the nodes
        sweep.wait()
    finally:
        if sweep.poll() is None:
            sweep.kill()

    out = finished(start_sweep(copy, cluster, output), output)
    assert " recorded, 0 failed" in out.splitlines()[-1], out  # what the first left, recorded
    assert (resumed_from(copy, waiting) or 0) >= 200, out
    assert train_record(copy) == undisturbed
    assert "up to date" in ok(dvc(copy, "status", "train"))


def test_only_a_run_whose_worker_is_lost_is_started_again(
    cluster: Any,
    add_node: Callable[[int], Any],
    tmp_path: Path,
) -> None:
    """The executor alone, with commands that end as runs can: a command that fails is reported
    as it ended, once; a run whose worker dies (its command kills it) is started again, and its
    log keeps both attempts; one whose worker dies every time is lost after ``retries`` more."""
    import ray

    def job(name: str, command: str) -> Job:
        return Job(
            name, [["/bin/sh", "-c", command]], str(tmp_path), {}, str(tmp_path / f"{name}.log")
        )

    kill_worker = "kill -9 $PPID"  # the shell's parent: the Ray worker running the job
    second = f'[ "$(wc -l < {tmp_path / "lost-once.attempts"})" -ge 2 ]'
    jobs = [
        job("fails", "exit 3"),
        job("lost-once", f"{second} || {kill_worker}; echo done"),
        job("lost-always", kill_worker),
    ]
    node = add_node(3)
    try:
        outcomes = {
            outcome.stage: outcome
            for outcome in RayExecutor(cluster.address, 1, None, retries=1).map_unordered(jobs)
        }
    finally:
        ray.shutdown()

    assert (outcomes["fails"].returncode, outcomes["fails"].attempts) == (3, 1)
    assert (outcomes["lost-once"].returncode, outcomes["lost-once"].attempts) == (0, 2)
    log = (tmp_path / "lost-once.log").read_text()
    assert log.count(f"# attempt 1 on {on(node)}\n") == 1 and log.endswith(
        f"# attempt 2 on {on(node)}\n$ /bin/sh -c {jobs[1].argvs[0][2]}\ndone\n"
    ), log
    lost = outcomes["lost-always"]
    assert (lost.returncode, lost.attempts) == (None, 2), lost
    assert lost.error.startswith("WorkerCrashedError: "), lost


def test_the_cluster_is_accepted_at_its_gcs_and_its_ray_client_address(cluster: Any) -> None:
    host = cluster.address.rpartition(":")[0]
    check_ray_address(cluster.address)
    wait_for("the head serves Ray Client", lambda: _accepts(host, cluster.client_port))
    check_ray_address(f"ray://{host}:{cluster.client_port}")


def _accepts(host: str, port: int) -> bool:
    try:
        socket.create_connection((host, port), timeout=1).close()
    except OSError:
        return False
    return True
