"""Prior-safety diagnostics on models with known answers, the training-time gradient-conflict logs,
the ``diagnose`` command line and common random numbers in the meta-test."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import yaml
from stable_baselines3.common.logger import configure

from sb3_pearl import PEARL, PEARLPlus
from sb3_pearl.common.buffers import MetaReplayBuffer
from sb3_pearl.diagnose import find_run
from sb3_pearl.diagnose import main as diagnose_main
from sb3_pearl.evaluation.meta_test import meta_test
from sb3_pearl.pearl.diagnostics import (
    actor_gradient_conflict,
    compute_diagnostics,
    compute_gradient_conflict,
    gaussian_classifier_auc,
    knn_classifier_auc,
    roc_auc,
    rollout_with_z,
)
from tests.conftest import TINY, make_discrete_env

ENV_ID = "SafePointGoalMeta-v0"
FAST = dict(n_tasks=4, n_z0=3, n_grad_batches=2)


def _kwargs(**overrides: Any) -> dict[str, Any]:
    kwargs = {key: (dict(value) if isinstance(value, dict) else value) for key, value in TINY.items()}
    kwargs.update(overrides)
    return kwargs


@pytest.fixture(scope="module")
def trained() -> PEARLPlus:
    """A tiny PEARL+ trained for a few hundred steps on the safe point family."""
    model = PEARLPlus("MlpPolicy", ENV_ID, seed=0, **_kwargs())
    model.learn(300)
    return model


def _fill(model: PEARLPlus, n_rows: int = 40, seed: int = 0) -> MetaReplayBuffer:
    """A replay / context buffer of random transitions for every training task of ``model``."""
    rng = np.random.default_rng(seed)
    buffer = MetaReplayBuffer(len(model.train_tasks), n_rows, n_rows, model.observation_space, model.action_space)
    for task in range(len(model.train_tasks)):
        for _ in range(n_rows):
            obs, next_obs = rng.uniform(-1, 1, (2, model.policy.obs_dim)).astype(np.float32)
            if model.policy.discrete:
                action = np.array([rng.integers(model.policy.action_dim)], dtype=np.float32)
            else:
                action = rng.uniform(-1, 1, model.policy.action_dim).astype(np.float32)
            row = (obs, action, float(rng.normal()), next_obs, False)
            buffer.rl.add(task, *row)
            buffer.context.add(task, *row)
    return buffer


# ----------------------------------------------------------------------------------------------
# Classifier AUC
# ----------------------------------------------------------------------------------------------
def test_roc_auc_known_values() -> None:
    labels = np.array([1, 1, 0, 0])
    assert roc_auc(np.array([3.0, 2.0, 1.0, 0.0]), labels) == 1.0
    assert roc_auc(np.array([0.0, 1.0, 2.0, 3.0]), labels) == 0.0
    assert roc_auc(np.ones(4), labels) == 0.5  # ties count half
    assert roc_auc(np.array([2.0, 0.0, 1.0, 0.0]), labels) == 0.625  # pairs: win, win, loss, tie
    assert math.isnan(roc_auc(np.ones(2), np.ones(2)))


def test_classifiers_see_scale_and_clusters() -> None:
    rng = np.random.default_rng(0)
    z0 = rng.standard_normal((300, 3))
    # Same mean, smaller spread: separable by the per-class covariances.
    assert gaussian_classifier_auc(0.1 * rng.standard_normal((300, 3)), z0) > 0.95
    # Tight clusters on +-1: mean 0 and a covariance close to the prior's along dimension 0; the kNN sees them.
    centres = np.array([[1.0, 0, 0], [-1.0, 0, 0]])[rng.integers(2, size=300)]
    assert knn_classifier_auc(centres + 0.05 * rng.standard_normal((300, 3)), z0) > 0.95


# ----------------------------------------------------------------------------------------------
# compute_diagnostics: overlap with a forced posterior
# ----------------------------------------------------------------------------------------------
def _force_posterior(monkeypatch: pytest.MonkeyPatch, model: PEARLPlus, mean: float, var: float) -> None:
    def posterior(context: th.Tensor, mask: th.Tensor | None = None) -> tuple[th.Tensor, th.Tensor]:
        shape = (context.shape[0], model.latent_dim)
        return th.full(shape, mean), th.full(shape, var)

    monkeypatch.setattr(model.encoder, "posterior", posterior)


def test_overlap_far_posterior_is_separable(monkeypatch: pytest.MonkeyPatch) -> None:
    model = PEARLPlus("MlpPolicy", ENV_ID, seed=1, **_kwargs())  # untrained, empty buffers: fresh rollouts
    _force_posterior(monkeypatch, model, mean=5.0, var=0.01)
    result = compute_diagnostics(model, gym.make(ENV_ID), seed=0, n_posterior_samples=64, **FAST)
    overlap = result["overlap"]
    assert overlap["auc_gaussian"] > 0.99 and overlap["auc_knn"] > 0.99
    assert overlap["posterior_mean_spread_avg"] == pytest.approx(0.0, abs=1e-6)
    assert overlap["posterior_var_avg"] == pytest.approx(0.01, rel=1e-4)
    assert result["data"]["posterior_from_fresh_rollouts"] == 4
    # Every z0 is about 5 * sqrt(3) from the single posterior mean.
    assert result["violations"]["distance_mean"] > 5.0
    json.dumps(result)  # JSON-serialisable as it is


def test_overlap_prior_posterior_is_not_separable(monkeypatch: pytest.MonkeyPatch) -> None:
    model = PEARLPlus("MlpPolicy", ENV_ID, seed=1, **_kwargs())
    _force_posterior(monkeypatch, model, mean=0.0, var=1.0)
    overlap = compute_diagnostics(model, gym.make(ENV_ID), seed=0, n_posterior_samples=64, **FAST)["overlap"]
    assert overlap["n_per_class"] == 256
    assert abs(overlap["auc_gaussian"] - 0.5) < 0.1
    assert abs(overlap["auc_knn"] - 0.5) < 0.1


# ----------------------------------------------------------------------------------------------
# Gradient conflict
# ----------------------------------------------------------------------------------------------
def test_gradient_conflict_pearl_has_no_prior_term() -> None:
    model = PEARL("MlpPolicy", ENV_ID, seed=0, **{k: v for k, v in _kwargs().items() if k != "prior_critic_arch"})
    conflict = compute_gradient_conflict(model, _fill(model), n_batches=2)
    assert conflict["ratio"] == 0.0
    assert math.isnan(conflict["cos"])
    assert conflict["post_norm"] > 0


def test_gradient_conflict_equal_prior_and_posterior_inputs(monkeypatch: pytest.MonkeyPatch) -> None:
    """z0 = z and one critic for both terms (shared, Discrete: no action sampling): the two terms are the same loss."""
    model = PEARLPlus("MlpPolicy", make_discrete_env(), seed=0, prior_critic="shared", prior_coef=0.3, **_kwargs())
    buffer = _fill(model)
    z_fixed = th.tensor([0.5, -1.0, 2.0])

    def posterior(context: th.Tensor, mask: th.Tensor | None = None) -> tuple[th.Tensor, th.Tensor]:
        return z_fixed.expand(context.shape[0], -1), th.zeros(context.shape[0], 3)  # variance 0: z = mean exactly

    monkeypatch.setattr(model.encoder, "posterior", posterior)
    tasks = np.arange(3)
    replay = buffer.rl.sample(tasks, model.batch_size)
    ctx = buffer.context.sample(tasks, model.embedding_batch_size)
    context = model.policy.make_context(ctx.observations, ctx.actions, ctx.rewards, ctx.next_observations)
    losses = model._compute_losses(replay, context, z_fixed.expand(3, -1))
    conflict = actor_gradient_conflict(model, losses)
    assert conflict["cos"] == pytest.approx(1.0, abs=1e-5)
    assert conflict["ratio"] == pytest.approx(0.3, rel=1e-5)


def test_training_logs_gradient_conflict_without_changing_training(tmp_path: Path) -> None:
    plain = PEARLPlus("MlpPolicy", ENV_ID, seed=3, **_kwargs())
    plain.learn(250)
    logged = PEARLPlus("MlpPolicy", ENV_ID, seed=3, grad_conflict_log_freq=2, **_kwargs())
    logged.set_logger(configure(str(tmp_path), ["csv"]))
    logged.learn(250)
    for a, b in zip(plain.policy.state_dict().values(), logged.policy.state_dict().values()):
        assert th.equal(a, b)  # the extra backward passes leave the parameters and the RNG streams alone
    with open(tmp_path / "progress.csv") as file:
        header, *rows = [line.rstrip("\n").split(",") for line in file]
    ratios = [
        float(row[header.index("train/grad_conflict_ratio")]) for row in rows if row[header.index("train/grad_conflict_ratio")]
    ]
    cosines = [
        float(row[header.index("train/grad_conflict_cos")]) for row in rows if row[header.index("train/grad_conflict_cos")]
    ]
    assert ratios and all(r > 0 for r in ratios)
    assert cosines and all(-1.0 <= c <= 1.0 for c in cosines)
    with pytest.raises(ValueError, match="grad_conflict_log_freq"):
        PEARLPlus("MlpPolicy", ENV_ID, grad_conflict_log_freq=-1, **_kwargs())


# ----------------------------------------------------------------------------------------------
# Rollouts, calibration and the full result on a trained model
# ----------------------------------------------------------------------------------------------
def test_rollout_with_z_leaves_the_adaptation_state(trained: PEARLPlus) -> None:
    env = gym.make(ENV_ID)
    trained.reset_adaptation()
    z_before = trained.policy.current_z.clone()
    traj = rollout_with_z(trained, env, trained.test_tasks[0], np.zeros(trained.latent_dim), deterministic=False, seed=0)
    assert traj.observations.shape == (traj.length + 1, 2) and traj.actions.shape == (traj.length, 2)
    assert np.all(np.isfinite(traj.log_probs)) and np.all(np.abs(traj.actions) <= 1)
    assert traj.length == 30 or traj.terminated
    assert th.equal(trained.policy.current_z, z_before) and trained._adapt_context == []
    again = rollout_with_z(trained, env, trained.test_tasks[0], np.zeros(trained.latent_dim), deterministic=True, seed=0)
    assert np.all(np.isnan(again.log_probs))


def test_calibration_and_all_keys_on_a_trained_model(trained: PEARLPlus) -> None:
    state = np.random.get_state()[1].copy(), th.get_rng_state().clone()
    result = compute_diagnostics(trained, gym.make(ENV_ID), seed=0, **FAST)
    assert np.array_equal(np.random.get_state()[1], state[0]) and th.equal(th.get_rng_state(), state[1])  # restored
    calibration = result["calibration"]
    assert calibration["critic"].startswith("prior critic")
    for key in ("q_mean", "mc_return_mean", "mc_return_bootstrapped_mean", "bias", "abs_error_mean", "env_return_mean"):
        assert math.isfinite(calibration[key]), key
    assert calibration["reward_scale"] == trained.reward_scale
    assert result["data"]["posterior_from_context_buffer"] == 4  # the trained model's context buffers hold data
    assert result["data"]["gradient_batches_from"] == "replay buffer"
    violations = result["violations"]
    assert [b["bin"] for b in violations["terciles"]] == ["near", "middle", "far"]
    assert sum(b["n_z0"] for b in violations["terciles"]) == 3
    assert 0.0 <= violations["violation_rate"] <= 1.0 and 0.0 <= violations["z_zero_violation_rate"] <= 1.0
    gradient = result["gradient_conflict"]
    assert gradient["ratio"] > 0 and -1.0 <= gradient["cos"] <= 1.0
    assert compute_diagnostics(trained, gym.make(ENV_ID), seed=0, **FAST) == result  # reproducible for a seed


def test_calibration_of_pearl_uses_the_critic() -> None:
    model = PEARL("MlpPolicy", ENV_ID, seed=0, **{k: v for k, v in _kwargs().items() if k != "prior_critic_arch"})
    result = compute_diagnostics(model, gym.make(ENV_ID), seed=0, n_tasks=2, n_z0=2, n_grad_batches=1)
    assert "PEARL has no prior critic" in result["calibration"]["critic"]
    assert math.isfinite(result["calibration"]["q_mean"])
    assert result["gradient_conflict"]["ratio"] == 0.0


# ----------------------------------------------------------------------------------------------
# The command line
# ----------------------------------------------------------------------------------------------
ARGS = ["--n-tasks", "2", "--n-z0", "2", "--n-grad-batches", "1"]


def test_cli_harness_and_zoo_layouts(trained: PEARLPlus, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = tmp_path / "results" / "exp" / "safe_point" / "pearlplus" / "seed0"
    run.mkdir(parents=True)
    trained.save(run / "model.zip")
    family = {"name": "safe-point", "env_id": ENV_ID, "env_kwargs": {"crash_penalty": 3.0}}
    spec = {"experiment": "fast", "family": family, "variant": {"name": "pearlplus", "algo": "pearlplus"}, "seed": 0}
    (run / "result.json").write_text(json.dumps({"spec": spec, "summary": []}))
    assert find_run(run) == (run / "model.zip", ENV_ID, {"crash_penalty": 3.0})
    diagnose_main([str(run), *ARGS])
    out = capsys.readouterr().out
    for heading in ("Posterior vs prior", "Violations at k = 0", "Calibration of the prior critic", "Gradient conflict"):
        assert heading in out

    zoo = tmp_path / "logs" / "pearlplus" / f"{ENV_ID}_1"
    (zoo / ENV_ID).mkdir(parents=True)
    trained.save(zoo / f"{ENV_ID}.zip")
    (zoo / ENV_ID / "config.yml").write_text("[]\n")
    (zoo / ENV_ID / "args.yml").write_text(yaml.dump({"env": ENV_ID, "env_kwargs": {"hazard_radius": 0.2}}))
    assert find_run(zoo) == (zoo / f"{ENV_ID}.zip", ENV_ID, {"hazard_radius": 0.2})
    result = diagnose_main([str(zoo / f"{ENV_ID}.zip"), "--json", *ARGS])
    printed = json.loads(capsys.readouterr().out)
    assert printed["run"]["env_id"] == ENV_ID and printed["algorithm"] == "PEARLPlus"
    assert printed["overlap"] == result["overlap"]


def test_cli_clear_errors(trained: PEARLPlus, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        diagnose_main([str(tmp_path)])
    assert "result.json and model.zip" in capsys.readouterr().err
    trained.save(tmp_path / "somewhere.zip")
    with pytest.raises(SystemExit):
        diagnose_main([str(tmp_path / "somewhere.zip")])
    assert "pass --env-id" in capsys.readouterr().err
    assert find_run(tmp_path / "somewhere.zip", ENV_ID)[1] == ENV_ID


# ----------------------------------------------------------------------------------------------
# Common random numbers in the meta-test
# ----------------------------------------------------------------------------------------------
class SeedRecorder(gym.Wrapper):
    """Records the seed of every reset."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.seeds: list[int | None] = []

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> Any:
        self.seeds.append(seed)
        return super().reset(seed=seed, options=options)


