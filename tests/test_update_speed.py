"""The fast gradient step computes the old one's math, and the default thread count yields to the user's.

The old path is kept here as a reference: the critics' frozen passes through ``torch.func.functional_call``, the
actor's two output heads as two products, Adam's single-tensor loop and SB3's per-tensor ``polyak_update``. Both run
100 updates from the same state on the same batch with the same random draws; the losses of every step and the
weights after the last one agree to float rounding (the fused Adam kernel and the fused heads round differently).
"""

from __future__ import annotations

import copy
import pathlib
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.logger import configure
from stable_baselines3.common.utils import polyak_update
from torch.func import functional_call

import sb3_pearl.pearl.pearl as pearl_module
from sb3_pearl import PEARL, PEARLPlus
from sb3_pearl.common import threads
from sb3_pearl.common.networks import LOG_STD_MAX, LOG_STD_MIN, LatentCritic, SquashedGaussianActor
from tests.conftest import make_discrete_env

ROOT = pathlib.Path(__file__).resolve().parents[1]
UPDATES = 100
LOSS_NAMES = ("critic_loss", "kl_loss", "prior_critic_loss", "actor_loss", "prior_actor_loss", "ent_coef_loss")
# Float32 rounding differences of the fused kernels, grown over 100 Adam steps (measured: weights <= 3e-7 apart, losses
# <= 1e-5 relative; the entropy coefficient's loss, which crosses 0, and its log coefficient <= 5e-5 absolute):
WEIGHT_RTOL, WEIGHT_ATOL = 1e-5, 1e-6
LOSS_RTOL, LOSS_ATOL = 1e-4, 1e-4


def _old_forward_frozen(self: LatentCritic, x: th.Tensor) -> th.Tensor:
    params = {name: p.detach() for name, p in self.named_parameters()}
    return functional_call(self, params, (x,))


