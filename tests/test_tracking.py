"""Velocity tracking: the split of the per-step velocity error on hand-computed traces, and the command on a run folder."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sb3_pearl import PEARLPlus
from sb3_pearl.evaluation.meta_test import MetaTestResult
from sb3_pearl.tracking import main, rerun_competence, velocity_tracking
from tests.conftest import ENV_ID, TINY, tiny_finetune


def _result() -> MetaTestResult:
    tasks = [{"velocity": 1.0}, {"velocity": 2.0}]
    traces = [
        {"task": 0, "repeat": 0, "k": 0, "x_velocity": [5.0, 5.0]},  # k = 0: the prior's, not counted
        {"task": 0, "repeat": 0, "k": 1, "x_velocity": [0.2, 0.6, 1.0, 0.6]},  # mean 0.6, per-step error 0.4
        {"task": 1, "repeat": 0, "k": 1, "x_velocity": [1.1, 1.1]},  # mean 1.1, no oscillation
        {"task": 1, "repeat": 0, "k": 2, "x_velocity": [0.1, 2.1]},  # mean 1.1, oscillating by 1
    ]
    return MetaTestResult(rows=[], summary=[], tasks=tasks, traces=traces)


def test_the_split_by_hand() -> None:
    tracking = velocity_tracking(_result())
    # per trajectory (per-step error, mean-speed error, std): (0.4, 0.4, sqrt(0.08)), (0.9, 0.9, 0), (1.0, 0.9, 1)
    assert tracking["n_trajectories"] == 3
    assert tracking["per_step_error"] == pytest.approx((0.4 + 0.9 + 1.0) / 3)
    assert tracking["mean_speed_error"] == pytest.approx((0.4 + 0.9 + 0.9) / 3)
    assert tracking["oscillation"] == pytest.approx((np.sqrt(0.08) + 0.0 + 1.0) / 3)
    # mean speed = 0.5 x target + 0.1 on every trajectory (one at target 1, two at target 2: the fit is over trajectories)
    assert tracking["slope"] == pytest.approx(0.5) and tracking["intercept"] == pytest.approx(0.1)
    task0, task1 = tracking["tasks"]
    assert (task0["target"], task0["n_trajectories"]) == (1.0, 1) and task0["mean_speed"] == pytest.approx(0.6)
    assert (task1["target"], task1["n_trajectories"]) == (2.0, 2) and task1["mean_speed"] == pytest.approx(1.1)
    assert task1["per_step_error"] == pytest.approx(0.95) and task1["mean_speed_error"] == pytest.approx(0.9)
    assert task1["oscillation"] == pytest.approx(0.5)
    # the prior's trajectory counts from min_k = 0 on
    assert velocity_tracking(_result(), min_k=0)["n_trajectories"] == 4
    # by part of the episode (horizon 4 steps; the two 2-step trajectories reach only the first half)
    # per-step errors: [0.8, 0.4, 0.0, 0.4], [0.9, 0.9], [1.9, 0.1]
    halves = velocity_tracking(_result(), n_parts=2)["parts"]
    assert [(p["first_step"], p["end_step"], p["n_trajectories"]) for p in halves] == [(0, 2, 3), (2, 4, 1)]
    assert halves[0]["error"] == pytest.approx((0.6 + 0.9 + 1.0) / 3) and halves[1]["error"] == pytest.approx(0.2)
    quarters = tracking["parts"]  # the default: 4 parts, one step each here
    assert [p["error"] for p in quarters] == pytest.approx([1.2, 1.4 / 3, 0.0, 0.4])
    assert [p["n_trajectories"] for p in quarters] == [3, 3, 1, 1]
    eighths = velocity_tracking(_result(), n_parts=8)["parts"]  # more parts than steps: the empty ones have no value
    assert [p["error"] is None for p in eighths] == [True, False] * 4
    with pytest.raises(ValueError, match="n_parts must be >= 1"):
        velocity_tracking(_result(), n_parts=0)
    # the episode's horizon, not the longest trajectory: with 8 steps, the second half holds no trajectory at all
    episode = velocity_tracking(_result(), n_parts=2, horizon=8)["parts"]
    assert [(p["first_step"], p["end_step"], p["n_trajectories"]) for p in episode] == [(0, 4, 3), (4, 8, 0)]
    assert episode[0]["error"] == pytest.approx((0.4 + 0.9 + 1.0) / 3) and episode[1]["error"] is None
    with pytest.raises(ValueError, match="more than the horizon 3"):
        velocity_tracking(_result(), horizon=3)
    # one target only: no line
    single = _result()
    single.traces = single.traces[2:]
    assert velocity_tracking(single)["slope"] is None


def test_bad_input_says_what_is_wrong() -> None:
    result = _result()
    with pytest.raises(ValueError, match="no trajectory with k >= 3"):
        velocity_tracking(result, min_k=3)
    result.tasks = [{"goal": 1.0}, {"goal": 2.0}]
    with pytest.raises(ValueError, match="has no 'velocity' entry .* not a velocity family"):
        velocity_tracking(result)


def test_the_command_reruns_the_competence_meta_test(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    model = PEARLPlus("MlpPolicy", "HalfCheetahVelMeta-v0", seed=0, **{**TINY, "num_initial_steps": 30})
    model.learn(30)
    run = tmp_path / "results" / "exp" / "cheetah-vel" / "pearlplus" / "seed0"
    run.mkdir(parents=True)
    model.save(run / "model.zip")
    family = {"name": "cheetah-vel", "env_id": "HalfCheetahVelMeta-v0", "env_kwargs": {}}
    spec = {"experiment": "exp", "family": family, "variant": {"name": "pearlplus", "algo": "pearlplus"}}
    settings = {"n_tasks": 2, "n_repeats": 1, "n_adapt": 1, "deterministic": True}
    criteria = [{"key": "reward_forward", "value": None}]  # the family's criterion, its value not recorded
    record = {"spec": spec, "eval_seed": 7, "competence": {"settings": settings, "criteria": criteria}}
    (run / "result.json").write_text(json.dumps(record))
    plot = tmp_path / "tracking.png"
    results = main([str(run), "--plot", str(plot), "--bar", "0.3"])
    tracking = results[str(run)]
    assert tracking["n_trajectories"] == 2 and len(tracking["tasks"]) == 2  # k = 1 on two training tasks
    assert [row["target"] for row in tracking["tasks"]] == [t["velocity"] for t in model.train_tasks[:2]]
    out = capsys.readouterr().out
    assert "per-step err" in out and "by part of the episode: steps 0-" in out and plot.stat().st_size > 0
    rerun = rerun_competence(run)
    # the cheetah never falls: every trajectory runs the horizon, and the four equal parts average to the per-step error
    assert {len(t["x_velocity"]) for t in rerun.traces if t["k"] >= 1} == {200}
    assert np.mean([p["error"] for p in tracking["parts"]]) == pytest.approx(tracking["per_step_error"])
    assert main([str(run), "--json"])[str(run)] == tracking  # the same trajectories: seeded by the run's eval seed
    # the family's own per-step error (the competence criterion's trace, -|v - v*|) is what the split starts from
    criterion = np.mean([-np.mean(t["reward_forward"]) for t in rerun.traces if t["k"] >= 1])
    assert tracking["per_step_error"] == pytest.approx(criterion, rel=1e-6)
    assert tracking["committed_per_step_error"] is None  # the record holds no criterion value

    # against the value a result.json holds: silent when the rerun reproduces it, a warning when it does not
    for value, warned in ((criterion, False), (criterion + 0.5, True)):
        record["competence"]["criteria"] = [{"key": "reward_forward", "value": value}]
        (run / "result.json").write_text(json.dumps(record))
        assert main([str(run), "--json"])[str(run)]["committed_per_step_error"] == value
        assert ("is not result.json's" in capsys.readouterr().err) is warned

    (run / "result.json").write_text(json.dumps({"spec": spec}))
    with pytest.raises(SystemExit):
        main([str(run)])
    assert "no competence settings or eval_seed" in capsys.readouterr().err


def _write_run(run: Path, model: object, algo: str, env_id: str, criterion_key: str = "reward_forward") -> None:
    run.mkdir(parents=True)
    model.save(run / "model.zip")  # type: ignore[attr-defined]
    spec = {"family": {"name": "f", "env_id": env_id, "env_kwargs": {}}, "variant": {"name": algo, "algo": algo}}
    settings = {"n_tasks": 1, "n_repeats": 1, "n_adapt": 1, "deterministic": True}
    competence = {"settings": settings, "criteria": [{"key": criterion_key, "value": None}]}
    (run / "result.json").write_text(json.dumps({"spec": spec, "eval_seed": 7, "competence": competence}))


def test_the_command_takes_a_run_of_any_algorithm_and_refuses_other_input_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Guards against: tracking refused every run not of PEARL / PEARL+ ("the diagnostics need one"), and a train.py
    run folder or a model zip ended in a FileNotFoundError / NotADirectoryError traceback; a run of a family without a
    velocity (SafePoint, Highway-Merge) was refused only after its whole competence meta-test had run."""
    finetune = tiny_finetune("HalfCheetahVelMeta-v0", adapt_gradient_steps=2)
    finetune.learn(20)
    run = tmp_path / "finetune" / "seed0"
    _write_run(run, finetune, "finetune", "HalfCheetahVelMeta-v0")
    tracking = main([str(run), "--json"])[str(run)]
    assert tracking["n_trajectories"] == 1 and tracking["tasks"][0]["target"] == finetune.train_tasks[0]["velocity"]
    capsys.readouterr()

    other = tmp_path / "safe" / "seed0"
    _write_run(other, tiny_finetune(), "finetune", ENV_ID, criterion_key="distance")
    zoo_folder = tmp_path / "logs" / "finetune" / "SafePointGoalMeta-v0_1"
    zoo_folder.mkdir(parents=True)
    for given, said in (
        (other, "is not a velocity family"),
        (run / "model.zip", "a file: tracking reruns the competence meta-test a finished harness run recorded"),
        (zoo_folder, "no result.json and model.zip in it: tracking reruns"),
    ):
        with pytest.raises(SystemExit):
            main([str(given)])
        err = capsys.readouterr().err
        assert said in err and "Traceback" not in err, err