def _prior_draws(model: PEARLPlus, crn_seed: int | None) -> tuple[dict[tuple[int, int], th.Tensor], list[int | None]]:
    """z at k = 0 per (task, repeat) and the reset seeds of a short meta-test."""
    draws: dict[tuple[int, int], th.Tensor] = {}

    def record(task: int, repeat: int, k: int) -> None:
        if k == 0:
            draws[(task, repeat)] = model.policy.current_z.clone()

    env = SeedRecorder(gym.make(ENV_ID))
    tasks = env.unwrapped.sample_tasks(2, seed=5)  # type: ignore[attr-defined]
    result = meta_test(model, env, tasks, n_adapt=1, n_repeats=2, max_steps=3, on_trajectory_start=record, crn_seed=crn_seed)
    assert result.config["crn_seed"] == crn_seed
    return draws, env.seeds


def test_common_random_numbers() -> None:
    a = PEARLPlus("MlpPolicy", ENV_ID, seed=0, **_kwargs())
    b = PEARL("MlpPolicy", ENV_ID, seed=1, **{k: v for k, v in _kwargs().items() if k != "prior_critic_arch"})
    draws_a, seeds_a = _prior_draws(a, crn_seed=7)
    th.randn(100)  # move the global RNG state between the models
    np.random.random(100)
    draws_b, seeds_b = _prior_draws(b, crn_seed=7)
    assert draws_a.keys() == draws_b.keys() and len(draws_a) == 4
    for key in draws_a:
        assert th.equal(draws_a[key], draws_b[key])  # same z0 for the same (task, repeat)
    assert len({tuple(z.tolist()) for z in draws_a.values()}) == 4  # but a new one for every (task, repeat)
    assert seeds_a == seeds_b and len(set(seeds_a)) == len(seeds_a) == 8  # one seed per (task, repeat, k)
    again, _ = _prior_draws(a, crn_seed=7)
    assert all(th.equal(again[key], draws_a[key]) for key in draws_a)

    # The global RNG states are left as they were; without crn_seed nothing changes (z0 differ, no reset seeds).
    state = th.get_rng_state().clone()
    _prior_draws(a, crn_seed=7)
    assert th.equal(th.get_rng_state(), state)
    plain_a, plain_seeds = _prior_draws(a, crn_seed=None)
    assert plain_seeds == [None] * 8
    assert not all(th.equal(plain_a[key], draws_a[key]) for key in draws_a)


