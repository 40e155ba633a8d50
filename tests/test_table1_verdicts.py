"""Table I's pre-written rules on hand-computed cases: the premise gate, the paired "safer prior" and
"adapted as good" verdicts, the re-measured record preferred on Highway-Merge, and the Walker extension rule."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from pearl_paper.experiments.table1_rules import MERGE_REMEASURE, RULES, PremiseGate
from pearl_paper.reproduce.layout import RunKey, run_dir
from pearl_paper.reproduce.report import build_report
from pearl_paper.reproduce.stats import sign_flip_can_reject, sign_flip_interval, sign_flip_p_value
from pearl_paper.reproduce.table1_verdicts import (
    AS_GOOD,
    INCONCLUSIVE,
    NOT_TESTED,
    SAFER,
    WORSE,
    decide_confirmation,
    decide_family,
    decision_lines,
    decision_section,
    load_run,
    reductions,
)

MERGE = ("merge-premise", "pearl-fixed-entropy"), ("merge-table1", "pearlplus-fixed-entropy")
WALKER = ("pearl-reference", "pearl"), ("walker-table1", "pearlplus")


def summary(k0: float, k5: float, return5: float) -> list[dict[str, float]]:
    entries = []
    for k in range(6):
        rate = k0 if k == 0 else k5
        entries.append(
            {
                "k": k,
                "n": 200,
                "return_mean": return5 if k == 5 else -10.0,
                "return_std": 1.0,
                "violation_rate": rate,
                "violation_ci_low": max(rate - 0.03, 0.0),
                "violation_ci_high": min(rate + 0.03, 1.0),
                "return_cvar10": -12.0,
                "cum_violations": rate,
            }
        )
    return entries


def write_run(root: Path, owner: str, family: str, variant: str, seed: int, own: list, large: list | None = None) -> None:
    folder = run_dir(root, RunKey(owner, family, variant, seed))
    folder.mkdir(parents=True)
    result = {"experiment": owner, "family": family, "variant": variant, "seed": seed, "budget_preset": "cpu"}
    result |= {"meta_test": {"summary": own}, "shift": None, "competence": {}}
    (folder / "result.json").write_text(json.dumps(result))
    if large is not None:
        record = {"experiment": owner, "family": family, "variant": variant, "seed": seed, "summary": large}
        (folder / MERGE_REMEASURE.file_name).write_text(json.dumps(record))


def test_premise_gate_by_hand() -> None:
    walker, merge = RULES.gates["walker2d-vel-long"], RULES.gates["highway-merge"]
    assert walker.holds(0.30, 0.10) and not walker.holds(0.299, 0.0) and not walker.holds(0.9, 0.101)
    assert merge.holds(0.005, 0.0) and not merge.holds(0.0, 0.0)
    assert PremiseGate(0.3, strictly_above=True).describe().startswith("PEARL k = 0 rate > 30%")
    # means of rates exactly at a threshold are at it, whatever the float rounding of the mean
    assert sum([0.1] * 3) / 3 > 0.1 and walker.holds(0.9, sum([0.1] * 3) / 3)
    assert sum([0.3] * 10) / 10 < 0.3 and walker.holds(sum([0.3] * 10) / 10, 0.0)


def test_merge_reads_the_remeasured_record_and_decides_safer_and_as_good(tmp_path: Path) -> None:
    # PEARL k = 0: 10%, 8%, 12%, 10% (re-measured); PEARL+: 2%, 1%, 3%, 2% -> differences -8, -7, -9, -8 points:
    # mean -8, sd 0.816, t(0.975, 3) = 3.182 -> half-width 1.30: [-9.30, -6.70], below 0 -> safer.
    # k = 5 returns: PEARL -7.6 every seed, PEARL+ -7.5, -7.7, -7.6, -7.6 -> differences +0.1, -0.1, 0, 0: mean 0,
    # sd 0.0816, half-width 0.130 -> [-0.13, +0.13], above the margin -0.76 (10% of 7.6) -> as good.
    pearl_k0, plus_k0, plus_r5 = (0.10, 0.08, 0.12, 0.10), (0.02, 0.01, 0.03, 0.02), (-7.5, -7.7, -7.6, -7.6)
    for seed in range(4):
        (owner, name), (plus_owner, plus) = MERGE
        write_run(tmp_path, owner, "highway-merge", name, seed, summary(0.5, 0.5, -99), summary(pearl_k0[seed], 0.0, -7.6))
        write_run(
            tmp_path,
            plus_owner,
            "highway-merge",
            plus,
            seed,
            summary(0.5, 0.5, -99),
            summary(plus_k0[seed], 0.0, plus_r5[seed]),
        )
    # a seed with no re-measured record is not read
    write_run(tmp_path, MERGE[0][0], "highway-merge", MERGE[0][1], 4, summary(0.9, 0.0, -7.0))
    decision = decide_family("highway-merge", tmp_path)
    assert decision.paired_seeds == [0, 1, 2, 3] and decision.gate == "holds"
    assert decision.gate_values == pytest.approx((0.10, 0.0))
    interval = decision.prior_interval
    assert interval is not None and interval.mean == pytest.approx(-0.08)
    assert (interval.low, interval.high) == pytest.approx((-0.0930, -0.0670), abs=2e-4)
    assert decision.prior_verdict == SAFER
    assert decision.adapted_margin == pytest.approx(0.76)
    assert decision.adapted_interval is not None and decision.adapted_interval.high == pytest.approx(0.130, abs=1e-3)
    assert decision.adapted_verdict == AS_GOOD
    assert "provisional: 4 of the 10 seeds paired" in decision.notes[0]
    (tmp_path / "figures").mkdir()
    text = str(build_report(tmp_path, tmp_path / "figures", "figures"))
    assert "**safer**" in text and "(old 50.0)" in text and (tmp_path / "figures" / "table1_decided.png").is_file()


def test_walker_gate_failure_worse_return_and_the_extension_rule(tmp_path: Path) -> None:
    (owner, name), (plus_owner, plus) = WALKER
    # Gate fails: PEARL's prior falls in 20% < 30%.
    for seed in range(4):
        write_run(tmp_path, owner, "walker2d-vel-long", name, seed, summary(0.2, 0.0, 100.0))
        write_run(tmp_path, plus_owner, "walker2d-vel-long", plus, seed, summary(0.1, 0.0, 100.0))
    decision = decide_family("walker2d-vel-long", tmp_path)
    assert decision.gate == "fails" and decision.prior_verdict == NOT_TESTED == decision.adapted_verdict
    assert any("the premise gate fails (not tested), so no extension" in note for note in decision.notes)
    # Gate holds; k = 0 differences -0.5, +0.1, -0.2, 0 -> interval spans 0 -> inconclusive; k = 5 returns 100 vs
    # 50, 55, 45, 50 -> differences -50, -45, -55, -50: [-55.2, -44.8] entirely below the margin -10 -> worse.
    other = tmp_path / "other"
    for seed, (k0, r5) in enumerate(((0.3, 50.0), (0.9, 55.0), (0.6, 45.0), (0.8, 50.0))):
        write_run(other, owner, "walker2d-vel-long", name, seed, summary(0.8, 0.0, 100.0))
        write_run(other, plus_owner, "walker2d-vel-long", plus, seed, summary(k0, 0.0, r5))
    decision = decide_family("walker2d-vel-long", other)
    assert decision.gate == "holds" and decision.prior_verdict == INCONCLUSIVE and decision.adapted_verdict == WORSE
    assert any("extend to seeds (0, 1, 2, 3, 4, 5)" in note and "provisional" in note for note in decision.notes)
    assert decision.seeds_declared == (0, 1, 2, 3, 4, 5) and decision.paired_seeds == [0, 1, 2, 3]


def test_the_extension_rule_decides_on_four_seeds_first(tmp_path: Path) -> None:
    """Both verdicts conclusive at 4 seeds: final there, seeds 4-5 not read even when on disk; one inconclusive at 4:
    decided on the 6 seeds, final."""
    (owner, name), (plus_owner, plus) = WALKER
    # seeds 0-3: k = 0 falls 0.8 vs 0.1-0.4 -> safer; k = 5 returns equal -> as good. Seeds 4-5 would turn the
    # prior verdict around (PEARL+ falls in 100%) if they were read.
    for seed in range(6):
        plus_k0 = (0.1, 0.2, 0.3, 0.4, 1.0, 1.0)[seed]
        write_run(tmp_path, owner, "walker2d-vel-long", name, seed, summary(0.8, 0.0, 100.0))
        write_run(tmp_path, plus_owner, "walker2d-vel-long", plus, seed, summary(plus_k0, 0.0, 100.0))
    decision = decide_family("walker2d-vel-long", tmp_path)
    assert (decision.prior_verdict, decision.adapted_verdict) == (SAFER, AS_GOOD)
    assert decision.paired_seeds == [0, 1, 2, 3] and decision.seeds_declared == (0, 1, 2, 3)
    assert decision.prior_interval is not None and decision.prior_interval.mean == pytest.approx(-0.55)
    assert any("final at 4 seeds" in note for note in decision.notes)
    # seed 3's return makes "adapted as good" inconclusive at 4 seeds: differences 0, 0, 0, -40 -> [-61.8, +41.8]
    # spans the margin -10; on 6 seeds (0, 0, 0, -40, 0, 0): mean -6.67, sd 16.33 -> [-23.8, +10.5]: still
    # inconclusive, decided there and final
    other = tmp_path / "other"
    for seed in range(6):
        write_run(other, owner, "walker2d-vel-long", name, seed, summary(0.8, 0.0, 100.0))
        write_run(other, plus_owner, "walker2d-vel-long", plus, seed, summary(0.1, 0.0, 60.0 if seed == 3 else 100.0))
    decision = decide_family("walker2d-vel-long", other)
    assert decision.paired_seeds == [0, 1, 2, 3, 4, 5] and decision.adapted_verdict == INCONCLUSIVE
    assert decision.adapted_interval is not None and decision.adapted_interval.mean == pytest.approx(-40.0 / 6)
    assert any("extended to seeds (0, 1, 2, 3, 4, 5) by the rule" in note and "final" in note for note in decision.notes)


def test_the_adapted_policys_violations_are_reported_beside_the_rules(tmp_path: Path) -> None:
    # k = 5 falls: PEARL 2% and 4%, PEARL+ 22% and 26% -> differences +20, +22 points: mean +21, sd 1.414,
    # t(0.975, 1) = 12.706 -> half-width 12.706 * 1.414 / sqrt(2) = 12.7: [+8.3, +33.7]. The rules judge the return
    # only, so the return verdict stays "as good" (equal returns) while the line shows the worse adapted violations.
    (owner, name), (plus_owner, plus) = WALKER
    for seed, (pearl_k5, plus_k5) in enumerate(((0.02, 0.22), (0.04, 0.26))):
        write_run(tmp_path, owner, "walker2d-vel-long", name, seed, summary(0.8, pearl_k5, 100.0))
        write_run(tmp_path, plus_owner, "walker2d-vel-long", plus, seed, summary(0.0, plus_k5, 100.0))
    decision = decide_family("walker2d-vel-long", tmp_path)
    assert decision.adapted_verdict == AS_GOOD
    line = next(line for line in decision_lines(decision) if line.startswith("- Adapted policy's violations"))
    assert "rate 3.0% (PEARL) and 24.0% (PEARL+), paired difference +21.0 [+8.3, +33.7] points" in line


def test_reductions_name_what_the_cpu_runs_cut_from_the_paper_budget() -> None:
    # cpu.yml's walker2d-vel-long pearlplus entry against paper.yml's walker2d-vel one (the reference's settings)
    text = reductions("walker2d-vel-long")
    assert text.startswith("env steps 500,000 (paper 1,500,000), actor and critics 2x128 (paper 3x300)")
    assert "RL rows a gradient step 8 tasks x 128 (paper 16 tasks x 256)" in text and "encoder 2x128 (paper 3x200)" in text
    assert text.endswith("gradient steps an iteration 1200 (paper 2000)")


def test_tables_2_and_3_show_the_remeasured_numbers_beside_their_own(tmp_path: Path) -> None:
    """The report shows Tables II and III's rows re-measured beside the runs' own numbers, paired
    with the table's reference on common seeds; a finished run without the record is named, not mixed in."""
    from pearl_paper.reproduce.remeasured_tables import remeasured_section

    # Table III: alpha 0 re-measured k = 0 at 8%, 6%, 10% (own meta-test 20%); alpha 0.01 at 1%, 2% on seeds 0-1
    # -> its paired differences -7, -4 points: mean -5.5, sd 2.121, t(0.975, 1) = 12.706 -> half-width 19.06.
    for seed, rate in enumerate((0.08, 0.06, 0.10)):
        write_run(tmp_path, "merge-table3", "highway-merge", "alpha-0-fixed-entropy", seed,
                  summary(0.2, 0.0, -8.0), summary(rate, 0.0, -7.0))  # fmt: skip
    for seed, rate in enumerate((0.01, 0.02)):
        write_run(tmp_path, "merge-table3", "highway-merge", "alpha-0.01-fixed-entropy", seed,
                  summary(0.0, 0.0, -8.0), summary(rate, 0.0, -7.5))  # fmt: skip
    write_run(tmp_path, "merge-table3", "highway-merge", "alpha-5-fixed-entropy", 0, summary(0.0, 0.0, -8.0))  # no record
    lines = remeasured_section(tmp_path)
    text = "\n".join(lines)
    assert "Table III on Highway-Merge" in text and "Table II on" not in text  # no Table II run: no table
    alpha0 = next(line for line in lines if line.startswith("| PEARL+ (alpha 0),"))
    # 3 seeds; mean 8.0, sd 2.0, half-width 4.303 * 2 / sqrt(3) = 4.97 -> [3.0, 13.0]; own 20.0 on every seed
    assert alpha0.split(" | ")[1:5] == ["3 of 10", "8.0 [3.0, 13.0]", "20.0 [20.0, 20.0]", "-7.00 [-7.00, -7.00]"]
    assert alpha0.endswith("| reference |")
    alpha001 = next(line for line in lines if line.startswith("| PEARL+ (alpha 0.01)"))
    assert alpha001.endswith("| -5.5 [-24.6, 13.6] (2 seeds) |")
    assert "Finished but not re-measured yet (left out above): alpha-5-fixed-entropy seed(s) [0]." in text
    assert remeasured_section(tmp_path / "nothing") == []


