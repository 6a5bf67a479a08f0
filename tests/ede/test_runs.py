"""A run's folder (ede.run.runs): written, read back, checked against the run it must be; and what
run.json records of the code and the machine (ede.io.provenance)."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest
import torch

from ede.config import Algo, EdeTD3Config, TD3Config
from ede.io import provenance
from ede.io.atomic import sha256
from ede.run.runs import (
    CHECKSUMMED,
    RunRejected,
    read_run,
    same_files,
    write_curves,
    write_finished,
    write_policy,
)
from ede.run.spec import RunSpec, identity_difference, unshared_params
from tests.support import REPO

SPEC = RunSpec("ede/Point-v0", "td3", 3, 2_000, TD3Config(), EdeTD3Config())


def finished(out: Path, spec: RunSpec = SPEC) -> None:
    history = [
        {
            "step": s,
            "episode": s // 100,
            "mean_return": -50.0 + s / 100,
            "std_return": 1.0,
            "wall_seconds": s / 1e3,
        }
        for s in (0, 1_000, 2_000)
    ]
    write_curves(
        out,
        history,
        [{"step": 1_000, "updates": 900, "critic_loss": 0.5, "actor_loss": 2.0, "mean_q": -2.0}],
    )
    write_finished(out, spec, {"final_return": -30.0}, torch.device("cpu"))


def test_a_finished_run_reads_back_as_written(tmp_path: Path) -> None:
    finished(tmp_path)
    run = read_run(tmp_path, SPEC.identity())
    assert run is not None
    assert run.curve.seed == 3
    assert run.curve.steps.tolist() == [0, 1_000, 2_000]
    assert run.curve.returns.tolist() == [-50.0, -40.0, -30.0]
    assert run.diagnostics is not None and run.diagnostics["critic_loss"].tolist() == [0.5]
    assert run.made["seed"] == 3 and run.software == provenance.software_versions()


def test_a_run_without_metrics_is_not_finished(tmp_path: Path) -> None:
    finished(tmp_path)
    (tmp_path / "metrics.json").unlink()
    assert read_run(tmp_path, SPEC.identity()) is None


def test_another_runs_folder_is_rejected_naming_the_first_difference(tmp_path: Path) -> None:
    finished(tmp_path)
    other = RunSpec("ede/Point-v0", "td3", 3, 2_000, TD3Config(tau=0.01), EdeTD3Config())
    with pytest.raises(
        RunRejected,
        match=r"run.json: made with td3.tau = 0.005, but the params "
        r"say 0.01$",
    ):
        read_run(tmp_path, other.identity())
    with pytest.raises(RunRejected, match=r"run.json: seed is 3, expected 4$"):
        read_run(tmp_path, {"seed": 4})


def test_identity_difference_names_one_key_in_words() -> None:
    identity = SPEC.identity()
    assert identity_difference(identity, identity) is None
    assert identity_difference(None, identity) == "its identity is not recorded"
    assert identity_difference(identity, {"algo": "ede-td3"}) == 'algo is "td3", expected "ede-td3"'
    assert (identity_difference(identity, {"embedding": "abc"}) or "").startswith(
        "made with another embedding"
    )
    other = RunSpec("ede/Point-v0", "td3", 3, 2_000, TD3Config(hidden=[64]), EdeTD3Config())
    assert identity_difference(identity, other.identity()) == (
        "made with td3.hidden = [400, 300], but the params say [64]"
    )


def test_run_json_names_the_code_and_the_machine(tmp_path: Path) -> None:
    provenance.code_version.cache_clear()  # read once a process: the checkout's HEAD of now
    finished(tmp_path)
    made = json.loads((tmp_path / "run.json").read_text())
    root = Path(provenance.__file__).resolve().parents[2]
    head = subprocess.run(
        ["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, check=True
    ).stdout.strip()
    assert made["code"]["commit"] == head
    assert isinstance(made["code"]["modified"], bool)
    machine = made["machine"]
    assert machine["cpu"] and set(machine["instruction_sets"]) <= set(provenance.INSTRUCTION_SETS)
    assert machine["torch_cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    assert machine["torch_threads"] == torch.get_num_threads() and machine["gpu"] is None


def test_outside_a_checkout_the_commit_comes_from_the_build(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def no_git(*args: object, **kwargs: object) -> None:
        raise FileNotFoundError("git")

    monkeypatch.setattr(subprocess, "run", no_git)
    monkeypatch.setenv(provenance.COMMIT_ENV, "f" * 40)
    assert provenance.code_version.__wrapped__() == {"commit": "f" * 40, "modified": None}
    monkeypatch.delenv(provenance.COMMIT_ENV)
    assert provenance.code_version.__wrapped__() == {"commit": None, "modified": None}


def test_run_json_records_the_sha256_of_each_result_file(tmp_path: Path) -> None:
    """Of the files there when the run finishes, metrics.json's as written after run.json; the
    rest of run.json as before."""
    write_policy(tmp_path / "policy", {"w": torch.ones(2)}, {"k": 1})
    finished(tmp_path)
    made = json.loads((tmp_path / "run.json").read_text())
    assert made["sha256"] == {name: sha256(tmp_path / name) for name in CHECKSUMMED}
    assert set(made) == {*SPEC.identity(), "software", "code", "machine", "sha256"}
    assert {k: made[k] for k in SPEC.identity()} == SPEC.identity()
    finished(tmp_path / "no-policy")
    assert set(json.loads((tmp_path / "no-policy" / "run.json").read_text())["sha256"]) == {
        "eval.csv",
        "diagnostics.csv",
        "metrics.json",
    }


def change(path: Path) -> None:
    """The last digit of ``path`` changed: a CSV or JSON file still reads, to another number."""
    data = bytearray(path.read_bytes())
    at = max(i for i, byte in enumerate(data) if byte in b"0123456789")
    data[at] = ord("1") if data[at] != ord("1") else ord("2")
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("name", CHECKSUMMED)
def test_a_file_changed_after_its_run_finished_is_rejected_by_name(
    tmp_path: Path, name: str
) -> None:
    write_policy(tmp_path / "policy", {"w": torch.ones(2)}, {"k": 1})
    finished(tmp_path)
    recorded = json.loads((tmp_path / "run.json").read_text())["sha256"][name]
    change(tmp_path / name)
    with pytest.raises(RunRejected) as rejected:
        read_run(tmp_path, SPEC.identity())
    assert str(rejected.value) == (
        f"{tmp_path / name}: not the file its run wrote (SHA-256 "
        f"{sha256(tmp_path / name)[:12]}…, run.json records {recorded[:12]}…)"
    )


def test_a_published_copy_without_its_policy_reads_and_one_without_a_recorded_file_does_not(
    tmp_path: Path,
) -> None:
    write_policy(tmp_path / "policy", {"w": torch.ones(2)}, {"k": 1})
    finished(tmp_path)
    shutil.rmtree(tmp_path / "policy")  # as `experiment export` publishes it
    assert read_run(tmp_path, SPEC.identity()) is not None
    (tmp_path / "diagnostics.csv").unlink()
    with pytest.raises(RunRejected) as rejected:
        read_run(tmp_path, SPEC.identity())
    assert str(rejected.value) == (
        f"{tmp_path / 'diagnostics.csv'}: missing, though run.json records its SHA-256"
    )


def test_a_run_that_records_no_checksums_reads_as_it_is(tmp_path: Path) -> None:
    """Runs finished before run.json recorded checksums (the committed docs/results/runs)."""
    finished(tmp_path)
    made = json.loads((tmp_path / "run.json").read_text())
    del made["sha256"]
    (tmp_path / "run.json").write_text(json.dumps(made))
    change(tmp_path / "eval.csv")
    assert read_run(tmp_path, SPEC.identity()) is not None
    (tmp_path / "run.json").write_text(json.dumps({**made, "sha256": ["eval.csv"]}))
    with pytest.raises(RunRejected, match=r"run.json: 'sha256' is not a SHA-256 by file name"):
        read_run(tmp_path, SPEC.identity())


def without_checksums(folder: Path, how: str) -> None:
    """``folder``'s run.json with its checksums turned off ``how``: the key removed, set null, an
    empty record, eval.csv's entry alone removed, or diagnostics.csv's with the file."""
    made = json.loads((folder / "run.json").read_text())
    if how == "removed":
        del made["sha256"]
    elif how == "eval.csv's removed":
        del made["sha256"]["eval.csv"]
    elif how == "diagnostics.csv removed with its":
        del made["sha256"]["diagnostics.csv"]
        (folder / "diagnostics.csv").unlink()
    else:
        made["sha256"] = {"null": None, "empty": {}}[how]
    (folder / "run.json").write_text(json.dumps(made))


@pytest.mark.parametrize(
    ("how", "line"),
    [
        ("removed", "records no 'sha256' of the run's files; every run made since runs recorded "
                    "them does, and those published before are kept unchanged (ede/run/early_runs.py)"),
        ("null", "'sha256' is not a SHA-256 by file name (eval.csv, diagnostics.csv, "
                 "metrics.json, policy/policy.safetensors, policy/policy.json)"),
        ("empty", "'sha256' records no SHA-256 of eval.csv, diagnostics.csv, metrics.json; a run "
                  "records one for each of its files"),
        ("eval.csv's removed", "'sha256' records no SHA-256 of eval.csv; a run records one for "
                               "each of its files"),
        ("diagnostics.csv removed with its", "'sha256' records no SHA-256 of diagnostics.csv; a "
                                             "run records one for each of its files"),
    ],
)  # fmt: skip
def test_a_published_run_whose_checksums_are_turned_off_is_rejected(
    tmp_path: Path, how: str, line: str
) -> None:
    """Every run made since run.json recorded checksums has them: one published without them is
    refused however they went (a run read for the report alone, made before, reads without)."""
    finished(tmp_path)
    without_checksums(tmp_path, how)
    with pytest.raises(RunRejected) as rejected:
        read_run(tmp_path, SPEC.identity(), published=True)
    assert str(rejected.value) == f"{tmp_path / 'run.json'}: {line}"


def test_the_runs_published_before_checksums_are_read_byte_for_byte_as_published(
    tmp_path: Path,
) -> None:
    """A committed run without checksums reads as published; one of its files changed does not."""
    from ede.run.early_runs import EARLY_RUNS

    early = [
        made.parent
        for made in sorted((REPO / "docs" / "results").rglob("run.json"))
        if "sha256" not in json.loads(made.read_text())
    ]
    assert len(early) == len(EARLY_RUNS)
    copy = tmp_path / "run"
    shutil.copytree(early[0], copy)
    identity = {k: json.loads((copy / "run.json").read_text())[k] for k in ("task", "seed")}
    assert read_run(copy, identity, published=True) is not None
    change(copy / "eval.csv")
    with pytest.raises(RunRejected, match="records no 'sha256' of the run's files"):
        read_run(copy, identity, published=True)


@pytest.mark.parametrize("embedding", ["", "../../../elsewhere", "A" * 64, "ab" * 33])
def test_a_published_ede_td3_run_names_its_embedding_by_a_sha256(
    tmp_path: Path, embedding: str
) -> None:
    """A published folder keeps an embedding under the first characters of its checksum."""
    finished(tmp_path, RunSpec("ede/Point-v0", "ede-td3", 3, 2_000, TD3Config(), EdeTD3Config()))
    made = json.loads((tmp_path / "run.json").read_text())
    (tmp_path / "run.json").write_text(json.dumps({**made, "embedding": embedding}))
    with pytest.raises(RunRejected) as rejected:
        read_run(tmp_path, {}, published=True)
    assert str(rejected.value) == (
        f"{tmp_path / 'run.json'}: 'embedding' is {json.dumps(embedding)}; expected the SHA-256 "
        "of the decoder the run acted through (64 hexadecimal digits)"
    )


def test_two_runs_of_the_same_files_are_one_whatever_their_run_json_says(tmp_path: Path) -> None:
    finished(tmp_path / "seed3")
    shutil.copytree(tmp_path / "seed3", tmp_path / "seed4")
    made = json.loads((tmp_path / "seed4" / "run.json").read_text())
    (tmp_path / "seed4" / "run.json").write_text(json.dumps({**made, "seed": 4}))
    runs = []
    for seed in (3, 4):
        run = read_run(tmp_path / f"seed{seed}", {"seed": seed})
        assert run is not None
        runs.append((tmp_path / f"seed{seed}", run))
    assert same_files(runs[:1]) is None
    digest = sha256(tmp_path / "seed3" / "eval.csv")
    assert same_files(runs) == (
        f"{tmp_path / 'seed4'}: the same run as {tmp_path / 'seed3'} (their eval.csv's SHA-256 "
        f"are both {digest[:12]}…); a run is published once, in the folder of its own seed"
    )


def made_with(algo: Algo, td3: TD3Config | None = None) -> dict:
    """A run.json's identity: seed 0 of ``algo`` made with ``td3``."""
    return RunSpec("ede/Point-v0", algo, 0, 2_000, td3 or TD3Config(), EdeTD3Config()).identity()


