"""The meta-test protocol on a scripted stand-in model whose posterior is known, plus the callback on PEARL+."""

from __future__ import annotations

import csv
import json
import math
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.logger import configure
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecMonitor

from sb3_pearl import PEARLPlus
from sb3_pearl.envs.task_protocol import MetaTaskEnv
from sb3_pearl.evaluation.callbacks import MetaTestCallback
from sb3_pearl.evaluation.held_out import held_out_meta_test, held_out_tasks, meta_test_record
from sb3_pearl.evaluation.meta_test import ROW_COLUMNS, MetaTestResult, json_value, meta_test
from sb3_pearl.evaluation.statistics import (
    PRIOR_POSTERIOR_ROWS,
    SUMMARY_COLUMNS,
    cvar,
    format_prior_posterior_table,
    summarize,
    wilson_interval,
)

HORIZON = 3
UNSAFE_ACTION = 3


class GuessEnv(MetaTaskEnv, gym.Env):
    """Task: a target action in {0, 1, 2}; reward 1 per step that plays it; action 3 costs 1; 3 steps.

    ``info`` carries merge-family style extras: ``b_min`` on step 2 only, ``merged`` every step,
    ``ego_speed`` (the step index) for the traces; declared as the merge family declares them.
    """

    observation_space = spaces.Box(0.0, 1.0, (1,), np.float32)
    action_space = spaces.Discrete(4)
    trajectory_info_keys = ("merged", "crashed", "b_min", "rear_deceleration")
    step_trace_keys = ("ego_speed",)

    def __init__(self) -> None:
        self._init_task()
        self.t = 0

    def _sample_task(self, rng: np.random.Generator) -> dict[str, Any]:
        return {"target": int(rng.integers(3))}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self._apply_pending_task()
        self.t = 0
        return np.zeros(1, np.float32), {}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        action = int(action)
        self.t += 1
        info: dict[str, Any] = {"cost": float(action == UNSAFE_ACTION), "merged": action == self._task["target"]}
        info["ego_speed"] = float(self.t)
        if self.t == 2:
            info["b_min"] = 10.0 * self._task["target"] + action
        reward = float(action == self._task["target"])
        return np.full(1, self.t / HORIZON, np.float32), reward, False, self.t >= HORIZON, info


class ScriptedModel:
    """Stand-in with a known posterior.

    Prior (k = 0): the unsafe action 3. After the j-th ``adapt()``: the rewarded action if one was
    observed since the reset, else action j - 1 (explores 0, 1, 2 in turn). Records every call.
    """

    def __init__(self) -> None:
        self.calls: list[str] = []
        self.observed: list[tuple[Any, ...]] = []
        self.n_adapt = 0
        self.action = UNSAFE_ACTION
        self.predict_phases: list[int] = []
        self.deterministic_calls: list[bool] = []

    def reset_adaptation(self) -> None:
        self.calls.append("reset")
        self.observed = []
        self.n_adapt = 0
        self.action = UNSAFE_ACTION

    def observe(self, obs: np.ndarray, action: Any, reward: float, next_obs: np.ndarray, done: bool) -> None:
        self.calls.append("observe")
        self.observed.append((np.asarray(obs).copy(), int(action), reward, np.asarray(next_obs).copy(), done))

    def adapt(self) -> None:
        self.calls.append("adapt")
        self.n_adapt += 1
        rewarded = [a for (_, a, r, _, _) in self.observed if r > 0]
        self.action = rewarded[0] if rewarded else self.n_adapt - 1

    def predict(self, observation: Any, state: Any = None, episode_start: Any = None, deterministic: bool = False) -> Any:
        self.predict_phases.append(self.n_adapt)
        self.deterministic_calls.append(deterministic)
        return np.int64(self.action), None


TASKS = [{"target": 0}, {"target": 2}]
# return per (task, k) for n_adapt = 3, from the scripted posterior
EXPECTED_RETURNS = {0: [0.0, 3.0, 3.0, 3.0], 1: [0.0, 0.0, 0.0, 3.0]}


def run_protocol(env: Any = None, n_repeats: int = 1) -> tuple[ScriptedModel, MetaTestResult]:
    model = ScriptedModel()
    return model, meta_test(model, env if env is not None else GuessEnv(), TASKS, n_adapt=3, n_repeats=n_repeats, seed=0)