# ----------------------------------------------------------------------------------------------
# The prior policy's paths (point families)
# ----------------------------------------------------------------------------------------------
def test_prior_paths_are_the_rollouts_the_violations_count(trained: PEARLPlus, monkeypatch: pytest.MonkeyPatch) -> None:
    from sb3_pearl.pearl.diagnostics import paths as paths_module
    from sb3_pearl.pearl.diagnostics import violations as violations_module
    from sb3_pearl.pearl.diagnostics.paths import prior_paths
    from sb3_pearl.pearl.diagnostics.violations import compute_violations

    calls: dict[str, list[tuple[Any, ...]]] = {"paths": [], "violations": []}

    def recorder(name: str) -> Any:
        def record(model: Any, env: Any, task: Any, z: Any, deterministic: bool, seed: Any, max_steps: Any) -> Any:
            calls[name].append((json.dumps(task), np.asarray(z).tolist(), deterministic, seed))
            return rollout_with_z(model, env, task, z, deterministic, seed, max_steps)

        return record

    monkeypatch.setattr(paths_module, "rollout_with_z", recorder("paths"))
    monkeypatch.setattr(violations_module, "rollout_with_z", recorder("violations"))
    env = gym.make(ENV_ID)
    tasks = list(trained.test_tasks)[:2]
    z0 = np.random.default_rng(1).standard_normal((4, trained.latent_dim))
    paths = prior_paths(trained, env, tasks, z0, seed=5)
    assert [len(rollouts) for rollouts in paths] == [4, 4]
    for rollouts in paths:
        for rollout in rollouts:
            np.testing.assert_allclose(rollout.observations[0], [0.0, 0.0])  # every task starts at the origin
            assert rollout.violated == (rollout.cost > 0) and rollout.observations.shape == (rollout.length + 1, 2)
    counted = compute_violations(trained, env, tasks, z0, np.zeros((1, trained.latent_dim)), seed=5, max_steps=None)
    # the same (task, z0, deterministic, seed) for every rollout; compute_violations adds one z = 0 rollout per task
    assert sorted(calls["paths"]) == sorted(calls["violations"][: len(calls["paths"])])
    assert len(calls["paths"]) == 8 and len({c[3] for c in calls["paths"]}) == 8  # distinct seeds per (draw, task)
    for j, rollouts in enumerate(paths):  # paths[j][i] is task j, draw i
        for i, rollout in enumerate(rollouts):
            again = rollout_with_z(trained, env, tasks[j], z0[i], True, None)
            np.testing.assert_allclose(rollout.observations, again.observations)
    assert counted["violation_rate"] == pytest.approx(np.mean([r.violated for rollouts in paths for r in rollouts]))
    assert counted["return_mean"] == pytest.approx(np.mean([r.episode_return for rollouts in paths for r in rollouts]))
    with pytest.raises(ValueError, match=r"z0 must have shape \(n_z0, "):
        prior_paths(trained, env, tasks, z0[:, :2], seed=5)


