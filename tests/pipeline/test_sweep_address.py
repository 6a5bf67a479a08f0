"""``sweep --executor ray``: an address where no Ray cluster answers is one line, at once, before
anything runs (Ray itself retries for minutes, printing warnings). Nothing listening, and services
that listen but are not Ray: an HTTP server, a gRPC server of something else, a server that says
nothing, one that hangs up. A real Ray cluster is accepted (tests/pipeline/test_sweep_cluster.py).
"""

from __future__ import annotations

import contextlib
import http.server
import re
import shutil
import socket
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path

import grpc
import pytest
from click.testing import CliRunner

from ede_pipeline.cli import main
from ede_pipeline.common import BadInput
from ede_pipeline.sweep.on_ray import RAY_CONNECT_TIMEOUT, check_ray_address
from tests.support import REPO


def closed_port() -> int:
    """A port nothing listens on: bound, then released."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture
def project(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    for name in ("params.yaml", "dvc.yaml"):
        shutil.copy(REPO / name, tmp_path)
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    return tmp_path


@contextmanager
def http_server() -> Iterator[int]:
    """A plain HTTP server (the issue's example: a local web server's address as RAY_ADDRESS)."""

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args: object) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Quiet)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield server.server_address[1]
    finally:
        server.shutdown()
        server.server_close()


@contextmanager
def grpc_server() -> Iterator[int]:
    """A gRPC server with no service of Ray's: it answers every call, UNIMPLEMENTED."""
    server = grpc.server(ThreadPoolExecutor(max_workers=1))
    port = server.add_insecure_port("127.0.0.1:0")
    server.start()
    try:
        yield port
    finally:
        server.stop(grace=None)


@contextmanager
def raw_server(on_accept: Callable[[socket.socket], None]) -> Iterator[int]:
    """A TCP server that accepts each connection, then does ``on_accept`` with it."""
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    accepted: list[socket.socket] = []

    def serve() -> None:
        while True:
            try:
                connection, _ = listener.accept()
            except OSError:  # closed: the test is over
                return
            accepted.append(connection)
            on_accept(connection)

    threading.Thread(target=serve, daemon=True).start()
    try:
        yield listener.getsockname()[1]
    finally:
        listener.close()
        for connection in accepted:
            connection.close()


def silent_server() -> contextlib.AbstractContextManager[int]:
    """Accepts and says nothing, ever."""
    return raw_server(lambda connection: None)


def hanging_up_server() -> contextlib.AbstractContextManager[int]:
    """Accepts and closes the connection at once."""
    return raw_server(lambda connection: connection.close())


NOT_RAY = {  # each service, and the end of what the refusal says of its answer
    "http": (http_server, r"UNAVAILABLE: ipv4:127\.0\.0\.1:\d+: Failed parsing HTTP/2 .*\)"),
    "grpc": (grpc_server, "UNIMPLEMENTED: Method not found!"),
    "silent": (silent_server, r"no answer within 1\.5 s"),
    "hangs up": (hanging_up_server, r"UNAVAILABLE: .*"),
}


@pytest.mark.parametrize("scheme", ["", "ray://"])
@pytest.mark.parametrize("service", list(NOT_RAY))
def test_a_service_that_is_not_ray_is_refused_in_one_line_within_the_bound(
    service: str, scheme: str
) -> None:
    serve, answer = NOT_RAY[service]
    question = "a Ray Client ping" if scheme else "its Ray cluster id"
    with serve() as port:
        address = f"{scheme}127.0.0.1:{port}"
        start = time.monotonic()
        with pytest.raises(BadInput) as refused:
            check_ray_address(address, timeout=1.5)
        seconds = time.monotonic() - start
    line = str(refused.value)
    assert re.fullmatch(
        rf"--address {re.escape(address)}: what answers there is not Ray "
        rf"\(asked for {question}: {answer}\); give the address `ray start "
        r"--head` prints \(the GCS, HOST:6379 by default, or ray://HOST:10001 "
        r"for Ray Client\)",
        line,
    ), line
    assert "\n" not in line
    assert seconds < 1.5 + 1.0  # the bound, and the time to import Ray once


