"""``python -m pearl_paper.reproduce report``: the tables and figures of docs/results.md from whatever results/ holds.

Results are grouped by (experiment, budget preset, family); within a group, per variant and k:

- violation rate: mean over seeds of the per-seed rates with its 95% t interval over seeds, and the
  pooled rate over every trajectory with its 95% Wilson interval;
- mean return: mean over seeds of the per-seed means with its 95% t interval;
- the number of trajectories and of seeds; the paper's number beside ours;
- the verdicts of the claims on that cell (:mod:`pearl_paper.reproduce.stats`: paired over seeds).

The generated part of the output file sits between :data:`BEGIN` and :data:`END`; the rest of the file
(a hand-written preamble, older sections) is kept. Figures (adaptation curves: return and violation
rate against k, one line per variant; per-seed violation rates at k = 0 and the last k, one line per seed
across the variants) go to ``figures/`` beside the output file.
"""

from __future__ import annotations

import math
import os
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pearl_paper.experiments import EXPERIMENTS
from pearl_paper.experiments.spec import VIOLATION_MARGIN, Claim, Experiment, resolve_k
from pearl_paper.reproduce.cells import Group, cell_stats, last_k, load_groups, load_partway_curves, seed_values
from pearl_paper.reproduce.curve import curve_table
from pearl_paper.reproduce.formatting import format_interval
from pearl_paper.reproduce.formatting import format_number as _num
from pearl_paper.reproduce.layout import find_results
from pearl_paper.reproduce.prior_report import outcome_section, prior_critic_table, selection_table
from pearl_paper.reproduce.stats import Interval, paired_differences, t_interval, verdict
from sb3_pearl.common.atomic import atomic_write
from sb3_pearl.evaluation.meta_test import PAPER_KS

BEGIN = "<!-- reproduce:begin -->"
END = "<!-- reproduce:end -->"
DIRECTION_TEXT = {"lower": "<", "higher": ">", "equal": "=", "not_lower": ">=", "not_higher": "<="}


@dataclass(frozen=True)
class ClaimResult:
    """A claim with our paired difference and the verdict."""

    claim: Claim
    k: int
    difference: Interval
    margin: float
    verdict: str


def claim_margin(claim: Claim, experiment: Experiment) -> float:
    """The claim's margin: its own, else 5 points for violation rates or the family's return margin."""
    if claim.margin is not None:
        return claim.margin
    return VIOLATION_MARGIN if claim.metric == "violation" else experiment.family(claim.family).return_margin


def evaluate_claim(claim: Claim, experiment: Experiment, group: Group) -> ClaimResult | None:
    """
    Our paired difference and the verdict of one claim (None if either variant has no runs).

    :param claim: the claim
    :param experiment: its experiment
    :param group: variant -> seed -> result of the claim's family
    :return: the result (None also when the runs did not roll out trajectory ``claim.k``)
    """
    if claim.variant not in group or claim.reference not in group:
        return None
    last = min(last_k(group[claim.variant]), last_k(group[claim.reference]))
    if claim.k > last:
        return None  # the meta-test did not roll out that trajectory
    k = resolve_k(claim.k, last)
    diffs = paired_differences(
        seed_values(group[claim.variant], k, claim.metric), seed_values(group[claim.reference], k, claim.metric)
    )
    interval = t_interval(list(diffs.values()))
    margin = claim_margin(claim, experiment)
    return ClaimResult(claim, k, interval, margin, verdict(interval, claim.direction, margin))


# ----------------------------------------------------------------------------------------------
# Formatting
# ----------------------------------------------------------------------------------------------
def _cell(text: str) -> str:
    """Text safe inside a markdown table cell."""
    return text.replace("|", "\\|")


def _label(experiment: Experiment, variant: str) -> str:
    try:
        return experiment.variant(variant).label
    except ValueError:
        return variant


