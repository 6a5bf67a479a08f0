"""The artifact store, for real: batch jobs push to an S3-compatible server and a wiped checkout
pulls back the same bytes.

A moto S3 server on 127.0.0.1 (a free port, stopped at the end) is the DVC remote of a scratch copy
of the repo with tiny params (``repo_copy``). ``scripts/batch-job.sh`` runs a stage there — pull,
its ``ede-pipeline`` command, push — then the cache and the outputs are wiped and pulled back.
"""

from __future__ import annotations

import hashlib
import logging
import shutil
from collections.abc import Iterator
from pathlib import Path

import boto3
import dvc_s3  # noqa: F401  (the remote type the test configures)
import moto.server as moto_server
import pytest

from tests.support import REPO, dvc, run

BUCKET = "ede-store"
STAGE = "collect@point"
UPSTREAM = ["task_code@point"]  # the stages STAGE depends on, each a batch job of its own first
OUT = "data/families/point/rollouts.zarr"


@pytest.fixture
def s3_endpoint() -> Iterator[str]:
    """An S3-compatible server on 127.0.0.1 with one empty bucket; its endpoint URL."""
    logging.getLogger("werkzeug").setLevel(logging.WARNING)  # one log line per request otherwise
    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    try:
        host, port = server.get_host_and_port()
        endpoint = f"http://{host}:{port}"
        boto3.client(
            "s3",
            endpoint_url=endpoint,
            region_name="us-east-1",
            aws_access_key_id="testing",
            aws_secret_access_key="testing",
        ).create_bucket(Bucket=BUCKET)
        yield endpoint
    finally:
        server.stop()


def run_ok(copy: Path, *args: str) -> str:
    result = dvc(copy, *args)
    assert result.returncode == 0, f"dvc {' '.join(args)}:\n{result.stdout}{result.stderr}"
    return result.stdout


def batch_job(copy: Path, stage: str) -> str:
    """``scripts/batch-job.sh STAGE`` in ``copy``, with the venv's ``dvc`` and ``ede-pipeline``."""
    result = run(copy, REPO / "scripts/batch-job.sh", stage)
    assert result.returncode == 0, result.stdout + result.stderr
    return result.stdout + result.stderr


def digest(path: Path) -> dict[str, str]:
    """SHA-256 of every file under ``path``, by relative name."""
    return {
        str(file.relative_to(path)): hashlib.sha256(file.read_bytes()).hexdigest()
        for file in sorted(path.rglob("*"))
        if file.is_file()
    }


def wipe(copy: Path) -> None:
    """Remove what only the store should still hold: DVC's cache and the stage's outputs."""
    shutil.rmtree(copy / ".dvc/cache")
    shutil.rmtree(copy / "data")


@pytest.mark.slow
def test_batch_job_round_trip_through_s3(repo_copy: Path, s3_endpoint: str) -> None:
    run_ok(repo_copy, "remote", "add", "--default", "s3", f"s3://{BUCKET}/dvc")
    run_ok(repo_copy, "remote", "modify", "s3", "endpointurl", s3_endpoint)
    run_ok(repo_copy, "remote", "modify", "s3", "region", "us-east-1")
    # Credentials in the git-ignored config.local, as a team would keep its keys out of git.
    run_ok(repo_copy, "remote", "modify", "--local", "s3", "access_key_id", "testing")
    run_ok(repo_copy, "remote", "modify", "--local", "s3", "secret_access_key", "testing")

    for stage in [*UPSTREAM, STAGE]:
        batch_job(repo_copy, stage)
    made = digest(repo_copy / OUT)
    assert any(name.startswith("obs/") for name in made), sorted(made)[:5]
    lock = (repo_copy / "dvc.lock").read_text()
    assert "in sync" in run_ok(repo_copy, "status", "--cloud"), "the job did not push everything"

    # A checkout that has dvc.lock: `dvc pull` brings back the same bytes, and nothing is stale.
    # (--allow-missing: the stages that never ran have nothing to pull.)
    wipe(repo_copy)
    run_ok(repo_copy, "pull", "--allow-missing")
    assert digest(repo_copy / OUT) == made
    assert "up to date" in run_ok(repo_copy, "status", STAGE)

    # A checkout without this run's dvc.lock (another machine of a sweep): `dvc repro --pull`
    # finds the run in the store's run cache and checks it out instead of running it again.
    wipe(repo_copy)
    (repo_copy / "dvc.lock").unlink()
    shutil.rmtree(repo_copy / ".dvc/tmp", ignore_errors=True)
    again = run_ok(repo_copy, "repro", "--pull", STAGE)
    assert "is cached - skipping run" in again, again
    assert digest(repo_copy / OUT) == made
    assert (repo_copy / "dvc.lock").read_text() == lock
    assert "up to date" in run_ok(repo_copy, "status", STAGE)
