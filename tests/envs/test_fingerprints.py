"""Every task's rollouts are the same bits on every machine: a recorded fingerprint per task.

The fingerprints were recorded on one machine and must hold on every other: observations, MuJoCo
state and rewards come only from MuJoCo (compiled once, no run-time CPU dispatch) and from the
fixed-order arithmetic of ``ede_envs._numerics``. A deliberate change of a task or of the locked
simulator (mujoco, gymnasium, numpy in ``requirements.lock``) changes them: then re-record them
with ``python tests/envs/test_fingerprints.py`` and say why in the commit.
"""

from __future__ import annotations

import hashlib
import math
import sys

import numpy as np
import pytest

import ede_envs
from ede.tasks import action_bounds, make, simulator
from ede_envs._numerics import cos_sin, norm, sum_of_squares

STEPS = 250  # two and a half episodes: resets inside the rollout are covered

FINGERPRINTS = {
    "ede/ReacherVertical-v0": "474bce1381ed8c05530a5a0691795bd5",
    "ede/ReacherTurn-v0": "69d9b4fbfba51b901c81e8f3b46b8aaa",
    "ede/ReacherPush-v0": "cbe82faed9f98ee29f06a2fa13aba7a8",
    "ede/Pusher-v0": "81deef4fd159ba8082cc2a736ebbc02b",
    "ede/Striker-v0": "eed94981f57881f8b6e293b16bac68c4",
    "ede/Point-v0": "e732f586aa5d312cbf93f77aedd19f04",
    "ede/PointMass-v0": "e55eaa95d05e63fdeea8d48e2bdbdaa0",
}


def fingerprint(task: str) -> str:
    """SHA-256 of a seeded rollout of uniform random actions: observations, state and rewards."""
    env = make(task)
    low, high = action_bounds(env)
    actions = (
        np.random.default_rng(0).uniform(low, high, size=(STEPS, *low.shape)).astype(np.float32)
    )
    digest = hashlib.sha256()

    def record(*arrays: object) -> None:
        for array in arrays:
            digest.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())

    data = simulator(env).data
    obs, _ = env.reset(seed=0)
    record(obs, data.qpos, data.qvel)
    for action in actions:
        obs, reward, terminated, truncated, _ = env.step(action)
        record(obs, data.qpos, data.qvel, [reward, terminated, truncated])
        if terminated or truncated:
            obs, _ = env.reset()
            record(obs, data.qpos, data.qvel)
    env.close()
    return digest.hexdigest()[:32]


@pytest.mark.parametrize("task", list(ede_envs.TASKS))
def test_a_tasks_rollout_matches_its_recorded_fingerprint(task: str) -> None:
    assert task in FINGERPRINTS, f"no fingerprint recorded for {task}"
    assert fingerprint(task) == FINGERPRINTS[task], (
        f"{task}: the rollout's bits changed. If the task or the locked simulator changed on "
        "purpose, re-record (python tests/envs/test_fingerprints.py); otherwise some step, "
        "reward or observation now depends on the machine"
    )


def misaligned(values: np.ndarray) -> np.ndarray:
    """A copy of ``values`` whose data starts 8 bytes past a 64-byte boundary."""
    buffer = np.zeros(values.size + 16, dtype=np.float64)
    shift = (-buffer.ctypes.data % 64) // 8 + 1
    view = buffer[shift : shift + values.size]
    view[:] = values
    assert view.ctypes.data % 64 == 8
    return view


def test_norms_do_not_depend_on_memory_alignment_and_are_correctly_summed() -> None:
    rng = np.random.default_rng(0)
    for size in (2, 3, 7, 23):
        for _ in range(200):
            v = rng.normal(size=size)
            assert norm(v) == norm(misaligned(v))
            expected = 0.0
            for x in v.tolist():
                expected += x * x
            assert sum_of_squares(v) == expected and norm(v) == math.sqrt(expected)
            assert abs(norm(v) - math.hypot(*v.tolist())) <= 2 * math.ulp(norm(v))
    assert norm([3.0, 4.0]) == 5.0


def test_cos_sin_is_the_c_librarys_angle_by_angle() -> None:
    angles = np.random.default_rng(1).uniform(-10, 10, size=5)
    got = cos_sin(angles)
    assert got.tolist() == [math.cos(a) for a in angles] + [math.sin(a) for a in angles]


if __name__ == "__main__":  # re-record: prints the dictionary to paste above
    print("FINGERPRINTS = {")
    for task in ede_envs.TASKS:
        print(f'    "{task}": "{fingerprint(task)}",')
    print("}")
    sys.exit(0)
