"""Tests for the Fine-Tune baseline (sb3_pearl.finetune): meta-training on the task mixture and adaptation (save / load:
tests/test_save_load.py)."""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecNormalize
from stable_baselines3.sac.policies import SACPolicy

import sb3_pearl  # noqa: F401  (registers the task families)
from sb3_pearl.common.tasks import draw_train_test_tasks
from sb3_pearl.envs.task_protocol import Task
from sb3_pearl.finetune import DiscreteSAC, DiscreteSACPolicy, FineTune
from sb3_pearl.registry import constructor_kwargs
from tests.conftest import make_discrete_env, make_point_env

th.set_num_threads(1)

TINY_FT: dict[str, Any] = dict(
    n_train_tasks=4,
    n_test_tasks=2,
    learning_starts=50,
    batch_size=32,
    adapt_gradient_steps=20,
    policy_kwargs=dict(net_arch=[32, 32]),
    seed=0,
)


def tiny_model(env: Any = "PointGoalMeta-v0", learn: int = 200, **kwargs: Any) -> FineTune:
    params = {**TINY_FT, **kwargs}
    model = FineTune("MlpPolicy", env, **params)
    if learn:
        model.learn(learn)
    return model


def rollout(model: FineTune, task: Task, deterministic: bool, observe: bool = True, seed: int = 0) -> float:
    """One trajectory of ``task`` acting with ``model.predict``; every transition goes to ``observe``."""
    env = gym.make("PointGoalMeta-v0")
    env.unwrapped.set_task(task)  # type: ignore[attr-defined]
    obs, _ = env.reset(seed=seed)
    done, ret = False, 0.0
    while not done:
        action, _ = model.predict(obs, deterministic=deterministic)
        next_obs, reward, terminated, truncated, _ = env.step(action)
        done = terminated or truncated
        ret += float(reward)
        if observe:
            model.observe(obs, action, float(reward), next_obs, done)
        obs = next_obs
    return ret


def probe_actions(model: FineTune, n: int = 16) -> np.ndarray:
    observations = np.random.default_rng(123).uniform(-1.5, 1.5, size=(n, 2)).astype(np.float32)
    return model.predict(observations, deterministic=True)[0]


def state_copy(policy: th.nn.Module) -> dict[str, th.Tensor]:
    return {name: value.detach().clone() for name, value in policy.state_dict().items()}


def observed_critic_loss(policy: SACPolicy, log_ent_coef: th.Tensor, buffer: Any, gamma: float) -> float:
    """SAC's critic loss on every stored transition, the next-state soft value averaged over 64 sampled actions."""
    n, samples = buffer.size(), 64
    obs = th.as_tensor(buffer.observations[:n, 0])
    actions = th.as_tensor(buffer.actions[:n, 0])
    rewards = th.as_tensor(buffer.rewards[:n])  # (n, 1): one env
    next_obs = th.as_tensor(buffer.next_observations[:n, 0]).repeat(samples, 1)
    not_done = 1.0 - th.as_tensor(buffer.dones[:n] * (1 - buffer.timeouts[:n]))
    with th.no_grad():
        th.manual_seed(0)
        next_actions, next_log_prob = policy.actor.action_log_prob(next_obs)
        next_q = th.min(th.cat(policy.critic_target(next_obs, next_actions), dim=1), dim=1, keepdim=True).values
        next_v = (next_q - log_ent_coef.exp() * next_log_prob.reshape(-1, 1)).reshape(samples, n, 1).mean(dim=0)
        target = rewards + gamma * not_done * next_v
        return float(sum(0.5 * ((q - target) ** 2).mean() for q in policy.critic(obs, actions)))


