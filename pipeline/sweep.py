"""``ede-pipeline sweep``: the out-of-date train stages of ``dvc.yaml``, run in parallel, recorded by DVC.

``dvc repro`` runs one stage at a time, and two ``dvc repro`` processes in one checkout race on the
repository's lock. A sweep takes that lock once, as ``dvc repro`` does, and inside it:

1. brings the train stages' upstream stages (collect, pretrain) up to date with ``dvc repro``,
   one at a time: they are few and cheap;
2. asks DVC which train stage instances are out of date (``Stage.changed``, what ``dvc status``
   reports); for each, it does what ``dvc repro`` does before the command — removes the stage's
   outputs (never the run's ``checkpoint/``, which is not one) and restores the run from DVC's run
   cache if this very run (command, dependencies, params) was recorded before;
3. with ``--group-size N`` (by default every seed on CUDA; on CPU as many as leave every job a
   process: ``default_group_size``), gathers the runs of
   one task and algorithm into processes of up to N (``ede-pipeline train --seeds``: their
   updates batched, each run's outputs those it gets alone), then
   runs the commands of the others in parallel — threads each waiting on one child process
   (``--executor local``), or one Ray task each (``--executor ray``);
4. records each run as it finishes, exactly as ``dvc repro`` would: the stage's dependencies and
   outputs hashed, the outputs committed to DVC's cache and the run cache, its ``dvc.lock`` entry
   written. A following ``dvc repro`` or ``dvc status`` sees it as up to date.

A run that fails (non-zero exit, a killed process) is reported with the path of its log and
recorded nowhere; the others are recorded all the same, and the sweep exits 1. Its checkpoint
stays, so the next ``sweep`` (or ``dvc repro``) runs only what is still out of date and resumes
that run where it stopped. On Ray, a run lost with its worker or node is not a failure: Ray
starts it again (``--retries`` times at most) on the nodes there are, and it resumes from its
checkpoint within this sweep.

On Ray, every node runs the command in this very checkout, which must be at the same path on every
node (a shared filesystem); only this process touches DVC. A cluster without a shared filesystem
runs each stage as a batch job instead (``scripts/batch-job.sh``: pull, run, push; README.md).
"""

from __future__ import annotations

import math
import os
import shlex
import shutil
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click
from click.core import ParameterSource
from tqdm import tqdm

from ede.atomic import claim, unwritable
from ede.config import Params
from ede.errors import first_line
from ede_pipeline import layout
from ede_pipeline.common import (
    DEFAULT_PARAMS,
    PARENT_ENV,
    BadInput,
    check_outputs,
    read_params,
)
from ede_pipeline.progress import PROGRESS_ENV, read_progress

if TYPE_CHECKING:
    from dvc.repo import Repo
    from dvc.stage import Stage

TRAIN_STAGES = "train*"  # dvc.yaml's train stage (one instance per run), unless told others
LOGS = Path(".dvc") / "tmp" / "sweep"  # DVC's own git-ignored scratch folder
LOGS_KIND = "folder of sweep logs"
TAIL = 20  # lines of a failed run's log shown in the report


@dataclass(frozen=True)
class RunId:
    """Which run a train stage is: what determines its command and its output folder."""

    task: str
    algo: str
    seed: int


def train_runs(params: Params) -> dict[str, RunId]:
    """Every run of ``dvc.yaml``'s train matrix, by the name DVC gives its stage
    (``train@<task>-<algo>-<seed>``): a stage's run known from the params, not from its command."""
    return {
        f"train@{task}-{algo}-{seed}": RunId(task, algo, seed)
        for task in params.runs.tasks
        for algo in params.runs.algos
        for seed in params.runs.seeds
    }


def train_command(task: str, algo: str, seeds: list[int]) -> list[str]:
    """The ``ede-pipeline train`` command of runs of one task and algorithm, their paths from
    :mod:`ede_pipeline.layout` (``dvc.yaml``'s train command for one seed;
    ``tests/pipeline/test_layout.py`` holds the two together)."""
    inputs = layout.task_inputs(task)
    out = (
        layout.run(task, algo, seeds[0])
        if len(seeds) == 1
        else layout.run(task, algo, 0).with_name("seed{seed}")
    )
    return [
        "ede-pipeline",
        "train",
        "--task",
        task,
        "--algo",
        algo,
        "--seed",
        ",".join(map(str, seeds)),
        "--out",
        str(out),
        "--encoder",
        str(inputs / layout.ENCODER),
        "--decoder",
        str(inputs / layout.DECODER),
    ]


