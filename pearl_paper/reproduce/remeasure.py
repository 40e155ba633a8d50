"""``reproduce remeasure``: a larger meta-test of committed models, without retraining.

A run's own meta-test rests on 200 k = 0 trajectories (20 held-out tasks x 10 prior draws); at violation rates of
1-10% that is a per-seed interval of +-3 to +-4 points, as large as the effect Table I is about. This command loads a
finished run's ``model.zip`` and meta-tests it again on the larger design of a
:class:`~pearl_paper.experiments.table1_rules.RemeasureConfig` (two passes on the same held-out tasks, with the
experiment's eval seed and common random numbers, as every run's own meta-test), and writes the record beside the run's
``result.json`` as ``meta_test_large.json`` (atomically). result.json is not touched: the old numbers stay where they
were, and the report shows both.

The prior pass and the adapted pass share their first draws: the adapted pass's k = 0 rows are the prior pass's
repeats 0..adapted_repeats-1 again (same env seeds, same z0). The record states whether they matched
(``crn_check``), a free check that the meta-test is deterministic on this machine.

A record is read only as its run's (:func:`read_remeasured`): an empty or unparsable file, one without its summary,
or one that names another run (experiment, family, variant, seed: a copied file) or another eval seed than the run's
``result.json`` is skipped with a warning naming the file, and ``remeasure`` measures such a run again instead of
taking the file for a finished measurement.
"""

from __future__ import annotations

import dataclasses
import json
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym

from pearl_paper.experiments.table1_rules import MERGE_REMEASURE, RemeasureConfig
from pearl_paper.reproduce.layout import (
    MODEL_FILE,
    RESULT_FILE,
    check_result_path,
    cpu_info,
    package_versions,
    read_run_result,
    write_json_atomic,
)
from sb3_pearl.evaluation.held_out import meta_test_record, model_test_tasks, run_meta_test
from sb3_pearl.evaluation.meta_test import MetaTestResult, json_value
from sb3_pearl.evaluation.statistics import summarize

MATCHED_COLUMNS = ("task", "repeat", "k", "return", "cost", "length", "violated")


def remeasure_model(model: Any, env: gym.Env, eval_seed: int, config: RemeasureConfig, what: str = "") -> dict[str, Any]:
    """
    The larger meta-test of one model (module docstring).

    :param model: a trained model with the adaptation API
    :param env: the evaluation env (the family's, with the run's env kwargs)
    :param eval_seed: the experiment's eval seed (tasks, env resets and prior draws)
    :param config: the design
    :param what: the run, for messages
    :return: the record: ``config``, ``summary`` (k = 0 from the prior pass, k >= 1 from the adapted pass), ``prior`` and
        ``adapted`` (each pass's meta-test record without traces), ``crn_check``, ``wall_time_s``
    """
    start = time.time()
    tasks = model_test_tasks(model, env, config.n_tasks, eval_seed, what)
    prior = run_meta_test(
        model, env, tasks, {"n_adapt": 0, "n_repeats": config.prior_repeats, "deterministic": True}, eval_seed, trace_keys=()
    )
    adapted = run_meta_test(
        model,
        env,
        tasks,
        {"n_adapt": config.n_adapt, "n_repeats": config.adapted_repeats, "deterministic": True},
        eval_seed,
        trace_keys=(),
    )
    return json_value(
        {
            "config": dataclasses.asdict(config),
            "eval_seed": eval_seed,
            "summary": combined_summary(prior, adapted),
            "crn_check": crn_check(prior, adapted),
            "prior": meta_test_record(prior),
            "adapted": meta_test_record(adapted),
            "wall_time_s": time.time() - start,
        }
    )


def combined_summary(prior: MetaTestResult, adapted: MetaTestResult) -> list[dict[str, Any]]:
    """The summary per k: k = 0 over the prior pass's rows, k >= 1 over the adapted pass's (its k = 0 dropped)."""
    info_keys = prior.info_keys
    k0 = [entry for entry in summarize(prior.rows, extra_keys=info_keys) if entry["k"] == 0]
    later = [entry for entry in summarize(adapted.rows, extra_keys=info_keys) if entry["k"] >= 1]
    for entry in later:  # cumulative counts over a sequence live in the adapted pass only; say so
        entry["cum_violations_source"] = "adapted pass"
    return [*k0, *later]


