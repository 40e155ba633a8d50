"""The prior-critic part of ``reproduce report``: the measures per variant and the pre-written selection rule.

:func:`prior_critic_table` shows, per variant of a group, the calibration of the prior term's critic and the
prior-optimality gap (result.json ``prior_critic``, :mod:`pearl_paper.reproduce.prior_measures`); a family whose bar
is a variant (Walker2D-vel: Fine-Tune) is paired with that variant's run of the same seed. :func:`selection_table`
applies the selection rule of docs/pearl.md ("The selection rule", written before the runs) to the ``prior-critic``
experiment: training-task measures only.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

from pearl_paper.experiments.prior_critic import DESIGNS, design_variant
from pearl_paper.experiments.spec import VIOLATION_MARGIN, Experiment
from pearl_paper.reproduce.cells import last_k, seed_values
from pearl_paper.reproduce.formatting import format_number
from pearl_paper.reproduce.stats import (
    REPRODUCED,
    Interval,
    mean_finite,
    median_finite,
    paired_differences,
    t_interval,
    verdict,
)

Group = Mapping[str, Mapping[int, dict[str, Any]]]

CALIBRATED_RELATIVE_ERROR = 0.25  # docs/pearl.md, the selection rule, step 2
CALIBRATED_RANK_CORR = 0.5
RETURN_TIE = 0.5  # step 3: designs within 0.5 of return are ordered by violations
N_SELECTED = 2
SELECTION_ALPHA = 0.1  # the alpha the rule ranks, and the one step 5 judges


def _number(value: Any) -> float:
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else math.nan


def _fmt(value: float, digits: int = 2, scale: float = 1.0) -> str:
    return format_number(value, digits, scale, missing="n/a")


def run_gaps(result: dict[str, Any], bar_run: dict[str, Any] | None, part: str) -> tuple[float, float]:
    """
    The (return, violation) gap of one run on ``part`` (``train`` or ``test``) against its family's bar.

    :param result: the run's result
    :param bar_run: the same seed's run of the bar variant (a variant bar), None for a scripted bar
    :param part: ``train`` or ``test``
    :return: model minus bar; nan where a value is missing
    """
    entry = ((result.get("prior_critic") or {}).get("prior_optimality") or {}).get(part) or {}
    if bar_run is None:
        gap = entry.get("gap") or {}
        return _number(gap.get("return")), _number(gap.get("violation"))
    bar = (((bar_run.get("prior_critic") or {}).get("prior_optimality") or {}).get(part) or {}).get("model") or {}
    mine = entry.get("model") or {}
    return (
        _number(mine.get("return")) - _number(bar.get("return")),
        _number(mine.get("violation")) - _number(bar.get("violation")),
    )


def calibration_of(result: dict[str, Any]) -> tuple[float, float, float]:
    """(bias, relative error, rank correlation) of one run; nan where missing (Fine-Tune, MAML)."""
    calibration = (result.get("prior_critic") or {}).get("calibration") or {}
    return tuple(_number(calibration.get(key)) for key in ("bias", "relative_error", "rank_corr"))  # type: ignore[return-value]


def task_blind_of(result: dict[str, Any]) -> tuple[float, float]:
    """
    The calibration's task-blind reference on the run's rollouts (docs/pearl.md, "Measures").

    :param result: the run's result
    :return: (relative error, rank correlation); nan before measures version 2 and for runs without a prior critic
    """
    calibration = (result.get("prior_critic") or {}).get("calibration") or {}
    return _number(calibration.get("task_blind_relative_error")), _number(calibration.get("task_blind_rank_corr"))


def _task_blind_cell(runs: Sequence[dict[str, Any]]) -> str:
    """The medians of the task-blind reference over runs, ``rel. error / rank corr.``."""
    blind = [task_blind_of(r) for r in runs]
    return f"{_fmt(median_finite([b[0] for b in blind]))} / {_fmt(median_finite([b[1] for b in blind]))}"


def _measured(result: dict[str, Any]) -> bool:
    section = result.get("prior_critic")
    return isinstance(section, dict) and "error" not in section


def _bar_runs(experiment: Experiment, family: str, group: Group) -> Mapping[int, dict[str, Any]] | None:
    bar = experiment.family(family).prior_bar
    if bar is None or bar.kind != "variant":
        return None
    return group.get(bar.name, {})


def prior_critic_table(experiment: Experiment, family: str, group: Group) -> list[str]:
    """
    Per variant: the calibration (medians over seeds, mean bias) and the prior-optimality gaps (means over seeds).

    The calibration is over every measured run. Where the bar is a variant (Walker2D-vel: Fine-Tune), the gaps are over
    the seeds that also have the bar's run (n/a where none has: experiments without Fine-Tune runs); a family without a
    bar (Highway-Merge) shows its critics' calibration with the gaps n/a.
    """
    bar = experiment.family(family).prior_bar
    bar_runs = _bar_runs(experiment, family, group)
    lines = [
        "| variant | bias Q~ - MC | rel. error (median) | rank corr. (median) | task-blind reference: rel. error / rank corr. "
        "| return gap, train | violation gap, train | return gap, test | violation gap, test | seeds |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for variant in [v.name for v in experiment.variants if v.name in group]:
        runs = {
            s: r
            for s, r in group[variant].items()
            if isinstance(r.get("prior_critic"), dict) and "error" not in r["prior_critic"]
        }
        if not runs:
            continue
        # the calibration needs only the run; a gap needs the bar: none declared (no gap), scripted (the run's record
        # holds the gap) or a variant (its run of the same seed)
        paired: Mapping[int, dict[str, Any]]
        if bar is None:
            paired = {}
        elif bar_runs is None:
            paired = runs
        else:
            paired = {s: r for s, r in runs.items() if s in bar_runs}
        calibration = [calibration_of(r) for r in runs.values()]
        train = [run_gaps(r, None if bar_runs is None else bar_runs[s], "train") for s, r in paired.items()]
        test = [run_gaps(r, None if bar_runs is None else bar_runs[s], "test") for s, r in paired.items()]
        cells = [
            _fmt(mean_finite([c[0] for c in calibration]), 1),
            _fmt(median_finite([c[1] for c in calibration])),
            _fmt(median_finite([c[2] for c in calibration])),
            _task_blind_cell(list(runs.values())),
            _fmt(mean_finite([g[0] for g in train]), 1),
            _fmt(mean_finite([g[1] for g in train]), 1, 100),
            _fmt(mean_finite([g[0] for g in test]), 1),
            _fmt(mean_finite([g[1] for g in test]), 1, 100),
        ]
        label = experiment.variant(variant).label
        seeds = f"{len(runs)}"
        if bar is not None and len(paired) < len(runs):
            seeds += f" ({len(paired)} with the bar's run)"
        lines.append(f"| {label} | {' | '.join(cells)} | {seeds} |")
    if len(lines) == 2:
        return []
    bar_text = f"bar: {bar.description}" if bar is not None else "no bar is declared for this family, so the gaps are n/a"
    return [
        f'Prior critic (docs/pearl.md, "Measures"): calibration on training tasks; the task-blind reference predicts each '
        "(z0, task) pair by its z0's bootstrapped return averaged over the tasks (what a task-blind critic fitted "
        "exactly would predict on these rollouts, n/a before measures version 2); prior-optimality gap = the prior "
        f"policy's k = 0 return / violation rate (points) minus the bar's; {bar_text}.",
        "",
        *lines,
    ]


class Ranked(NamedTuple):
    """One design's row of the selection."""

    design: str
    variant: str
    relative_error: float
    rank_corr: float
    return_gap: float
    violation_gap: float
    n_runs: int
    task_blind: str = "n/a"  # the task-blind reference's medians (not read by the rule)

    @property
    def calibrated(self) -> bool:
        return self.relative_error < CALIBRATED_RELATIVE_ERROR and self.rank_corr > CALIBRATED_RANK_CORR