@dataclass(frozen=True)
class Job:
    """One stage's command, ready for any executor: plain data that pickles."""

    stage: str
    argvs: list[list[str]]  # one argv per line of the stage's ``cmd``, as DVC would run them
    cwd: str  # the checkout, the same path on every node
    env: dict[str, str]  # set on top of the executing process's environment
    log: str  # where the commands' output goes
    members: tuple[str, ...] = ()  # a group's stages (one process trains them all); () for one
    runs: tuple[RunId, ...] = ()  # the train runs it makes (several for a group); () for others


def group_jobs(jobs: list[Job], size: int) -> list[Job]:
    """Jobs of train runs that differ only in their seed, as jobs of up to ``size`` runs each:
    one ``ede-pipeline train --seed a,b,… --out …/seed{seed}`` per group
    (docs/performance.md). A job is grouped by its run's identity
    (``Job.runs``); jobs of other stages stay alone. A group runs its command as DVC runs the
    members' (through the same shell, with the same environment)."""
    if size <= 1:
        return jobs
    groups: dict[tuple[str, str], list[Job]] = {}
    alone: list[Job] = []
    for job in jobs:
        if len(job.runs) == 1 and len(job.argvs) == 1:
            groups.setdefault((job.runs[0].task, job.runs[0].algo), []).append(job)
        else:
            alone.append(job)
    grouped: list[Job] = []
    for (task, algo), members in groups.items():
        members.sort(key=lambda job: job.runs[0].seed)
        for start in range(0, len(members), size):
            chunk = members[start : start + size]
            if len(chunk) == 1:
                grouped.append(chunk[0])
                continue
            first = chunk[0]
            command = train_command(task, algo, [job.runs[0].seed for job in chunk])
            shell = first.argvs[0][:-1]  # DVC's ``sh -c``: the command is its last word
            argv = [*shell, shlex.join(command)] if shell else command
            stages = tuple(job.stage for job in chunk)
            log = str(Path(first.log).with_name(f"{Path(first.log).stem}+{len(chunk) - 1}.log"))
            grouped.append(
                Job(
                    " + ".join(stages),
                    [argv],
                    first.cwd,
                    first.env,
                    log,
                    stages,
                    tuple(job.runs[0] for job in chunk),
                )
            )
    return alone + grouped


def seed_by_seed(jobs: list[Job]) -> list[Job]:
    """Jobs in the order of their runs' lowest seed, and within a seed in the order given
    (dvc.yaml's: task, then algorithm); jobs that train nothing first. A sweep stopped partway
    (a time limit, a lost cluster) so leaves every task and algorithm at the same seeds, a
    comparison, where dvc.yaml's order would leave every seed of one algorithm and none of the
    other."""
    return sorted(jobs, key=lambda job: min(run.seed for run in job.runs) if job.runs else -1)


@dataclass(frozen=True)
class Outcome:
    stage: str
    returncode: int | None  # None: no exit status, the executor lost the run (``error`` says why)
    seconds: float
    error: str = ""
    attempts: int = 1  # the job's starts: more than one after a lost Ray worker or node


def run_job(job: Job, where: str = "") -> Outcome:
    """Run a job's commands one after the other, output to its log; stop at the first failure.

    Each start is an attempt, counted in :func:`attempts_file`: Ray starts a job again when its
    worker or node is lost. A first attempt starts the log afresh; a later one adds to it, under
    a line saying which attempt it is and ``where`` it runs.

    Module-level and free of DVC so that a Ray worker can import and run it.
    """
    start = time.perf_counter()
    env = {**os.environ, **job.env}
    # The interpreter's own scripts first: `ede-pipeline` and `dvc` of the environment running this.
    bin_dir = str(Path(sys.executable).parent)
    env["PATH"] = os.pathsep.join([bin_dir, env.get("PATH", "")])
    env[PROGRESS_ENV] = str(progress_file(job))  # the sweep's overall line reads it
    env[PARENT_ENV] = str(os.getpid())  # the run ends with this process (follow_parent)
    progress_file(job).unlink(missing_ok=True)  # an earlier sweep's, or the lost attempt's
    log_path = Path(job.log)
    log_path.parent.mkdir(parents=True, exist_ok=True)
    attempt = _start_attempt(job, where)
    returncode = 0
    with log_path.open("w" if attempt == 1 else "a") as log:
        if where or attempt > 1:
            log.write(f"# attempt {attempt}{f' on {where}' if where else ''}\n")
        for argv in job.argvs:
            log.write(f"$ {' '.join(argv)}\n")
            log.flush()
            returncode = subprocess.run(
                argv, cwd=job.cwd, env=env, stdout=log, stderr=subprocess.STDOUT, check=False
            ).returncode
            if returncode != 0:
                break
    return Outcome(job.stage, returncode, time.perf_counter() - start, attempts=attempt)


