"""learn(), the SB3 contract, data collection per task, determinism and errors (save / load: tests/test_save_load.py)."""

from __future__ import annotations

import inspect
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecNormalize

from sb3_pearl import PEARL, PEARLPlus
from sb3_pearl.envs.point_goal import PointGoalMetaEnv
from sb3_pearl.pearl.losses import LossSettings
from tests.conftest import CountSteps, make_discrete_env, make_point_env, tiny_pearl


def _assert_rewards_match_tasks(model: PEARLPlus) -> None:
    """PointGoal reward is -||s' - goal||: every stored transition must belong to its task's goal."""
    rl = model.replay_buffer.rl
    for task_index, task in enumerate(model.train_tasks):
        n = rl.size[task_index]
        assert n > 0
        expected = -np.linalg.norm(rl.next_observations[task_index, :n] - np.asarray(task["goal"], dtype=np.float32), axis=-1)
        np.testing.assert_allclose(rl.rewards[task_index, :n, 0], expected, atol=1e-5)


@pytest.mark.parametrize("n_envs,vec_env_cls", [(1, DummyVecEnv), (2, DummyVecEnv), (2, SubprocVecEnv)])
def test_learn_box_n_envs_keeps_tasks_apart(n_envs: int, vec_env_cls: type, tiny_kwargs: dict[str, Any]) -> None:
    env = make_vec_env(make_point_env, n_envs=n_envs, vec_env_cls=vec_env_cls, seed=0)
    model = PEARLPlus("MlpPolicy", env, seed=0, **tiny_kwargs)
    counter = CountSteps()
    total = 4 * 60 + 2 * 70
    model.learn(total, callback=counter)
    assert model.num_timesteps == total
    assert model.replay_buffer.total_transitions() == total
    assert counter.calls >= total // n_envs
    assert model.n_iterations == 2
    _assert_rewards_match_tasks(model)
    env.close()


@pytest.mark.parametrize("n_envs", [1, 2])
def test_learn_discrete(n_envs: int, tiny_kwargs: dict[str, Any]) -> None:
    env = make_vec_env(make_discrete_env, n_envs=n_envs, seed=0)
    model = PEARLPlus("MlpPolicy", env, seed=0, **tiny_kwargs)
    model.learn(400)
    assert model.num_timesteps == 400 and model._n_updates > 0
    _assert_rewards_match_tasks(model)
    actions = model.replay_buffer.rl.actions[0, : model.replay_buffer.rl.size[0], 0]
    assert set(np.unique(actions)) <= set(range(5))
    model.reset_adaptation()
    action, _ = model.predict(np.zeros(2, dtype=np.float32), deterministic=True)
    assert env.action_space.contains(int(action))


def test_termination_vs_truncation_and_cost(tiny_kwargs: dict[str, Any]) -> None:
    """Hazard entries (true terminations) store done=1; time-limit ends store done=0."""
    task = {"goal": [0.866, 0.5], "hazard": [0.0, 0.6]}
    kwargs = {**tiny_kwargs, "num_initial_steps": 300, "train_tasks": [task] * 4, "test_tasks": [task]}
    model = PEARLPlus("MlpPolicy", "SafePointGoalMeta-v0", seed=1, **kwargs)
    # A scripted collection policy drives straight up into the hazard, 0.065 per step:
    # positions 0.065 .. 0.325 are outside (distance >= 0.275), 0.39 is inside (0.21), clear of the boundary.
    model.policy.act = lambda obs, z, deterministic=False: th.tensor([[0.0, 0.65]]).expand(obs.shape[0], -1)  # type: ignore[method-assign]
    model.learn(300)
    rl = model.replay_buffer.rl
    n = rl.size[0]
    dones = rl.dones[0, :n, 0]
    in_hazard = np.linalg.norm(rl.next_observations[0, :n] - np.array([0.0, 0.6]), axis=-1) < 0.25
    np.testing.assert_array_equal(dones == 1.0, in_hazard)
    assert dones.sum() > 0


