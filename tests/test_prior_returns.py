"""Monte-Carlo targets of the prior critic (``prior_target="mc"``, :mod:`sb3_pearl.pearl.returns`): the returns by hand,
what collection writes into the replay buffer, the behaviour log-probabilities, save / load and exact resumption."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th

from sb3_pearl import PEARLPlus
from sb3_pearl.common.soft_actor_critic import log_prob_of_actions
from sb3_pearl.pearl.returns import PendingPiece, finish_piece, piece_returns
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


@pytest.mark.parametrize("discrete", [False, True])
def test_log_prob_of_stored_actions_is_the_policys(discrete: bool) -> None:
    env = make_discrete_env() if discrete else gym.make("PointGoalMeta-v0")
    model = PEARLPlus("MlpPolicy", env, seed=0, n_train_tasks=2, n_test_tasks=1)
    x = th.randn(6, model.policy.obs_dim + model.latent_dim)
    with th.no_grad():
        if discrete:
            probs, log_probs = model.actor.probs(x)
            actions = th.multinomial(probs, 1).float()  # (6, 1) stored indices
            expected = log_probs.gather(-1, actions.long())
        else:
            actions, expected = model.actor.action_log_prob(x)  # sampled actions and their log-probabilities
        got = log_prob_of_actions(model.actor, x, actions)
    assert got.shape == (6, 1)
    th.testing.assert_close(got.reshape(-1), expected.reshape(-1), rtol=1e-4, atol=1e-4)


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


def test_finish_piece_uses_the_behaviour_policys_log_probabilities(tiny_kwargs: dict[str, Any]) -> None:
    model = _mc_model(tiny_kwargs, prior_return_steps=4).learn(240)
    rl, z = model.replay_buffer.rl, np.linspace(-1.0, 1.0, model.latent_dim).astype(np.float32)
    finish_piece(model, PendingPiece(task=2, z=z, rows=list(range(5, 15))), terminated=False)  # rows 5..14 as one piece
    rows = np.arange(5, 15)
    x = th.cat([th.as_tensor(rl.observations[2, rows]), th.as_tensor(z).expand(10, -1)], dim=-1)
    with th.no_grad():
        log_probs = log_prob_of_actions(model.actor, x, th.as_tensor(rl.actions[2, rows]))[:, 0].double().numpy()
    want = piece_returns(rl.rewards[2, rows, 0], log_probs, model.gamma, False, 4)
    np.testing.assert_allclose(rl.return_log_prob[2, rows, 0], want.log_prob_sum, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(rl.return_discount[2, rows, 0], want.discount, rtol=1e-6)
    assert list(rl.return_tail[2, rows, 0]) == [8, 9, 10, 11, 12, 13, 14, 14, 14, 14]
    # A row the buffer overwrites loses its return until its new trajectory piece ends.
    rl.pos[2] = 7
    rl.add(2, rl.observations[2, 0], rl.actions[2, 0], 0.0, rl.observations[2, 1], False, prior_z=True)
    assert rl.return_ready[2, 7, 0] == 0.0 and rl.return_ready[2, 8, 0] == 1.0


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
