"""Monte-Carlo targets of the prior critic (``prior_target="mc"``, :mod:`sb3_pearl.pearl.returns`): the returns by hand,
what collection writes into the replay buffer, the behaviour log-probabilities, save / load and exact resumption."""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env

from sb3_pearl import PEARLPlus
from sb3_pearl.pearl.collection import requeue_open_segments, start_piece
from sb3_pearl.pearl.diagnostics.gradients import compute_gradient_conflict
from sb3_pearl.pearl.returns import PendingPiece, piece_returns
from tests.conftest import make_discrete_env

REWARDS, LOG_PROBS, GAMMA = np.array([1.0, 2.0, 3.0]), np.array([0.5, -1.0, 2.0]), 0.5


@pytest.mark.parametrize(
    "terminated, horizon, expected",
    [
        # Monte-Carlo to a termination: G_0 = 1 + 0.5 * 2 + 0.25 * 3; the entropy sums start one row later; no tail.
        (True, 0, ([2.75, 3.5, 3.0], [0.5 * -1.0 + 0.25 * 2.0, 0.5 * 2.0, 0.0], [0.0, 0.0, 0.0], [2, 2, 2])),
        # The same piece cut (a time limit or the segment's end): every row's tail is gamma^k V~(s_3).
        (False, 0, ([2.75, 3.5, 3.0], [0.0, 1.0, 0.0], [0.125, 0.25, 0.5], [2, 2, 2])),
        # 2-step returns: row 0's window ends at row 1 (tail from s_2); rows 1 and 2 reach the termination.
        (True, 2, ([2.0, 3.5, 3.0], [-0.5, 1.0, 0.0], [0.25, 0.0, 0.0], [1, 2, 2])),
        # 1-step returns are the one-step soft Bellman target (the paper's), with gamma on every tail but the last.
        (True, 1, ([1.0, 2.0, 3.0], [0.0, 0.0, 0.0], [0.5, 0.5, 0.0], [0, 1, 2])),
    ],
)
def test_piece_returns_by_hand(terminated: bool, horizon: int, expected: tuple[list[float], ...]) -> None:
    got = piece_returns(REWARDS, LOG_PROBS, GAMMA, terminated, horizon)
    for values, want in zip(got, expected, strict=True):
        np.testing.assert_allclose(values, want, rtol=1e-12)
    with pytest.raises(ValueError, match=r"shape \(K,\)"):
        piece_returns(REWARDS, LOG_PROBS[:2], GAMMA, terminated, horizon)


def _box_log_prob_by_hand(model: PEARLPlus, x: th.Tensor) -> th.Tensor:
    """log pi of the Gaussian draw the actor's distribution holds: N(u; mu, sigma) minus the tanh Jacobian, summed."""
    mean, log_std = model.actor._params(x)
    u = model.actor.action_dist.gaussian_actions  # (N, A) the pre-tanh draw of the last sample
    gaussian = -0.5 * ((u - mean) / log_std.exp()) ** 2 - log_std - 0.5 * np.log(2 * np.pi)
    return (gaussian - th.log(1 - th.tanh(u) ** 2 + 1e-6)).sum(dim=-1)


@pytest.mark.parametrize("discrete", [False, True])
def test_act_with_log_prob_draws_as_act_and_scores_the_draw(discrete: bool) -> None:
    env = make_discrete_env() if discrete else gym.make("PointGoalMeta-v0")
    model = PEARLPlus("MlpPolicy", env, seed=0, n_train_tasks=2, n_test_tasks=1)
    obs, z = th.randn(6, model.policy.obs_dim), th.randn(model.latent_dim)
    with th.no_grad():
        th.manual_seed(1)
        acted = model.policy.act(obs, z)
        th.manual_seed(1)
        actions, log_probs = model.policy.act_with_log_prob(obs, z)
        assert th.equal(actions, acted) and log_probs.shape == (6,)  # the same draws: mc models collect the same data
        x = th.cat([obs, z.expand(6, -1)], dim=-1)
        if discrete:
            want = th.log_softmax(model.actor.logits(x), dim=-1).gather(-1, actions.long().reshape(-1, 1))[:, 0]
        else:
            want = _box_log_prob_by_hand(model, x)
    th.testing.assert_close(log_probs, want, rtol=1e-5, atol=1e-5)


