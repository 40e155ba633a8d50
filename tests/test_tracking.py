"""Velocity tracking: the split of the per-step velocity error on hand-computed traces, and the command on a run folder."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sb3_pearl import PEARLPlus
from sb3_pearl.evaluation.meta_test import MetaTestResult
from sb3_pearl.evaluation.tracking import main, rerun_competence, velocity_tracking
from tests.conftest import TINY


def _result() -> MetaTestResult:
    tasks = [{"velocity": 1.0}, {"velocity": 2.0}]
    traces = [
        {"task": 0, "repeat": 0, "k": 0, "x_velocity": [5.0, 5.0]},  # k = 0: the prior's, not counted
        {"task": 0, "repeat": 0, "k": 1, "x_velocity": [0.0, 1.0, 2.0, 1.0]},  # mean 1: no mean-speed error
        {"task": 1, "repeat": 0, "k": 1, "x_velocity": [1.0, 1.0]},  # mean 1 for a target of 2, no oscillation
        {"task": 1, "repeat": 0, "k": 2, "x_velocity": [0.0, 2.0]},  # mean 1, oscillating by 1
    ]
    return MetaTestResult(rows=[], summary=[], tasks=tasks, traces=traces)


def test_the_split_by_hand() -> None:
    tracking = velocity_tracking(_result())
    # per trajectory (per-step error, mean-speed error, std): (0.5, 0, sqrt(0.5)), (1, 1, 0), (1, 1, 1)
    assert tracking["n_trajectories"] == 3
    assert tracking["per_step_error"] == pytest.approx((0.5 + 1.0 + 1.0) / 3)
    assert tracking["mean_speed_error"] == pytest.approx(2.0 / 3)
    assert tracking["oscillation"] == pytest.approx((np.sqrt(0.5) + 0.0 + 1.0) / 3)
    # every trajectory walks at 1 m/s whatever its target: slope 0, intercept 1
    assert tracking["slope"] == pytest.approx(0.0, abs=1e-12) and tracking["intercept"] == pytest.approx(1.0)
    task0, task1 = tracking["tasks"]
    assert (task0["target"], task0["mean_speed"], task0["n_trajectories"]) == (1.0, 1.0, 1)
    assert (task1["target"], task1["per_step_error"], task1["mean_speed_error"], task1["n_trajectories"]) == (2.0, 1.0, 1.0, 2)
    assert task1["oscillation"] == pytest.approx(0.5)
    # the prior's trajectory counts from min_k = 0 on
    assert velocity_tracking(_result(), min_k=0)["n_trajectories"] == 4


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
    (run / "result.json").write_text(json.dumps({"spec": spec, "eval_seed": 7, "competence": {"settings": settings}}))
    plot = tmp_path / "tracking.png"
    results = main([str(run), "--plot", str(plot)])
    tracking = results[str(run)]
    assert tracking["n_trajectories"] == 2 and len(tracking["tasks"]) == 2  # k = 1 on two training tasks
    assert [row["target"] for row in tracking["tasks"]] == [t["velocity"] for t in model.train_tasks[:2]]
    assert tracking["per_step_error"] >= tracking["mean_speed_error"]  # |mean(v - v*)| <= mean |v - v*|
    assert "per-step err" in capsys.readouterr().out and plot.stat().st_size > 0
    assert main([str(run), "--json"])[str(run)] == tracking  # the same trajectories: seeded by the run's eval seed
    # the family's own per-step error (the competence criterion's trace, -|v - v*|) is what the split starts from
    rerun = rerun_competence(run)
    criterion = np.mean([-np.mean(t["reward_forward"]) for t in rerun.traces if t["k"] >= 1])
    assert tracking["per_step_error"] == pytest.approx(criterion, rel=1e-6)

    (run / "result.json").write_text(json.dumps({"spec": spec}))
    with pytest.raises(SystemExit):
        main([str(run)])
    assert "no competence settings or eval_seed" in capsys.readouterr().err