def test_unshared_params_names_the_run_the_key_and_both_values() -> None:
    first, second = Path("runs/td3/seed0"), Path("runs/td3/seed1")
    assert unshared_params([(first, made_with("td3")), (second, made_with("td3"))]) is None
    assert unshared_params(
        [(first, made_with("td3")), (second, made_with("td3", TD3Config(lr=0.002)))]
    ) == (
        "runs/td3/seed1/run.json: made with td3.lr = 0.002, but runs/td3/seed0 was made with "
        "0.001; a task's runs share every param that changes a result"
    )
    # td3's params are shared by both algorithms.
    other = Path("runs/ede-td3/seed0")
    assert unshared_params(
        [(first, made_with("td3")), (other, made_with("ede-td3", TD3Config(tau=0.01)))]
    ) == (
        "runs/ede-td3/seed0/run.json: made with td3.tau = 0.01, but runs/td3/seed0 was made with "
        "0.005; a task's runs share every param that changes a result"
    )


def test_unshared_params_sets_aside_result_neutral_keys_and_ede_td3_for_td3_runs() -> None:
    td3, ede = made_with("td3"), made_with("ede-td3")
    older = json.loads(json.dumps(td3))
    older["params"]["td3"].update(device="cuda", threads=4, checkpoint_every=10)  # as recorded
    assert unshared_params([(Path("a"), td3), (Path("b"), older)]) is None
    wider = json.loads(json.dumps(ede))
    wider["params"]["ede_td3"]["bound_scale"] = 2.0
    assert unshared_params([(Path("td3/seed0"), td3), (Path("ede-td3/seed0"), wider)]) is None
    assert unshared_params(
        [(Path("td3/seed0"), td3), (Path("ede-td3/seed0"), ede), (Path("ede-td3/seed1"), wider)]
    ) == (
        "ede-td3/seed1/run.json: made with ede_td3.bound_scale = 2.0, but ede-td3/seed0 was made "
        "with 1.0; a task's runs share every param that changes a result"
    )