def test_rows_and_k_indexing() -> None:
    model, result = run_protocol(n_repeats=2)
    assert [(r["task"], r["repeat"], r["k"]) for r in result.rows] == [
        (t, rep, k) for t in range(2) for rep in range(2) for k in range(4)
    ]
    for row in result.rows:
        assert row["return"] == EXPECTED_RETURNS[row["task"]][row["k"]]
        assert row["length"] == HORIZON
        # k = 0 is the prior (unsafe action 3 on every step); the scripted posterior never plays it
        assert row["cost"] == (3.0 if row["k"] == 0 else 0.0)
        assert row["violated"] is (row["k"] == 0)
        assert row["merged"] == float(EXPECTED_RETURNS[row["task"]][row["k"]] > 0)
    # call sequence per (task, repeat): reset, then 3 observes per trajectory with adapt between trajectories
    per_episode = ["reset"] + ["observe"] * 3 + (["adapt"] + ["observe"] * 3) * 3
    assert model.calls == per_episode * 4
    # predict at trajectory k saw exactly k adapt() calls: k = 0 really used the prior
    assert model.predict_phases == [k for _ in range(4) for k in range(4) for _ in range(HORIZON)]


def test_stochastic_adaptation_models_act_stochastically() -> None:
    model, result = run_protocol()
    assert all(model.deterministic_calls) and result.config["deterministic"] is True
    explorer = ScriptedModel()
    explorer.stochastic_adaptation = True  # type: ignore[attr-defined]  # as MAML declares
    result = meta_test(explorer, GuessEnv(), TASKS, n_adapt=1)
    assert not any(explorer.deterministic_calls) and result.config["deterministic"] is False


def test_observe_gets_every_transition() -> None:
    model = ScriptedModel()
    meta_test(model, GuessEnv(), [{"target": 1}], n_adapt=1)
    # the last trajectory's transitions (k = 1): action 0 (nothing rewarded in k = 0), obs chain 0 -> 1/3 -> 2/3 -> 1
    last = model.observed[-3:]
    assert [a for (_, a, _, _, _) in last] == [0, 0, 0]
    assert [float(o[0]) for (o, _, _, _, _) in last] == pytest.approx([0.0, 1 / 3, 2 / 3])
    assert [float(n[0]) for (_, _, _, n, _) in last] == pytest.approx([1 / 3, 2 / 3, 1.0])
    assert [d for (_, _, _, _, d) in last] == [False, False, True]


def test_summary_numbers() -> None:
    _, result = run_protocol()
    s = {entry["k"]: entry for entry in result.summary}
    assert list(s) == [0, 1, 2, 3]
    assert s[0]["n"] == 2 and s[0]["return_mean"] == 0.0 and s[0]["return_std"] == 0.0
    assert s[0]["violation_rate"] == 1.0
    assert (s[0]["violation_ci_low"], s[0]["violation_ci_high"]) == pytest.approx(wilson_interval(2, 2))
    assert s[0]["cum_violations"] == 1.0 and s[3]["cum_violations"] == 1.0
    assert s[1]["return_mean"] == 1.5 and s[1]["return_std"] == 1.5 and s[1]["return_cvar10"] == 0.0
    assert s[1]["violation_rate"] == 0.0
    assert s[3]["return_mean"] == 3.0 and s[3]["return_cvar10"] == 3.0
    # family extras: mean of the per-trajectory last value; b_min = 10 * target + action on step 2
    assert s[0]["b_min_mean"] == pytest.approx(np.mean([0 + 3, 20 + 3]))
    assert s[3]["merged_mean"] == 1.0
    assert [e["k"] for e in result.paper_table()] == [0, 1, 3]
    assert set(SUMMARY_COLUMNS) <= set(s[0])


def test_statistics() -> None:
    low, high = wilson_interval(0, 10)
    assert low == 0.0 and high == pytest.approx(0.2775, abs=1e-4)
    low, high = wilson_interval(5, 10)
    assert (low, high) == pytest.approx((0.2366, 0.7634), abs=1e-4)
    assert all(math.isnan(v) for v in wilson_interval(0, 0))
    assert cvar(np.arange(1.0, 21.0), 0.1) == 1.5  # worst 2 of 20
    assert cvar([5.0, -1.0, 3.0], 0.1) == -1.0  # at least one value
    # cumulative violations count each (task, repeat) sequence
    rows = [
        {"task": 0, "repeat": 0, "k": 0, "return": 0.0, "violated": True},
        {"task": 0, "repeat": 0, "k": 1, "return": 0.0, "violated": True},
        {"task": 1, "repeat": 0, "k": 0, "return": 0.0, "violated": False},
        {"task": 1, "repeat": 0, "k": 1, "return": 0.0, "violated": True},
    ]
    assert [e["cum_violations"] for e in summarize(rows)] == [0.5, 1.5]


