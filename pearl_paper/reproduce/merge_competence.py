"""Competence against the oracle on Highway-Merge, the family without a velocity: rule 3 of the oracle rules.

:data:`~pearl_paper.experiments.oracle.COMPETENCE_RULES` (committed before the oracle's runs) judges Highway-Merge from
the runs' own meta-tests, which share the held-out tasks (``merge-table1``'s eval seed: 20 tasks x 10 repeats,
k = 0..5): the oracle is competent if its adapted (k >= 1) failure rate (a crash or a failure to merge: the family's
violation) is at most ``merge_max_failure``; PEARL (or PEARL+) is competent if its k >= 1 failure rate is at most the
oracle's plus ``merge_failure_margin`` and its k >= 1 return at least the oracle's minus ``merge_return_fraction`` of
|the oracle's|. Each value is the mean over the seeds of each run's mean over its k >= 1 trajectories.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pearl_paper.experiments import get_experiment
from pearl_paper.experiments.oracle import COMPETENCE_RULES, ORACLE_MERGE, CompetenceRules
from pearl_paper.reproduce.layout import RESULT_FILE, RunKey, read_run_result, run_dir

MERGE_JUDGED_RUNS: tuple[tuple[str, str, str], ...] = (
    ("PEARL", "merge-table1", "pearl-fixed-entropy"),
    ("PEARL+", "merge-table1", "pearlplus-fixed-entropy"),
    ("Fine-Tune", "merge-columns", "finetune"),
    ("MAML", "merge-columns", "maml"),
)
"""The meta-learners judged against the Merge oracle: (label, experiment, variant), Table I's Merge runs, whose eval seed
(and so held-out tasks) the oracle's experiment shares; Table I's other columns (``merge-columns``, the same eval seed)
by the same rule beside them."""


@dataclass(frozen=True)
class MergeRun:
    """One run's meta-test on Highway-Merge: its failure rates (k = 0 and k >= 1) and k >= 1 return."""

    seed: int
    prior_failure: float
    adapted_failure: float
    adapted_return: float


def merge_run(rows: Sequence[Mapping[str, Any]], seed: int) -> MergeRun:
    """
    A run's rates from its meta-test rows (``violated`` is a crash or a failure to merge on this family).

    :param rows: the rows of its ``result.json``'s ``meta_test``
    :param seed: the run's model seed
    """
    prior = [row for row in rows if int(row["k"]) == 0]
    adapted = [row for row in rows if int(row["k"]) >= 1]
    if not prior or not adapted:
        raise ValueError(f"seed {seed}: a meta-test with k = 0 and k >= 1 rows is needed, got {len(rows)} rows")
    return MergeRun(
        seed=seed,
        prior_failure=float(np.mean([bool(row["violated"]) for row in prior])),
        adapted_failure=float(np.mean([bool(row["violated"]) for row in adapted])),
        adapted_return=float(np.mean([float(row["return"]) for row in adapted])),
    )


def read_merge_runs(results_dir: str | os.PathLike[str], experiment: str, variant: str) -> list[MergeRun]:
    """
    The finished runs of one variant on Highway-Merge, in seed order (runs without a result left out).

    :param results_dir: root of the results layout
    :param experiment: the experiment that declares the variant (its runs may live in another that owns them)
    :param variant: the variant name
    :return: the runs
    """
    spec = get_experiment(experiment)
    owner = spec.owner(variant)
    runs = []
    family = ORACLE_MERGE.families[0].name
    for seed in spec.seeds_of(variant, family):
        path = run_dir(results_dir, RunKey(owner, family, variant, seed)) / RESULT_FILE
        if path.is_file():
            runs.append(merge_run(read_run_result(path)["meta_test"]["rows"], seed))
    return runs


@dataclass(frozen=True)
class MergeVerdicts:
    """Rule 3's verdicts in words: the oracle's, and each judged meta-learner's (label -> verdict)."""

    oracle: str
    competent: dict[str, str]


def _mean(runs: Sequence[MergeRun], name: str) -> float:
    return float(np.mean([getattr(run, name) for run in runs]))