# ----------------------------------------------------------------------------------------------
# Meta-training
# ----------------------------------------------------------------------------------------------
class TaskLog(gym.Wrapper):
    """Records the task in force at every reset and step (the env's current task, not the pending one)."""

    def __init__(self, env: gym.Env, log: list[tuple[str, Task]]) -> None:
        super().__init__(env)
        self.log = log

    def reset(self, **kwargs: Any) -> Any:
        out = self.env.reset(**kwargs)
        self.log.append(("reset", dict(self.env.unwrapped._task)))  # type: ignore[attr-defined]
        return out

    def step(self, action: Any) -> Any:
        out = self.env.step(action)
        self.log.append(("step", dict(self.env.unwrapped._task)))  # type: ignore[attr-defined]
        return out


def test_meta_training_runs_one_training_task_per_episode() -> None:
    logs: list[list[tuple[str, Task]]] = [[], []]
    env = DummyVecEnv([lambda i=i: TaskLog(gym.make("PointGoalMeta-v0"), logs[i]) for i in range(2)])  # type: ignore[misc]
    model = tiny_model(env, learn=0, n_train_tasks=6)
    model.learn(400)
    seen = []
    for log in logs:
        episodes = []
        for kind, task in log:
            if kind == "reset":
                episodes.append([task])
            else:
                episodes[-1].append(task)
        for episode in episodes:
            assert all(task == episode[0] for task in episode), "the task changed inside an episode"
            assert episode[0] in model.train_tasks
            seen.append(episode[0]["goal"])
    assert len(seen) >= 20  # 2 envs x 200 steps / 20-step episodes
    assert len({tuple(goal) for goal in seen}) >= 4, "episodes do not mix the training tasks"


def test_learn_with_subproc_vec_env() -> None:
    env = SubprocVecEnv([make_point_env, make_point_env])
    try:
        model = tiny_model(env, learn=100)
        assert model.num_timesteps >= 100
        pending = env.env_method("get_task")  # every env holds a pending training task for its next episode
        assert all(task in model.train_tasks for task in pending)
    finally:
        env.close()


def test_tasks_are_drawn_with_the_seed_like_every_algorithm() -> None:
    model = tiny_model(learn=0, n_train_tasks=5, n_test_tasks=3, seed=7)
    again = tiny_model(learn=0, n_train_tasks=5, n_test_tasks=3, seed=7)
    expected = draw_train_test_tasks(make_vec_env("PointGoalMeta-v0"), 5, 3, 7)
    assert (model.train_tasks, model.test_tasks) == (again.train_tasks, again.test_tasks) == expected
    assert model.max_episode_steps == 20  # the registered time limit
    explicit = tiny_model(learn=0, train_tasks=[{"goal": [0.5, 0.5]}], test_tasks=[{"goal": [-0.5, 0.5]}])
    assert explicit.train_tasks == [{"goal": [0.5, 0.5]}] and explicit.test_tasks == [{"goal": [-0.5, 0.5]}]


def test_box_uses_sb3_sac_and_logs_train_keys() -> None:
    model = tiny_model(learn=200)
    assert isinstance(model.policy, SACPolicy)
    assert model._n_updates > 0
    for key in ("train/critic_loss", "train/actor_loss", "train/ent_coef"):
        assert key in model.logger.name_to_value


# ----------------------------------------------------------------------------------------------
# Adaptation API
# ----------------------------------------------------------------------------------------------
def test_adapt_fine_tunes_a_copy_toward_lower_critic_loss_on_the_observed_data() -> None:
    model = tiny_model(learn=300, adapt_gradient_steps=100)
    pretrained = state_copy(model.policy)
    before = probe_actions(model)
    model.reset_adaptation()
    model.adapt()  # nothing observed: no change
    assert model.adapted_policy is model.policy
    rollout(model, model.test_tasks[0], deterministic=False)
    assert model.n_observed == 20
    buffer = model._adapt_buffer
    assert buffer is not None and buffer.timeouts[19, 0] == 1.0  # the time-limit end keeps its bootstrap
    assert model.log_ent_coef is not None
    loss_before = observed_critic_loss(model.policy, model.log_ent_coef, buffer, model.gamma)
    model.adapt()
    adapted = model.adapted_policy
    assert adapted is not model.policy
    assert isinstance(adapted, SACPolicy)
    assert model._adapted is not None
    loss_after = observed_critic_loss(adapted, model._adapted["log_ent_coef"], buffer, model.gamma)
    assert loss_after < 0.5 * loss_before, (loss_before, loss_after)
    assert set(model.adapt_stats) >= {"critic_loss", "actor_loss", "ent_coef"}
    # The pretrained networks are untouched; predict acts with the fine-tuned copy.
    assert all(th.equal(value, model.policy.state_dict()[name]) for name, value in pretrained.items())
    assert not np.allclose(probe_actions(model), before)
    assert model._n_updates == 300 - TINY_FT["learning_starts"]  # adaptation steps do not count as training