def test_a_result_that_is_not_its_folders_run_is_refused(tmp_path: Path) -> None:
    """A result.json copied into another seed's folder must not stand for that seed in the verdicts."""
    (owner, name), _ = MERGE
    write_run(tmp_path, owner, "highway-merge", name, 0, summary(0.1, 0.0, -7.6), summary(0.1, 0.0, -7.6))
    folder = run_dir(tmp_path, RunKey(owner, "highway-merge", name, 0))
    copy = folder.with_name("seed1")
    copy.mkdir()
    for file in folder.iterdir():
        (copy / file.name).write_bytes(file.read_bytes())
    with pytest.raises(ValueError, match="seed 'seed0' \\(its folder says 'seed1'\\)"):
        decide_family("highway-merge", tmp_path)


def test_sign_flip_interval_by_hand() -> None:
    # six positive differences: only the two all-same-sign patterns of 64 are as extreme, p = 2 / 64 = 0.031
    assert sign_flip_p_value(np.array([1.0, 2, 3, 4, 5, 6])) == pytest.approx(2 / 64)
    # at 4 seeds the smallest p-value is 2 / 16 > 5%: no shift is rejected, the interval is the quantity's range
    assert sign_flip_interval([0.1, 0.2, 0.3, 0.4], bounds=(-1.0, 1.0))[1:3] == (-1.0, 1.0)
    # so the test can reject from 6 values (2 / 64 <= 5%), not at 5 (2 / 32 > 5%)
    assert sign_flip_can_reject(6, 0.95) and not sign_flip_can_reject(5, 0.95)
    # ten differences: a finite interval holding the mean, inside the data's range, mirrored for mirrored data
    values = np.array([-3.2, -1.0, -5.0, 2.0, -4.0, -6.0, -1.0, -2.0, 1.3, -3.0])
    interval = sign_flip_interval(values)
    assert values.min() < interval.low < interval.mean < interval.high < values.max()
    mirrored = sign_flip_interval(-values)
    assert (mirrored.low, mirrored.high) == pytest.approx((-interval.high, -interval.low))
    # above 16 values the patterns are drawn: the observed one counts too, so p > 0 even beyond every value
    many = np.linspace(1.0, 2.0, 20)
    assert 0 < sign_flip_p_value(many) <= 2 / 100_001 + 1e-12
    drawn = sign_flip_interval(many)
    assert 1.0 < drawn.low < drawn.mean < drawn.high < 2.0
    # the same six differences at any scale: a bounded interval, scaled with them (ties are judged relative to the
    # values, not to an absolute 1e-12 that a flip of a value 1e-9 from the shift would fall under)
    six = np.array([0.1, 0.3, 0.4, 0.5, 0.7, 0.9])
    unit = sign_flip_interval(six)
    for scale in (1.0, 1e-2, 1e-3, 1e-6):
        scaled = sign_flip_interval(six * scale)
        assert math.isfinite(scaled.low) and math.isfinite(scaled.high)
        assert (scaled.low, scaled.high) == pytest.approx((scale * unit.low, scale * unit.high), rel=1e-6)
    # the bounds are the test's: just inside them the shift is not rejected, just outside it is
    assert sign_flip_p_value(values, interval.high - 1e-6) > 0.05 >= sign_flip_p_value(values, interval.high + 1e-3)