def test_time_limit_is_not_terminal(tiny_kwargs: dict[str, Any]) -> None:
    model = PEARL(
        "MlpPolicy", "PointGoalMeta-v0", seed=0, **{k: v for k, v in tiny_kwargs.items() if k != "prior_critic_arch"}
    )
    model.learn(240)
    assert model.replay_buffer.rl.dones.sum() == 0.0  # 20-step episodes end by truncation only


def test_seeded_runs_are_identical(tiny_kwargs: dict[str, Any]) -> None:
    def run() -> tuple[list[dict[str, Any]], list[th.Tensor]]:
        model = PEARLPlus("MlpPolicy", "SafePointGoalMeta-v0", seed=7, **tiny_kwargs)
        model.learn(400)
        return model.train_tasks, [p.detach().clone() for p in model.policy.parameters()]

    tasks_a, params_a = run()
    tasks_b, params_b = run()
    assert tasks_a == tasks_b
    assert all(th.equal(a, b) for a, b in zip(params_a, params_b))


def test_tasks_come_from_sample_tasks_with_the_seed(tiny_kwargs: dict[str, Any]) -> None:
    model = PEARLPlus("MlpPolicy", "SafePointGoalMeta-v0", seed=5, **tiny_kwargs)
    expected = gym.make("SafePointGoalMeta-v0").unwrapped.sample_tasks(6, seed=5)
    assert model.train_tasks == expected[:4] and model.test_tasks == expected[4:]


def test_adaptation_api(tiny_kwargs: dict[str, Any]) -> None:
    model = PEARLPlus("MlpPolicy", "PointGoalMeta-v0", seed=0, **tiny_kwargs)
    model.learn(300)
    model.reset_adaptation()
    prior_z = model.policy.current_z.clone()
    mean, var = model.infer_posterior()
    assert th.equal(mean, th.zeros(3)) and th.equal(var, th.ones(3))  # no data: the prior
    env = gym.make("PointGoalMeta-v0")
    env.unwrapped.set_task(model.test_tasks[0])
    obs, _ = env.reset(seed=0)
    for _ in range(20):
        action, _ = model.predict(obs, deterministic=True)
        assert th.equal(model.policy.current_z, prior_z)  # z is held during the prior trajectory
        next_obs, reward, terminated, truncated, _ = env.step(action)
        model.observe(obs, action, float(reward), next_obs, terminated or truncated)
        obs = next_obs
    model.adapt(sample_z=False)
    mean, var = model.infer_posterior()
    assert th.equal(model.policy.current_z, mean) and bool((var < 1).all())
    model.reset_adaptation()
    assert model._adapt_context == [] and not th.equal(model.policy.current_z, mean)


def test_progress_bar_and_logger_keys(tiny_kwargs: dict[str, Any]) -> None:
    model = PEARLPlus("MlpPolicy", "SafePointGoalMeta-v0", seed=0, **tiny_kwargs)
    model.learn(300, progress_bar=True, log_interval=1000)  # no dump: the recorded values stay readable
    expected = {"critic_loss", "prior_critic_loss", "actor_loss", "prior_actor_loss", "kl", "ent_coef", "z_mean_abs", "z_var"}
    assert {f"train/{key}" for key in expected} <= set(model.logger.name_to_value)
    assert model.logger.name_to_value["train/kl"] > 0


class NoTaskEnv(gym.Env):
    observation_space = spaces.Box(-1, 1, (2,))
    action_space = spaces.Box(-1, 1, (2,))

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        return np.zeros(2, dtype=np.float32), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        return np.zeros(2, dtype=np.float32), 0.0, False, False, {}


class MultiDiscretePoint(PointGoalMetaEnv):
    def __init__(self) -> None:
        super().__init__()
        self.action_space = spaces.MultiDiscrete([3, 3])