def rank_designs(experiment: Experiment, groups: Mapping[str, Group], alpha: float = 0.1) -> list[Ranked]:
    """
    Steps 1-3 of the selection rule: every design at ``alpha`` over its runs on every family, best first.

    :param experiment: the ``prior-critic`` experiment
    :param groups: family -> its group of runs
    :param alpha: the prior coefficient of the designs ranked
    :return: the designs with runs, ranked
    """
    rows = []
    for design in DESIGNS:
        variant = f"alpha-{alpha:g}-{design}"
        runs = [r for group in groups.values() for r in group.get(variant, {}).values() if _measured(r)]
        if not runs:
            continue
        calibration = [calibration_of(r) for r in runs]
        gaps = [run_gaps(r, None, "train") for r in runs]
        rows.append(
            Ranked(
                design,
                variant,
                median_finite([c[1] for c in calibration]),
                median_finite([c[2] for c in calibration]),
                mean_finite([g[0] for g in gaps]),
                mean_finite([g[1] for g in gaps]),
                len(runs),
                _task_blind_cell(runs),
            )
        )
    rows.sort(key=lambda r: -r.return_gap if math.isfinite(r.return_gap) else math.inf)
    # Step 3's tie rule: neighbours within RETURN_TIE of return are ordered by the lower violation gap.
    for _ in range(len(rows)):
        for i in range(len(rows) - 1):
            a, b = rows[i], rows[i + 1]
            if abs(a.return_gap - b.return_gap) <= RETURN_TIE and b.violation_gap < a.violation_gap:
                rows[i], rows[i + 1] = b, a
    return rows