def attempts_file(job: Job) -> Path:
    """Where each start of a job adds a line, beside its log.

    Only the job sees that Ray started it again (the task's result says nothing of the lost
    attempts, and Ray's state API needs its dashboard): a file on the shared filesystem, like the
    log, is counted by the sweep wherever the attempts ran. The sweep removes an earlier sweep's
    before it starts the job; the attempts of one job never run at once.
    """
    return Path(job.log).with_suffix(".attempts")


def _start_attempt(job: Job, where: str) -> int:
    """Count a start of the job; its number (1 for the first)."""
    with attempts_file(job).open("a") as file:
        file.write(f"{where or socket.gethostname()}\n")
    return attempts(job)


def attempts(job: Job) -> int:
    """How many times the job has started in this sweep (0: not yet)."""
    try:
        return len(attempts_file(job).read_text().splitlines())
    except FileNotFoundError:
        return 0


# ---------------------------------------------------------------------------------------------
# Executors: submit jobs, hand back outcomes as they finish.


class LocalExecutor:
    """At most ``jobs`` child processes at once, on this machine."""

    def __init__(self, jobs: int) -> None:
        self.pool = ThreadPoolExecutor(max_workers=jobs)

    def map_unordered(self, jobs: list[Job]) -> Iterator[Outcome]:
        pending: set[Future[Outcome]] = {self.pool.submit(run_job, job) for job in jobs}
        try:
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                yield from (future.result() for future in done)
        finally:
            self.pool.shutdown(wait=True, cancel_futures=True)


def _finite(param: click.Parameter, value: float) -> float:
    """Refuse ``inf`` and ``nan``, which click's ranges let through."""
    if not math.isfinite(value):
        raise click.BadParameter(f"{value} is not a finite number", param=param)
    return value


RAY_CONNECT_TIMEOUT = 10.0  # seconds the sweep waits for a Ray address to answer
RETRIES = 3  # times Ray starts a run again when its worker or node is lost, unless told


def _import_ray() -> Any:
    """Ray, or one line saying how to install it (with gRPC, which ``ray[default]`` brings and
    :func:`check_ray_address` asks through)."""
    try:
        import grpc  # noqa: F401 — only to fail here, with the line below, when it is missing
        import ray
    except ImportError:
        raise BadInput("--executor ray needs Ray: pip install -e '.[ray]'") from None
    return ray


def check_ray_address(
    address: str | None, timeout: float = RAY_CONNECT_TIMEOUT, name: str = "--address"
) -> None:
    """A Ray address is refused at once, before anything runs, unless a Ray cluster answers there:
    Ray itself would retry for minutes, printing warnings, after the upstream stages have run.
    ``auto`` (and no address) are Ray's to resolve.

    Two questions, within ``timeout`` seconds in all: does anything accept a connection there (if
    not, the system's reason: refused, unknown host), and does it answer as Ray does — the GCS
    (``HOST:PORT``, what ``ray start --head`` prints) with its cluster's id, the Ray Client server
    (``ray://HOST:PORT``) to a ping. An HTTP server, a server that says nothing or one that hangs
    up is not Ray.

    Raises:
        BadInput: one line naming the address (``name``: where it came from) and why.
    """
    if address is None or address in ("auto", "local"):
        return
    target = address.removeprefix("ray://")
    host, colon, port = target.rpartition(":")
    if not colon or not host or not port.isdigit():
        raise BadInput(
            f"{name} {address!r}: expected HOST:PORT, ray://HOST:PORT or auto, as "
            "`ray start --head` prints it"
        )
    deadline = time.monotonic() + timeout
    if why := _unreachable(host.strip("[]"), int(port), timeout):
        raise BadInput(
            f"{name} {address}: no Ray cluster can be reached there ({why}); start "
            "one with `ray start --head`, or give the address it prints"
        )
    left = max(deadline - time.monotonic(), 0.01)
    if why := _not_ray(target, address.startswith("ray://"), left, timeout):
        raise BadInput(
            f"{name} {address}: {why}; give the address `ray start --head` prints "
            "(the GCS, HOST:6379 by default, or ray://HOST:10001 for Ray Client)"
        )


def _unreachable(host: str, port: int, timeout: float) -> str:
    """Why nothing accepts a TCP connection at ``host:port`` within ``timeout`` s ("" if it does)."""
    try:
        socket.create_connection((host, port), timeout=timeout).close()
    except TimeoutError:
        return f"no answer within {timeout:g} s"
    except socket.gaierror as error:
        return f"unknown host: {error.strerror}"
    except OSError as error:
        return error.strerror or type(error).__name__
    return ""


