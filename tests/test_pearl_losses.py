"""Which losses reach which parameters, and the critic target's detached z (Algorithm 1)."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from torch import nn

from sb3_pearl import PEARL, PEARLPlus
from tests.conftest import make_discrete_env


def _model(kind: str, discrete: bool, tiny_kwargs: dict[str, Any]) -> PEARLPlus:
    env = make_discrete_env() if discrete else gym.make("PointGoalMeta-v0")
    if kind == "pearl":
        model: PEARLPlus = PEARL(
            "MlpPolicy", env, seed=0, **{k: v for k, v in tiny_kwargs.items() if k != "prior_critic_arch"}
        )
    else:
        model = PEARLPlus("MlpPolicy", env, seed=0, prior_critic=kind, **tiny_kwargs)
    model.learn(4 * tiny_kwargs["num_initial_steps"])  # fills every task's buffers
    return model


def _grads(loss: th.Tensor, module: nn.Module | None) -> list[th.Tensor]:
    if module is None:
        return []
    params = [p for p in module.parameters() if p.requires_grad]
    if not loss.requires_grad:  # a constant (e.g. PEARL's prior terms) reaches nothing
        return [th.zeros_like(p) for p in params]
    grads = th.autograd.grad(loss, params, retain_graph=True, allow_unused=True)
    return [th.zeros_like(p) if g is None else g for g, p in zip(grads, params)]


def _is_zero(loss: th.Tensor, module: nn.Module | None) -> bool:
    return all(bool((g == 0).all()) for g in _grads(loss, module))


def _reaches(loss: th.Tensor, module: nn.Module | None) -> bool:
    return any(bool((g != 0).any()) for g in _grads(loss, module))


@pytest.mark.parametrize("discrete", [False, True])
@pytest.mark.parametrize("kind", ["separate", "shared", "pearl"])
def test_gradient_isolation(kind: str, discrete: bool, tiny_kwargs: dict[str, Any]) -> None:
    model = _model(kind, discrete, tiny_kwargs)
    replay, context, z0 = model._sample_meta_batch()
    losses = model._compute_losses(replay, context, z0)
    enc, actor, critic = model.encoder, model.actor, model.critic
    prior = model.prior_critic if isinstance(model, PEARLPlus) else None

    # The encoder learns from the critic loss and the KL, and from nothing else.
    assert _reaches(losses.critic_loss, enc)
    assert _reaches(losses.kl_loss, enc)
    for name in ("actor_loss", "prior_actor_loss", "prior_critic_loss", "ent_coef_loss"):
        assert _is_zero(getattr(losses, name), enc), name

    # Critic loss reaches the critic only; actor terms reach the actor only (critics frozen).
    assert _reaches(losses.critic_loss, critic)
    assert _is_zero(losses.critic_loss, actor) and _is_zero(losses.critic_loss, prior)
    assert _reaches(losses.actor_loss, actor)
    for module in (critic, prior):
        assert _is_zero(losses.actor_loss, module)
        assert _is_zero(losses.prior_actor_loss, module)
    if kind == "pearl":
        assert not hasattr(model, "prior_critic") and model.policy.prior_critic is None  # PEARL has none
        assert not _reaches(losses.prior_actor_loss, actor)
        assert float(losses.prior_actor_loss) == 0.0 and float(losses.prior_critic_loss) == 0.0
    else:
        assert _reaches(losses.prior_actor_loss, actor)
    if kind == "separate":
        assert _reaches(losses.prior_critic_loss, prior)
        assert _is_zero(losses.prior_critic_loss, actor) and _is_zero(losses.prior_critic_loss, critic)
    if kind == "shared":
        assert prior is None and float(losses.prior_critic_loss) == 0.0


@pytest.mark.parametrize("discrete", [False, True])
def test_critic_target_uses_detached_z(discrete: bool, tiny_kwargs: dict[str, Any]) -> None:
    """With the critic blind to z, the critic loss may not reach the encoder: the target's z is detached."""
    model = _model("separate", discrete, tiny_kwargs)
    obs_dim = model.policy.obs_dim
    with th.no_grad():
        for q_net in model.critic.q_networks:
            first = q_net[0]
            assert isinstance(first, nn.Linear)
            first.weight[:, obs_dim : obs_dim + model.latent_dim] = 0.0  # Q(s, a, z) ignores z ...
    replay, context, z0 = model._sample_meta_batch()
    losses = model._compute_losses(replay, context, z0)
    # ... while the target network and the actor (which use z) are untouched.
    assert _is_zero(losses.critic_loss, model.encoder)
    assert _reaches(losses.kl_loss, model.encoder)