def test_an_http_server_as_ray_address_is_one_line_before_anything_runs(
    project: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    before = sorted(p.name for p in project.iterdir())
    with http_server() as port:
        monkeypatch.setenv("RAY_ADDRESS", f"127.0.0.1:{port}")
        start = time.monotonic()
        result = CliRunner().invoke(main, ["sweep", "--executor", "ray"])
        seconds = time.monotonic() - start
    assert result.exit_code == 2, result.output
    assert result.stderr.startswith(
        f"Error: RAY_ADDRESS 127.0.0.1:{port}: what answers there is "
        "not Ray (asked for its Ray cluster id: UNAVAILABLE: "
    )
    assert result.stderr.count("\n") == 1 and "Traceback" not in result.output
    assert seconds < RAY_CONNECT_TIMEOUT
    assert sorted(p.name for p in project.iterdir()) == before


def test_retries_are_for_ray(project: Path) -> None:
    result = CliRunner().invoke(main, ["sweep", "--retries", "2"])
    assert result.exit_code == 2
    assert result.stderr == (
        "Error: --retries is for --executor ray (a local run that fails is "
        "reported, and the next sweep resumes it)\n"
    )


@pytest.mark.parametrize("retries", ["-1", "two"])
def test_retries_are_a_count(project: Path, retries: str) -> None:
    result = CliRunner().invoke(main, ["sweep", "--executor", "ray", "--retries", retries])
    assert result.exit_code == 2 and "Invalid value for '--retries'" in result.stderr


def test_an_address_where_nothing_listens_is_one_line_before_anything_runs(project: Path) -> None:
    port = closed_port()
    before = sorted(p.name for p in project.iterdir())
    result = CliRunner().invoke(
        main, ["sweep", "--executor", "ray", "--address", f"127.0.0.1:{port}"]
    )
    assert result.exit_code == 2
    assert result.stderr == (
        f"Error: --address 127.0.0.1:{port}: no Ray cluster can be reached "
        "there (Connection refused); start one with `ray start --head`, or "
        "give the address it prints\n"
    )
    assert sorted(p.name for p in project.iterdir()) == before


def test_an_empty_address_is_one_line_before_anything_runs(project: Path) -> None:
    """``--address ""`` is an address given, not none: refused before the upstream stages run
    (it once reached Ray and its ``ValueError: Invalid address format`` after them)."""
    before = sorted(p.name for p in project.iterdir())
    result = CliRunner().invoke(main, ["sweep", "--executor", "ray", "--address", ""])
    assert result.exit_code == 2
    assert result.stderr == (
        "Error: --address '': expected HOST:PORT, ray://HOST:PORT or auto, as "
        "`ray start --head` prints it\n"
    )
    assert sorted(p.name for p in project.iterdir()) == before


def test_ray_address_from_the_environment_is_checked_too(
    project: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    port = closed_port()
    monkeypatch.setenv("RAY_ADDRESS", f"ray://127.0.0.1:{port}")
    result = CliRunner().invoke(main, ["sweep", "--executor", "ray"])
    assert result.exit_code == 2
    assert result.stderr.startswith(
        f"Error: RAY_ADDRESS ray://127.0.0.1:{port}: no Ray cluster "
        "can be reached there (Connection refused)"
    )


def test_an_address_that_never_answers_gives_up_after_the_documented_wait(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    waited = []

    def silent(address: tuple[str, int], timeout: float) -> socket.socket:
        waited.append(timeout)
        raise TimeoutError("timed out")

    monkeypatch.setattr(socket, "create_connection", silent)
    with pytest.raises(BadInput, match=r"no answer within 10 s"):
        check_ray_address("10.1.2.3:6379")
    assert waited == [RAY_CONNECT_TIMEOUT] == [10.0]


@pytest.mark.parametrize(
    ("address", "problem"),
    [
        ("nonsense", "expected HOST:PORT, ray://HOST:PORT or auto"),
        ("host:port", "expected HOST:PORT"),
        ("no-such-host.invalid:6379", "unknown host"),
    ],
)
def test_addresses_that_are_not_addresses(address: str, problem: str) -> None:
    with pytest.raises(BadInput, match=problem):
        check_ray_address(address)


def test_auto_and_no_address_are_rays_to_resolve() -> None:
    check_ray_address(None)
    check_ray_address("auto")


@pytest.mark.parametrize("cpus", ["inf", "nan", "0"])
def test_a_run_needs_a_finite_positive_share_of_cpus(project: Path, cpus: str) -> None:
    result = CliRunner().invoke(main, ["sweep", "--executor", "ray", "--cpus-per-run", cpus])
    assert result.exit_code == 2 and "Invalid value for '--cpus-per-run'" in result.stderr


def test_dvc_yaml_without_a_dvc_repository_is_one_line(project: Path) -> None:
    result = CliRunner().invoke(main, ["sweep"])
    assert result.exit_code == 2
    assert result.stderr == (
        f"Error: {project}: dvc.yaml but no DVC repository; run `dvc init` "
        "(in a git repository) first\n"
    )