def crn_check(prior: MetaTestResult, adapted: MetaTestResult) -> dict[str, Any]:
    """Whether the adapted pass's k = 0 rows equal the prior pass's rows of the same (task, repeat)."""
    first = {(row["task"], row["repeat"]): row for row in prior.rows if int(row["k"]) == 0}
    compared = mismatched = 0
    for row in adapted.rows:
        if int(row["k"]) != 0:
            continue
        twin = first.get((row["task"], row["repeat"]))
        if twin is None:
            continue
        compared += 1
        mismatched += any(row.get(key) != twin.get(key) for key in MATCHED_COLUMNS)
    return {"compared": compared, "mismatched": mismatched, "matched": compared > 0 and mismatched == 0}


IDENTITY_KEYS = ("experiment", "family", "variant", "seed")


def remeasured_record_problem(path: Path, record: Any, result: Mapping[str, Any] | None = None) -> str | None:
    """
    Why a re-measured record cannot stand for the run of its folder, or None when it can.

    :param path: the record, ``<results-dir>/<experiment>/<family>/<variant>/seed<N>/<file>``
    :param record: its parsed content
    :param result: the run's ``result.json`` (None: its eval seed is not compared)
    :return: the problem, for a message naming the file
    """
    if not isinstance(record, dict):
        return "does not hold a record (a JSON object)"
    summary = record.get("summary")
    if not isinstance(summary, list) or not summary or not all(isinstance(e, dict) and "k" in e for e in summary):
        return "lacks its summary (entries per k)"
    missing = [key for key in IDENTITY_KEYS if key not in record]
    if missing:
        return f"lacks {missing}, which tell the run it was measured from"
    try:
        check_result_path(path, record)
    except ValueError as error:
        parts = Path(path).parts
        if len(parts) < 5:
            return str(error).removeprefix(f"{path} ")
        found = {**{key: record[key] for key in IDENTITY_KEYS[:3]}, "seed": f"seed{record['seed']}"}
        expected = dict(zip(IDENTITY_KEYS, parts[-5:-1]))
        wrong = [
            f"{key} {found[key]!r} (its folder says {expected[key]!r})" for key in IDENTITY_KEYS if found[key] != expected[key]
        ]
        return f"holds the record of another run: {', '.join(wrong)} (a copied file?)"
    if result is not None and "eval_seed" in result and record.get("eval_seed") != result["eval_seed"]:
        return f"was measured with eval seed {record.get('eval_seed')!r}, the run's result.json says {result['eval_seed']!r}"
    return None


