"""Tests for MAML-TRPO (sb3_pearl.maml)."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

import sb3_pearl  # noqa: F401  (registers the task families)
from sb3_pearl.envs.task_protocol import MetaTaskEnv, Task
from sb3_pearl.maml import MAML
from sb3_pearl.maml.maml import EpisodeBatch, TaskSamples

th.set_num_threads(1)


class LineGoalEnv(MetaTaskEnv, gym.Env):
    """A 1-D walk to an unobserved goal cell: a tiny task family with Discrete (or other) actions."""

    def __init__(self, action_space: spaces.Space | None = None) -> None:
        self.observation_space = spaces.Box(-5.0, 5.0, shape=(1,), dtype=np.float32)
        self.action_space = spaces.Discrete(3) if action_space is None else action_space
        self._pos = 0
        self._init_task()

    def _sample_task(self, rng: np.random.Generator) -> Task:
        return {"goal": int(rng.integers(-3, 4))}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self._apply_pending_task()
        self._pos = 0
        return np.array([self._pos], dtype=np.float32), {}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        self._pos = int(np.clip(self._pos + int(action) - 1, -5, 5))
        reward = -abs(self._pos - self._task["goal"])
        return np.array([self._pos], dtype=np.float32), float(reward), False, False, {"cost": 0.0}


def make_model(n_envs: int = 2, **kwargs: Any) -> MAML:
    env = make_vec_env("PointGoalMeta-v0", n_envs=n_envs, seed=0)
    params: dict[str, Any] = dict(meta_batch_size=4, episodes_per_task=4, n_train_tasks=8, n_test_tasks=4, seed=0)
    params.update(kwargs)
    return MAML("MlpPolicy", env, **params)


def collect(model: MAML) -> tuple[list[TaskSamples], list[TaskSamples]]:
    assert model.train_tasks is not None
    tasks = model.train_tasks[: model.meta_batch_size]
    pre_batch, _ = model._collect_episodes(tasks, None)
    pre = model._task_samples(pre_batch)
    post_batch, _ = model._collect_episodes(tasks, model._adapt_all(pre))
    return pre, model._task_samples(post_batch)


def test_inner_gradient_linear_gaussian_closed_form() -> None:
    model = make_model(n_envs=1, policy_kwargs=dict(net_arch=[]), inner_lr=0.3)
    policy = model.policy
    assert set(policy.meta_parameters()) == {"mlp.0.weight", "mlp.0.bias", "log_std"}
    gen = th.Generator().manual_seed(0)
    weight, bias, log_std = th.randn(2, 2, generator=gen), th.randn(2, generator=gen), th.tensor([-0.3, 0.2])
    params = {
        "mlp.0.weight": weight.clone().requires_grad_(True),
        "mlp.0.bias": bias.clone().requires_grad_(True),
        "log_std": log_std.clone().requires_grad_(True),
    }
    obs, actions, adv = th.randn(7, 2, generator=gen), th.randn(7, 2, generator=gen), th.randn(7, generator=gen)
    adapted = model.adapt_params(params, TaskSamples(obs, actions, adv), create_graph=False)

    # d/d theta of -mean_t A_t log N(a_t; W s_t + b, diag(sigma^2))
    var = th.exp(2 * log_std)
    score_mu = (actions - (obs @ weight.T + bias)) / var  # (N, 2)
    grad_w = -((adv[:, None, None] * score_mu[:, :, None] * obs[:, None, :]).mean(0))
    grad_b = -((adv[:, None] * score_mu).mean(0))
    grad_log_std = -((adv[:, None] * ((actions - (obs @ weight.T + bias)) ** 2 / var - 1)).mean(0))
    th.testing.assert_close(adapted["mlp.0.weight"], weight - 0.3 * grad_w)
    th.testing.assert_close(adapted["mlp.0.bias"], bias - 0.3 * grad_b)
    th.testing.assert_close(adapted["log_std"], log_std - 0.3 * grad_log_std)


def test_inner_gradient_linear_categorical_closed_form() -> None:
    env = DummyVecEnv([LineGoalEnv])
    model = MAML("MlpPolicy", env, policy_kwargs=dict(net_arch=[]), max_episode_steps=5, inner_lr=0.5, seed=0)
    gen = th.Generator().manual_seed(1)
    weight, bias = th.randn(3, 1, generator=gen), th.randn(3, generator=gen)
    params = {"mlp.0.weight": weight.clone().requires_grad_(True), "mlp.0.bias": bias.clone().requires_grad_(True)}
    obs, actions, adv = th.randn(6, 1, generator=gen), th.tensor([0, 1, 2, 2, 1, 0]), th.randn(6, generator=gen)
    adapted = model.adapt_params(params, TaskSamples(obs, actions, adv), create_graph=False)
    score_logits = th.nn.functional.one_hot(actions, 3).float() - th.softmax(obs @ weight.T + bias, dim=-1)  # (N, 3)
    grad_w = -((adv[:, None, None] * score_logits[:, :, None] * obs[:, None, :]).mean(0))
    grad_b = -((adv[:, None] * score_logits).mean(0))
    th.testing.assert_close(adapted["mlp.0.weight"], weight - 0.5 * grad_w)
    th.testing.assert_close(adapted["mlp.0.bias"], bias - 0.5 * grad_b)


def test_batched_distribution_matches_functional_call() -> None:
    policy = make_model(n_envs=1).policy
    gen = th.Generator().manual_seed(2)
    stacked = {name: p.detach() + 0.1 * th.randn((3, *p.shape), generator=gen) for name, p in policy.meta_parameters().items()}
    obs = th.randn(3, 5, 2, generator=gen)
    batched = policy.batched_distribution(obs, stacked)
    for k in range(3):
        single = policy.distribution(obs[k], {name: value[k] for name, value in stacked.items()})
        th.testing.assert_close(batched.mean[k], single.mean)
        th.testing.assert_close(batched.stddev[k], single.stddev)


def test_advantages_gae_and_linear_baseline() -> None:
    model = make_model(n_envs=1, normalize_advantage=False, gamma=0.9)
    rng = np.random.default_rng(0)
    horizon = model.max_episode_steps
    assert horizon == 20
    obs = rng.normal(size=(2, 3, horizon, 2)).astype(np.float32)
    rewards = rng.normal(size=(2, 3, horizon)).astype(np.float32)
    lengths = np.array([[20, 12, 5], [20, 20, 1]])
    for j in range(2):
        for e in range(3):
            rewards[j, e, lengths[j, e] :] = 0.0
    batch = EpisodeBatch(obs, np.zeros((2, 3, horizon, 2), np.float32), rewards, lengths)
    # A baseline regularised to zero: GAE(lambda=1) advantages are the discounted returns-to-go.
    model.baseline_reg = 1e12
    adv = model.compute_advantages(batch).numpy()
    for j in range(2):
        for e in range(3):
            n = lengths[j, e]
            returns = [sum(0.9**k * rewards[j, e, t + k] for k in range(n - t)) for t in range(n)]
            np.testing.assert_allclose(adv[j, e, :n], returns, rtol=1e-4, atol=1e-4)
            assert np.all(adv[j, e, n:] == 0)
    # Returns exactly linear in the time feature (gamma = 1, constant reward, full episodes): the fitted
    # baseline explains them and the advantages vanish.
    model.baseline_reg, model.gamma = 1e-8, 1.0
    full = EpisodeBatch(obs, batch.actions, np.ones_like(rewards), np.full((2, 3), horizon))
    np.testing.assert_allclose(model.compute_advantages(full).numpy(), 0.0, atol=1e-3)


def test_task_lists() -> None:
    model = make_model(n_envs=1)
    expected = gym.make("PointGoalMeta-v0").unwrapped.sample_tasks(8 + 4, seed=0)  # type: ignore[attr-defined]
    assert model.train_tasks == expected[:8] and model.test_tasks == expected[8:]
    explicit = make_model(n_envs=1, train_tasks=expected[:2], test_tasks=expected[2:3])
    assert explicit.train_tasks == expected[:2] and explicit.test_tasks == expected[2:3]


def test_sampler_assigns_tasks_and_counts_steps() -> None:
    # 3 envs for 4 tasks and episodes cut at 7 < the registered 20 steps
    model = make_model(n_envs=3, max_episode_steps=7, episodes_per_task=5)
    assert model.train_tasks is not None
    tasks = model.train_tasks[:4]
    batch, _ = model._collect_episodes(tasks, None)
    assert (batch.lengths == 7).all()
    assert model.num_timesteps == 4 * 5 * 7
    for j, task in enumerate(tasks):
        goal = np.asarray(task["goal"])
        # reward_t = -||s_{t+1} - g||: the stored trajectories belong to the task they are filed under
        np.testing.assert_allclose(
            batch.rewards[j, :, :-1], -np.linalg.norm(batch.observations[j, :, 1:] - goal, axis=-1), atol=1e-5
        )
        np.testing.assert_allclose(batch.observations[j, :, 0], 0.0)  # every episode starts from a reset


def test_trpo_step_respects_kl_bound_and_improves_surrogate() -> None:
    for max_kl in (1e-2, 1e-3):
        model = make_model(max_kl=max_kl)
        pre, post = collect(model)
        theta_old = th.nn.utils.parameters_to_vector(model.policy.parameters()).detach().clone()
        info = model.trpo_step(pre, post)
        assert info.accepted
        assert info.surrogate_after > info.surrogate_before
        assert 0 < info.kl <= max_kl
        # Independent re-evaluation at the new parameters (re-adapting from them).
        theta_new = th.nn.utils.parameters_to_vector(model.policy.parameters()).detach()
        assert not th.equal(theta_new, theta_old)
        th.nn.utils.vector_to_parameters(theta_old, model.policy.parameters())
        old = model._old_policies(pre, post)
        th.nn.utils.vector_to_parameters(theta_new, model.policy.parameters())
        surrogate, kl = model.meta_objective(model.policy.meta_parameters(), pre, post, old, create_graph=False)
        assert float(kl.detach()) <= max_kl
        assert float(surrogate.detach()) == pytest.approx(info.surrogate_after, rel=1e-5)


def test_second_order_term_flows_through_inner_step() -> None:
    model = make_model()
    pre, post = collect(model)
    second = model.meta_gradient(pre, post)
    model.first_order = True
    first = model.meta_gradient(pre, post)
    model.first_order = False

    # Expected difference: -lr * mean_j H_j(theta) grad S_j(theta'_j), with H_j the Hessian of the inner loss.
    theta = model.policy.meta_parameters()
    old = model._old_policies(pre, post)
    expected = th.zeros_like(second)
    for pre_j, post_j, old_j in zip(pre, post, old, strict=True):
        adapted = {k: v.detach().requires_grad_(True) for k, v in model.adapt_params(theta, pre_j, False).items()}
        log_prob = model.policy.log_prob(post_j.observations, post_j.actions, adapted)
        surrogate = (th.exp(log_prob - old_j.log_prob) * post_j.advantages).mean()
        outer_grad = th.autograd.grad(surrogate, list(adapted.values()))
        inner_grad = th.autograd.grad(model.inner_loss(theta, pre_j), list(theta.values()), create_graph=True)
        hvp = th.autograd.grad(inner_grad, list(theta.values()), grad_outputs=outer_grad)
        expected -= model.inner_lr * th.nn.utils.parameters_to_vector(hvp) / len(pre)
    assert (second - first).norm() > 1e-4 * second.norm()
    th.testing.assert_close(second - first, expected, rtol=1e-3, atol=1e-6)


def test_subproc_vec_env_and_discrete_actions() -> None:
    env = make_vec_env(LineGoalEnv, n_envs=2, vec_env_cls=SubprocVecEnv)
    try:
        model = MAML("MlpPolicy", env, meta_batch_size=3, episodes_per_task=2, max_episode_steps=6, n_train_tasks=5, seed=0)
        model.learn(1)
        assert model.num_timesteps == 2 * 3 * 2 * 6
    finally:
        env.close()


def test_unsupported_spaces_and_envs() -> None:
    with pytest.raises(ValueError, match="action spaces"):
        MAML("MlpPolicy", DummyVecEnv([lambda: LineGoalEnv(spaces.MultiDiscrete([3, 3]))]), max_episode_steps=5)
    with pytest.raises(ValueError, match="action spaces"):
        MAML("MlpPolicy", DummyVecEnv([lambda: LineGoalEnv(spaces.MultiBinary(2))]), max_episode_steps=5)
    with pytest.raises(ValueError, match="task-family"):
        MAML("MlpPolicy", "Pendulum-v1")
    with pytest.raises(ValueError, match="time limit"):
        MAML("MlpPolicy", DummyVecEnv([LineGoalEnv]))


def rollout(model: MAML, env: gym.Env, n_episodes: int, seed: int) -> None:
    for k in range(n_episodes):
        obs, _ = env.reset(seed=seed + k)
        done = False
        while not done:
            action, _ = model.predict(obs)
            next_obs, reward, terminated, truncated, _ = env.step(action)
            done = terminated or truncated
            model.observe(obs, action, reward, next_obs, done)
            obs = next_obs


def test_adaptation_api() -> None:
    model = make_model(n_envs=1)
    assert model.test_tasks is not None
    env = gym.make("PointGoalMeta-v0")
    env.unwrapped.set_task(model.test_tasks[0])  # type: ignore[attr-defined]
    obs = np.random.default_rng(0).uniform(-1, 1, size=(8, 2)).astype(np.float32)
    theta = th.nn.utils.parameters_to_vector(model.policy.parameters()).detach().clone()
    prior_actions = model.predict(obs, deterministic=True)[0]

    model.reset_adaptation()
    model.adapt()  # nothing observed: still the meta-learned policy (k = 0)
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], prior_actions)
    rollout(model, env, 3, seed=0)
    assert len(model._adapt_episodes) == 3
    model.adapt()
    assert model.policy.adapted_params is not None
    adapted_actions = model.predict(obs, deterministic=True)[0]
    assert not np.allclose(adapted_actions, prior_actions)
    # adapt() never touches the meta-parameters, and the adapted parameters equal one inner step on the data
    th.testing.assert_close(th.nn.utils.parameters_to_vector(model.policy.parameters()), theta)
    model.reset_adaptation()
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], prior_actions)


def evaluate_adaptation(model: MAML, tasks: list[Task], n_adapt: int, n_eval: int) -> tuple[float, float]:
    """Mean return of the adaptation trajectories (meta-learned policy) and of trajectories after adapt()."""
    env = gym.make("PointGoalMeta-v0")
    pre, post = [], []
    for i, task in enumerate(tasks):
        env.unwrapped.set_task(task)  # type: ignore[attr-defined]
        model.reset_adaptation()
        for phase, n_episodes in (("pre", n_adapt), ("post", n_eval)):
            if phase == "post":
                model.adapt()
            for k in range(n_episodes):
                obs, _ = env.reset(seed=10_000 * i + 100 * k + (phase == "post"))
                done, episode_return = False, 0.0
                while not done:
                    action, _ = model.predict(obs)
                    next_obs, reward, terminated, truncated, _ = env.step(action)
                    done = terminated or truncated
                    if phase == "pre":
                        model.observe(obs, action, reward, next_obs, done)
                    obs, episode_return = next_obs, episode_return + float(reward)
                (pre if phase == "pre" else post).append(episode_return)
    return float(np.mean(pre)), float(np.mean(post))


@pytest.mark.slow
def test_learning_post_adaptation_beats_pre_adaptation() -> None:
    env = make_vec_env("PointGoalMeta-v0", n_envs=4, seed=0)
    model = MAML("MlpPolicy", env, meta_batch_size=20, episodes_per_task=20, n_test_tasks=20, seed=0)
    assert model.test_tasks is not None
    before = evaluate_adaptation(model, model.test_tasks, n_adapt=20, n_eval=5)
    model.learn(15 * 2 * 20 * 20 * 20)  # 15 meta-iterations
    pre, post = evaluate_adaptation(model, model.test_tasks, n_adapt=20, n_eval=5)
    print(f"held-out tasks: before training pre {before[0]:.2f} post {before[1]:.2f}; after pre {pre:.2f} post {post:.2f}")
    assert post > pre + 3.0
    assert post - pre > before[1] - before[0]
