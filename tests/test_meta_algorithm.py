"""The shared frame of the meta-algorithms (sb3_pearl.common.meta_algorithm), PEARLPlus's SB3 set-up idiom and the
explicit inputs of PEARL's loss step."""

from __future__ import annotations

import inspect
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th

from sb3_pearl import PEARL, PEARLPlus
from sb3_pearl.common.meta_algorithm import MetaAlgorithm, check_observed_transition, check_task_arguments
from sb3_pearl.finetune import FineTune
from sb3_pearl.maml import MAML
from sb3_pearl.oracle import Oracle
from sb3_pearl.pearl.losses import LossSettings, compute_losses
from sb3_pearl.registry import ZOO_SET_KWARGS, constructor_kwargs, constructor_parameters

th.set_num_threads(1)

PRIOR_ARGUMENTS = {
    "prior_coef",
    "prior_critic",
    "prior_critic_arch",
    "prior_n_critics",
    "prior_data",
    "prior_critic_input",
    "prior_target",
    "prior_conservative_weight",
    "prior_return_steps",
}

TINY_BUILD: dict[str, dict[str, Any]] = {
    "pearl": dict(n_train_tasks=3, n_test_tasks=2, latent_dim=2, encoder_arch=[8], policy_kwargs=dict(net_arch=[8])),
    "finetune": dict(n_train_tasks=3, n_test_tasks=2, policy_kwargs=dict(net_arch=[8])),
    "maml": dict(n_train_tasks=3, n_test_tasks=2, meta_batch_size=2, episodes_per_task=1, policy_kwargs=dict(net_arch=[8])),
}
CLASSES: dict[str, type] = {"pearl": PEARL, "pearlplus": PEARLPlus, "finetune": FineTune, "maml": MAML}


def build(name: str, env: Any = "PointGoalMeta-v0", **kwargs: Any) -> Any:
    params = {**TINY_BUILD["pearl" if name == "pearlplus" else name], "seed": 3, **kwargs}
    return CLASSES[name]("MlpPolicy", env, **params)


# ----------------------------------------------------------------------------------------------
# The frame
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(CLASSES))
def test_every_algorithm_uses_the_frame(name: str) -> None:
    """One task draw for every algorithm: the same seed gives the same training and test tasks."""
    assert issubclass(CLASSES[name], MetaAlgorithm)
    model = build(name)
    reference = build("pearl")
    assert (model.n_train_tasks, model.n_test_tasks) == (3, 2)
    assert model.train_tasks == reference.train_tasks and len(model.train_tasks) == 3
    assert model.test_tasks == reference.test_tasks and len(model.test_tasks) == 2
    assert model.stochastic_adaptation is (name == "maml")


def test_each_algorithm_has_one_project_base() -> None:
    """Every algorithm is its own class on the one base class MetaAlgorithm, then SB3's: no mixins in between."""
    from sb3_pearl.finetune.discrete_sac import DiscreteSAC
    from sb3_pearl.oracle import Oracle

    def project_classes(cls: type) -> list[type]:
        return [c for c in cls.__mro__ if c.__module__.startswith("sb3_pearl")]

    assert project_classes(PEARL) == [PEARL, MetaAlgorithm]
    assert project_classes(PEARLPlus) == [PEARLPlus, PEARL, MetaAlgorithm]
    assert project_classes(FineTune) == [FineTune, MetaAlgorithm, DiscreteSAC]
    assert project_classes(Oracle) == [Oracle, FineTune, MetaAlgorithm, DiscreteSAC]
    assert project_classes(MAML) == [MAML, MetaAlgorithm]
    # One _setup_learn in the project: the base's (the algorithms hook into it).
    assert [
        k.__name__
        for c in (PEARLPlus, FineTune, Oracle, MAML)
        for k in c.__mro__
        if "_setup_learn" in vars(k) and k.__module__.startswith("sb3_pearl")
    ] == ["MetaAlgorithm"] * 4
    # MAML is on-policy: it keeps no replay buffer and offers no replay-buffer persistence.
    assert not hasattr(MAML, "save_replay_buffer") and not hasattr(MAML, "load_replay_buffer")


@pytest.mark.parametrize("name", sorted(CLASSES))
def test_task_arguments_and_env_are_checked_by_the_frame(name: str) -> None:
    with pytest.raises(ValueError, match="n_train_tasks must be an integer >= 1"):
        build(name, n_train_tasks=0)
    with pytest.raises(ValueError, match="n_test_tasks must be an integer >= 0"):
        build(name, n_test_tasks=-1)
    with pytest.raises(ValueError, match=r"train_tasks must hold at least one task \(or be None to draw them\)"):
        build(name, train_tasks=[])
    with pytest.raises(ValueError, match=f"{CLASSES[name].__name__} needs a task-family env"):
        build(name, env="Pendulum-v1")
    explicit = build(name, train_tasks=[{"goal": [0.5, 0.5]}], test_tasks=[{"goal": [-0.5, 0.5]}])
    assert explicit.train_tasks == [{"goal": [0.5, 0.5]}] and explicit.test_tasks == [{"goal": [-0.5, 0.5]}]


