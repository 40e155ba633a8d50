"""A fresh install as a new user makes it: a non-editable install that runs from anywhere, the ``python -m`` entry
points, headless rendering, and no noise at import or ``gym.make``. What the wheel holds is in
tests/test_package_split.py."""

from __future__ import annotations

import ctypes.util
import os
import runpy
import shutil
import site
import subprocess
import sys
from pathlib import Path
from unittest import mock

import pytest

from tests.conftest import ENV_ID, TINY_ZOO_PARAMS

ROOT = Path(__file__).resolve().parent.parent


TINY_PARAMS = TINY_ZOO_PARAMS  # the packaged zoo_hyperparams/ file is read, its entry shrunk


QUIET_ENV = {key: value for key, value in os.environ.items() if key not in ("DISPLAY", "WAYLAND_DISPLAY", "MUJOCO_GL")}


def run(command: list[str], cwd: Path, timeout: float = 120, installed: bool = False) -> subprocess.CompletedProcess[str]:
    env = {**QUIET_ENV, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    if installed:  # the installed copy is what is tested: a PYTHONPATH naming a checkout would put its sb3_pearl first
        env.pop("PYTHONPATH", None)
    return subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


# ----------------------------------------------------------------------------------------------
# A non-editable install runs from anywhere (and on the way: the cost lines, the meta-test bar)
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
# Headless rendering, and no noise at import or make
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