def test_one_backward_equals_separate_updates(tiny_kwargs: dict[str, Any]) -> None:
    """The summed loss gives each network exactly the gradient of its own loss."""
    model = _model("separate", False, tiny_kwargs)
    replay, context, z0 = model._sample_meta_batch()
    th.manual_seed(3)
    losses = model._compute_losses(replay, context, z0)
    total = model._total_loss(losses)
    own = {
        "encoder": losses.critic_loss + model.kl_weight * losses.kl_loss,
        "actor": losses.actor_loss + model.prior_coef * losses.prior_actor_loss,
        "critic": losses.critic_loss,
        "prior_critic": losses.prior_critic_loss,
    }
    for name, loss in own.items():
        module = getattr(model, name)
        for g_total, g_own in zip(_grads(total, module), _grads(loss, module)):
            assert th.allclose(g_total, g_own, atol=1e-6), name


def test_z0_is_one_per_task_and_actor_loss_weights(tiny_kwargs: dict[str, Any]) -> None:
    model = _model("separate", False, tiny_kwargs)
    replay, context, z0 = model._sample_meta_batch()
    assert z0.shape == (tiny_kwargs["meta_batch"], tiny_kwargs["latent_dim"])
    assert context.shape == (tiny_kwargs["meta_batch"], tiny_kwargs["embedding_batch_size"], model.policy.context_dim)
    losses = model._compute_losses(replay, context, z0)
    expected = (
        losses.critic_loss
        + model.kl_weight * losses.kl_loss
        + losses.prior_critic_loss
        + losses.actor_loss
        + 0.1 * losses.prior_actor_loss
        + losses.ent_coef_loss
    )
    assert model.prior_coef == 0.1
    assert th.allclose(model._total_loss(losses), expected)


def test_bf16_hidden_layers_keep_float32_heads_and_master_weights(tiny_kwargs: dict[str, Any]) -> None:
    model = PEARLPlus("MlpPolicy", gym.make("PointGoalMeta-v0"), seed=0, use_bf16=True, **tiny_kwargs)
    model.learn(4 * tiny_kwargs["num_initial_steps"])
    assert model._n_updates > 0
    replay, context, z0 = model._sample_meta_batch()
    with th.autocast("cpu", dtype=th.bfloat16):
        hidden = model.critic.q_networks[0][0](th.zeros(4, model.critic.q_networks[0][0].in_features))
        losses = model._compute_losses(replay, context, z0)
        z_mean, z_var = model.encoder.posterior(context)
        x = th.zeros(4, model.critic.q_networks[0][0].in_features)
        q = model.critic(x)
    assert hidden.dtype == th.bfloat16  # the hidden layers really run in bfloat16 ...
    assert q.dtype == z_mean.dtype == z_var.dtype == th.float32  # ... the output layers in float32
    for name in ("critic_loss", "kl_loss", "prior_critic_loss", "actor_loss", "prior_actor_loss"):
        value = getattr(losses, name)
        assert value.dtype == th.float32 and th.isfinite(value), name
    assert all(p.dtype == th.float32 and th.isfinite(p).all() for p in model.policy.parameters())
    assert _is_zero(losses.prior_critic_loss, model.encoder) and _is_zero(losses.actor_loss, model.encoder)


# ----------------------------------------------------------------------------------------------
# prior_data="prior": the prior terms use only the rows collected with z from the prior
# ----------------------------------------------------------------------------------------------
def test_masked_regression_and_mean_by_hand() -> None:
    from sb3_pearl.common.soft_actor_critic import critic_regression_loss, masked_mean

    q = th.tensor([[[1.0], [2.0], [4.0]], [[0.0], [0.0], [3.0]]])  # 2 critics, 3 rows
    target = th.tensor([[0.0], [1.0], [1.0]])
    rows = th.tensor([[1.0], [0.0], [1.0]])  # rows 0 and 2
    # critic 1: (1 + 9) / 2 = 5; critic 2: (0 + 4) / 2 = 2; summed: 7 (unmasked: (1 + 1 + 9) / 3 + (0 + 1 + 4) / 3 = 16 / 3)
    assert float(critic_regression_loss(q, target, weights=rows)) == pytest.approx(7.0)
    assert float(critic_regression_loss(q, target)) == pytest.approx(16 / 3)
    assert float(masked_mean(th.tensor([[2.0], [5.0], [4.0]]), rows)) == pytest.approx(3.0)
    assert float(masked_mean(th.tensor([[2.0], [5.0]]), th.zeros(2, 1))) == 0.0  # no rows: 0, not nan