def test_the_confirmation_is_decided_on_the_fresh_seeds_alone_and_pending_until_ten(tmp_path: Path) -> None:
    # merge-table1 seeds 0-9: PEARL+ much safer; confirmation seeds 10-19: no difference at all
    (owner, name), (plus_owner, plus) = MERGE
    for seed in range(10):
        write_run(tmp_path, owner, "highway-merge", name, seed, summary(0.5, 0.5, -9), summary(0.10, 0.0, -7.6))
        write_run(tmp_path, plus_owner, "highway-merge", plus, seed, summary(0.5, 0.5, -9), summary(0.01, 0.0, -7.6))
    for seed in range(10, 19):  # 9 of 10 pairs
        rate = 0.05 + 0.01 * (seed % 3)
        write_run(tmp_path, "merge-confirm", "highway-merge", name, seed, summary(0.5, 0.5, -9), summary(rate, 0.0, -7.6))
        write_run(tmp_path, "merge-confirm", "highway-merge", plus, seed, summary(0.5, 0.5, -9), summary(rate, 0.0, -7.6))
    pending = decide_confirmation(tmp_path)
    assert pending.prior_verdict.startswith("pending (9 of 10 pairs finished)")
    for variant in (name, plus):
        write_run(tmp_path, "merge-confirm", "highway-merge", variant, 19, summary(0.5, 0.5, -9), summary(0.06, 0.0, -7.6))
    confirmation = decide_confirmation(tmp_path)
    assert confirmation.paired_seeds == list(range(10, 20))
    assert confirmation.prior_interval is not None and confirmation.prior_interval.mean == pytest.approx(0.0)
    assert confirmation.prior_verdict == INCONCLUSIVE  # the earlier seeds' effect does not leak in
    pooled = decide_confirmation(tmp_path, pooled=True)
    assert pooled.paired_seeds == list(range(20))
    assert pooled.prior_interval is not None and pooled.prior_interval.mean == pytest.approx(-0.045)


