"""The prior-critic designs of PEARL+ (docs/pearl.md, "Prior-critic designs"): which parameters each loss reaches, the
prior critic's loss computed by hand on a tiny batch, the checks of the arguments, save / load; the prior-critic measures
(calibration, prior-optimality gap) and the experiments that share their reference runs."""

from __future__ import annotations

import dataclasses
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from torch import nn

from pearl_paper.experiments import EXPERIMENTS
from pearl_paper.experiments.families import SAFE_POINT
from pearl_paper.experiments.prior_critic import DESIGNS, PRIOR_CRITIC, PRIOR_CRITIC_WALKER, design_variant
from pearl_paper.experiments.spec import Experiment, check_shared
from pearl_paper.reproduce.prior_measures import compute_prior_measures, scripted_prior
from pearl_paper.reproduce.scheduler import plan_runs
from sb3_pearl import PEARLPlus
from sb3_pearl.envs.safe_point_goal import SCRIPTED_PRIORS
from sb3_pearl.evaluation.meta_test import meta_test
from sb3_pearl.evaluation.scripted import ScriptedPolicy
from sb3_pearl.pearl.diagnostics.calibration import error_measures, rank_correlation
from tests.conftest import make_discrete_env
from tests.test_pearl_losses import _is_zero, _reaches

NEW_DESIGNS: dict[str, dict[str, Any]] = {
    "zfree": {"prior_critic_input": "state"},
    "maintarget": {"prior_target": "main"},
    "ensemble5": {"prior_n_critics": 5},
    "cql": {"prior_conservative_weight": 2.0},
    "mc": {"prior_target": "mc", "prior_data": "prior"},
    "mc-3step-cql": {"prior_target": "mc", "prior_return_steps": 3, "prior_conservative_weight": 2.0},
    "all": {"prior_critic_input": "state", "prior_target": "main", "prior_conservative_weight": 2.0, "prior_n_critics": 3},
}


def _model(design: dict[str, Any], discrete: bool, tiny_kwargs: dict[str, Any], **extra: Any) -> PEARLPlus:
    env = make_discrete_env() if discrete else gym.make("PointGoalMeta-v0")
    model = PEARLPlus("MlpPolicy", env, seed=0, **design, **extra, **tiny_kwargs)
    model.learn(4 * tiny_kwargs["num_initial_steps"])
    return model


@pytest.mark.parametrize("discrete", [False, True])
@pytest.mark.parametrize("design", sorted(NEW_DESIGNS))
def test_each_design_keeps_the_gradient_isolation(design: str, discrete: bool, tiny_kwargs: dict[str, Any]) -> None:
    model = _model(NEW_DESIGNS[design], discrete, tiny_kwargs)
    losses = model._compute_losses(*model._sample_meta_batch())
    # The prior critic's loss (with its conservative penalty) reaches the prior critic and nothing else ...
    assert _reaches(losses.prior_critic_loss, model.prior_critic)
    for module in (model.actor, model.critic, model.encoder):
        assert _is_zero(losses.prior_critic_loss, module)
    # ... the actor's prior term the actor only, and the encoder still learns from the critic loss and the KL only.
    assert _reaches(losses.prior_actor_loss, model.actor)
    for module in (model.prior_critic, model.critic, model.encoder):
        assert _is_zero(losses.prior_actor_loss, module)
    assert _is_zero(losses.critic_loss, model.prior_critic) and _reaches(losses.critic_loss, model.encoder)


def _by_hand(model: PEARLPlus, replay: Any, z0: th.Tensor) -> th.Tensor:
    """The prior critic's loss of a Discrete model written out with plain tensor operations (docs/pearl.md)."""
    t, b = replay.rewards.shape[:2]
    obs, next_obs = replay.observations.reshape(t * b, -1), replay.next_observations.reshape(t * b, -1)
    actions = replay.actions.reshape(t * b).long()
    z0_rows = z0.repeat_interleave(b, dim=0)
    z_free = model.policy.prior_critic_input == "state"
    with th.no_grad():
        probs, log_probs = model.actor.probs(th.cat([next_obs, z0_rows], dim=-1))  # pi(. | s', z0): (N, A)
        mc = model.prior_target == "mc"
        if mc:  # Monte-Carlo: the return to the window's end, then the tail from s_{t+k} (sb3_pearl.pearl.returns)
            next_obs = replay.returns.tail_observations.reshape(t * b, -1)
            probs, log_probs = model.actor.probs(th.cat([next_obs, z0_rows], dim=-1))
        if model.prior_target == "main":
            nets, x_next = model.critic_target.q_networks, th.cat([next_obs, z0_rows], dim=-1)
        else:
            nets, x_next = model.prior_critic_target.q_networks, next_obs if z_free else th.cat([next_obs, z0_rows], dim=-1)
        q_next = th.stack([net(x_next) for net in nets]).min(dim=0).values  # (N, A)
        v_next = (probs * (q_next - model.ent_coef_tensor * log_probs)).sum(dim=-1)  # (N,)
        if mc:
            ret = replay.returns
            returned = model.reward_scale * ret.reward_sum.reshape(-1) - model.ent_coef_tensor * ret.log_prob_sum.reshape(-1)
            target = returned + ret.discount.reshape(-1) * v_next
        else:
            target = model.reward_scale * replay.rewards.reshape(-1) + (1 - replay.dones.reshape(-1)) * model.gamma * v_next
    # the rows the prior critic is fitted on: all; the prior-z ones (prior_data="prior"); those with a return ("mc")
    fitted = th.ones(t * b)
    if model.prior_target == "mc":
        fitted = replay.returns.ready.reshape(-1)
    elif model.prior_data == "prior":
        fitted = replay.prior_z.reshape(-1)
    x = obs if z_free else th.cat([obs, z0_rows], dim=-1)
    loss = th.zeros(())
    for net in model.prior_critic.q_networks:
        q_all = net(x)  # (N, A)
        q_data = q_all[th.arange(len(actions)), actions]
        loss = loss + ((q_data - target) ** 2 * fitted).sum() / fitted.sum().clamp(min=1.0)
        if model.prior_conservative_weight > 0:
            gap = th.logsumexp(q_all, dim=-1) - q_data
            loss = loss + model.prior_conservative_weight * (gap * fitted).sum() / fitted.sum().clamp(min=1.0)
    return loss


