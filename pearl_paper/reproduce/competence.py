"""The competence check of a run: its family's criteria evaluated on a meta-test over training tasks."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from pearl_paper.experiments.spec import Criterion
from sb3_pearl.evaluation.meta_test import MetaTestResult


def criterion_value(result: MetaTestResult, criterion: Criterion) -> float:
    """
    The value a criterion measures on a meta-test (trajectories ``k >= criterion.min_k``).

    :param result: a meta-test run with the criterion's trace key among its ``trace_keys``
    :param criterion: the criterion
    :return: the value (nan if no trajectory has the key)
    """
    values: list[float] = []
    if criterion.kind == "row_mean":
        for row in result.rows:
            if int(row["k"]) >= criterion.min_k and criterion.key in row:
                value = float(row[criterion.key])
                if not math.isnan(value):
                    values.append(value)
    else:
        for trace in result.traces:
            series = trace.get(criterion.key)
            if int(trace["k"]) < criterion.min_k or not series:
                continue
            values.append(float(np.mean(series)) if criterion.kind == "trace_mean" else float(series[-1]))
    return criterion.scale * float(np.mean(values)) if values else math.nan


def evaluate_competence(result: MetaTestResult, criteria: Sequence[Criterion]) -> dict[str, Any]:
    """
    Every criterion's value against its threshold.

    :param result: the meta-test on training tasks
    :param criteria: the family's criteria
    :return: ``{"passed": all passed, "criteria": [{description, key, value, threshold, better, passed}]}``
    """
    entries = []
    for criterion in criteria:
        value = criterion_value(result, criterion)
        passed = (value <= criterion.threshold) if criterion.better == "lower" else (value >= criterion.threshold)
        entries.append(
            {
                "description": criterion.description,
                "key": criterion.key,
                "kind": criterion.kind,
                "value": value,
                "threshold": criterion.threshold,
                "better": criterion.better,
                "min_k": criterion.min_k,
                "passed": bool(passed) and not math.isnan(value),
            }
        )
    return {"passed": all(e["passed"] for e in entries), "criteria": entries}