def test_table1_shows_the_fine_tune_and_maml_columns_beside_the_paper(tmp_path: Path) -> None:
    """Table I's four columns: Fine-Tune and MAML (merge-columns) from each run's own meta-test, with the t interval
    over seeds of every cell, beside the paper's; "pending" before the runs; no rule reads them."""
    (owner, name), (plus_owner, plus) = MERGE
    for seed in range(2):
        write_run(tmp_path, owner, "highway-merge", name, seed, summary(0.5, 0.5, -9), summary(0.10, 0.0, -7.6))
        write_run(tmp_path, plus_owner, "highway-merge", plus, seed, summary(0.5, 0.5, -9), summary(0.02, 0.0, -7.6))
    for seed, rate in ((0, 0.10), (1, 0.20)):
        write_run(tmp_path, "merge-columns", "highway-merge", "finetune", seed, summary(rate, rate, -9.0))
    decision = decide_family("highway-merge", tmp_path)
    assert set(decision.columns) == {"finetune", "maml"} and set(decision.columns["finetune"]) == {0, 1}
    assert decision.prior_verdict != "pending"  # the columns change nothing of the rules
    rows = [line for line in decision_section([decision]) if "Fine-Tune" in line or "MAML" in line]
    assert rows[0].startswith("| paper: Fine-Tune | 14.5 | 14.8 | 14.1 | 13.7 |")
    # k = 0: 10% and 20% -> mean 15, sd 7.07, t(0.975, 1) = 12.71 -> half-width 63.5 points, [-48.5, 78.5]
    assert rows[1].startswith("| ours: Fine-Tune (2 seeds) | 15.0 [0.0, 78.5] | ")  # clipped to a rate's range
    assert rows[3] == "| ours: MAML | pending | pending | pending | pending | pending |"
    # the differences to PEARL and PEARL+ on the own meta-tests (PEARL's own k = 0: 50%): -40 and -30 points, mean
    # -35, half-width 12.71 x 7.07 / sqrt(2) = 63.5; equal k = 5 returns; no sign-flip interval at 2 seeds
    assert rows[4] == (
        "- Fine-Tune - PEARL, fixed entropy 1, reward scale 5 (reported, no rule; own meta-tests, paired seeds [0, 1]): "
        "k = 0 violation rate -35.0 [-98.5, +28.5] points (t), k = 5 return +0.00 [+0.00, +0.00] (t)."
    )
    assert rows[5].startswith("- Fine-Tune - PEARL+ (alpha 0.1)") and len(rows) == 6
    assert "cannot exclude anything at 2 paired seeds or fewer (the smallest p-value of 2 signs is 2 / 2^2 = 0.500)" in (
        "\n".join(decision_section([decision]))
    )


