"""train.py / enjoy.py / plots end to end on a tiny budget: their flags, run folders, plans and the errors checked
before training (the one-line answers to other mistakes are in tests/test_cli_errors.py).

``python train.py`` and ``python enjoy.py`` run as separate processes once each, as users run them (the ``trained``
fixture, the harness-run replay); the other commands call the same entry points in-process
(:func:`tests.conftest.run_in_process`: no interpreter start per command).
"""

from __future__ import annotations

import csv
import json
import math
import multiprocessing
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import gymnasium as gym
import pytest
import yaml

from sb3_pearl import PEARL, PEARLPlus
from sb3_pearl.budgets import load_budget
from sb3_pearl.evaluation.callbacks import MetaTestCallback
from sb3_pearl.evaluation.figures import main as plots_main
from sb3_pearl.evaluation.meta_test import MetaTestResult
from sb3_pearl.evaluation.progress import TrainingProgressCallback, format_duration
from sb3_pearl.evaluation.statistics import format_prior_posterior_table, summarize
from sb3_pearl.finetune import FineTune
from sb3_pearl.zoo import MetaExperimentManager, constructor_kwargs, register_algos
from sb3_pearl.zoo import enjoy as enjoy_main
from sb3_pearl.zoo import train as train_main
from sb3_pearl.zoo.budget import budget_hyperparams, faster_option
from sb3_pearl.zoo.safe_config import load_run_yaml
from tests.conftest import (
    ENV_ID,
    TINY_ZOO_PARAMS,
    Completed,
    run_in_process,
)

ROOT = Path(__file__).resolve().parent.parent
# kl_weight / latent_dim check that -params reach the model.
TINY_PARAMS = [*TINY_ZOO_PARAMS, "kl_weight:0.37", "latent_dim:3"]


