"""What a new user meets (issue 13): the cost of a run said and measured, meta-test progress, a non-editable install
that runs from anywhere, headless rendering, no noise, one-line user errors, plots into the run folder."""

from __future__ import annotations

import ctypes.util
import os
import runpy
import shutil
import site
import subprocess
import sys
from pathlib import Path
from typing import Any
from unittest import mock

import gymnasium as gym
import pytest

from sb3_pearl import PEARLPlus
from sb3_pearl.budgets import load_budget
from sb3_pearl.evaluation.callbacks import MetaTestCallback
from sb3_pearl.evaluation.meta_test import MetaTestResult
from sb3_pearl.evaluation.progress import TrainingProgressCallback, format_duration
from sb3_pearl.evaluation.statistics import summarize
from sb3_pearl.finetune import FineTune
from sb3_pearl.zoo import enjoy, train
from sb3_pearl.zoo.budget import budget_hyperparams, faster_option
from tests.conftest import TINY_ZOO_PARAMS

ROOT = Path(__file__).resolve().parent.parent
ENV_ID = "SafePointGoalMeta-v0"
TINY_PARAMS = TINY_ZOO_PARAMS  # the packaged zoo_hyperparams/ file is read, its entry shrunk
QUIET_ENV = {key: value for key, value in os.environ.items() if key not in ("DISPLAY", "WAYLAND_DISPLAY", "MUJOCO_GL")}