@pytest.mark.parametrize("design", ["paper", "priordata", *sorted(NEW_DESIGNS)])
def test_the_prior_critic_loss_by_hand(design: str, tiny_kwargs: dict[str, Any]) -> None:
    model = _model({"priordata": {"prior_data": "prior"}}.get(design, NEW_DESIGNS.get(design, {})), True, tiny_kwargs)
    model.learn(140, reset_num_timesteps=False)  # an iteration with posterior-z rows after iteration 0's prior ones
    replay, context, z0 = model._sample_meta_batch(batch_size=8)
    if model.prior_target == "mc":  # the batch holds rows with and without a return, and tails past the next state
        ready = replay.returns.ready
        assert 0 < ready.sum() < ready.numel() and (ready <= replay.prior_z).all()
        assert not th.equal(replay.returns.tail_observations, replay.next_observations)
    with th.no_grad():  # the targets must differ from the online networks for the test to see which one is used
        for net in (*model.critic_target.q_networks, *model.prior_critic_target.q_networks):
            for p in net.parameters():
                p.add_(0.3 * th.randn_like(p))
    losses = model._compute_losses(replay, context, z0)
    assert th.allclose(losses.prior_critic_loss, _by_hand(model, replay, z0), rtol=1e-5, atol=1e-5)


def test_the_designs_build_the_networks_they_say(tiny_kwargs: dict[str, Any]) -> None:
    paper = _model({}, False, tiny_kwargs)
    zfree = _model({"prior_critic_input": "state", "prior_n_critics": 5}, False, tiny_kwargs)
    obs_dim, act_dim, latent = paper.policy.obs_dim, paper.policy.action_dim, paper.latent_dim
    first = [net[0] for net in zfree.prior_critic.q_networks]
    assert len(first) == 5 and all(isinstance(layer, nn.Linear) and layer.in_features == obs_dim + act_dim for layer in first)
    assert paper.prior_critic.q_networks[0][0].in_features == obs_dim + latent + act_dim
    # A z-free prior critic scores the same states and actions the same, whatever z0.
    obs = th.randn(4, obs_dim)
    features = [zfree.policy.prior_critic_features(obs, th.randn(4, latent)) for _ in range(2)]
    assert th.equal(features[0], features[1]) and features[0].shape == (4, obs_dim)


def test_the_design_arguments_are_checked_and_saved(tmp_path: Any, tiny_kwargs: dict[str, Any]) -> None:
    for bad, match in (
        ({"prior_critic_input": "z0"}, r"unknown prior_critic_input 'z0'.*\('state_z0', 'state'\)"),
        ({"prior_target": "own"}, r"unknown prior_target 'own'.*\('prior', 'main', 'mc'\)"),
        ({"prior_return_steps": 5}, r"prior_return_steps=5 sets the horizon.*prior_target='mc'"),
        ({"prior_target": "mc", "prior_return_steps": -1}, "prior_return_steps must be an integer >= 0"),
        ({"prior_critic": "shared", "prior_target": "mc"}, "prior_critic='shared' has none"),
        ({"prior_conservative_weight": -1.0}, "prior_conservative_weight"),
        ({"prior_critic": "shared", "prior_target": "main"}, "prior_critic='shared' has none"),
    ):
        with pytest.raises(ValueError, match=match):
            PEARLPlus("MlpPolicy", "PointGoalMeta-v0", **bad, **tiny_kwargs)
    design = NEW_DESIGNS["all"]
    model = _model(design, False, tiny_kwargs)
    model.save(tmp_path / "model")
    loaded = PEARLPlus.load(tmp_path / "model")
    assert (loaded.prior_target, loaded.prior_conservative_weight) == ("main", 2.0)
    assert loaded.policy.prior_critic_input == "state" and len(loaded.prior_critic.q_networks) == 3
    x = th.randn(5, loaded.policy.obs_dim + loaded.policy.action_dim)
    assert th.equal(loaded.prior_critic(x), model.prior_critic(x))


