"""What long runs meet (docs/reliability.md, "Long runs"): two processes and one run, a stopped parent, partial and
corrupt results, and flags that must be refused before anything starts."""

from __future__ import annotations

import json
import os
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pearl_paper.experiments import get_experiment
from pearl_paper.reproduce.cli import main
from pearl_paper.reproduce.layout import LOG_FILE, RunKey, parse_seeds, read_result, run_dir, write_json_atomic
from pearl_paper.reproduce.ownership import LOCKED_EXIT, RunLockedError, lock_holder, run_lock
from pearl_paper.reproduce.scheduler import plan_runs, run_experiment
from sb3_pearl.zoo import train
from sb3_pearl.zoo.usage import UsageError, check_yaml_n_timesteps
from tests.conftest import run_in_process

ROOT = Path(__file__).resolve().parent.parent
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
KEY = RunKey("safe-point", "safe-point", "alpha-0", 0)
HOLD = (
    "import sys, time\nfrom pearl_paper.reproduce.ownership import run_lock\n"
    "with run_lock(sys.argv[1]):\n    print('held', flush=True)\n    time.sleep(60)"
)


def _holder(folder: Path) -> subprocess.Popen[str]:
    process = subprocess.Popen([sys.executable, "-c", HOLD, str(folder)], stdout=subprocess.PIPE, text=True, env=ENV)
    assert process.stdout is not None and process.stdout.readline().strip() == "held"
    return process


# -- one run, one owner -----------------------------------------------------------------------------------------
def test_the_lock_names_its_live_owner_and_dies_with_it(tmp_path: Path) -> None:
    assert lock_holder(tmp_path) is None
    with run_lock(tmp_path):
        assert lock_holder(tmp_path) == os.getpid()
        with pytest.raises(RunLockedError, match=f"pid {os.getpid()}"), run_lock(tmp_path):
            pass
    assert lock_holder(tmp_path) is None  # released on exit
    other = _holder(tmp_path)
    assert lock_holder(tmp_path) == other.pid
    other.kill()  # SIGKILL: no clean-up code runs, the kernel drops the lock; the pid left in the file is stale
    other.wait()
    assert lock_holder(tmp_path) is None


def test_a_run_owned_by_another_command_is_skipped_and_its_log_kept(tmp_path: Path) -> None:
    folder = run_dir(tmp_path, KEY)
    folder.mkdir(parents=True)
    (folder / LOG_FILE).write_text("the other command's log\n")
    other = _holder(folder)
    try:
        lines: list[str] = []
        summary = run_experiment(
            get_experiment("safe-point"),
            "smoke",
            [0],
            tmp_path,
            families=["safe-point"],
            variants=["alpha-0"],
            echo=lines.append,
        )
        assert summary.skipped == [KEY] and not summary.done and not summary.failed
        assert any(f"being run by another process (pid {other.pid})" in line for line in lines)
        assert (folder / LOG_FILE).read_text() == "the other command's log\n"
        # A child that loses the race for the lock exits at once with its own status, touching nothing.
        argv = ["run-one", "--experiment", "safe-point", "--family", "safe-point", "--variant", "alpha-0"]
        assert main([*argv, "--seed", "0", "--budget", "smoke", "--results-dir", str(tmp_path)]) == LOCKED_EXIT
        assert not (folder / "checkpoint").exists()
    finally:
        other.kill()
        other.wait()


def test_names_given_twice_plan_one_run() -> None:
    experiment = get_experiment("safe-point")
    runs = plan_runs(experiment, "smoke", [0, 0, 1], ["safe-point", "safe-point"], ["alpha-0", "alpha-0.1", "alpha-0"])
    assert [(r.variant, r.seed) for r in runs] == [("alpha-0", 0), ("alpha-0", 1), ("alpha-0.1", 0), ("alpha-0.1", 1)]


# -- children die with the parent -----------------------------------------------------------------------------------
def _children(pid: int) -> list[int]:
    out = subprocess.run(["pgrep", "-P", str(pid)], capture_output=True, text=True).stdout
    return [int(line) for line in out.split()]