def shown_ks(group: Group, section: str = "meta_test") -> list[int]:
    """The k columns of a table: the paper's 0, 1, 3, 5 that were rolled out, and the last k."""
    last = min(last_k(results, section) for results in group.values())
    return sorted({k for k in PAPER_KS if k <= last} | {last})


def results_table(experiment: Experiment, family: str, group: Group, claims: Sequence[ClaimResult]) -> list[str]:
    """The main table of a group: one row per (variant, k)."""
    lines = [
        "| variant | k | violation rate, % (95% t over seeds) | pooled, % (95% Wilson) | paper | "
        "return (95% t over seeds) | paper | n traj. | seeds | verdicts |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    ks = shown_ks(group)
    last = min(last_k(results) for results in group.values())
    for variant in [v.name for v in experiment.variants if v.name in group]:
        for k in ks:
            stats = cell_stats(group[variant], k)
            if stats is None:
                continue
            paper_v = experiment.paper_value(family, variant, "violation", k, last)
            paper_r = experiment.paper_value(family, variant, "return", k, last)
            verdicts = [
                f"{c.claim.metric} vs {_label(experiment, c.claim.reference)}: {c.verdict}"
                for c in claims
                if c.claim.variant == variant and c.k == k
            ]
            pooled = f"{_num(stats.pooled_rate, 1, 100)} [{_num(stats.pooled_low, 1, 100)}, {_num(stats.pooled_high, 1, 100)}]"
            lines.append(
                f"| {_label(experiment, variant)} | {k} | {format_interval(stats.violation, 1, 100)} | {pooled} | "
                f"{_num(paper_v.value, 2, 100) if paper_v else ''} | {format_interval(stats.ret)} | "
                f"{_num(paper_r.value, 2) if paper_r else ''} | {stats.n_trajectories} | {stats.n_seeds} | "
                f"{'; '.join(verdicts) if variant != experiment.reference or verdicts else 'reference'} |"
            )
    return lines


def claims_table(experiment: Experiment, claims: Sequence[ClaimResult]) -> list[str]:
    """One row per claim: what the paper says, our paired difference, the margin and the verdict."""
    if not claims:
        return []
    lines = [
        "| claim | k | paper | ours: variant - reference (95% t, paired over seeds) | margin | seeds | verdict |",
        "|---|---|---|---|---|---|---|",
    ]
    for c in claims:
        scale, digits = (100.0, 1) if c.claim.metric == "violation" else (1.0, 2)
        unit = " pts" if c.claim.metric == "violation" else ""
        text = (
            f"{c.claim.metric} {_label(experiment, c.claim.variant)} {DIRECTION_TEXT[c.claim.direction]} "
            f"{_label(experiment, c.claim.reference)}"
        )
        lines.append(
            f"| {text} | {c.k} | {_cell(c.claim.source)} | {format_interval(c.difference, digits, scale)}{unit} | "
            f"{_num(c.margin, digits, scale)}{unit} | {c.difference.n} | **{c.verdict}** |"
        )
    return lines


def seed_table(experiment: Experiment, group: Group) -> list[str]:
    """
    Per-seed violation rate and mean return at k = 0 and the last k: one row per (variant, k), one column per seed.

    Every variant of a seed is meta-tested on the same tasks, env seeds and z0 draws, so a column is a paired
    comparison; the spread between columns is the seed-to-seed variation the t intervals summarise.
    """
    seeds = sorted({seed for results in group.values() for seed in results})
    if len(seeds) < 2:
        return []
    last = min(last_k(results) for results in group.values())
    lines = [
        "| variant | k | " + " | ".join(f"seed {seed}" for seed in seeds) + " |",
        "|---|---|" + "---|" * len(seeds),
    ]
    for variant in [v.name for v in experiment.variants if v.name in group]:
        for k in sorted({0, last}):
            rates = seed_values(group[variant], k, "violation")
            returns = seed_values(group[variant], k, "return")
            cells = [
                f"{_num(rates[seed], 1, 100)}% / {_num(returns[seed])}" if seed in rates and seed in returns else ""
                for seed in seeds
            ]
            lines.append(f"| {_label(experiment, variant)} | {k} | {' | '.join(cells)} |")
    return lines


def competence_table(experiment: Experiment, group: Group) -> list[str]:
    """The competence criteria per variant: mean value over seeds and how many seeds pass."""
    lines = [
        "| variant | criterion (training tasks, k >= 1) | mean over seeds | bar | seeds passing |",
        "|---|---|---|---|---|",
    ]
    for variant in [v.name for v in experiment.variants if v.name in group]:
        per_criterion: dict[str, list[dict[str, Any]]] = defaultdict(list)
        for result in group[variant].values():
            for entry in (result.get("competence") or {}).get("criteria", []):
                per_criterion[entry["description"]].append(entry)
        for description, entries in per_criterion.items():
            values = [e["value"] for e in entries if e["value"] is not None]
            mean = float(np.mean(values)) if values else math.nan
            bar = f"{'<=' if entries[0]['better'] == 'lower' else '>='} {entries[0]['threshold']:g}"
            passing = sum(bool(e["passed"]) for e in entries)
            name = _label(experiment, variant)
            lines.append(f"| {name} | {_cell(description)} | {_num(mean, 3)} | {bar} | {passing}/{len(entries)} |")
    return lines if len(lines) > 2 else []


def shift_table(experiment: Experiment, group: Group) -> list[str]:
    """The meta-test on the shifted task distribution, if the runs have one."""
    shifted = {v: {s: r for s, r in seeds.items() if r.get("shift")} for v, seeds in group.items()}
    shifted = {v: seeds for v, seeds in shifted.items() if seeds}
    if not shifted:
        return []
    lines = [
        "| variant | k | violation rate, % (95% t) | pooled, % (95% Wilson) | return (95% t) | n traj. | seeds |",
        "|---|---|---|---|---|---|---|",
    ]
    for variant in [v.name for v in experiment.variants if v.name in shifted]:
        for k in shown_ks(shifted, "shift"):
            stats = cell_stats(shifted[variant], k, "shift")
            if stats is None:
                continue
            pooled = f"{_num(stats.pooled_rate, 1, 100)} [{_num(stats.pooled_low, 1, 100)}, {_num(stats.pooled_high, 1, 100)}]"
            lines.append(
                f"| {_label(experiment, variant)} | {k} | {format_interval(stats.violation, 1, 100)} | {pooled} | "
                f"{format_interval(stats.ret)} | {stats.n_trajectories} | {stats.n_seeds} |"
            )
    return lines


DIAGNOSTIC_COLUMNS = (
    ("overlap", "posterior_mean_norm_avg", "posterior mean norm", 2),
    ("overlap", "posterior_var_avg", "posterior var", 4),
    ("overlap", "auc_gaussian", "AUC posterior vs z0", 2),
    ("violations", "distance_mean", "z0 to nearest posterior mean", 2),
    ("violations", "violation_rate", "k=0 violation (diag.)", 2),
    ("violations", "z_zero_violation_rate", "violation at z=0", 2),
    ("calibration", "bias", "prior-critic bias", 1),
    ("calibration", "q_mc_corr_over_z0", "Q~ vs MC corr.", 2),
    ("gradient_conflict", "ratio", "grad ratio (alpha*prior / post)", 3),
    ("gradient_conflict", "cos", "grad cosine", 2),
)


def diagnostics_table(experiment: Experiment, group: Group) -> list[str]:
    """The prior diagnostics (docs/diagnostics.md) per variant: means over the seeds that have them."""
    header = " | ".join(label for _, _, label, _ in DIAGNOSTIC_COLUMNS)
    lines = [f"| variant | {header} | seeds |", "|---|" + "---|" * (len(DIAGNOSTIC_COLUMNS) + 1)]
    for variant in [v.name for v in experiment.variants if v.name in group]:
        found = [r["diagnostics"] for r in group[variant].values() if isinstance(r.get("diagnostics"), dict)]
        found = [d for d in found if "overlap" in d]
        if not found:
            continue
        cells = []
        for section, key, _, digits in DIAGNOSTIC_COLUMNS:
            values = [d.get(section, {}).get(key) for d in found]
            numbers = [float(v) for v in values if isinstance(v, (int, float))]
            cells.append(_num(float(np.mean(numbers)), digits) if numbers else "n/a")
        lines.append(f"| {_label(experiment, variant)} | {' | '.join(cells)} | {len(found)} |")
    return lines if len(lines) > 2 else []


def timing_table(experiment: Experiment, group: Group) -> list[str]:
    """Mean wall times per variant (minutes), with the CPU and the load average seen."""
    lines = [
        "| variant | train min | meta-test min | total min | runs | CPU | load avg (start) |",
        "|---|---|---|---|---|---|---|",
    ]
    for variant in [v.name for v in experiment.variants if v.name in group]:
        results = list(group[variant].values())
        times = [r.get("wall_time_s", {}) for r in results]
        mean = {key: float(np.mean([t.get(key, math.nan) for t in times])) / 60 for key in ("train", "meta_test", "total")}
        cpu = results[0].get("cpu", {})
        loads = [r.get("cpu", {}).get("load_average") or [math.nan] for r in results]
        load = float(np.mean([entry[0] for entry in loads]))
        lines.append(
            f"| {_label(experiment, variant)} | {_num(mean['train'])} | {_num(mean['meta_test'])} | {_num(mean['total'])} | "
            f"{len(results)} | {cpu.get('model')} ({cpu.get('cores')} cores) | {_num(load)} |"
        )
    return lines


def build_report(results_dir: str | os.PathLike[str], figures_dir: str | os.PathLike[str], figures_link: str) -> str:
    """
    The generated markdown (without the markers) and the figures.

    :param results_dir: root of the results layout
    :param figures_dir: where the figures are written
    :param figures_link: how the markdown links to ``figures_dir`` (relative to the output file)
    :return: the markdown
    """
    from pearl_paper.reproduce.figures import plot_curves, plot_decisions, plot_group, plot_prior_selection, plot_seeds
    from pearl_paper.reproduce.remeasured_tables import remeasured_section
    from pearl_paper.reproduce.table1_verdicts import decide, decide_confirmation, decision_section

    groups = load_groups(results_dir)
    out = [
        "## Reproduction runs (generated by `python -m pearl_paper.reproduce report`)",
        "",
        "Generated from the runs under `" + str(results_dir) + "`; settings, statistics and the verdict rule: "
        "[docs/reproduce.md](reproduce.md). Violation rates in %; k = 0 is the prior policy, k >= 1 after k "
        "trajectories; the paper column is the paper's number for the same cell.",
        "",
    ]
    if not groups:
        out += ["No complete run found.", ""]
    decisions = decide(results_dir)
    if any(decision.runs[decision.variants[0]] for decision in decisions):
        out += ["### Table I decided: PEARL+ against PEARL by the pre-written rules", ""]
        out += decision_section(decisions)
        if plot_decisions(decisions, Path(figures_dir) / "table1_decided.png"):
            out += [f"![k = 0 violation rate per seed, Table I decided]({figures_link.rstrip('/')}/table1_decided.png)", ""]
    confirmation = [decide_confirmation(results_dir), decide_confirmation(results_dir, pooled=True)]
    if any(decision.runs[decision.variants[0]] for decision in confirmation):
        out += [
            "### Highway-Merge confirmed on fresh seeds: the same rules on seeds 10-19 alone",
            "",
            "Rules committed before the runs: `pearl_paper/experiments/merge_confirm.py` (merge-table1's variants, budget, "
            "held-out tasks and re-measure; Table I's rules; decided on seeds 10-19 alone, the pooled 20 seeds secondary). "
            "The t interval decides; the sign-flip permutation interval beside it assumes only differences symmetric "
            "about their mean (not normal), and never leaves the range a rate difference can take. Multiplicity: the "
            "headline tests two rules on two families (four verdicts) at 95% each, unadjusted; with a Bonferroni "
            "correction each would need a 98.75% interval.",
            "",
        ]
        out += decision_section(confirmation)
    out += remeasured_section(results_dir)
    for (experiment_name, budget, family), group in groups.items():
        experiment = EXPERIMENTS.get(experiment_name)
        if experiment is None:
            out += [f"### {experiment_name} / {family} (budget {budget})", "", "Unknown experiment: not reported.", ""]
            continue
        claims = [
            c
            for c in (evaluate_claim(claim, experiment, group) for claim in experiment.claims if claim.family == family)
            if c is not None
        ]
        seeds = sorted({seed for results in group.values() for seed in results})
        own_seeds = (  # rows that declare their own seeds: each row's, where they differ
            " (by row: " + "; ".join(f"{_label(experiment, name)} {sorted(runs)}" for name, runs in group.items()) + ")"
            if experiment.variant_seeds
            else ""
        )
        out += [
            f"### {experiment.title}: {family} (budget `{budget}`)",
            "",
            f"{experiment.description}. Seeds {seeds}{own_seeds}; test tasks drawn with eval seed {experiment.eval_seed} "
            "(the same for every variant and seed).",
            "",
            *results_table(experiment, family, group, claims),
            "",
        ]
        if claims:
            counts = {v: sum(c.verdict == v for c in claims) for v in ("reproduced", "not reproduced", "inconclusive")}
            out += [
                f"Claims: {counts['reproduced']} reproduced, {counts['not reproduced']} not reproduced, "
                f"{counts['inconclusive']} inconclusive.",
                "",
                *claims_table(experiment, claims),
                "",
            ]
        per_seed = seed_table(experiment, group)
        if per_seed:
            out += [
                "Per seed (violation rate / mean return; a column is paired: the same test tasks, env seeds and z0 draws):",
                "",
                *per_seed,
                "",
            ]
        competence = competence_table(experiment, group)
        if competence:
            out += ["Competence on training tasks (docs/reproduce.md):", "", *competence, ""]
        shift = shift_table(experiment, group)
        if shift:
            out += [f"Shifted test distribution: {experiment.family(family).shift_description}.", "", *shift, ""]
        diagnostics = diagnostics_table(experiment, group)
        if diagnostics:
            out += [
                "Prior diagnostics (docs/diagnostics.md; PEARL's critic stands in for the prior critic it lacks):",
                "",
                *diagnostics,
                "",
            ]
        prior_critic = prior_critic_table(experiment, family, group)
        if prior_critic:
            out += [*prior_critic, ""]
        out += ["Wall times:", "", *timing_table(experiment, group), ""]
        name = f"reproduce_{experiment_name}_{family}_{budget}.png"
        title = f"{experiment.name} / {family} (budget {budget})"
        plot_group(experiment, group, Path(figures_dir) / name, title=title)
        out += [f"![adaptation curves, {experiment_name} / {family}]({figures_link.rstrip('/')}/{name})", ""]
        curves_name = f"reproduce_{experiment_name}_{family}_{budget}_curves.png"
        if plot_curves(experiment, group, Path(figures_dir) / curves_name, title=title):
            out += [
                'Learning curves on the test tasks (docs/reproduce.md, "Learning curves": the reference\'s protocol; '
                "mean over seeds, the shade spans the seeds):",
                "",
                *curve_table(experiment, group),
                "",
                f"![learning curves, {experiment_name} / {family}]({figures_link.rstrip('/')}/{curves_name})",
                "",
            ]
        seeds_name = f"reproduce_{experiment_name}_{family}_{budget}_seeds.png"
        if plot_seeds(experiment, group, Path(figures_dir) / seeds_name, title=title):
            out += [f"![per-seed rates, {experiment_name} / {family}]({figures_link.rstrip('/')}/{seeds_name})", ""]
    for (experiment_name, budget, family), group in load_partway_curves(results_dir).items():
        experiment = EXPERIMENTS[experiment_name]  # the loader keeps declared experiments, families and variants only
        curves_name = f"reproduce_{experiment_name}_{family}_{budget}_curves_partway.png"
        title = f"{experiment.name} / {family} (budget {budget}): runs in progress"
        if plot_curves(experiment, group, Path(figures_dir) / curves_name, title=title, per_seed=True):
            out += [
                f"### {experiment.title}: {family}, runs in progress (budget `{budget}`)",
                "",
                "Runs committed part-way (a checkpoint; the same `reproduce run` command resumes them): their learning "
                "curves so far, from `curve.csv`, one line per seed. The env steps column is the last curve point.",
                "",
                *curve_table(experiment, group),
                "",
                f"![learning curves so far, {experiment_name} / {family}]({figures_link.rstrip('/')}/{curves_name})",
                "",
            ]
    for experiment in EXPERIMENTS.values():
        by_family = {  # the rule is written for the experiment's own budget: other presets' runs are not pooled in
            family: group
            for (name, budget, family), group in groups.items()
            if name == experiment.name and budget == experiment.budget
        }
        selection = selection_table(experiment, by_family) if experiment.name == "prior-critic" and by_family else []
        if selection:
            out += [f"### {experiment.title}: the rule applied", "", *selection, ""]
            selection_name = f"reproduce_{experiment.name}_selection_{experiment.budget}.png"
            if plot_prior_selection(experiment, by_family, Path(figures_dir) / selection_name, title=experiment.title):
                out += [
                    f"![the selection rule's measures, {experiment.name}]({figures_link.rstrip('/')}/{selection_name})",
                    "",
                ]
            outcome = outcome_section(groups)
            if outcome:
                out += ["### Prior-critic designs: the outcome (step 5 of the rule)", "", *outcome, ""]
    return "\n".join(out)


def splice(document: str, generated: str) -> str:
    """
    Put ``generated`` between the markers of ``document`` (appended with markers if it has none).

    :param document: the current file content
    :param generated: the new generated part
    :return: the new file content
    """
    block = f"{BEGIN}\n{generated.rstrip()}\n{END}"
    if BEGIN in document and END in document:
        head, rest = document.split(BEGIN, 1)
        _, tail = rest.split(END, 1)
        return head + block + tail
    if BEGIN in document or END in document:
        raise ValueError(f"the output file has only one of the markers {BEGIN} / {END}: fix it by hand")
    return document.rstrip() + ("\n\n" if document.strip() else "") + block + "\n"


def write_report(results_dir: str | os.PathLike[str], out: str | os.PathLike[str]) -> Path:
    """
    Rebuild the generated part of ``out`` (and its figures in ``figures/`` beside it) from ``results_dir``.

    :param results_dir: root of the results layout
    :param out: the markdown file (created if missing; its text outside the markers is kept), written atomically (a
        temporary file in its folder, then renamed over it)
    :return: the path written
    """
    root = Path(results_dir)
    if not root.is_dir():
        raise ValueError(f"results folder {root} does not exist or is not a folder: nothing reported, {out} left as it is")
    if not find_results(root):
        raise ValueError(f"results folder {root} holds no result.json: nothing reported, {out} left as it is")
    out = Path(out)
    if out.is_dir():
        raise ValueError(f"--out {out} is a folder: give the markdown file to write, e.g. {out / 'results.md'}")
    out.parent.mkdir(parents=True, exist_ok=True)
    figures_dir = out.parent / "figures"
    figures_dir.mkdir(parents=True, exist_ok=True)
    generated = build_report(results_dir, figures_dir, "figures")
    document = out.read_text() if out.is_file() else "# Results\n"
    with atomic_write(out, "w") as file:  # a write cut half-way leaves the previous file whole
        file.write(splice(document, generated))
    return out