def test_a_saturated_box_action_keeps_the_log_prob_of_its_draw() -> None:
    """tanh(u) = 1.0 in float32 for u > ~9: the draw's log-probability is finite and exact; inverting the action is not."""
    model = PEARLPlus("MlpPolicy", gym.make("PointGoalMeta-v0"), seed=0, n_train_tasks=2, n_test_tasks=1)
    with th.no_grad():
        model.actor.mu.bias.fill_(30.0)  # every mean far in the saturated region
        x = th.randn(4, model.policy.obs_dim + model.latent_dim)
        actions, log_probs = model.actor.action_log_prob(x)
        assert th.all(actions == 1.0)
        th.testing.assert_close(log_probs, _box_log_prob_by_hand(model, x), rtol=1e-5, atol=1e-4)
        mean, log_std = model.actor._params(x)
        inverted = model.actor.action_dist.proba_distribution(mean, log_std).log_prob(actions)  # tanh clipped off 1
    assert th.all(th.isfinite(log_probs)) and not th.allclose(inverted, log_probs, atol=1.0)


def _mc_model(tiny_kwargs: dict[str, Any], **extra: Any) -> PEARLPlus:
    return PEARLPlus("MlpPolicy", gym.make("PointGoalMeta-v0"), seed=0, prior_target="mc", **{**tiny_kwargs, **extra})


def test_collection_writes_the_returns_of_the_prior_rows(tiny_kwargs: dict[str, Any]) -> None:
    """Iteration 0 collects 60 prior steps per task: three 20-step episodes, each ended by PointGoal's time limit."""
    model = _mc_model(tiny_kwargs).learn(240)
    rl, gamma = model.replay_buffer.rl, model.gamma
    assert rl.has_returns and (rl.return_ready[:, :60] == 1.0).all()
    for start in (0, 20, 40):  # each episode a piece: returns to its end, tails from its last row, bootstrapped
        rows = np.arange(start, start + 20)
        rewards = rl.rewards[1, rows, 0].astype(np.float64)
        want = [sum(gamma**i * r for i, r in enumerate(rewards[j:])) for j in range(20)]
        np.testing.assert_allclose(rl.return_reward[1, rows, 0], want, rtol=1e-5)
        np.testing.assert_allclose(rl.return_discount[1, rows, 0], gamma ** np.arange(20, 0, -1), rtol=1e-5)
        assert (rl.return_tail[1, rows, 0] == start + 19).all()
    model.learn(140, reset_num_timesteps=False)  # iteration 1: per visit 30 prior steps, then 40 posterior ones
    prior = rl.prior_z[:, : rl.size.max()] == 1.0
    ready = rl.return_ready[:, : rl.size.max()] == 1.0
    assert np.array_equal(prior, ready)  # every prior row has its return, no posterior row has one
    visited = int(np.flatnonzero(rl.size > 60)[0])
    # The visit's 30 prior steps: one 20-step episode, then 10 steps cut by the segment's end (bootstrapped).
    np.testing.assert_allclose(rl.return_discount[visited, 80:90, 0], gamma ** np.arange(10, 0, -1), rtol=1e-5)
    assert (rl.return_tail[visited, 80:90, 0] == 89).all()


def test_finish_piece_uses_the_recorded_log_probabilities(tiny_kwargs: dict[str, Any]) -> None:
    model = _mc_model(tiny_kwargs, prior_return_steps=4).learn(240)
    rl, log_probs = model.replay_buffer.rl, np.linspace(-3.0, 1.0, 10)
    model._finish_piece(PendingPiece(task=2, rows=list(range(5, 15)), log_probs=list(log_probs)), terminated=False)
    rows = np.arange(5, 15)
    want = piece_returns(rl.rewards[2, rows, 0], log_probs, model.gamma, False, 4)
    np.testing.assert_allclose(rl.return_log_prob[2, rows, 0], want.log_prob_sum, rtol=1e-6)
    np.testing.assert_allclose(rl.return_discount[2, rows, 0], want.discount, rtol=1e-6)
    assert list(rl.return_tail[2, rows, 0]) == [8, 9, 10, 11, 12, 13, 14, 14, 14, 14]
    # A row the buffer overwrites loses its return until its new trajectory piece ends.
    rl.pos[2] = 7
    rl.add(2, rl.observations[2, 0], rl.actions[2, 0], 0.0, rl.observations[2, 1], False, prior_z=True)
    assert rl.return_ready[2, 7, 0] == 0.0 and rl.return_ready[2, 8, 0] == 1.0


