"""Behaviour preserved across refactors (issue 39's constraint): a smoke experiment's result.json and a ``train.py``
smoke run's meta_test.json, against the numbers committed in ``tests/data/golden_results.json``.

Every meta-test row (return, cost, violation) of both runs is compared. On the kind of machine that wrote the file
(the same CPU model and feature flags, torch CPU capability, torch and numpy versions), the comparison is
exact, so a change to the code that moves any number fails. Elsewhere matrix products round differently (MKL takes
other paths on other CPUs), so returns are compared within 1e-4 (relative) and violations must still be equal. A
change that is meant to move the numbers (new math, a new default) rewrites the file, and its commit says why:

    SB3_PEARL_WRITE_GOLDEN=1 python -m pytest tests/test_golden_results.py
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch as th

from pearl_paper.reproduce.cli import main as reproduce_main
from pearl_paper.reproduce.layout import cpu_info
from sb3_pearl.zoo import train
from tests.conftest import TINY_ZOO_PARAMS, run_in_process

GOLDEN = Path(__file__).resolve().parent / "data" / "golden_results.json"
WRITE = os.environ.get("SB3_PEARL_WRITE_GOLDEN") == "1"
ROW_KEYS = ("task", "repeat", "k", "return", "cost", "violated")


def cpu_flags_digest() -> str:
    """A digest of the CPU's feature flags (``/proc/cpuinfo``), or ``unknown``: two machines that report one model name
    may still differ in the instruction sets MKL and torch dispatch on."""
    try:
        with open("/proc/cpuinfo") as file:
            flags = next((line.split(":", 1)[1] for line in file if line.startswith("flags")), "")
    except OSError:
        return "unknown"
    return hashlib.sha256(" ".join(sorted(flags.split())).encode()).hexdigest()[:16] if flags else "unknown"


def _rows(meta_test: dict[str, Any]) -> list[dict[str, Any]]:
    return [{key: row[key] for key in ROW_KEYS} for row in meta_test["rows"]]


def smoke_experiment_rows(results_dir: Path) -> list[dict[str, Any]]:
    """One smoke run of the harness (safe-point, PEARL+ alpha 0.1, seed 0): its held-out meta-test rows."""
    args = ["run", "safe-point", "--budget", "smoke", "--seeds", "0", "--family", "safe-point", "--variants", "alpha-0.1"]
    run_in_process(reproduce_main, *args, "--results-dir", str(results_dir))
    result = json.loads((results_dir / "safe-point" / "safe-point" / "alpha-0.1" / "seed0" / "result.json").read_text())
    return _rows(result["meta_test"])


def train_py_rows(log_folder: Path) -> list[dict[str, Any]]:
    """``train.py`` on SafePointGoalMeta-v0 at the tests' tiny size (seed 1, 200 env steps): its meta_test.json rows,
    some of which violate (the harness's smoke run above has none)."""
    argv = ["--algo", "pearlplus", "--env", "SafePointGoalMeta-v0", "-n", "200", "--seed", "1", "--eval-freq", "-1"]
    params = [*TINY_ZOO_PARAMS, "kl_weight:0.37", "latent_dim:3"]
    run_in_process(train, *argv, "-f", str(log_folder), "--num-threads", "1", "-params", *params)
    return _rows(json.loads((log_folder / "pearlplus" / "SafePointGoalMeta-v0_1" / "meta_test.json").read_text()))


def assert_same(found: list[dict[str, Any]], golden: list[dict[str, Any]], exact: bool, what: str) -> None:
    assert len(found) == len(golden), f"{what}: {len(found)} meta-test rows, the golden file has {len(golden)}"
    for row, expected in zip(found, golden, strict=True):
        where = f"{what}, task {row['task']} repeat {row['repeat']} k {row['k']}"
        assert (row["task"], row["repeat"], row["k"], row["violated"]) == (
            expected["task"],
            expected["repeat"],
            expected["k"],
            expected["violated"],
        ), where
        for key in ("return", "cost"):
            if exact:
                assert row[key] == expected[key], f"{where}: {key} {row[key]!r}, golden {expected[key]!r}"
            else:
                assert row[key] == pytest.approx(expected[key], rel=1e-4, abs=1e-6), f"{where}: {key}"


def test_smoke_runs_give_the_golden_numbers(tmp_path: Path) -> None:
    found = {
        "reproduce run safe-point --budget smoke (alpha-0.1, seed 0)": smoke_experiment_rows(tmp_path / "results"),
        "train.py -n 200 at the tests' tiny size (SafePointGoalMeta-v0, seed 1)": train_py_rows(tmp_path / "logs"),
    }
    machine = {
        "cpu": cpu_info()["model"],
        "cpu_flags": cpu_flags_digest(),  # the instruction sets the kernels dispatch on, not only the model's name
        "cpu_capability": th.backends.cpu.get_cpu_capability(),
        "torch": th.__version__,
        "numpy": np.__version__,  # the envs' dynamics
    }
    if WRITE:
        GOLDEN.parent.mkdir(exist_ok=True)
        GOLDEN.write_text(json.dumps({**machine, "runs": found}, indent=1))
        pytest.skip(f"wrote {GOLDEN}")
    golden = json.loads(GOLDEN.read_text())
    rows = [row for runs in golden["runs"].values() for row in runs]
    assert any(row["violated"] for row in rows) and any(row["cost"] > 0 for row in rows)  # the check can see them
    exact = all(golden.get(key) == value for key, value in machine.items())
    assert set(found) == set(golden["runs"])
    for what, rows in found.items():
        assert_same(rows, golden["runs"][what], exact, what)


def test_the_comparison_on_hand_made_rows() -> None:
    row = {"task": 0, "repeat": 0, "k": 0, "return": -10.0, "cost": 0.0, "violated": False}
    nudged = {**row, "return": -10.0 * (1 + 1e-6)}  # another CPU's rounding
    assert_same([nudged], [row], exact=False, what="other CPU")
    with pytest.raises(AssertionError, match="return"):
        assert_same([nudged], [row], exact=True, what="same CPU")
    with pytest.raises(AssertionError):
        assert_same([{**row, "violated": True}], [row], exact=False, what="a flipped violation")
    with pytest.raises(AssertionError, match="1 meta-test rows, the golden file has 2"):
        assert_same([row], [row, row], exact=True, what="a row lost")
