"""``ede-pipeline collect`` and ``inspect`` end to end, kills, and bad input."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner, Result

from ede.io.provenance import software_versions
from ede.io.rollouts import Rollouts, RolloutsError
from ede_pipeline.cli import main


def tiny(params: dict, steps: int = 400, num_envs: int = 2) -> None:
    params["collect"].update(steps=steps, num_envs=num_envs)


def run(*args: str) -> Result:
    return CliRunner().invoke(main, list(args))


def test_collect_writes_a_store_the_reader_accepts(tmp_path: Path, write_params) -> None:
    params = write_params(tiny)
    out = tmp_path / "data" / "reacher" / "rollouts.zarr"
    result = run("collect", "--family", "reacher", "--out", str(out), "--params", str(params))
    assert result.exit_code == 0, result.output
    rollouts = Rollouts.open(out, env_id="ede/ReacherVertical-v0")
    assert len(rollouts) == 400 and rollouts.num_episodes == 4
    attrs = rollouts.attrs
    assert (attrs["family"], attrs["seed"], attrs["num_envs"]) == ("reacher", 0, 2)
    assert attrs["params"]["collect"] == {
        "steps": 400,
        "num_envs": 2,
        "seed": 0,
        "saturated_episodes": 0.0,
    }
    assert attrs["spaces"]["action_low"] == [-1.0, -1.0]
    assert attrs["state_source"] == "physics"
    assert len(attrs["fingerprint"]) == 64
    assert attrs["software"] == software_versions()  # what made it: Python, numpy, torch, ...
    assert set(attrs["software"]) == {"python", "numpy", "torch", "mujoco", "gymnasium"}
    # Quiet in logs: no bar redraws, a handful of lines.
    assert "\r" not in result.stderr and len(result.stderr.splitlines()) <= 11

    summary = run("inspect", "--family", "reacher", "--rollouts", str(out), "--params", str(params))
    assert summary.exit_code == 0 and "400 steps in 4 episodes" in summary.output


def test_a_task_without_mujoco_physics_is_collected_with_its_observation_as_state(
    tmp_path: Path, write_params
) -> None:
    def pendulum(params: dict) -> None:
        tiny(params)
        params["families"]["pendulum"] = {"source": "Pendulum-v1"}

    params = write_params(pendulum)
    out = tmp_path / "rollouts.zarr"
    result = run("collect", "--family", "pendulum", "--out", str(out), "--params", str(params))
    assert result.exit_code == 0, result.output
    rollouts = Rollouts.open(out, env_id="Pendulum-v1")
    assert rollouts.attrs["state_source"] == "observation"
    assert rollouts.attrs["spaces"]["state_size"] == 3
    np.testing.assert_array_equal(rollouts.state, rollouts.obs)

    summary = run(
        "inspect", "--family", "pendulum", "--rollouts", str(out), "--params", str(params)
    )
    assert summary.exit_code == 0 and "400 steps in 2 episodes" in summary.output, summary.output


def test_rerunning_with_the_same_params_gives_the_same_arrays(tmp_path: Path, write_params) -> None:
    params = write_params(tiny)
    stores = []
    for name in ("a.zarr", "b.zarr"):
        result = run(
            "collect", "--family", "point", "--out", str(tmp_path / name), "--params", str(params)
        )
        assert result.exit_code == 0, result.output
        stores.append(Rollouts.open(tmp_path / name))
    for key, value in stores[0].arrays().items():
        np.testing.assert_array_equal(value, getattr(stores[1], key))
    assert stores[0].attrs == stores[1].attrs


def test_a_collection_killed_midway_leaves_nothing_a_reader_accepts(
    tmp_path: Path, write_params
) -> None:
    params = write_params(lambda p: tiny(p, steps=2_000_000, num_envs=2))
    out = tmp_path / "rollouts.zarr"
    command = [sys.executable, "-m", "ede_pipeline", "collect", "--family", "reacher"]
    process = subprocess.Popen(
        [*command, "--out", str(out), "--params", str(params)],
        start_new_session=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    time.sleep(3)
    os.killpg(process.pid, signal.SIGKILL)
    process.wait()
    assert not out.exists()
    with pytest.raises(RolloutsError):
        Rollouts.open(out)

    result = run(
        "collect", "--family", "reacher", "--out", str(out), "--params", str(write_params(tiny))
    )
    assert result.exit_code == 0, result.output
    assert len(Rollouts.open(out)) == 400


def test_a_store_killed_while_being_written_is_never_accepted(tmp_path: Path) -> None:
    """Kill the writer between two arrays: only the temporary exists, and the reader refuses it."""
    out = tmp_path / "rollouts.zarr"
    script = textwrap.dedent(
        f"""
        import sys, time
        import numpy as np
        import zarr
        from ede.io import rollouts
        original = zarr.Group.create_array
        def slow(self, name, **kwargs):
            array = original(self, name, **kwargs)
            if name == "action":
                print("writing", flush=True)
                time.sleep(60)
            return array
        zarr.Group.create_array = slow
        n = 10
        arrays = dict(obs=np.zeros((n, 2)), state=np.zeros((n, 2)), action=np.zeros((n, 2)),
                      reward=np.zeros(n), episode=np.zeros(n, dtype=int), t=np.arange(n))
        rollouts.write_store({str(out)!r}, arrays, dict(env_id="x", family="x", seed=0,
                             num_envs=1, steps=n, spaces={{}}, params={{}}))
        """
    )
    process = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    assert process.stdout is not None and process.stdout.readline().strip() == "writing"
    process.kill()
    process.wait()
    temporaries = list(tmp_path.glob("rollouts.zarr.tmp-*"))
    assert not out.exists() and len(temporaries) == 1
    with pytest.raises(RolloutsError):
        Rollouts.open(temporaries[0])


@pytest.mark.parametrize(
    ("args", "edit", "message"),
    [
        (["--family", "cartpole"], None, "--family 'cartpole': unknown"),
        (["--family", "point"], lambda p: p["collect"].update(steps=0), "collect.steps: got 0"),
        (
            ["--family", "point"],
            lambda p: p["collect"].update(num_envs=-1),
            "collect.num_envs: got -1",
        ),
    ],
)
def test_bad_collect_input_is_one_line_exit_2_and_writes_nothing(
    tmp_path: Path, write_params, args: list[str], edit, message: str
) -> None:
    params = write_params(edit)
    out = tmp_path / "out.zarr"
    result = run("collect", *args, "--out", str(out), "--params", str(params))
    assert result.exit_code == 2
    assert result.stderr.count("\n") == 1 and message in result.stderr, result.stderr
    assert "Traceback" not in result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["params.yaml"]


def test_a_truncated_or_foreign_store_is_one_line_exit_2(tmp_path: Path, write_params) -> None:
    params = write_params(tiny)
    out = tmp_path / "point.zarr"
    assert (
        run("collect", "--family", "point", "--out", str(out), "--params", str(params)).exit_code
        == 0
    )

    foreign = run(
        "inspect", "--family", "pointmass", "--rollouts", str(out), "--params", str(params)
    )
    assert foreign.exit_code == 2 and foreign.stderr.count("\n") == 1
    assert "collected on ede/Point-v0 (family point), expected ede/PointMass-v0" in foreign.stderr

    for chunk in sorted((out / "action").rglob("*")):
        if chunk.is_file() and chunk.name != "zarr.json":
            chunk.write_bytes(chunk.read_bytes()[:10])  # truncate a chunk
            break
    truncated = run("inspect", "--family", "point", "--rollouts", str(out), "--params", str(params))
    assert truncated.exit_code == 2 and truncated.stderr.count("\n") == 1, truncated.stderr
    assert str(out) in truncated.stderr and "Traceback" not in truncated.output


def test_one_sub_environment_per_core_stops_where_the_steps_run_out(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``collect.num_envs: null`` on a machine of many cores: each sub-environment records one
    episode at least, so no more of them than the steps hold episodes (64 cores, 2,000 steps of
    100-step episodes: 20, not 64 recording 6,400 steps)."""
    from ede_pipeline.collect import default_num_envs

    monkeypatch.setattr(os, "cpu_count", lambda: 64)
    assert default_num_envs(2_000, 100) == 20
    assert default_num_envs(100_000, 100) == 64
    assert default_num_envs(50, 100) == 1
    assert default_num_envs(10, None) == 10
    monkeypatch.setattr(os, "cpu_count", lambda: None)
    assert default_num_envs(2_000, 100) == 1