def test_prior_posterior_table_puts_the_ks_side_by_side() -> None:
    """enjoy.py's summary: one column per k (the prior first), the summary's numbers, wrapped after max_columns."""
    rows = [
        {"task": task, "repeat": 0, "k": k, "return": float(-10 * (task + 1) + k), "violated": k == 0 and task == 0}
        for task in range(2)
        for k in range(8)
    ]
    table = format_prior_posterior_table(summarize(rows))
    first, second = table.split("\n\n")  # k = 0..5, then k = 6, 7
    lines = first.splitlines()
    assert lines[0].split("  ")[-1].strip() == "k = 5" and lines[0].strip().startswith("k = 0 (prior)")
    assert [line[:22].strip() for line in lines[1:]] == list(PRIOR_POSTERIOR_ROWS)
    assert lines[1][22:].split()[:3] == ["-15.0", "+-", "5.0"]  # k = 0: returns -10 and -20
    assert lines[3][22:].split()[:6] == ["50", "[9,", "91]", "0", "[0,", "66]"]  # k = 0: 1 of 2 violated; k = 1: none
    assert second.splitlines()[0].split() == ["k", "=", "6", "k", "=", "7"]
    assert len(format_prior_posterior_table(summarize(rows), max_columns=8).split("\n\n")) == 1


def test_csv_and_json_schema(tmp_path: Any) -> None:
    _, result = run_protocol()
    result.to_csv(tmp_path / "m.csv")
    lines = (tmp_path / "m.csv").read_text().splitlines()
    assert lines[0] == "task,repeat,k,return,cost,length,violated,merged,b_min"
    assert lines[1] == "0,0,0,0.0,3.0,3,1,0.0,3.0"
    assert lines[2] == "0,0,1,3.0,0.0,3,0,1.0,0.0"
    assert len(lines) == 1 + 8
    with open(tmp_path / "m.csv") as file:
        assert list(csv.DictReader(file).fieldnames or []) == [*ROW_COLUMNS, "merged", "b_min"]
    result.to_json(tmp_path / "m.json")
    data = json.loads((tmp_path / "m.json").read_text())
    assert set(data) == {"config", "summary", "paper", "tasks", "rows", "traces"}
    assert data["config"]["n_adapt"] == 3 and data["tasks"] == TASKS
    assert list(data["paper"]) == ["0", "1", "3"]
    assert data["traces"][0] == {"task": 0, "repeat": 0, "k": 0, "ego_speed": [1.0, 2.0, 3.0]}
    back = MetaTestResult.from_json(tmp_path / "m.json")
    assert back.rows == result.rows and back.summary == result.summary


def test_info_keys_come_from_the_family() -> None:
    _, result = run_protocol()
    assert result.config["trajectory_info_keys"] == list(GuessEnv.trajectory_info_keys)
    assert result.config["step_trace_keys"] == ["ego_speed"]

    class UndeclaredEnv(GuessEnv):
        trajectory_info_keys = ()
        step_trace_keys = ()

    plain = meta_test(ScriptedModel(), UndeclaredEnv(), TASKS, n_adapt=1)
    assert set(plain.rows[0]) == set(ROW_COLUMNS) and plain.traces == [] and plain.columns == list(ROW_COLUMNS)
    assert "b_min_mean" not in plain.summary[0]
    # an explicit trace_keys overrides the family's, also through a generic VecEnv
    traced = meta_test(ScriptedModel(), VecMonitor(DummyVecEnv([UndeclaredEnv])), TASKS, n_adapt=1, trace_keys=["ego_speed"])
    assert traced.traces[0] == {"task": 0, "repeat": 0, "k": 0, "ego_speed": [1.0, 2.0, 3.0]}
    assert traced.config["step_trace_keys"] == ["ego_speed"]


def test_vec_envs_give_the_same_rows() -> None:
    _, reference = run_protocol()
    _, dummy = run_protocol(DummyVecEnv([GuessEnv]))
    _, wrapped = run_protocol(VecMonitor(DummyVecEnv([GuessEnv])))  # generic VecEnv path (auto-reset, terminal obs)
    assert dummy.rows == reference.rows
    assert wrapped.rows == reference.rows
    # a worker process: the meta-test asks whether the env tells a task before reading what it tells (a missing
    # attribute would end the worker); an env without the task in its observation records no standardisation
    subproc_env = SubprocVecEnv([GuessEnv])
    _, subproc = run_protocol(subproc_env)
    subproc_env.close()
    assert subproc.rows == reference.rows and "task_standardisation" not in subproc.config


