"""The per-task replay buffer's pickle: only the rows in use are written, and a loaded buffer samples the same batches."""

from __future__ import annotations

import pickle

import numpy as np
from gymnasium import spaces

from sb3_pearl.common.buffers import TaskReplayBuffer, gather_rows

OBS = spaces.Box(-1.0, 1.0, (3,), np.float32)
ACT = spaces.Box(-1.0, 1.0, (2,), np.float32)


def filled_buffer() -> TaskReplayBuffer:
    """Four tasks of capacity 50: 40 rows, 3 rows, none, and a ring that wrapped (60 adds); task 1 cleared once."""
    buffer = TaskReplayBuffer(4, 50, OBS, ACT)
    rng = np.random.default_rng(0)

    def add(task: int, n: int) -> None:
        for _ in range(n):
            buffer.add(task, rng.normal(size=3), rng.normal(size=2), float(rng.normal()), rng.normal(size=3), False, True)

    add(0, 40)
    add(1, 30)
    buffer.clear(1)  # rows 3..29 of task 1 are stale: never sampled, not written
    add(1, 3)
    add(3, 60)
    return buffer


def test_pickle_holds_the_rows_in_use_only_and_loads_to_the_same_samples() -> None:
    buffer = filled_buffer()
    np.testing.assert_array_equal(buffer.size, [40, 3, 0, 50])
    state = buffer.__getstate__()
    assert state["layout"] == "rows-in-use-shared-next"
    assert state["observations"].shape == (40 + 3 + 0 + 50, 3)  # not (4, 50, 3): the largest task does not pad the rest
    np.testing.assert_array_equal(state["rewards"][40:43, 0], buffer.rewards[1, :3, 0])

    pickled = pickle.dumps(buffer)
    loaded = pickle.loads(pickled)
    assert pickle.dumps(loaded) == pickled  # a loaded buffer saved again writes the same bytes
    assert loaded.observations.shape == (4, 50, 3) and loaded.capacity == 50
    np.testing.assert_array_equal(loaded.pos, buffer.pos)
    np.testing.assert_array_equal(loaded.size, buffer.size)
    for name in TaskReplayBuffer._ARRAYS:
        for task, n in enumerate(buffer.size):
            np.testing.assert_array_equal(getattr(loaded, name)[task, :n], getattr(buffer, name)[task, :n])
    assert not loaded.observations[1, 3:].any()  # the stale rows are gone, where the original still holds them
    assert buffer.observations[1, 3:30].any()

    tasks = np.array([0, 1, 3, 3])
    np.random.seed(7)
    expected = buffer.sample(tasks, 16)
    np.random.seed(7)
    got = loaded.sample(tasks, 16)
    assert expected.returns is None and got.returns is None  # no Monte-Carlo returns unless asked for
    for a, b in zip(expected[:-1], got[:-1]):
        assert a.shape == (4, 16, a.shape[-1])
        np.testing.assert_array_equal(a.numpy(), b.numpy())

    loaded.add(1, np.ones(3), np.ones(2), 1.0, np.ones(3), True, False)  # keeps filling where it stopped
    assert loaded.size[1] == 4 and loaded.dones[1, 3, 0] == 1.0


def test_a_padded_pickle_of_an_earlier_version_still_loads() -> None:
    buffer = filled_buffer()
    state = buffer.__dict__.copy()
    for name in TaskReplayBuffer._ARRAYS:
        state[name] = getattr(buffer, name)[:, :50].copy()  # the earlier layout: (n_tasks, largest size, dim)
    old = TaskReplayBuffer.__new__(TaskReplayBuffer)
    old.__setstate__(state)
    for name in TaskReplayBuffer._ARRAYS:
        np.testing.assert_array_equal(getattr(old, name), getattr(buffer, name))


def test_next_observations_shared_with_the_following_rows_are_written_once_and_load_bit_for_bit() -> None:
    """Trajectories: each row's next observation is the next row's observation except at an episode's end, at a task's
    last row and where a ring wrapped; only those are written, and the loaded buffer has the same bits (-0.0, NaN)."""
    buffer = TaskReplayBuffer(3, 20, OBS, ACT)
    rng = np.random.default_rng(1)

    def trajectories(task: int, n: int, length: int) -> None:
        obs = rng.normal(size=3).astype(np.float32)
        for t in range(n):
            next_obs = rng.normal(size=3).astype(np.float32)
            if t == 2:
                next_obs[0] = -0.0  # equal to 0.0 as a float, not as bits
            if t == 3:
                next_obs[1] = np.nan  # unequal to itself as a float, equal as bits
            done = (t + 1) % length == 0
            buffer.add(task, obs, rng.normal(size=2), 1.0, next_obs, done)
            obs = rng.normal(size=3).astype(np.float32) if done else next_obs  # a reset starts elsewhere

    trajectories(0, 12, 5)  # ends after rows 4 and 9; row 11 is the task's last
    trajectories(1, 26, 100)  # one trajectory over a ring of 20: wrapped at row 5, so row 5 does not precede row 6
    trajectories(2, 7, 7)  # one whole trajectory
    state = buffer.__getstate__()
    n_rows = 12 + 20 + 7
    assert state["observations"].shape == (n_rows, 3)
    # written: task 0's rows 4, 9, 11; task 1's row 5 (its successor in time went to row 0) and row 19; task 2's row 6
    assert state["next_observations"].shape == (6, 3)
    assert len(state["next_follows"]) == (n_rows + 7) // 8  # one bit a row

    pickled = pickle.dumps(buffer)
    loaded = pickle.loads(pickled)
    assert pickle.dumps(loaded) == pickled
    for name in TaskReplayBuffer._ARRAYS:
        for task, n in enumerate(buffer.size):
            want, got = getattr(buffer, name)[task, :n], getattr(loaded, name)[task, :n]
            np.testing.assert_array_equal(got.view(np.uint32), want.view(np.uint32))  # the same bits
    assert np.isnan(loaded.next_observations[0, 3, 1]) and np.signbit(loaded.next_observations[0, 2, 0])

    whole = pickle.dumps({name: getattr(buffer, name) for name in TaskReplayBuffer._ARRAYS})  # what sharing saves
    assert len(pickled) < len(whole)


def test_a_rows_in_use_pickle_without_shared_next_observations_still_loads() -> None:
    buffer = filled_buffer()
    used = int(buffer.size.max())
    held = buffer._rows_in_use(used)
    state = buffer.__dict__.copy()
    for name in TaskReplayBuffer._ARRAYS:
        state[name] = getattr(buffer, name)[:, :used][held]
    state["layout"] = "rows-in-use"  # an earlier layout, still read: the committed walker checkpoint has it
    old = TaskReplayBuffer.__new__(TaskReplayBuffer)
    old.__setstate__(state)
    for name in TaskReplayBuffer._ARRAYS:
        for task, n in enumerate(buffer.size):
            np.testing.assert_array_equal(getattr(old, name)[task, :n], getattr(buffer, name)[task, :n])


def test_gather_rows_is_the_fancy_index() -> None:
    rng = np.random.default_rng(0)
    array = rng.standard_normal((5, 7, 3)).astype(np.float32)
    tasks, rows = np.array([4, 0, 4]), rng.integers(0, 7, (3, 6))
    np.testing.assert_array_equal(gather_rows(array, tasks, rows), array[tasks[:, None], rows])
    strided = array[:, ::2]  # not contiguous: the fancy index itself
    np.testing.assert_array_equal(gather_rows(strided, tasks, rows % 4), strided[tasks[:, None], rows % 4])