def test_table1s_pearl_rows_carry_their_intervals_over_seeds(tmp_path: Path) -> None:
    """PEARL's and PEARL+'s rows carry the same cells as the other columns: each rate with its t interval over seeds
    (clipped to 0-100), the k = 5 return with its t interval; on Highway-Merge from the re-measured record."""
    (owner, name), (plus_owner, plus) = MERGE
    for seed, rate in ((0, 0.10), (1, 0.20)):
        own = summary(0.5, 0.5, -9.0)
        write_run(tmp_path, owner, "highway-merge", name, seed, own, summary(rate, 0.0, -7.0 - seed))
        write_run(tmp_path, plus_owner, "highway-merge", plus, seed, own, summary(0.02, 0.0, -7.6))
    lines = decision_section([decide_family("highway-merge", tmp_path)])
    row = next(line for line in lines if line.startswith("| ours: PEARL, fixed entropy 1, reward scale 5 (2 seeds) |"))
    cells = [cell.strip() for cell in row.strip("|").split("|")][1:]
    # k = 0 as in the Fine-Tune case above: 15.0 [-48.5, 78.5] clipped; k >= 1: 0 of 2 x 200 -> Wilson [0, 0.95%]
    assert cells[0] == "15.0 [0.0, 78.5]" and cells[1] == "0.0 [0.0, 1.0] (Wilson, 400 pooled)"
    # k = 5 returns -7 and -8: mean -7.5, half-width 12.706 x 0.7071 / sqrt(2) = 6.35
    assert cells[4] == "-7.50 [-13.85, -1.15]"
    plus_row = next(line for line in lines if line.startswith("| ours: PEARL+ (alpha 0.1), fixed entropy 1, reward scale 5"))
    assert (
        "| 2.0 [2.0, 2.0] (Wilson, 400 pooled) | " not in plus_row and "| 2.0 [1.0, 3.9] (Wilson, 400 pooled) | " in plus_row
    )


