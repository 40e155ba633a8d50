"""Per-task replay storage for meta-RL.

:class:`TaskReplayBuffer` keeps one float32 ring buffer per task in arrays of shape
``(n_tasks, capacity, dim)``, so that a batch for ``T`` tasks is a single gather
(:func:`gather_rows`) (no per-task Python loop). :class:`MetaReplayBuffer` bundles the two buffers PEARL
needs: the RL buffer (all data of a task, sampled uniformly for the actor-critic losses) and
the context buffer (the task's most recent collection, cleared when the task is sampled again,
sampled for the encoder), as in the reference implementation.

Arrays are allocated with ``np.zeros``, whose pages are only backed by memory once written, so a
large per-task capacity costs what is actually stored.
"""

from __future__ import annotations

import numpy as np
import torch as th
from gymnasium import spaces

from sb3_pearl.common.type_aliases import MetaReplaySamples, ReturnTargets


def gather_rows(array: np.ndarray, tasks: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """
    ``array[tasks[:, None], rows]`` for an array of shape ``(n_tasks, capacity, ...)``: one ``take`` of the flat rows
    ``task * capacity + row`` on the array seen as ``(n_tasks * capacity, ...)`` (the same values as the broadcast fancy
    index, in one gather: docs/speed.md; a non-contiguous array, which that view would copy, takes the fancy index).

    :param array: the per-task array
    :param tasks: task indices, shape ``(T,)``
    :param rows: row indices of each task, shape ``(T, B)``
    :return: the rows, shape ``(T, B, ...)``
    """
    if not array.flags.c_contiguous:
        return array[tasks[:, None], rows]
    trailing = array.shape[2:]
    flat = (tasks[:, None] * array.shape[1] + rows).reshape(-1)
    return array.reshape(-1, *trailing).take(flat, axis=0).reshape(*rows.shape, *trailing)


class TaskReplayBuffer:
    """
    One ring buffer per task.

    :param n_tasks: number of tasks
    :param capacity: transitions kept per task (the oldest are overwritten)
    :param observation_space: flat Box observation space
    :param action_space: Box (actions stored scaled to [-1, 1]) or Discrete (stored as an index)
    """

    # Allocated by enable_returns (ReturnTargets): each (n_tasks, capacity, 1).
    return_reward: np.ndarray
    return_log_prob: np.ndarray
    return_discount: np.ndarray
    return_tail: np.ndarray  # int64 buffer rows
    return_ready: np.ndarray

    def __init__(self, n_tasks: int, capacity: int, observation_space: spaces.Space, action_space: spaces.Space) -> None:
        if not isinstance(observation_space, spaces.Box) or len(observation_space.shape) != 1:
            raise ValueError(f"TaskReplayBuffer needs a flat Box observation space, got {observation_space}")
        if capacity < 1 or n_tasks < 1:
            raise ValueError(f"n_tasks and capacity must be >= 1, got {n_tasks} and {capacity}")
        self.n_tasks = n_tasks
        self.capacity = capacity
        self.obs_dim = int(observation_space.shape[0])
        self.action_dim = 1 if isinstance(action_space, spaces.Discrete) else int(np.prod(action_space.shape or ()))
        self.observations = np.zeros((n_tasks, capacity, self.obs_dim), dtype=np.float32)
        self.next_observations = np.zeros((n_tasks, capacity, self.obs_dim), dtype=np.float32)
        self.actions = np.zeros((n_tasks, capacity, self.action_dim), dtype=np.float32)
        self.rewards = np.zeros((n_tasks, capacity, 1), dtype=np.float32)
        self.dones = np.zeros((n_tasks, capacity, 1), dtype=np.float32)
        self.prior_z = np.zeros((n_tasks, capacity, 1), dtype=np.float32)  # 1.0: collected with z from the prior
        self.pos = np.zeros(n_tasks, dtype=np.int64)
        self.size = np.zeros(n_tasks, dtype=np.int64)
        self.has_returns = False  # the return arrays exist (enable_returns: a prior critic with Monte-Carlo targets)

    def enable_returns(self) -> None:
        """
        Allocate the arrays of :meth:`write_returns` (once): per row, the discounted reward and log-probability sums to
        the end of its trajectory piece, the tail's discount and row, and whether they are known yet.
        """
        if self.has_returns:
            return
        shape = (self.n_tasks, self.capacity, 1)
        for name in self._RETURN_ARRAYS:
            setattr(self, name, np.zeros(shape, dtype=np.int64 if name == "return_tail" else np.float32))
        self.has_returns = True

    def add(
        self,
        task: int,
        obs: np.ndarray,
        action: np.ndarray,
        reward: float,
        next_obs: np.ndarray,
        terminated: bool,
        prior_z: bool = False,
    ) -> None:
        """
        Store one transition of ``task`` (``terminated`` is True only for a true terminal state; ``prior_z`` when the
        policy acted with z drawn from the prior).
        """
        p = self.pos[task]
        self.observations[task, p] = obs
        self.actions[task, p] = action
        self.rewards[task, p, 0] = reward
        self.next_observations[task, p] = next_obs
        self.dones[task, p, 0] = float(terminated)
        self.prior_z[task, p, 0] = float(prior_z)
        if self.has_returns:
            self.return_ready[task, p, 0] = 0.0  # a new row: its return is not known until its trajectory piece ends
        self.pos[task] = (p + 1) % self.capacity
        self.size[task] = min(self.size[task] + 1, self.capacity)

    def write_returns(
        self,
        task: int,
        rows: np.ndarray,
        reward_sum: np.ndarray,
        log_prob_sum: np.ndarray,
        discount: np.ndarray,
        tail: np.ndarray,
    ) -> None:
        """
        Store the returns of rows of ``task`` (:class:`~sb3_pearl.common.type_aliases.ReturnTargets`), each array (K,):
        ``tail`` holds the buffer row whose ``next_observations`` start the bootstrapped tail.
        """
        self.enable_returns()
        for name, values in (
            ("return_reward", reward_sum),
            ("return_log_prob", log_prob_sum),
            ("return_discount", discount),
            ("return_tail", tail),
        ):
            getattr(self, name)[task, rows, 0] = values
        self.return_ready[task, rows, 0] = 1.0

    _ARRAYS = ("observations", "next_observations", "actions", "rewards", "dones", "prior_z")
    _RETURN_ARRAYS = ("return_reward", "return_log_prob", "return_discount", "return_tail", "return_ready")

    def _saved_arrays(self) -> tuple[str, ...]:
        return self._ARRAYS + (self._RETURN_ARRAYS if self.has_returns else ())

    def _rows_in_use(self, used: int) -> np.ndarray:
        """Mask of shape ``(n_tasks, used)``: True on the rows a task holds (``row < size[task]``)."""
        return np.arange(used)[None, :] < self.size[:, None]

    def __getstate__(self) -> dict:
        """
        Pickle only the rows in use (``save_replay_buffer``), task after task: neither the capacity nor the rows a
        task has not filled are written, so a buffer of unequal task sizes (PEARL samples 5 tasks an iteration) costs
        what it holds. Rows past a task's size are never sampled, so the loaded buffer trains the same weights.

        A row's next observation is, within a trajectory, the observation of the row written after it: it is written
        only where it is not bit for bit the next written row's observation (episode ends, the last row, a ring that
        wrapped), with one bit per row saying which. That drops a third of a MuJoCo buffer (Walker2D-vel: 17 of ~44
        floats a row) and the loaded arrays are the same bits.
        """
        state = self.__dict__.copy()
        used = int(self.size.max()) if self.size.size else 0
        held = self._rows_in_use(used)
        for name in self._saved_arrays():
            state[name] = getattr(self, name)[:, :used][held]  # (size.sum(), dim): task 0's rows, then task 1's, ...
        observations, next_observations = state["observations"], state["next_observations"]  # float32, C-contiguous
        follows = np.zeros(len(observations), dtype=bool)  # row i's next observation is row i + 1's observation
        follows[:-1] = (next_observations[:-1].view(np.uint32) == observations[1:].view(np.uint32)).all(axis=1)
        state["next_observations"] = next_observations[~follows]  # (rows not followed, dim)
        state["next_follows"] = np.packbits(follows)
        state["layout"] = "rows-in-use-shared-next"
        return state

    def __setstate__(self, state: dict) -> None:
        layout = state.pop("layout", "padded")  # "padded": earlier pickles, arrays (n_tasks, largest size, dim)
        if layout == "rows-in-use-shared-next":  # rebuild the next observations the pickle shares with the rows after
            observations = state["observations"]  # (size.sum(), dim)
            follows = np.unpackbits(state.pop("next_follows"), count=len(observations)).astype(bool)
            next_observations = np.empty_like(observations)
            next_observations[:-1] = observations[1:]  # right where ``follows``; the rest is overwritten next
            next_observations[~follows] = state["next_observations"]  # the last row is never followed
            state["next_observations"] = next_observations
            layout = "rows-in-use"
        if "prior_z" not in state:  # a buffer saved before the flag existed: its z sources are unknown (none marked)
            state["prior_z"] = np.zeros_like(state["rewards"])
        state.setdefault("has_returns", False)  # saved before the return arrays existed
        self.__dict__.update(state)  # every attribute in its saved place (a re-pickle writes the same bytes)
        used = int(self.size.max()) if self.size.size else 0
        held = self._rows_in_use(used)
        for name in self._saved_arrays():
            stored = state[name]
            if layout == "rows-in-use":  # (size.sum(), dim)
                full = np.zeros((self.n_tasks, self.capacity, *stored.shape[1:]), stored.dtype)
                full[:, :used][held] = stored  # the view writes through to ``full``
            else:  # (n_tasks, largest size, dim)
                full = np.zeros((self.n_tasks, self.capacity, *stored.shape[2:]), stored.dtype)
                full[:, : stored.shape[1]] = stored
            setattr(self, name, full)

    def clear(self, task: int) -> None:
        """Forget every transition of ``task``."""
        self.pos[task] = 0
        self.size[task] = 0

    def sample_indices(self, tasks: np.ndarray, batch_size: int) -> np.ndarray:
        """Uniform row indices, shape ``(T, batch_size)``, for tasks that all hold data."""
        sizes = self.size[tasks]
        if np.any(sizes == 0):
            raise ValueError(f"cannot sample tasks without data: {tasks[sizes == 0].tolist()}")
        return (np.random.random_sample((len(tasks), batch_size)) * sizes[:, None]).astype(np.int64)

    def sample(
        self, tasks: np.ndarray, batch_size: int, device: th.device | str = "cpu", returns: bool = False
    ) -> MetaReplaySamples:
        """
        Sample ``batch_size`` transitions uniformly from each task in ``tasks``.

        :param tasks: task indices, shape ``(T,)`` (repeats allowed)
        :param batch_size: rows per task
        :param device: torch device of the returned tensors
        :param returns: also return the rows' Monte-Carlo returns (:meth:`write_returns`; none known: ready is 0)
        :return: tensors of leading shape ``(T, batch_size)``
        """
        tasks = np.asarray(tasks, dtype=np.int64)
        rows = self.sample_indices(tasks, batch_size)
        arrays = (self.observations, self.actions, self.rewards, self.next_observations, self.dones, self.prior_z)
        observations, actions, rewards, next_observations, dones, prior_z = (
            th.as_tensor(gather_rows(a, tasks, rows), device=device) for a in arrays
        )
        samples = MetaReplaySamples(observations, actions, rewards, next_observations, dones, prior_z)
        if not returns:
            return samples
        self.enable_returns()
        tail_rows = gather_rows(self.return_tail, tasks, rows)[..., 0]  # (T, B) buffer rows of each sampled row's tail
        parts = (
            gather_rows(self.return_reward, tasks, rows),
            gather_rows(self.return_log_prob, tasks, rows),
            gather_rows(self.return_discount, tasks, rows),
            gather_rows(self.next_observations, tasks, tail_rows),  # (T, B, obs_dim)
            gather_rows(self.return_ready, tasks, rows),
        )
        return samples._replace(returns=ReturnTargets(*(th.as_tensor(a, device=device) for a in parts)))


class MetaReplayBuffer:
    """
    The RL buffer and the context buffer of every training task, saved together by
    ``save_replay_buffer``.

    :param n_tasks: number of training tasks
    :param buffer_size: RL transitions kept per task
    :param context_size: context transitions kept per task (the latest collection)
    :param observation_space: flat Box observation space
    :param action_space: Box or Discrete action space
    """

    def __init__(
        self,
        n_tasks: int,
        buffer_size: int,
        context_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
    ) -> None:
        self.rl = TaskReplayBuffer(n_tasks, buffer_size, observation_space, action_space)
        self.context = TaskReplayBuffer(n_tasks, context_size, observation_space, action_space)

    @property
    def n_tasks(self) -> int:
        return self.rl.n_tasks

    def tasks_with_data(self) -> np.ndarray:
        """Indices of the tasks whose RL and context buffers both hold data."""
        return np.flatnonzero((self.rl.size > 0) & (self.context.size > 0))

    def total_transitions(self) -> int:
        return int(self.rl.size.sum())