def test_clear_errors(tiny_kwargs: dict[str, Any]) -> None:
    with pytest.raises(ValueError, match="task-family env"):
        PEARLPlus("MlpPolicy", NoTaskEnv())
    with pytest.raises(ValueError, match="Box and Discrete"):
        PEARLPlus("MlpPolicy", MultiDiscretePoint())
    with pytest.raises(ValueError, match="prior_coef must be a finite number >= 0"):
        PEARLPlus("MlpPolicy", "PointGoalMeta-v0", prior_coef=-0.1)
    with pytest.raises(ValueError, match="unknown prior_critic mode 'both'"):
        PEARLPlus("MlpPolicy", "PointGoalMeta-v0", prior_critic="both")
    with pytest.raises(TypeError, match="prior_coef"):
        PEARL("MlpPolicy", "PointGoalMeta-v0", prior_coef=0.1)
    with pytest.raises(ValueError, match="VecNormalize"):
        PEARLPlus("MlpPolicy", VecNormalize(make_vec_env("PointGoalMeta-v0")))
    with pytest.raises(ValueError, match="ent_coef"):
        PEARLPlus("MlpPolicy", "PointGoalMeta-v0", ent_coef="fixed")


def test_pearl_has_no_prior_term(tiny_kwargs: dict[str, Any]) -> None:
    """PEARL names nothing of PEARL+: no prior critic in its policy, no prior setting, no prior term in its losses."""
    kwargs = {k: v for k, v in tiny_kwargs.items() if k != "prior_critic_arch"}
    model = PEARL("MlpPolicy", "PointGoalMeta-v0", seed=0, **kwargs)
    assert model.policy.prior_critic is None and model.policy.prior_critic_mode == "none"
    assert not any("prior" in name for name in model.policy.state_dict())
    assert not [name for name in dir(model) if name.startswith("prior_") or name == "uses_prior_term"]
    assert not [name for name in inspect.signature(PEARL).parameters if name.startswith("prior_")]
    assert "prior_critic" not in model.policy_kwargs and "prior_critic" not in model.networks
    settings = model._loss_settings()
    assert settings == LossSettings(model.gamma, model.reward_scale, float(model.target_entropy))  # no prior switch set
    assert not settings.prior_term and settings.prior_conservative_weight == 0.0
    model.learn(4 * kwargs["num_initial_steps"], log_interval=1000)  # no dump: the logged keys stay readable
    losses = model._compute_losses(*model._sample_meta_batch())
    assert float(losses.prior_critic_loss) == 0.0 and float(losses.prior_actor_loss) == 0.0
    assert not losses.prior_critic_loss.requires_grad and not losses.prior_actor_loss.requires_grad
    plain = losses.critic_loss + model.kl_weight * losses.kl_loss + losses.actor_loss + losses.ent_coef_loss
    assert th.equal(model._total_loss(losses), plain)  # the total has no prior term
    assert model._target_pairs()[0] == [*model.critic.parameters()]  # the critic's pairs only
    assert model._get_torch_save_params()[0] == ["policy", "encoder.optimizer", "actor.optimizer", "critic.optimizer"]
    assert "prior_coef" not in model._divergence_settings()
    assert not [name for name in model._named_losses(losses) if "prior" in name]
    assert (
        not [key for key in model.logger.name_to_value if "prior" in key] and "train/actor_loss" in model.logger.name_to_value
    )
    shared = PEARLPlus("MlpPolicy", "PointGoalMeta-v0", seed=0, prior_critic="shared", **kwargs)
    assert shared.prior_critic is None and shared.prior_coef == 0.1


def test_twin_critics_have_distinct_initialisations(tiny_kwargs: dict[str, Any]) -> None:
    model = PEARLPlus("MlpPolicy", "PointGoalMeta-v0", seed=0, prior_n_critics=2, **tiny_kwargs)
    for critic in (model.critic, model.prior_critic):
        assert critic is not None and len(critic.q_networks) == 2
        first, second = (q[0].weight for q in critic.q_networks)
        assert not th.equal(first, second)
    assert len(PEARLPlus("MlpPolicy", "PointGoalMeta-v0", seed=0, **tiny_kwargs).prior_critic.q_networks) == 1