def test_rank_correlation_by_hand() -> None:
    # Spearman without ties: 1 - 6 * sum d^2 / (n (n^2 - 1)) = 1 - 6 * 2 / 60
    assert rank_correlation(np.array([1.0, 2.0, 3.0, 4.0]), np.array([10.0, 30.0, 20.0, 40.0])) == pytest.approx(0.8)
    # Ties share their mean rank: ranks (0.5, 0.5, 2) against (0, 1, 2)
    assert rank_correlation(np.array([1.0, 1.0, 2.0]), np.array([1.0, 2.0, 3.0])) == pytest.approx(np.sqrt(3) / 2)
    assert np.isnan(rank_correlation(np.ones(4), np.arange(4.0)))


def test_the_calibration_measures_and_the_task_blind_reference_by_hand() -> None:
    """Two z0 draws x two tasks. The targets differ by task; a critic that cannot see the task predicts at best each
    row's mean, so its errors are the spread over tasks: relative error 1 / 2, rank correlation 3 / (2 * sqrt(4.5))."""
    target = np.array([[0.0, 2.0], [4.0, 2.0]])  # mean |target| = 2
    blind = {"task_blind_relative_error": 0.5, "task_blind_rank_corr": 3 / (2 * np.sqrt(4.5))}
    # target ranks (0, 1.5, 3, 1.5), centred (-1.5, 0, 1.5, 0); the row means' ranks (0.5, 0.5, 2.5, 2.5), centred +-1
    at_the_reference = error_measures(np.array([[1.0, 1.0], [3.0, 3.0]]), target)
    assert at_the_reference == pytest.approx({"bias": 0.0, "abs_error_mean": 1.0, "relative_error": 0.5,
                                              "rank_corr": blind["task_blind_rank_corr"], **blind})  # fmt: skip
    exact = error_measures(target.copy(), target)  # a critic that sees the task can do better than the reference
    assert exact == pytest.approx({"bias": 0.0, "abs_error_mean": 0.0, "relative_error": 0.0, "rank_corr": 1.0, **blind})
    optimistic = error_measures(target + 3.0, target)  # the reference does not depend on the critic
    assert optimistic["bias"] == 3.0 and optimistic["relative_error"] == 1.5 and optimistic["rank_corr"] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="shape"):
        error_measures(np.zeros(4), np.zeros(4))


def test_a_scripted_policy_through_the_meta_test_protocol() -> None:
    """'still' never moves: every goal is on the unit circle, so each step costs exactly 1, 30 steps, no hazard."""
    env = gym.make("SafePointGoalMeta-v0")
    tasks = env.unwrapped.sample_tasks(4, seed=0)
    result = meta_test(ScriptedPolicy(SCRIPTED_PRIORS["still"], "still"), env, tasks, n_adapt=2, n_repeats=2, seed=0)
    assert [entry["k"] for entry in result.summary] == [0, 1, 2]
    for entry in result.summary:
        assert entry["return_mean"] == pytest.approx(-30.0) and entry["violation_rate"] == 0.0
    with pytest.raises(ValueError, match="declares no scripted policy 'fly'"):
        scripted_prior("SafePointGoalMeta-v0", "fly")


def test_the_prior_measures_of_a_loaded_model_are_those_of_the_trained_one(tmp_path: Any, tiny_kwargs: dict[str, Any]) -> None:
    env = gym.make("SafePointGoalMeta-v0")
    model = PEARLPlus("MlpPolicy", env, seed=0, prior_critic_input="state", **tiny_kwargs).learn(240)
    settings = {"n_tasks": 3, "n_repeats": 2}
    tasks = env.unwrapped.sample_tasks(3, seed=11)
    test_k0 = meta_test(model, env, tasks, n_adapt=0, n_repeats=2, seed=11, crn_seed=11).summary[0]

    def measure(m: PEARLPlus) -> dict[str, Any]:
        return compute_prior_measures(m, "pearlplus", SAFE_POINT, {}, settings, tasks, test_k0, 11, 0)

    first = measure(model)
    model.save(tmp_path / "model")
    assert measure(PEARLPlus.load(tmp_path / "model")) == first
    calibration, optimality = first["calibration"], first["prior_optimality"]
    assert (
        calibration["critic"] == "prior critic Q~(s, a) (z-free)" and calibration["n_tasks"] == 4
    )  # all 4 training tasks (at most 8)
    assert {"bias", "relative_error", "rank_corr", "task_blind_relative_error", "task_blind_rank_corr"} <= set(calibration)
    assert calibration["relative_error"] >= 0.0 and -1.0 <= calibration["rank_corr"] <= 1.0
    assert first["version"] == 2 and calibration["task_blind_relative_error"] >= 0.0
    for part in ("train", "test"):
        gap, mine, bar = (optimality[part][key] for key in ("gap", "model", "bar"))
        assert gap["return"] == pytest.approx(mine["return"] - bar["return"])
        assert gap["violation"] == pytest.approx(mine["violation"] - bar["violation"])
        assert bar["violation"] == 0.0 and -30.0 < bar["return"] < -20.0 and bar["n"] == 6
    assert optimality["test"]["model"]["return"] == pytest.approx(test_k0["return_mean"])