def _not_ray(target: str, client: bool, timeout: float, bound: float) -> str:
    """Why the service at ``target`` is not a Ray cluster ("" if it is), asked over gRPC as Ray's
    own clients ask (through Ray's channel: its TLS and token settings) within ``timeout`` s:
    the GCS for its cluster's id, a Ray Client server (``client``) for a ping. ``bound``: the
    whole check's time, as the line says it."""
    _import_ray()  # its line if Ray is missing
    import grpc
    from ray._private.grpc_utils import init_grpc_channel

    if client:
        from ray.core.generated import ray_client_pb2 as messages
        from ray.core.generated import ray_client_pb2_grpc as services

        question = "asked for a Ray Client ping"
        request = messages.ClusterInfoRequest(type=messages.ClusterInfoType.PING)
    else:
        from ray.core.generated import gcs_service_pb2 as messages
        from ray.core.generated import gcs_service_pb2_grpc as services

        question = "asked for its Ray cluster id"
        request = messages.GetClusterIdRequest()
    try:
        with init_grpc_channel(target) as channel:
            if client:
                services.RayletDriverStub(channel).ClusterInfo(request, timeout=timeout)
            else:
                services.NodeInfoGcsServiceStub(channel).GetClusterId(request, timeout=timeout)
    except grpc.RpcError as error:
        code = error.code()
        if code == grpc.StatusCode.DEADLINE_EXCEEDED:
            return f"what answers there is not Ray ({question}: no answer within {bound:g} s)"
        # gRPC's own words end with the reason, e.g. "… last error: UNAVAILABLE: ipv4:…: Failed
        # parsing HTTP/2 (…)" from an HTTP server, "Socket closed" from one that hangs up.
        detail = (error.details() or "").rpartition("last error: ")[2]
        answer = detail if detail.startswith(code.name) else f"{code.name}: {detail}".rstrip(": ")
        if code in (grpc.StatusCode.UNAUTHENTICATED, grpc.StatusCode.PERMISSION_DENIED):
            return (
                f"the Ray cluster there refused this machine's credentials ({question}: {answer})"
            )
        return f"what answers there is not Ray ({question}: {answer})"
    return ""


class RayExecutor:
    """One Ray task per job, ``num_cpus`` each; at most ``jobs`` in flight if given.

    A job lost with its Ray worker or node is started again by Ray, up to ``retries`` times, on
    the nodes there are then; it resumes from the run's checkpoint (on the shared filesystem).
    Only a lost job is: :func:`run_job` returns a failed command's exit status rather than
    raising, and an exception is not retried (``retry_exceptions=False``).
    """

    def __init__(
        self, address: str | None, num_cpus: float, jobs: int | None, retries: int
    ) -> None:
        ray = self.ray = _import_ray()
        if not ray.is_initialized():
            try:
                ray.init(
                    address=address,
                    include_dashboard=False,
                    log_to_driver=False,
                    configure_logging=False,
                )
            except ConnectionError as error:  # e.g. auto, and no cluster on this machine
                first = (str(error).strip().splitlines() or [type(error).__name__])[0]
                raise BadInput(f"--address {address}: {first}") from None
        self.task = ray.remote(run_on_ray).options(
            num_cpus=num_cpus, max_retries=retries, retry_exceptions=False
        )
        self.jobs = jobs

    def map_unordered(self, jobs: list[Job]) -> Iterator[Outcome]:
        ray = self.ray
        queue = list(reversed(jobs))
        running: dict[Any, tuple[Job, float]] = {}
        limit = self.jobs or len(jobs)
        while queue or running:
            while queue and len(running) < limit:
                job = queue.pop()
                running[self.task.remote(job)] = (job, time.perf_counter())
            [ref], _ = ray.wait(list(running), num_returns=1)
            job, start = running.pop(ref)
            try:
                yield ray.get(ref)
            except ray.exceptions.RayError as error:  # lost every attempt, or run_job raised
                yield Outcome(
                    job.stage,
                    None,
                    time.perf_counter() - start,
                    error=f"{type(error).__name__}: {first_line(error)}",
                    attempts=attempts(job),
                )


def run_on_ray(job: Job) -> Outcome:
    """:func:`run_job` as a Ray task, its log saying on which node each attempt ran."""
    import ray

    return run_job(job, where=f"Ray node {ray.get_runtime_context().get_node_id()}")


# ---------------------------------------------------------------------------------------------
# DVC: which stages, what to run, how to record.


def dvc_executable() -> str:
    beside = Path(sys.executable).parent / "dvc"
    return str(beside) if beside.exists() else (shutil.which("dvc") or "dvc")


