"""The command lines' answers to mistakes (train.py, enjoy.py, diagnose, plots): one line that names the flag or file
and the fix, exit status 2, nothing half-made left behind; and configs and run folders read without running code.

docs/reliability.md lists each case and what it gets; the runs that succeed are in tests/test_cli.py."""

from __future__ import annotations

import os
import sys
from collections import OrderedDict
from pathlib import Path
from typing import Any

import pytest
import torch as th
import yaml

from sb3_pearl.diagnose import main as diagnose_main
from sb3_pearl.evaluation.figures import main as plots_main
from sb3_pearl.zoo import enjoy, train
from sb3_pearl.zoo.safe_config import UnsafeConfigError, load_run_yaml, parse_dict_string
from tests.conftest import (
    ENV_ID,
    TINY_ZOO_PARAMS,
    _read_only_for_root,
    run_in_process,
    tiny_pearl,
)


# ----------------------------------------------------------------------------------------------
# Unclear cases: one line naming what to fix
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "extra, message",
    [
        (["--env-kwargs", "hazrd_radius:0.3"], "--env-kwargs / env_kwargs: SafePointGoalMeta-v0 does not take 'hazrd_radius'"),
        (["--seed", "-5"], "--seed must be an integer in [0, 4294967295] (omit it for a random seed), got '-5'"),
        (["--seed", str(2**32)], "--seed must be an integer in [0, 4294967295]"),
        (["-params", "learning_rate:float('nan')"], "learning_rate must be a finite number >= 0"),
        (["-f", "FILE"], "is a file, not a folder: give a folder for the run folders"),
        (["-f", "FILE/logs"], "is a file, not a folder"),
    ],
)
def test_train_py_mistakes_are_one_line(tmp_path: Path, extra: list[str], message: str) -> None:
    (tmp_path / "file").write_text("")
    extra = [arg.replace("FILE", str(tmp_path / "file")) for arg in extra]
    logs = tmp_path / "logs"
    argv = ["--algo", "pearlplus", "--env", ENV_ID, "-f", str(logs), "-n", "60", *extra]
    refused = run_in_process(train, *argv, check=False)
    assert refused.returncode == 2, refused.stdout[-2000:] + refused.stderr[-2000:]
    assert "Traceback" not in refused.stderr
    lines = [line for line in refused.stderr.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and message in lines[0], lines  # one line, naming what to fix
    assert not logs.exists() or not any(logs.rglob("*.csv"))  # no run folder left


def test_train_py_on_a_folder_it_cannot_write_is_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """-f on a folder without write permission (faked: the tests may run as root, who may write anywhere)."""
    locked = tmp_path / "locked"
    locked.mkdir()
    real_access = os.access

    def access(path: str, mode: int, **kwargs: Any) -> bool:
        return False if Path(path) == locked else real_access(path, mode, **kwargs)

    monkeypatch.setattr(os, "access", access)
    argv = ["--algo", "pearlplus", "--env", ENV_ID, "-f", str(locked / "logs"), "-n", "60"]
    refused = run_in_process(train, *argv, check=False)
    lines = [line for line in refused.stderr.strip().splitlines() if line.strip()]
    assert refused.returncode == 2 and len(lines) == 1 and f"{locked} is not writable" in lines[0], lines
    assert list(locked.iterdir()) == []


def test_a_truncated_model_is_named_by_enjoy_and_diagnose(
    tmp_path: Path, tiny_kwargs: dict[str, Any], capsys: pytest.CaptureFixture[str]
) -> None:
    run = tmp_path / "logs" / "pearlplus" / f"{ENV_ID}_1"
    run.mkdir(parents=True)
    tiny_pearl(tiny_kwargs, seed=0).save(tmp_path / "model.zip")
    data = (tmp_path / "model.zip").read_bytes()
    (run / f"{ENV_ID}.zip").write_bytes(data[: len(data) // 2])
    expected = f"{run / f'{ENV_ID}.zip'} is not a readable zip"  # diagnose said "not a PEARL / PEARL+ model"
    argv = ["--algo", "pearlplus", "--env", ENV_ID, "-f", str(tmp_path / "logs"), "--no-render", "--n-tasks", "1"]
    refused = run_in_process(enjoy, *argv, check=False)
    assert refused.returncode == 2 and expected in refused.stderr and "Traceback" not in refused.stderr
    with pytest.raises(SystemExit) as exit_info:
        diagnose_main([str(run / f"{ENV_ID}.zip"), "--env-id", ENV_ID])
    assert exit_info.value.code == 2
    assert expected in capsys.readouterr().err  # the same words as enjoy's, not "not a PEARL / PEARL+ model"


def test_plots_names_a_truncated_meta_test_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "meta_test.json").write_text('{"config": {"algo": "pearl"}, "summ')
    with pytest.raises(SystemExit) as exit_info:
        plots_main([str(tmp_path), "-o", str(tmp_path / "out.png")])
    assert exit_info.value.code == 2
    assert f"{tmp_path / 'meta_test.json'} is not valid JSON" in capsys.readouterr().err


# ----------------------------------------------------------------------------------------------
# Configs and run folders never run code
# ----------------------------------------------------------------------------------------------
def _zoo_run_folder(root: Path, tiny_kwargs: dict[str, Any]) -> Path:
    """A run folder in rl_zoo3's layout, its YAML written the way rl_zoo3 writes it (yaml.dump of OrderedDicts)."""
    run_dir = root / "pearlplus" / f"{ENV_ID}_1"
    tiny_pearl(tiny_kwargs, seed=0).save(run_dir / f"{ENV_ID}.zip")
    (run_dir / ENV_ID).mkdir()
    args = OrderedDict(sorted({"algo": "pearlplus", "env": ENV_ID, "env_kwargs": None, "seed": 1, "gym_packages": []}.items()))
    config = OrderedDict([("n_envs", 1), ("policy", "MlpPolicy"), ("policy_kwargs", "dict(net_arch=[32, 32])")])
    (run_dir / ENV_ID / "args.yml").write_text(yaml.dump(args))
    (run_dir / ENV_ID / "config.yml").write_text(yaml.dump(config))
    return run_dir


def test_run_folder_yaml_is_read_safely(tmp_path: Path) -> None:
    written = OrderedDict([("env", ENV_ID), ("train_freq", (1, "episode")), ("env_kwargs", {"a": [1.5, None]})])
    path = tmp_path / "args.yml"
    path.write_text(yaml.dump(written))
    assert "!!python/object/apply:collections.OrderedDict" in path.read_text()  # what rl_zoo3 writes
    assert load_run_yaml(path) == written
    path.write_text('!!python/object/apply:os.system ["echo pwned"]\n')
    with pytest.raises(UnsafeConfigError, match="refusing the YAML tag '!!python/object/apply:os.system'"):
        load_run_yaml(path)
    path.write_text("env: !!python/name:os.system\n")
    with pytest.raises(UnsafeConfigError, match="python/name:os.system"):
        load_run_yaml(path)
    # an Optuna trial's config.yml names its activation class (convert_pearl_params): looked up, nothing else is
    trial = OrderedDict([("policy_kwargs", {"net_arch": [64, 64], "activation_fn": th.nn.ReLU})])
    path.write_text(yaml.dump(trial))
    assert "!!python/name:torch.nn.modules.activation.ReLU" in path.read_text()
    assert load_run_yaml(path) == trial
    for name in ("__class__", "Tensor", "F"):  # the module itself, a non-Module class, a submodule
        path.write_text(f"a: !!python/name:torch.nn.modules.activation.{name} ''\n")
        with pytest.raises(UnsafeConfigError, match=f"python/name:torch.nn.modules.activation.{name}"):
            load_run_yaml(path)


@pytest.mark.parametrize("poisoned", ["args.yml", "config.yml"])
def test_enjoy_refuses_a_run_folder_that_would_run_code(tmp_path: Path, tiny_kwargs: dict[str, Any], poisoned: str) -> None:
    run_dir = _zoo_run_folder(tmp_path / "logs", tiny_kwargs)
    marker = tmp_path / "pwned"
    (run_dir / ENV_ID / poisoned).write_text(f'!!python/object/apply:os.system ["touch {marker}"]\n')
    with pytest.raises(SystemExit, match="refusing the YAML tag '!!python/object/apply:os.system'"):
        enjoy(["--algo", "pearlplus", "--env", ENV_ID, "-f", str(tmp_path / "logs"), "--no-render", "--n-tasks", "1"])
    assert not marker.exists()


def test_meta_test_strings_are_parsed_without_eval(tmp_path: Path) -> None:
    assert parse_dict_string("dict(n_adapt=3, deterministic=False)", "meta_test") == {"n_adapt": 3, "deterministic": False}
    assert parse_dict_string("{'n_tasks': None}", "meta_test") == {"n_tasks": None}
    marker = tmp_path / "pwned"
    for text in (f"__import__('os').system('touch {marker}')", f"dict(n_adapt=__import__('os').system('touch {marker}'))"):
        with pytest.raises(ValueError, match="meta_test: .* is not a dict of literals"):
            parse_dict_string(text, "meta_test")
    assert not marker.exists()
    with pytest.raises(ValueError, match=r"meta_test: cannot parse 'dict\(n_adapt=' \(.*\); write a dict of literals"):
        parse_dict_string("dict(n_adapt=", "meta_test")
    with pytest.raises(ValueError, match="meta_test must be a dict"):
        parse_dict_string("[1, 2]", "meta_test")


# ----------------------------------------------------------------------------------------------
# A model of another task family: the message names the env id to pass
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("flag", ["-i", "--resume"])
def test_train_py_with_a_model_of_another_family_names_the_env_to_pass(
    tmp_path: Path, point_goal_model: Path, flag: str
) -> None:
    """Guards against: the constructor's advice ('give it an env of that family'), which a train.py user cannot follow."""
    extra = ["--resume-without-buffer"] if flag == "--resume" else []
    proc = run_in_process(
        train,
        *("--algo", "pearlplus", "--env", ENV_ID, "-f", str(tmp_path / "logs"), "-n", "200", flag, str(point_goal_model)),
        *extra,
        *("-params", *TINY_ZOO_PARAMS),
        check=False,
    )
    assert proc.returncode == 2, proc.stderr[-2000:]
    line = proc.stderr.strip().splitlines()[-1]
    assert f"{flag} {point_goal_model} was not trained on {ENV_ID}: the model was trained on PointGoalMetaEnv tasks" in line
    assert line.endswith("; pass --env PointGoalMeta-v0"), line
    assert not list((tmp_path / "logs" / "pearlplus").iterdir())  # refused before anything was trained or kept


def test_diagnose_with_a_model_of_another_family_names_the_env_id_to_pass(
    point_goal_model: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Guards against: the constructor's ValueError as a traceback."""
    with pytest.raises(SystemExit) as exit_info:
        diagnose_main([str(point_goal_model), "--env-id", ENV_ID, "--n-tasks", "1"])
    assert exit_info.value.code == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert f"{point_goal_model} was not trained on {ENV_ID}: the model was trained on PointGoalMetaEnv tasks" in line
    assert line.endswith("; pass --env-id PointGoalMeta-v0"), line


def test_train_py_log_folder_that_root_cannot_write_is_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Guards against: accepted, then a PermissionError / OSError traceback from os.makedirs."""
    locked = tmp_path / "mount"
    locked.mkdir()
    _read_only_for_root(monkeypatch, locked)
    refused = run_in_process(
        train, "--algo", "pearlplus", "--env", ENV_ID, "-f", str(locked / "logs"), "-n", "60", check=False
    )
    lines = [line for line in refused.stderr.strip().splitlines() if line.strip()]
    assert refused.returncode == 2 and len(lines) == 1, lines
    assert f"-f {locked / 'logs'}: {locked} is not writable (Read-only file system)" in lines[0], lines
    assert list(locked.iterdir()) == []


@pytest.mark.skipif(
    not os.path.isdir("/sys") or os.access("/sys", os.W_OK) is False, reason="needs /sys, writable per os.access"
)
def test_a_log_folder_under_sys_is_one_line(tmp_path: Path) -> None:
    """The real case: root's os.access says /sys is writable; creating a folder there fails (EPERM or EROFS)."""
    target = f"/sys/sb3-pearl-logs-{os.getpid()}"
    refused = run_in_process(train, "--algo", "pearlplus", "--env", ENV_ID, "-f", target, "-n", "60", check=False)
    lines = [line for line in refused.stderr.strip().splitlines() if line.strip()]
    assert refused.returncode == 2 and len(lines) == 1 and f"-f {target}: /sys is not writable (" in lines[0], lines


# ----------------------------------------------------------------------------------------------
# User errors: one line, exit status 2
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


def test_enjoy_user_error_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(sys, "argv", ["enjoy.py"])
    with pytest.raises(SystemExit) as exit_info:
        enjoy(["--algo", "pearlplus", "--env", ENV_ID, "-f", str(tmp_path / "nowhere"), "--no-render"])
    assert exit_info.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("enjoy.py: error: ") and "folder was not found" in lines[0], lines
