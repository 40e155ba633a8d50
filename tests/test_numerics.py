"""Numbers that go wrong: a non-finite env output or observation is named where it enters, the divergence guard skips
non-finite losses and gradients and stops training on repeated ones, and bfloat16 is used only where it is native."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env

import tests.faulty_envs  # noqa: F401  (registers the failing families)
from sb3_pearl import PEARL, PEARLPlus
from sb3_pearl.common.divergence import DivergenceError, NonFiniteEnvError
from tests.conftest import tiny_finetune, tiny_maml, tiny_pearl


# ----------------------------------------------------------------------------------------------
# Divergence guard
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("what, shown", [("reward", r"reward \(nan\)"), ("obs", r"observation \(\[inf, inf\]\)")])
@pytest.mark.parametrize("algo", ["pearlplus", "finetune", "maml"])
def test_non_finite_env_output_names_env_task_and_step(algo: str, what: str, shown: str, tiny_kwargs: dict[str, Any]) -> None:
    value = float("nan") if what == "reward" else float("inf")
    env = make_vec_env("NonFiniteSafePointGoalMeta-v0", n_envs=2, env_kwargs=dict(what=what, value=value, fail_after=40))
    model = {
        "pearlplus": lambda: PEARLPlus("MlpPolicy", env, seed=0, **tiny_kwargs),
        "finetune": lambda: tiny_finetune(env),  # type: ignore[arg-type]
        "maml": lambda: tiny_maml(env),  # type: ignore[arg-type]
    }[algo]()
    with pytest.raises(
        NonFiniteEnvError,
        match=rf"NonFiniteSafePointGoalMeta-v0 returned a non-finite {shown} at timestep \d+ \(env index \d, task \{{'goal'",
    ):
        model.learn(400)


def all_finite(model: PEARL) -> bool:
    tensors = list(model.policy.parameters())
    for optimizer in model.policy.optimizers():
        tensors += [v for state in optimizer.state.values() for v in state.values() if th.is_tensor(v)]
    return all(bool(th.isfinite(t).all()) for t in tensors)


def test_non_finite_losses_are_skipped_and_repeated_ones_stop_training(tiny_kwargs: dict[str, Any]) -> None:
    # One reward of 1e30 (finite, so no env error): its critic targets overflow; those steps are skipped and the
    # Adam state stays finite; the poisoned context keeps coming back, so training stops with the cause named.
    env = gym.make("NonFiniteSafePointGoalMeta-v0", value=1e30, fail_after=100)
    model = PEARLPlus("MlpPolicy", env, seed=0, **tiny_kwargs)
    with (
        pytest.warns(UserWarning, match="skipped a gradient step with non-finite critic_loss=inf"),
        pytest.raises(
            DivergenceError, match=r"10 gradient steps in a row had a non-finite loss .*critic_loss=inf.*reward_scale"
        ),
    ):
        model.learn(2000)
    assert model._update_guard.skipped >= 10 and all_finite(model)


def test_huge_learning_rate_stops_with_a_message_instead_of_a_torch_error(tiny_kwargs: dict[str, Any]) -> None:
    model = tiny_pearl(tiny_kwargs, seed=0, learning_rate=1e6)
    with (
        pytest.warns(UserWarning, match="skipped a gradient step"),
        pytest.raises(DivergenceError, match=r"Likely fixes: a lower learning_rate.*learning_rate=1000000.0"),
    ):
        model.learn(3000)
    assert all(bool(th.isfinite(p).all()) for p in model.policy.parameters())


def test_guard_skips_a_step_with_a_non_finite_gradient_only(tiny_kwargs: dict[str, Any]) -> None:
    model = tiny_pearl(tiny_kwargs, seed=0)
    model.learn(100)
    before = {k: v.clone() for k, v in model.policy.state_dict().items()}
    hook = model.actor.mu.weight.register_hook(lambda grad: grad * float("inf"))
    with pytest.warns(UserWarning, match="finite losses but a non-finite gradient"):
        model.train(gradient_steps=3, batch_size=8)
    hook.remove()
    assert model._update_guard.skipped == 3 and model._update_guard.consecutive == 3
    assert all(th.equal(v, before[k]) for k, v in model.policy.state_dict().items())  # nothing stepped
    model.train(gradient_steps=1, batch_size=8)
    assert model._update_guard.consecutive == 0 and all_finite(model)


# ----------------------------------------------------------------------------------------------
# bfloat16 only where it is native
# ----------------------------------------------------------------------------------------------
def test_bf16_falls_back_to_float32_without_native_support(
    monkeypatch: pytest.MonkeyPatch, tiny_kwargs: dict[str, Any]
) -> None:
    from sb3_pearl.common import precision

    monkeypatch.setattr(precision, "cpu_flags", lambda: frozenset({"avx2", "fma"}))  # an AVX2-only CPU
    with pytest.warns(UserWarning, match=r"no native bfloat16 .*1.5-18x slower.*trains in float32.*use_bf16='force'"):
        model = tiny_pearl(tiny_kwargs, seed=0, use_bf16=True, device="cpu")
    assert model.use_bf16 is True and not model._bf16_enabled
    assert tiny_pearl(tiny_kwargs, seed=0, use_bf16="force", device="cpu")._bf16_enabled
    monkeypatch.setattr(precision, "cpu_flags", lambda: frozenset({"avx2", "avx512_bf16"}))
    assert tiny_pearl(tiny_kwargs, seed=0, use_bf16=True, device="cpu")._bf16_enabled
    assert precision.native_bf16(th.device("cpu"))[0]


@pytest.mark.parametrize("algo", ["pearlplus", "finetune", "maml"])
def test_predict_refuses_a_non_finite_observation(algo: str, tiny_kwargs: dict[str, Any]) -> None:
    model = {"pearlplus": lambda: tiny_pearl(tiny_kwargs, seed=0), "finetune": tiny_finetune, "maml": tiny_maml}[algo]()
    model.reset_adaptation()
    obs = np.array([np.nan, 0.0], dtype=np.float32)
    with pytest.raises(ValueError, match=r"\.predict\(\): the observation holds a non-finite value \(\[nan, 0.0\]\)"):
        model.predict(obs, deterministic=True)
    action, _ = model.predict(np.zeros(2, dtype=np.float32), deterministic=True)
    assert np.isfinite(action).all()