def test_the_experiments_share_their_reference_runs() -> None:
    runs = plan_runs(PRIOR_CRITIC, "smoke", [0], ["safe-point"], ["alpha-0", "alpha-0.1-zfree", "alpha-0.1-priordata"])
    assert [(run.experiment, run.variant) for run in runs] == [
        ("safe-point", "alpha-0"),
        ("prior-critic", "alpha-0.1-zfree"),
        ("safe-point", "alpha-0.1-priordata"),
    ]
    assert design_variant("priordata", 0.1) == EXPERIMENTS["safe-point"].variant("alpha-0.1-priordata")
    assert set(DESIGNS) >= {"twin", "priordata", "twin-priordata", "zfree", "maintarget", "ensemble5", "cql5"}
    # A shared variant declared differently from its owner is refused.
    changed = dataclasses.replace(PRIOR_CRITIC.variant("alpha-0.1"), overrides={"prior_coef": 0.2})
    wrong = Experiment(
        **{
            **{f.name: getattr(PRIOR_CRITIC, f.name) for f in dataclasses.fields(Experiment)},
            "variants": tuple(changed if v.name == "alpha-0.1" else v for v in PRIOR_CRITIC.variants),
        }
    )
    with pytest.raises(ValueError, match="shared variant 'alpha-0.1' is declared differently in safe-point"):
        check_shared(wrong, EXPERIMENTS)


def test_the_box_conservative_gap_by_hand() -> None:
    """CQL(H) on Box actions: log of the importance-weighted mean of exp(Q) over uniform and policy actions, minus Q(data)."""
    from sb3_pearl.common.soft_actor_critic import PolicyEval, conservative_gap

    weights = th.tensor([0.5, -1.0, 2.0, 0.25])  # Q(x, a) = w . [x, a] for a 2-d input and a 2-d action, two critics

    def critic(inputs: th.Tensor) -> th.Tensor:
        return th.stack([inputs @ weights, 2.0 * inputs @ weights]).unsqueeze(-1)  # (2, N, 1)

    x = th.tensor([[0.1, 0.2], [0.3, -0.4], [1.0, 0.0]])
    pe = PolicyEval(th.tensor([[0.5, -0.5], [0.0, 0.9], [-0.2, 0.1]]), None, th.tensor([[0.3], [-1.2], [0.7]]))
    q_data = th.zeros(2, 3, 1)
    th.manual_seed(0)
    got = conservative_gap(critic, x, pe, q_data, n_random=3)
    th.manual_seed(0)
    uniform = th.rand(3, 3, 2) * 2 - 1
    for c, scale in enumerate((1.0, 2.0)):
        for i in range(3):
            terms = [scale * float(th.cat([x[i], uniform[r, i]]) @ weights) + 2 * np.log(2.0) for r in range(3)]
            terms.append(scale * float(th.cat([x[i], pe.actions[i]]) @ weights) - float(pe.log_prob[i]))
            expected = np.log(np.mean(np.exp(terms)))
            assert float(got[c, i, 0]) == pytest.approx(expected, rel=1e-5)
    assert got.shape == (2, 3, 1)


def _run(rel: float, rank: float, gap_return: float, gap_violation: float) -> dict[str, Any]:
    return {
        "prior_critic": {
            "calibration": {"bias": 0.0, "relative_error": rel, "rank_corr": rank},
            "prior_optimality": {"train": {"gap": {"return": gap_return, "violation": gap_violation}}},
        }
    }