def test_sigterm_to_the_parent_stops_its_runs_and_says_how_to_finish_them(tmp_path: Path) -> None:
    args = ["run", "safe-point", "--budget", "smoke", "--seeds", "0-1", "--family", "safe-point", "--variants", "alpha-0"]
    parent = subprocess.Popen(
        [sys.executable, "-m", "pearl_paper.reproduce", *args, "--jobs", "2", "--results-dir", str(tmp_path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=ENV,
    )
    deadline = time.time() + 60
    while len(children := _children(parent.pid)) < 2 and time.time() < deadline:
        time.sleep(0.2)
    assert len(children) == 2, "the two runs did not start"
    time.sleep(2.0)  # inside their imports or training
    parent.send_signal(signal.SIGTERM)
    out, err = parent.communicate(timeout=90)
    assert parent.returncode == 130, (out, err)
    assert "interrupted: 2 run(s) stopped" in out and "run the same command again" in out
    assert "Traceback" not in out + err
    for child in children:
        assert not Path(f"/proc/{child}").exists() or "zombie" in Path(f"/proc/{child}/status").read_text()
    assert not list(tmp_path.rglob("result.json"))
    for seed in (0, 1):
        assert lock_holder(run_dir(tmp_path, RunKey("safe-point", "safe-point", "alpha-0", seed))) is None


# -- partial and corrupt results ------------------------------------------------------------------------------------
def test_report_refuses_an_empty_or_missing_folder_and_keeps_the_page(tmp_path: Path) -> None:
    page = tmp_path / "results.md"
    page.write_text("committed tables\n")
    for folder in (tmp_path / "missing", tmp_path / "empty"):
        (tmp_path / "empty").mkdir(exist_ok=True)
        assert main(["report", "--results-dir", str(folder), "--out", str(page)]) == 2
    assert page.read_text() == "committed tables\n"


def test_a_result_without_its_summary_or_truncated_is_refused_by_name(tmp_path: Path) -> None:
    path = tmp_path / "result.json"
    good = {"experiment": "safe-point", "family": "safe-point", "variant": "alpha-0", "seed": 0, "budget_preset": "smoke"}
    write_json_atomic(path, {**good, "meta_test": {"summary": [{"k": 0, "n": 1, "return_mean": -1.0, "violation_rate": 0}]}})
    assert read_result(path)["variant"] == "alpha-0"
    assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~_umask()  # like any new file, not mkstemp's 0600
    write_json_atomic(path, {**good, "meta_test": {"config": {}}})
    with pytest.raises(ValueError, match=f"{path} lacks its meta_test summary"):
        read_result(path)
    write_json_atomic(path, good)
    with pytest.raises(ValueError, match=r"lacks the key\(s\) \['meta_test'\]"):
        read_result(path)
    path.write_text(json.dumps(good)[:40])
    with pytest.raises(ValueError, match=f"{path} is not valid JSON"):
        read_result(path)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


# -- flags -----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("steps", ["0", "-5"])
def test_train_py_refuses_a_zero_or_negative_budget(steps: str) -> None:
    proc = run_in_process(train, "--algo", "pearl", "--env", "SafePointGoalMeta-v0", "-n", steps, check=False)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "-n must be a positive number of env steps" in lines[0], proc.stderr


def test_a_yaml_entry_with_a_negative_budget_is_refused() -> None:
    check_yaml_n_timesteps({"n_timesteps": 1000}, "x.yml [Env]")
    with pytest.raises(UsageError, match=r"n_timesteps in x.yml \[Env\] must be a positive number"):
        check_yaml_n_timesteps({"n_timesteps": -100}, "x.yml [Env]")


def test_a_results_dir_that_is_a_file_is_refused_before_any_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    target = tmp_path / "results.txt"
    target.write_text("not a folder")
    args = ["run", "safe-point", "--budget", "smoke", "--seeds", "0", "--family", "safe-point", "--variants", "alpha-0"]
    assert main([*args, "--results-dir", str(target / "sub")]) == 2
    assert f"{target} is a file, not a folder" in capsys.readouterr().err


def test_seed_ranges_and_large_plans_are_bounded(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(ValueError, match="names more than 1000 seeds"):
        parse_seeds("0-120000")
    assert main(["run", "prior-critic", "--budget", "smoke", "--seeds", "0-9"]) == 2  # 340 runs
    assert "runs planned (more than 200)" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        main(["run", "safe-point", "--jobs", "0"])
    assert exit_info.value.code == 2 and "argument --jobs: must be an integer >= 1, got 0" in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv, message",
    [
        (["/nonexistent"], "/nonexistent not found"),
        (["a", "--labels", "x", "y"], "--labels: 2 labels for 1 runs"),
        (["a", "-o", "/nonexistent/dir/x.png"], "-o/--output: the folder of /nonexistent/dir/x.png does not exist"),
    ],
)
def test_plots_flags_are_one_line_errors(argv: list[str], message: str, capsys: pytest.CaptureFixture[str]) -> None:
    from sb3_pearl.plots import main as plots_main

    with pytest.raises(SystemExit) as exit_info:
        plots_main(argv)
    lines = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 2 and message in lines[-1] and "Traceback" not in "\n".join(lines)