def _old_params(self: SquashedGaussianActor, x: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
    h = self.latent_pi(x)
    with th.autocast(device_type=h.device.type, enabled=False):
        h = h.float()
        return self.mu(h), th.clamp(self.log_std(h), LOG_STD_MIN, LOG_STD_MAX)


def _old_polyak(params: list[th.Tensor], target_params: list[th.Tensor], tau: float) -> None:
    polyak_update(params, target_params, tau)


def _train_fixed_batch(model: PEARLPlus, batch: Any, seed: int) -> list[list[float]]:
    """``UPDATES`` gradient steps on ``batch``; the losses of every step."""
    recorded: list[list[float]] = []
    compute = model._compute_losses

    def record(*args: Any) -> Any:
        losses = compute(*args)
        recorded.append([float(getattr(losses, name).detach()) for name in LOSS_NAMES])
        return losses

    model._sample_meta_batch = lambda batch_size=None: batch  # type: ignore[method-assign]
    model._compute_losses = record  # type: ignore[method-assign]
    th.manual_seed(seed)
    model.train(gradient_steps=UPDATES, batch_size=model.batch_size)
    return recorded


@pytest.mark.parametrize("discrete", [False, True])
def test_fast_update_equals_the_old_path(discrete: bool, tiny_kwargs: dict[str, Any], monkeypatch: Any) -> None:
    env = make_discrete_env() if discrete else gym.make("PointGoalMeta-v0")
    kwargs = {**tiny_kwargs, "ent_coef": "auto"}  # the entropy optimizer and loss too
    new = PEARLPlus("MlpPolicy", env, seed=0, **kwargs)
    new.learn(4 * tiny_kwargs["num_initial_steps"])  # fills every task's buffers
    old_kwargs = {**kwargs, "policy_kwargs": {**kwargs.get("policy_kwargs", {}), "optimizer_kwargs": {"foreach": False}}}
    old = PEARLPlus("MlpPolicy", env, seed=0, **old_kwargs)
    old.policy.load_state_dict(new.policy.state_dict())
    for fast, slow in zip(new.policy.optimizers(), old.policy.optimizers()):
        assert fast.param_groups[0]["fused"] and not slow.param_groups[0]["fused"]
        slow.load_state_dict(copy.deepcopy(fast.state_dict()))
        for group in slow.param_groups:  # load_state_dict restored the fused flag: the old single-tensor loop
            group["fused"], group["foreach"] = None, False
    assert new.log_ent_coef is not None and old.log_ent_coef is not None and old.ent_coef_optimizer is not None
    with th.no_grad():
        old.log_ent_coef.copy_(new.log_ent_coef)
    for model in (new, old):
        model.set_logger(configure(None, [""]))
    batch = new._sample_meta_batch(new.batch_size)

    fast_losses = _train_fixed_batch(new, batch, seed=1)
    monkeypatch.setattr(LatentCritic, "forward_frozen", _old_forward_frozen)
    monkeypatch.setattr(SquashedGaussianActor, "_params", _old_params)
    monkeypatch.setattr(pearl_module, "polyak_update_foreach", _old_polyak)
    old_losses = _train_fixed_batch(old, batch, seed=1)

    assert len(fast_losses) == len(old_losses) == UPDATES
    np.testing.assert_allclose(np.array(fast_losses), np.array(old_losses), rtol=LOSS_RTOL, atol=LOSS_ATOL)
    fast_state, old_state = new.policy.state_dict(), old.policy.state_dict()
    assert fast_state.keys() == old_state.keys()  # the parameter layout is unchanged: saved models load as they are
    for name in fast_state:
        np.testing.assert_allclose(
            fast_state[name].numpy(), old_state[name].numpy(), rtol=WEIGHT_RTOL, atol=WEIGHT_ATOL, err_msg=name
        )
    # Adam's normalised step turns the rounding of a near-zero gradient into a sizeable share of lr: 1.2e-5 measured
    np.testing.assert_allclose(new.log_ent_coef.detach().numpy(), old.log_ent_coef.detach().numpy(), atol=LOSS_ATOL)


def test_a_loaded_model_steps_with_fused_adam(tmp_path: Any, tiny_kwargs: dict[str, Any]) -> None:
    model = PEARLPlus("MlpPolicy", gym.make("PointGoalMeta-v0"), seed=0, **tiny_kwargs)
    model.learn(4 * tiny_kwargs["num_initial_steps"])
    for optimizer in model.policy.optimizers():  # as a model saved before the optimizers were fused
        for group in optimizer.param_groups:
            group["fused"] = None
    model.save(tmp_path / "model.zip")
    loaded = PEARLPlus.load(tmp_path / "model.zip")
    assert all(group["fused"] for optimizer in loaded.policy.optimizers() for group in optimizer.param_groups)


@pytest.fixture
def fresh_threads(monkeypatch: Any) -> Any:
    """The thread module as in a fresh process where nobody chose a count; torch's count restored afterwards."""
    before = th.get_num_threads()
    for name in threads.THREAD_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setattr(threads, "_count_at_import", th.get_num_threads())
    monkeypatch.setattr(threads, "_state", {"applied": None, "explicit": False})
    yield threads
    th.set_num_threads(before)


def test_the_thread_default_applies_unless_the_user_chose(
    fresh_threads: Any, monkeypatch: Any, tiny_kwargs: dict[str, Any]
) -> None:
    model = PEARLPlus("MlpPolicy", gym.make("PointGoalMeta-v0"), seed=0, **tiny_kwargs)
    assert threads.network_width(model.policy) == 32
    assert threads.default_num_threads(16) == 1
    monkeypatch.setattr(threads, "idle_cores", lambda: 3)
    assert threads.default_num_threads(threads.WIDE_LAYER) == 3
    monkeypatch.setattr(threads, "idle_cores", lambda: 0)
    assert threads.default_num_threads(300) == 1
    monkeypatch.setattr(threads, "idle_cores", lambda: 64)
    assert threads.default_num_threads(300) == threads.MAX_THREADS

    th.set_num_threads(2)  # torch's default on a 2-core machine, seen at import
    monkeypatch.setattr(threads, "_count_at_import", 2)
    model.learn(20)  # learn() applies the default: small networks, one thread
    assert th.get_num_threads() == 1
    model.learn(20)  # its own default is not taken for the user's choice
    assert th.get_num_threads() == 1

    th.set_num_threads(2)  # the user's call after import wins
    model.learn(20)
    assert th.get_num_threads() == 2


def test_explicit_thread_counts_win(fresh_threads: Any, monkeypatch: Any) -> None:
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    assert threads.num_threads_is_explicit()
    assert threads.apply_default_num_threads(th.nn.Linear(3, 4)) is None
    monkeypatch.delenv("OMP_NUM_THREADS")
    assert not threads.num_threads_is_explicit()
    assert threads.num_threads_flag(["--algo", "pearl", "--num-threads", "3"]) == 3
    assert threads.num_threads_flag(["--algo", "pearl"]) == -1
    threads.mark_num_threads_explicit()  # train.py / enjoy.py with --num-threads N
    assert threads.apply_default_num_threads(th.nn.Linear(3, 4)) is None


@pytest.mark.parametrize(
    "cls, path",
    [
        (PEARLPlus, "results/merge-table1/highway-merge/pearlplus-fixed-entropy/seed0/model.zip"),  # Discrete
        (PEARL, "results/pearl-reference/walker2d-vel-long/pearl/seed0/model.zip"),  # Box
    ],
)
def test_committed_models_load_and_predict_as_before(cls: type[PEARL], path: str, monkeypatch: Any) -> None:
    model = cls.load(ROOT / path, device="cpu")
    assert all(group["fused"] for optimizer in model.policy.optimizers() for group in optimizer.param_groups)
    policy = model.policy
    generator = th.Generator().manual_seed(0)
    obs = th.randn(64, policy.obs_dim, generator=generator)
    z = th.randn(64, policy.latent_dim, generator=generator)
    x = th.cat([obs, z], dim=-1)
    critic_input = x if policy.discrete else th.cat([x, th.rand(64, policy.action_dim, generator=generator) * 2 - 1], -1)

    def outputs() -> list[th.Tensor]:
        th.manual_seed(1)
        with th.no_grad():
            actions = [policy.act(obs, z, deterministic=True), policy.act(obs, z)]
            return [*actions, policy.critic.forward_frozen(critic_input), policy.critic(critic_input)]

    new = outputs()
    monkeypatch.setattr(LatentCritic, "forward_frozen", _old_forward_frozen)
    monkeypatch.setattr(SquashedGaussianActor, "_params", _old_params)
    old = outputs()
    for fast, slow in zip(new, old):
        # the fused heads' product sums the hidden units in another order: pre-tanh means up to 15 move by <= 2e-5
        np.testing.assert_allclose(fast.numpy(), slow.numpy(), rtol=1e-5, atol=5e-5)
