"""What made an output: the versions of the software that decides a stage's results, the code
(its commit) and the machine (what of a CPU changes a result's last bits)."""

from __future__ import annotations

import os
import platform
import subprocess
from functools import cache
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import torch

__all__ = [
    "CODE",
    "INSTRUCTION_SETS",
    "SOFTWARE",
    "code_version",
    "describe_software",
    "machine",
    "software_versions",
]

# Python, the array and learning libraries, and the simulator. Each is pinned by
# requirements.lock; recording them beside every output says which pins made it.
SOFTWARE = ("python", "numpy", "torch", "mujoco", "gymnasium")


def software_versions() -> dict[str, str]:
    """``{"python": "3.11.7", "numpy": …, "torch": …, "mujoco": …, "gymnasium": …}``."""
    versions = {"python": platform.python_version()}
    for name in SOFTWARE[1:]:
        try:
            versions[name] = version(name)
        except PackageNotFoundError:
            versions[name] = "not installed"
    return versions


def describe_software(versions: dict[str, str] | None) -> str:
    """One line for people: ``Python 3.11.7, numpy 2.4.6, …``; ``unrecorded`` for ``None``."""
    if not versions:
        return "unrecorded"
    return ", ".join(
        f"{'Python' if name == 'python' else name} {value}" for name, value in versions.items()
    )


COMMIT_ENV = "EDE_COMMIT"  # the commit an installed copy (the image) was built from
# CPU features whose kernels round differently (oneDNN and MKL pick their paths by them): two
# machines that differ here may differ in a result's last bits, and so, over a run, in its curve.
INSTRUCTION_SETS = ("avx2", "avx512f", "avx512_bf16", "amx_tile", "amx_bf16")


CODE = ("ede", "envs", "pipeline")  # the packages' folders (pyproject.toml's package-dir)


@cache
def code_version() -> dict[str, Any]:
    """The code that runs: ``{"commit": …, "modified": …}``.

    From git where the ``ede`` package is imported from a checkout (an editable install, or an
    experiment's working copy): ``modified`` says whether a tracked file of the code (:data:`CODE`;
    not params.yaml or dvc.lock, which a run records apart) differed from the commit. Elsewhere (an installed
    copy, as in the image) the commit is ``$EDE_COMMIT`` when set at build time, ``modified``
    unknown (null); with neither, both are null.
    """
    root = Path(__file__).resolve().parents[2]  # ede/io/provenance.py: the checkout

    def git(*args: str) -> str | None:
        done = subprocess.run(
            ["git", "-C", str(root), *args], capture_output=True, text=True, timeout=30
        )
        return done.stdout.strip() if done.returncode == 0 else None

    try:
        # The checkout's own top level: not a venv's site-packages inside some checkout.
        if git("rev-parse", "--show-toplevel") == str(root):
            commit, status = (
                git("rev-parse", "HEAD"),
                git("status", "--porcelain", "--untracked-files=no", "--", *CODE),
            )
            if commit is not None and status is not None:
                return {"commit": commit, "modified": bool(status)}
    except (OSError, subprocess.SubprocessError):  # no git, or it hung
        pass
    return {"commit": os.environ.get(COMMIT_ENV) or None, "modified": None}


def machine(device: torch.device | None = None) -> dict[str, Any]:
    """The machine that computes: CPU model, which of :data:`INSTRUCTION_SETS` it has, the kernels
    torch picked for it (its CPU capability), torch's threads, and the GPU where ``device`` is
    one."""
    import torch  # here: the stages that record only software versions need no torch

    model, flags = _cpu()
    return {
        "cpu": model,
        "instruction_sets": [name for name in INSTRUCTION_SETS if name in flags],
        "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "torch_threads": torch.get_num_threads(),
        "gpu": torch.cuda.get_device_name(device)
        if device is not None and device.type == "cuda"
        else None,
    }


@cache
def _cpu() -> tuple[str, frozenset[str]]:
    """The CPU's model name and flags (Linux's /proc/cpuinfo; elsewhere the platform's name)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return platform.processor() or platform.machine(), frozenset()
    fields: dict[str, str] = {}
    for line in text.splitlines():
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    return (
        fields.get("model name") or platform.processor() or platform.machine(),
        frozenset(fields.get("flags", "").split()),
    )
