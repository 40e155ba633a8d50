"""The state of PEARL / PEARL+'s data collection (Algorithm 1's inner loop over tasks), one task per env at a time.

Iteration 0 collects ``num_initial_steps`` per training task with z from the prior; every later
iteration picks ``num_tasks_sample`` training tasks and, for each, clears its context buffer and
collects ``num_steps_prior`` steps with z from the prior, ``num_steps_posterior`` steps with z from
the posterior (both also stored as context) and ``num_extra_rl_steps_posterior`` posterior steps for
the RL buffer only. z is drawn once per trajectory. Each visit is a *program*: a list of
:class:`Segment`, run in order on one env; with ``n_envs > 1`` every env runs its own program.

The collection itself is PEARL's (:meth:`~sb3_pearl.pearl.pearl.PEARL.collect_iteration`); this module holds what it
works on: the segments, the open iteration (:class:`OpenIteration`, saved with a model whose ``learn`` budget ended
inside an iteration) and the changes to it that need no model.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from sb3_pearl.pearl.returns import PendingPiece


class Segment(NamedTuple):
    """A stretch of data collection on one training task (one line of Algorithm 1's inner loop)."""

    task: int  # index into train_tasks
    n_steps: int
    z_source: str  # "prior": z ~ N(0, I); "posterior": z ~ q(z | context buffer of the task)
    add_to_context: bool  # also store the data in the task's context buffer
    clear_context: bool  # clear the task's context buffer before collecting


@dataclass
class OpenIteration:
    """
    An iteration being collected: the visits still queued, where each env stands in its own, and the counts.

    ``learn`` keeps it between calls when ``partial_iteration="carry"`` and a budget ends inside the iteration
    (and saves it with the model), so that the next ``learn`` finishes the same iteration.
    """

    queue: deque[deque[Segment]]  # visits not started yet
    running: list[deque[Segment]]  # per env: the rest of its current visit
    segments: list[Segment | None]  # per env: the segment it is running
    remaining: np.ndarray  # (n_envs,) steps left in each env's current segment
    z: np.ndarray  # (n_envs, latent_dim) each env's z for its current trajectory
    collected: int = 0
    planned: int = 0
    # per env: the prior-z trajectory piece whose rows await their Monte-Carlo returns (prior_target="mc"), or None
    pieces: list[PendingPiece | None] | None = None

    @property
    def finished(self) -> bool:
        return self.collected >= self.planned


def requeue_open_segments(state: OpenIteration, n_envs: int) -> None:
    """
    Put each env's unfinished segment (its remaining steps) and the rest of its visit back at the head of the queue,
    for ``n_envs`` envs: the envs were reset (or their number changed), so these segments start on a fresh episode.
    The counts are kept: the iteration still collects what it planned.
    Open trajectory pieces (``prior_target="mc"``) must have been cut first
    (:meth:`~sb3_pearl.pearl.pearl.PEARL._finish_open_pieces`).
    """
    if any(piece is not None for piece in state.pieces or ()):
        raise RuntimeError("cut the open trajectory pieces (_finish_open_pieces) before requeueing their segments")
    state.pieces = None  # one slot per env: the number of envs may change
    visits: list[deque[Segment]] = []
    for slot in range(len(state.remaining)):
        visit = deque(state.running[slot])
        current = state.segments[slot]
        if state.remaining[slot] > 0 and current is not None:
            visit.appendleft(current._replace(n_steps=int(state.remaining[slot]), clear_context=False))
        if visit:
            visits.append(visit)
    state.queue.extendleft(reversed(visits))
    state.running = [deque() for _ in range(n_envs)]
    state.segments = [None] * n_envs
    state.remaining = np.zeros(n_envs, dtype=np.int64)
    state.z = np.zeros((n_envs, state.z.shape[1]), dtype=np.float32)


def start_piece(state: OpenIteration, slot: int, task: int) -> None:
    """Env ``slot`` starts a trajectory with z from the prior on ``task``: its rows will get Monte-Carlo returns."""
    if state.pieces is None:
        state.pieces = [None] * len(state.remaining)
    state.pieces[slot] = PendingPiece(task)