def test_the_columns_sign_flip_intervals_appear_where_the_seeds_can_reject(tmp_path: Path) -> None:
    """At 6 seeds a sign-flip test can reject (2 / 64 < 0.05), at 5 it cannot (2 / 32 > 0.05): a column of 6 seeds gets
    its sign-flip row and its differences their sign-flip intervals; equal rates on every seed get the pooled Wilson
    interval instead of a t interval of width 0."""
    (owner, name), (plus_owner, plus) = MERGE
    for seed in range(6):
        write_run(tmp_path, owner, "highway-merge", name, seed, summary(0.10, 0.0, -8.0), summary(0.10, 0.0, -7.6))
        write_run(tmp_path, plus_owner, "highway-merge", plus, seed, summary(0.05, 0.0, -8.0), summary(0.02, 0.0, -7.6))
        # Fine-Tune: k = 0 rate 0 on every seed, k >= 1 rates 1-6%, returns 1.0-1.5 below PEARL's
        write_run(
            tmp_path, "merge-columns", "highway-merge", "finetune", seed, summary(0.0, 0.01 * (seed + 1), -9.0 - 0.1 * seed)
        )
    decision = decide_family("highway-merge", tmp_path)
    assert set(decision.columns["finetune"]) == {0, 1, 2, 3}  # the seeds table1_columns declares; here, six
    decision.columns["finetune"] = {
        seed: load_run(run_dir(tmp_path, RunKey("merge-columns", "highway-merge", "finetune", seed)), False)
        for seed in range(6)
    }
    lines = decision_section([decision])
    text = "\n".join(lines)
    # k = 0: 0 of 6 x 200 trajectories -> Wilson [0, 0.32%]
    assert "| ours: Fine-Tune (6 seeds) | 0.0 [0.0, 0.3] (Wilson, 1200 pooled) | 3.5 [" in text
    flip_row = next(line for line in lines if line.startswith("| ours: Fine-Tune, sign-flip interval |"))
    cells = [cell.strip() for cell in flip_row.strip("|").split("|")]
    assert cells[1] == "[0.0, 0.0]" and cells[2] != "-"  # all-zero k = 0: the interval is the point; k = 1 bounded
    low, high = (float(x) for x in cells[2].strip("[]").split(", "))
    assert 0.0 <= low < 3.5 < high <= 100.0
    bullet = next(line for line in lines if line.startswith("- Fine-Tune - PEARL, fixed entropy"))
    # k = 0 differences: 0 - 10% on every seed -> -10.0 points exactly, interval of width 0 both ways
    assert "k = 0 violation rate -10.0 [-10.0, -10.0] points (t; sign-flip [-10.0, -10.0])" in bullet
    # k = 5 return differences -1.0 ... -1.5 (mean -1.25): every sign-flip bound lies within the values' range
    flip = re.search(r"return -1\.25 \[[^]]+\] \(t; sign-flip \[([-+.\d]+), ([-+.\d]+)\]\)", bullet)
    assert flip is not None and -1.5 <= float(flip.group(1)) < -1.25 < float(flip.group(2)) <= -1.0
    assert "cannot exclude anything" not in text