class _TerminalAtTheTimeLimit(gym.Wrapper):
    """Ends every episode in a terminal state at the time limit's step (as Highway-Merge's failure to merge does)."""

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        return obs, float(reward), terminated or truncated, False, info


def test_the_meta_test_tells_a_terminal_state_at_the_time_limit_from_a_cut() -> None:
    """Through the meta-test's rollout, the last transition is terminal when the env terminated at the time limit's
    step, and bootstrapped when a step cap or the time limit cut the episode; without the keyword (the adaptation
    API's five arguments), the step count decides."""
    from sb3_pearl.evaluation.meta_test import SingleEnvRunner, observes_truncation
    from sb3_pearl.evaluation.meta_test import rollout as meta_rollout

    model = tiny_model(learn=0)
    assert observes_truncation(model) and model.max_episode_steps == 20

    def last_stored(env: gym.Env, max_steps: int | None = None) -> tuple[float, float]:
        runner = SingleEnvRunner(env)
        runner.set_task(model.test_tasks[0])
        runner.seed(0)
        model.reset_adaptation()
        values, _ = meta_rollout(model, runner, max_steps=max_steps)
        buffer = model._adapt_buffer
        assert buffer is not None and buffer.pos == values["length"]
        return float(buffer.dones[buffer.pos - 1, 0]), float(buffer.timeouts[buffer.pos - 1, 0])

    assert last_stored(_TerminalAtTheTimeLimit(gym.make("PointGoalMeta-v0"))) == (1.0, 0.0)  # terminal, at step 20
    assert last_stored(gym.make("PointGoalMeta-v0")) == (1.0, 1.0)  # the time limit: a cut
    assert last_stored(gym.make("PointGoalMeta-v0"), max_steps=5) == (1.0, 1.0)  # a step cap: a cut
    model.reset_adaptation()
    rollout(model, model.test_tasks[0], deterministic=True)  # observe() with five arguments: the step count decides
    assert model._adapt_buffer is not None and model._adapt_buffer.timeouts[19, 0] == 1.0


def test_reset_adaptation_restores_the_pretrained_weights_and_optimizers() -> None:
    model = tiny_model(learn=300)
    pretrained_actions = probe_actions(model)

    def adapt_twice() -> np.ndarray:
        model.set_random_seed(5)
        for k in range(2):
            rollout(model, model.test_tasks[1], deterministic=False, seed=k)
            model.adapt()
        return probe_actions(model)

    model.reset_adaptation()
    first = adapt_twice()
    assert not np.allclose(first, pretrained_actions)
    model.reset_adaptation()
    assert model.n_observed == 0
    np.testing.assert_array_equal(probe_actions(model), pretrained_actions)
    # Same seed, same data: identical fine-tuned policy, so the weights, the Adam moments and the
    # entropy coefficient all started from the pretrained ones again.
    np.testing.assert_allclose(adapt_twice(), first, atol=1e-6)


