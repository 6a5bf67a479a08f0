"""Ray: the sweep's jobs as Ray tasks on a cluster, and the check that refuses an address where no
Ray cluster answers before anything runs. Only Ray's public API, and gRPC's."""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ede.errors import first_line
from ede_pipeline.common import BadInput
from ede_pipeline.sweep.execute import Outcome, attempts, run_job
from ede_pipeline.sweep.plan import Job

if TYPE_CHECKING:
    import grpc

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
    own clients ask (:func:`_channel`) within ``timeout`` s: the GCS for its cluster's id, a Ray
    Client server (``client``) for a ping. ``bound``: the whole check's time, as the line says
    it."""
    _import_ray()  # its line if Ray is missing
    import grpc

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
        with _channel(target) as channel:
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
            return ""  # a Ray cluster asking for its token, which ray.init presents
        return f"what answers there is not Ray ({question}: {answer})"
    return ""


# Ray's documented TLS settings (docs.ray.io, "TLS Authentication"): its clients' certificates.
RAY_TLS = {"certificate_chain": "RAY_TLS_SERVER_CERT", "private_key": "RAY_TLS_SERVER_KEY"}
RAY_TLS_CA = "RAY_TLS_CA_CERT"


def _channel(target: str) -> grpc.Channel:
    """A gRPC channel to ``target`` as Ray's clients open one: over TLS where the cluster uses it
    (``RAY_USE_TLS``, with the certificates Ray's TLS settings name), in the clear otherwise."""
    import grpc

    if os.environ.get("RAY_USE_TLS", "0").lower() not in ("1", "true"):
        return grpc.insecure_channel(target)
    files = {**RAY_TLS, "root_certificates": RAY_TLS_CA}
    pem: dict[str, bytes | None] = {}
    for argument, variable in files.items():
        path = os.environ.get(variable)
        try:
            pem[argument] = Path(path).read_bytes() if path else None
        except OSError as error:
            raise BadInput(f"{variable}={path}: {error.strerror} (RAY_USE_TLS is set)") from None
    return grpc.secure_channel(target, grpc.ssl_channel_credentials(**pem))


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