def test_collected_returns_use_the_actors_density_of_the_stored_actions(
    tiny_kwargs: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Iteration 0 of task 0 (60 rows, three 20-step episodes), its entropy sums rebuilt from the stored actions."""
    model = _mc_model(tiny_kwargs, prior_return_steps=3, num_train_steps_per_itr=0)  # the actor as it collected
    drawn: list[tuple[th.Tensor, th.Tensor]] = []
    act_with_log_prob = model.policy.act_with_log_prob

    def recording(observations: th.Tensor, z: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        drawn.append((observations.clone(), z.clone()))
        return act_with_log_prob(observations, z)

    monkeypatch.setattr(model.policy, "act_with_log_prob", recording)
    model.learn(60)  # the budget ends with task 0's initial data
    rl = model.replay_buffer.rl
    assert len(drawn) == 60 and rl.size[0] == 60
    actions = th.as_tensor(rl.actions[0, :60]).double()  # (60, A)
    assert th.all(actions.abs() < 0.999)  # not saturated: the tanh can be inverted
    x = th.cat([th.cat([obs, z.expand(len(obs), -1)], dim=-1) for obs, z in drawn])  # (60, obs + L)
    with th.no_grad():
        mean, log_std = (t.double() for t in model.actor._params(x))
    u = th.atanh(actions)
    density = (-0.5 * ((u - mean) / log_std.exp()) ** 2 - log_std - 0.5 * np.log(2 * np.pi)).sum(-1)
    log_probs = (density - th.log(1 - actions**2 + 1e-6).sum(-1)).numpy()  # (60,)
    for start in (0, 20, 40):
        rows = np.arange(start, start + 20)
        want = piece_returns(rl.rewards[0, rows, 0], log_probs[rows], model.gamma, False, 3)
        np.testing.assert_allclose(rl.return_log_prob[0, rows, 0], want.log_prob_sum, rtol=1e-4, atol=1e-4)


def test_two_envs_on_one_task_never_write_a_return_on_an_overwritten_row(
    tiny_kwargs: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    """One training task, two envs on it and a ring of 25 rows: two interleaved 20-step pieces span 40 rows, so the ring
    reaches the oldest row of an open piece; that piece is cut before the row is reused."""
    kwargs = {**tiny_kwargs, "n_train_tasks": 1, "n_test_tasks": 1, "meta_batch": 1, "buffer_size": 25}
    env = make_vec_env("PointGoalMeta-v0", n_envs=2, seed=0)
    model = PEARLPlus("MlpPolicy", env, seed=0, prior_target="mc", **kwargs)
    rl, added, finished, counter = model.replay_buffer.rl, {}, [], itertools.count()
    add = rl.add

    def counting_add(task: int, *args: Any, **kwargs: Any) -> None:
        added[int(rl.pos[task])] = next(counter)  # row -> the index of the add that last wrote it
        add(task, *args, **kwargs)

    finish = model._finish_piece

    def checked_finish(piece: PendingPiece, terminated: bool) -> None:
        order = [added[row] for row in piece.rows]  # when each row was last written
        finished.append(order == sorted(order))  # in collection order: no row rewritten since the piece recorded it
        finish(piece, terminated)

    monkeypatch.setattr(rl, "add", counting_add)
    monkeypatch.setattr(model, "_finish_piece", checked_finish)
    model.learn(600)
    assert len(finished) > 20 and all(finished)
    ready, prior = rl.return_ready[0, :, 0] == 1.0, rl.prior_z[0, :, 0] == 1.0
    assert not (ready & ~prior).any()  # a return only on a row collected with z from the prior


def test_cut_before_overwrite_cuts_only_the_piece_holding_the_row(tiny_kwargs: dict[str, Any]) -> None:
    model = _mc_model(tiny_kwargs).learn(240)
    state = type("State", (), {"pieces": None, "remaining": np.zeros(3, dtype=np.int64)})()
    for slot, task in enumerate((1, 1, 2)):
        start_piece(state, slot, task)  # type: ignore[arg-type]
    state.pieces[0].rows, state.pieces[0].log_probs = [7, 9], [0.1, 0.2]
    state.pieces[1].rows, state.pieces[1].log_probs = [8, 10], [0.3, 0.4]
    state.pieces[2].rows, state.pieces[2].log_probs = [7, 8], [0.5, 0.6]
    model.replay_buffer.rl.return_ready[1, 7:11] = 0.0
    model._cut_before_overwrite(state, task=1, row=7)  # type: ignore[arg-type]
    assert state.pieces[0].rows == [] and state.pieces[0].task == 1  # cut, goes on as a new piece
    assert state.pieces[1].rows == [8, 10] and state.pieces[2].rows == [7, 8]  # another start row, another task
    assert list(model.replay_buffer.rl.return_ready[1, 7:11, 0]) == [1.0, 0.0, 1.0, 0.0]


def test_requeueing_forgets_the_pieces_so_the_number_of_envs_may_change(tiny_kwargs: dict[str, Any]) -> None:
    model = _mc_model(tiny_kwargs, partial_iteration="carry").learn(250)
    state = model._open_iteration
    assert state is not None and state.pieces is not None
    state.pieces = [None] * len(state.pieces)  # cut (_finish_open_pieces) as learn() does before requeueing
    requeue_open_segments(state, n_envs=3)
    assert state.pieces is None and len(state.remaining) == 3
    start_piece(state, 2, task=0)  # the third env starts a piece: one slot per env again
    assert state.pieces is not None and len(state.pieces) == 3


def test_gradient_conflict_of_an_mc_model_samples_the_returns(tiny_kwargs: dict[str, Any]) -> None:
    model = _mc_model(tiny_kwargs, prior_coef=0.5).learn(240)
    conflict = compute_gradient_conflict(model, model.replay_buffer, n_batches=2)
    assert conflict["prior_norm"] > 0 and -1.0 <= conflict["cos"] <= 1.0


def test_the_returns_survive_save_load_and_an_old_buffer_loads(tmp_path: Path, tiny_kwargs: dict[str, Any]) -> None:
    model = _mc_model(tiny_kwargs).learn(380)
    model.save_replay_buffer(tmp_path / "buffer")
    loaded = _mc_model(tiny_kwargs)
    loaded.load_replay_buffer(tmp_path / "buffer.pkl")
    for name in ("return_reward", "return_log_prob", "return_discount", "return_tail", "return_ready"):
        assert np.array_equal(getattr(loaded.replay_buffer.rl, name), getattr(model.replay_buffer.rl, name)), name
    # A buffer of a model without Monte-Carlo targets has no return arrays; an mc model loading it knows no return yet.
    plain = PEARLPlus("MlpPolicy", gym.make("PointGoalMeta-v0"), seed=0, **tiny_kwargs).learn(240)
    assert not plain.replay_buffer.rl.has_returns
    plain.save_replay_buffer(tmp_path / "plain")
    loaded.load_replay_buffer(tmp_path / "plain.pkl")
    batch = loaded.replay_buffer.rl.sample(np.array([0, 1]), 8, returns=True)
    assert batch.returns is not None and float(batch.returns.ready.sum()) == 0.0
    losses = loaded._compute_losses(*loaded._sample_meta_batch())
    assert float(losses.prior_critic_loss.detach()) == 0.0  # no row with a return: nothing to fit yet


def test_an_open_iteration_cuts_its_pieces_when_the_envs_are_reset(tiny_kwargs: dict[str, Any]) -> None:
    model = _mc_model(tiny_kwargs, partial_iteration="carry").learn(250)  # 10 steps into iteration 1's first visit
    state = model._open_iteration
    assert state is not None and state.pieces is not None and any(piece is not None for piece in state.pieces)
    model.learn(130)  # reset_num_timesteps=True: the open piece is cut, its segment requeued; 130 steps finish it
    rl = model.replay_buffer.rl
    assert model._open_iteration is None and rl.size.sum() == 380
    assert np.array_equal(rl.prior_z[:, : rl.size.max()], rl.return_ready[:, : rl.size.max()])


def test_a_discrete_mc_model_collects_a_return_for_every_prior_row(tiny_kwargs: dict[str, Any]) -> None:
    model = PEARLPlus("MlpPolicy", make_discrete_env(), seed=0, prior_target="mc", **tiny_kwargs).learn(380)
    rl = model.replay_buffer.rl
    prior, ready = rl.prior_z[:, : rl.size.max()], rl.return_ready[:, : rl.size.max()]
    assert prior.any() and np.array_equal(prior, ready)
    log_prob_sums = rl.return_log_prob[:, : rl.size.max()][ready == 1.0]  # sums of log-probabilities of 3 actions: <= 0
    assert np.all(np.isfinite(log_prob_sums)) and np.all(log_prob_sums <= 0.0)