def test_discrete_learn_and_adapt() -> None:
    model = tiny_model(make_discrete_env(), learn=300)
    assert isinstance(model, DiscreteSAC) and isinstance(model.policy, DiscreteSACPolicy)
    assert model.target_entropy == pytest.approx(0.6 * np.log(5))
    assert "train/critic_loss" in model.logger.name_to_value
    actions, _ = model.predict(np.zeros((3, 2), dtype=np.float32), deterministic=True)
    assert actions.shape == (3,) and actions.dtype.kind == "i"
    env = make_discrete_env()
    env.unwrapped.set_task(model.test_tasks[0])  # type: ignore[attr-defined]
    obs, _ = env.reset(seed=0)
    pretrained = state_copy(model.policy)
    done = False
    while not done:
        action, _ = model.predict(obs)
        next_obs, reward, terminated, truncated, _ = env.step(action)
        done = terminated or truncated
        model.observe(obs, action, float(reward), next_obs, done)
        obs = next_obs
    model.adapt()
    adapted = model.adapted_policy.state_dict()
    assert any(not th.equal(value, adapted[name]) for name, value in pretrained.items())
    assert all(th.equal(value, model.policy.state_dict()[name]) for name, value in pretrained.items())
    assert np.isfinite(model.adapt_stats["critic_loss"])


def test_discrete_sac_alone_learns_a_plain_discrete_env() -> None:
    model = DiscreteSAC(
        "MlpPolicy", "CartPole-v1", learning_starts=50, batch_size=32, policy_kwargs=dict(net_arch=[16]), seed=0
    )
    model.learn(150)
    assert isinstance(model.policy, DiscreteSACPolicy) and model._n_updates > 0


# ----------------------------------------------------------------------------------------------
# Clear errors
# ----------------------------------------------------------------------------------------------
class MultiDiscretePointEnv(gym.Env):
    observation_space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
    action_space = spaces.MultiDiscrete([3, 3])

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        return np.zeros(2, dtype=np.float32), {}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        return np.zeros(2, dtype=np.float32), 0.0, False, False, {}


def test_clear_errors() -> None:
    with pytest.raises(ValueError, match="Box .*Discrete.*MultiDiscrete"):
        FineTune("MlpPolicy", MultiDiscretePointEnv())
    with pytest.raises(ValueError, match="task"):
        FineTune("MlpPolicy", "Pendulum-v1")
    with pytest.raises(ValueError, match="VecNormalize"):
        FineTune("MlpPolicy", VecNormalize(make_vec_env("PointGoalMeta-v0")))
    with pytest.raises(ValueError, match="Discrete action spaces need"):
        FineTune("MultiInputPolicy", make_discrete_env())
    with pytest.raises(ValueError, match="DiscreteSACPolicy needs a Discrete"):
        FineTune(DiscreteSACPolicy, "PointGoalMeta-v0")
    bad_kwargs: list[dict[str, Any]] = [
        dict(adapt_gradient_steps=-1),
        dict(n_train_tasks=0),
        dict(adapt_buffer_size=0),
        dict(train_tasks=[]),
    ]
    for bad in bad_kwargs:
        with pytest.raises(ValueError):
            FineTune("MlpPolicy", "PointGoalMeta-v0", **bad)
    model = tiny_model(learn=0)
    with pytest.raises(ValueError, match="one transition"):
        model.observe(np.zeros((3, 2)), np.zeros(2), 0.0, np.zeros(2), False)


