"""The oracle (task-aware SAC) and the task vector it is told, on every family."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
import torch
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

import sb3_pearl  # noqa: F401  (registers the families)
from pearl_paper.experiments.oracle import ORACLE
from pearl_paper.reproduce.velocity import constant_references, family_verdicts, geometric_median
from sb3_pearl import Oracle
from sb3_pearl.envs import FAMILIES
from sb3_pearl.envs.task_observation import TaskObservation, task_features
from sb3_pearl.evaluation.meta_test import meta_test
from sb3_pearl.oracle.oracle import with_task_observation

FLAT_FAMILIES = list(FAMILIES)
TINY = {"learning_starts": 50, "batch_size": 16, "policy_kwargs": {"net_arch": [16]}, "n_train_tasks": 4, "n_test_tasks": 2}


@pytest.mark.parametrize("env_id", FLAT_FAMILIES)
def test_task_vector_for_every_family(env_id: str) -> None:
    """The observation is the family's, then the standardised task of the episode, which a new task changes at reset."""
    env = TaskObservation(gym.make(env_id))
    base = env.unwrapped
    raw_dim = base.observation_space.shape[0]
    assert env.observation_space.shape == (raw_dim + env.task_dim,)
    first, second = base.sample_tasks(2, seed=123)
    base.set_task(first)
    obs, _ = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    expected = (task_features(base, first) - env.task_mean) / env.task_std
    np.testing.assert_allclose(obs[raw_dim:], expected, rtol=1e-5, atol=1e-5)
    # a task set during the episode takes effect at the next reset, not in this episode's observations
    base.set_task(second)
    obs, *_ = env.step(env.action_space.sample())
    np.testing.assert_allclose(obs[raw_dim:], expected, rtol=1e-5, atol=1e-5)
    obs, _ = env.reset(seed=1)
    assert not np.allclose(obs[raw_dim:], expected)
    np.testing.assert_allclose(obs[raw_dim:], (task_features(base, second) - env.task_mean) / env.task_std, rtol=1e-5)
    env.close()


def test_task_vector_is_standardised_over_the_family_distribution() -> None:
    env = TaskObservation(gym.make("HighwayMergeMeta-v0"))
    vectors = np.stack([env.task_vector(task) for task in env.unwrapped.sample_tasks(1000, seed=0)])
    np.testing.assert_allclose(vectors.mean(axis=0), 0.0, atol=1e-5)
    np.testing.assert_allclose(vectors.std(axis=0), 1.0, atol=1e-4)


