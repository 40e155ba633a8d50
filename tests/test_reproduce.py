"""The reproduction harness: the CLI end to end on the smoke budget, the statistics, the presets and the specs."""

from __future__ import annotations

import csv
import dataclasses
import math
from pathlib import Path
from typing import Any

import gymnasium as gym
import pytest

from pearl_paper.experiments import EXPERIMENTS, get_experiment
from pearl_paper.experiments.families import get_family
from pearl_paper.experiments.spec import Claim, Criterion, Experiment, PaperCell, Variant, claims_from_paper, resolve_k
from pearl_paper.reproduce.cells import cell_stats, load_groups
from pearl_paper.reproduce.cli import main
from pearl_paper.reproduce.competence import criterion_value, evaluate_competence
from pearl_paper.reproduce.layout import RESULT_KEYS, parse_seeds, write_json_atomic
from pearl_paper.reproduce.report import BEGIN, END, GENERATED, splice
from pearl_paper.reproduce.stats import (
    INCONCLUSIVE,
    NOT_REPRODUCED,
    REPRODUCED,
    Interval,
    clip_interval,
    paired_differences,
    t_interval,
    t_quantile,
    verdict,
)
from sb3_pearl import PEARLPlus
from sb3_pearl.budgets import (
    PRESETS,
    check_preset,
    check_statistics_floor,
    load_budget,
    model_kwargs,
    validate_entry,
)
from sb3_pearl.evaluation.held_out import held_out_record
from sb3_pearl.evaluation.meta_test import MetaTestResult
from tests.conftest import (
    Completed,
    _read_only_for_root,
    run_in_process,
    write_model_zip,
)

ROOT = Path(__file__).resolve().parent.parent
RUN_ARGS = ["safe-point", "--budget", "smoke", "--seeds", "0", "--family", "safe-point", "--variants", "alpha-0", "alpha-0.1"]


def reproduce(*args: str) -> Completed:
    """``python -m pearl_paper.reproduce ...``'s entry point in this process (its runs are still child processes)."""
    return run_in_process(main, *args)