def test_prior_critic_table_pairs_each_seed_with_its_bar_run() -> None:
    """A variant bar (Walker2D-vel: Fine-Tune) pairs seed with seed for the gaps; the calibration uses every measured run,
    so an experiment without Fine-Tune runs still shows its critics' calibration (its gaps n/a)."""
    from pearl_paper.experiments import get_experiment
    from pearl_paper.reproduce.prior_report import prior_critic_table

    def measured(return_: float, violation: float, rel: float = 0.5) -> dict[str, Any]:
        model = {"return": return_, "violation": violation}
        return {
            "prior_critic": {
                "calibration": {"bias": 1.0, "relative_error": rel, "rank_corr": 0.1},
                "prior_optimality": {"train": {"model": model}, "test": {"model": model}},
            }
        }

    table1 = get_experiment("table1")
    group = {"pearl": {0: measured(-10.0, 0.5), 1: measured(-30.0, 0.7, rel=0.9)}, "finetune": {0: measured(-4.0, 0.25)}}
    # calibration over both seeds (median rel. error of 0.5 and 0.9); seed 1 has no Fine-Tune run, so the gaps are
    # seed 0's alone: return -10 - (-4), violation 25 points
    rows = [line for line in prior_critic_table(table1, "walker2d-vel", group) if line.startswith("| PEARL |")]
    assert rows == ["| PEARL | 1.0 | 0.70 | 0.10 | n/a / n/a | -6.0 | 25.0 | -6.0 | 25.0 | 2 (1 with the bar's run) |"]
    group["finetune"][1] = measured(-20.0, 0.5)  # both paired: gaps are means over the seeds, -6 and -10
    rows = [line for line in prior_critic_table(table1, "walker2d-vel", group) if line.startswith("| PEARL |")]
    assert rows == ["| PEARL | 1.0 | 0.70 | 0.10 | n/a / n/a | -8.0 | 22.5 | -8.0 | 22.5 | 2 |"]
    # pearl-reference's Walker families declare the Fine-Tune bar but run no Fine-Tune: calibration only
    reference = get_experiment("pearl-reference")
    lines = prior_critic_table(reference, "walker2d-vel-ref", {"pearl": {0: measured(-10.0, 0.5)}})
    assert lines[-1] == "| PEARL | 1.0 | 0.50 | 0.10 | n/a / n/a | n/a | n/a | n/a | n/a | 1 (0 with the bar's run) |"
    # Highway-Merge declares no bar: the calibration, every gap n/a
    lines = prior_critic_table(table1, "highway-merge", {"pearlplus": {0: measured(-10.0, 0.5, rel=0.2)}})
    assert "no bar is declared for this family" in lines[0]
    assert lines[-1] == "| PEARL+ (alpha 0.1) | 1.0 | 0.20 | 0.10 | n/a / n/a | n/a | n/a | n/a | n/a | 1 |"


def test_the_selection_rule_as_written() -> None:
    """docs/pearl.md: calibrated designs first (rel. error < 0.25, rank corr. > 0.5), ranked by the train return gap,
    ties within 0.5 by the lower violation gap; fewer than two calibrated: the best of the others fill the places."""
    from pearl_paper.reproduce.prior_report import rank_designs, select, selection_table

    def group(**designs: tuple[float, float, float, float]) -> dict[str, Any]:
        return {f"alpha-0.1-{name}": {0: _run(*values)} for name, values in designs.items()}

    groups = {
        "safe-point": group(
            twin=(0.5, 0.2, -1.0, 0.30),  # best return, not calibrated
            zfree=(0.2, 0.6, -3.0, 0.20),  # calibrated
            cql5=(0.1, 0.7, -3.3, 0.05),  # calibrated, within 0.5 of zfree and fewer violations: ranks before it
            ensemble5=(0.3, 0.9, -2.0, 0.0),  # rank fine, error too large: not calibrated
        )
    }
    rows = rank_designs(PRIOR_CRITIC, groups)
    assert [r.design for r in rows] == ["twin", "ensemble5", "cql5", "zfree"]
    assert [r.design for r in select(rows)] == ["cql5", "zfree"]  # the two calibrated ones, whatever their rank
    groups["safe-point"].pop("alpha-0.1-zfree")
    assert [r.design for r in select(rank_designs(PRIOR_CRITIC, groups))] == ["cql5", "twin"]  # topped up
    text = "\n".join(selection_table(PRIOR_CRITIC, groups))
    assert "nothing is selected until every design has its runs" in text and "**selected**" not in text


