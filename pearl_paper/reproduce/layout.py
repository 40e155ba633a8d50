"""The results layout of ``python -m pearl_paper.reproduce`` and the provenance stored with every run.

::

    <results-dir>/<experiment>/<family>/<variant>/seed<N>/
        result.json    written last and atomically: its presence means the run is complete
        model.zip      the trained model (``<Algo>.load``)
        progress.csv   the training log (SB3 logger, csv format)
        run.log        the run's stdout and stderr

``result.json`` keys: :data:`RESULT_KEYS`.
"""

from __future__ import annotations

import json
import os
import platform
import re
import subprocess
from importlib import metadata
from pathlib import Path
from typing import Any, NamedTuple

from sb3_pearl.common.atomic import atomic_write

RESULT_FILE = "result.json"
MODEL_FILE = "model.zip"
PROGRESS_FILE = "progress.csv"
LOG_FILE = "run.log"
RESULT_KEYS = (
    "experiment",
    "family",
    "variant",
    "seed",
    "budget_preset",
    "spec",
    "budget",
    "model_kwargs",
    "eval_seed",
    "versions",
    "cpu",
    "wall_time_s",
    "num_timesteps",
    "device",
    "meta_test",
    "shift",
    "competence",
    "diagnostics",
)
PACKAGES = ("sb3-pearl", "stable-baselines3", "torch", "gymnasium", "numpy", "mujoco", "highway-env")


class RunKey(NamedTuple):
    """One run of the reproduction: (experiment, family, variant, seed)."""

    experiment: str
    family: str
    variant: str
    seed: int

    def label(self) -> str:
        return f"{self.experiment} {self.family} {self.variant} seed{self.seed}"


def run_dir(results_dir: str | os.PathLike[str], key: RunKey) -> Path:
    """The folder of one run: ``<results-dir>/<experiment>/<family>/<variant>/seed<N>``."""
    return Path(results_dir) / key.experiment / key.family / key.variant / f"seed{key.seed}"


def find_results(results_dir: str | os.PathLike[str]) -> list[Path]:
    """Every complete run (its ``result.json``) under ``results_dir``, sorted."""
    return sorted(Path(results_dir).glob(f"*/*/*/seed*/{RESULT_FILE}"))


def write_json_atomic(path: str | os.PathLike[str], data: Any) -> None:
    """
    Write JSON so that the file either does not exist or is complete (temporary file, fsync, then ``os.replace``),
    with the permissions of any other new file (0644 under the usual umask, not ``mkstemp``'s 0600).

    :param path: destination
    :param data: JSON-serialisable data (nan / inf are written as null by the caller's conversion)
    """
    with atomic_write(path, "w") as file:
        json.dump(data, file, indent=1, allow_nan=False)


SUMMARY_KEYS = ("k", "n", "return_mean", "violation_rate")


def read_result(path: str | os.PathLike[str]) -> dict[str, Any]:
    """
    Read a ``result.json`` and check that it is complete: a clear error naming the file and what is missing otherwise.

    :param path: the file
    :return: the result
    """
    try:
        with open(path) as file:
            result = json.load(file)
    except json.JSONDecodeError as error:
        raise ValueError(f"{path} is not valid JSON ({error}): truncated or edited; delete it to rerun the run") from None
    if not isinstance(result, dict):
        raise ValueError(f"{path} does not hold a result (a JSON object); delete it to rerun the run")
    missing = [key for key in ("experiment", "family", "variant", "seed", "budget_preset", "meta_test") if key not in result]
    if missing:
        raise ValueError(f"{path} lacks the key(s) {missing}: it is not a complete result; delete it to rerun the run")
    summary = (result["meta_test"] or {}).get("summary") if isinstance(result["meta_test"], dict) else None
    if not summary or not all(isinstance(e, dict) and all(k in e for k in SUMMARY_KEYS) for e in summary):
        raise ValueError(
            f"{path} lacks its meta_test summary (entries with {list(SUMMARY_KEYS)}): it is not a complete result; "
            "delete it to rerun the run"
        )
    return result


