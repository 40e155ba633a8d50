"""Table I's verdicts by the pre-written rules of :mod:`pearl_paper.experiments.table1_rules`.

:func:`decide` reads the runs of each decided family (Highway-Merge: ``merge-table1``, whose PEARL runs live in
``merge-premise``; Walker2D-vel at 500k: ``walker-table1``, whose PEARL runs live in ``pearl-reference``), applies the
premise gate, the "safer prior" and the "adapted as good" rules to the seeds both variants have, and
:func:`decision_section` writes the result for docs/results.md: the paper's rows beside ours, every seed's k = 0 rate
with its Wilson interval, the paired intervals and the verdict of every rule. On Highway-Merge the rules read the
re-measured meta-test (``meta_test_large.json``, ``reproduce remeasure``); the runs' own 200-trajectory numbers stay
beside them.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pearl_paper.experiments import get_experiment
from pearl_paper.experiments.table1_rules import DECIDED, MERGE_REMEASURE, RULES, DecisionRules
from pearl_paper.reproduce.formatting import format_interval, format_number, seed_count
from pearl_paper.reproduce.layout import RESULT_FILE, RunKey, read_run_result, run_dir
from pearl_paper.reproduce.remeasure import read_remeasured as read_remeasured_record
from pearl_paper.reproduce.stats import (
    Interval,
    clip_interval,
    paired_differences,
    sign_flip_can_reject,
    sign_flip_interval,
    t_interval,
)
from sb3_pearl.budgets import load_budget
from sb3_pearl.evaluation.statistics import wilson_interval

PAPER_KS = (0, 1, 3, 5)
SAFER, LESS_SAFE = "safer", "less safe"
AS_GOOD, WORSE = "as good", "worse"
INCONCLUSIVE = "inconclusive"
NOT_TESTED = "not tested (premise absent)"
PENDING = "pending"


@dataclass
class RunNumbers:
    """One run's meta-test numbers the rules read: per k, the violation rate (with its Wilson interval and count)
    and the mean return, from the re-measured record when the family reads one, else from result.json."""

    seed: int
    summary: dict[int, dict[str, Any]]
    own_summary: dict[int, dict[str, Any]]
    remeasured: bool
    velocity_error: float | None = None
    shift_k0_rate: float | None = None


@dataclass
class FamilyDecision:
    """The verdicts of one family, with every number they rest on."""

    family: str
    experiment: str
    variants: tuple[str, str]
    seeds_declared: tuple[int, ...]
    runs: dict[str, dict[int, RunNumbers]]
    paired_seeds: list[int]
    gate: str = PENDING
    gate_values: tuple[float, float] = (math.nan, math.nan)
    prior_interval: Interval | None = None
    prior_verdict: str = PENDING
    adapted_interval: Interval | None = None
    adapted_margin: float = math.nan
    adapted_verdict: str = PENDING
    prior_flip: Interval | None = None
    adapted_flip: Interval | None = None
    title: str = ""
    columns: dict[str, dict[int, RunNumbers]] = field(default_factory=dict)  # Fine-Tune and MAML (table1_columns)
    notes: list[str] = field(default_factory=list)


def _by_k(summary: list[dict[str, Any]]) -> dict[int, dict[str, Any]]:
    return {int(entry["k"]): entry for entry in summary}


def _velocity_error(result: dict[str, Any]) -> float | None:
    for criterion in (result.get("competence") or {}).get("criteria", []):
        if criterion.get("key") == "reward_forward":
            return float(criterion["value"])
    return None


def load_run(folder: Path, read_remeasured: bool) -> RunNumbers | None:
    """The numbers of the finished run in ``folder`` (None if unfinished, or if the family reads a re-measured record
    that is not there yet)."""
    if not (folder / RESULT_FILE).is_file():
        return None
    result = read_run_result(folder / RESULT_FILE)  # refused if it is not the result of its folder's run
    own = _by_k(result["meta_test"]["summary"])
    summary = own
    if read_remeasured:
        record = read_remeasured_record(folder, result)  # None: missing, empty, or another run's (warned)
        if record is None:
            return None
        summary = _by_k(record["summary"])
    shift = result.get("shift")
    return RunNumbers(
        seed=int(result["seed"]),
        summary=summary,
        own_summary=own,
        remeasured=read_remeasured,
        velocity_error=_velocity_error(result),
        shift_k0_rate=float(shift["summary"][0]["violation_rate"]) if shift else None,
    )


def _interval_side(interval: Interval, bound: float) -> int:
    """-1 if the interval lies entirely below ``bound``, +1 entirely above, 0 otherwise (or no interval)."""
    if interval.n < 2 or not (math.isfinite(interval.low) and math.isfinite(interval.high)):
        return 0
    if interval.high < bound:
        return -1
    if interval.low > bound:
        return 1
    return 0


def load_runs(
    experiment_name: str, family: str, names: tuple[str, str], seeds: tuple[int, ...], results_dir: str | os.PathLike[str]
) -> dict[str, dict[int, RunNumbers]]:
    """
    The finished runs of two variants of an experiment on one family (Highway-Merge: re-measured runs only).

    :param experiment_name: the experiment (shared variants are read from their owners' folders)
    :param family: the family name
    :param names: the two variants, the reference first
    :param seeds: the seeds to read
    :param results_dir: root of the results layout
    :return: variant -> seed -> numbers
    """
    experiment = get_experiment(experiment_name)
    read_remeasured = family == "highway-merge"
    runs: dict[str, dict[int, RunNumbers]] = {}
    for name in names:
        runs[name] = {}
        for seed in seeds:
            folder = run_dir(results_dir, RunKey(experiment.owner(name), family, name, seed))
            numbers = load_run(folder, read_remeasured)
            if numbers is not None:
                runs[name][seed] = numbers
    return runs


def decide_family(
    family: str,
    results_dir: str | os.PathLike[str],
    rules: DecisionRules = RULES,
    seeds: tuple[int, ...] | None = None,
) -> FamilyDecision:
    """
    Apply the rules to one decided family (module docstring).

    :param family: a family name of :data:`~pearl_paper.experiments.table1_rules.DECIDED`
    :param results_dir: root of the results layout
    :param rules: the rules
    :param seeds: decide on these seeds only (None: the declared ones, with the extension rule)
    :return: the decision
    """
    experiment_name, names = DECIDED[family]
    experiment = get_experiment(experiment_name)
    first, extended = rules.extend_seeds.get(family, (experiment.seeds, experiment.seeds))
    if seeds is not None:
        first = extended = seeds
    runs = load_runs(experiment_name, family, names, tuple(sorted(set(first) | set(extended))), results_dir)
    columns = load_columns(family, results_dir)

    def on(decided: tuple[int, ...]) -> FamilyDecision:
        """The rules on the runs of these seeds only (a seed outside them is not read, whatever is on disk)."""
        chosen = {name: {s: run for s, run in by_seed.items() if s in decided} for name, by_seed in runs.items()}
        decision = FamilyDecision(family, experiment_name, names, tuple(decided), chosen, [], columns=columns)
        return apply_rules(decision, rules, tuple(decided))

    decision = on(tuple(first))
    if set(extended) == set(first) or not set(first) <= set(decision.paired_seeds):
        return decision
    if INCONCLUSIVE not in (decision.prior_verdict, decision.adapted_verdict):
        reason = "the premise gate fails (not tested)" if decision.gate == "fails" else "no verdict inconclusive"
        decision.notes.append(f"final at {len(first)} seeds: {reason}, so no extension")
        return decision
    # the extension rule: a verdict inconclusive on the first seeds -> decided on the extended seeds, final there
    at_first = f"prior {decision.prior_verdict}, adapted {decision.adapted_verdict}"
    decision = on(tuple(extended))
    if set(extended) <= set(decision.paired_seeds):
        decision.notes.append(f"extended to seeds {tuple(extended)} by the rule (at {len(first)} seeds: {at_first}); final")
    else:
        missing = sorted(set(extended) - set(decision.paired_seeds))
        decision.notes.append(
            f"a verdict was inconclusive at {len(first)} seeds ({at_first}): by the rule, extend to seeds "
            f"{tuple(extended)}; provisional until they are paired ({missing} missing)"
        )
    return decision


def load_columns(family: str, results_dir: str | os.PathLike[str]) -> dict[str, dict[int, RunNumbers]]:
    """
    Table I's Fine-Tune and MAML columns on a decided family (:mod:`pearl_paper.experiments.table1_columns`), from each
    run's own meta-test (the rows' 20 held-out tasks x 10 prior draws); no rule reads them.

    :param family: a decided family
    :param results_dir: root of the results layout
    :return: variant -> seed -> numbers (empty before the runs)
    """
    from pearl_paper.experiments.table1_columns import MERGE_COLUMNS, WALKER_COLUMNS

    experiment = next((e for e in (WALKER_COLUMNS, MERGE_COLUMNS) if e.families[0].name == family), None)
    if experiment is None:
        return {}
    columns: dict[str, dict[int, RunNumbers]] = {}
    for variant in experiment.variants:
        columns[variant.name] = {}
        for seed in experiment.seeds:
            numbers = load_run(run_dir(results_dir, RunKey(experiment.name, family, variant.name, seed)), False)
            if numbers is not None:
                columns[variant.name][seed] = numbers
    return columns


def decide_confirmation(results_dir: str | os.PathLike[str], pooled: bool = False) -> FamilyDecision:
    """
    Highway-Merge's fresh-seed confirmation (:mod:`pearl_paper.experiments.merge_confirm`): Table I's rules on seeds
    10-19 alone, "pending" until all 10 pairs are in; ``pooled``: on the 20 seeds of ``merge-table1`` and
    ``merge-confirm`` together (secondary).

    :param results_dir: root of the results layout
    :param pooled: the pooled 20-seed decision instead
    :return: the decision
    """
    from pearl_paper.experiments.merge_confirm import CONFIRM_RULES, CONFIRMED_FAMILY, CONFIRMED_VARIANTS, MERGE_CONFIRM

    runs = load_runs(MERGE_CONFIRM.name, CONFIRMED_FAMILY, CONFIRMED_VARIANTS, MERGE_CONFIRM.seeds, results_dir)
    seeds = MERGE_CONFIRM.seeds
    title = "Highway-Merge confirmation, fresh seeds 10-19"
    if pooled:
        original_name, _ = DECIDED[CONFIRMED_FAMILY]
        original = get_experiment(original_name)
        earlier = load_runs(original_name, CONFIRMED_FAMILY, CONFIRMED_VARIANTS, original.seeds, results_dir)
        runs = {name: {**earlier[name], **runs[name]} for name in CONFIRMED_VARIANTS}
        seeds = tuple(original.seeds) + tuple(seeds)
        title = "Highway-Merge pooled, seeds 0-19 (secondary)"
    decision = FamilyDecision(CONFIRMED_FAMILY, MERGE_CONFIRM.name, CONFIRMED_VARIANTS, seeds, runs, [], title=title)
    decision = apply_rules(decision, CONFIRM_RULES, tuple(seeds))
    paired = len(decision.paired_seeds)
    if not pooled and paired < len(seeds):
        pending = f"{PENDING} ({paired} of {len(seeds)} pairs finished)"
        decision.prior_verdict = decision.adapted_verdict = pending
    return decision


def apply_rules(decision: FamilyDecision, rules: DecisionRules, seeds: tuple[int, ...]) -> FamilyDecision:
    """
    The premise gate, "safer prior" and "adapted as good" on the runs of ``decision`` (module docstring), with the
    sign-flip permutation intervals beside the t intervals (reported; the t intervals decide); the gate and both
    verdicts read the same paired seeds. The extension rule is :func:`decide_family`'s.

    :param decision: the decision, its runs loaded
    :param rules: the rules
    :param seeds: the seeds the verdicts are decided on ("provisional" while some are not paired)
    :return: ``decision``, filled in
    """
    family, runs = decision.family, decision.runs
    reference, variant = decision.variants
    paired = sorted(set(runs[reference]) & set(runs[variant]))
    decision.paired_seeds = paired
    pearl = runs[reference]
    adapted_k, prior_k = rules.adapted_k, rules.prior_k
    if len(paired) >= 2:
        k0 = sum(pearl[s].summary[prior_k]["violation_rate"] for s in paired) / len(paired)
        k5 = sum(pearl[s].summary[adapted_k]["violation_rate"] for s in paired) / len(paired)
        decision.gate_values = (k0, k5)
        decision.gate = "holds" if rules.gates[family].holds(k0, k5) else "fails"
    if len(paired) < 2:
        decision.notes.append(f"{len(paired)} paired seed(s): the rules need at least 2")
        return decision
    if decision.gate == "fails":
        decision.prior_verdict = decision.adapted_verdict = NOT_TESTED
    prior_diff = list(
        paired_differences(
            {s: runs[variant][s].summary[prior_k]["violation_rate"] for s in paired},
            {s: pearl[s].summary[prior_k]["violation_rate"] for s in paired},
        ).values()
    )
    decision.prior_interval = t_interval(prior_diff, rules.confidence)
    decision.prior_flip = sign_flip_interval(prior_diff, rules.confidence, bounds=(-1.0, 1.0))
    return_diff = list(
        paired_differences(
            {s: runs[variant][s].summary[adapted_k]["return_mean"] for s in paired},
            {s: pearl[s].summary[adapted_k]["return_mean"] for s in paired},
        ).values()
    )
    decision.adapted_interval = t_interval(return_diff, rules.confidence)
    decision.adapted_flip = sign_flip_interval(return_diff, rules.confidence)
    pearl_return = sum(pearl[s].summary[adapted_k]["return_mean"] for s in paired) / len(paired)
    decision.adapted_margin = rules.return_margin_fraction * abs(pearl_return)
    if decision.gate == "holds":
        side = _interval_side(decision.prior_interval, 0.0)
        decision.prior_verdict = {-1: SAFER, 1: LESS_SAFE, 0: INCONCLUSIVE}[side]
        side = _interval_side(decision.adapted_interval, -decision.adapted_margin)
        decision.adapted_verdict = {1: AS_GOOD, -1: WORSE, 0: INCONCLUSIVE}[side]
    if not set(seeds) <= set(paired):
        decision.notes.append(
            f"provisional: {len(paired)} of the {len(seeds)} seeds paired ({sorted(set(seeds) - set(paired))} missing)"
        )
    return decision


def decide(results_dir: str | os.PathLike[str], rules: DecisionRules = RULES) -> list[FamilyDecision]:
    """The decision of every family of :data:`~pearl_paper.experiments.table1_rules.DECIDED`."""
    return [decide_family(family, results_dir, rules) for family in DECIDED]


# Each decided family's entry of the `paper` preset (the paper's / the reference implementation's budget), against
# which the `cpu` runs' reductions are stated.
PAPER_FAMILY = {"highway-merge": "highway-merge", "walker2d-vel-long": "walker2d-vel"}


def _size(arch: Any) -> str:
    return f"{len(arch)}x{arch[0]}" if arch and len(set(arch)) == 1 else "x".join(map(str, arch or []))


def _budget_facts(entry: dict[str, Any]) -> dict[str, str]:
    kwargs = entry["kwargs"]
    return {
        "env steps": f"{entry['n_timesteps']:,}",
        "actor and critics": _size(kwargs.get("policy_kwargs", {}).get("net_arch")),
        "prior critic": _size(kwargs.get("prior_critic_arch")),
        "encoder": _size(kwargs.get("encoder_arch")),
        "RL rows a gradient step": f"{kwargs['meta_batch']} tasks x {kwargs['batch_size']}",
        "gradient steps an iteration": str(kwargs["num_train_steps_per_itr"]),
    }


def reductions(family: str, preset: str = "cpu", algo: str = "pearlplus") -> str:
    """
    What the decided family's runs reduced against the paper's budget: every setting of :func:`_budget_facts` where the
    ``preset`` entry differs from the ``paper`` preset's entry of the paper's family (:data:`PAPER_FAMILY`).

    :param family: a family of :data:`~pearl_paper.experiments.table1_rules.DECIDED`
    :param preset: the runs' budget preset
    :param algo: the algorithm whose entry is compared
    :return: one sentence, e.g. ``env steps 100,000 (paper 1,000,000), ...``
    """
    ours = _budget_facts(load_budget(preset, family, algo))
    paper = _budget_facts(load_budget("paper", PAPER_FAMILY[family], algo))
    changed = [f"{name} {value} (paper {paper[name]})" for name, value in ours.items() if value != paper[name]]
    return ", ".join(changed) if changed else "nothing"


def _pct(value: float) -> str:
    return format_number(value, 1, scale=100.0)


def _num(value: float) -> str:
    return format_number(value, 2)


def _interval(interval: Interval | None, scale: float = 1.0, digits: int = 1) -> str:
    if interval is None or interval.n == 0:
        return "-"
    mean = f"{scale * interval.mean:+.{digits}f}"
    if interval.n < 2 or not math.isfinite(interval.low):
        return mean
    return f"{mean} [{scale * interval.low:+.{digits}f}, {scale * interval.high:+.{digits}f}]"


def _bounds(interval: Interval | None, scale: float = 1.0, digits: int = 1) -> str:
    """``[low, high]`` of an interval (the mean is the t interval's, given beside it)."""
    if interval is None or interval.n < 2 or math.isnan(interval.low):
        return "-"
    if math.isinf(interval.low) or math.isinf(interval.high):
        return f"unbounded: no shift is rejected at {interval.n} seeds"
    return f"[{interval.low * scale:+.{digits}f}, {interval.high * scale:+.{digits}f}]"


def _entries(runs: dict[int, RunNumbers], k: int, own: bool = False) -> list[dict[str, Any]]:
    """Each run's summary entry at trajectory ``k`` (its own meta-test's with ``own``), the runs that have one."""
    return [
        (run.own_summary if own else run.summary)[k] for run in runs.values() if k in (run.own_summary if own else run.summary)
    ]


def _mean(runs: dict[int, RunNumbers], k: int, key: str, own: bool = False) -> float:
    values = [(run.own_summary if own else run.summary)[k][key] for run in runs.values() if k in run.summary]
    return sum(values) / len(values) if values else math.nan


def _column_label(name: str) -> str:
    """A Fine-Tune or MAML column's label, as :mod:`pearl_paper.experiments.table1_columns` declares its variant."""
    from pearl_paper.experiments.table1_columns import COLUMNS

    return next(variant.label for variant in COLUMNS if variant.name == name)


def rate_cell(entries: list[dict[str, Any]], rules: DecisionRules = RULES) -> str:
    """
    One Table I cell of a column over seeds: the mean violation rate (%) and its t interval over the seeds, clipped to
    0-100; where every seed has the same rate (a t interval of width 0 says nothing), the Wilson interval of all the
    seeds' trajectories pooled instead, marked so.

    :param entries: one meta-test summary entry per seed at this k (``violation_rate``, ``n``)
    :param rules: the confidence of the interval
    """
    rates = [float(entry["violation_rate"]) for entry in entries]
    if len(rates) < 2:
        return _pct(rates[0]) if rates else "-"
    if max(rates) == min(rates):
        n = sum(int(entry["n"]) for entry in entries)
        low, high = wilson_interval(round(sum(rate * int(entry["n"]) for rate, entry in zip(rates, entries))), n)
        return f"{_pct(rates[0])} [{_pct(low)}, {_pct(high)}] (Wilson, {n} pooled)"
    rate = clip_interval(t_interval(rates, rules.confidence))
    return f"{_pct(rate.mean)} [{_pct(rate.low)}, {_pct(rate.high)}]"


def return_cell(entries: list[dict[str, Any]], rules: DecisionRules = RULES) -> str:
    """
    One Table I return cell of a column over seeds: the mean return and its t interval over the seeds (the value alone
    at one seed).

    :param entries: one meta-test summary entry per seed at this k (``return_mean``)
    :param rules: the confidence of the interval
    """
    returns = [float(entry["return_mean"]) for entry in entries]
    return format_interval(t_interval(returns, rules.confidence), digits=2) if returns else "-"  # one seed: the mean


def decision_section(decisions: list[FamilyDecision], rules: DecisionRules = RULES) -> list[str]:
    """The markdown of the decisions (one table per family, then the verdicts)."""
    from pearl_paper.experiments.table1 import TABLE1

    out = [
        "Rules written before the runs: `pearl_paper/experiments/table1_rules.py` (premise gate; **safer prior**: the 95% "
        "t interval of the paired k = 0 violation difference, PEARL+ minus PEARL, below 0; **adapted as good**: the "
        f"paired k = {rules.adapted_k} return difference above -{rules.return_margin_fraction:.0%} of |PEARL's k = "
        f"{rules.adapted_k} return|). Violation rates in %.",
        "",
    ]
    for decision in decisions:
        reference, variant = decision.variants
        experiment = get_experiment(decision.experiment)
        paper_family = "walker2d-vel" if decision.family.startswith("walker2d-vel") else decision.family
        source = (
            f"re-measured: {MERGE_REMEASURE.n_tasks} held-out tasks x {MERGE_REMEASURE.prior_repeats} prior draws at k = 0, "
            f"x {MERGE_REMEASURE.adapted_repeats} at k >= 1, common random numbers"
            if decision.family == "highway-merge"
            else "the runs' own meta-test: 20 held-out tasks x 10 prior draws, common random numbers"
        )
        out += [
            f"#### {decision.title or experiment.family(decision.family).title} ({decision.experiment}; paired seeds "
            f"{decision.paired_seeds})",
            "",
            f"Numbers: {source}.",
            "",
            "| row | " + " | ".join(f"k = {k}" for k in PAPER_KS) + " | k = 5 return |",
            "|---|" + "---|" * (len(PAPER_KS) + 1),
        ]
        for name in (reference, variant):
            paper = {
                cell.k: cell.value
                for cell in TABLE1.paper
                if cell.family == paper_family and cell.variant == name.replace("-fixed-entropy", "")
            }
            label = experiment.variant(name).label
            runs = decision.runs[name]
            out.append(f"| paper: {label} | " + " | ".join(_pct(paper.get(k, math.nan)) for k in PAPER_KS) + " | - |")
            ours = " | ".join(rate_cell(_entries(runs, k), rules) for k in PAPER_KS)
            returns = return_cell(_entries(runs, 5), rules)
            out.append(f"| ours: {label} ({seed_count(len(runs))}) | {ours} | {returns} |")
            if decision.family == "highway-merge":
                old = " | ".join(_pct(_mean(runs, k, "violation_rate", own=True)) for k in PAPER_KS)
                out.append(f"| ours, old meta-test (200 a k): {label} | {old} | {_num(_mean(runs, 5, 'return_mean', True))} |")
        for name, runs in decision.columns.items():  # Table I's other columns: reported, no rule
            paper = {cell.k: cell.value for cell in TABLE1.paper if cell.family == paper_family and cell.variant == name}
            label = _column_label(name)
            out.append(f"| paper: {label} | " + " | ".join(_pct(paper.get(k, math.nan)) for k in PAPER_KS) + " | - |")
            if not runs:
                out.append(f"| ours: {label} | " + " | ".join("pending" for _ in PAPER_KS) + " | pending |")
                continue
            cells, flips = [], []
            for k in PAPER_KS:
                entries = _entries(runs, k, own=True)
                cells.append(rate_cell(entries, rules))
                if len(entries) >= 2 and sign_flip_can_reject(len(entries), rules.confidence):
                    rates = [entry["violation_rate"] for entry in entries]
                    flip = sign_flip_interval(rates, rules.confidence, bounds=(0.0, 1.0))
                    flips.append(f"[{_pct(flip.low)}, {_pct(flip.high)}]")
                else:
                    flips.append("-")
            returns = return_cell(_entries(runs, 5, own=True), rules)
            out.append(f"| ours: {label} ({seed_count(len(runs))}) | {' | '.join(cells)} | {returns} |")
            if any(flip != "-" for flip in flips):
                out.append(f"| ours: {label}, sign-flip interval | {' | '.join(flips)} | - |")
        out += ["", "Per seed, k = 0 violation rate % [Wilson 95%] (old 200-trajectory meta-test where re-measured):", ""]
        out += ["| seed | " + " | ".join(experiment.variant(n).label for n in decision.variants) + " |", "|---|---|---|"]
        for seed in sorted(set(decision.runs[reference]) | set(decision.runs[variant])):
            cells = []
            for name in decision.variants:
                run = decision.runs[name].get(seed)
                if run is None:
                    cells.append("-")
                    continue
                entry = run.summary[0]
                low, high = _pct(entry["violation_ci_low"]), _pct(entry["violation_ci_high"])
                cell = f"{_pct(entry['violation_rate'])} [{low}, {high}]"
                if run.remeasured:
                    cell += f" (old {_pct(run.own_summary[0]['violation_rate'])})"
                cells.append(cell)
            out.append(f"| {seed} | " + " | ".join(cells) + " |")
        out += ["", *decision_lines(decision, rules), *column_lines(decision, rules), ""]
    return out


def column_lines(decision: FamilyDecision, rules: DecisionRules = RULES) -> list[str]:
    """
    The Fine-Tune and MAML columns against the decided pair, reported and not decided
    (:mod:`pearl_paper.experiments.table1_columns`): per column and per reference (PEARL, PEARL+), the paired k = 0
    violation difference and k = 5 return difference over their common seeds, with the t and the sign-flip intervals.
    Both sides come from the runs' own meta-tests (the same held-out tasks, env seeds and prior draws), so a re-measured
    family's PEARL numbers here are its old meta-test's.

    :param decision: the family's decision, its columns loaded
    :param rules: the confidence of the intervals
    :return: markdown bullets (none before two paired seeds)
    """
    experiment = get_experiment(decision.experiment)
    adapted_k = rules.adapted_k
    out = []
    too_few: set[int] = set()  # paired seed counts at which a sign-flip test cannot reject
    for name, runs in decision.columns.items():
        label = _column_label(name)
        for reference in decision.variants:
            against = decision.runs[reference]
            seeds = sorted(set(runs) & set(against))
            if len(seeds) < 2:
                continue
            prior = paired_differences(
                {s: runs[s].own_summary[0]["violation_rate"] for s in seeds},
                {s: against[s].own_summary[0]["violation_rate"] for s in seeds},
            )
            adapted = paired_differences(
                {s: runs[s].own_summary[adapted_k]["return_mean"] for s in seeds},
                {s: against[s].own_summary[adapted_k]["return_mean"] for s in seeds},
            )
            prior_values, adapted_values = list(prior.values()), list(adapted.values())
            prior_flip = adapted_flip = ""
            if sign_flip_can_reject(len(seeds), rules.confidence):
                prior_flip = f"; sign-flip {_bounds(sign_flip_interval(prior_values, rules.confidence, (-1.0, 1.0)), 100)}"
                adapted_flip = f"; sign-flip {_bounds(sign_flip_interval(adapted_values, rules.confidence), 1, 2)}"
            else:
                too_few.add(len(seeds))
            out.append(
                f"- {label} - {experiment.variant(reference).label} (reported, no rule; own meta-tests, paired seeds "
                f"{seeds}): k = 0 violation rate {_interval(t_interval(prior_values, rules.confidence), 100)} points "
                f"(t{prior_flip}), k = {adapted_k} return {_interval(t_interval(adapted_values, rules.confidence), 1, 2)} "
                f"(t{adapted_flip})."
            )
    if too_few:
        n = max(too_few)
        out.append(
            f"- Where a difference shows no sign-flip interval, it cannot exclude anything at {n} paired seeds or fewer "
            f"(the smallest p-value of {n} signs is 2 / 2^{n} = {2 / 2**n:.3f}); the t interval assumes normal per-seed "
            "differences."
        )
    return out


def decision_lines(decision: FamilyDecision, rules: DecisionRules = RULES) -> list[str]:
    """
    The verdicts of one family as markdown bullets: the premise gate, "safer prior", "adapted as good" (each with the
    numbers it rests on), then what is reported beside the rules (the adapted policy's violations, the shift column,
    the velocity error) and the notes (provisional, extension).

    :param decision: the family's decision
    :param rules: the rules it was decided by
    :return: the lines
    """
    experiment = get_experiment(decision.experiment)
    k0, k5 = decision.gate_values
    shift = {n: [r.shift_k0_rate for r in decision.runs[n].values() if r.shift_k0_rate is not None] for n in decision.variants}
    velocity = {
        n: [r.velocity_error for r in decision.runs[n].values() if r.velocity_error is not None] for n in decision.variants
    }
    out = [
        f"- **Premise gate** ({rules.gates[decision.family].describe()}): **{decision.gate}** (PEARL k = 0 "
        f"{_pct(k0)}%, k = 5 {_pct(k5)}%).",
        f"- **Safer prior**: paired k = 0 difference {_interval(decision.prior_interval, 100)} points (t; sign-flip "
        f"{_bounds(decision.prior_flip, 100)}): **{decision.prior_verdict}**.",
        f"- **Adapted as good**: paired k = 5 return difference {_interval(decision.adapted_interval, 1, 2)} (t; "
        f"sign-flip {_bounds(decision.adapted_flip, 1, 2)}) against the margin -{_num(decision.adapted_margin)}: "
        f"**{decision.adapted_verdict}**.",
    ]
    reference, variant = decision.variants
    if len(decision.paired_seeds) >= 2:  # reported beside the rules, which judge the adapted policy by its return
        adapted_k = rules.adapted_k
        violations = paired_differences(
            {s: decision.runs[variant][s].summary[adapted_k]["violation_rate"] for s in decision.paired_seeds},
            {s: decision.runs[reference][s].summary[adapted_k]["violation_rate"] for s in decision.paired_seeds},
        )
        out.append(
            f"- Adapted policy's violations (reported, not a rule): k = {adapted_k} rate "
            f"{_pct(_mean(decision.runs[reference], adapted_k, 'violation_rate'))}% (PEARL) and "
            f"{_pct(_mean(decision.runs[variant], adapted_k, 'violation_rate'))}% (PEARL+), paired difference "
            f"{_interval(t_interval(list(violations.values()), rules.confidence), 100)} points."
        )
    if any(shift.values()):
        out.append(
            "- Shift column (k = 0 violation rate on the shifted tasks, mean over seeds): "
            + ", ".join(f"{experiment.variant(n).label} {_pct(sum(v) / len(v))}%" for n, v in shift.items() if v)
            + "."
        )
    if any(velocity.values()):
        out.append(
            "- Velocity error on training tasks (k >= 1, m/s; the family's 0.3 bar, reported, not a gate): "
            + ", ".join(f"{experiment.variant(n).label} {sum(v) / len(v):.2f}" for n, v in velocity.items() if v)
            + "."
        )
    out.append(
        f"- Reduced against the paper's budget (`{PAPER_FAMILY[decision.family]}` in the `paper` preset): "
        f"{reductions(decision.family)}."
    )
    out += [f"- {note}." for note in decision.notes]
    return out