def _record_problem(path: Path, result: Mapping[str, Any] | None) -> tuple[dict[str, Any] | None, str | None]:
    """The record at ``path`` (None when it cannot be read) and why it cannot stand for its run (None: it can)."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as error:
        return None, f"cannot be read ({error})"
    if not text.strip():
        return None, "is empty"
    try:
        record = json.loads(text)
    except json.JSONDecodeError as error:
        return None, f"is not valid JSON ({error})"
    problem = remeasured_record_problem(path, record, result)
    return (record if problem is None else None), problem


def read_remeasured(
    folder: str | Path, result: Mapping[str, Any] | None = None, file_name: str = MERGE_REMEASURE.file_name
) -> dict[str, Any] | None:
    """
    The run's re-measured record (``meta_test_large.json``), or None: none in the folder, or one that cannot stand for
    the run (:func:`remeasured_record_problem`: empty, unparsable, without summary, another run's, another eval seed),
    which is skipped with a warning naming the file; the run then counts as not re-measured.

    :param folder: the run folder
    :param result: the run's ``result.json`` (its eval seed must be the record's), if the caller has read it
    :param file_name: the record's file name
    :return: the record, or None
    """
    path = Path(folder, file_name)
    if not path.is_file():
        return None
    record, problem = _record_problem(path, result)
    if problem is not None:
        warnings.warn(
            f"{path} {problem}: skipped, the run counts as not re-measured (`python -m pearl_paper.reproduce remeasure` "
            "measures it again)",
            stacklevel=2,
        )
        return None
    return record


def remeasure_run(
    folder: Path, config: RemeasureConfig, force: bool = False, echo: Callable[[str], None] = print
) -> Path | None:
    """
    Remeasure the finished run in ``folder`` (``result.json`` present) unless its record exists (``force``: again).

    A record that is empty, unparsable or not the run's (:func:`remeasured_record_problem`) does not count: the run is
    measured again, and ``echo`` says why.

    :param folder: the run folder
    :param config: the design
    :param force: measure again when the record exists
    :param echo: progress output
    :return: the record written, or None (no finished run, or already measured)
    """

    out = folder / config.file_name
    if not (folder / RESULT_FILE).is_file():
        return None
    result = read_run_result(folder / RESULT_FILE)  # refused if it is not the result of its folder's run
    if out.is_file() and not force:
        _, problem = _record_problem(out, result)
        if problem is None:
            return None
        echo(f"{out} {problem}: measuring it again")
    record = measure_committed_model(
        folder, result, lambda model, env: remeasure_model(model, env, int(result["eval_seed"]), config, what=str(folder))
    )
    write_json_atomic(out, record)
    return out


def measure_committed_model(
    folder: Path, result: Mapping[str, Any], measure: Callable[[Any, gym.Env], dict[str, Any]]
) -> dict[str, Any]:
    """
    Load the finished run's model and its family's env (the run's env kwargs), ``measure`` them, and return the record
    with the run it was measured from, the package versions and the CPU: what ``remeasure`` and ``velocity`` share.

    :param folder: the run folder
    :param result: the run's ``result.json``
    :param measure: (model, env) -> the record
    :return: the record, identified
    """
    from pearl_paper.experiments import get_experiment
    from sb3_pearl.registry import algorithm_class

    experiment = get_experiment(result["experiment"])
    family = experiment.family(result["family"])
    algo = experiment.variant(result["variant"]).algo
    env_kwargs = dict(result.get("spec", {}).get("family", {}).get("env_kwargs") or family.env_kwargs)
    model = algorithm_class(algo).load(folder / MODEL_FILE, device="cpu")  # type: ignore[attr-defined]
    env = gym.make(family.env_id, **env_kwargs)
    try:
        record = measure(model, env)
    finally:
        env.close()
    identity = {key: result[key] for key in ("experiment", "family", "variant", "seed")}
    return {**record, **identity, "algo": algo, "env_kwargs": env_kwargs, "versions": package_versions(), "cpu": cpu_info()}


def remeasure_experiments(
    results_dir: str | Path,
    experiments: Sequence[str],
    config: RemeasureConfig,
    seeds: Sequence[int] | None = None,
    force: bool = False,
    echo: Callable[[str], None] = print,
) -> list[Path]:
    """
    Remeasure every finished run the experiments declare (their shared variants in their owners' folders), under
    each run's lock (a run being trained is skipped and reported).

    :param results_dir: root of the results layout
    :param experiments: experiment names
    :param config: the design
    :param seeds: model seeds (None: each experiment's declared seeds)
    :param force: measure runs that have a record again
    :param echo: progress output
    :return: the records written
    """
    return measure_finished_runs(
        results_dir,
        experiments,
        lambda folder: remeasure_run(folder, config, force, echo),
        seeds,
        echo=echo,
        verb="remeasured",
    )


def measure_finished_runs(
    results_dir: str | Path,
    experiments: Sequence[str],
    measure: Callable[[Path], Path | None],
    seeds: Sequence[int] | None = None,
    families: Callable[[str], bool] | None = None,
    echo: Callable[[str], None] = print,
    verb: str = "measured",
) -> list[Path]:
    """
    Run ``measure`` on every finished run the experiments declare (their shared variants in their owners' folders,
    each once), under each run's lock (a run being trained is skipped and reported): what ``remeasure`` and
    ``velocity`` share.

    :param results_dir: root of the results layout
    :param experiments: experiment names
    :param measure: run folder -> the record written, or None (nothing to do)
    :param seeds: model seeds (None: each experiment's declared seeds)
    :param families: which family names to measure (None: all)
    :param echo: progress output
    :param verb: the progress line's verb
    :return: the records written
    """
    from pearl_paper.experiments import get_experiment
    from pearl_paper.reproduce.layout import RunKey, run_dir
    from pearl_paper.reproduce.ownership import RunLockedError, run_lock

    root = Path(results_dir)
    if not root.is_dir():
        raise ValueError(f"results dir {root} does not exist or is not a folder: pass --results-dir")
    folders: dict[Path, None] = {}  # shared runs appear once, in declaration order
    for name in experiments:
        experiment = get_experiment(name)
        for family in experiment.families:
            if families is not None and not families(family.name):
                continue
            for variant in experiment.variants:
                for seed in experiment.seeds_of(variant.name, family.name) if seeds is None else seeds:
                    key = RunKey(experiment.owner(variant.name), family.name, variant.name, seed)
                    folders[run_dir(root, key)] = None
    written: list[Path] = []
    for folder in folders:
        if not (folder / RESULT_FILE).is_file():
            continue
        try:
            with run_lock(folder, wait_s=0.0):
                start = time.time()
                out = measure(folder)
        except RunLockedError as error:
            echo(f"skip {folder}: {error}")
            continue
        if out is not None:
            written.append(out)
            echo(f"{verb} {folder} in {time.time() - start:.0f} s")
    return written
