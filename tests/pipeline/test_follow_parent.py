"""A command started by another ede-pipeline command ends when that one does, however it ends:
killing an experiment stops its sweep, killing a sweep stops its runs (``EDE_PARENT``,
``ede_pipeline.common.follow_parent``), so that nothing is left running on, holding the locks
of the outputs a rerun must write."""

from __future__ import annotations

import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from tests.support import BIN, REPO

PARENT = """
import os, subprocess, sys, time
env = {**os.environ, "EDE_PARENT": str(os.getpid())}
child = subprocess.Popen(sys.argv[1:], env=env)
print(child.pid, flush=True)
time.sleep(600)
"""


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state != "Z"  # a zombie has ended; its parent (here: none) has not reaped it


def children(pid: int) -> list[int]:
    return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]


# DVC runs a stage's command as `$SHELL -c CMD`, `/bin/sh` where SHELL is unset (as under CI):
# bash becomes the command, dash waits for it, so the run's parent is then the shell.
@pytest.mark.parametrize("shell", ["", "/bin/sh"])
def test_a_command_whose_parent_is_killed_ends_too(tmp_path: Path, shell: str) -> None:
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    params["runs"].update(
        tasks={"ede/Point-v0": "point"}, seeds=[0], budgets={"ede/Point-v0": 1_000_000}
    )
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    train = [str(BIN / "ede-pipeline"), "train", "--task", "ede/Point-v0", "--algo", "td3"]
    train += ["--seed", "0", "--out", "run"]
    if shell:
        train = [shell, "-c", shlex.join(train)]
    parent = subprocess.Popen(
        [sys.executable, "-c", PARENT, *train],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert parent.stdout is not None
    child = int(parent.stdout.readline())
    deadline = time.monotonic() + 120
    while not (tmp_path / "run" / "eval.csv").exists():  # training: past the start
        assert time.monotonic() < deadline and alive(child), "the run did not start"
        time.sleep(0.5)
    if shell:  # the shell is still there, waiting for the run it started
        assert len(children(child)) == 1, f"{shell} became the command it ran"
    parent.send_signal(signal.SIGKILL)
    parent.wait()
    deadline = time.monotonic() + 30
    while alive(child):  # the shell ends once the run has
        assert time.monotonic() < deadline, "the run went on after its parent was killed"
        time.sleep(0.2)


def test_a_command_whose_parent_is_gone_before_it_starts_ends_at_once() -> None:
    env = {**os.environ, "EDE_PARENT": "1"}  # not this command's parent: as if it had died
    done = subprocess.run(
        [str(BIN / "ede-pipeline"), "validate"], cwd=REPO, env=env, capture_output=True
    )
    assert done.returncode == -signal.SIGTERM
    env.pop("EDE_PARENT")
    assert (
        subprocess.run([str(BIN / "ede-pipeline"), "validate"], cwd=REPO, env=env).returncode == 0
    )


def test_what_a_follower_starts_does_not_take_its_parent_for_its_own() -> None:
    """The sweep follows an experiment and runs ``dvc repro``, whose stages are ede-pipeline
    commands: they must not read the experiment's PID as their parent's and end at once."""
    env = {**os.environ, "EDE_PARENT": str(os.getpid())}
    script = (
        "import os, subprocess, sys\n"
        "from ede_pipeline.common import follow_parent\n"
        "follow_parent()\n"
        f"sys.exit(subprocess.run([{str(BIN / 'ede-pipeline')!r}, 'validate']).returncode)\n"
    )
    done = subprocess.run([sys.executable, "-c", script], cwd=REPO, env=env, capture_output=True)
    assert done.returncode == 0, done.stderr