def read_run_result(path: str | os.PathLike[str]) -> dict[str, Any]:
    """
    :func:`read_result` of a ``result.json`` in the results layout, checked against its path: the run it names
    (experiment, family, variant, seed) must be the run of its folder, else a copy or a moved file would stand for
    another run in the tables.

    :param path: ``<results-dir>/<experiment>/<family>/<variant>/seed<N>/result.json``
    :return: the result
    """
    result = read_result(path)
    check_result_path(path, result)
    return result


def discard_result(folder: str | os.PathLike[str]) -> None:
    """
    The first step of a forced rerun (``--force``): the run's ``result.json`` goes (the folder is incomplete until the
    rerun writes it again), and so does every record measured from the model it replaces (``reproduce remeasure``'s
    larger meta-test), so that nothing in the folder describes another model.

    :param folder: the run folder
    """
    from pearl_paper.experiments.table1_rules import MERGE_REMEASURE

    for name in (RESULT_FILE, MERGE_REMEASURE.file_name):
        Path(folder, name).unlink(missing_ok=True)


def check_result_path(path: str | os.PathLike[str], result: dict[str, Any]) -> None:
    """
    Raise a ``ValueError`` naming ``path`` if ``result`` (read from it) is not the result of the run of its folder.

    :param path: ``<results-dir>/<experiment>/<family>/<variant>/seed<N>/result.json``
    :param result: its content (:func:`read_result`)
    """
    parts = Path(path).parts
    if len(parts) < 5:
        raise ValueError(f"{path} is not in the results layout (<experiment>/<family>/<variant>/seed<N>/{Path(path).name})")
    experiment, family, variant, seed_folder = parts[-5:-1]
    expected = {"experiment": experiment, "family": family, "variant": variant, "seed": seed_folder}
    found = {**{key: result[key] for key in ("experiment", "family", "variant")}, "seed": f"seed{result['seed']}"}
    wrong = [f"{key} {found[key]!r} (its folder says {expected[key]!r})" for key in expected if found[key] != expected[key]]
    if wrong:
        raise ValueError(
            f"{path} holds the result of another run: {', '.join(wrong)}. A result is reported only from its own run "
            "folder: move it back to the folder of the run it names, or delete it (a copy of a results folder inside "
            "the results folder is such a case)"
        )


MAX_SEEDS = 1000  # a typo such as 0-120000 is refused instead of planning runs for ever
MAX_SEED_VALUE = 2**32 - 1  # numpy's bound: a larger seed failed in the run, after planning


def parse_seeds(text: str) -> list[int]:
    """
    Seeds from the command line: ``"0-3"``, ``"0,2,5"``, ``"0-3,7"``.

    :param text: the argument
    :return: sorted distinct seeds
    """
    seeds: set[int] = set()
    for part in text.split(","):
        part = part.strip()
        match = re.fullmatch(r"(\d+)(?:-(\d+))?", part)
        if not match:
            raise ValueError(f"--seeds: {part!r} is not a seed or a range like 0-3 (full argument {text!r})")
        first, last = int(match.group(1)), int(match.group(2) or match.group(1))
        if max(first, last) > MAX_SEED_VALUE:
            raise ValueError(f"--seeds: seeds must be integers in [0, {MAX_SEED_VALUE}], got {max(first, last)} (in {text!r})")
        if last < first:
            raise ValueError(f"--seeds: empty range {part!r}")
        if last - first + 1 + len(seeds) > MAX_SEEDS:
            raise ValueError(f"--seeds {text!r} names more than {MAX_SEEDS} seeds: give a smaller range")
        seeds.update(range(first, last + 1))
    return sorted(seeds)


def package_versions() -> dict[str, str | None]:
    """Installed versions of the packages a result depends on, and the git commit of the code if it is a checkout."""
    versions: dict[str, str | None] = {}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    versions["python"] = platform.python_version()
    versions["git_commit"] = _git_commit()
    return versions


def _git_commit() -> str | None:
    source = Path(__file__).resolve().parent
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=source, capture_output=True, text=True, timeout=10, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"], cwd=source, capture_output=True, text=True, timeout=10
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return commit + ("-dirty" if dirty else "")


def cpu_info() -> dict[str, Any]:
    """The CPU model, core count and load average (the machine may be shared: the load says how much)."""
    model = platform.processor() or None
    try:
        with open("/proc/cpuinfo") as file:
            for line in file:
                if line.startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    load = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    return {"model": model, "cores": os.cpu_count(), "load_average": load, "machine": platform.machine()}
