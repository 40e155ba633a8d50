"""Which losses reach which parameters, and the critic target's detached z (Algorithm 1)."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
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
    enc, actor, critic, prior = model.encoder, model.actor, model.critic, model.prior_critic

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
        assert prior is None and not _reaches(losses.prior_actor_loss, actor)
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