def run(script: str, *args: str, check: bool = True, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    proc = subprocess.run(
        [sys.executable, *([script] if script.startswith("-") else [str(ROOT / script)]), *args],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    if check and proc.returncode != 0:
        raise AssertionError(f"{script} {' '.join(args)} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return proc


def train_args(folder: Path, algo: str, *extra: str, params: list[str] = TINY_PARAMS) -> list[str]:
    return [
        *("--algo", algo, "--env", ENV_ID, "-f", str(folder), "--seed", "1", "--num-threads", "1"),
        *("-n", "200", "--eval-freq", "100", "--eval-episodes", "2"),
        *extra,
        "-params",
        *params,
    ]


def train(
    folder: Path, algo: str = "pearlplus", *extra: str, params: list[str] = TINY_PARAMS, check: bool = True
) -> Completed:
    """train.py's entry point in-process on the tiny budget."""
    return run_in_process(train_main, *train_args(folder, algo, *extra, params=params), check=check)


def enjoy(*args: str, check: bool = True) -> Completed:
    """enjoy.py's entry point in-process."""
    return run_in_process(enjoy_main, *args, check=check)


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``python train.py ...`` as a user runs it: a separate process."""
    folder = tmp_path_factory.mktemp("logs")
    run("train.py", *train_args(folder, "pearlplus"))
    return folder


def test_train_writes_zoo_layout_and_meta_test(trained: Path) -> None:
    run_dir = trained / "pearlplus" / f"{ENV_ID}_1"
    for name in (
        f"{ENV_ID}.zip",
        "best_model.zip",
        "meta_test.csv",
        "meta_test.json",
        "adaptation.png",
        "meta_test_history.csv",
    ):
        assert (run_dir / name).is_file(), name
    for name in ("config.yml", "args.yml", "command.txt"):
        assert (run_dir / ENV_ID / name).is_file(), name
    lines = (run_dir / "meta_test.csv").read_text().splitlines()
    assert lines[0] == "task,repeat,k,return,cost,length,violated,distance"  # distance: the goal family's measure
    assert len(lines) == 1 + 3 * 3  # 3 saved test tasks, k = 0..2
    history = (run_dir / "meta_test_history.csv").read_text().splitlines()
    assert len(history) == 1 + 2 * 3  # evaluations at 100 and 200 steps, k = 0..2
    with open(run_dir / ENV_ID / "config.yml") as file:
        config = yaml.load(file, Loader=yaml.UnsafeLoader)
    assert config["kl_weight"] == 0.37


def test_zoo_meta_test_is_the_harness_meta_test(trained: Path) -> None:
    """One meta-test: train.py's meta_test.csv / .json hold the numbers the harness's held-out phase gives the same model."""
    import gymnasium as gym

    from sb3_pearl.evaluation.held_out import DEFAULT_EVAL_SEED, held_out_record

    run_dir = trained / "pearlplus" / f"{ENV_ID}_1"
    model = PEARLPlus.load(run_dir / f"{ENV_ID}.zip")
    settings = {"n_adapt": 2, "n_repeats": 1, "n_tasks": 3, "deterministic": True}  # TINY_ZOO_PARAMS' meta_test
    harness = held_out_record(model, gym.make(ENV_ID), settings, DEFAULT_EVAL_SEED, {})
    with open(run_dir / "meta_test.csv") as file:
        zoo_rows = list(csv.DictReader(file))
    assert len(zoo_rows) == len(harness["rows"]) == 3 * 3
    for zoo_row, harness_row in zip(zoo_rows, harness["rows"]):
        assert {key: float(value) for key, value in zoo_row.items()} == pytest.approx(
            {key: float(harness_row[key]) for key in zoo_row}, abs=1e-9
        )
    zoo = json.loads((run_dir / "meta_test.json").read_text())
    assert zoo["summary"] == harness["summary"] and zoo["tasks"] == harness["tasks"]
    assert zoo["config"]["eval_seed"] == zoo["config"]["crn_seed"] == DEFAULT_EVAL_SEED


def test_params_reach_the_saved_model(trained: Path) -> None:
    model = PEARLPlus.load(trained / "pearlplus" / f"{ENV_ID}_1" / f"{ENV_ID}.zip")
    assert model.kl_weight == 0.37
    assert model.latent_dim == 3
    assert len(model.test_tasks) == 3 and len(model.train_tasks) == 4
    assert model.prior_coef == 0.1  # from zoo_hyperparams/pearlplus.yml


def test_enjoy_prints_prior_and_posterior(trained: Path, tmp_path: Path) -> None:
    plot = tmp_path / "enjoy.png"
    proc = enjoy(
        *("--algo", "pearlplus", "--env", ENV_ID, "-f", str(trained), "--no-render"),
        *("--n-tasks", "2", "--n-adapt", "2", "--plot", str(plot)),
    )
    out = proc.stdout
    assert out.count("Task ") == 2
    assert out.count("  prior ") == 2 and out.count("  posterior ") == 4  # the rows of the task tables
    assert "Summary over tasks: the prior (k = 0) and the posterior after k = 1..2, 2 trajectories each" in out
    header = next(line for line in out.splitlines() if line.strip().startswith("k = 0 (prior)"))  # the ks side by side
    assert header.split() == ["k", "=", "0", "(prior)", "k", "=", "1", "k", "=", "2"]
    assert "violations, % [95%]" in out and "return, mean +- std" in out
    assert plot.is_file() and (tmp_path / "enjoy_violations.png").is_file()
    best = enjoy("--algo", "pearlplus", "--env", ENV_ID, "-f", str(trained), "--no-render", "--load-best", "--n-adapt", "1")
    assert "best_model.zip" in best.stdout


def test_plots_cli(trained: Path, tmp_path: Path) -> None:
    run_dir = trained / "pearlplus" / f"{ENV_ID}_1"
    out = tmp_path / "cmp.png"
    proc = run_in_process(plots_main, str(run_dir), str(run_dir / "meta_test.json"), "-o", str(out), "--labels", "a", "b")
    assert out.is_file() and (tmp_path / "cmp_violations.png").is_file()
    assert "Saved" in proc.stdout


def test_pearl_subproc_checkpoints_progress(tmp_path: Path) -> None:
    train(tmp_path, "pearl", "--vec-env", "subproc", "--save-freq", "100", "-P", params=[*TINY_PARAMS, "n_envs:2"])
    run_dir = tmp_path / "pearl" / f"{ENV_ID}_1"
    assert (run_dir / "meta_test.json").is_file()
    # resumable checkpoints at the start of an iteration (iteration 0: 4 tasks x 30 steps = 120), with the buffer
    assert (run_dir / "rl_model_120_steps.zip").is_file() and (run_dir / "rl_model_replay_buffer_120_steps.pkl").is_file()
    model = PEARL.load(run_dir / f"{ENV_ID}.zip")
    assert not hasattr(model, "prior_coef") and model.kl_weight == 0.37  # a PEARL model: no prior term


def test_optimize_uses_the_meta_test(tmp_path: Path) -> None:
    proc = train(
        tmp_path,
        "pearlplus",
        *("-optimize", "--n-trials", "1", "--n-evaluations", "1", "--no-optim-plots", "--n-startup-trials", "1"),
        params=[*TINY_PARAMS, "num_train_steps_per_itr:2"],
    )
    (report,) = (tmp_path / "pearlplus").glob("report_*.csv")  # Optuna's log goes to logging, the report to a file
    with open(report) as file:
        (trial,) = list(csv.DictReader(file))
    assert trial["state"] == "COMPLETE" and math.isfinite(float(trial["value"]))
    assert "params_prior_coef" in trial  # the PEARL+ sampler's parameters
    assert "prior_coef" in proc.stdout


def test_unknown_algo_and_env(tmp_path: Path) -> None:
    proc = run_in_process(train_main, "--algo", "nope", "--env", ENV_ID, "-f", str(tmp_path), check=False)
    assert proc.returncode != 0 and "invalid choice: 'nope'" in proc.stderr and "pearlplus" in proc.stderr
    proc = run_in_process(train_main, "--algo", "pearl", "--env", "SafePointGoalMta-v0", "-f", str(tmp_path), check=False)
    assert proc.returncode != 0 and "not found in gym registry" in proc.stderr and ENV_ID in proc.stderr


def test_yaml_key_the_algorithm_does_not_take(tmp_path: Path) -> None:
    with open(ROOT / "zoo_hyperparams" / "pearl.yml") as file:
        entry = yaml.safe_load(file)[ENV_ID]
    conf = tmp_path / "bad.yml"
    conf.write_text(yaml.safe_dump({ENV_ID: {**entry, "warp_factor": 9}}))
    proc = run_in_process(
        train_main, "--algo", "pearl", "--env", ENV_ID, "-f", str(tmp_path), "-conf", str(conf), "-n", "10", check=False
    )
    assert proc.returncode != 0
    assert "PEARL does not take the hyperparameter(s) 'warp_factor'" in proc.stderr
    assert "help(PEARL)" in proc.stderr  # where the accepted ones are (not a 1,000-character list)
    # PEARL refuses the PEARL+ prior term before any env is built
    proc = train(tmp_path, "pearl", params=["prior_coef:0.2"], check=False)
    assert proc.returncode != 0 and "hyperparameter(s) 'prior_coef'" in proc.stderr


def test_held_out_tasks_that_are_training_tasks_are_refused_before_training(tmp_path: Path) -> None:
    """--seed equal to the meta-test's eval seed draws the test tasks among the training tasks: exit 2, nothing trained."""
    proc = run_in_process(
        train_main,
        *("--algo", "pearl", "--env", ENV_ID, "-f", str(tmp_path), "--seed", "10000", "-n", "200", "-params", *TINY_PARAMS),
        check=False,
    )
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "drawn with eval_seed 10000 are training tasks" in proc.stderr and "Traceback" not in proc.stderr
    assert not list(tmp_path.rglob("*.zip"))
    bad_seed = [*TINY_PARAMS, "meta_test:dict(eval_seed=-1)"]
    proc = train(tmp_path, "pearl", params=bad_seed, check=False)
    assert proc.returncode == 2 and "eval_seed must be an integer >= 0" in proc.stderr


@pytest.mark.parametrize(
    "meta_test, message",
    [
        ("dict(n_tasks=0)", "meta_test n_tasks must be None (the model's test tasks) or an integer >= 1, got 0"),
        ("dict(deterministic='False')", "meta_test deterministic must be True or False, got 'False'"),
        ("dict(n_adapt=-1)", "meta_test n_adapt must be an integer >= 0"),
        ("dict(n_repeats=0)", "meta_test n_repeats must be an integer >= 1"),
    ],
)
def test_invalid_meta_test_settings_are_refused_before_training(tmp_path: Path, meta_test: str, message: str) -> None:
    """A meta_test value out of range is a one-line error (exit 2) before anything is trained, not replaced by a default
    (n_tasks=0 gave the model's test tasks, deterministic='False' gave True) nor found after training (n_adapt=-1)."""
    proc = train(tmp_path, "pearl", params=[*TINY_PARAMS, f"meta_test:{meta_test}"], check=False)
    assert proc.returncode == 2 and message in proc.stderr and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert not list(tmp_path.rglob("*.zip"))


def test_params_meta_test_overrides_only_its_keys(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """-params "meta_test:dict(n_tasks=3)" overrides that key of the YAML entry's meta_test and keeps the others; a
    value the YAML gives out of range is refused whatever -params adds."""
    from sb3_pearl.zoo import MetaExperimentManager
    from sb3_pearl.zoo.usage import UsageError

    def stop(manager: MetaExperimentManager) -> None:  # the settings as they reach the run, before any folder or env
        raise UsageError(f"meta_test settings {sorted(manager.meta_test_kwargs.items())}")

    monkeypatch.setattr(MetaExperimentManager, "create_log_folder", stop)
    with open(ROOT / "zoo_hyperparams" / "pearl.yml") as file:
        entry = yaml.safe_load(file)[ENV_ID]
    conf = tmp_path / "conf.yml"
    conf.write_text(yaml.safe_dump({ENV_ID: {**entry, "meta_test": {"n_adapt": 1, "n_repeats": 4, "deterministic": False}}}))
    argv = ["--algo", "pearl", "--env", ENV_ID, "-f", str(tmp_path), "-conf", str(conf), "-n", "10"]
    proc = run_in_process(train_main, *argv, "-params", "meta_test:dict(n_tasks=3)", check=False)
    expected = {"deterministic": False, "eval_seed": 10000, "n_adapt": 1, "n_repeats": 4, "n_tasks": 3}
    assert f"meta_test settings {sorted(expected.items())}" in proc.stderr, proc.stderr[-2000:]
    conf.write_text(yaml.safe_dump({ENV_ID: {**entry, "meta_test": {"n_adapt": -1}}}))
    proc = run_in_process(train_main, *argv, "-params", "meta_test:dict(n_tasks=3)", check=False)
    assert proc.returncode == 2 and "meta_test n_adapt must be an integer >= 0" in proc.stderr, proc.stderr[-2000:]


def test_enjoy_replays_a_committed_harness_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--run: a results/ folder replays without training, on the run's own test tasks and draws (its result.json rows)."""
    folder = ROOT / "results" / "safe-point" / "safe-point" / "alpha-0.1" / "seed0"
    result = json.loads((folder / "result.json").read_text())
    args = ["--env", ENV_ID, "--run", str(folder), "--no-render", "--n-tasks", "2", "--n-adapt", "2"]
    out = run("enjoy.py", "--algo", "pearlplus", *args).stdout
    assert f"eval seed {result['eval_seed']}" in out
    replayed = [row for row in result["meta_test"]["rows"] if row["task"] < 2 and row["repeat"] == 0 and row["k"] <= 2]
    for row in replayed:
        assert f"{row['return']:>10.2f}" in out  # the committed number, from model.zip alone
    # after the replay, one table: the prior (k = 0) and the posteriors (k = 1, 2) side by side, the committed numbers
    assert format_prior_posterior_table(summarize(replayed)) in out
    from sb3_pearl.zoo import enjoy  # the refusals in-process: they come before any model or env is built

    for argv, message in (
        (["--algo", "pearl", *args], "is a pearlplus model: pass --algo pearlplus"),
        (["--algo", "pearlplus", "--env", "PointGoalMeta-v0", *args[2:]], "not on PointGoalMeta-v0: pass --env " + ENV_ID),
        (["--algo", "pearlplus", *args[:2], "--run", str(tmp_path), "--no-render"], "not a finished harness run"),
        (["--algo", "pearlplus", *args[:2], "--run", str(folder / "model.zip")], "a file; pass the run's folder"),
        (["--algo", "pearlplus", *args, "--load-best"], "--load-best choose a model of a train.py run folder instead"),
        (["--algo", "pearlplus", *args, "-f", "logs2", "--exp-id", "2"], "-f, --exp-id choose a model of a train.py"),
        (["--algo", "pearlplus", *args[:2], "-f", str(folder)], f"replay it with --run {folder}"),
    ):
        with pytest.raises(SystemExit) as exit_info:
            enjoy(argv)
        assert exit_info.value.code == 2 and message in capsys.readouterr().err


def test_enjoy_missing_folder_and_other_env(trained: Path, tmp_path: Path) -> None:
    proc = enjoy("--algo", "pearlplus", "--env", ENV_ID, "-f", str(tmp_path / "nowhere"), "--no-render", check=False)
    assert proc.returncode != 0 and "folder was not found" in proc.stderr
    # a run folder renamed as if it held a PointGoalMeta-v0 model
    other = tmp_path / "logs" / "pearlplus" / "PointGoalMeta-v0_1"
    shutil.copytree(trained / "pearlplus" / f"{ENV_ID}_1", other)
    (other / f"{ENV_ID}.zip").rename(other / "PointGoalMeta-v0.zip")
    proc = enjoy("--algo", "pearlplus", "--env", "PointGoalMeta-v0", "-f", str(tmp_path / "logs"), "--no-render", check=False)
    assert proc.returncode != 0 and f"was trained on {ENV_ID}, not on PointGoalMeta-v0" in proc.stderr


@pytest.mark.parametrize("recorded", [True, False])
def test_enjoy_refuses_a_model_of_another_family_without_args_yml(tmp_path: Path, recorded: bool) -> None:
    """No args.yml beside the model: its task family (recorded in the zip; for an older zip, its training tasks checked
    with the env's task_error) is checked against --env, one line naming both, before any rollout."""
    model = PEARLPlus("MlpPolicy", "PointGoalMeta-v0", n_train_tasks=2, n_test_tasks=1, seed=0)  # spaces as SafePointGoal
    if not recorded:
        model.task_family = None  # a zip saved before the family was recorded
    folder = tmp_path / "pearlplus" / f"{ENV_ID}_1"
    model.save(folder / f"{ENV_ID}.zip")
    proc = enjoy("--algo", "pearlplus", "--env", ENV_ID, "-f", str(tmp_path), "--no-render", "--n-tasks", "1", check=False)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    line = proc.stderr.strip().splitlines()[-1]
    assert f"{ENV_ID}.zip was not trained on {ENV_ID}" in line
    assert ("trained on PointGoalMetaEnv tasks, the env is a SafePointGoalMetaEnv" if recorded else "train_tasks[0]") in line
    assert "Task 0" not in proc.stdout  # nothing rolled out


def test_every_yaml_entry_is_valid() -> None:
    """Every key of zoo_hyperparams/<algo>.yml is a constructor kwarg or a zoo key, for every registered family."""
    from sb3_pearl import MAML, FineTune, Oracle
    from sb3_pearl.envs import FAMILIES
    from sb3_pearl.zoo import ZOO_SPECIAL_KEYS

    register_algos()
    algos = (("pearl", PEARL), ("pearlplus", PEARLPlus), ("finetune", FineTune), ("maml", MAML), ("oracle", Oracle))
    for algo, cls in algos:
        with open(ROOT / "zoo_hyperparams" / f"{algo}.yml") as file:
            entries = yaml.safe_load(file)
        assert set(FAMILIES) <= set(entries), f"{algo}.yml misses {sorted(set(FAMILIES) - set(entries))}"
        for env_id, entry in entries.items():
            unknown = set(entry) - constructor_kwargs(cls) - ZOO_SPECIAL_KEYS
            assert not unknown, f"{algo}.yml {env_id}: {unknown}"
            assert entry["n_timesteps"] > 0
            if "learning_rate" in entry:
                assert isinstance(entry["learning_rate"], float)


def test_train_and_enjoy_the_oracle(tmp_path: Path) -> None:
    """``train.py --algo oracle`` trains the task-aware SAC (its observation is the family's plus the task vector) and
    meta-tests it like the meta-learners, with the family's measure beside return and violations; ``enjoy.py`` replays
    it on held-out tasks."""
    from sb3_pearl import Oracle

    params = ["learning_starts:50", "batch_size:16", "policy_kwargs:dict(net_arch=[16])", "n_train_tasks:4"]
    params += ["n_test_tasks:2", "meta_test:dict(n_adapt=1)"]
    args = ("--algo", "oracle", "--env", ENV_ID, "-f", str(tmp_path), "--seed", "1", "--num-threads", "1", "-n", "200")
    run_in_process(train_main, *args, "-params", *params)
    run_dir = tmp_path / "oracle" / f"{ENV_ID}_1"
    model = Oracle.load(run_dir / f"{ENV_ID}.zip")
    raw_dim = gym.make(ENV_ID).observation_space.shape[0]
    assert model.observation_space.shape[0] > raw_dim  # the task vector appended
    lines = (run_dir / "meta_test.csv").read_text().splitlines()
    assert lines[0] == "task,repeat,k,return,cost,length,violated,distance" and len(lines) == 1 + 2 * 2
    out = enjoy("--algo", "oracle", "--env", ENV_ID, "-f", str(tmp_path), "--no-render", "--n-tasks", "1", "--n-adapt", "1")
    assert out.stdout.count("Task ") == 1 and "violations, % [95%]" in out.stdout and "distance" in out.stdout


def test_a_short_run_meta_tests_on_a_few_tasks(tmp_path: Path) -> None:
    """A short run is meta-tested quickly: -n under a tenth of the entry's n_timesteps meta-tests on at most 5 held-out
    tasks instead of the model's n_test_tasks (8 here), and says so in the plan line; the meta_test key's n_tasks still
    decides."""
    params = [*TINY_ZOO_PARAMS, "n_test_tasks:8"]
    short = train(tmp_path / "short", params=params)
    assert "the final meta-test: at most 5 tasks x 1 prior draw(s) x 3 trajectories (a short run" in short.stdout
    rows = json.loads((tmp_path / "short" / "pearlplus" / f"{ENV_ID}_1" / "meta_test.json").read_text())["rows"]
    assert len({row["task"] for row in rows}) == 5 and len(rows) == 5 * 3
    chosen = train(tmp_path / "chosen", params=[*params, 'meta_test:"dict(n_tasks=7, n_adapt=2)"'])
    assert "the final meta-test: 7 tasks x 1 prior draw(s) x 3 trajectories (a short run" in chosen.stdout
    rows = json.loads((tmp_path / "chosen" / "pearlplus" / f"{ENV_ID}_1" / "meta_test.json").read_text())["rows"]
    assert len({row["task"] for row in rows}) == 7
    # a budget preset's meta-test is capped too (cpu: 20 tasks x 10 prior draws; 90k env steps against -n 200)
    params = [param for param in TINY_ZOO_PARAMS if not param.startswith("meta_test")]
    budget = train(tmp_path / "budget", "pearlplus", "--budget", "cpu", params=params)
    assert "the final meta-test: 5 tasks x 1 prior draw(s) x 6 trajectories (a short run" in budget.stdout
    rows = json.loads((tmp_path / "budget" / "pearlplus" / f"{ENV_ID}_1" / "meta_test.json").read_text())["rows"]
    assert len(rows) == 5 * 1 * 6
    # with -i (not --resume), -n counts steps added to a trained model: not a short run
    model = tmp_path / "short" / "pearlplus" / f"{ENV_ID}_1" / f"{ENV_ID}.zip"
    more = train(tmp_path / "more", "pearlplus", "-i", str(model), params=params)
    assert "the final meta-test: the model's test tasks x 1 prior draw(s)" in more.stdout and "a short run" not in more.stdout


def test_params_n_envs_below_one_is_refused(tmp_path: Path) -> None:
    proc = train(tmp_path, "pearl", params=[*TINY_PARAMS, "n_envs:0"], check=False)
    assert proc.returncode == 2 and "n_envs must be an integer >= 1, got 0 (in -params)" in proc.stderr, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr and not list(tmp_path.rglob("*.zip"))


@pytest.mark.parametrize(
    "content, message",
    [
        ("[1, 2]", "holds a list: it must hold a mapping of env ids to hyperparameter entries"),
        ("", "holds nothing (the file is empty): it must hold a mapping of env ids to hyperparameter entries"),
        ("a: [", "is not valid YAML (expected the node content, but found '<stream end>' at line 1, column 5)"),
        (f"{ENV_ID}: 5", f"the entry {ENV_ID} must be a mapping of hyperparameters, got 5"),
    ],
)
def test_conf_file_that_is_not_a_mapping_is_refused(tmp_path: Path, content: str, message: str) -> None:
    conf = tmp_path / "conf.yml"
    conf.write_text(content)
    argv = ["--algo", "pearl", "--env", ENV_ID, "-f", str(tmp_path), "-conf", str(conf), "-n", "10"]
    proc = run_in_process(train_main, *argv, check=False)
    assert proc.returncode == 2 and f"-conf {conf}" in proc.stderr and message in proc.stderr, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


# ----------------------------------------------------------------------------------------------
# Run folders: reserved atomically; a refused set-up leaves none behind
# ----------------------------------------------------------------------------------------------
def _train_at_the_barrier(barrier: Any, logs: str, seed: int) -> None:  # a forked child: train.py's entry point
    barrier.wait(timeout=60)
    argv = ["--algo", "pearlplus", "--env", ENV_ID, "-f", logs, "--seed", str(seed), "-n", "60", "--num-threads", "1"]
    argv += ["--eval-freq", "-1", "-params", *TINY_ZOO_PARAMS]
    os._exit(run_in_process(train_main, *argv, check=False).returncode)


def test_runs_started_together_on_one_folder_each_get_their_own(tmp_path: Path) -> None:
    context = multiprocessing.get_context("fork")
    seeds = (1, 2, 3)
    barrier = context.Barrier(len(seeds))
    children = [context.Process(target=_train_at_the_barrier, args=(barrier, str(tmp_path), seed)) for seed in seeds]
    for child in children:
        child.start()
    for child in children:
        child.join(timeout=240)
    assert [child.exitcode for child in children] == [0, 0, 0]
    runs = sorted((tmp_path / "pearlplus").iterdir())
    assert [run.name for run in runs] == [f"{ENV_ID}_{n}" for n in (1, 2, 3)]  # guards against: 2 or 3 runs in one folder
    found = set()
    for run in runs:
        seed = load_run_yaml(run / ENV_ID / "args.yml")["seed"]
        found.add(seed)
        assert PEARLPlus.load(run / f"{ENV_ID}.zip").seed == seed
        monitor = (run / "0.monitor.csv").read_text().splitlines()
        assert sum(line.startswith("#") for line in monitor) == 1  # one writer
    assert found == set(seeds)


def test_a_refused_hyperparameter_leaves_no_run_folder(tmp_path: Path) -> None:
    argv = ["--algo", "pearlplus", "--env", ENV_ID, "-f", str(tmp_path), "--seed", "1", "-params", "latent_dim:-3"]
    refused = run_in_process(train_main, *argv, check=False)
    assert refused.returncode == 2 and "latent_dim" in refused.stderr
    assert not any((tmp_path / "pearlplus").iterdir())  # guards against: <EnvId>_1 with its monitor file and config


def test_enjoy_skips_a_newer_run_folder_without_a_model(tmp_path: Path) -> None:
    """A run killed before its first save (SIGKILL: nothing can clean up) left <env>_2 without a model; <env>_1 has one.
    Guards against: 'No model found ... <env>_2/<env>.zip'."""
    runs = tmp_path / "pearlplus"
    PEARLPlus("MlpPolicy", ENV_ID, n_train_tasks=2, n_test_tasks=1, seed=0).save(runs / f"{ENV_ID}_1" / f"{ENV_ID}.zip")
    (runs / f"{ENV_ID}_2" / ENV_ID).mkdir(parents=True)
    args = ("--algo", "pearlplus", "--env", ENV_ID, "-f", str(tmp_path), "--no-render", "--n-tasks", "1", "--n-adapt", "0")
    proc = run_in_process(enjoy_main, *args)
    assert (
        f"Loading the latest run with a model, {runs / f'{ENV_ID}_1'}: {ENV_ID}_2 holds none (a run stopped before its "
        "first save; --exp-id chooses)" in proc.stdout
    )
    refused = run_in_process(enjoy_main, *args, "--exp-id", "2", check=False)  # an explicit choice is kept
    assert refused.returncode == 2 and f"No model found for pearlplus on {ENV_ID}" in refused.stderr


def test_n_timesteps_takes_the_yaml_notation() -> None:
    """``-n 2e3`` as the YAML files write ``2e6``; rl_zoo3's int parser gets ``2000``."""
    from sb3_pearl.zoo.usage import check_n_timesteps

    assert check_n_timesteps(["--algo", "pearl", "-n", "2e3"]) == ["--algo", "pearl", "-n", "2000"]
    assert check_n_timesteps(["--n-timesteps=2_000"]) == ["--n-timesteps=2000"]


# ----------------------------------------------------------------------------------------------
# The plan and the ETA of a run; --budget takes the preset's entry
# ----------------------------------------------------------------------------------------------
def test_plan_eta_and_the_slow_run_hint(tiny_kwargs: dict[str, Any], capsys: pytest.CaptureFixture[str]) -> None:
    model = PEARLPlus("MlpPolicy", "PointGoalMeta-v0", seed=0, device="cpu", **tiny_kwargs)
    plan = model.training_plan(400)
    # iteration 0: 60 steps x 4 tasks, then iterations of 2 x (30 + 10 + 30) = 140 steps: 240 + 140 + 20 (partial)
    assert (plan.env_steps, plan.initial_steps, plan.first_updates, plan.gradient_steps) == (400, 240, 5, 5 + 5 + 1)
    meta_test_callback = MetaTestCallback(gym.make("PointGoalMeta-v0"), eval_freq=300, n_tasks=2, n_adapt=1, verbose=1)
    progress = TrainingProgressCallback(progress_bar=True, slow_hint="Faster: the HINT.", slow_after_s=0.0)
    model.learn(400, callback=[progress, meta_test_callback])
    assert model._n_updates == plan.gradient_steps  # the plan counts what learn() does
    assert model.gradient_step_callback is None  # the progress hook is removed after training (and never saved)
    out = capsys.readouterr().out
    assert "Initial collection: the first 240 env steps only collect data (iteration 0: 60 steps" in out
    assert "First iteration: 240 env steps in " in out and "5 gradient steps in " in out
    assert "ETA of the whole run: " in out and "(160 env steps and 6 gradient steps to go)" in out
    assert "This run takes more than 0.0 s on a CPU. Faster: the HINT." in out
    assert "Meta-test num_timesteps=300 over 2 test tasks x 1 repeat(s)" in out  # the in-training line says how many


def test_finetune_plan_counts_sac_updates() -> None:
    model = FineTune(
        "MlpPolicy",
        "PointGoalMeta-v0",
        learning_starts=50,
        batch_size=16,
        n_train_tasks=4,
        n_test_tasks=2,
        policy_kwargs=dict(net_arch=[16]),
        seed=0,
    )
    plan = model.training_plan(120)
    assert plan is not None and (plan.gradient_steps, plan.initial_steps) == (70, 50)
    model.learn(120)
    assert model._n_updates == plan.gradient_steps


def test_budget_flag_takes_the_preset_entry() -> None:
    entry = budget_hyperparams("cpu", "Walker2dVelMeta-v0", "maml")
    budget = load_budget("cpu", "walker2d-vel", "maml")
    assert entry["n_timesteps"] == budget["n_timesteps"] and entry["meta_test"] == budget["meta_test"]
    assert entry["policy_kwargs"] == {"net_arch": [64, 64], "activation_fn": "tanh"}  # the preset's plain data, no eval
    assert entry["meta_batch_size"] == budget["kwargs"]["meta_batch_size"]
    hint = faster_option("AntVelMeta-v0", "pearlplus", None)
    assert "--budget cpu" in hint and f"{load_budget('cpu', 'ant3d-vel', 'pearlplus')['n_timesteps']:,} env steps" in hint
    assert faster_option("PointGoalMeta-v0", "pearl", None).startswith("No CPU-sized budget exists for PointGoalMeta-v0")
    assert format_duration(2 * 86_400 + 11 * 3600) == "2 d 11 h"


# ----------------------------------------------------------------------------------------------
# Plots without -o go into the run folder
# ----------------------------------------------------------------------------------------------
def test_plots_without_output_write_into_the_run_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from sb3_pearl.plots import main as plots_main

    rows = [
        {"task": t, "repeat": 0, "k": k, "return": float(k - t), "cost": 0.0, "length": 20, "violated": False}
        for t in range(2)
        for k in range(2)
    ]
    run_dir = tmp_path / "logs" / "pearl" / f"{ENV_ID}_1"
    run_dir.mkdir(parents=True)
    MetaTestResult(rows=rows, summary=summarize(rows), config={"algo": "pearl", "n_adapt": 1}).to_json(
        run_dir / "meta_test.json"
    )
    monkeypatch.chdir(tmp_path)
    plots_main([str(run_dir)])
    assert (run_dir / "plots.png").is_file() and (run_dir / "plots_violations.png").is_file()
    assert not list(tmp_path.glob("*.png"))


def test_budget_preset_policy_kwargs_reach_the_model_without_eval(tmp_path: Path) -> None:
    """``train.py --budget smoke``: the preset's ``policy_kwargs`` (activation by name) reach the saved model as the
    harness builds them, and the run's config.yml keeps them as the preset's plain data (no string, no eval)."""
    from torch import nn

    from sb3_pearl.maml import MAML
    from sb3_pearl.zoo import train
    from sb3_pearl.zoo.safe_config import load_run_yaml

    env_id = "SafePointGoalMeta-v0"
    train(["--algo", "maml", "--env", env_id, "--budget", "smoke", "-f", str(tmp_path), "--seed", "0", "--num-threads", "1"])
    run_dir = tmp_path / "maml" / f"{env_id}_1"
    model = MAML.load(run_dir / f"{env_id}.zip")
    assert model.policy_kwargs["activation_fn"] is nn.Tanh and model.policy_kwargs["net_arch"] == [16, 16]
    assert any(isinstance(module, nn.Tanh) for module in model.policy.modules())
    saved = dict(load_run_yaml(run_dir / env_id / "config.yml"))  # the safe loader: a class would be refused
    assert dict(saved["policy_kwargs"]) == {"net_arch": [16, 16], "activation_fn": "tanh"}


def test_enjoy_replays_a_run_in_its_evaluation_env(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Guards against: enjoy built its env from args.yml's env_kwargs only, so a run trained with --eval-env-kwargs
    (whose meta-tests ran in that env) was replayed on other tasks than its meta_test.json's."""
    train(tmp_path, "pearlplus", "--eval-env-kwargs", "goal_radius:1.5")
    run_dir = tmp_path / "pearlplus" / f"{ENV_ID}_1"
    recorded = json.loads((run_dir / "meta_test.json").read_text())
    assert all(math.isclose(math.hypot(*task["goal"]), 1.5) for task in recorded["tasks"])  # the evaluation env's
    result = enjoy_main(
        ["--algo", "pearlplus", "--env", ENV_ID, "-f", str(tmp_path), "--no-render", "--n-tasks", "3", "--n-adapt", "2"]
    )
    assert "ran in its evaluation env (--eval-env-kwargs {'goal_radius': 1.5})" in capsys.readouterr().out
    assert [list(task["goal"]) for task in result.tasks] == [list(task["goal"]) for task in recorded["tasks"]]
    assert result.summary == recorded["summary"]