def test_collection_sizes_are_validated_and_zero_initial_steps_work(tiny_kwargs: dict[str, Any]) -> None:
    with pytest.raises(ValueError, match="context buffer"):
        PEARLPlus("MlpPolicy", "PointGoalMeta-v0", **{**tiny_kwargs, "num_steps_prior": 0, "num_steps_posterior": 0})
    with pytest.raises(ValueError, match=">= 0"):
        PEARLPlus("MlpPolicy", "PointGoalMeta-v0", **{**tiny_kwargs, "num_initial_steps": -1})
    model = PEARLPlus("MlpPolicy", "PointGoalMeta-v0", seed=0, **{**tiny_kwargs, "num_initial_steps": 0})
    model.learn(200)  # no initial phase: every iteration visits sampled tasks
    assert model.num_timesteps == 200 and model._n_updates > 0


def test_pearlplus_without_prior_term_is_pearl(tiny_kwargs: dict[str, Any]) -> None:
    """prior_coef=0 is the one switch: no prior critic is built or trained, and the numbers are PEARL's."""
    kwargs = {k: v for k, v in tiny_kwargs.items() if k != "prior_critic_arch"}
    plus = PEARLPlus("MlpPolicy", "PointGoalMeta-v0", seed=0, prior_coef=0.0, **kwargs)
    assert isinstance(plus, PEARL) and not plus.uses_prior_term
    assert plus.prior_critic is None and plus.policy.prior_critic_mode == "none"
    plus.learn(300)  # each model is built and trained in turn: construction reseeds the global RNGs
    pearl = PEARL("MlpPolicy", "PointGoalMeta-v0", seed=0, **kwargs)
    pearl.learn(300)
    plus_state, pearl_state = plus.policy.state_dict(), pearl.policy.state_dict()
    assert plus_state.keys() == pearl_state.keys()
    assert all(th.equal(plus_state[k], pearl_state[k]) for k in plus_state)


def test_train_honours_batch_size(tiny_kwargs: dict[str, Any]) -> None:
    model = PEARLPlus("MlpPolicy", "PointGoalMeta-v0", seed=0, **tiny_kwargs)
    model.learn(4 * tiny_kwargs["num_initial_steps"])
    replay, _, _ = model._sample_meta_batch(3)
    assert replay.rewards.shape == (model.meta_batch, 3, 1)
    model.train(gradient_steps=2, batch_size=3)  # runs with 3 rows per task
    assert model._n_updates > 0


class _RecordRates(BaseCallback):
    """The env steps done and the optimizers' learning rates at each iteration's start (after the previous train())."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: list[tuple[int, set[float]]] = []

    def _on_rollout_start(self) -> None:
        rates = {group["lr"] for optimizer in self.model.policy.optimizers() for group in optimizer.param_groups}
        self.seen.append((self.model.num_timesteps, rates))

    def _on_step(self) -> bool:
        return True


def test_learning_rate_schedule_follows_training_progress(tiny_kwargs: dict[str, Any]) -> None:
    """A schedule (rl-zoo's ``lin_3e-4``) decays with the env steps done, as in SB3's SAC, in every optimizer."""
    model = tiny_pearl(tiny_kwargs, seed=0, learning_rate=lambda progress_remaining: 1e-3 * progress_remaining)
    record = _RecordRates()
    total = 480
    model.learn(total, callback=record)
    # each train() sets every optimizer to lr_schedule(1 - env steps so far / total): by hand, at the env steps the
    # next iteration starts from (the first iteration's start has trained on nothing yet)
    trained = [(steps, rates) for steps, rates in record.seen if steps > 0]
    assert len(trained) >= 2
    for steps, rates in trained:
        assert sorted(rates) == [pytest.approx(1e-3 * (1.0 - steps / total))]
    final = {group["lr"] for optimizer in model.policy.optimizers() for group in optimizer.param_groups}
    assert sorted(final) == [pytest.approx(0.0)]  # the last gradient steps ran at the end of training