def stage_argvs(stage: Stage) -> list[list[str]]:
    """The argv DVC's ``cmd_run`` would execute for each line of the stage's command."""
    from dvc.stage.run import _enforce_cmd_list, _make_cmd, get_executable

    executable = get_executable()
    return [list(_make_cmd(executable, cmd)) for cmd in _enforce_cmd_list(stage.cmd)]


def stage_env(stage: Stage) -> dict[str, str]:
    """The variables DVC's ``cmd_run`` sets for a stage's command."""
    from dvc.env import DVC_ROOT, DVC_STAGE

    return {DVC_ROOT: stage.repo.root_dir, DVC_STAGE: stage.addressing}


def collect_stages(repo: Repo, targets: tuple[str, ...]) -> list[Stage]:
    from dvc.exceptions import DvcException

    stages: dict[str, Stage] = {}
    for target in targets or (TRAIN_STAGES,):
        try:
            found = repo.stage.collect(target, glob="*" in target)
        except DvcException as error:
            raise BadInput(f"{target}: {error}") from None
        stages.update((stage.addressing, stage) for stage in found)
    if not stages:
        raise BadInput(f"no stages match {' '.join(targets or (TRAIN_STAGES,))}")
    return list(stages.values())


def upstream_of(repo: Repo, stages: list[Stage]) -> list[Stage]:
    """Every stage the given ones depend on, directly or not, that is not one of them."""
    import networkx as nx

    graph = repo.index.graph
    names = {stage.addressing for stage in stages}
    upstream: dict[str, Stage] = {}
    for stage in stages:
        for dependency in nx.descendants(graph, stage):  # DVC's edges point to dependencies
            if dependency.addressing not in names:
                upstream[dependency.addressing] = dependency
    return list(upstream.values())


def record(stage: Stage) -> None:
    """What ``dvc repro`` does once a stage's command has succeeded: hash the dependencies and
    outputs, save the run to the run cache, commit the outputs to the cache, write ``dvc.lock``."""
    no_cache_outs = any(
        not out.use_cache for out in stage.outs if not (out.is_metric or out.is_plot)
    )
    stage.save(run_cache=not no_cache_outs)
    stage.commit()
    stage.dump(update_pipeline=False)


def restore_from_run_cache(stage: Stage) -> bool:
    """``dvc repro``'s first resort: check out this very run's outputs if DVC has them."""
    from dvc.stage.cache import RunCacheNotFoundError

    try:
        stage.repo.stage_cache.restore(stage)
    except RunCacheNotFoundError:
        return False
    return True


@contextmanager
def repo_lock(repo: Repo) -> Iterator[None]:
    from dvc.lock import LockError
    from dvc.repo import lock_repo

    try:
        with lock_repo(repo):
            yield
    except LockError as error:
        raise BadInput(f"{error} (a `dvc` command or another sweep is running here)") from None


# ---------------------------------------------------------------------------------------------
# Progress.


def _duration(seconds: float) -> str:
    seconds = round(seconds)
    hours, rest = divmod(seconds, 3600)
    return (
        f"{hours}h{rest // 60:02d}m{rest % 60:02d}s" if hours else f"{rest // 60}m{rest % 60:02d}s"
    )


def progress_file(job: Job) -> Path:
    """Where the job's command publishes its step counts (``EDE_PROGRESS``)."""
    return Path(job.log).with_suffix(".progress")


def job_steps(job: Job, budgets: dict[str, int]) -> int:
    """The environment steps a train job runs: its runs' budgets (0: not a train job)."""
    return sum(budgets.get(run.task, 0) for run in job.runs)


