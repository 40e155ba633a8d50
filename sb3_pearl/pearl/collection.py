"""Data collection of PEARL / PEARL+ (Algorithm 1's inner loop over tasks), one task per env at a time.

Iteration 0 collects ``num_initial_steps`` per training task with z from the prior; every later
iteration picks ``num_tasks_sample`` training tasks and, for each, clears its context buffer and
collects ``num_steps_prior`` steps with z from the prior, ``num_steps_posterior`` steps with z from
the posterior (both also stored as context) and ``num_extra_rl_steps_posterior`` posterior steps for
the RL buffer only. z is drawn once per trajectory. Each visit is a *program*: a list of
:class:`Segment`, run in order on one env; with ``n_envs > 1`` every env runs its own program.
:func:`plan_training` counts what ``learn`` will collect and train (the progress callback's ETA).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecEnv

from sb3_pearl.common.divergence import check_env_step, check_finite_actions
from sb3_pearl.common.tasks import set_vec_env_task
from sb3_pearl.common.type_aliases import TrainingPlan
from sb3_pearl.pearl.returns import PendingPiece, cut_before_overwrite, finish_open_pieces, record_row, start_piece

if TYPE_CHECKING:
    from sb3_pearl.pearl.pearl import PEARL


class Segment(NamedTuple):
    """A stretch of data collection on one training task (one line of Algorithm 1's inner loop)."""

    task: int  # index into train_tasks
    n_steps: int
    z_source: str  # "prior": z ~ N(0, I); "posterior": z ~ q(z | context buffer of the task)
    add_to_context: bool  # also store the data in the task's context buffer
    clear_context: bool  # clear the task's context buffer before collecting


def plan_iteration(model: PEARL) -> list[list[Segment]]:
    """The segments of the next iteration, one program (list of segments) per visited task."""
    without_data = np.flatnonzero(model.replay_buffer.rl.size == 0)
    if len(without_data) > 0 and model.num_initial_steps > 0:  # iteration 0 (or an interrupted one): initial prior data
        return [
            [Segment(task=int(t), n_steps=model.num_initial_steps, z_source="prior", add_to_context=True, clear_context=True)]
            for t in without_data
        ]
    programs = []
    for task in np.random.randint(len(model.train_tasks), size=model.num_tasks_sample):
        t = int(task)
        program = [
            Segment(task=t, n_steps=model.num_steps_prior, z_source="prior", add_to_context=True, clear_context=True),
            Segment(t, n_steps=model.num_steps_posterior, z_source="posterior", add_to_context=True, clear_context=False),
            Segment(
                t,
                n_steps=model.num_extra_rl_steps_posterior,
                z_source="posterior",
                add_to_context=False,
                clear_context=False,
            ),
        ]
        if model.num_steps_prior == 0:  # the context buffer is still cleared when the task is visited
            program.insert(0, Segment(t, n_steps=0, z_source="prior", add_to_context=False, clear_context=True))
        programs.append(program)
    return programs


def draw_z(model: PEARL, segment: Segment) -> th.Tensor:
    """z for a new trajectory: from the prior, or from the posterior of the task's context buffer."""
    if segment.z_source == "posterior" and model.replay_buffer.context.size[segment.task] > 0:
        with th.no_grad():
            return model.sample_posterior(model._sample_context(np.array([segment.task]))).z[0]
    return th.randn(model.latent_dim, device=model.device)


def start_segment(model: PEARL, env: VecEnv, slot: int, segment: Segment, obs: np.ndarray) -> None:
    """Switch env ``slot`` to the segment's task and reset it explicitly (no auto-reset leak)."""
    set_vec_env_task(env, model.train_tasks[segment.task], [slot])
    obs[slot] = env.env_method("reset", indices=[slot])[0][0]


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


def start_iteration(model: PEARL, programs: list[list[Segment]]) -> OpenIteration:
    """The collection state of a new iteration made of ``programs`` (:func:`plan_iteration`)."""
    n_envs = model.n_envs
    return OpenIteration(
        queue=deque(deque(program) for program in programs),
        running=[deque() for _ in range(n_envs)],
        segments=[None] * n_envs,
        remaining=np.zeros(n_envs, dtype=np.int64),
        z=np.zeros((n_envs, model.latent_dim), dtype=np.float32),
        planned=sum(seg.n_steps for program in programs for seg in program),
    )


def requeue_open_segments(state: OpenIteration, n_envs: int) -> None:
    """
    Put each env's unfinished segment (its remaining steps) and the rest of its visit back at the head of the queue,
    for ``n_envs`` envs: the envs were reset (or their number changed), so these segments start on a fresh episode.
    The counts are kept: the iteration still collects what it planned.
    Open trajectory pieces (``prior_target="mc"``) must have been cut first
    (:func:`~sb3_pearl.pearl.returns.finish_open_pieces`).
    """
    if any(piece is not None for piece in state.pieces or ()):
        raise RuntimeError("cut the open trajectory pieces (finish_open_pieces) before requeueing their segments")
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


def collect_iteration(model: PEARL, env: VecEnv, callback: BaseCallback, state: OpenIteration) -> bool:
    """
    Run the iteration's programs on the envs, each env one task at a time, until the iteration or the budget ends.

    The caller calls ``callback.on_rollout_start()`` before planning a new iteration (:func:`plan_iteration` draws
    from the global RNG), so that a checkpoint saved there resumes exactly; this ends with ``on_rollout_end()``.

    :param state: the iteration (updated in place: what is left of it, the steps collected)
    :return: whether training should go on (False: a callback asked to stop)
    """
    n_envs = env.num_envs
    obs = np.array(model._last_obs, dtype=np.float32)  # type: ignore[arg-type]
    z = th.as_tensor(state.z, device=model.device)
    returns = model.prior_target == "mc"  # the prior-z rows get Monte-Carlo returns (sb3_pearl.pearl.returns)
    continue_training = True
    while True:
        for slot in range(n_envs):
            while state.remaining[slot] == 0 and (state.running[slot] or state.queue):
                if not state.running[slot]:
                    state.running[slot] = state.queue.popleft()
                segment = state.running[slot].popleft()
                if segment.clear_context:
                    model.replay_buffer.context.clear(segment.task)
                if segment.n_steps > 0:
                    start_segment(model, env, slot, segment, obs)
                    state.segments[slot] = segment
                    state.remaining[slot] = segment.n_steps
                    z[slot] = draw_z(model, segment)
                    if returns and segment.z_source == "prior":
                        start_piece(state, slot, segment.task)
        active = np.flatnonzero(state.remaining > 0)
        if len(active) == 0 or model.num_timesteps >= model._total_timesteps:
            break

        with th.no_grad():
            if returns:  # the same draws as act(), with the log-probabilities the returns need
                actions_t, log_probs_t = model.policy.act_with_log_prob(th.as_tensor(obs, device=model.device), z)
                log_probs = log_probs_t.cpu().numpy().astype(np.float64)  # (n_envs,)
            else:
                actions_t = model.policy.act(th.as_tensor(obs, device=model.device), z)
            actions = actions_t.cpu().numpy()
        check_finite_actions(actions, model.num_timesteps, type(model).__name__)
        env_actions = actions if model.policy.discrete else model.policy.unscale_action(actions)
        new_obs, rewards, dones, infos = env.step(env_actions)
        # Divergence guard: a non-finite observation or reward is an error naming the env, task and timestep.
        check_env_step(env, new_obs, rewards, dones, infos, model.num_timesteps, type(model).__name__, active.tolist())

        for slot in active.tolist():
            current = state.segments[slot]
            assert current is not None
            next_obs = infos[slot]["terminal_observation"] if dones[slot] else new_obs[slot]  # type: ignore[call-overload,index]
            terminated = bool(dones[slot]) and not infos[slot].get("TimeLimit.truncated", False)
            transition = (current.task, obs[slot], actions[slot].reshape(-1), rewards[slot], next_obs, terminated)
            row = int(model.replay_buffer.rl.pos[current.task])
            if returns:
                cut_before_overwrite(model, state, current.task, row)
            model.replay_buffer.rl.add(*transition, prior_z=current.z_source == "prior")
            if current.add_to_context:
                model.replay_buffer.context.add(*transition)
            state.remaining[slot] -= 1
            if returns:
                record_row(model, state, slot, row, float(log_probs[slot]), bool(dones[slot]), terminated)
                if state.remaining[slot] == 0:  # the segment ends inside the trajectory: the next one resets the env
                    finish_open_pieces(model, state, [slot])
            if dones[slot]:
                model._episode_num += 1
                if state.remaining[slot] > 0:
                    z[slot] = draw_z(model, current)  # z is drawn once per trajectory
                    if returns and current.z_source == "prior":
                        start_piece(state, slot, current.task)
        state.collected += len(active)
        model.num_timesteps += len(active)
        obs = np.array(new_obs, dtype=np.float32)
        model._update_info_buffer([infos[i] for i in active], dones[active])
        callback.update_locals(locals())
        if not callback.on_step():
            continue_training = False
            break
    model._last_obs = obs
    state.z = z.cpu().numpy()
    callback.on_rollout_end()
    return continue_training


def plan_training(model: PEARL, total_timesteps: int) -> TrainingPlan:
    """
    What ``learn(total_timesteps)`` will still do: iteration 0's initial data (if some training task has none yet),
    then full iterations and maybe a partial last one, whose gradient steps are scaled as ``learn`` scales them.

    :param model: the model (its counters and replay buffer: a resumed run plans what is left)
    :param total_timesteps: the ``learn`` budget, counted from 0
    :return: the plan
    """
    remaining = max(total_timesteps - model.num_timesteps, 0)
    steps = model.num_train_steps_per_itr
    chunks: list[tuple[int, int]] = []  # (collected, planned) per iteration
    open_iteration = model._open_iteration
    if open_iteration is not None and remaining > 0:  # first, the iteration a previous learn() left open
        rest = min(open_iteration.planned - open_iteration.collected, remaining)
        chunks.append((open_iteration.collected + rest, open_iteration.planned))
        remaining -= rest
    without_data = int(np.count_nonzero(model.replay_buffer.rl.size == 0)) if model.num_initial_steps > 0 else 0
    if open_iteration is None and without_data > 0 and remaining > 0:
        planned = model.num_initial_steps * without_data
        chunks.append((min(planned, remaining), planned))
        remaining -= chunks[-1][0]
    per_iteration = model.num_tasks_sample * (
        model.num_steps_prior + model.num_steps_posterior + model.num_extra_rl_steps_posterior
    )
    full, rest = divmod(remaining, per_iteration) if per_iteration > 0 else (0, 0)
    chunks += [(per_iteration, per_iteration)] * full + ([(rest, per_iteration)] if rest > 0 else [])
    carry = model.partial_iteration == "carry"  # an unfinished last iteration is trained by a later learn()
    updates = [0 if carry and done < planned else math.ceil(steps * done / planned) for done, planned in chunks]
    pending = int(model._pending_gradient_steps)  # an iteration whose gradient steps a stop interrupted: trained first
    if pending > 0:
        updates.insert(0, pending)
    initial = chunks[0][0] if chunks and open_iteration is None and without_data > 0 and pending == 0 else 0
    note = ""
    if initial:
        per_task, planned = model.num_initial_steps, model.num_initial_steps * without_data
        note = f"iteration 0: {per_task:,} steps with z from the prior per training task, {without_data} tasks"
        if initial < planned:  # the budget ends inside iteration 0: say how much of it runs
            note += f"; this run's {initial:,} steps reach {math.ceil(initial / per_task)} of them"
        else:
            note += f" ({planned:,} in all)"
    return TrainingPlan(
        env_steps=max(total_timesteps - model.num_timesteps, 0),
        gradient_steps=sum(updates),
        initial_steps=initial,
        first_updates=updates[0] if updates else 0,
        note=note,
    )