@pytest.fixture(scope="module")
def results(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two smoke runs of the fast family (alpha 0 and 0.1, seed 0), run once for the module."""
    results_dir = tmp_path_factory.mktemp("results")
    out = reproduce("run", *RUN_ARGS, "--jobs", "2", "--results-dir", str(results_dir)).stdout
    assert "[2/2]" in out and "ETA" in out and "2 done, 0 skipped, 0 failed" in out
    return results_dir


def run_folder(results_dir: Path, variant: str) -> Path:
    return results_dir / "safe-point" / "safe-point" / variant / "seed0"


# ----------------------------------------------------------------------------------------------
# CLI end to end
# ----------------------------------------------------------------------------------------------
def test_train_py_and_the_harness_build_and_train_the_same_model(results: Path, tmp_path: Path) -> None:
    """The two paths from a budget preset to a model (``train.py --budget`` through rl_zoo3's experiment manager, and
    ``reproduce run`` through ``runner.run_one``) make the same model from the same entry and seed: every setting means
    the same on both, down to the weights after training (one process, so bit for bit on any CPU)."""
    import torch as th

    from sb3_pearl.zoo import train

    train(["--algo", "pearlplus", "--env", "SafePointGoalMeta-v0", "--budget", "smoke", "--seed", "0", "-f", str(tmp_path)])
    harness = PEARLPlus.load(run_folder(results, "alpha-0.1") / "model.zip")  # the smoke pearlplus entry, alpha 0.1
    zoo = PEARLPlus.load(tmp_path / "pearlplus" / "SafePointGoalMeta-v0_1" / "SafePointGoalMeta-v0.zip")
    assert (harness.num_timesteps, harness._n_updates) == (zoo.num_timesteps, zoo._n_updates) == (400, 17)
    assert harness.train_tasks == zoo.train_tasks and harness.test_tasks == zoo.test_tasks
    assert (harness.prior_coef, harness.latent_dim, harness.batch_size) == (zoo.prior_coef, zoo.latent_dim, zoo.batch_size)
    harness_weights, zoo_weights = harness.policy.state_dict(), zoo.policy.state_dict()
    assert harness_weights.keys() == zoo_weights.keys()
    for name, weight in harness_weights.items():
        assert th.equal(weight, zoo_weights[name]), name


def test_run_writes_the_layout(results: Path) -> None:
    import json

    for variant in ("alpha-0", "alpha-0.1"):
        folder = run_folder(results, variant)
        result = json.loads((folder / "result.json").read_text())
        assert set(RESULT_KEYS) <= set(result)
        assert (result["experiment"], result["family"], result["variant"], result["seed"]) == (
            "safe-point",
            "safe-point",
            variant,
            0,
        )
        assert result["budget_preset"] == "smoke" and result["eval_seed"] == get_experiment("safe-point").eval_seed
        assert result["model_kwargs"]["prior_coef"] == float(variant.split("-")[1])
        settings = result["budget"]["meta_test"]
        assert len(result["meta_test"]["rows"]) == settings["n_tasks"] * settings["n_repeats"] * (settings["n_adapt"] + 1)
        assert [entry["k"] for entry in result["meta_test"]["summary"]] == list(range(settings["n_adapt"] + 1))
        assert result["meta_test"]["config"]["crn_seed"] == result["eval_seed"]
        assert result["shift"] is None  # the fast family declares no shifted distribution
        assert {"train", "meta_test", "total"} <= set(result["wall_time_s"])
        assert result["versions"]["torch"] and result["cpu"]["cores"] >= 1
        assert "passed" in result["competence"] and result["competence"]["criteria"][0]["key"] == "distance"
        assert "error" not in result["diagnostics"] and "overlap" in result["diagnostics"]
        model = PEARLPlus.load(folder / "model.zip", device="cpu")
        assert model.prior_coef == result["model_kwargs"]["prior_coef"]
        # The record is the meta-test of every trained model (train.py's too), reproduced from model.zip alone.
        env = gym.make("SafePointGoalMeta-v0", **result["spec"]["family"]["env_kwargs"])
        again = held_out_record(model, env, settings, result["eval_seed"], {})
        assert again["rows"] == result["meta_test"]["rows"] and again["summary"] == result["meta_test"]["summary"]
        with open(folder / "progress.csv") as file:
            rows = list(csv.DictReader(file))
        assert rows and "train/critic_loss" in rows[0] and "time/total_timesteps" in rows[0]
    # CRN: both variants saw the same test tasks
    tasks = [
        json.loads((run_folder(results, v) / "result.json").read_text())["meta_test"]["tasks"]
        for v in ("alpha-0", "alpha-0.1")
    ]
    assert tasks[0] == tasks[1]


def test_run_is_idempotent_and_force_reruns(results: Path) -> None:
    path = run_folder(results, "alpha-0") / "result.json"
    before = path.stat().st_mtime_ns
    out = reproduce("run", *RUN_ARGS, "--results-dir", str(results)).stdout
    assert out.count("skip ") == 2 and "0 done, 2 skipped" in out
    assert path.stat().st_mtime_ns == before
    args = [a for a in RUN_ARGS if a != "alpha-0.1"]
    stale = path.parent / "meta_test_large.json"  # a record measured from the model the rerun replaces
    stale.write_text("{}")
    out = reproduce("run", *args, "--force", "--results-dir", str(results)).stdout
    assert "1 done, 0 skipped" in out
    assert path.stat().st_mtime_ns != before
    assert not stale.exists()  # nothing in the folder describes the old model


def test_measure_brings_older_measures_up_to_date(results: Path, tmp_path: Path) -> None:
    """`reproduce measure` brings a run measured by version 1 up to date (the calibration, from its model.zip) and
    leaves current ones; --force measures everything again."""
    import json
    import shutil

    from pearl_paper.reproduce.prior_measures import MEASURES_VERSION

    folder = tmp_path / "safe-point" / "safe-point" / "alpha-0.1" / "seed0"
    shutil.copytree(run_folder(results, "alpha-0.1"), folder)
    path = folder / "result.json"
    current = json.loads(path.read_text())
    assert current["prior_critic"]["version"] == MEASURES_VERSION
    older = json.loads(path.read_text())
    older["prior_critic"]["version"] = MEASURES_VERSION - 1
    for key in ("task_blind_relative_error", "task_blind_rank_corr"):
        del older["prior_critic"]["calibration"][key]
    older["prior_critic"]["prior_optimality"]["kept"] = True  # version 1 -> 2 redoes the calibration only
    path.write_text(json.dumps(older))
    assert "1 run(s) measured" in reproduce("measure", "--results-dir", str(tmp_path)).stdout
    upgraded = json.loads(path.read_text())
    assert upgraded["prior_critic"]["prior_optimality"].pop("kept")
    assert upgraded["prior_critic"].pop("calibration_remeasured")["from_version"] == 1
    assert upgraded == current  # the measures of the run's own end, from its model.zip
    assert "0 run(s) measured" in reproduce("measure", "--results-dir", str(tmp_path)).stdout
    assert "1 run(s) measured" in reproduce("measure", "--force", "--results-dir", str(tmp_path)).stdout
    # a run whose model.zip is gone is named and skipped (not a traceback that stops the other runs' measurement)
    (folder / "model.zip").unlink()
    out = reproduce("measure", "--force", "--results-dir", str(tmp_path)).stdout
    assert f"skip {path}" in out and "model.zip" in out and "0 run(s) measured" in out


def test_report_builds_tables_and_figures(results: Path, tmp_path: Path) -> None:
    out = tmp_path / "docs" / "results.md"
    out.parent.mkdir()
    out.write_text("# Results\n\nHand-written preamble.\n\n" + BEGIN + "\nold\n" + END + "\n\nHand-written tail.\n")
    reproduce("report", "--results-dir", str(results), "--out", str(out))
    text = out.read_text()
    assert text.startswith("# Results\n\nHand-written preamble.") and text.rstrip().endswith("Hand-written tail.")
    assert "old" not in text.split(BEGIN)[1].split(END)[0]
    assert "| [safe-point](experiments/safe-point.md) |" in text  # the summary's index of the experiment pages
    page = (out.parent / "experiments" / "safe-point.md").read_text()  # the experiment's detail: a page of its own
    assert page.startswith(GENERATED) and "| PEARL+ (alpha 0) | 0 |" not in text
    assert "| PEARL+ (alpha 0) | 0 |" in page and "| PEARL+ (alpha 0.1) | 2 |" in page
    assert "violation PEARL+ (alpha 0.1) < PEARL+ (alpha 0)" in page and "**inconclusive**" in page  # one seed
    diagnostics = page.split("Prior diagnostics")[1].split("Wall times")[0]  # one row per diagnosed variant
    assert "| PEARL+ (alpha 0) |" in diagnostics and "| PEARL+ (alpha 0.1) |" in diagnostics
    figure = out.parent / "figures" / "reproduce_safe-point_safe-point_smoke.png"
    assert figure.is_file() and figure.stat().st_size > 1000
    assert "(../figures/reproduce_safe-point_safe-point_smoke.png)" in page  # from docs/experiments/ to docs/figures/
    # A generated page whose experiment has no result any more goes; a hand-written page there stays.
    (out.parent / "experiments" / "gone.md").write_text(GENERATED + "\n\n# an experiment without results\n")
    (out.parent / "experiments" / "notes.md").write_text("# hand-written\n")
    reproduce("report", "--results-dir", str(results), "--out", str(out))
    assert sorted(path.name for path in (out.parent / "experiments").iterdir()) == ["notes.md", "safe-point.md"]


def _fake_result(rates: list[float], returns: list[float]) -> dict[str, Any]:
    return {
        "meta_test": {
            "summary": [
                {"k": k, "violation_rate": r, "return_mean": g, "n": 200} for k, (r, g) in enumerate(zip(rates, returns))
            ]
        }
    }


def test_seed_table_and_figure_show_each_seed(tmp_path: Path) -> None:
    from pearl_paper.reproduce.figures import plot_seeds
    from pearl_paper.reproduce.report import seed_table

    experiment = get_experiment("safe-point")
    group = {
        "alpha-0": {
            0: _fake_result([0.38, 0.1, 0.05], [-30.0, -20.0, -15.0]),
            1: _fake_result([0.335, 0.2, 0.1], [-31, -21, -16]),
        },
        "alpha-0.1": {
            0: _fake_result([0.42, 0.0, 0.0], [-33.0, -19.0, -18.5]),
            1: _fake_result([0.17, 0.0, 0.0], [-29, -20, -17]),
        },
    }
    lines = seed_table(experiment, group)
    assert lines[0] == "| variant | k | seed 0 | seed 1 |"
    # k = 0 and the last k (2) per variant, seed columns in order
    assert "| PEARL+ (alpha 0) | 0 | 38.0% / -30.0 | 33.5% / -31.0 |" in lines
    assert "| PEARL+ (alpha 0.1) | 2 | 0.0% / -18.5 | 0.0% / -17.0 |" in lines
    assert len(lines) == 2 + 2 * 2
    # a seed missing for one variant leaves its cell empty
    del group["alpha-0.1"][1]
    assert "| PEARL+ (alpha 0.1) | 0 | 42.0% / -33.0 |  |" in seed_table(experiment, group)
    assert plot_seeds(experiment, group, tmp_path / "seeds.png")
    assert (tmp_path / "seeds.png").stat().st_size > 1000
    # one seed: nothing to compare across seeds
    one = {v: {0: seeds[0]} for v, seeds in group.items()}
    assert seed_table(experiment, one) == [] and not plot_seeds(experiment, one, tmp_path / "none.png")
    assert not (tmp_path / "none.png").exists()


def test_run_rejects_bad_arguments(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from pearl_paper.reproduce.cli import main

    for args, message in (
        (["run", "safe-point", "--budget", "smoke", "--family", "nope"], "has no family 'nope'"),
        (["run", "safe-point", "--budget", "smoke", "--variants", "pearl"], "has no variant 'pearl'"),
        (["run", "safe-point", "--budget", "smoke", "--seeds", "3-1"], "empty range"),
        (["run", "safe-point", "--budget", "smoke", "--seeds", "10004"], "differ from eval_seed 10004"),
    ):
        assert main([*args, "--results-dir", str(tmp_path)]) == 2
        assert message in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # nothing started


def test_run_refuses_a_result_of_another_budget(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from pearl_paper.reproduce.cli import main
    from pearl_paper.reproduce.layout import write_json_atomic

    folder = run_folder(tmp_path, "alpha-0")
    folder.mkdir(parents=True)
    summary = [{"k": 0, "n": 1, "return_mean": -1.0, "violation_rate": 0.0}]
    keys = {
        "experiment": "safe-point",
        "family": "safe-point",
        "variant": "alpha-0",
        "seed": 0,
        "meta_test": {"summary": summary},
    }
    write_json_atomic(folder / "result.json", {**keys, "budget_preset": "cpu"})
    assert main(["run", *RUN_ARGS[:-1], "--results-dir", str(tmp_path)]) == 2
    assert "was run with budget preset 'cpu', not 'smoke'" in capsys.readouterr().err
    assert sorted(p.name for p in folder.iterdir()) == ["result.json"]  # atomic write left no temporary file


def test_run_dry_run_lists_the_plan(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from pearl_paper.reproduce.cli import main

    args = ["run", "table2", "--budget", "cpu", "--seeds", "0-1", "--family", "highway-merge", "--dry-run"]
    assert main([*args, "--results-dir", str(tmp_path)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 4 * 2 + 1 and lines[0].startswith("table2 highway-merge pearl seed0: starts: pearl, ")
    assert lines[-1].startswith("Dry run, nothing started: 0 done (skipped), 0 would resume from a checkpoint, 8 would start")
    assert not any(tmp_path.iterdir())


def test_run_notes_seeds_a_variant_does_not_declare(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--seeds applies to every chosen variant; a seed the report would leave out is named before anything runs."""
    from pearl_paper.reproduce.cli import main

    args = ["run", "merge-table3", "--variants", "alpha-0-fixed-entropy", "alpha-1-fixed-entropy", "--seeds", "3-5"]
    assert main([*args, "--dry-run", "--results-dir", str(tmp_path)]) == 0
    err = capsys.readouterr().err
    assert (
        "merge-table3 does not declare seeds [4, 5] for alpha-1-fixed-entropy on highway-merge (its seeds there: [0, 1, 2, 3])"
        in err
    )
    assert "for alpha-0-fixed-entropy" not in err  # alpha 0 declares Table I's 10 seeds


def test_run_dry_run_says_what_is_done_resumed_and_started(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A finished run is listed as skipped, one with a checkpoint as resumed, the others as started (a dry
    run must not list finished runs as if they would run); --force starts all from zero; nothing on disk changes."""
    from pearl_paper.reproduce.checkpoint import RunCheckpoint
    from pearl_paper.reproduce.cli import main
    from pearl_paper.reproduce.layout import write_json_atomic

    done, partway = run_folder(tmp_path, "alpha-0.1"), tmp_path / "safe-point" / "safe-point" / "alpha-0.1" / "seed1"
    done.mkdir(parents=True)
    keys = {"experiment": "safe-point", "family": "safe-point", "variant": "alpha-0.1", "seed": 0, "budget_preset": "smoke"}
    summary = [{"k": 0, "n": 1, "return_mean": -1.0, "violation_rate": 0.0}]
    times = {"cpu": {"cpu_time_s": 3600.0}, "wall_time_s": {"total": 3600.0, "train": 3000.0}}
    write_json_atomic(done / "result.json", {**keys, "meta_test": {"summary": summary}, **times})
    (partway / "checkpoint").mkdir(parents=True)
    write_model_zip(partway / "checkpoint" / "model_240.zip")
    state = {"phase": "train", "files": {"model": "model_240.zip"}, "num_timesteps": 240, "phases": {},
             "spent": {"cpu_s": 24.0, "wall_s": 30.0}}  # fmt: skip
    RunCheckpoint(partway).write_state(state)
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    args = ["run", "safe-point", "--budget", "smoke", "--seeds", "0-2", "--family", "safe-point", "--variants", "alpha-0.1"]
    args.append("--results-dir")
    assert main([*args, str(tmp_path), "--dry-run"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    label = "safe-point safe-point alpha-0.1 seed"
    assert lines[0] == f"{label}0: done, skipped ({done / 'result.json'} exists; --force reruns it)"
    assert lines[1].startswith("safe-point safe-point alpha-0.1 seed1: resumes from its checkpoint (train 240/400 steps")
    assert lines[2].startswith("safe-point safe-point alpha-0.1 seed2: starts: pearlplus, 400 steps, meta-test ")
    # the missing run at the finished one's CPU time (1 h), the part-way one at its own rate (0.1 s a step, 160 steps
    # left) plus the finished one's evaluation (600 s): `reproduce status`'s estimate
    assert lines[3] == (
        "Dry run, nothing started: 1 done (skipped), 1 would resume from a checkpoint, 1 would start; "
        f"CPU time left {(3600 + 16 + 600) / 3600:.2f} h (one core)"
    )
    assert main([*args, str(tmp_path), "--dry-run", "--force"]) == 0
    forced = capsys.readouterr().out.strip().splitlines()
    assert forced[0].startswith("safe-point safe-point alpha-0.1 seed0: starts from zero (--force replaces its result.json)")
    assert forced[1].startswith("safe-point safe-point alpha-0.1 seed1: starts from zero (--force drops its checkpoint)")
    assert forced[-1] == "Dry run, nothing started: 0 done (skipped), 0 would resume from a checkpoint, 3 would start"
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before  # a dry run touches nothing
    # a finished run of another preset: the dry run refuses it as the run would
    write_json_atomic(done / "result.json", {**keys, "budget_preset": "cpu", "meta_test": {"summary": summary}})
    assert main([*args, str(tmp_path), "--dry-run"]) == 2
    assert "was run with budget preset 'cpu', not 'smoke'" in capsys.readouterr().err


# ----------------------------------------------------------------------------------------------
# Statistics
# ----------------------------------------------------------------------------------------------
def test_t_quantile_and_interval_by_hand() -> None:
    for df, expected in ((1, 12.7062), (3, 3.1824), (9, 2.2622), (30, 2.0423)):
        assert t_quantile(0.975, df) == pytest.approx(expected, abs=1e-4)
    assert t_quantile(0.025, 3) == pytest.approx(-3.1824, abs=1e-4)
    # [1, 2, 3, 4]: mean 2.5, sd sqrt(5/3), half-width 3.1824 * 1.2910 / 2 = 2.0543
    interval = t_interval([1.0, 2.0, 3.0, 4.0])
    assert interval.mean == 2.5 and interval.n == 4
    assert interval.low == pytest.approx(0.4457, abs=1e-4) and interval.high == pytest.approx(4.5543, abs=1e-4)
    single = t_interval([0.3])
    assert single.mean == 0.3 and math.isnan(single.low) and math.isnan(single.high)
    assert tuple(t_interval([0.2, 0.2, 0.2])) == pytest.approx((0.2, 0.2, 0.2, 3))


def test_a_rates_interval_is_clipped_to_0_1_and_a_missing_bound_stays_missing() -> None:
    # rates 0.0 and 0.4 over 2 seeds: mean 0.2, sd 0.283, half-width 12.706 * 0.283 / sqrt(2) = 2.54 -> [-2.34, 2.74]
    interval = t_interval([0.0, 0.4])
    assert interval.low < -2.0 and interval.high > 2.0
    assert tuple(clip_interval(interval)) == pytest.approx((0.2, 0.0, 1.0, 2))
    single = clip_interval(t_interval([0.3]))
    assert single.mean == 0.3 and math.isnan(single.low) and math.isnan(single.high)
    assert tuple(clip_interval(t_interval([0.3, 0.4, 0.5]))) == tuple(t_interval([0.3, 0.4, 0.5]))  # inside: unchanged
    # the experiment pages' cells use it: a rate's t interval over seeds never leaves 0-100%
    stats = cell_stats(
        {
            0: {"meta_test": {"summary": [{"k": 0, "n": 10, "violation_rate": 0.0, "return_mean": 1.0}]}},
            1: {"meta_test": {"summary": [{"k": 0, "n": 10, "violation_rate": 0.4, "return_mean": 2.0}]}},
        },
        0,
    )
    assert stats is not None and (stats.violation.low, stats.violation.high) == (0.0, 1.0)


def test_paired_differences_use_common_seeds() -> None:
    assert paired_differences({0: 0.1, 1: 0.2, 3: 0.5}, {0: 0.3, 1: 0.2, 2: 0.9}) == pytest.approx({0: -0.2, 1: 0.0})


@pytest.mark.parametrize(
    "direction, low, high, expected",
    [
        ("lower", -0.40, -0.10, REPRODUCED),
        ("lower", 0.02, 0.20, NOT_REPRODUCED),  # the other direction
        ("lower", -0.03, 0.02, NOT_REPRODUCED),  # any effect smaller than the margin
        ("lower", -0.04, -0.01, NOT_REPRODUCED),  # significant but negligible
        ("lower", -0.30, 0.10, INCONCLUSIVE),
        ("higher", 0.10, 0.40, REPRODUCED),
        ("higher", -0.20, -0.02, NOT_REPRODUCED),
        ("higher", -0.10, 0.30, INCONCLUSIVE),
        ("equal", -0.02, 0.03, REPRODUCED),
        ("equal", 0.06, 0.20, NOT_REPRODUCED),
        ("equal", -0.02, 0.10, INCONCLUSIVE),
        ("not_lower", -0.04, 0.50, REPRODUCED),
        ("not_lower", -0.50, -0.06, NOT_REPRODUCED),
        ("not_lower", -0.10, 0.10, INCONCLUSIVE),
        ("not_higher", -0.50, 0.04, REPRODUCED),
        ("not_higher", 0.06, 0.50, NOT_REPRODUCED),
        ("not_higher", -0.10, 0.10, INCONCLUSIVE),
    ],
)
def test_verdict_rule(direction: str, low: float, high: float, expected: str) -> None:
    assert verdict(Interval(0.5 * (low + high), low, high, 4), direction, margin=0.05) == expected


def test_verdict_needs_two_seeds_and_a_margin() -> None:
    assert verdict(Interval(-0.5, math.nan, math.nan, 1), "lower", 0.05) == INCONCLUSIVE
    assert verdict(t_interval([0.0, 0.0, 0.0]), "equal", 0.05) == REPRODUCED  # both never violate
    with pytest.raises(ValueError, match="margin"):
        verdict(Interval(0.0, -1.0, 1.0, 3), "lower", 0.0)
    with pytest.raises(ValueError, match="direction"):
        verdict(Interval(0.0, -1.0, 1.0, 3), "sideways", 0.05)


# ----------------------------------------------------------------------------------------------
# Presets
# ----------------------------------------------------------------------------------------------
def test_presets_load() -> None:
    for preset in PRESETS:
        assert check_preset(preset) >= 16  # 4 families x 4 algorithms
    budget = load_budget("cpu", "safe-point", "pearlplus")
    assert budget["n_timesteps"] >= 90_000 and budget["kwargs"]["prior_coef"] == 0.1
    assert budget["meta_test"]["n_repeats"] >= 10 and budget["meta_test"]["n_tasks"] * budget["meta_test"]["n_repeats"] >= 200
    assert budget["competence_meta_test"]["n_tasks"] >= 1
    maml = model_kwargs(load_budget("cpu", "walker2d-vel", "maml")["kwargs"])
    assert maml["policy_kwargs"]["activation_fn"].__name__ == "Tanh"


@pytest.mark.parametrize(
    "args, message",
    [
        (("gpu", "safe-point", "pearl"), "unknown budget preset 'gpu'"),
        (("cpu", "cheetah", "pearl"), "has no family 'cheetah'"),
        (("cpu", "safe-point", "sac"), "has no algorithm 'sac'"),
    ],
)
def test_presets_reject_unknown_names(args: tuple[str, str, str], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        load_budget(*args)


def test_walker_reference_family_reduces_only_the_rows_of_the_reference_configuration() -> None:
    """walker2d-vel-ref at `cpu` is the paper preset's Walker2D-vel PEARL (the reference's) with cheetah-vel's one cut."""
    experiment = get_experiment("pearl-reference")
    names = ["cheetah-vel", "walker2d-vel-long", "walker2d-vel-ref", "walker2d-vel-ref-long", "ant3d-vel-long"]
    assert [f.name for f in experiment.families] == names
    ref = next(f for f in experiment.families if f.name == "walker2d-vel-ref")
    assert ref.env_id == "Walker2dVelMeta-v0" and ref.competence == get_family("walker2d-vel").competence
    cpu, paper = load_budget("cpu", "walker2d-vel-ref", "pearl"), load_budget("paper", "walker2d-vel", "pearl")
    cheetah_cpu, cheetah_paper = load_budget("cpu", "cheetah-vel", "pearl"), load_budget("paper", "cheetah-vel", "pearl")
    differs = {k for k in cpu["kwargs"].keys() | paper["kwargs"].keys() if cpu["kwargs"].get(k) != paper["kwargs"].get(k)}
    assert differs == {"batch_size"} and cpu["kwargs"]["batch_size"] == cheetah_cpu["kwargs"]["batch_size"] == 32
    assert paper["kwargs"]["batch_size"] == cheetah_paper["kwargs"]["batch_size"] == 256
    assert cpu["n_timesteps"] == 500_000 and cpu["curve"]["every"] == 20_000
    # walker2d-vel-ref-long: the same entry, only trained three times longer (its first 500k steps are walker2d-vel-ref's)
    long = load_budget("cpu", "walker2d-vel-ref-long", "pearl")
    assert {k: v for k, v in long.items() if k != "n_timesteps"} == {k: v for k, v in cpu.items() if k != "n_timesteps"}
    assert long["n_timesteps"] == 1_500_000
    ref_long = next(f for f in experiment.families if f.name == "walker2d-vel-ref-long")
    assert dataclasses.replace(ref_long, name=ref.name, title=ref.title, budget_family=ref.budget_family) == ref
    # ant3d-vel-long: Table I's Ant-3D-Vel PEARL (family and `cpu` entry) to 500k env steps with the curve, nothing else
    ant_long, ant = experiment.family("ant3d-vel-long"), get_family("ant3d-vel")
    assert dataclasses.replace(ant_long, name=ant.name, title=ant.title, budget_family=ant.budget_family) == ant
    long_ant, table1_ant = load_budget("cpu", "ant3d-vel-long", "pearl"), load_budget("cpu", "ant3d-vel", "pearl")
    assert {k: v for k, v in long_ant.items() if k not in ("n_timesteps", "curve")} == {
        k: v for k, v in table1_ant.items() if k not in ("n_timesteps", "curve")
    }
    assert (long_ant["n_timesteps"], table1_ant["n_timesteps"]) == (500_000, 80_000) and long_ant["curve"]["every"] == 20_000


def test_preset_entry_validation() -> None:
    good: dict[str, Any] = {"n_timesteps": 1000, "kwargs": {"batch_size": 16}, "meta_test": {"n_tasks": 20, "n_repeats": 10}}
    assert validate_entry(good, "pearl", "test")["meta_test"]["n_adapt"] == 5
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['n_steps'\]"):
        validate_entry({**good, "n_steps": 5}, "pearl", "test")
    with pytest.raises(ValueError, match=r"PEARL does not take \['prior_coef'\]"):
        validate_entry({**good, "kwargs": {"prior_coef": 0.1}}, "pearl", "test")
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['n_task'\]"):
        validate_entry({**good, "meta_test": {"n_task": 3}}, "pearl", "test")
    with pytest.raises(ValueError, match="activation_fn"):
        validate_entry({**good, "kwargs": {"policy_kwargs": {"activation_fn": "swish"}}}, "pearl", "test")
    with pytest.raises(ValueError, match="n_timesteps must be a positive integer"):
        validate_entry({**good, "n_timesteps": 0}, "pearl", "test")
    with pytest.raises(ValueError, match=r"n_repeats >= 10 prior draws per test task .* got 40 x 5"):
        check_statistics_floor({"n_tasks": 40, "n_repeats": 5}, (10, 200), "test")
    with pytest.raises(ValueError, match=r">= 200 k = 0 trajectories, got 10 x 10"):
        check_statistics_floor({"n_tasks": 10, "n_repeats": 10}, (10, 200), "test")


# ----------------------------------------------------------------------------------------------
# Specs
# ----------------------------------------------------------------------------------------------
def test_experiments_are_declared() -> None:
    assert set(EXPERIMENTS) == {
        "table1",
        "table2",
        "table3",
        "safe-point",
        "prior-critic",
        "prior-critic-walker",
        "pearl-reference",
        "merge-premise",
        "merge-table1",
        "merge-table2",
        "merge-table3",
        "walker-table1",
        "merge-confirm",
        "oracle",
        "oracle-merge",
        "walker-columns",
        "merge-columns",
    }
    confirm, table1_merge = get_experiment("merge-confirm"), get_experiment("merge-table1")
    # the confirmation is merge-table1's comparison on fresh seeds: same models, family, budget and held-out tasks
    assert confirm.seeds == tuple(range(10, 20)) and not set(confirm.seeds) & set(table1_merge.seeds)
    assert all(a.same_model(b) for a, b in zip(confirm.variants, table1_merge.variants, strict=True))
    assert (confirm.families, confirm.budget, confirm.eval_seed) == (
        table1_merge.families,
        table1_merge.budget,
        table1_merge.eval_seed,
    )
    assert not confirm.shared  # both variants' runs in its own folder
    premise = get_experiment("merge-premise")  # only the entropy setting differs from table1's PEARL, which it shares
    fixed = premise.variant("pearl-fixed-entropy")
    assert fixed.algo == "pearl" and dict(fixed.overrides) == {"ent_coef": 1.0, "reward_scale": 5.0}
    assert premise.shared == {"pearl": "table1"} and premise.eval_seed == get_experiment("table1").eval_seed
    table1 = get_experiment("table1")
    assert {f.name for f in table1.families} == {"walker2d-vel", "ant3d-vel", "highway-merge"}
    assert {v.algo for v in table1.variants} == {"pearl", "pearlplus", "finetune", "maml"}
    assert table1.paper_value("walker2d-vel", "pearl", "violation", 0, 5).value == pytest.approx(0.607)  # type: ignore[union-attr]
    table2 = get_experiment("table2")
    assert table2.variant("pearlplus-wo").overrides["prior_critic"] == "shared"
    assert table2.variant("pearlplus-100").overrides["prior_critic_arch"] == [100, 100, 100]
    assert table2.paper_value("highway-merge", "pearl", "return", 5, 5).value == -33.44 + 100.72  # type: ignore[union-attr]
    table3 = get_experiment("table3")
    assert table3.paper_value("highway-merge", "alpha-0.01", "violation", 0, 5).value == pytest.approx(0.35)  # type: ignore[union-attr]
    safe = get_experiment("safe-point")
    assert [f.name for f in safe.families] == ["safe-point", "safe-point-crash5"]
    assert safe.family("safe-point-crash5").env_kwargs == {"crash_penalty": 5.0}
    assert {v.overrides["prior_coef"] for v in safe.variants} == {0.0, 0.1, 1.0, 5.0}
    assert resolve_k(-1, 5) == 5 and resolve_k(3, 5) == 3


def test_spec_validation_errors() -> None:
    pearl = Variant("pearl", "PEARL", "pearl")
    family = get_experiment("table3").families[0]
    with pytest.raises(ValueError, match="names an unknown family or variant"):
        Experiment("x", "x", "x", (family,), (pearl,), claims=(Claim(family.name, "ghost", "pearl", "violation", 0, "lower"),))
    with pytest.raises(ValueError, match="duplicated variant names"):
        Experiment("x", "x", "x", (family,), (pearl, pearl))
    with pytest.raises(ValueError, match="eval_seed"):
        Experiment("x", "x", "x", (family,), (pearl,), seeds=(0, 7), eval_seed=7)
    with pytest.raises(ValueError, match="after_selection names unknown variants"):
        Experiment("x", "x", "x", (family,), (pearl,), after_selection=("ghost",))
    with pytest.raises(ValueError, match="after_selection names shared variants"):
        Experiment("x", "x", "x", (family,), (pearl,), shared={"pearl": "table3"}, after_selection=("pearl",))
    with pytest.raises(ValueError, match="unknown algo"):
        Variant("sac", "SAC", "sac")
    with pytest.raises(ValueError, match="results folder"):
        Variant("PEARL plus", "PEARL+", "pearlplus")


def test_claims_from_paper() -> None:
    paper = (
        PaperCell("f", "pearl", "violation", 0, 0.6),
        PaperCell("f", "plus", "violation", 0, 0.0),
        PaperCell("f", "pearl", "violation", 1, 0.03),
        PaperCell("f", "plus", "violation", 1, 0.0),
        PaperCell("f", "worse", "violation", 1, 0.2),
    )
    claims = {(c.variant, c.k): c.direction for c in claims_from_paper(paper, "pearl")}
    assert claims == {("plus", 0): "lower", ("plus", 1): "equal", ("worse", 1): "higher"}


# ----------------------------------------------------------------------------------------------
# Small helpers
# ----------------------------------------------------------------------------------------------
def test_parse_seeds() -> None:
    assert parse_seeds("0-3") == [0, 1, 2, 3]
    assert parse_seeds("5,0-1,1") == [0, 1, 5]
    with pytest.raises(ValueError, match="not a seed"):
        parse_seeds("a")


def test_splice_keeps_the_hand_written_text() -> None:
    assert splice("# R\n\nintro\n", "gen") == f"# R\n\nintro\n\n{BEGIN}\ngen\n{END}\n"
    assert splice(f"a\n{BEGIN}\nold\n{END}\nb\n", "new") == f"a\n{BEGIN}\nnew\n{END}\nb\n"
    with pytest.raises(ValueError, match="only one of the markers"):
        splice(f"a\n{BEGIN}\n", "new")


def test_competence_criteria() -> None:
    rows = [
        {"task": 0, "repeat": 0, "k": 0, "violated": True, "merged": 0.0},
        {"task": 0, "repeat": 0, "k": 1, "violated": False, "merged": 1.0},
        {"task": 0, "repeat": 0, "k": 2, "violated": True, "merged": 0.0},
    ]
    traces = [
        {"task": 0, "repeat": 0, "k": 0, "reward_forward": [-9.0]},
        {"task": 0, "repeat": 0, "k": 1, "reward_forward": [-0.1, -0.3]},
        {"task": 0, "repeat": 0, "k": 2, "reward_forward": [-0.2, -0.6]},
    ]
    result = MetaTestResult(rows=rows, summary=[], traces=traces)
    error = Criterion("tracking error", "trace_mean", "reward_forward", 0.5, "lower", scale=-1.0)
    last = Criterion("last", "trace_last", "reward_forward", 0.5, "lower", scale=-1.0)
    merged = Criterion("merge rate", "row_mean", "merged", 0.9, "higher")
    assert criterion_value(result, error) == pytest.approx(0.3)  # mean of 0.2 and 0.4, k = 0 left out
    assert criterion_value(result, last) == pytest.approx(0.45)
    assert criterion_value(result, merged) == pytest.approx(0.5)
    outcome = evaluate_competence(result, (error, merged))
    assert [c["passed"] for c in outcome["criteria"]] == [True, False] and outcome["passed"] is False


def test_curve_table_and_figure_say_where_a_run_became_competent(tmp_path: Path) -> None:
    """The report's curve row: last point, first competent env step (all criteria passed), each criterion's last and best."""
    from pearl_paper.reproduce.curve import curve_table
    from pearl_paper.reproduce.figures import plot_curves

    experiment = get_experiment("pearl-reference")

    def point(steps: int, error: float, falls: float) -> dict[str, float]:
        competent = float(error <= 0.3 and falls <= 0.1)
        return dict(env_steps=steps, reference_return=steps / 1000, k0_return=-1.0, k0_violation=0.5, competent=competent,
                    criterion_0=error, criterion_1=falls)  # fmt: skip

    curves = {
        0: [point(20_000, 1.0, 0.5), point(40_000, 0.25, 0.05), point(60_000, 0.35, 0.0)],  # competent at 40k, then not
        1: [point(20_000, 0.9, 0.2), point(40_000, 0.5, 0.0), point(60_000, 0.4, 0.0)],
    }
    group = {"pearl": {seed: {"family": "walker2d-vel-long", "curve": rows} for seed, rows in curves.items()}}
    header, _, first, second = curve_table(experiment, group)
    assert "first competent at" in header
    assert first == "| PEARL | 0 | 60000 | 60.0 | -1.0 | 50.0 | 40000 | 0.35 (0.25; bar <= 0.3); 0 (0; bar <= 0.1) |"
    assert "| not competent | 0.4 (0.4; bar <= 0.3); 0 (0; bar <= 0.1) |" in second
    assert plot_curves(experiment, group, tmp_path / "curves.png") and (tmp_path / "curves.png").is_file()
    assert not plot_curves(experiment, {"pearl": {0: {"family": "walker2d-vel-long", "curve": None}}}, tmp_path / "no.png")
    assert not any(line.startswith("Published") for line in curve_table(experiment, group))  # none for Walker
    cheetah = {"pearl": {0: {"family": "cheetah-vel", "curve": curves[0]}}}
    lines = curve_table(experiment, cheetah)
    assert lines[2].startswith("| PEARL | 0 | 60000 | 60.0 | -1.0 | n/a | 40000 |")  # the cheetah cannot violate
    assert lines[-2] == "" and lines[-1].startswith("Published: -44 at 780,000 env steps, an independent PyTorch reimpl")
    assert plot_curves(experiment, cheetah, tmp_path / "cheetah.png")


def test_curve_figure_panels_and_env_step_ticks() -> None:
    """The cheetah never falls: no violation panel; every figure shows the prior policy's return; ticks read 200k, 1.5M."""
    from pearl_paper.reproduce.figures import curve_panels, env_steps_label

    experiment = get_experiment("pearl-reference")
    walker, cheetah = experiment.family("walker2d-vel-ref"), experiment.family("cheetah-vel")
    checked = list(enumerate(walker.competence))
    assert [p[0] for p in curve_panels(walker, checked)] == [
        "reference_return", "k0_return", "k0_violation", "criterion_0", "criterion_1"
    ]  # fmt: skip
    assert [p[0] for p in curve_panels(cheetah, [(0, cheetah.competence[0])])] == [
        "reference_return", "k0_return", "criterion_0"
    ]  # fmt: skip
    assert curve_panels(walker, checked)[3][3] == walker.competence[0].threshold == 0.3
    assert [env_steps_label(x) for x in (0, 500, 20_000, 200_000, 1_000_000, 1_500_000)] == [
        "0", "500", "20k", "200k", "1M", "1.5M"
    ]  # fmt: skip


def test_the_report_draws_runs_in_progress_and_leaves_out_folders_that_are_not(tmp_path: Path) -> None:
    """Part-way runs (checkpoint + curve.csv, no result.json) get a section; stray or unreadable folders do not crash it;
    the part-way figure of a run no longer in progress is removed."""
    from pearl_paper.reproduce.cells import load_partway_curves
    from pearl_paper.reproduce.checkpoint import RunCheckpoint
    from pearl_paper.reproduce.curve import write_curve
    from pearl_paper.reproduce.report import build_report

    def partway(relative: str, steps: int, state: str | None = None) -> None:
        folder = tmp_path / relative
        (folder / "checkpoint").mkdir(parents=True)
        (folder / "checkpoint" / "model.zip").write_bytes(b"")
        rows = [dict(env_steps=float(s), reference_return=-s / 1000, k0_return=-1.0, k0_violation=0.0, competent=0.0,
                     criterion_0=1.0) for s in range(200_000, steps + 1, 20_000)]  # fmt: skip
        write_curve(folder / "curve.csv", rows)
        if state is not None:
            (folder / "checkpoint" / "state.json").write_text(state)
        else:
            state_fields = {"identity": {"budget_preset": "cpu"}, "phase": "train", "num_timesteps": steps,
                            "files": {"model": "model.zip"}, "spent": {"cpu_s": 1.0}, "phases": {}}  # fmt: skip
            RunCheckpoint(folder).write_state(state_fields)

    partway("pearl-reference/cheetah-vel/pearl/seed0", 260_000)
    partway("pearl-reference/cheetah-vel/pearl/seed1", 300_000)  # seeds part-way at different steps
    partway("pearl-reference/cheetah-vel/pearl/seed2", 240_000, state="{not json")  # unreadable: left out
    partway("pearl-reference/cheetah-vel/pearl/seed4", 240_000)  # not a declared seed of pearl-reference
    partway("pearl-reference/cheetah-vel/pearl/seed0-old", 240_000)  # not a run folder
    partway("pearl-reference/walker2d-vel/pearl/seed0", 240_000)  # a family pearl-reference does not declare
    partway("no-such-experiment/cheetah-vel/pearl/seed0", 240_000)
    groups = load_partway_curves(tmp_path)
    assert {key: {v: sorted(runs) for v, runs in group.items()} for key, group in groups.items()} == {
        ("pearl-reference", "cpu", "cheetah-vel"): {"pearl": [0, 1]}
    }
    assert groups[("pearl-reference", "cpu", "cheetah-vel")]["pearl"][1]["num_timesteps"] == 300_000
    (tmp_path / "figures").mkdir()
    stale = tmp_path / "figures" / "reproduce_oracle_walker2d-vel-long_cpu_curves_partway.png"  # a run since finished
    stale.write_bytes(b"")
    report = str(build_report(tmp_path, tmp_path / "figures", "figures"))
    assert not stale.exists()  # no page links it any more
    assert "No complete run found." in report and "cheetah-vel, runs in progress (budget `cpu`)" in report
    assert "| PEARL | 0 | 260000 | -260.0 |" in report and "| PEARL | 1 | 300000 | -300.0 |" in report
    assert "Published: -44 at 780,000 env steps" in report
    assert (tmp_path / "figures" / "reproduce_pearl-reference_cheetah-vel_cpu_curves_partway.png").is_file()


def test_the_merge_tables_at_the_reference_entropy_share_the_runs_of_one_model() -> None:
    """merge-table1..3: the tables' merge variants plus fixed entropy 1 / reward scale 5; one run folder per model."""
    from pearl_paper.experiments.merge_fixed_entropy import at_reference_entropy, merge_at_reference_entropy
    from pearl_paper.experiments.table1 import TABLE1
    from pearl_paper.experiments.table3 import TABLE3
    from pearl_paper.reproduce.scheduler import plan_runs

    table1, table3 = get_experiment("merge-table1"), get_experiment("merge-table3")
    for experiment in (table1, get_experiment("merge-table2"), table3):
        assert experiment.eval_seed == get_experiment("merge-premise").eval_seed
        assert [family.name for family in experiment.families] == ["highway-merge"]
        for variant in experiment.variants:
            assert variant.overrides["ent_coef"] == 1.0 and variant.overrides["reward_scale"] == 5.0
        assert all(cell.family == "highway-merge" for cell in experiment.paper)
        names = {variant.name for variant in experiment.variants}
        assert all(claim.variant in names and claim.reference in names for claim in experiment.claims)
    # Table I's paper row moves with its variant: PEARL+'s 0.04% crash rate at k = 0
    cell = table1.paper_value("highway-merge", "pearlplus-fixed-entropy", "violation", 0, 5)
    assert cell is not None and cell.value == pytest.approx(0.0004)
    # PEARL's runs are merge-premise's (seeds 2-3 too); alpha 0.1 of Table III is Table I's PEARL+
    runs = plan_runs(table3, "cpu", [0], ["highway-merge"], ["pearlplus-fixed-entropy", "alpha-0-fixed-entropy"])
    assert [(run.experiment, run.variant) for run in runs] == [
        ("merge-table1", "pearlplus-fixed-entropy"),
        ("merge-table3", "alpha-0-fixed-entropy"),
    ]
    runs = plan_runs(table1, "cpu", [3], ["highway-merge"], ["pearl-fixed-entropy"])
    assert [(run.experiment, run.variant, run.seed) for run in runs] == [("merge-premise", "pearl-fixed-entropy", 3)]
    assert at_reference_entropy(TABLE1.variant("pearl")).overrides == {"ent_coef": 1.0, "reward_scale": 5.0}
    with pytest.raises(ValueError, match="alpha-1 is not the model of pearlplus-fixed-entropy"):
        merge_at_reference_entropy(TABLE3, "x", ("alpha-1",), (0,), {}, same_as={"alpha-1": table1.variants[1]})


def test_a_group_holds_the_seeds_its_experiment_declares(tmp_path: Path) -> None:
    """A shared variant's owner may hold more seeds (run for another experiment): each report shows its own seeds."""
    import json

    from pearl_paper.reproduce.cells import load_groups
    from pearl_paper.reproduce.layout import RunKey, run_dir

    def write(experiment: str, variant: str, seed: int) -> None:
        folder = run_dir(tmp_path, RunKey(experiment, "highway-merge", variant, seed))
        folder.mkdir(parents=True)
        result = {key: None for key in RESULT_KEYS}
        result.update(experiment=experiment, family="highway-merge", variant=variant, seed=seed, budget_preset="cpu")
        result["meta_test"] = {"summary": [{"k": 0, "n": 1, "return_mean": -1.0, "violation_rate": 0.0}]}
        (folder / "result.json").write_text(json.dumps(result))

    for seed in (0, 1, 2, 3):  # merge-premise declares seeds 0-1; merge-table1 runs 2-3 of its PEARL into its folder
        write("merge-premise", "pearl-fixed-entropy", seed)
    write("merge-table1", "pearlplus-fixed-entropy", 0)
    write("merge-table3", "alpha-0.01-fixed-entropy", 5)  # a seed merge-table3 does not declare for alpha 0.01 ...
    write("merge-table3", "alpha-0-fixed-entropy", 5)  # ... but does for alpha 0 (variant_seeds: Table I's 10 seeds)
    groups = load_groups(tmp_path)
    assert sorted(groups[("merge-premise", "cpu", "highway-merge")]["pearl-fixed-entropy"]) == [0, 1]
    assert sorted(groups[("merge-table1", "cpu", "highway-merge")]["pearl-fixed-entropy"]) == [0, 1, 2, 3]
    # merge-table3's alpha-0.01 run (seed 5) is left out; alpha 0's seed 5 and the PEARL+ run shared with merge-table1 stay
    table3 = groups[("merge-table3", "cpu", "highway-merge")]
    assert sorted(table3) == ["alpha-0-fixed-entropy", "pearlplus-fixed-entropy"]
    assert list(table3["pearlplus-fixed-entropy"]) == [0] and list(table3["alpha-0-fixed-entropy"]) == [5]


def test_a_variant_may_declare_its_own_seeds() -> None:
    """Table I takes Table III's alpha 0 and 0.1 rows and Table II's 300-node row (beside PEARL) to Table I's 10
    seeds: a run without --seeds plans each variant's declared seeds, --seeds still names them for every variant."""
    from pearl_paper.reproduce.scheduler import plan_runs, undeclared_seeds

    table2, table3 = get_experiment("merge-table2"), get_experiment("merge-table3")
    assert table3.seeds_of("alpha-0-fixed-entropy") == tuple(range(10)) == table3.seeds_of("pearlplus-fixed-entropy")
    assert table3.seeds_of("alpha-1-fixed-entropy") == (0, 1, 2, 3)
    assert all(table2.seeds_of(variant.name) == tuple(range(10)) for variant in table2.variants)  # Table II: every row
    runs = plan_runs(table3, "cpu", None, None, ["alpha-0-fixed-entropy", "alpha-5-fixed-entropy"])
    assert [(run.variant, run.seed) for run in runs] == [("alpha-0-fixed-entropy", s) for s in range(10)] + [
        ("alpha-5-fixed-entropy", s) for s in range(4)
    ]
    runs = plan_runs(table3, "cpu", [7], None, ["alpha-0-fixed-entropy", "alpha-5-fixed-entropy"])
    assert [(run.variant, run.seed) for run in runs] == [("alpha-0-fixed-entropy", 7), ("alpha-5-fixed-entropy", 7)]
    assert undeclared_seeds(table3, runs) == {("highway-merge", "alpha-5-fixed-entropy"): [7]}  # alpha 5: 0-3 only
    assert undeclared_seeds(table3, plan_runs(table3, "cpu", None, None, None)) == {}
    with pytest.raises(ValueError, match="variant_seeds names unknown variants"):
        dataclasses.replace(table3, variant_seeds={"alpha-7": (0,)})
    with pytest.raises(ValueError, match="eval_seed 10001 must differ"):
        dataclasses.replace(table3, variant_seeds={"alpha-0-fixed-entropy": (0, 10001)})
    for bad in ((), (1, 1), (-1, 2)):  # nothing to run, one run twice, a folder the report's seed pattern skips
        with pytest.raises(ValueError, match="must be distinct integers >= 0, at least one"):
            dataclasses.replace(table3, variant_seeds={"alpha-0-fixed-entropy": bad})


def test_a_family_may_declare_its_own_seeds() -> None:
    """The oracle's Ant3D-vel candidates and its calibration are declared at one seed, the families a meta-learner is
    judged on at three: a run without --seeds plans each family's seeds, --seeds beyond them is noted as undeclared,
    and a bad family_seeds entry is refused like a bad variant_seeds one."""
    from pearl_paper.reproduce.scheduler import plan_runs, undeclared_seeds

    oracle = get_experiment("oracle")
    assert oracle.seeds_of("oracle", "walker2d-vel-long") == (0, 1, 2) == oracle.seeds_of("oracle")
    assert oracle.seeds_of("oracle", "ant3d-vel-fwd-spread-2m") == (0,)
    runs = plan_runs(oracle, "cpu", None, ["walker2d-vel-long", "ant3d-vel-run"])
    assert [(run.family, run.seed) for run in runs] == [("walker2d-vel-long", s) for s in range(3)] + [("ant3d-vel-run", 0)]
    runs = plan_runs(oracle, "cpu", [0, 1], ["walker2d-vel-long", "ant3d-vel-run"])
    assert undeclared_seeds(oracle, runs) == {("ant3d-vel-run", "oracle"): [1]}
    with pytest.raises(ValueError, match="family_seeds names unknown families"):
        dataclasses.replace(oracle, family_seeds={"ant3d-vel-nope": (0,)})
    with pytest.raises(ValueError, match="must be distinct integers >= 0, at least one"):
        dataclasses.replace(oracle, family_seeds={"ant3d-vel-run": ()})
    with pytest.raises(ValueError, match="must differ from the model seeds"):
        dataclasses.replace(oracle, family_seeds={"ant3d-vel-run": (oracle.eval_seed,)})


def test_remeasure_repeats_the_runs_own_meta_test_and_adds_draws(results: Path, tmp_path: Path) -> None:
    """`reproduce remeasure` (Table I's larger meta-test): on the run's own design it reproduces result.json's
    numbers from model.zip alone; on a larger one the k = 0 row rests on every prior draw and the adapted pass's k = 0
    rows equal the prior pass's (common random numbers); a run with a record is skipped unless forced."""
    import json
    import shutil

    from pearl_paper.experiments.table1_rules import RemeasureConfig
    from pearl_paper.reproduce.remeasure import remeasure_experiments
    from sb3_pearl.evaluation.statistics import summarize

    folder = tmp_path / "safe-point" / "safe-point" / "alpha-0.1" / "seed0"
    shutil.copytree(run_folder(results, "alpha-0.1"), folder)
    result = json.loads((folder / "result.json").read_text())
    settings = result["budget"]["meta_test"]
    same = RemeasureConfig(settings["n_tasks"], settings["n_repeats"], settings["n_repeats"], settings["n_adapt"], "same.json")
    written = remeasure_experiments(tmp_path, ["safe-point"], same, seeds=[0], echo=lambda _: None)
    assert written == [folder / "same.json"]  # alpha-0's folder has no finished run here: nothing else
    record = json.loads((folder / "same.json").read_text())
    assert record["summary"][0] == result["meta_test"]["summary"][0]
    assert [e["return_mean"] for e in record["summary"][1:]] == [e["return_mean"] for e in result["meta_test"]["summary"][1:]]
    assert record["crn_check"]["matched"] and record["crn_check"]["compared"] == settings["n_tasks"] * settings["n_repeats"]

    larger = RemeasureConfig(settings["n_tasks"] + 2, prior_repeats=3, adapted_repeats=1, n_adapt=2, file_name="l.json")
    assert remeasure_experiments(tmp_path, ["safe-point"], larger, seeds=[0], echo=lambda _: None) == [folder / "l.json"]
    record = json.loads((folder / "l.json").read_text())
    prior_rows = record["prior"]["rows"]
    assert len(prior_rows) == (settings["n_tasks"] + 2) * 3 and {row["k"] for row in prior_rows} == {0}
    assert [e["k"] for e in record["summary"]] == [0, 1, 2]
    assert record["summary"][0]["violation_rate"] == summarize(prior_rows)[0]["violation_rate"]
    assert record["crn_check"] == {"compared": settings["n_tasks"] + 2, "mismatched": 0, "matched": True}
    assert (record["experiment"], record["variant"], record["seed"]) == ("safe-point", "alpha-0.1", 0)
    before = (folder / "l.json").stat().st_mtime_ns
    assert remeasure_experiments(tmp_path, ["safe-point"], larger, seeds=[0], echo=lambda _: None) == []
    assert (folder / "l.json").stat().st_mtime_ns == before
    assert remeasure_experiments(tmp_path, ["safe-point"], larger, seeds=[0], force=True, echo=lambda _: None)
    bad = run_in_process(main, "remeasure", "--results-dir", str(tmp_path / "nowhere"), check=False)
    assert bad.returncode == 2 and "does not exist" in bad.stderr


# ----------------------------------------------------------------------------------------------
# The report's inputs and outputs: atomic write, re-measured records that may not be the run's
# ----------------------------------------------------------------------------------------------
COMMITTED_RUN = ROOT / "results" / "safe-point" / "safe-point" / "alpha-0.1" / "seed0"
REMEASURED_RUN = ROOT / "results" / "merge-table1" / "highway-merge" / "pearlplus-fixed-entropy"


def _copy_run(source: Path, results_dir: Path, names: tuple[str, ...] = ("result.json",)) -> Path:
    """A committed run's files (``names``) copied into the same layout under ``results_dir``: its run folder."""
    import shutil

    folder = results_dir.joinpath(*source.parts[-4:])
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        shutil.copy(source / name, folder / name)
    return folder


def test_report_writes_its_file_atomically(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A write of docs/results.md that fails half-way (here an unencodable character) leaves the previous file whole,
    and no temporary file beside it."""
    from pearl_paper.reproduce import report

    _copy_run(COMMITTED_RUN, tmp_path / "results")
    out = tmp_path / "docs" / "results.md"
    out.parent.mkdir()
    out.write_text("# Results\n\nhand-written text\n")
    monkeypatch.setattr(report, "build_report", lambda *args: report.Report("a table\n\ud800 cut here\n", {}))
    with pytest.raises(UnicodeEncodeError):
        report.write_report(tmp_path / "results", out)
    assert out.read_text() == "# Results\n\nhand-written text\n"
    assert not [path.name for path in out.parent.iterdir() if ".tmp" in path.name]
    monkeypatch.setattr(report, "build_report", lambda *args: report.Report("a table", {}))
    report.write_report(tmp_path / "results", out)
    assert "hand-written text" in out.read_text() and f"{BEGIN}\na table\n{END}" in out.read_text()


def test_a_remeasured_record_of_another_run_is_skipped_with_a_warning(tmp_path: Path) -> None:
    """read_remeasured: the run's own record is read; a record copied from another seed's folder (or one whose eval seed
    is not the run's), an empty or an unparsable one is skipped with a warning naming the file, never read as the run's."""
    import json
    import shutil

    from pearl_paper.reproduce.remeasure import read_remeasured

    seed0 = _copy_run(REMEASURED_RUN / "seed0", tmp_path, ("result.json", "meta_test_large.json"))
    seed1 = _copy_run(REMEASURED_RUN / "seed1", tmp_path, ("result.json",))
    record = read_remeasured(seed0)
    assert record is not None and record["seed"] == 0 and record["summary"][0]["k"] == 0
    assert read_remeasured(seed1) is None  # none there: no warning
    shutil.copy(seed0 / "meta_test_large.json", seed1 / "meta_test_large.json")  # seed 0's record in seed 1's folder
    with pytest.warns(
        UserWarning, match=r"seed1/meta_test_large.json .*another run: seed 'seed0' \(its folder says 'seed1'\)"
    ):
        assert read_remeasured(seed1) is None
    result = json.loads((seed0 / "result.json").read_text())
    with pytest.warns(UserWarning, match=r"was measured with eval seed \d+, the run's result.json says 7"):
        assert read_remeasured(seed0, {**result, "eval_seed": 7}) is None
    for text, problem in (("", "is empty"), ("{", "is not valid JSON")):
        (seed1 / "meta_test_large.json").write_text(text)
        with pytest.warns(UserWarning, match=rf"seed1/meta_test_large.json {problem}"):
            assert read_remeasured(seed1) is None


def test_remeasure_measures_an_empty_or_unparsable_record_again(tmp_path: Path) -> None:
    """`reproduce remeasure` does not take a zero-byte (or cut) record for a measured run: it measures it again and
    says so."""
    import json

    from pearl_paper.experiments.table1_rules import RemeasureConfig
    from pearl_paper.reproduce.remeasure import remeasure_run

    folder = _copy_run(COMMITTED_RUN, tmp_path, ("result.json", "model.zip"))
    tiny = RemeasureConfig(n_tasks=1, prior_repeats=1, adapted_repeats=1, n_adapt=1, file_name="tiny.json")
    for text, problem in (("", "is empty"), ('{"summary": [', "is not valid JSON")):
        (folder / "tiny.json").write_text(text)
        said: list[str] = []
        assert remeasure_run(folder, tiny, echo=said.append) == folder / "tiny.json"
        assert json.loads((folder / "tiny.json").read_text())["summary"][0]["k"] == 0
        assert any(problem in line and "measuring it again" in line for line in said), said
    said = []
    assert remeasure_run(folder, tiny, echo=said.append) is None and not said  # a complete record: left as it is


def test_reproduce_seeds_beyond_numpys_bound_are_refused(tmp_path: Path) -> None:
    from pearl_paper.reproduce.cli import main
    from pearl_paper.reproduce.layout import parse_seeds

    assert parse_seeds("4294967295") == [4294967295]
    for text in ("4294967296", "0,4294967290-4294967296"):
        with pytest.raises(ValueError, match=r"--seeds: seeds must be integers in \[0, 4294967295\], got 4294967296"):
            parse_seeds(text)
    argv = ["status", "safe-point", "--seeds", "4294967296", "--results-dir", str(tmp_path)]
    proc = run_in_process(main, *argv, check=False)
    assert proc.returncode == 2 and proc.stderr.strip().splitlines() == [
        "error: --seeds: seeds must be integers in [0, 4294967295], got 4294967296 (in '4294967296')"
    ]


# ----------------------------------------------------------------------------------------------
# Reports: each result owns its place (no copy, no result in another run's folder)
# ----------------------------------------------------------------------------------------------
def _write_result(results: Path, seed: int, folder_seed: int | None = None, experiment_folder: str = "safe-point") -> Path:
    path = results / experiment_folder / "safe-point" / "alpha-0" / f"seed{seed if folder_seed is None else folder_seed}"
    summary = [{"k": 0, "n": 1, "return_mean": -1.0 - seed, "violation_rate": 0.0}]
    result = {"experiment": "safe-point", "family": "safe-point", "variant": "alpha-0", "seed": seed, "budget_preset": "smoke"}
    write_json_atomic(path / "result.json", {**result, "meta_test": {"summary": summary}})
    return path / "result.json"


def test_report_refuses_a_copy_of_a_result_naming_both_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    results, page = tmp_path / "results", tmp_path / "results.md"
    real = _write_result(results, 0)
    assert set(load_groups(results)[("safe-point", "smoke", "safe-point")]["alpha-0"]) == {0}
    backup = _write_result(results, 0, experiment_folder="safe-point.bak")  # a backup copy beside the real folder
    assert main(["report", "--results-dir", str(results), "--out", str(page)]) == 2
    assert (
        f"error: {real} and {backup} both hold the result of safe-point smoke safe-point alpha-0 seed0"
        in capsys.readouterr().err
    )
    assert not page.exists()


def test_report_and_status_refuse_a_result_in_another_runs_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    results = tmp_path / "results"
    moved = _write_result(results, 0, folder_seed=1)  # seed1/result.json says seed 0 (beside seed0's: both files named)
    with pytest.raises(
        ValueError, match=rf"{moved} holds the result of another run: seed 'seed0' \(its folder says 'seed1'\)"
    ):
        load_groups(results)
    assert main(["status", "safe-point", "--results-dir", str(results), "--seeds", "0-1", "--budget", "smoke"]) == 2
    assert f"error: {moved} holds the result of another run" in capsys.readouterr().err


def test_report_out_on_a_folder_and_status_of_a_missing_folder_are_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    results = tmp_path / "results"
    _write_result(results, 0)
    assert main(["report", "--results-dir", str(results), "--out", str(tmp_path)]) == 2
    assert (
        capsys.readouterr().err
        == f"error: --out {tmp_path} is a folder: give the markdown file to write, e.g. {tmp_path / 'results.md'}\n"
    )
    assert not (tmp_path / "figures").exists()  # nothing written beside it
    assert main(["status", "safe-point", "--results-dir", str(tmp_path / "nowhere")]) == 2
    assert "error: --results-dir" in capsys.readouterr().err


def test_results_dir_that_root_cannot_write_is_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    locked = tmp_path / "mount"
    locked.mkdir()
    _read_only_for_root(monkeypatch, locked)
    argv = ["run", "safe-point", "--budget", "smoke", "--seeds", "0", "--results-dir", str(locked / "results")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.strip().splitlines() == [
        f"error: --results-dir {locked / 'results'}: {locked} is not writable (Read-only file system)"
    ]
    assert list(locked.iterdir()) == []
