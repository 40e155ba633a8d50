"""The library and the paper apart: ``import sb3_pearl`` loads nothing of ``pearl_paper``, and the wheel holds none of it.

``sb3_pearl`` is the installable library; ``pearl_paper`` (the paper's experiments, runner, report and demo) lives in
the repository beside it, as rl-baselines3-zoo stands beside sb3-contrib. tests/test_layout.py checks the same rule
on the static import graph; these tests check it on what Python actually loads and on what the build ships.
"""

from __future__ import annotations

import ast
import os
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import setuptools

from pearl_paper.experiments import FAMILIES
from sb3_pearl.budgets import ENV_PRESET_FAMILY, preset_entries

ROOT = Path(__file__).resolve().parent.parent

IMPORT_EVERYTHING = """
import importlib, pkgutil, sys
import sb3_pearl
after_package = sorted(m for m in sys.modules if m.startswith("pearl_paper"))
walked = [module.name for module in pkgutil.walk_packages(sb3_pearl.__path__, "sb3_pearl.")]
for name in walked:
    importlib.import_module(name)
print(len(walked))
print(after_package)
print(sorted(m for m in sys.modules if m.startswith("pearl_paper")))
"""


def test_importing_the_library_loads_nothing_of_the_paper() -> None:
    """In a fresh interpreter that could import ``pearl_paper`` (the checkout on its path): ``import sb3_pearl``, then
    every submodule of it (pkgutil), loads no module of the paper's harness."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)}
    lines = subprocess.run(
        [sys.executable, "-c", IMPORT_EVERYTHING], capture_output=True, text=True, check=True, cwd=ROOT, env=env
    ).stdout.splitlines()[-3:]
    n_modules, after_package, after_all = lines
    n_files = len([path for path in (ROOT / "sb3_pearl").rglob("*.py") if path.name != "__init__.py"])
    n_packages = len(list((ROOT / "sb3_pearl").rglob("__init__.py"))) - 1  # sb3_pearl itself is not walked
    assert int(n_modules) == n_files + n_packages, "the walk missed modules: the check would mean less than it says"
    assert after_package == "[]"
    assert after_all == "[]"


def test_the_package_finder_finds_no_paper_module() -> None:
    """The packages setuptools puts in the wheel, from pyproject.toml's ``[tool.setuptools.packages.find]``."""
    section = re.search(
        r"^\[tool\.setuptools\.packages\.find\]\n(.*?)(?=^\[)", (ROOT / "pyproject.toml").read_text(), re.M | re.S
    )
    assert section is not None and "exclude" not in section.group(1)
    include = re.search(r"^include = (\[.*?\])$", section.group(1), re.M)
    assert include is not None
    packages = setuptools.find_packages(where=str(ROOT), include=ast.literal_eval(include.group(1)))
    assert "sb3_pearl" in packages and "sb3_pearl.pearl" in packages
    assert [p for p in packages if not p.startswith("sb3_pearl")] == []


def test_the_wheel_holds_the_library_and_not_the_paper(tmp_path: Path) -> None:
    """A wheel built from a copy of the sources (the build writes its folders beside them) lists ``sb3_pearl``'s modules
    and package data (the zoo hyperparameters, the budget presets) and no module of ``pearl_paper``."""
    source = tmp_path / "source"
    source.mkdir()
    for name in ("pyproject.toml", "README.md", "MANIFEST.in"):
        shutil.copy(ROOT / name, source / name)
    for package in ("sb3_pearl", "pearl_paper"):
        shutil.copytree(ROOT / package, source / package, ignore=shutil.ignore_patterns("__pycache__"))
    wheels = tmp_path / "wheels"
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", ".", "--no-deps", "--no-build-isolation", "-q", "-w", str(wheels)],
        cwd=source,
        check=True,
        capture_output=True,
    )
    (wheel,) = wheels.glob("*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert [n for n in names if "pearl_paper" in n] == []
    assert [n for n in names if not n.startswith(("sb3_pearl/", "sb3_pearl-"))] == []
    for needed in ("sb3_pearl/pearl/pearl.py", "sb3_pearl/budgets.py", "sb3_pearl/config/presets/cpu.yml"):
        assert needed in names, needed
    assert any(n.startswith("sb3_pearl/config/zoo_hyperparams/") for n in names)


def test_the_presets_env_mapping_agrees_with_the_papers_families() -> None:
    """``train.py --budget`` finds an env's entries through :data:`sb3_pearl.budgets.ENV_PRESET_FAMILY`; the paper's
    families name the same preset keys, so the two paths train an env id with one entry."""
    assert {f.env_id: f.budget_name for f in FAMILIES.values()} == ENV_PRESET_FAMILY
    for preset in ("smoke", "cpu", "paper"):
        assert set(ENV_PRESET_FAMILY.values()) <= set(preset_entries(preset)), preset