def select(rows: Sequence[Ranked]) -> list[Ranked]:
    """Step 4: the two best-ranked calibrated designs, topped up with the best-ranked others."""
    chosen = [r for r in rows if r.calibrated][:N_SELECTED]
    chosen += [r for r in rows if not r.calibrated][: N_SELECTED - len(chosen)]
    return chosen


def incomplete_designs(experiment: Experiment, rows: Sequence[Ranked]) -> list[str]:
    """
    The designs without every run the rule reads.

    :param experiment: the ``prior-critic`` experiment (its families and seeds)
    :param rows: :func:`rank_designs`'s rows (measured runs only)
    :return: the designs with fewer measured runs than families x seeds, and those with none
    """
    full = len(experiment.families) * len(experiment.seeds)
    return [r.design for r in rows if r.n_runs < full] + [d for d in DESIGNS if d not in {r.design for r in rows}]


class SelectionGate(NamedTuple):
    """Which of an experiment's ``after_selection`` variants may run (:func:`selection_gate`)."""

    final: bool  # every run the rule reads is complete and measured
    selected: tuple[str, ...]  # the after_selection variants of the selected designs (empty until final)
    held: tuple[str, ...]  # the others: awaiting the selection (not final) or not selected (final)
    unmeasured: tuple[str, ...] = ()  # finished runs the rule reads that lack the measures (`reproduce measure`)


def design_of(variant: str) -> str | None:
    """The prior-critic design a variant name ends with (``alpha-1-twin-priordata``: ``twin-priordata``), or None."""
    matches = [design for design in DESIGNS if variant.endswith(f"-{design}")]
    return max(matches, key=len) if matches else None


def selection_gate(experiment: Experiment, budget_preset: str, results_dir: str | os.PathLike[str]) -> SelectionGate:
    """
    The selection rule applied to the complete runs under ``results_dir``: the ``after_selection`` variants of the
    designs it selects may run, once every design has all its runs at alpha 0.1, measured.

    :param experiment: an experiment whose ``after_selection`` variants each end with a design's name (``prior-critic``:
        ``alpha-1-<design>``; ``prior-critic-walker``: ``pearlplus-<design>``, gated by ``selected_by="prior-critic"``)
    :param budget_preset: the budget preset being run; the rule reads the runs of this preset when the experiment
        gates itself, and those of the ruling experiment's own preset otherwise
    :param results_dir: root of the results layout
    :return: the gate
    """
    from pearl_paper.experiments import get_experiment
    from pearl_paper.reproduce.cells import load_groups

    gated = tuple(experiment.after_selection)
    foreign = [v for v in gated if design_of(v) is None]
    if foreign:
        raise ValueError(
            f"experiment {experiment.name}: after_selection variants {foreign} do not name a prior-critic design "
            f"(a variant name ending with one of {sorted(DESIGNS)})"
        )
    ruling = get_experiment(experiment.selected_by) if experiment.selected_by else experiment
    budget = budget_preset if ruling is experiment else ruling.budget
    groups = {
        family: group
        for (name, preset, family), group in load_groups(results_dir).items()
        if name == ruling.name and preset == budget
    }
    ranked = {f"alpha-0.1-{design}" for design in DESIGNS}
    unmeasured = tuple(
        f"{family} {variant} seed{seed}"
        for family, group in groups.items()
        for variant, runs in group.items()
        if variant in ranked
        for seed, result in runs.items()
        if not _measured(result)
    )
    rows = rank_designs(ruling, groups)
    if not gated or incomplete_designs(ruling, rows):
        return SelectionGate(False, (), gated, unmeasured)
    chosen = {r.design for r in select(rows)}
    return SelectionGate(
        True, tuple(v for v in gated if design_of(v) in chosen), tuple(v for v in gated if design_of(v) not in chosen)
    )


