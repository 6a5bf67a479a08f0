"""``sweep --executor ray``: an address that cannot be reached is one line, at once, before
anything runs (Ray itself retries for minutes, printing warnings)."""

from __future__ import annotations

import shutil
import socket
from pathlib import Path

import pytest
from click.testing import CliRunner

from tests.support import REPO
from ede_pipeline.cli import main
from ede_pipeline.common import BadInput
from ede_pipeline.sweep import RAY_CONNECT_TIMEOUT, check_ray_address


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


def test_an_address_where_nothing_listens_is_one_line_before_anything_runs(project: Path) -> None:
    port = closed_port()
    before = sorted(p.name for p in project.iterdir())
    result = CliRunner().invoke(main, ["sweep", "--executor", "ray", "--address", f"127.0.0.1:{port}"])
    assert result.exit_code == 2
    assert result.stderr == (f"Error: --address 127.0.0.1:{port}: no Ray cluster can be reached "
                             "there (Connection refused); start one with `ray start --head`, or "
                             "give the address it prints\n")
    assert sorted(p.name for p in project.iterdir()) == before


def test_ray_address_from_the_environment_is_checked_too(project: Path,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RAY_ADDRESS", f"ray://127.0.0.1:{closed_port()}")
    result = CliRunner().invoke(main, ["sweep", "--executor", "ray"])
    assert result.exit_code == 2 and "no Ray cluster can be reached there" in result.stderr


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


@pytest.mark.parametrize(("address", "problem"), [
    ("nonsense", "expected HOST:PORT, ray://HOST:PORT or auto"),
    ("host:port", "expected HOST:PORT"),
    ("no-such-host.invalid:6379", "unknown host"),
])
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
    assert result.stderr == (f"Error: {project}: dvc.yaml but no DVC repository; run `dvc init` "
                             "(in a git repository) first\n")