class Tally:
    """The sweep's progress: a line per finished run, and one overall line — runs finished,
    retries (runs started again after a lost Ray worker or node), environment steps done of all,
    the aggregate rate and an ETA — live at the bottom of a terminal (``watch``), or printed at
    every tenth of the steps in a log.

    Steps come from the runs' progress files (``EDE_PROGRESS``); the steps a resumed run had
    already done count as done but not towards the rate. Without step counts (stages other
    than train) the ETA is from the pace of finished runs.
    """

    POLL = 2.0  # seconds between two reads of the progress files

    def __init__(self, total: int) -> None:
        self.total, self.done, self.start = total, 0, time.perf_counter()
        self.jobs: dict[str, Job] = {}
        self.steps: dict[str, int] = {}
        self.finished: set[str] = set()
        self.resumed: dict[str, int] = {}  # per job: the steps done when first seen
        self.lock = threading.Lock()
        self.bar: tqdm | None = None
        self.next_line = 0.1

    def track(self, jobs: list[Job], budgets: dict[str, int]) -> None:
        """Count the steps of these jobs (``budgets``: the environment steps of a run per task)."""
        self.jobs = {job.stage: job for job in jobs}
        self.steps = {job.stage: job_steps(job, budgets) for job in jobs}

    # The counts --------------------------------------------------------------------------

    def _counts(self) -> tuple[int, int, int]:
        """(steps done, steps in all, steps done before this sweep) over the jobs."""
        done = total = before = 0
        for name, job in self.jobs.items():
            read = None if name in self.finished else read_progress(progress_file(job))
            steps = read[1] if read else self.steps[name]
            if read and name not in self.resumed:
                self.resumed[name] = read[0]
            total += steps
            done += steps if name in self.finished else (read[0] if read else 0)
            before += self.resumed.get(name, 0)
        return done, total, before

    def _eta(self, elapsed: float, counts: tuple[int, int, int]) -> str:
        done, total, before = counts
        if total and done > before:
            rate = (done - before) / elapsed
            return f"ETA {_duration((total - done) / rate)}" if total > done else "done"
        left = self.total - self.done
        if not left:
            return "done"
        return f"ETA {_duration(elapsed / self.done * left)}" if self.done else "ETA unknown"

    def retries(self) -> int:
        """The jobs' starts after their first: each a job lost with its Ray worker or node."""
        return sum(max(attempts(job) - 1, 0) for job in self.jobs.values())

    def overall(self) -> str:
        """The one line: runs, retries (if any), steps, rate, ETA."""
        elapsed = max(time.perf_counter() - self.start, 1e-9)
        counts = done, total, before = self._counts()
        retries = self.retries()
        again = f", {retries} {'retry' if retries == 1 else 'retries'}" if retries else ""
        steps = ""
        if total:
            rate = (done - before) / elapsed
            steps = (
                f", {_count(done)}/{_count(total)} steps ({done / total:.0%}), {rate:,.0f} steps/s"
            )
        return (
            f"sweep: {self.done}/{self.total} runs{again}{steps}, elapsed {_duration(elapsed)}, "
            f"{self._eta(elapsed, counts)}"
        )

    # Output ------------------------------------------------------------------------------

    def line(self, status: str, stage: str, detail: str, job: str | None = None) -> str:
        """A finished run's line (``job``: the job it was part of, when all of it is over)."""
        with self.lock:
            self.done += 1
            if job is not None:
                self.finished.add(job)
            elapsed = time.perf_counter() - self.start
            return (
                f"[{self.done}/{self.total}] {status:<6} {stage}  {detail}  "
                f"(elapsed {_duration(elapsed)}, {self._eta(elapsed, self._counts())})"
            )

    def echo(self, text: str) -> None:
        with self.lock:
            if self.bar is not None:
                self.bar.write(text)
            else:
                click.echo(text)

    def tick(self) -> None:
        """Refresh the overall line (terminal), or print it at each further tenth (log)."""
        with self.lock:
            text = self.overall()
            if self.bar is not None:
                self.bar.set_description_str(text, refresh=True)
                return
            done, total, _ = self._counts()
            if total and done >= self.next_line * total:
                click.echo(text, err=True)
                while self.next_line * total <= done:
                    self.next_line += 0.1

    @contextmanager
    def watch(self) -> Iterator[None]:
        """Keep the overall line up to date while the runs run."""
        stop = threading.Event()
        if sys.stderr.isatty():
            self.bar = tqdm(total=0, bar_format="{desc}", file=sys.stderr, dynamic_ncols=True)

        def loop() -> None:
            while not stop.wait(self.POLL):
                self.tick()

        thread = threading.Thread(target=loop, name="sweep-progress", daemon=True)
        thread.start()
        try:
            yield
        finally:
            stop.set()
            thread.join()
            if self.bar is not None:
                self.bar.close()
                self.bar = None
            click.echo(self.overall(), err=True)


def _count(steps: int) -> str:
    for size, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if steps >= size:
            return f"{steps / size:.3g}{suffix}"
    return str(steps)


def _tail(text: str) -> str:
    lines = text.rstrip().splitlines()[-TAIL:]
    return "\n".join(f"    | {line}" for line in lines)


# ---------------------------------------------------------------------------------------------
# The command.