def selection_table(experiment: Experiment, groups: Mapping[str, Group]) -> list[str]:
    """The selection rule applied to the runs there are, with how many runs each design has."""
    rows = rank_designs(experiment, groups)
    if not rows:
        return []
    chosen = {r.design for r in select(rows)}
    full = len(experiment.families) * len(experiment.seeds)
    partial = incomplete_designs(experiment, rows)
    lines = [
        "| rank | design | median rel. error | median rank corr. | calibrated | task-blind reference: rel. error / rank corr. "
        "| mean return gap, train | mean violation gap, train (points) | runs | selected |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for rank, row in enumerate(rows, start=1):
        lines.append(
            f"| {rank} | {row.design} ({DESIGNS[row.design][0]}) | {_fmt(row.relative_error)} | {_fmt(row.rank_corr)} | "
            f"{'yes' if row.calibrated else 'no'} | {row.task_blind} | {_fmt(row.return_gap, 1)} | "
            f"{_fmt(row.violation_gap, 1, 100)} | "
            f"{row.n_runs} | {('leading' if partial else '**selected**') if row.design in chosen else ''} |"
        )
    note = (
        f" Incomplete ({full} runs each when complete; missing or part-way: {', '.join(partial)}): the ranking is "
        "provisional and nothing is selected until every design has its runs."
        if partial
        else ""
    )
    return [
        'Selection (docs/pearl.md, "The selection rule", written before the runs; training tasks only, alpha 0.1, '
        f"both crash penalties pooled).{note} The task-blind reference (medians over the design's runs) is not read by "
        "the rule: it is what a task-blind critic fitted exactly would score against the same rollouts.",
        "",
        *lines,
    ]


# -- step 5: the outcome ------------------------------------------------------------------------------------
class OutcomeRow(NamedTuple):
    """One design variant on one family, against that family's PEARL (step 5 of the selection rule)."""

    family: str
    variant: str
    n_seeds: int  # seeds paired with PEARL at k = 0
    relative_error: float  # medians over the variant's runs on this family (training tasks)
    rank_corr: float
    safer: Interval  # k = 0 violation rate minus PEARL's, paired over seeds
    vs_paper: Interval  # k = 0 violation rate minus the paper's form's (same alpha), paired
    adapted_violation: Interval  # last trajectory's violation rate minus PEARL's, paired
    adapted_return: Interval  # last trajectory's return minus PEARL's, paired
    return_margin: float  # the family's return margin
    n_expected: int  # the experiment's seeds: a row with fewer is not judged yet

    @property
    def complete(self) -> bool:
        return self.n_seeds >= self.n_expected

    @property
    def calibrated(self) -> bool:
        return self.relative_error < CALIBRATED_RELATIVE_ERROR and self.rank_corr > CALIBRATED_RANK_CORR

    @property
    def is_safer(self) -> bool:
        """The k = 0 violation rate is lower than PEARL's with a paired 95% interval that excludes zero."""
        return self.safer.n >= 2 and math.isfinite(self.safer.high) and self.safer.high < 0

    @property
    def adapted_not_worse(self) -> bool:
        """
        The adapted policy is not worse than PEARL's: its violation rate within 5 points (equivalent at 95%, the
        experiments' own "equal" claims) and its return not lower by more than the family's margin (non-inferior at 95%).
        """
        return (
            verdict(self.adapted_violation, "equal", VIOLATION_MARGIN) == REPRODUCED
            and verdict(self.adapted_return, "not_lower", self.return_margin) == REPRODUCED
        )

    @property
    def passes(self) -> bool:
        return self.calibrated and self.is_safer and self.adapted_not_worse

    @property
    def failures(self) -> list[str]:
        """Which conditions of step 5 the row does not meet."""
        checks = [(self.calibrated, "not calibrated"), (self.is_safer, "prior not safer")]
        return [text for ok, text in checks + [(self.adapted_not_worse, "adapted policy not shown as good")] if not ok]


def paper_form_of(variant: str) -> str:
    """The paper's PEARL+ at the same alpha as a design variant: its name without the design (``alpha-1-mc``: ``alpha-1``)."""
    design = design_of(variant)
    if design is None:
        raise ValueError(f"{variant!r} does not name a prior-critic design (a name ending with one of {sorted(DESIGNS)})")
    return variant[: -len(design) - 1]


def _paired(group: Group, variant: str, reference: str, k: int, metric: str) -> Interval:
    if reference not in group:
        return Interval(math.nan, math.nan, math.nan, 0)
    diffs = paired_differences(seed_values(group[variant], k, metric), seed_values(group[reference], k, metric))
    return t_interval(list(diffs.values()))


def outcome_rows(experiment: Experiment, family: str, group: Group) -> list[OutcomeRow]:
    """
    Step 5 of the selection rule (docs/pearl.md) for every design variant of ``group`` with runs: calibration on this
    family's runs, the k = 0 violation rate against PEARL's (``experiment.reference``) and the paper's form's, and the
    adapted policy (the last trajectory both rolled out) against PEARL's; every difference paired over seeds.

    :param experiment: ``prior-critic`` or ``prior-critic-walker`` (its reference is PEARL)
    :param family: the family of ``group``
    :param group: variant -> seed -> result
    :return: one row per design variant, in the experiment's order
    """
    reference = experiment.reference
    if reference is None or reference not in group:
        return []
    rows = []
    for variant in [v.name for v in experiment.variants if v.name in group and design_of(v.name) is not None]:
        measured = [r for r in group[variant].values() if _measured(r)]
        calibration = [calibration_of(r) for r in measured]
        last = min(last_k(group[variant]), last_k(group[reference]))
        safer = _paired(group, variant, reference, 0, "violation")
        rows.append(
            OutcomeRow(
                family,
                variant,
                safer.n,
                median_finite([c[1] for c in calibration]),
                median_finite([c[2] for c in calibration]),
                safer,
                _paired(group, variant, paper_form_of(variant), 0, "violation"),
                _paired(group, variant, reference, last, "violation"),
                _paired(group, variant, reference, last, "return"),
                experiment.family(family).return_margin,
                len(experiment.seeds),
            )
        )
    return rows


def _interval_cell(interval: Interval, digits: int = 1, scale: float = 1.0) -> str:
    if interval.n == 0:
        return "n/a"
    mean = _fmt(interval.mean, digits, scale)
    if not (math.isfinite(interval.low) and math.isfinite(interval.high)):
        return mean
    return f"{mean} [{_fmt(interval.low, digits, scale)}, {_fmt(interval.high, digits, scale)}]"


def outcome_table(rows: Sequence[OutcomeRow], selected: Sequence[str], families: Sequence[str]) -> list[str]:
    """
    Step 5 of the selection rule over the families of both experiments, and its verdict for the selected designs.

    :param rows: :func:`outcome_rows` of every family
    :param selected: the designs steps 1-4 selected (empty while the selection is incomplete)
    :param families: the families step 5 reads (every one must pass)
    :return: markdown lines
    """
    if not rows:
        return []
    lines = [
        "| family | variant | seeds | rel. error / rank corr. | calibrated | k = 0 violations minus PEARL's (points) "
        "| minus the paper's form's (points) | last k: violations minus PEARL's (points) | last k: return minus PEARL's "
        "| safer | adapted not worse | passes |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]

    def judged(row: OutcomeRow, value: bool, bold: bool = False) -> str:
        if row.n_seeds < 2:
            return "n/a"
        text = ("**yes**" if bold else "yes") if value else "no"
        return text if row.complete else f"{text} (so far)"

    for row in rows:
        lines.append(
            f"| {row.family} | {row.variant} | {row.n_seeds} of {row.n_expected} | {_fmt(row.relative_error)} / "
            f"{_fmt(row.rank_corr)} | {'yes' if row.calibrated else 'no'} | {_interval_cell(row.safer, 1, 100)} | "
            f"{_interval_cell(row.vs_paper, 1, 100)} | {_interval_cell(row.adapted_violation, 1, 100)} | "
            f"{_interval_cell(row.adapted_return)} | {judged(row, row.is_safer)} | {judged(row, row.adapted_not_worse)} | "
            f"{judged(row, row.passes, bold=True)} |"
        )
    verdicts = []
    recommended = []
    for design in selected:
        names = {design_variant(design, SELECTION_ALPHA).name, design_variant(design, SELECTION_ALPHA, "pearlplus").name}
        mine = {r.family: r for r in rows if r.variant in names}
        # a family is judged once the design has every seed there; before that it is awaited
        missing = [
            f if f not in mine else f"{f} ({mine[f].n_seeds} of {mine[f].n_expected} seeds)"
            for f in families
            if f not in mine or not mine[f].complete
        ]
        failed = [
            f"{f} ({', '.join(mine[f].failures)})" for f in families if f in mine and mine[f].complete and not mine[f].passes
        ]
        if failed:
            not_run = f"; awaiting {', '.join(missing)}" if missing else ""
            verdicts.append(f"{design}: fails on {', '.join(failed)}{not_run}")
        elif missing:
            verdicts.append(f"{design}: passes so far; awaiting {', '.join(missing)}")
        else:
            verdicts.append(f"{design}: passes on every family")
            recommended.append(design)
    if not selected:
        outcome = "The selection is incomplete: no design is judged yet."
    elif recommended:
        outcome = f"**Recommended: {', '.join(recommended)}** ({'; '.join(verdicts)})."
    elif all("fails" in v for v in verdicts):
        outcome = f"**No selected design passes step 5** ({'; '.join(verdicts)})."
    else:
        outcome = f"Not decided yet ({'; '.join(verdicts)})."
    return [
        'Step 5 of the selection rule (docs/pearl.md, "The selection rule"): a selected design is recommended if, on '
        f"every family ({', '.join(families)}), it is calibrated on that family's training-task runs, its k = 0 "
        "violation rate on the held-out tasks is lower than PEARL's with a paired 95% t interval that excludes zero, "
        "and its adapted policy (the last trajectory) is not worse: violations within 5 points of PEARL's (equivalent "
        "at 95%) and return not lower by more than the family's margin (non-inferior at 95%). A family is judged once "
        "the design has all its seeds there. Every design variant is shown; the verdict reads the selected designs at "
        "alpha 0.1.",
        "",
        *lines,
        "",
        outcome,
    ]


def outcome_section(groups: Mapping[tuple[str, str, str], Group]) -> list[str]:
    """
    Step 5 over ``prior-critic`` (SafePointGoal) and ``prior-critic-walker`` (Walker2D-vel), each at its own budget.

    :param groups: :func:`~pearl_paper.reproduce.cells.load_groups`'s (experiment, budget preset, family) -> group
    :return: markdown lines (empty when no design variant has runs beside PEARL's)
    """
    from pearl_paper.experiments.prior_critic import PRIOR_CRITIC, PRIOR_CRITIC_WALKER

    rows: list[OutcomeRow] = []
    for experiment in (PRIOR_CRITIC, PRIOR_CRITIC_WALKER):
        for family in experiment.families:
            group = groups.get((experiment.name, experiment.budget, family.name))
            if group:
                rows += outcome_rows(experiment, family.name, group)
    ruling = (PRIOR_CRITIC.name, PRIOR_CRITIC.budget)
    selection_groups = {family: group for (name, budget, family), group in groups.items() if (name, budget) == ruling}
    ranked = rank_designs(PRIOR_CRITIC, selection_groups) if selection_groups else []
    selected = [] if not ranked or incomplete_designs(PRIOR_CRITIC, ranked) else [r.design for r in select(ranked)]
    families = [f.name for e in (PRIOR_CRITIC, PRIOR_CRITIC_WALKER) for f in e.families]
    return outcome_table(rows, selected, families)
