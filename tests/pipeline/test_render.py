"""``ede-pipeline render``'s bounds and refusals, on a policy made here (no training): the frames
stream to the encoder, ``--episodes`` is bounded before any work, and a policy that disagrees
with its run, a file in another encoding, a bad ``MUJOCO_GL`` and a write that fails midway are
each one line. (Playing a trained policy: tests/pipeline/test_train.py.)"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import weakref
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner, Result
from safetensors.torch import load_file, save_file

from ede.analysis.video import MAX_FRAMES, encode
from ede.config import EdeTD3Config, TD3Config
from ede.io.atomic import sha256
from ede.method.td3 import Actor
from ede.run.runs import write_policy
from ede.run.spec import RunSpec
from ede_pipeline.cli import main

TASK = "ede/Point-v0"  # 2 actions, observations of 4, episodes of 100 steps


def run(*args: str) -> Result:
    return CliRunner().invoke(main, list(args))


def one_line(result: Result, code: int, said: str) -> None:
    assert result.exit_code == code, result.output
    assert said in result.output and result.output.count("\n") == 1, result.output


@pytest.fixture
def policy_run(write_params: Callable[..., Path], tmp_path: Path, monkeypatch) -> Path:
    """A TD3 run of ede/Point-v0 with an untrained final policy, and a run.json that records the
    identity its policy.json repeats (no checksums: as a run made before them)."""
    write_params()
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MUJOCO_GL", "egl")
    hidden, low, high = [8], torch.full((2,), -1.0), torch.ones(2)
    actor = Actor(4, low, high, hidden)
    spec = RunSpec(TASK, "td3", 0, 1_000, TD3Config(hidden=hidden), EdeTD3Config())
    meta = {
        **spec.identity(),
        "k": 1,
        "code_size": 2,
        "code_low": low.tolist(),
        "code_high": high.tolist(),
        "hidden": hidden,
    }
    folder = tmp_path / "run"
    write_policy(
        folder / "policy", actor.export(actor.initial(torch.Generator().manual_seed(0))), meta
    )
    (folder / "run.json").write_text(json.dumps(spec.identity()))
    return folder


def listing(path: Path) -> list[str]:
    return sorted(str(p.relative_to(path)) for p in path.rglob("*"))


def test_render_plays_a_policy_made_here(policy_run: Path) -> None:
    done = run("render", str(policy_run), "--out", "v.mp4")  # (episodes in a row: test_train.py)
    assert done.exit_code == 0, done.output
    assert done.output.startswith("v.mp4: 100 frames, ede/Point-v0 td3 seed 0; returns ")


@pytest.mark.parametrize(("suffix", "fits"), [(".mp4", 100), (".gif", 10)])
def test_episodes_beyond_a_videos_frames_are_refused_before_any_work(
    policy_run: Path, suffix: str, fits: int
) -> None:
    before = listing(policy_run.parent)
    start = time.perf_counter()
    done = run("render", str(policy_run), "--episodes", "1000000000", "--out", f"v{suffix}")
    assert time.perf_counter() - start < 30
    kind = "an MP4" if suffix == ".mp4" else "a GIF"
    one_line(
        done,
        2,
        f"--episodes 1000000000: at most {fits} of ede/Point-v0 (episodes of up to 100 steps) "
        f"fit in {kind} of {MAX_FRAMES[suffix]:,} frames",
    )
    assert listing(policy_run.parent) == before
    assert fits * 100 == MAX_FRAMES[suffix]
    done = run("render", str(policy_run), "--episodes", str(fits + 1), "--out", f"v{suffix}")
    assert done.exit_code == 2 and listing(policy_run.parent) == before


@pytest.mark.parametrize("suffix", [".mp4", ".gif"])
def test_frames_go_to_the_encoder_as_they_are_made(tmp_path: Path, suffix: str) -> None:
    """No frame is kept once encoded: at most the one being encoded and the next are alive
    (a GIF keeps a halved copy of every other frame for its palette, not the frame)."""
    alive: list[weakref.ref] = []
    most = 0

    def frames() -> Iterator[np.ndarray]:
        nonlocal most
        for n in range(40):
            frame = np.full((480, 480, 3), 6 * n, dtype=np.uint8)
            alive.append(weakref.ref(frame))
            most = max(most, sum(ref() is not None for ref in alive))
            yield frame
            del frame

    assert encode(frames(), 20.0, suffix, tmp_path / f"v{suffix}") == 40
    assert most <= 2, most
    assert (tmp_path / f"v{suffix}").stat().st_size > 0


def edit_policy(folder: Path, change: Callable[[dict], None]) -> None:
    meta = json.loads((folder / "policy/policy.json").read_text())
    change(meta)
    (folder / "policy/policy.json").write_text(json.dumps(meta))


def edit_tensors(folder: Path, change: Callable[[dict], None]) -> None:
    tensors = load_file(folder / "policy/policy.safetensors")
    change(tensors)
    save_file(tensors, folder / "policy/policy.safetensors")


POLICY_JSON, WEIGHTS = "run/policy/policy.json", "run/policy/policy.safetensors"
DISAGREEING: dict[str, tuple[Callable[[Path], object], str]] = {
    "another task": (
        lambda f: edit_policy(f, lambda m: m.update(task="ede/PointMass-v0")),
        f"{POLICY_JSON}: not the policy of the run its run.json describes (task is "
        '"ede/PointMass-v0", expected "ede/Point-v0")',
    ),
    "another algorithm": (
        lambda f: edit_policy(f, lambda m: m.update(algo="ede-td3")),
        f'{POLICY_JSON}: not the policy of the run its run.json describes (algo is "ede-td3"',
    ),
    "another seed": (
        lambda f: edit_policy(f, lambda m: m.update(seed=3)),
        f"{POLICY_JSON}: not the policy of the run its run.json describes (seed is 3, expected 0)",
    ),
    "hidden not widths": (
        lambda f: edit_policy(f, lambda m: m.update(hidden=["8"])),
        f"{POLICY_JSON}: hidden.0: Input should be a valid integer",
    ),
    "params not a mapping": (
        lambda f: edit_policy(f, lambda m: m.update(params=[1])),
        f"{POLICY_JSON}: params: Input should be a valid dictionary",
    ),
    "an EDE-TD3 policy without its bound": (
        lambda f: edit_policy(f, lambda m: m.update(algo="ede-td3", params={"ede_td3": {}})),
        f"{POLICY_JSON}: params.ede_td3.bound_scale: expected a number",
    ),
    "a box of another size": (
        lambda f: edit_policy(f, lambda m: m.update(code_size=3)),
        f"{POLICY_JSON}: code_low and code_high: expected 3 numbers each",
    ),
    "other hidden widths": (
        lambda f: edit_policy(f, lambda m: m.update(hidden=[16])),
        f"{WEIGHTS}: not the actor policy.json describes (net.0.weight of shape [8, 4], "
        "expected [16, 4]: an actor of layers [4, 16, 2] for ede/Point-v0)",
    ),
    "weights of another shape": (
        lambda f: edit_tensors(f, lambda t: t.update({"net.2.weight": torch.zeros(2, 9)})),
        f"{WEIGHTS}: not the actor policy.json describes (net.2.weight of shape [2, 9], "
        "expected [2, 8]",
    ),
    "a missing tensor": (
        lambda f: edit_tensors(f, lambda t: t.pop("centre")),
        f"{WEIGHTS}: not the actor policy.json describes (no tensor centre",
    ),
    "a layer of another type": (
        lambda f: edit_tensors(f, lambda t: t.update({"net.0.bias": t["net.0.bias"].double()})),
        f"{WEIGHTS}: not the actor policy.json describes (layers other than float32",
    ),
    "policy.json in UTF-16": (
        lambda f: (f / "policy/policy.json").write_text(
            (f / "policy/policy.json").read_text(), encoding="utf-16"
        ),
        "run/policy: unreadable (",
    ),
    "policy.json with bytes not UTF-8": (
        lambda f: (f / "policy/policy.json").write_bytes(b'{"task": "\xff"}'),
        "run/policy: unreadable (",
    ),
    "run.json in UTF-16": (
        lambda f: (f / "run.json").write_text((f / "run.json").read_text(), encoding="utf-16"),
        "run/run.json: not JSON (",
    ),
    "run.json with bytes not UTF-8": (
        lambda f: (f / "run.json").write_bytes(b"\xfe\xff{}"),
        "run/run.json: not JSON (",
    ),
}


@pytest.mark.parametrize("case", DISAGREEING)
def test_a_policy_that_disagrees_with_its_run_is_one_line_naming_the_file(
    policy_run: Path, case: str
) -> None:
    damage, said = DISAGREEING[case]
    damage(policy_run)
    before = listing(policy_run.parent)
    one_line(run("render", str(policy_run), "--out", "v.mp4"), 2, said)
    assert listing(policy_run.parent) == before


def test_checksummed_policy_files_are_checked_before_they_are_read(policy_run: Path) -> None:
    """(A run made since checksums exist: a changed policy file is not its run's.)"""
    made = json.loads((policy_run / "run.json").read_text())
    for name in ("eval.csv", "diagnostics.csv", "metrics.json"):  # a finished run's other files
        (policy_run / name).write_text("")
    made["sha256"] = {
        name: sha256(policy_run / name)
        for name in (
            "eval.csv",
            "diagnostics.csv",
            "metrics.json",
            "policy/policy.json",
            "policy/policy.safetensors",
        )
    }
    (policy_run / "run.json").write_text(json.dumps(made))
    edit_policy(policy_run, lambda m: m.update(hidden=[16]))
    one_line(run("render", str(policy_run)), 2, "policy.json: not the file its run wrote")


def cli(args: list[str], env: dict[str, str], prelude: str = "") -> subprocess.CompletedProcess:
    code = f"{prelude}\nimport sys\nfrom ede_pipeline.cli import main\nmain(sys.argv[1:])"
    return subprocess.run(
        [sys.executable, "-c", code, *args],
        env={**os.environ, **env},
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_a_mujoco_gl_that_mujoco_refuses_is_one_line_before_the_video_module(
    policy_run: Path,
) -> None:
    done = cli(["render", str(policy_run), "--out", "v.mp4"], {"MUJOCO_GL": "junk"})
    assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
    assert done.stderr.startswith("Error: MUJOCO_GL=junk: MuJoCo cannot start with it")
    assert not Path("v.mp4").exists()


# A write that fails midway (tests/pipeline/test_outputs.py): each file this process and ffmpeg
# write may hold at most this many bytes, as a full disk would stop them.
LIMITED = """
import resource, signal
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (3_000, 3_000))
"""


@pytest.mark.parametrize("suffix", [".mp4", ".gif"])
def test_a_video_that_fails_midway_is_one_line_and_leaves_nothing(
    policy_run: Path, suffix: str
) -> None:
    before = listing(policy_run.parent)
    args = ["render", str(policy_run), "--out", f"v{suffix}"]
    done = cli(args, {}, prelude=LIMITED)
    assert done.returncode == 1 and done.stderr.count("\n") == 1, done.stderr
    assert done.stderr.startswith(f"Error: v{suffix}: not written (File too large)"), done.stderr
    assert listing(policy_run.parent) == before


@pytest.mark.parametrize(
    "meta",
    ['{"kind": "ede-encoder"}'.encode("utf-16"), b'{"kind": "\xff"}'],
    ids=["utf-16", "bytes"],
)
def test_an_embedding_meta_not_utf8_json_is_one_line(policy_run: Path, meta: bytes) -> None:
    for name in ("policy/policy.json", "run.json"):  # an EDE-TD3 run: it acts through its embedding
        edit = json.loads((policy_run / name).read_text())
        (policy_run / name).write_text(json.dumps({**edit, "algo": "ede-td3"}))
    for part in ("encoder", "decoder"):
        Path(part).mkdir()
        (Path(part) / "meta.json").write_bytes(meta)
        (Path(part) / "weights.safetensors").write_bytes(b"")
    done = run("render", str(policy_run), "--encoder", "encoder", "--decoder", "decoder")
    one_line(done, 2, "decoder/meta.json: Invalid JSON: ")


def test_a_pages_clip_that_fails_midway_names_itself_as_not_written(tmp_path: Path) -> None:
    """(The report's clips: its command turns this into one line, exit 1.)"""
    code = LIMITED + (
        "import numpy as np\n"
        "from pathlib import Path\n"
        "from ede.io.atomic import NotWritten\n"
        "from ede.analysis.video import video_bytes\n"
        "frames = (np.random.default_rng(n).integers(0, 255, (64, 64, 3), np.uint8)"
        " for n in range(50))\n"
        "try:\n"
        "    video_bytes(frames, 20.0, Path('clip-x.mp4'))\n"
        "except NotWritten as error:\n"
        "    print(error.strerror)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path
    )
    assert done.stdout.startswith("clip-x.mp4: not written (File too large)"), done
