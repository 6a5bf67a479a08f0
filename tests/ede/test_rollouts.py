"""Rollout stores: what is collected is what is read, windows, determinism, atomic writes."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zarr

from ede.io.rollouts import (
    ARRAYS,
    COLLECTOR_VERSION,
    Rollouts,
    RolloutsError,
    state_of,
    state_source,
    write_store,
)
from ede.run.collect import collect, row_bytes
from ede.tasks import action_bounds, make, simulator

ATTRS = {
    "env_id": "ede/Point-v0",
    "family": "point",
    "seed": 0,
    "num_envs": 1,
    "steps": 0,
    "spaces": {},
    "params": {},
}


def store_of(path: Path, arrays: dict[str, np.ndarray], env_id: str = "ede/Point-v0") -> Path:
    write_store(path, arrays, {**ATTRS, "env_id": env_id, "steps": len(arrays["reward"])})
    return path


def ragged(lengths: list[int], state_size: int = 3, action_size: int = 2) -> dict[str, np.ndarray]:
    """Hand-built rows of episodes of the given lengths; state[:, 0] is the global row index."""
    n = sum(lengths)
    state = np.zeros((n, state_size))
    state[:, 0] = np.arange(n)
    return {
        "obs": np.random.default_rng(0).normal(size=(n, 4)),
        "state": state,
        "action": np.arange(n * action_size, dtype=np.float32).reshape(n, action_size),
        "reward": np.zeros(n),
        "episode": np.repeat(np.arange(len(lengths)), lengths),
        "t": np.concatenate([np.arange(length) for length in lengths]).astype(np.int32),
    }


def direct_rollout(env_id: str, seed: int, index: int, steps: int) -> dict[str, np.ndarray]:
    """Sub-environment ``index`` of a collection, replayed with a plain reset/step loop."""
    env = make(env_id)
    rng = np.random.default_rng([seed, index, 1])
    low, high = (bound.astype(np.float64) for bound in action_bounds(env))
    rows: dict[str, list] = {"obs": [], "state": [], "action": [], "reward": []}
    obs, _ = env.reset(seed=seed + index)
    while len(rows["reward"]) < steps:
        action = rng.uniform(low, high).astype(np.float32)  # one action per call, no blocks
        rows["obs"].append(obs)
        rows["state"].append(state_of(env, obs))
        rows["action"].append(action)
        obs, reward, terminated, truncated, _ = env.step(action)
        rows["reward"].append(reward)
        if terminated or truncated:
            obs, _ = env.reset()
    env.close()
    return {key: np.asarray(value) for key, value in rows.items()}


def test_what_the_collector_stepped_is_what_the_reader_returns(tmp_path: Path) -> None:
    arrays = collect("ede/ReacherVertical-v0", steps=400, num_envs=2, seed=5, workers=1)
    rollouts = Rollouts.open(store_of(tmp_path / "r.zarr", arrays, "ede/ReacherVertical-v0"))
    assert len(rollouts) == 400 and rollouts.num_episodes == 4
    for index in range(2):  # sub-env i owns episodes 2i, 2i + 1
        rows = slice(200 * index, 200 * (index + 1))
        expected = direct_rollout("ede/ReacherVertical-v0", seed=5, index=index, steps=200)
        for key, value in expected.items():
            np.testing.assert_array_equal(getattr(rollouts, key)[rows], value, err_msg=key)
    np.testing.assert_array_equal(rollouts.t[:100], np.arange(100))
    np.testing.assert_array_equal(np.unique(rollouts.episode), np.arange(4))


def test_the_state_column_of_a_mujoco_task_is_qpos_then_qvel(tmp_path: Path) -> None:
    arrays = collect("ede/PointMass-v0", steps=100, num_envs=1, seed=0, workers=1)
    env = make("ede/PointMass-v0")
    env.reset(seed=0)
    data = simulator(env).data
    assert state_source(env) == "physics"
    np.testing.assert_array_equal(arrays["state"][0], np.concatenate([data.qpos, data.qvel]))


def test_the_state_column_of_a_task_without_mujoco_physics_is_its_observation(
    tmp_path: Path,
) -> None:
    assert state_source(make("Pendulum-v1")) == "observation"
    arrays = collect("Pendulum-v1", steps=400, num_envs=2, seed=3, workers=1)
    rollouts = Rollouts.open(store_of(tmp_path / "r.zarr", arrays, "Pendulum-v1"))
    assert len(rollouts) == 400 and rollouts.num_episodes == 2  # 200-step episodes
    assert rollouts.state.dtype == np.float64 and rollouts.obs.dtype == np.float32
    np.testing.assert_array_equal(rollouts.state, rollouts.obs)
    for index in range(2):  # the vector collector steps what a plain loop steps
        expected = direct_rollout("Pendulum-v1", seed=3, index=index, steps=200)
        for key, value in expected.items():
            np.testing.assert_array_equal(
                getattr(rollouts, key)[200 * index : 200 * (index + 1)], value, err_msg=key
            )
    state, actions, later = rollouts.windows(rollouts.window_starts(4), 4)
    assert (state.shape, actions.shape, later.shape) == ((392, 3), (392, 4, 1), (392, 3))


def test_a_task_ede_cannot_use_is_refused_before_any_step() -> None:
    with pytest.raises(ValueError, match=r"^CartPole-v1 cannot be used: its actions are Discrete"):
        collect("CartPole-v1", steps=10, num_envs=1, seed=0, workers=1)


def test_episodes_stay_whole_when_steps_do_not_divide() -> None:
    arrays = collect("ede/Point-v0", steps=250, num_envs=2, seed=0, workers=1)
    # 125 steps a sub-env, rounded up to whole 100-step episodes: 2 episodes each.
    assert len(arrays["reward"]) == 400
    np.testing.assert_array_equal(np.bincount(arrays["episode"]), [100] * 4)


def test_saturated_episodes_are_bang_bang_and_chosen_episode_by_episode() -> None:
    """``collect.saturated_episodes``: an episode's actions are all at the box's corners (each
    uniform draw snapped to the nearer bound) or all uniform, which ones drawn apart from the
    actions, so that the other episodes keep the uniform draws they have with none saturated."""
    env = make("ede/Point-v0")
    low, high = action_bounds(env)
    env.close()
    uniform = collect("ede/Point-v0", 2_000, 2, seed=0, workers=1)
    mixed = collect("ede/Point-v0", 2_000, 2, seed=0, workers=1, saturated=0.5)
    np.testing.assert_array_equal(
        mixed["action"],  # the worker count changes nothing
        collect("ede/Point-v0", 2_000, 2, 0, 2, saturated=0.5)["action"],
    )
    cornered = np.all((mixed["action"] == low) | (mixed["action"] == high), axis=1)
    episodes = [cornered[mixed["episode"] == e] for e in range(mixed["episode"][-1] + 1)]
    assert all(e.all() or not e.any() for e in episodes)  # whole episodes, one kind each
    saturated = np.concatenate([np.full(len(e), e.all()) for e in episodes])
    assert 0 < sum(e.all() for e in episodes) < len(episodes)  # 20 episodes at 0.5: some of each
    snapped = np.where(uniform["action"] < (low + high) / 2, low, high)
    np.testing.assert_array_equal(mixed["action"][saturated], snapped[saturated])
    np.testing.assert_array_equal(mixed["action"][~saturated], uniform["action"][~saturated])
    everything = collect("ede/Point-v0", 200, 1, seed=0, workers=1, saturated=1.0)["action"]
    assert np.all((everything == low) | (everything == high))
    with pytest.raises(ValueError, match=r"saturated is a share of episodes in \[0, 1\], got 1\.5"):
        collect("ede/Point-v0", 200, 1, seed=0, workers=1, saturated=1.5)


@pytest.mark.parametrize("env_id", ["ede/Pusher-v0", "Pendulum-v1"])
def test_a_rows_size_read_from_the_spaces_is_what_collect_records_a_step(env_id: str) -> None:
    """The collect stage sizes its memory check by :func:`row_bytes`, stepping nothing: a task
    whose state is its physics (22 values beside 23 observed) and one whose float32 observation
    is its float64 state."""
    arrays = collect(env_id, steps=1, num_envs=1, seed=0, workers=1)  # one whole episode
    assert row_bytes(env_id) * len(arrays["reward"]) == sum(a.nbytes for a in arrays.values())


@pytest.mark.parametrize("k", [1, 2, 4])
def test_windows_never_cross_an_episode_end_and_every_start_is_reachable(
    tmp_path: Path, k: int
) -> None:
    lengths = [3, 7, 1, 5, 4, 9]
    rollouts = Rollouts.open(store_of(tmp_path / "r.zarr", ragged(lengths)))
    starts = rollouts.window_starts(k)
    expected, row = [], 0
    for length in lengths:
        expected += [row + t for t in range(length - k)]  # state[t + k] is a row of the episode
        row += length
    np.testing.assert_array_equal(starts, expected)
    state, actions, later = rollouts.windows(starts, k)
    assert actions.shape == (len(starts), k, 2)
    np.testing.assert_array_equal(later[:, 0] - state[:, 0], k)  # k rows on, same episode
    assert np.all(rollouts.episode[starts] == rollouts.episode[starts + k])
    np.testing.assert_array_equal(actions[:, 0], rollouts.action[starts])
    np.testing.assert_array_equal(actions[:, -1], rollouts.action[starts + k - 1])


def test_windows_can_be_restricted_to_episodes(tmp_path: Path) -> None:
    rollouts = Rollouts.open(store_of(tmp_path / "r.zarr", ragged([6, 6, 6])))
    starts = rollouts.window_starts(2, episodes=np.array([1]))
    np.testing.assert_array_equal(starts, [6, 7, 8, 9])


def test_whitening_of_state_and_k_step_change(tmp_path: Path) -> None:
    rollouts = Rollouts.open(store_of(tmp_path / "r.zarr", ragged([10, 10])))
    state_white, delta_white = rollouts.whitening(3)
    starts = rollouts.window_starts(3)
    np.testing.assert_allclose(state_white.mean[0], rollouts.state[starts, 0].mean())
    np.testing.assert_allclose(delta_white.mean, [3.0, 0.0, 0.0])
    np.testing.assert_allclose(delta_white.std, [1.0, 1.0, 1.0])  # constant columns: unscaled
    whitened = state_white.apply(rollouts.state[starts])
    np.testing.assert_allclose(whitened[:, 0].mean(), 0, atol=1e-12)
    np.testing.assert_allclose(whitened[:, 0].std(), 1)


def test_change_whitening_pooled_over_every_step_as_the_authors_code(tmp_path: Path) -> None:
    # Column 0 counts steps, so its changes after 0..3 steps are 0, 1, 2, 3 in every window.
    # Column 1 is a random walk, whose change spreads more the more steps it spans.
    data = ragged([30, 30])
    data["state"][:, 1] = np.random.default_rng(0).normal(size=60).cumsum()
    rollouts = Rollouts.open(store_of(tmp_path / "r.zarr", data))
    final = rollouts.whitening(3)[1]
    state_white, pooled = rollouts.whitening(3, change="all")
    np.testing.assert_allclose(pooled.mean[0], 1.5)
    np.testing.assert_allclose(pooled.std[0], np.std([0, 1, 2, 3]))
    np.testing.assert_allclose(state_white.mean, rollouts.whitening(3)[0].mean)  # state: unchanged
    starts = rollouts.window_starts(3)
    change = rollouts.state[starts + 3] - rollouts.state[starts]
    assert pooled.std[1] < final.std[1]
    assert pooled.apply(change)[:, 1].std() > 1.2  # the target's variance exceeds 1
    with pytest.raises(ValueError, match="'final' or 'all'"):
        rollouts.whitening(3, change="mixed")


def test_same_seed_same_store_byte_for_byte_other_seed_differs(tmp_path: Path) -> None:
    def files(path: Path) -> dict[str, bytes]:
        return {
            str(f.relative_to(path)): f.read_bytes() for f in sorted(path.rglob("*")) if f.is_file()
        }

    one = store_of(tmp_path / "a.zarr", collect("ede/Point-v0", 300, 3, seed=1, workers=1))
    two = store_of(tmp_path / "b.zarr", collect("ede/Point-v0", 300, 3, seed=1, workers=2))
    other = collect("ede/Point-v0", 300, 3, seed=2, workers=1)
    assert files(one) == files(two)  # also: the worker count changes nothing
    assert not np.array_equal(other["state"], Rollouts.open(one).state)


def test_a_foreign_store_is_refused(tmp_path: Path) -> None:
    path = store_of(tmp_path / "r.zarr", ragged([5]))
    with pytest.raises(RolloutsError, match=r"collected on ede/Point-v0.*expected ede/Pusher-v0"):
        Rollouts.open(path, env_id="ede/Pusher-v0")


def test_a_store_missing_a_chunk_is_refused(tmp_path: Path) -> None:
    path = store_of(tmp_path / "r.zarr", ragged([50]))
    chunk = next((path / "state" / "c").rglob("*"))
    while chunk.is_dir():
        chunk = next(chunk.iterdir())
    chunk.unlink()  # Zarr would read it back as fill values: only the fingerprint can tell
    with pytest.raises(RolloutsError, match="fingerprint"):
        Rollouts.open(path)


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("env_id", "ede/PointMass-v0"),
        ("family", "pointmass"),
        ("params", {"collect": {"seed": 1}}),
        ("seed", 1),
        ("spaces", {"action_low": [-2.0, -2.0]}),
    ],
)
def test_a_store_whose_attributes_were_edited_is_refused(
    tmp_path: Path, key: str, value: Any
) -> None:
    path = store_of(tmp_path / "r.zarr", ragged([5, 5]))
    Rollouts.open(path)  # untouched, it opens
    zarr.open_group(path, mode="a").attrs[key] = value  # same arrays, same shapes
    with pytest.raises(RolloutsError) as raised:
        Rollouts.open(path)
    message = str(raised.value)
    assert message.startswith(f"{path}: ") and "fingerprint" in message and "\n" not in message
    assert "arrays or attributes were changed" in message


def test_an_edited_env_id_is_refused_as_edited_not_as_foreign(tmp_path: Path) -> None:
    path = store_of(tmp_path / "r.zarr", ragged([5]))
    zarr.open_group(path, mode="a").attrs["env_id"] = "ede/PointMass-v0"
    with pytest.raises(RolloutsError, match="fingerprint"):
        Rollouts.open(path, env_id="ede/PointMass-v0")


def test_the_software_versions_are_not_part_of_the_fingerprint(tmp_path: Path) -> None:
    # They name the machine that wrote the store, not its content: the same rollouts collected
    # in the container and on the host share a fingerprint (scripts/container-test.sh).
    one = store_of(tmp_path / "a.zarr", ragged([5]))
    two = tmp_path / "b.zarr"
    write_store(two, ragged([5]), {**ATTRS, "steps": 5, "software": {"python": "0.0"}})
    assert Rollouts.open(one).attrs["fingerprint"] == Rollouts.open(two).attrs["fingerprint"]


def test_a_store_of_an_older_collector_is_refused_in_one_line(tmp_path: Path) -> None:
    path = store_of(tmp_path / "r.zarr", ragged([5]))
    zarr.open_group(path, mode="a").attrs["collector"] = COLLECTOR_VERSION - 1
    with pytest.raises(RolloutsError) as raised:
        Rollouts.open(path)
    assert str(raised.value) == (
        f"{path}: written by collector version {COLLECTOR_VERSION - 1}, but this code reads "
        f"version {COLLECTOR_VERSION} only; collect it again (`ede-pipeline collect`)"
    )


def test_arrays_of_unequal_length_are_refused(tmp_path: Path) -> None:
    path = store_of(tmp_path / "r.zarr", ragged([5, 5]))
    group = zarr.open_group(path, mode="a")
    del group["reward"]
    group.create_array("reward", data=np.zeros(7))
    with pytest.raises(RolloutsError, match="differ in length"):
        Rollouts.open(path)


def test_interleaved_episodes_are_refused(tmp_path: Path) -> None:
    arrays = ragged([4, 4])
    arrays["episode"] = np.array([0, 1, 0, 1, 0, 1, 0, 1])
    with pytest.raises(RolloutsError, match="contiguous"):
        Rollouts.open(store_of(tmp_path / "r.zarr", arrays))


@pytest.mark.parametrize("what", ["attribute", "array", "store"])
def test_incomplete_stores_are_refused_with_the_path(tmp_path: Path, what: str) -> None:
    path = store_of(tmp_path / "r.zarr", ragged([5]))
    if what == "attribute":
        group = zarr.open_group(path, mode="a")
        attrs = dict(group.attrs)
        del attrs["fingerprint"]
        group.attrs.clear()
        group.attrs.update(attrs)
    elif what == "array":
        del zarr.open_group(path, mode="a")["t"]
    else:
        (path / "zarr.json").unlink()
    with pytest.raises(RolloutsError, match=str(path)):
        Rollouts.open(path)


def test_write_replaces_an_old_store_and_clears_stale_temporaries(tmp_path: Path) -> None:
    path = tmp_path / "r.zarr"
    stale = tmp_path / "r.zarr.tmp-999999"
    stale.mkdir()
    store_of(path, ragged([5]))
    store_of(path, ragged([3, 3]))
    assert Rollouts.open(path).num_episodes == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.zarr"]
    assert set(ARRAYS) <= {p.name for p in path.iterdir()}