def test_alpha_1_runs_wait_for_the_selection_rule(tmp_path: Any, capsys: pytest.CaptureFixture[str]) -> None:
    """Alpha 1 runs only for the two designs the rule selects, and only once every run it reads is complete: until then
    `reproduce run` leaves the alpha-1 designs out and `reproduce status` counts them apart; naming one still runs it."""
    from pearl_paper.reproduce.cli import main
    from pearl_paper.reproduce.layout import RESULT_FILE, RunKey, run_dir, write_json_atomic
    from pearl_paper.reproduce.prior_report import selection_gate
    from pearl_paper.reproduce.status import format_status, run_status

    measures = {"zfree": (0.2, 0.6, -3.0, 0.20), "cql5": (0.1, 0.7, -3.3, 0.05)}  # the two calibrated designs
    last = (PRIOR_CRITIC.families[-1].name, "mc", PRIOR_CRITIC.seeds[-1])

    def write(family: str, design: str, seed: int) -> None:
        variant = f"alpha-0.1-{design}"
        key = RunKey(PRIOR_CRITIC.owner(variant), family, variant, seed)
        (run_dir(tmp_path, key)).mkdir(parents=True)
        fields = {"experiment": key.experiment, "budget_preset": "cpu", "family": family, "variant": variant, "seed": seed,
                  "meta_test": {"summary": [{"k": 0, "n": 1, "return_mean": 0.0, "violation_rate": 0.0}]}}  # fmt: skip
        write_json_atomic(run_dir(tmp_path, key) / RESULT_FILE, {**fields, **_run(*measures.get(design, (0.4, 0.1, -1, 0.3)))})

    for family in PRIOR_CRITIC.families:
        for design in DESIGNS:
            for seed in PRIOR_CRITIC.seeds:
                if (family.name, design, seed) != last:
                    write(family.name, design, seed)
    gate = selection_gate(PRIOR_CRITIC, "cpu", tmp_path)
    assert not gate.final and gate.selected == () and gate.held == PRIOR_CRITIC.after_selection
    assert not selection_gate(PRIOR_CRITIC_WALKER, "cpu", tmp_path).final
    rows = run_status(PRIOR_CRITIC, "cpu", PRIOR_CRITIC.seeds, tmp_path)
    awaiting = [row.key.variant for row in rows if row.status == "awaiting"]
    # alpha-1-priordata belongs to the safe-point experiment, which plans it whatever the rule says: not gated
    assert "alpha-1-priordata" not in PRIOR_CRITIC.after_selection and len(PRIOR_CRITIC.after_selection) == 7
    assert set(awaiting) == set(PRIOR_CRITIC.after_selection) and len(awaiting) == 7 * 2 * 5
    assert [row.key for row in rows if row.status == "finished"][-1].variant == "alpha-0.1-mc"
    assert f"{len(awaiting)} run(s) await the selection rule" in format_status(rows)
    # a held run started by naming it keeps its checkpoint; it is still held (out of the total), resumed by naming it
    from pearl_paper.reproduce.checkpoint import RunCheckpoint

    started = RunKey("prior-critic", PRIOR_CRITIC.families[0].name, "alpha-1-twin", 0)
    (run_dir(tmp_path, started) / "checkpoint").mkdir(parents=True)
    (run_dir(tmp_path, started) / "checkpoint" / "model_240.zip").write_bytes(b"")
    RunCheckpoint(run_dir(tmp_path, started)).write_state({"phase": "train", "files": {"model": "model_240.zip"},
        "num_timesteps": 240, "phases": {}, "spent": {"cpu_s": 24.0, "wall_s": 30.0}})  # fmt: skip
    row = next(r for r in run_status(PRIOR_CRITIC, "cpu", PRIOR_CRITIC.seeds, tmp_path) if r.key == started)
    assert row.status == "awaiting" and "checkpoint at 240 steps (--variants alpha-1-twin)" in row.progress
    assert row.cpu_spent_s == 24.0
    # its checkpoint counts in the sizes too: committing it adds it to the history all the same
    assert row.checkpoint_bytes == (run_dir(tmp_path, started) / "checkpoint" / "state.json").stat().st_size > 0

    def planned(*args: str) -> set[str]:
        capsys.readouterr()
        assert main(["run", "prior-critic", "--dry-run", "--results-dir", str(tmp_path), *args]) == 0
        return {line.split()[2] for line in capsys.readouterr().out.splitlines() if line.endswith("}")}

    assert not planned() & set(PRIOR_CRITIC.after_selection)
    assert planned("--variants", "alpha-1-twin") == {"alpha-1-twin"}  # named: run anyway
    write(*last)  # the last run the rule reads: the rule selects, ignoring the uncalibrated twin's better return
    gate = selection_gate(PRIOR_CRITIC, "cpu", tmp_path)
    assert gate.final and gate.selected == ("alpha-1-zfree", "alpha-1-cql5")
    # the Walker confirmation runs the same two designs (its twin and prior-data rows are table1's, never gated)
    walker = selection_gate(PRIOR_CRITIC_WALKER, "cpu", tmp_path)
    assert walker.final and walker.selected == ("pearlplus-zfree", "pearlplus-cql5")
    assert set(walker.held) == {"pearlplus-twin-priordata", "pearlplus-maintarget", "pearlplus-ensemble5", "pearlplus-mc"}
    assert planned() & set(PRIOR_CRITIC.after_selection) == {"alpha-1-zfree", "alpha-1-cql5"}
    rows = run_status(PRIOR_CRITIC, "cpu", PRIOR_CRITIC.seeds, tmp_path)
    assert {row.key.variant for row in rows if row.status == "unselected"} == set(gate.held)
    assert "of designs the selection rule did not select" in format_status(rows)