def merge_verdicts(
    runs: Mapping[str, Sequence[MergeRun]],
    rules: CompetenceRules = COMPETENCE_RULES,
    n_oracle_seeds: int = len(ORACLE_MERGE.seeds),
) -> MergeVerdicts:
    """
    Apply rule 3 to the runs of the oracle (key ``"oracle"``) and of the judged meta-learners.

    :param runs: label -> its runs; ``"oracle"`` must be present with at least one run
    :param rules: the rules
    :param n_oracle_seeds: the oracle seeds declared; fewer make every verdict provisional
    :return: the verdicts, as words
    """
    oracle = runs.get("oracle")
    if not oracle:
        raise ValueError("merge_verdicts needs at least one oracle run (key 'oracle')")
    note = f" (provisional: {len(oracle)} of {n_oracle_seeds} oracle seeds)" if len(oracle) < n_oracle_seeds else ""
    oracle_failure, oracle_return = _mean(oracle, "adapted_failure"), _mean(oracle, "adapted_return")
    oracle_ok = oracle_failure <= rules.merge_max_failure
    competent = {}
    for label, label_runs in runs.items():
        if label == "oracle" or not label_runs:
            continue
        failure_ok = _mean(label_runs, "adapted_failure") <= oracle_failure + rules.merge_failure_margin
        return_ok = _mean(label_runs, "adapted_return") >= oracle_return - rules.merge_return_fraction * abs(oracle_return)
        reasons = [] if failure_ok else ["fails more"]
        reasons += [] if return_ok else ["returns less"]
        competent[label] = ("competent" if not reasons else "not competent: " + " and ".join(reasons)) + note
    return MergeVerdicts(oracle=("competent" if oracle_ok else "not competent") + note, competent=competent)


def merge_competence_section(results_dir: str | os.PathLike[str], rules: CompetenceRules = COMPETENCE_RULES) -> list[str]:
    """
    The markdown of rule 3 on Highway-Merge (empty while no oracle run is finished).

    :param results_dir: root of the results layout
    :param rules: the rules
    :return: the lines
    """
    oracle_variant = ORACLE_MERGE.variants[0].name
    runs = {"oracle": read_merge_runs(results_dir, ORACLE_MERGE.name, oracle_variant)}
    if not runs["oracle"]:
        return []
    runs.update({label: read_merge_runs(results_dir, exp, variant) for label, exp, variant in MERGE_JUDGED_RUNS})
    verdicts = merge_verdicts(runs, rules)
    oracle_failure = _mean(runs["oracle"], "adapted_failure")
    oracle_return = _mean(runs["oracle"], "adapted_return")
    out = [
        "#### Highway-Merge",
        "",
        f"From each run's own meta-test (the same 20 held-out tasks x 10 repeats). The oracle is competent if its k >= 1 "
        f"failure rate (crash or no merge) is at most {100 * rules.merge_max_failure:.0f}%; any other agent if its k >= 1 "
        f"failure rate is at most the oracle's + {100 * rules.merge_failure_margin:.0f} points "
        f"({100 * (oracle_failure + rules.merge_failure_margin):.1f}%) and its k >= 1 return at least the oracle's "
        f"- {100 * rules.merge_return_fraction:.0f}% of |the oracle's| "
        f"({oracle_return - rules.merge_return_fraction * abs(oracle_return):.2f}).",
        "",
        "| agent (seeds) | failures k >= 1 [seed range] | failures k = 0 | return k >= 1 | verdict |",
        "|---|---|---|---|---|",
    ]
    for label, label_runs in runs.items():
        if not label_runs:
            continue
        failures = [100 * run.adapted_failure for run in label_runs]
        verdict = verdicts.oracle if label == "oracle" else verdicts.competent[label]
        out.append(
            f"| {'Oracle' if label == 'oracle' else label} ({len(label_runs)}) | {np.mean(failures):.1f}% "
            f"[{min(failures):.1f}, {max(failures):.1f}] | {100 * _mean(label_runs, 'prior_failure'):.1f}% "
            f"| {_mean(label_runs, 'adapted_return'):.2f} | {verdict} |"
        )
    return [*out, ""]


__all__ = ["MERGE_JUDGED_RUNS", "MergeRun", "MergeVerdicts", "merge_competence_section", "merge_run", "merge_verdicts"]