def test_collection_marks_the_prior_z_transitions(tiny_kwargs: dict[str, Any]) -> None:
    # iteration 0: 4 tasks x 60 prior steps; iteration 1: 2 visits x (30 prior + 10 posterior + 30 posterior RL-only)
    model = PEARLPlus("MlpPolicy", "PointGoalMeta-v0", seed=0, **tiny_kwargs).learn(380)
    rl = model.replay_buffer.rl
    flags = [rl.prior_z[t, : rl.size[t], 0] for t in range(rl.n_tasks)]
    assert sum(int(f.sum()) for f in flags) == 240 + 2 * 30 and sum(len(f) for f in flags) == 380
    assert set(np.unique(np.concatenate(flags)).tolist()) == {0.0, 1.0}


def test_prior_data_prior_ignores_the_posterior_rows(tiny_kwargs: dict[str, Any]) -> None:
    model = PEARLPlus("MlpPolicy", "PointGoalMeta-v0", seed=0, prior_data="prior", **tiny_kwargs).learn(380)
    th.manual_seed(0)
    replay, context, z0 = model._sample_meta_batch()
    assert replay.prior_z is not None
    flags = th.zeros_like(replay.prior_z)
    flags[:, ::2] = 1.0  # every other row counts as collected with the prior
    replay = replay._replace(prior_z=flags)

    def losses(batch: Any) -> Any:
        th.manual_seed(1)  # the same posterior z and policy noise for both batches
        return model._compute_losses(batch, context, z0)

    # Rows marked as posterior data changed beyond recognition: the prior terms do not move; the posterior ones do.
    scrambled = replay._replace(
        observations=th.where(flags.bool(), replay.observations, replay.observations + 3.0),
        rewards=th.where(flags.bool(), replay.rewards, replay.rewards - 100.0),
    )
    a, b = losses(replay), losses(scrambled)
    assert th.equal(a.prior_critic_loss, b.prior_critic_loss) and th.equal(a.prior_actor_loss, b.prior_actor_loss)
    assert not th.equal(a.critic_loss, b.critic_loss) and not th.equal(a.actor_loss, b.actor_loss)
    assert _reaches(a.prior_critic_loss, model.prior_critic) and _reaches(a.prior_actor_loss, model.actor)
    # No prior rows in the batch: the prior terms are 0 and reach nothing.
    none = losses(replay._replace(prior_z=th.zeros_like(flags)))
    assert none.prior_critic_loss.item() == 0.0 and _is_zero(none.prior_critic_loss, model.prior_critic)
    assert none.prior_actor_loss.item() == 0.0 and _is_zero(none.prior_actor_loss, model.actor)
    # Every row a prior row: the paper's losses (prior_data="all") on the same batch.
    everything = losses(replay._replace(prior_z=th.ones_like(flags)))
    model.prior_data = "all"
    paper = losses(replay)
    assert th.allclose(everything.prior_critic_loss, paper.prior_critic_loss)
    assert th.allclose(everything.prior_actor_loss, paper.prior_actor_loss)


def test_prior_data_is_checked_and_saved(tmp_path: Any, tiny_kwargs: dict[str, Any]) -> None:
    with pytest.raises(ValueError, match=r"unknown prior_data 'posterior'.*\('all', 'prior'\)"):
        PEARLPlus("MlpPolicy", "PointGoalMeta-v0", prior_data="posterior", **tiny_kwargs)
    model = PEARLPlus("MlpPolicy", "PointGoalMeta-v0", seed=0, prior_data="prior", **tiny_kwargs)
    model.save(tmp_path / "model")
    assert PEARLPlus.load(tmp_path / "model").prior_data == "prior"
    pearl = PEARL("MlpPolicy", "PointGoalMeta-v0", **{k: v for k, v in tiny_kwargs.items() if k != "prior_critic_arch"})
    assert not hasattr(pearl, "prior_data") and pearl._loss_settings().prior_data == "all"  # PEARL's losses: every row


def test_a_buffer_saved_before_the_prior_z_flag_loads_with_no_row_marked(tiny_kwargs: dict[str, Any]) -> None:
    rl = PEARLPlus("MlpPolicy", "PointGoalMeta-v0", seed=0, **tiny_kwargs).learn(240).replay_buffer.rl
    state = rl.__getstate__()
    del state["prior_z"]  # the pickle of an older version
    old = type(rl).__new__(type(rl))
    old.__setstate__(state)
    assert old.prior_z.shape == rl.prior_z.shape and not old.prior_z.any() and rl.prior_z.any()
    np.testing.assert_array_equal(old.observations, rl.observations)