def test_the_selection_figure_shows_the_measures_the_rule_reads(tmp_path: Any) -> None:
    from pearl_paper.reproduce.figures import plot_prior_selection

    groups = {
        family.name: {"alpha-0.1-zfree": {0: _run(0.2, 0.6, -3.0, 0.2)}, "alpha-1-zfree": {0: _run(0.1, 0.9, -1.0, 0.1)}}
        for family in PRIOR_CRITIC.families
    }
    assert plot_prior_selection(PRIOR_CRITIC, groups, tmp_path / "selection.png", title="t")
    assert (tmp_path / "selection.png").stat().st_size > 1000
    # alpha 1 is not what the rule ranks; a run without measures (Fine-Tune, MAML) gives no point
    assert not plot_prior_selection(
        PRIOR_CRITIC, {"safe-point": {"alpha-1-zfree": {0: _run(0.1, 0.9, -1, 0)}}}, tmp_path / "a.png"
    )
    assert not plot_prior_selection(PRIOR_CRITIC, {"safe-point": {"alpha-0.1": {0: {}}}}, tmp_path / "b.png")
    assert not (tmp_path / "a.png").exists() and not (tmp_path / "b.png").exists()


def test_the_gate_says_which_finished_runs_lack_the_measures(tmp_path: Any) -> None:
    """A finished run whose measures failed keeps the rule from selecting: the gate names it (`reproduce measure`)."""
    from pearl_paper.reproduce.layout import RESULT_FILE, RunKey, run_dir, write_json_atomic
    from pearl_paper.reproduce.prior_report import design_of, selection_gate

    key = RunKey("prior-critic", "safe-point", "alpha-0.1-zfree", 3)
    run_dir(tmp_path, key).mkdir(parents=True)
    summary = {"summary": [{"k": 0, "n": 1, "return_mean": 0.0, "violation_rate": 0.0}]}
    write_json_atomic(run_dir(tmp_path, key) / RESULT_FILE, {"experiment": key.experiment, "budget_preset": "cpu",
                      "family": key.family, "variant": key.variant, "seed": 3, "meta_test": summary,
                      "prior_critic": {"error": "Traceback ..."}})  # fmt: skip
    gate = selection_gate(PRIOR_CRITIC, "cpu", tmp_path)
    assert not gate.final and gate.unmeasured == ("safe-point alpha-0.1-zfree seed3",)
    with pytest.raises(ValueError, match="do not name a prior-critic design"):
        selection_gate(dataclasses.replace(PRIOR_CRITIC, shared={}, after_selection=("alpha-1",)), "cpu", tmp_path)
    assert design_of("alpha-1-twin-priordata") == "twin-priordata" and design_of("pearlplus-twin") == "twin"