# ----------------------------------------------------------------------------------------------
# Learning check
# ----------------------------------------------------------------------------------------------
@pytest.mark.slow  # a learning check (5 min of one core under load): make test-slow
def test_fine_tuning_improves_the_return_on_held_out_point_goals() -> None:
    """
    Pretrain on the goal mixture (2,000 steps), then on 4 held-out goals: deterministic trajectories,
    300 adaptation steps after each. The mean return after 3 trajectories beats the pretrained policy's
    (measured, docs/finetune.md: seed 0: -11.0 -> -8.6, seed 1: -19.0 -> -10.5, seed 2: -21.6 -> -18.6).
    """
    model = FineTune(
        "MlpPolicy",
        "PointGoalMeta-v0",
        n_train_tasks=40,
        n_test_tasks=4,
        learning_starts=200,
        adapt_gradient_steps=300,
        adapt_learning_rate=1e-3,
        adapt_batch_size=64,
        policy_kwargs=dict(net_arch=[64, 64]),
        seed=0,
    )
    model.learn(2000)
    returns = np.zeros((len(model.test_tasks), 4))
    for i, task in enumerate(model.test_tasks):
        model.reset_adaptation()
        for k in range(4):
            returns[i, k] = rollout(model, task, deterministic=True, seed=1000 * i + k)
            model.adapt()
    mean = returns.mean(axis=0)
    assert mean[3] > mean[0] + 1.0, mean


def test_finetune_states_only_its_own_arguments() -> None:
    """SAC's arguments are written once (DiscreteSAC); FineTune forwards them and the registry still lists them."""
    own = set(inspect.signature(FineTune.__init__).parameters) - {"self", "policy", "env", "kwargs", "_init_setup_model"}
    sac = set(inspect.signature(DiscreteSAC.__init__).parameters) - {"self", "policy", "env"}
    assert not own & sac
    shown = inspect.signature(FineTune).parameters  # inspect.signature shows both, each with its default
    assert set(shown) == own | sac | {"policy", "env", "_init_setup_model"}
    assert all(shown[name].default == inspect.signature(DiscreteSAC).parameters[name].default for name in sac)
    assert sac - {"tensorboard_log", "seed", "verbose", "device", "_init_setup_model"} <= constructor_kwargs(FineTune)
    assert {"adapt_gradient_steps", "n_train_tasks"} <= constructor_kwargs(FineTune)
    with pytest.raises(ValueError, match="batch_size must be an integer >= 1"):
        FineTune("MlpPolicy", "NoSuchEnv-v0", batch_size=0)  # SAC's checks still come before the env is made


@pytest.mark.parametrize("discrete", [False, True])
def test_adam_is_fused_by_default_and_the_same_update(discrete: bool, tmp_path: Path) -> None:
    """Fine-Tune's (and DiscreteSAC's) actor and critic step Adam in torch's fused form unless the user chose, as PEARL
    does: the same training as the single-tensor loop to float rounding; the caller's policy_kwargs are not changed;
    a saved model loads fused."""
    env = make_discrete_env() if discrete else "PointGoalMeta-v0"
    policy_kwargs: dict[str, Any] = dict(net_arch=[32, 32])
    fast = tiny_model(env, learn=300, policy_kwargs=policy_kwargs)
    assert "optimizer_kwargs" not in policy_kwargs  # the caller's dict (SB3's own use_sde entry aside) ...
    assert "optimizer_kwargs" not in fast.policy_kwargs  # ... and the saved ones: `load` compares them with the user's
    slow = tiny_model(env, learn=300, policy_kwargs=dict(net_arch=[32, 32], optimizer_kwargs=dict(foreach=False)))

    def optimizers(model: FineTune) -> list[th.optim.Optimizer]:
        return [model.actor.optimizer, model.critic.optimizer]

    assert all(group["fused"] for optimizer in optimizers(fast) for group in optimizer.param_groups)
    assert not any(group["fused"] for optimizer in optimizers(slow) for group in optimizer.param_groups)
    assert fast._n_updates == slow._n_updates > 200
    fast_state, slow_state = fast.policy.state_dict(), slow.policy.state_dict()
    for name in fast_state:  # fused and single-tensor Adam round differently: after 250 updates <= 2e-7 apart (measured)
        np.testing.assert_allclose(fast_state[name].numpy(), slow_state[name].numpy(), rtol=1e-5, atol=1e-6, err_msg=name)
    fast.save(tmp_path / "model.zip")
    loaded = FineTune.load(tmp_path / "model.zip")
    assert all(group["fused"] for optimizer in optimizers(loaded) for group in optimizer.param_groups)