def test_only_pearl_requires_flat_observations() -> None:
    assert PEARL.requires_flat_observations and PEARLPlus.requires_flat_observations
    assert not FineTune.requires_flat_observations and not MAML.requires_flat_observations


@pytest.mark.parametrize("name", sorted(CLASSES))
def test_learning_without_training_tasks_is_a_clear_error(name: str) -> None:
    model = build(name)
    model.train_tasks = []
    with pytest.raises(ValueError, match=f"{CLASSES[name].__name__} has no training tasks: .*pass train_tasks"):
        model.learn(10)


@pytest.mark.parametrize("name", sorted(CLASSES))
def test_observe_checks_one_finite_transition(name: str) -> None:
    model = build(name)
    model.reset_adaptation()
    obs = np.zeros(2, dtype=np.float32)
    with pytest.raises(ValueError, match=r"observe\(\) takes one transition: obs and next_obs of shape \(2,\), got \(3, 2\)"):
        model.observe(np.zeros((3, 2)), np.zeros(2), 0.0, obs, False)
    with pytest.raises(ValueError, match=r"observe\(\) takes one transition: .*got \(2,\) and \(3,\)"):
        model.observe(obs, np.zeros(2), 0.0, np.zeros(3), False)
    with pytest.raises(ValueError, match=r"observe\(\): next_obs holds a non-finite value"):
        model.observe(obs, np.zeros(2), 0.0, np.array([np.nan, 0.0]), False)
    model.observe(obs[None], np.zeros(2), 0.0, obs, True)  # (1, obs_dim) is one observation


def test_check_observed_transition_returns_arrays_of_the_space_shape() -> None:
    space = gym.spaces.Box(-1.0, 1.0, shape=(2, 3))
    obs, next_obs = check_observed_transition(space, np.arange(6), 1.0, np.ones((1, 6)))
    assert obs.shape == next_obs.shape == (2, 3) and obs.dtype == next_obs.dtype == np.float32
    check_task_arguments(1, 0, None, None)
    with pytest.raises(ValueError, match="train_tasks must hold at least one task"):
        check_task_arguments(1, 0, [], None)


def test_training_plans() -> None:
    """PEARL and Fine-Tune plan their schedules; MAML (iterations end with their episodes) has none."""
    pearl = build("pearl", num_initial_steps=10, num_tasks_sample=1, num_steps_prior=5, num_extra_rl_steps_posterior=5)
    plan = pearl.training_plan(60)
    assert plan is not None and plan.initial_steps == 30 and plan.env_steps == 60
    finetune = build("finetune", learning_starts=20, gradient_steps=2)
    ft_plan = finetune.training_plan(100)
    assert ft_plan is not None and ft_plan.initial_steps == 20 and ft_plan.gradient_steps == 2 * (100 - 20)
    assert build("maml").training_plan(100) is None


# ----------------------------------------------------------------------------------------------
# PEARLPlus: its own arguments plus PEARL's through **kwargs (SB3's set-up idiom)
# ----------------------------------------------------------------------------------------------
def test_pearlplus_takes_pearls_arguments_and_its_own() -> None:
    # Each parameter is written once: PEARL+'s in PEARLPlus.__init__, PEARL's in PEARL.__init__ (forwarded by name).
    own = inspect.signature(PEARLPlus.__init__).parameters
    assert {name for name, p in own.items() if p.kind == p.KEYWORD_ONLY} == PRIOR_ARGUMENTS | {"_init_setup_model"}
    assert any(p.kind == p.VAR_KEYWORD for p in own.values())
    # inspect.signature shows the whole constructor: PEARL+'s arguments, then PEARL's with their defaults, no **kwargs.
    full = inspect.signature(PEARLPlus).parameters
    pearl = inspect.signature(PEARL).parameters
    assert not any(p.kind in (p.VAR_KEYWORD, p.VAR_POSITIONAL) for p in full.values())
    prior_order = [name for name in own if name in PRIOR_ARGUMENTS]
    pearl_order = [name for name in pearl if name not in ("policy", "env", "_init_setup_model")]
    assert list(full) == ["policy", "env", *prior_order, *pearl_order, "_init_setup_model"]
    for name, parameter in pearl.items():
        assert (full[name].default, full[name].annotation) == (parameter.default, parameter.annotation), name
        if name not in ("policy", "env"):
            assert full[name].kind == parameter.KEYWORD_ONLY, name  # passed by name, as PEARLPlus forwards them
    # The registry reads that signature: exactly PEARL's arguments and the prior term's.
    assert constructor_parameters(PEARLPlus) == dict(full)
    assert constructor_kwargs(PEARLPlus) == constructor_kwargs(PEARL) | PRIOR_ARGUMENTS
    assert constructor_kwargs(PEARLPlus) == (set(pearl) | PRIOR_ARGUMENTS) - ZOO_SET_KWARGS
    assert len(constructor_kwargs(PEARLPlus)) == 39