@click.command()
@click.argument("targets", nargs=-1)
@click.option(
    "-j",
    "--jobs",
    type=click.IntRange(min=1),
    help="Runs at once  [default: local: the number of cores; ray: as the cluster fits]",
)
@click.option(
    "--executor",
    type=click.Choice(["local", "ray"]),
    default="local",
    show_default=True,
    help="Child processes on this machine, or Ray tasks on a cluster.",
)
@click.option(
    "--address",
    help="Ray: the cluster to join (`ray start --head` prints it; "
    "default: $RAY_ADDRESS, else a new local Ray instance). One where no Ray cluster "
    "answers within 10 s is refused before anything runs.",
)
@click.option(
    "--retries",
    type=click.IntRange(min=0),
    default=RETRIES,
    show_default=True,
    help="Ray: times a run lost with its Ray worker or node is started again on the "
    "nodes there are (it resumes from its checkpoint). A run whose command fails "
    "is not.",
)
@click.option(
    "--cpus-per-run",
    type=click.FloatRange(min=0, min_open=True),
    default=1.0,
    callback=lambda ctx, param, value: _finite(param, value),
    show_default=True,
    help="Ray: the num_cpus of each run's task.",
)
@click.option(
    "--group-size",
    type=click.IntRange(min=1),
    help="Runs of one task and algorithm trained by one process (`train --seeds`)  "
    "[default: on CUDA (td3.device cuda, or auto with a GPU) every seed; on CPU as "
    "many as leave every job a process]",
)
@click.option(
    "--logs",
    type=click.Path(path_type=Path),
    default=LOGS,
    show_default=True,
    help="Where each run's output goes, one file per stage.",
)
@click.pass_context
def sweep(
    ctx: click.Context,
    targets: tuple[str, ...],
    jobs: int | None,
    executor: str,
    address: str | None,
    retries: int,
    cpus_per_run: float,
    group_size: int | None,
    logs: Path,
) -> None:
    """Run the out-of-date train stages in parallel and record each with DVC.

    TARGETS are stages as `dvc repro` takes them, `*` a wildcard (default: every run of
    dvc.yaml's `train` stage, e.g. `'train@ede/Reacher*'` only those).
    Their upstream stages are brought up to date first with `dvc repro`. Exits 1 if any run failed;
    what succeeded is recorded all the same, and running the sweep again runs only the rest.
    """
    from dvc.exceptions import DvcException, NotDvcRepoError
    from dvc.repo import Repo

    if not Path("dvc.yaml").is_file():
        raise BadInput(f"run from the repository root (no dvc.yaml in {Path.cwd()})")
    if executor == "local" and address:
        raise BadInput("--address is for --executor ray")
    if executor == "local" and ctx.get_parameter_source("retries") != ParameterSource.DEFAULT:
        raise BadInput(
            "--retries is for --executor ray (a local run that fails is reported, "
            "and the next sweep resumes it)"
        )
    if executor == "ray":
        given = address is not None
        check_ray_address(
            address if given else os.environ.get("RAY_ADDRESS"),
            name="--address" if given else "RAY_ADDRESS",
        )
    params = read_params(DEFAULT_PARAMS)  # bad params end here, before anything runs
    runs = train_runs(params)
    # A folder given for the logs is checked as every output is (new, empty or an earlier
    # sweep's), and marked; the default is inside DVC's own scratch folder, where no user's file is.
    chosen = ctx.get_parameter_source("logs") != ParameterSource.DEFAULT
    try:
        if chosen:
            check_outputs((logs, LOGS_KIND))
        elif problem := unwritable(logs, directory=True):
            raise BadInput(problem)
    except BadInput as error:
        raise BadInput(f"--logs {error.format_message()}") from None
    try:
        Repo(".").close()
    except NotDvcRepoError:
        raise BadInput(
            f"{Path.cwd()}: dvc.yaml but no DVC repository; run `dvc init` (in a git "
            "repository) first"
        ) from None

    with Repo(".") as repo:
        stages = collect_stages(repo, targets)
        _bring_upstream_up_to_date(repo, stages)

    with Repo(".") as repo, repo_lock(repo):
        stages = collect_stages(repo, targets)  # the index as it is after the upstream stages ran
        stale = [stage for stage in stages if stage.changed()]
        click.echo(f"sweep: {len(stale)} of {len(stages)} stages out of date", err=True)
        if not stale:
            return
        if chosen:
            claim(logs, LOGS_KIND, ("*.log", "*.attempts"))
        tally = Tally(len(stale))
        failed: list[str] = []
        pending: list[Job] = []
        for stage in stale:
            try:
                stage.remove_outs(ignore_remove=False, force=False)
                if restore_from_run_cache(stage):
                    record(stage)
                    click.echo(
                        tally.line("cached", stage.addressing, "restored from the run cache")
                    )
                    continue
                stage.save_deps()
            except (DvcException, OSError) as error:  # this stage only; the others go on
                failed.append(stage.addressing)
                click.echo(
                    tally.line(
                        "FAILED", stage.addressing, f"not started: {type(error).__name__}: {error}"
                    )
                )
                continue
            log = (Path(repo.root_dir) / logs / f"{_safe(stage.addressing)}.log").resolve()
            run = runs.get(stage.addressing)
            pending.append(
                Job(
                    stage.addressing,
                    stage_argvs(stage),
                    repo.root_dir,
                    stage_env(stage),
                    str(log),
                    runs=(run,) if run else (),
                )
            )
        workers = jobs or (os.cpu_count() if executor == "local" else None)
        pending = seed_by_seed(
            group_jobs(pending, group_size or default_group_size(params, len(pending), workers))
        )
        logs_of = {job.stage: Path(job.log) for job in pending}
        for job in pending:
            attempts_file(job).unlink(missing_ok=True)  # an earlier sweep's
        runner = _executor(executor, jobs, address, cpus_per_run, retries)
        by_name = {stage.addressing: stage for stage in stale}
        tally.track(pending, params.runs.budgets)
        with tally.watch():
            for outcome in runner.map_unordered(pending):
                _report(outcome, by_name, logs_of[outcome.stage], tally, failed)

    recorded = len(stale) - len(failed)
    click.echo(f"sweep: {recorded} recorded, {len(failed)} failed", err=True)
    if failed:
        click.echo(
            "failed (run `ede-pipeline sweep` again to resume them): " + " ".join(failed), err=True
        )
        ctx.exit(1)