def run(command: list[str], cwd: Path, timeout: float = 120, installed: bool = False) -> subprocess.CompletedProcess[str]:
    env = {**QUIET_ENV, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    if installed:  # the installed copy is what is tested: a PYTHONPATH naming a checkout would put its sb3_pearl first
        env.pop("PYTHONPATH", None)
    return subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


# ----------------------------------------------------------------------------------------------
# 3. A non-editable install runs from anywhere (and 1-2 on the way: the cost lines, the meta-test bar)
# ----------------------------------------------------------------------------------------------
def test_non_editable_install_runs_from_anywhere(tmp_path: Path) -> None:
    source = tmp_path / "source"
    source.mkdir()
    shutil.copytree(ROOT / "sb3_pearl", source / "sb3_pearl", ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml", "MANIFEST.in", "README.md"):
        shutil.copy2(ROOT / name, source / name)
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", "--without-pip", str(venv)], check=True)
    python = venv / "bin" / "python"
    purelib_cmd = [str(python), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"]
    purelib = Path(run(purelib_cmd, tmp_path, installed=True).stdout.strip())
    # The project venv's packages (torch, SB3, ...) as plain paths: its editable sb3_pearl finder is not loaded.
    (purelib / "project_venv.pth").write_text(site.getsitepackages()[0] + "\n")
    install = [str(python), "-m", "pip", "install", "-v", "--no-deps", "--no-build-isolation", "--ignore-installed", "."]
    proc = run(install, source, installed=True)  # -v: the build backend's warnings too
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "project.license" not in proc.stdout + proc.stderr  # "... as a TOML table is deprecated"
    assert (purelib / "sb3_pearl" / "config" / "zoo_hyperparams" / "pearlplus.yml").is_file()
    assert (purelib / "sb3_pearl" / "config" / "presets" / "cpu.yml").is_file()
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()

    train_args = ["--algo", "pearlplus", "--env", ENV_ID, "--seed", "1", "-n", "300", "--eval-freq", "-1", "-P"]
    proc = run([str(venv / "bin" / "sb3-pearl-train"), *train_args, "-params", *TINY_PARAMS], elsewhere, installed=True)
    output = proc.stdout
    assert proc.returncode == 0, output[-3000:] + proc.stderr[-3000:]
    assert f"Loading hyperparameters from: {purelib / 'sb3_pearl' / 'config' / 'zoo_hyperparams' / 'pearlplus.yml'}" in output
    # 1. the collection-only start, then the measured costs and the ETA of the whole run
    assert "PEARLPlus: 300 env steps and 8 gradient steps. Initial collection: the first 120 env steps only collect" in output
    assert "First iteration: 120 env steps in " in output and "5 gradient steps in " in output
    assert "ETA of the whole run: " in output and "(180 env steps and 3 gradient steps to go)" in output
    assert "PEARLPlus: done" in output and "300/300 env steps, 8/8 gradient steps" in output  # -P's bar, at its end
    # 2. the final meta-test's progress bar with the Ctrl-C hint
    assert "Meta-test (Ctrl-C skips it)" in output and "9/9 trajectories" in output
    assert (elsewhere / "logs" / "pearlplus" / f"{ENV_ID}_1" / "meta_test.json").is_file()


@pytest.mark.parametrize(
    "module, argv, status, stream, text",
    [
        ("sb3_pearl.train", ["--help"], 0, "out", "--budget PRESET"),
        ("sb3_pearl.zoo", [], 0, "out", "python -m sb3_pearl.train"),
        ("sb3_pearl.zoo", ["--bogus"], 2, "err", "python -m sb3_pearl.train"),
    ],
)
def test_python_dash_m_entry_points(
    module: str, argv: list[str], status: int, stream: str, text: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """``python -m sb3_pearl.train --help`` lists the project's flags; ``python -m sb3_pearl.zoo`` says what to run."""
    with mock.patch.object(sys, "argv", [module, *argv]), pytest.raises(SystemExit) as exit_info:
        runpy.run_module(module, run_name="__main__", alter_sys=True)
    assert exit_info.value.code == status
    assert text in getattr(capsys.readouterr(), stream)


# ----------------------------------------------------------------------------------------------
# 4-5. Headless rendering, and no noise at import or make
# ----------------------------------------------------------------------------------------------
def test_import_and_make_every_family_without_noise(tmp_path: Path) -> None:
    script = """
import os
import gymnasium as gym
import sb3_pearl
from sb3_pearl.envs import FAMILIES
for env_id in FAMILIES:
    env = gym.make(env_id)
    env.reset(seed=0)
    env.step(env.action_space.sample())
    env.close()
print("MUJOCO_GL", os.environ.get("MUJOCO_GL"))
if os.environ.get("MUJOCO_GL"):
    env = gym.make("AntVelMeta-v0", render_mode="rgb_array")
    env.reset(seed=0)
    print("frame", env.render().shape)
"""
    proc = run([sys.executable, "-c", script], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == "", proc.stderr  # no Adroit notice, no settotalmass deprecation, no other warning
    if sys.platform.startswith("linux") and ctypes.util.find_library("EGL"):
        assert "MUJOCO_GL egl" in proc.stdout and "frame (480, 480, 3)" in proc.stdout  # offscreen without a display


# ----------------------------------------------------------------------------------------------
# 5. User errors: one line, exit status 2
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["--env", "SafePointGoalMta-v0"],
            "--env SafePointGoalMta-v0: not found in gym registry, did you mean SafePointGoalMeta-v0?",
        ),
        (["--env", ENV_ID, "-params", "prior_coef:abc"], "-params prior_coef:abc: the value 'abc' is not a Python expression"),
        (["--env", ENV_ID, "-params", "prior_coef"], "-params prior_coef: expected key:value"),
        (["--env", ENV_ID, "-params", "warp_factor:9"], "PEARLPlus does not take the hyperparameter(s) 'warp_factor' given"),
        (["--env", ENV_ID, "-params", "latnt_dim:5"], "'latnt_dim' (did you mean latent_dim?) given in -params (latnt_dim)"),
        (["--env", ENV_ID, "-n", "1.5"], "-n takes a whole number of env steps, got '1.5'"),
        (
            ["--env", "PointGoalMeta-v0", "--budget", "cpu"],
            "--budget cpu: the cpu preset has no pearlplus entry for PointGoalMeta-v0",
        ),
    ],
)
def test_train_user_errors_are_one_line(
    args: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(sys, "argv", ["train.py"])
    with pytest.raises(SystemExit) as exit_info:
        train(["--algo", "pearlplus", "-f", str(tmp_path), "-n", "10", *args])
    assert exit_info.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("train.py: error: ") and message in lines[0], lines
    assert "hyperparameter" not in message or len(lines[0]) < 200, lines[0]  # a key typo: no list of every accepted key


def test_n_timesteps_takes_the_yaml_notation() -> None:
    """``-n 2e3`` as the YAML files write ``2e6``; rl_zoo3's int parser gets ``2000``."""
    from sb3_pearl.zoo.usage import check_n_timesteps

    assert check_n_timesteps(["--algo", "pearl", "-n", "2e3"]) == ["--algo", "pearl", "-n", "2000"]
    assert check_n_timesteps(["--n-timesteps=2_000"]) == ["--n-timesteps=2000"]


def test_enjoy_user_error_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(sys, "argv", ["enjoy.py"])
    with pytest.raises(SystemExit) as exit_info:
        enjoy(["--algo", "pearlplus", "--env", ENV_ID, "-f", str(tmp_path / "nowhere"), "--no-render"])
    assert exit_info.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("enjoy.py: error: ") and "folder was not found" in lines[0], lines


# ----------------------------------------------------------------------------------------------
# 1. The plan and the ETA of a run; --budget takes the preset's entry
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
# 6. Plots without -o go into the run folder
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