def test_every_algorithm_shows_its_whole_constructor() -> None:
    """inspect.signature of each algorithm lists every argument it takes, its parent's forwarded ones included (no
    **kwargs), and nothing it refuses; a subclass with a constructor of its own shows its own."""
    from sb3_pearl.oracle.oracle import _FINE_TUNING_KWARGS
    from sb3_pearl.registry import algorithm_classes

    for name, cls in algorithm_classes().items():
        parameters = inspect.signature(cls).parameters
        assert not any(p.kind in (p.VAR_KEYWORD, p.VAR_POSITIONAL) for p in parameters.values()), name
    finetune, oracle = inspect.signature(FineTune).parameters, inspect.signature(Oracle).parameters
    assert set(oracle) == set(finetune) - set(_FINE_TUNING_KWARGS)  # Oracle refuses the fine-tuning arguments
    with pytest.raises(ValueError, match="Oracle does not fine-tune"):
        Oracle("MlpPolicy", "PointGoalMeta-v0", adapt_gradient_steps=1)

    class Variant(PEARLPlus):
        def __init__(self, policy: str, env: str, *, extra: int = 1, **kwargs: Any) -> None:
            super().__init__(policy, env, **kwargs)

    assert list(inspect.signature(Variant).parameters) == ["policy", "env", "extra", "kwargs"]


def test_pearlplus_refuses_a_misspelled_argument() -> None:
    with pytest.raises(TypeError, match="unexpected keyword argument 'latnt_dim'"):
        PEARLPlus("MlpPolicy", "PointGoalMeta-v0", latnt_dim=3)
    with pytest.raises(TypeError, match="positional argument"):  # PEARL's arguments are passed by name
        PEARLPlus("MlpPolicy", "PointGoalMeta-v0", 3e-4)
    with pytest.raises(ValueError, match="unknown prior_critic mode 'twin'"):  # its own checks come first
        PEARLPlus("MlpPolicy", "PointGoalMeta-v0", prior_critic="twin", latnt_dim=3)


def test_pearlplus_sets_up_once_with_its_own_settings(monkeypatch: pytest.MonkeyPatch) -> None:
    setups = []
    original = PEARL._setup_model
    monkeypatch.setattr(PEARL, "_setup_model", lambda self: (setups.append(type(self).__name__), original(self)))
    model = build("pearlplus", prior_n_critics=2, prior_critic_arch=[4], prior_data="prior", prior_target="main")
    assert setups == ["PEARLPlus"]  # PEARL's constructor defers the set-up to PEARLPlus's
    assert model.policy.prior_critic is not None and model.policy.prior_n_critics == 2
    assert model.policy.prior_critic_arch == [4] and model.policy_kwargs["prior_critic"] == "separate"
    assert (model.prior_data, model.prior_target, model.prior_conservative_weight) == ("prior", "main", 0.0)
    # prior_coef=0 is PEARL: no prior critic is built.
    assert build("pearlplus", prior_coef=0.0).policy.prior_critic is None
    setups.clear()
    deferred = build("pearlplus", _init_setup_model=False)
    assert setups == []
    deferred._setup_model()
    assert deferred.policy.prior_critic is not None


def test_policy_kwargs_of_the_caller_are_left_as_they_are() -> None:
    policy_kwargs = dict(net_arch=[8])
    build("pearl", policy_kwargs=policy_kwargs)
    build("pearlplus", policy_kwargs=policy_kwargs, prior_critic_arch=[4])
    assert policy_kwargs == dict(net_arch=[8])


# ----------------------------------------------------------------------------------------------
# The loss step reads only its arguments
# ----------------------------------------------------------------------------------------------
def test_compute_losses_reads_only_its_arguments(tiny_kwargs: dict[str, Any]) -> None:
    model = PEARLPlus("MlpPolicy", "PointGoalMeta-v0", seed=0, prior_data="prior", **tiny_kwargs)
    model.learn(4 * tiny_kwargs["num_initial_steps"])
    replay, context, z0 = model._sample_meta_batch()
    th.manual_seed(5)
    via_model = model._compute_losses(replay, context, z0)
    th.manual_seed(5)
    settings = LossSettings(
        gamma=model.gamma,
        reward_scale=model.reward_scale,
        prior_term=True,
        prior_data="prior",
        prior_target="prior",
        prior_conservative_weight=0.0,
        target_entropy=float(model.target_entropy),
    )
    explicit = compute_losses(model.policy, replay, model.sample_posterior(context), z0, model.ent_coef_tensor, None, settings)
    for name, value in via_model._asdict().items():
        assert th.equal(value, getattr(explicit, name)), name
    # A setting changed on the model reaches the next step: the loss step keeps no copy of it.
    model.reward_scale = 50.0
    th.manual_seed(5)
    assert not th.equal(model._compute_losses(replay, context, z0).critic_loss, via_model.critic_loss)