def test_clear_errors() -> None:
    with pytest.raises(TypeError, match="adaptation API"):
        meta_test(object(), GuessEnv(), TASKS)
    with pytest.raises(ValueError, match="no test tasks"):
        meta_test(ScriptedModel(), GuessEnv(), [])
    with pytest.raises(ValueError, match="one env at a time"):
        meta_test(ScriptedModel(), DummyVecEnv([GuessEnv, GuessEnv]), TASKS)


def test_held_out_tasks_are_the_eval_seed_draw_and_never_training_tasks() -> None:
    assert held_out_tasks(GuessEnv(), 5, eval_seed=3) == GuessEnv().sample_tasks(5, 3)
    assert held_out_tasks(DummyVecEnv([GuessEnv]), 5, eval_seed=3) == GuessEnv().sample_tasks(5, 3)
    drawn = GuessEnv().sample_tasks(4, 7)
    n_same = sum(task == drawn[2] for task in drawn)  # 3 targets only: a draw repeats tasks
    with pytest.raises(ValueError, match=rf"run x: {n_same} test task\(s\) drawn with eval_seed 7 are training tasks"):
        held_out_tasks(GuessEnv(), 4, eval_seed=7, train_tasks=[drawn[2]], what="run x")
    with pytest.raises(ValueError, match="has no sample_tasks"):
        held_out_tasks(gym.make("CartPole-v1"), 2, eval_seed=0)


def test_held_out_meta_test_is_the_protocol_with_common_random_numbers() -> None:
    """One meta-test definition: the held-out draw, seed = crn_seed = eval_seed, the eval seed recorded."""
    model = ScriptedModel()
    model.test_tasks = TASKS[:2]  # type: ignore[attr-defined]  # n_tasks None: as many as the model's test tasks
    settings = {"n_adapt": 2, "n_repeats": 2, "n_tasks": None, "deterministic": True}
    result = held_out_meta_test(model, GuessEnv(), settings, eval_seed=5)
    direct = meta_test(ScriptedModel(), GuessEnv(), GuessEnv().sample_tasks(2, 5), n_adapt=2, n_repeats=2, seed=5, crn_seed=5)
    assert result.rows == direct.rows and result.tasks == direct.tasks
    assert result.config["eval_seed"] == 5 and result.config["crn_seed"] == 5
    record = meta_test_record(result, wall_time_s=1.0)
    assert record["summary"] == json_value(direct.summary) and record["wall_time_s"] == 1.0
    # settings left out take the defaults (n_repeats 1, ...); an unknown key or a value out of range is named
    partial = held_out_meta_test(ScriptedModel(), GuessEnv(), {"n_adapt": 2, "n_tasks": 2}, eval_seed=5)
    assert partial.config["n_repeats"] == 1 and len(partial.rows) == 2 * 3
    refused = (({"n_adapt": 1, "bogus": 1}, r"unknown key\(s\) \['bogus'\]"), ({"n_repeats": 0}, "n_repeats must be"))
    for bad, message in refused:
        with pytest.raises(ValueError, match=message):
            held_out_meta_test(ScriptedModel(), GuessEnv(), bad, eval_seed=5)


def test_callback_logs_meta_test(tiny_kwargs: dict[str, Any], tmp_path: Any) -> None:
    env = gym.make("SafePointGoalMeta-v0")
    model = PEARLPlus("MlpPolicy", "SafePointGoalMeta-v0", seed=0, **tiny_kwargs)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    callback = MetaTestCallback(
        env, eval_freq=60, n_tasks=2, n_adapt=2, best_model_save_path=str(tmp_path), log_path=str(tmp_path)
    )
    model.learn(130, callback=callback)
    assert callback.n_evaluations == 2
    assert callback.last_result is not None and len(callback.last_result.rows) == 2 * 3
    with open(tmp_path / "progress.csv") as file:
        columns = csv.DictReader(file).fieldnames or []
    for key in ("meta_test/return_k0", "meta_test/return_k2", "meta_test/violation_rate_k0", "meta_test/return_adapted"):
        assert key in columns
    assert (tmp_path / "best_model.zip").is_file()
    history = (tmp_path / "meta_test_history.csv").read_text().splitlines()
    assert history[0].startswith("timesteps,k,n,return_mean") and len(history) == 1 + 2 * 3


def test_figures_read_a_harness_run_like_a_zoo_run(tmp_path: Any) -> None:
    """One output format: a committed result.json's meta_test section loads as train.py's meta_test.json does."""
    import json
    from pathlib import Path

    from sb3_pearl.evaluation.figures import load_run, plot_adaptation

    folder = Path(__file__).resolve().parents[1] / "results" / "safe-point" / "safe-point" / "alpha-0.1" / "seed0"
    label, result = load_run(folder)
    committed = json.loads((folder / "result.json").read_text())["meta_test"]
    assert label == "alpha-0.1" and result.rows == committed["rows"] and result.tasks == committed["tasks"]
    assert [entry["k"] for entry in result.summary] == list(range(6))
    plot_adaptation({label: result}, tmp_path / "a.png")
    assert (tmp_path / "a.png").stat().st_size > 0