def test_angles_are_continuous_features() -> None:
    """An Ant target just below 2 pi and one at 0 are the same velocity: their features agree (theta itself would not)."""
    base = gym.make("AntVelMeta-v0").unwrapped
    near_zero = task_features(base, {"direction": 0.0, "speed": 2.0})
    near_two_pi = task_features(base, {"direction": 2 * math.pi - 1e-6, "speed": 2.0})
    np.testing.assert_allclose(near_zero, near_two_pi, atol=1e-5)
    np.testing.assert_allclose(near_zero, [2.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(task_features(base, {"direction": math.pi / 2, "speed": 1.0}), [0.0, 1.0], atol=1e-9)
    ant_dir = gym.make("AntDirMeta-v0").unwrapped
    np.testing.assert_allclose(task_features(ant_dir, {"direction": math.pi}), [-1.0, 0.0], atol=1e-9)


def test_task_observation_refuses_what_it_cannot_serve() -> None:
    with pytest.raises(ValueError, match="task-family env"):
        TaskObservation(gym.make("Pendulum-v1"))
    with pytest.raises(ValueError, match="flat Box observation"):
        TaskObservation(_DictObservation(gym.make("PointGoalMeta-v0")))


class _DictObservation(gym.ObservationWrapper):
    """A family env whose observation is a dict (as gymnasium-robotics' goal envs before flattening)."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.observation_space = gym.spaces.Dict({"observation": env.observation_space})

    def observation(self, observation: np.ndarray) -> dict[str, np.ndarray]:
        return {"observation": observation}


def test_oracle_meta_test_on_the_plain_env_is_informed_and_does_not_adapt() -> None:
    """The meta-test gives the oracle the family env as is; it acts told the task, the same policy at every k."""
    model = Oracle("MlpPolicy", "PointGoalMeta-v0", seed=0, **TINY)
    model.learn(200)
    env = gym.make("PointGoalMeta-v0")
    result = meta_test(model, env, model.test_tasks, n_adapt=2, n_repeats=1, seed=0, crn_seed=5)
    assert len(result.rows) == 2 * 3 and model.n_observed == 3 * 20  # every trajectory observed (20 steps each) ...
    before = [p.detach().clone() for p in model.policy.parameters()]
    model.adapt()  # ... and adapt() changes nothing
    assert all(torch.equal(a, b) for a, b in zip(before, model.policy.parameters()))
    assert model.adapted_policy is model.policy
    # the actions depend on the task: the same position with two goals gives two actions
    wrapped = TaskObservation(gym.make("PointGoalMeta-v0"))
    a, b = (np.concatenate([[0.0, 0.0], wrapped.task_vector({"goal": goal})]) for goal in ([1.0, 1.0], [-1.0, -1.0]))
    actions = model.predict(np.stack([a, b]).astype(np.float32), deterministic=True)[0]
    assert not np.allclose(actions[0], actions[1])


def test_oracle_discrete_actions_on_highway_merge() -> None:
    model = Oracle("MlpPolicy", "HighwayMergeMeta-v0", seed=0, **TINY)
    assert model.observation_space.shape == (24 + 2,)  # kinematics + (density, speed)
    model.learn(120)
    action, _ = model.predict(model.observation_space.sample(), deterministic=True)
    assert model.action_space.contains(int(action))


def test_shifted_env_is_standardised_as_in_training(tmp_path) -> None:
    """A target beyond the training range reads as one: the shifted env takes the training env's standardisation."""
    model = Oracle("MlpPolicy", "Walker2dVelMeta-v0", seed=0, **TINY)
    training = TaskObservation(gym.make("Walker2dVelMeta-v0"))
    assert model.task_standardisation == training.standardisation
    shifted_env = gym.make("Walker2dVelMeta-v0", velocity_low=2.0, velocity_high=3.0)
    by_itself = TaskObservation(gym.make("Walker2dVelMeta-v0", velocity_low=2.0, velocity_high=3.0))
    wrapped = model.prepare_env(shifted_env)
    fast = {"velocity": 2.5}
    # by hand: (2.5 - mean) / std over the training tasks, U[0, 2]: mean ~1, std ~2 / sqrt(12)
    expected = (2.5 - training.task_mean[0]) / training.task_std[0]
    assert 2.4 < expected < 2.8
    np.testing.assert_allclose(wrapped.task_vector(fast), [expected], rtol=1e-6)
    assert abs(by_itself.task_vector(fast)[0]) < 0.2  # what the shifted env's own statistics would have told it
    wrapped.unwrapped.set_task(fast)
    obs, _ = wrapped.reset(seed=0)
    assert obs[-1] == pytest.approx(expected, rel=1e-5)
    # an env already wrapped (with its own statistics) is re-standardised, not wrapped twice
    assert model.prepare_env(by_itself) is by_itself
    np.testing.assert_allclose(by_itself.task_vector(fast), [expected], rtol=1e-6)

    # saved with the model, and given to the env load() and set_env() receive
    model.save(tmp_path / "oracle.zip")
    loaded = Oracle.load(tmp_path / "oracle.zip", env=gym.make("Walker2dVelMeta-v0", velocity_low=2.0, velocity_high=3.0))
    assert loaded.task_standardisation == model.task_standardisation
    assert loaded.env.env_method("task_vector", fast)[0][0] == pytest.approx(expected, rel=1e-6)
    loaded.set_env(gym.make("Walker2dVelMeta-v0", velocity_low=2.0, velocity_high=3.0))
    assert loaded.env.env_method("task_vector", fast)[0][0] == pytest.approx(expected, rel=1e-6)
    plain = Oracle.load(tmp_path / "oracle.zip")
    np.testing.assert_allclose(plain.prepare_env(shifted_env).task_vector(fast), [expected], rtol=1e-6)
    with pytest.raises(ValueError, match="1 means and 1 positive stds"):
        by_itself.standardise_with({"mean": [0.0, 1.0], "std": [1.0, 1.0]})


def test_an_oracle_saved_without_its_standardisation_takes_it_from_the_env_it_is_loaded_with(tmp_path) -> None:
    """A zip from before the standardisation was saved: load(env=training env) recovers it; without an env, a warning."""
    model = Oracle("MlpPolicy", "Walker2dVelMeta-v0", seed=0, **TINY)
    expected = model.task_standardisation
    model.task_standardisation = None  # what such a zip holds
    model.save(tmp_path / "old.zip")
    assert Oracle.load(tmp_path / "old.zip", env=gym.make("Walker2dVelMeta-v0")).task_standardisation == expected
    plain = Oracle.load(tmp_path / "old.zip")
    assert plain.task_standardisation is None
    with pytest.warns(UserWarning, match="saved without its task standardisation"):
        wrapped = plain.prepare_env(gym.make("Walker2dVelMeta-v0"))
    assert wrapped.standardisation == expected  # on the training distribution, the env's own is the same


def test_oracle_refuses_fine_tuning_settings_and_unwrappable_vec_envs() -> None:
    with pytest.raises(ValueError, match=r"does not fine-tune .*adapt_gradient_steps"):
        Oracle("MlpPolicy", "PointGoalMeta-v0", adapt_gradient_steps=10)
    venv = VecNormalize(DummyVecEnv([lambda: gym.make("PointGoalMeta-v0")]))
    with pytest.raises(ValueError, match="wrapper_class"):
        with_task_observation(venv)
    # a DummyVecEnv of family envs is rebuilt around wrapped envs; an already wrapped one is kept
    plain = DummyVecEnv([lambda: gym.make("PointGoalMeta-v0")])
    rebuilt = with_task_observation(plain)
    assert rebuilt.observation_space.shape == (4,)
    assert with_task_observation(rebuilt) is rebuilt


# ----------------------------------------------------------------------------------------------
# Competence against the oracle: the held-out velocity measure and its rules
# ----------------------------------------------------------------------------------------------
def test_geometric_median_and_constant_references_by_hand() -> None:
    # 1-D: the median; the best constant's mean error on {0, 1, 3} is (1 + 0 + 2) / 3
    refs = constant_references(np.array([[0.0], [1.0], [3.0]]))
    assert refs["constant"] == [1.0]
    assert refs["best_constant"] == pytest.approx(1.0) and refs["standing"] == pytest.approx(4.0 / 3.0)
    # 2-D, targets symmetric around the origin (any direction, one speed): the best constant is to stand still
    square = np.array([[2.0, 0.0], [0.0, 2.0], [-2.0, 0.0], [0.0, -2.0]])
    refs = constant_references(square)
    np.testing.assert_allclose(refs["constant"], [0.0, 0.0], atol=1e-6)
    assert refs["best_constant"] == pytest.approx(2.0) == refs["standing"]
    # three collinear points: the middle one (a data point, where Weiszfeld's weights are undefined)
    np.testing.assert_allclose(geometric_median(np.array([[0.0, 0.0], [1.0, 0.0], [5.0, 0.0]])), [1.0, 0.0], atol=1e-6)


def _record(seed: int, errors: dict[int, float], targets: list[list[float]]) -> dict:
    rows = [
        {
            "task": task,
            "repeat": 0,
            "k": k,
            "error": errors[k] + 0.1 * task,
            "length": 200,
            "violated": False,
            "return": 10.0 * k,
        }
        for task in range(len(targets))
        for k in errors
    ]
    return {"seed": seed, "targets": targets, "rows": rows}


def test_competence_rules_against_the_oracle() -> None:
    """Oracle error 0.3 against a best constant of 1.0 (learnable); PEARL 0.4 competent, PEARL+ 0.8 not (> 0.75 C)."""
    targets = [[0.0], [1.0], [3.0]]  # best constant 1.0 (the median)
    shift = 0.1  # the mean of 0.1 * task over tasks 0..2
    records = {
        "oracle": [_record(0, {0: 0.3 - shift, 1: 0.3 - shift}, targets)],
        "pearl": [_record(0, {0: 1.0, 1: 0.4 - shift}, targets), _record(1, {0: 1.0, 1: 0.4 - shift}, targets)],
        "pearlplus": [_record(0, {0: 1.0, 1: 0.8 - shift}, targets)],
    }
    decision = family_verdicts("walker2d-vel-long", records)
    assert decision.references["best_constant"] == pytest.approx(1.0)
    assert decision.mean("oracle") == pytest.approx(0.3) and decision.mean("pearl") == pytest.approx(0.4)
    assert decision.mean("pearl", "prior") == pytest.approx(1.1)
    assert decision.learnable == "learnable"
    assert decision.competent == {"pearl": "competent", "pearlplus": "not competent"}
    # per target-speed bin ([0, 1): task 0; >= 1: tasks 1 and 2)
    assert decision.runs["pearl"][0].by_bin == pytest.approx({"[0, 1)": 0.3, ">= 1": 0.45})
    # an oracle above half the best constant: the family is not learnable at the budget
    records["oracle"] = [_record(0, {0: 0.6 - shift, 1: 0.6 - shift}, targets)]
    assert family_verdicts("walker2d-vel-long", records).learnable == "not learnable"
    # records measured on other tasks are refused, not mixed
    records["pearlplus"] = [_record(0, {0: 1.0, 1: 0.5}, [[0.0], [2.0], [3.0]])]
    with pytest.raises(ValueError, match="other held-out tasks"):
        family_verdicts("walker2d-vel-long", records)


def test_competence_section_reports_the_oracle_and_the_judged_runs(tmp_path) -> None:
    """The report's section: the records under results/ (the oracle's and the runs JUDGED_RUNS names), the references,
    the per-bin errors and the verdicts, provisional while the oracle has fewer seeds than declared."""
    import json

    from pearl_paper.reproduce.velocity import VELOCITY_FILE, competence_section

    assert competence_section(tmp_path) == []  # no oracle record: no section
    targets = [[0.0], [1.0], [3.0]]
    shift = 0.1

    def write(experiment: str, variant: str, seed: int, errors: dict[int, float]) -> None:
        folder = tmp_path / experiment / "walker2d-vel-long" / variant / f"seed{seed}"
        folder.mkdir(parents=True)
        (folder / VELOCITY_FILE).write_text(json.dumps(_record(seed, errors, targets)))

    write("oracle", "oracle", 0, {0: 0.3 - shift, 1: 0.3 - shift})
    write("pearl-reference", "pearl", 0, {0: 1.0, 1: 0.35 - shift})
    write("pearl-reference", "pearl", 1, {0: 1.0, 1: 0.45 - shift})  # mean 0.40 <= 1.5 x 0.30 and <= 0.75 x 1.0
    write("walker-table1", "pearlplus", 0, {0: 1.0, 1: 0.8 - shift})
    lines = competence_section(tmp_path)
    text = "\n".join(lines)
    assert "standing still 1.333 m/s, the best constant velocity 1.000" in text
    assert "**learnable (provisional: 1 of 3 oracle seeds)**" in text
    assert "| Oracle (1) | 0.300 [0.300, 0.300] | 0.200 | 0.350 | 0.300 | 0.0% | 10.0 | learnable (provisional" in text
    assert "| PEARL (2) | 0.400 [0.350, 0.450] | 0.300 | 0.450 | 1.100 | 0.0% | 10.0 | competent |" in text
    assert "| PEARL+ (1) | 0.800 [0.800, 0.800] | 0.700 | 0.850 | 1.100 | 0.0% | 10.0 | not competent |" in text


def test_reproduce_velocity_measures_finished_runs_on_their_own_held_out_tasks(tmp_path) -> None:
    """`reproduce run oracle` (smoke) then `reproduce velocity oracle`: one record per finished run, on the run's own
    meta-test tasks (its n_tasks), every trajectory's velocity error; a second call measures nothing again."""
    import json

    from pearl_paper.reproduce.cli import main as reproduce_main

    args = ["--family", "walker2d-vel-long", "--seeds", "0", "--results-dir", str(tmp_path)]
    assert reproduce_main(["run", "oracle", "--budget", "smoke", *args]) == 0
    assert reproduce_main(["velocity", "oracle", *args]) == 0
    folder = tmp_path / "oracle" / "walker2d-vel-long" / "oracle" / "seed0"
    record = json.loads((folder / "velocity_held_out.json").read_text())
    result = json.loads((folder / "result.json").read_text())
    assert record["settings"]["n_tasks"] == result["meta_test"]["config"]["n_tasks"] == len(record["targets"])
    assert len(record["rows"]) == len(record["targets"]) * 2 * 6  # 2 repeats, k = 0..5
    assert all(row["error"] >= 0 for row in record["rows"]) and record["seed"] == 0
    before = (folder / "velocity_held_out.json").stat().st_mtime_ns
    assert reproduce_main(["velocity", "oracle", *args]) == 0
    assert (folder / "velocity_held_out.json").stat().st_mtime_ns == before
    # a family that is not a velocity family (or a typo) is refused, not filtered out into "0 run(s) measured"
    assert reproduce_main(["velocity", "oracle", "--family", "walker2d-vel-lng", "--results-dir", str(tmp_path)]) == 2


def test_reproduce_measure_redoes_an_oracle_shift_standardised_over_the_shifted_tasks(tmp_path) -> None:
    """A run's shifted meta-test records the training standardisation it told the oracle; a record without it (made
    before it was saved) is measured again by `reproduce measure` from model.zip, equal to the run's own measurement."""
    import json

    from pearl_paper.reproduce.cli import main as reproduce_main

    args = ["--family", "walker2d-vel-long", "--seeds", "0", "--results-dir", str(tmp_path)]
    assert reproduce_main(["run", "oracle", "--budget", "smoke", *args]) == 0
    path = tmp_path / "oracle" / "walker2d-vel-long" / "oracle" / "seed0" / "result.json"
    result = json.loads(path.read_text())
    training = TaskObservation(gym.make("Walker2dVelMeta-v0")).standardisation
    for section in ("meta_test", "shift"):  # told on the training scale, in- and out-of-distribution alike
        assert result[section]["config"]["task_standardisation"] == training
    # a zip and record from before the standardisation was saved
    old_model = Oracle.load(path.parent / "model.zip")
    old_model.task_standardisation = None
    old_model.save(path.parent / "model.zip")
    stale = json.loads(path.read_text())
    del stale["shift"]["config"]["task_standardisation"]
    stale["shift"]["summary"] = []  # what the old measurement said is replaced
    path.write_text(json.dumps(stale))
    assert reproduce_main(["measure", "oracle", "--results-dir", str(tmp_path)]) == 0
    measured = json.loads(path.read_text())
    assert "shifted env's tasks" in measured["shift"].pop("remeasured")["reason"]
    for record in (measured["shift"], result["shift"]):
        record.pop("wall_time_s")
    assert measured["shift"] == result["shift"]
    assert {key: value for key, value in measured.items() if key != "shift"} == {
        key: value for key, value in result.items() if key != "shift"
    }
    before = path.stat().st_mtime_ns
    assert reproduce_main(["measure", "oracle", "--results-dir", str(tmp_path)]) == 0  # up to date: nothing to do
    assert path.stat().st_mtime_ns == before
    # enjoy.py replays that older zip on the shifted ranges told on its training scale (the run's own env kwargs)
    from sb3_pearl.zoo.replay import enjoy

    shifted = ["--env-kwargs", "velocity_low:2.0", "velocity_high:3.0"]
    replayed = enjoy(
        ["--algo", "oracle", "--env", "Walker2dVelMeta-v0", "--run", str(path.parent), "--no-render"]
        + ["--n-tasks", "1", "--n-adapt", "0", *shifted]
    )
    assert replayed.config["task_standardisation"] == training and replayed.tasks[0]["velocity"] >= 2.0


def _merge_rows(failures_k0: int, failures_adapted: int, adapted_return: float) -> list[dict]:
    """10 trajectories at k = 0 and 10 at k = 1 with the given numbers of violations (crash or no merge)."""
    rows = [{"k": 0, "return": -5.0, "violated": i < failures_k0} for i in range(10)]
    return rows + [{"k": 1, "return": adapted_return, "violated": i < failures_adapted} for i in range(10)]


def test_merge_rule_by_hand() -> None:
    """Rule 3: the oracle at most 10% failures after adaptation; a meta-learner within 5 points of its failures and 10%
    of its return."""
    from pearl_paper.reproduce.merge_competence import merge_run, merge_verdicts

    oracle = [merge_run(_merge_rows(1, 1, -10.0), 0), merge_run(_merge_rows(0, 0, -10.0), 1)]  # 5% and -10.0
    assert (oracle[0].prior_failure, oracle[0].adapted_failure, oracle[0].adapted_return) == (0.1, 0.1, -10.0)
    runs = {
        "oracle": oracle,
        "PEARL": [merge_run(_merge_rows(3, 1, -10.9), 0)],  # 10% <= 5% + 5 points; -10.9 >= -11.0
        "PEARL+": [merge_run(_merge_rows(0, 2, -11.5), 0)],  # 20% > 10%; -11.5 < -11.0
        "fails more only": [merge_run(_merge_rows(0, 2, -10.0), 0)],
        "returns less only": [merge_run(_merge_rows(0, 1, -11.5), 0)],
    }
    verdicts = merge_verdicts(runs, n_oracle_seeds=2)
    assert verdicts.oracle == "competent"
    assert verdicts.competent == {
        "PEARL": "competent",
        "PEARL+": "not competent: fails more and returns less",
        "fails more only": "not competent: fails more",
        "returns less only": "not competent: returns less",
    }
    assert merge_verdicts({"oracle": [merge_run(_merge_rows(0, 2, -1.0), 0)]}).oracle == (
        "not competent (provisional: 1 of 3 oracle seeds)"
    )
    with pytest.raises(ValueError, match="needs at least one oracle run"):
        merge_verdicts({"PEARL": runs["PEARL"]})


def test_merge_competence_section_reads_the_oracle_and_table1s_runs(tmp_path) -> None:
    """The report's Merge rows come from the runs' result.json: the oracle's (oracle-merge) and Table I's Merge runs
    (PEARL's live in the experiment that owns them)."""
    import json

    from pearl_paper.reproduce.layout import RESULT_FILE
    from pearl_paper.reproduce.merge_competence import merge_competence_section
    from pearl_paper.reproduce.velocity import competence_section

    assert merge_competence_section(tmp_path) == []

    owners = {"oracle": "oracle-merge", "pearl-fixed-entropy": "merge-premise", "pearlplus-fixed-entropy": "merge-table1"}

    def write(variant: str, seed: int, rows: list[dict]) -> None:
        owner = owners[variant]  # where each variant's runs live (PEARL's: the experiment that owns them)
        folder = tmp_path / owner / "highway-merge" / variant / f"seed{seed}"
        folder.mkdir(parents=True)
        summary = [{key: 0.0 for key in ("k", "n", "return_mean", "violation_rate")}]
        result = {"experiment": owner, "family": "highway-merge", "variant": variant, "seed": seed, "budget_preset": "cpu"}
        result["meta_test"] = {"rows": rows, "summary": summary}
        (folder / RESULT_FILE).write_text(json.dumps(result))

    write("oracle", 0, _merge_rows(0, 1, -10.0))
    write("pearl-fixed-entropy", 0, _merge_rows(3, 1, -10.5))
    write("pearl-fixed-entropy", 1, _merge_rows(1, 3, -10.5))
    text = "\n".join(competence_section(tmp_path))
    assert text.startswith("### Competence against the oracle") and "#### Highway-Merge" in text
    assert "(15.0%) and its k >= 1 return at least the oracle's - 10% of |the oracle's| (-11.00)" in text
    assert "| Oracle (1) | 10.0% [10.0, 10.0] | 0.0% | -10.00 | competent (provisional: 1 of 3 oracle seeds) |" in text
    assert "| PEARL (2) | 20.0% [10.0, 30.0] | 20.0% | -10.50 | not competent: fails more (provisional" in text
    assert "PEARL+ (" not in text  # no run of PEARL+: no row


def test_tracking_panels_and_figure_from_the_velocity_records(tmp_path) -> None:
    """The report's tracking figure: per task the target speed, the best constant's error and each agent's adapted
    error averaged over seeds and repeats (k = 0 left out)."""
    import json

    from pearl_paper.reproduce.figures import plot_tracking
    from pearl_paper.reproduce.velocity import VELOCITY_FILE, oracle_family_records, tracking_panels

    targets = [[0.0], [1.0], [3.0]]  # best constant 1.0: errors 1, 0, 2
    for experiment, variant, seed, adapted in (
        ("oracle", "oracle", 0, 0.2),
        ("pearl-reference", "pearl", 0, 0.4),
        ("pearl-reference", "pearl", 1, 0.6),
    ):
        folder = tmp_path / experiment / "walker2d-vel-long" / variant / f"seed{seed}"
        folder.mkdir(parents=True)
        (folder / VELOCITY_FILE).write_text(json.dumps(_record(seed, {0: 5.0, 1: adapted, 2: adapted}, targets)))
    (panel,) = tracking_panels(oracle_family_records(tmp_path))
    np.testing.assert_allclose(panel["speeds"], [0.0, 1.0, 3.0])
    np.testing.assert_allclose(panel["constant_errors"], [1.0, 0.0, 2.0])
    assert list(panel["errors"]) == ["Oracle (1)", "PEARL (2)"]
    np.testing.assert_allclose(panel["errors"]["Oracle (1)"], [0.2, 0.3, 0.4])  # + 0.1 x task
    np.testing.assert_allclose(panel["errors"]["PEARL (2)"], [0.5, 0.6, 0.7])  # seeds 0.4 and 0.6 averaged
    assert plot_tracking([panel], tmp_path / "t.png") and (tmp_path / "t.png").stat().st_size > 0
    assert not plot_tracking([], tmp_path / "none.png") and not (tmp_path / "none.png").exists()


TASK_RANGE_KEYS = ("speed_low", "speed_high", "velocity_low", "velocity_high", "direction_low", "direction_high")


@pytest.mark.parametrize("family", ORACLE.families, ids=lambda family: family.name)
def test_oracle_families_shift_only_the_task_ranges(family) -> None:
    """The shifted meta-test (``{**env_kwargs, **shift_env_kwargs}``, as the runner merges them) changes the task ranges
    and nothing of the family's reward: a candidate whose fall penalty is moved into the healthy reward keeps it moved."""
    merged = {**family.env_kwargs, **dict(family.shift_env_kwargs or {})}
    for key, value in family.env_kwargs.items():
        if key not in TASK_RANGE_KEYS:
            assert merged[key] == value, key
    if family.name == "ant3d-vel-fwd-spread":
        assert merged["unhealthy_penalty"] == 0.0 and merged["healthy_reward"] == 4.0
        env = gym.make(family.env_id, **merged)
        env.reset(seed=0)
        _, reward, _, _, info = env.step(np.zeros(env.action_space.shape))
        assert reward == pytest.approx(4.0 + info["reward_forward"] + info["reward_ctrl"] + info["reward_contact"])


def test_a_calibration_family_is_reported_without_the_learnability_rule(tmp_path) -> None:
    """The learner calibration (one target) shows its error, not a verdict: its best constant is the target itself."""
    import json

    from pearl_paper.experiments.oracle import CALIBRATIONS
    from pearl_paper.reproduce.velocity import VELOCITY_FILE, competence_section

    (family,) = CALIBRATIONS
    folder = tmp_path / "oracle" / family / "oracle" / "seed0"
    folder.mkdir(parents=True)
    (folder / VELOCITY_FILE).write_text(json.dumps(_record(0, {0: 0.5, 1: 0.5}, [[2.9], [2.95], [3.0]])))
    text = "\n".join(competence_section(tmp_path))
    assert "**not judged: a calibration of the learner (one target), read its error and falls**" in text
    assert "| Oracle (1) | 0.600 [0.600, 0.600] |" in text and "not learnable" not in text


def test_given_standardisation_draws_no_reference_tasks(monkeypatch) -> None:
    """With the training standardisation given, the wrapper neither draws the env's own reference tasks nor uses them."""
    training = TaskObservation(gym.make("Walker2dVelMeta-v0")).standardisation
    shifted = gym.make("Walker2dVelMeta-v0", velocity_low=2.0, velocity_high=3.0)

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("sample_tasks called although the standardisation was given")

    monkeypatch.setattr(type(shifted.unwrapped), "sample_tasks", refuse)
    wrapped = TaskObservation(shifted, training)
    assert wrapped.task_dim == 1
    assert wrapped.standardisation == training