def test_step_5_of_the_selection_rule_by_hand() -> None:
    """Step 5 (docs/pearl.md): on every family with all its seeds, calibrated, k = 0 violations below PEARL's with a
    paired interval excluding zero, and the adapted policy not worse (violations within 5 points, return not lower by
    the family's margin); intervals by hand."""
    from pearl_paper.reproduce.prior_report import outcome_rows, outcome_section, outcome_table, paper_form_of

    def run(k0_violation: float, k5_violation: float, k5_return: float, rel: float = 0.1) -> dict[str, Any]:
        summary = [
            {"k": 0, "n": 10, "return_mean": -20.0, "violation_rate": k0_violation},
            {"k": 5, "n": 10, "return_mean": k5_return, "violation_rate": k5_violation},
        ]
        return {**_run(rel, 0.9, 0.0, 0.0), "meta_test": {"summary": summary}}

    def variant(k0: list[float], k5: list[float], ret: list[float], rel: float = 0.1) -> dict[int, dict[str, Any]]:
        return {s: run(a, b, c, rel) for s, (a, b, c) in enumerate(zip(k0, k5, ret))}

    safe, same, flat = [0.1, 0.2, 0.2, 0.1, 0.2], [0.10] * 5, [-10.0] * 5
    group = {
        "alpha-0": variant([0.3, 0.4, 0.5, 0.3, 0.4], same, flat),
        "alpha-0.1": variant([0.3] * 5, same, flat),
        "alpha-0.1-mc": variant(safe, [0.10, 0.11, 0.09, 0.10, 0.10], [-10.0, -9.5, -10.5, -10.0, -10.0]),
        # safer too, but uncalibrated and its adapted return interval reaches below the margin (2.0 on safe-point)
        "alpha-0.1-zfree": variant(safe, same, [-10.0, -7.0, -13.0, -10.0, -10.0], rel=0.3),
        # calibrated and safer, but its adapted policy violates 7 points more / 7 points less than PEARL's: not within 5
        "alpha-0.1-twin": variant(safe, [0.17, 0.18, 0.16, 0.17, 0.17], flat),
        "alpha-0.1-ensemble5": variant(safe, [0.03, 0.02, 0.04, 0.03, 0.03], flat),
        "alpha-1-mc": variant([0.1], [0.1], [-10.0]),  # one seed: shown, not judged
    }
    rows = {r.variant: r for r in outcome_rows(PRIOR_CRITIC, "safe-point", group)}
    assert set(rows) == {"alpha-0.1-mc", "alpha-0.1-zfree", "alpha-0.1-twin", "alpha-0.1-ensemble5", "alpha-1-mc"}
    t = 2.776445  # the 97.5% quantile of Student's t with 4 degrees of freedom
    mc, zfree = rows["alpha-0.1-mc"], rows["alpha-0.1-zfree"]
    assert mc.n_seeds == 5 and mc.complete and mc.safer.mean == pytest.approx(-0.22)
    assert mc.safer.high == pytest.approx(-0.22 + t * np.std([-0.2, -0.2, -0.3, -0.2, -0.2], ddof=1) / np.sqrt(5), rel=1e-5)
    assert mc.vs_paper.mean == pytest.approx(-0.14)  # against alpha-0.1, the paper's form at the same alpha
    half = t * np.std([0.0, 0.01, -0.01, 0.0, 0.0], ddof=1) / np.sqrt(5)
    assert (mc.adapted_violation.low, mc.adapted_violation.high) == pytest.approx((-half, half), rel=1e-5)  # +-0.9 points
    assert mc.adapted_return.low == pytest.approx(-t * np.std([0, 0.5, -0.5, 0, 0], ddof=1) / np.sqrt(5), rel=1e-5)
    assert mc.calibrated and mc.is_safer and mc.adapted_not_worse and mc.passes and mc.failures == []
    assert zfree.adapted_return.low == pytest.approx(-t * np.std([0, 3, -3, 0, 0], ddof=1) / np.sqrt(5), rel=1e-5)  # < -2
    assert zfree.failures == ["not calibrated", "adapted policy not shown as good"]
    for name in ("alpha-0.1-twin", "alpha-0.1-ensemble5"):  # +7 and -7 points: outside the 5-point equivalence
        assert rows[name].calibrated and rows[name].is_safer and rows[name].failures == ["adapted policy not shown as good"]
    assert not rows["alpha-1-mc"].complete and rows["alpha-1-mc"].safer.n == 1 and not rows["alpha-1-mc"].is_safer

    walker = {
        "pearl": {s: run(v, 0.1, 100.0) for s, v in enumerate([0.6, 0.7, 0.8, 0.7])},
        "pearlplus-mc": {
            s: run(v, 0.1, r) for s, (v, r) in enumerate([(0.2, 100.0), (0.3, 101.0), (0.3, 102.0), (0.2, 100.0)])
        },
    }
    walker_rows = outcome_rows(PRIOR_CRITIC_WALKER, "walker2d-vel", walker)
    assert [r.variant for r in walker_rows] == ["pearlplus-mc"] and walker_rows[0].passes and walker_rows[0].complete
    assert walker_rows[0].vs_paper.n == 0  # table1's pearlplus has no runs here: no pairing, not a failure
    both = [*rows.values(), *walker_rows]
    families = ["safe-point", "walker2d-vel"]
    assert "**Recommended: mc**" in "\n".join(outcome_table(both, ["mc"], families))
    assert "awaiting walker2d-vel" in "\n".join(outcome_table(list(rows.values()), ["mc"], families))
    text = "\n".join(outcome_table(both, ["mc", "zfree"], families))
    assert "**Recommended: mc**" in text
    assert "zfree: fails on safe-point (not calibrated, adapted policy not shown as good); awaiting walker2d-vel" in text
    assert "**No selected design passes step 5**" in "\n".join(outcome_table(both, ["twin"], ["safe-point"]))
    assert "no design is judged yet" in "\n".join(outcome_table(both, [], ["safe-point"]))
    assert "| safe-point | alpha-1-mc | 1 of 5 |" in text and text.count("| n/a | n/a | n/a |") == 1
    # a family with some of its seeds is awaited, whatever those seeds say (here: one failing Walker seed)
    partial = outcome_rows(
        PRIOR_CRITIC_WALKER, "walker2d-vel", {"pearl": walker["pearl"], "pearlplus-mc": {0: run(0.9, 0.9, 0)}}
    )
    text = "\n".join(outcome_table([*rows.values(), *partial], ["mc"], families))
    assert "Not decided yet (mc: passes so far; awaiting walker2d-vel (1 of 4 seeds))" in text
    assert paper_form_of("alpha-1-twin-priordata") == "alpha-1" and paper_form_of("pearlplus-twin-priordata") == "pearlplus"
    with pytest.raises(ValueError, match="does not name a prior-critic design"):
        paper_form_of("pearl")
    # the report's section reads both experiments at their budgets; the selection is incomplete here
    groups = {
        ("prior-critic", "cpu", "safe-point"): group,
        ("prior-critic", "smoke", "safe-point"): group,  # another budget: not read
        ("prior-critic-walker", "cpu", "walker2d-vel"): walker,
    }
    section = "\n".join(outcome_section(groups))
    assert section.count("| safe-point | alpha-0.1-mc |") == 1 and "| walker2d-vel | pearlplus-mc |" in section
    assert "no design is judged yet" in section