def test_prior_paths_need_a_position_observation() -> None:
    from sb3_pearl.pearl.diagnostics.paths import check_position_observation

    model = PEARLPlus("MlpPolicy", "Walker2dVelMeta-v0", seed=0, **_kwargs())  # 17-D observation
    with pytest.raises(ValueError, match=r"2-D position observation .* got shape \(17,\)"):
        check_position_observation(model)
    check_position_observation(PEARLPlus("MlpPolicy", make_discrete_env(), seed=0, **_kwargs()))  # (2,): accepted


def test_spread_tasks_and_the_paths_figure(trained: PEARLPlus, tmp_path: Path) -> None:
    from sb3_pearl.diagnose import spread_tasks
    from sb3_pearl.evaluation.figures import plot_prior_paths
    from sb3_pearl.pearl.diagnostics.paths import prior_paths

    angles = [2.0, 0.5, 1.5, 1.0, 2.5]
    tasks = [{"goal": [float(np.cos(a)), float(np.sin(a))]} for a in angles]
    picked = spread_tasks(tasks, 3)
    assert [round(float(np.arctan2(t["goal"][1], t["goal"][0])), 6) for t in picked] == [0.5, 1.5, 2.5]
    assert spread_tasks([{"x": 1}, {"x": 2}, {"x": 3}], 2) == [{"x": 1}, {"x": 3}]  # no goals: given order
    assert len(spread_tasks(tasks, 10)) == 5

    env = gym.make(ENV_ID)
    chosen = list(trained.test_tasks)[:2]
    paths = prior_paths(trained, env, chosen, np.zeros((2, trained.latent_dim)), seed=0)
    plot_prior_paths(paths, chosen, tmp_path / "paths.png", hazard_radius=0.25, title="t")
    assert (tmp_path / "paths.png").stat().st_size > 1000
    with pytest.raises(ValueError, match="one list of rollouts per task"):
        plot_prior_paths(paths, chosen[:1], tmp_path / "bad.png")


def test_cli_draws_the_paths(trained: PEARLPlus, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    trained.save(tmp_path / "model.zip")
    out = tmp_path / "paths.png"
    diagnose_main(
        [str(tmp_path / "model.zip"), "--env-id", ENV_ID, *ARGS, "--paths", str(out), "--paths-tasks", "2", "--paths-z0", "3"]
    )
    assert out.stat().st_size > 1000 and "Violations at k = 0" in capsys.readouterr().out
    with pytest.raises(SystemExit):  # refused before the diagnostics run
        diagnose_main([str(tmp_path / "model.zip"), "--env-id", ENV_ID, "--paths", str(out), "--paths-z0", "0"])
    assert "argument --paths-z0: must be an integer >= 1, got 0" in capsys.readouterr().err