@pytest.mark.parametrize("env_id", ["Walker2dVelMeta-v0", "AntVelMeta-v0", "HalfCheetahVelMeta-v0"])
def test_velocity_families_record_each_trajectorys_velocity_error(env_id: str) -> None:
    """The family's own measure of the job: per trajectory the mean of |v - v*| over its steps, in the rows, the summary
    and both tables, beside return and violations."""
    from sb3_pearl.evaluation.scripted import ScriptedPolicy

    env = gym.make(env_id)
    still = ScriptedPolicy(lambda obs: np.zeros(env.action_space.shape), "zero torque")
    tasks = env.unwrapped.sample_tasks(2, seed=3)
    result = meta_test(still, env, tasks, n_adapt=1, n_repeats=1, seed=0, max_steps=30, trace_keys=("reward_forward",))
    for row, trace in zip(result.rows, result.traces, strict=True):
        assert row["velocity_error"] == pytest.approx(-np.mean(trace["reward_forward"]))
    k0 = result.summary[0]
    assert k0["velocity_error_mean"] == pytest.approx(np.mean([r["velocity_error"] for r in result.rows if r["k"] == 0]))
    assert "velocity error, m/s" in result.format_summary()
    assert "velocity error, m/s" in format_prior_posterior_table(result.summary)


@pytest.mark.parametrize(
    "env_id", ["PointGoalMeta-v0", "SafePointGoalMeta-v0", "SparsePointGoalMeta-v0", "AntGoalMeta-v0", "PointMazeGoalMeta-v0"]
)
def test_goal_families_record_each_trajectorys_final_distance(env_id: str) -> None:
    """The goal families' measure of the job: the Euclidean distance to the goal at the trajectory's last step, in the
    rows, the summary and both tables."""
    from sb3_pearl.evaluation.scripted import ScriptedPolicy

    env = gym.make(env_id)
    still = ScriptedPolicy(lambda obs: np.zeros(env.action_space.shape), "no action")
    tasks = env.unwrapped.sample_tasks(2, seed=3)
    result = meta_test(still, env, tasks, n_adapt=1, n_repeats=1, seed=0, max_steps=30, trace_keys=("distance",))
    for row, trace in zip(result.rows, result.traces, strict=True):
        assert row["distance"] == trace["distance"][-1]
        if env_id in ("PointGoalMeta-v0", "SafePointGoalMeta-v0", "SparsePointGoalMeta-v0"):  # a still point stays at 0
            assert row["distance"] == pytest.approx(np.linalg.norm(tasks[row["task"]]["goal"]))
    k0 = result.summary[0]
    assert k0["distance_mean"] == pytest.approx(np.mean([r["distance"] for r in result.rows if r["k"] == 0]))
    assert "final goal distance" in result.format_summary()
    assert "final goal distance" in format_prior_posterior_table(result.summary)


def test_ant_goal_distance_is_the_torsos_euclidean_distance_to_the_goal() -> None:
    """AntGoalMeta-v0's ``info["distance"]`` by hand: the torso's planar position against the task's goal."""
    env = gym.make("AntGoalMeta-v0")
    task = {"goal": [1.5, -2.0]}
    env.unwrapped.set_task(task)
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.zeros(env.action_space.shape))
    expected = np.hypot(info["x_position"] - 1.5, info["y_position"] + 2.0)
    assert info["distance"] == pytest.approx(expected)
    assert -info["reward_forward"] == pytest.approx(abs(info["x_position"] - 1.5) + abs(info["y_position"] + 2.0))


def test_callback_evaluations_leave_training_unchanged(tiny_kwargs: dict[str, Any]) -> None:
    """A run with meta-test evaluations trains on the same random numbers as one without: the same weights."""

    def trained(evaluate: bool) -> list[th.Tensor]:
        model = PEARLPlus("MlpPolicy", "SafePointGoalMeta-v0", seed=0, **tiny_kwargs)
        callback = MetaTestCallback(gym.make("SafePointGoalMeta-v0"), eval_freq=60, n_tasks=2, n_adapt=1) if evaluate else None
        model.learn(200, callback=callback)
        return [p.detach().clone() for p in model.policy.parameters()]

    assert all(th.equal(a, b) for a, b in zip(trained(True), trained(False), strict=True))