def _report(
    outcome: Outcome, by_name: dict[str, Stage], log: Path, tally: Tally, failed: list[str]
) -> None:
    """Record each run of a finished job, or say why not; a line per run."""
    from dvc.exceptions import DvcException

    members = outcome.stage.split(" + ")
    for name in members:
        problem = _problem(outcome)
        if not problem:
            try:
                record(by_name[name])
            except (DvcException, OSError) as error:  # reported with the run
                problem = f"not recorded: {type(error).__name__}: {error}"
        if problem:
            failed.append(name)
            tally.echo(tally.line("FAILED", name, f"{problem}; log: {log}", outcome.stage))
        else:
            shared = f" (one process for {len(members)})" if len(members) > 1 else ""
            lost = outcome.attempts - 1
            again = (
                f" (attempt {outcome.attempts}: {lost} lost with a Ray worker or node)"
                if lost
                else ""
            )
            tally.echo(
                tally.line("ok", name, f"{outcome.seconds:.1f}s{shared}{again}", outcome.stage)
            )
    if _problem(outcome) and log.is_file():
        tally.echo(_tail(log.read_text()))


def _bring_upstream_up_to_date(repo: Repo, stages: list[Stage]) -> None:
    with repo_lock(repo):
        stale = [stage.addressing for stage in upstream_of(repo, stages) if stage.changed()]
    if not stale:
        return
    click.echo(f"sweep: dvc repro {' '.join(stale)}", err=True)
    result = subprocess.run([dvc_executable(), "repro", *stale], check=False)
    if result.returncode != 0:
        raise click.ClickException(
            f"dvc repro of the upstream stages failed "
            f"(exit {result.returncode}); nothing else was run"
        )


def _executor(
    kind: str, jobs: int | None, address: str | None, cpus_per_run: float, retries: int
) -> LocalExecutor | RayExecutor:
    if kind == "local":
        return LocalExecutor(jobs or os.cpu_count() or 1)
    return RayExecutor(address, cpus_per_run, jobs, retries)


def _problem(outcome: Outcome) -> str:
    if outcome.returncode is None:
        tries = f" in each of {outcome.attempts} attempts" if outcome.attempts > 1 else ""
        return f"lost{tries} after {outcome.seconds:.1f}s ({outcome.error})"
    if outcome.returncode < 0:
        return f"killed by signal {-outcome.returncode} after {outcome.seconds:.1f}s"
    if outcome.returncode > 0:
        return f"exit {outcome.returncode} after {outcome.seconds:.1f}s"
    return ""


def default_group_size(params: Params, runs: int, workers: int | None) -> int:
    """Seeds per process when ``--group-size`` is not given.

    On CUDA every seed of a task and algorithm: the update is bound by kernel launches, so a group
    costs about what one run costs. On CPU as many as still leave every worker a process
    (``runs // workers``): batching saves per-operation overhead (``benchmarks/
    train_throughput.py`` measures groups against one run), but a group runs on one core; on Ray
    without ``--jobs`` (workers unknown) one.
    """
    seeds = len(params.runs.seeds)
    if _on_cuda(params.td3.device):
        return seeds
    if workers is None:
        return 1
    return max(1, min(seeds, runs // workers))


def _on_cuda(device: str) -> bool:
    if device == "cpu":
        return False
    import torch

    return torch.cuda.is_available()


def _safe(name: str) -> str:
    return name.replace("/", "_").replace("@", "__")
