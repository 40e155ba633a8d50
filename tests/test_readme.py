"""The documented commands run as written (a command that a page shows and that fails is a user's first failure): the
README's Python examples, every command of the README, docs/README.md, docs/cli.md and the algorithm pages at a smoke
budget, the algorithm pages' examples and parameter lists, and ``make demo`` with its own defaults.

**The convention for command blocks** (```` ```bash ```` blocks of the pages in :data:`COMMAND_PAGES`): every command
runs in the fast suite, in the page's order in one temporary folder per page (so an ``enjoy.py`` line replays the
``train.py`` line above it), shrunk to a smoke budget by :func:`smoke_argv`. A block that cannot run in CI (days of
training, a Ray cluster, a display, files it would overwrite) is preceded by the HTML comment
``<!-- commands: parse-only (the reason) -->``: its commands are only parsed against their command line (train.py's
full parser, rl_zoo3's included; enjoy.py's; the reproduction harness's, ...). ``make X`` lines must name a Makefile
target; ``make demo`` runs in :func:`test_make_demo_defaults_are_runnable` and :func:`test_demo_at_a_small_size`.
"""

from __future__ import annotations

import ast
import itertools
import os
import re
import shlex
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, NamedTuple
from unittest import mock

import pytest

from pearl_paper import demo
from tests.conftest import TINY_ZOO_PARAMS

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
ALGORITHM_PAGES = ("docs/pearl.md", "docs/finetune.md", "docs/maml.md")
COMMAND_PAGES = ("README.md", "docs/README.md", "docs/cli.md", *ALGORITHM_PAGES)
ALGORITHM_SECTIONS = ["Example", "Results", "How to replicate", "Parameters", "Notes"]
PARSE_ONLY = re.compile(r"<!--\s*commands:\s*parse-only\b")
SMOKE_STEPS = "300"
SMOKE_PARAMS = [*TINY_ZOO_PARAMS[:-1], "meta_test:dict(n_adapt=1, n_tasks=2)"]


@pytest.mark.parametrize("shrink", [True, pytest.param(False, marks=pytest.mark.slow)])
def test_readme_python_examples_run(shrink: bool, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The examples as written; in the fast suite with one change, the training budget shrunk to 300 env steps (the
    API is checked there, ~3 minutes become seconds); the slow suite runs them exactly as written."""
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert len(blocks) >= 2, "README lost its Python examples"
    assert sum(len(re.findall(r"model\.learn\(\d+\)", block)) for block in blocks) == 1, "README's learn() call changed"
    if shrink:
        blocks = [re.sub(r"model\.learn\(\d+\)", "model.learn(300)", block) for block in blocks]
    cwd = os.getcwd()
    os.chdir(tmp_path)  # the example saves a model in the working directory
    try:
        exec(compile("\n".join(blocks), str(README), "exec"), {"__name__": "readme"})
    finally:
        os.chdir(cwd)
    assert (tmp_path / "pearlplus_safepoint.zip").exists()
    printed = capsys.readouterr().out
    assert [line.split()[0] for line in printed.splitlines() if line.startswith("k=")] == ["k=0", "k=1", "k=2"]


# ----------------------------------------------------------------------------------------------
# The algorithm pages: sb3-contrib's shape, their examples, their parameter lists
# ----------------------------------------------------------------------------------------------
def _section(text: str, title: str) -> str:
    """The text of a page's ``## title`` section."""
    return text.split(f"\n## {title}\n", 1)[1].split("\n## ", 1)[0]


@pytest.mark.parametrize("page", ALGORITHM_PAGES)
def test_algorithm_page_examples_run(page: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each algorithm page opens in sb3-contrib's order (what it is with its arXiv paper, Example, Results, How to
    replicate, Parameters, then the notes) and its Example runs, the training budget shrunk to 300 env steps."""
    text = (ROOT / page).read_text()
    titles = re.findall(r"^## (.+)$", text, flags=re.M)
    assert titles[: len(ALGORITHM_SECTIONS)] == ALGORITHM_SECTIONS, titles
    assert re.search(r"arXiv:\d{4}\.\d{5}", text.split("\n## ", 1)[0]), "the opening paragraph names no arXiv paper"
    blocks = re.findall(r"```python\n(.*?)```", _section(text, "Example"), flags=re.S)
    assert len(blocks) == 1 and len(re.findall(r"model\.learn\([\d_]+\)", blocks[0])) == 1, page
    monkeypatch.chdir(tmp_path)  # the examples save models in the working directory
    exec(compile(re.sub(r"model\.learn\([\d_]+\)", "model.learn(300)", blocks[0]), page, "exec"), {"__name__": "page"})


@pytest.mark.parametrize("page", ALGORITHM_PAGES)
def test_algorithm_page_parameters_are_the_constructors(page: str) -> None:
    """The Parameters section's ``Class(...)`` signatures name only real parameters, with their real defaults."""
    import sb3_pearl
    from sb3_pearl.registry import constructor_parameters

    section = _section((ROOT / page).read_text(), "Parameters")
    signatures = re.findall(r"`(PEARL|PEARLPlus|FineTune|MAML)\((.*?)\)`", section, flags=re.S)
    assert signatures, f"{page}: no constructor signature in its Parameters section"
    for name, arguments in signatures:
        parameters = constructor_parameters(getattr(sb3_pearl, name))  # inspect.signature: a parent's forwarded too
        documented = re.findall(r"(\w+)=([^,]+)", arguments.replace("\n", " "))
        assert documented, name
        for key, value in documented:
            assert key in parameters, f"{page}: {name} has no parameter {key}"
            assert ast.literal_eval(value.strip()) == parameters[key].default, f"{page}: {name}({key}=...)"


# ----------------------------------------------------------------------------------------------
# Every documented command
# ----------------------------------------------------------------------------------------------
class Command(NamedTuple):
    """One documented command line: where it is, its tool, its arguments, and whether it may run in the tests."""

    page: str
    line: int
    tool: str
    argv: list[str]
    run: bool


TOOLS = {
    "python train.py": "train",
    "python -m sb3_pearl.train": "train",
    "sb3-pearl-train": "train",
    "python enjoy.py": "enjoy",
    "python -m sb3_pearl.enjoy": "enjoy",
    "sb3-pearl-enjoy": "enjoy",
    "python -m sb3_pearl.plots": "plots",
    "python -m pearl_paper.reproduce": "reproduce",
    "python -m sb3_pearl.diagnose": "diagnose",
    "python -m pearl_paper.demo": "demo",
    "make": "make",
}


def page_commands(page: str) -> Iterator[Command]:
    """The commands of a page's bash blocks, with their parse-only marks (module docstring)."""
    lines = (ROOT / page).read_text().splitlines()
    index = 0
    while index < len(lines):
        if lines[index].strip() != "```bash":
            index += 1
            continue
        previous = next((line for line in reversed(lines[:index]) if line.strip()), "")
        run = not PARSE_ONLY.search(previous)
        index += 1
        while index < len(lines) and lines[index].strip() != "```":
            words = shlex.split(lines[index], comments=True)
            if words:
                text = " ".join(words)
                prefix = next((p for p in sorted(TOOLS, key=len, reverse=True) if text == p or text.startswith(p + " ")), None)
                assert prefix is not None, f"{page}:{index + 1}: no handler for {text!r} in tests/test_readme.py"
                yield Command(page, index + 1, TOOLS[prefix], words[len(prefix.split()) :], run)
            index += 1
        index += 1


def _set(argv: list[str], flag: str, value: str) -> list[str]:
    """``argv`` with ``flag value`` (replacing the flag's value where it is given)."""
    if flag in argv:
        argv = list(argv)
        argv[argv.index(flag) + 1] = value
        return argv
    return [*argv, flag, value]


def smoke_argv(command: Command, workdir: Path) -> list[str]:
    """
    The command at a smoke budget: train.py with 300 env steps, the tests' tiny networks and a two-task meta-test
    (the command's own ``-params`` win); enjoy.py on one task and one posterior trajectory, ``--run`` folders read
    from the checkout's ``results/`` and never written to.
    """
    argv = list(command.argv)
    if command.tool == "train":
        params: list[str] = []
        if "-params" in argv:
            start = argv.index("-params") + 1
            end = next((i for i in range(start, len(argv)) if argv[i].startswith("-") and ":" not in argv[i]), len(argv))
            params, argv = argv[start:end], argv[: start - 1] + argv[end:]
        evaluates = "--eval-freq" in argv and argv[argv.index("--eval-freq") + 1] != "-1"
        argv = _set(_set(argv, "-n", SMOKE_STEPS), "--num-threads", "1")
        argv = _set(argv, "--eval-freq", "200" if evaluates else "-1")  # an evaluating command keeps best_model.zip
        return [*argv, "-params", *SMOKE_PARAMS, *params]
    if command.tool == "enjoy":
        argv = _set(_set(_set(argv, "--n-tasks", "1"), "--n-adapt", "1"), "--num-threads", "1")
        if "--run" in argv:
            run = argv[argv.index("--run") + 1]
            argv = _set(argv, "--run", str(ROOT / run))
            if "--plot" in argv:  # its default is the run folder: not under results/
                argv.insert(argv.index("--plot") + 1, str(workdir / "enjoy.png"))
        return argv
    return argv


class _Parsed(Exception):
    """Raised in place of building the experiment: train.py's command line was fully parsed."""


def parse_train(argv: list[str]) -> None:
    """Parse a train.py command line with train.py's own parser (rl_zoo3's, the project's flags and checks)."""
    from sb3_pearl.zoo import experiment_manager

    def stop(*args: Any, **kwargs: Any) -> None:
        raise _Parsed

    with mock.patch.object(experiment_manager, "MetaExperimentManager", stop), pytest.raises(_Parsed):
        experiment_manager.train(argv)


def parse(command: Command) -> None:
    """Parse a command against its command line without running it."""
    where = f"{command.page}:{command.line}"
    if command.tool == "train":
        parse_train(command.argv)
    elif command.tool == "enjoy":
        from sb3_pearl.zoo import enjoy_parser, register_algos

        register_algos()  # --algo's choices: rl_zoo3's ALGOS with the project's (train.py's parse registers them too)
        enjoy_parser().parse_args(command.argv)
    elif command.tool == "reproduce":
        from pearl_paper.reproduce.cli import build_parser

        build_parser().parse_args(command.argv)
    elif command.tool == "diagnose":
        from sb3_pearl.diagnose import parser

        parser().parse_args(command.argv)
    elif command.tool == "demo":
        demo.demo_parser().parse_args(command.argv)
    elif command.tool == "plots":
        assert command.argv and not command.argv[0].startswith("-"), where
    elif command.tool == "make":
        targets = re.findall(r"^([\w-]+):", (ROOT / "Makefile").read_text(), flags=re.M)
        assert command.argv and set(command.argv) <= set(targets), f"{where}: no Makefile target {command.argv}"


def run(command: Command, workdir: Path) -> None:
    """Run a command at its smoke budget in ``workdir``."""
    argv = smoke_argv(command, workdir)
    if command.tool == "train":
        from sb3_pearl.zoo import train

        train(argv)
    elif command.tool == "enjoy":
        from sb3_pearl.zoo import enjoy

        enjoy(argv)
    elif command.tool == "plots":
        from sb3_pearl.plots import main as plots_main

        plots_main(argv)
    else:  # the harness, diagnostics, make and the demo: parsed here, run by their own tests
        parse(command)


@pytest.mark.parametrize("page", COMMAND_PAGES)
def test_documented_commands_run(
    page: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    commands = list(page_commands(page))
    assert commands, f"{page} lost its commands"
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    for command in commands:
        parse(command)  # every command, also those that run: the documented line itself parses
        if command.run:
            run(command, tmp_path)


def test_the_readme_runs_its_quick_start_and_every_pretrained_model() -> None:
    """The README's enjoy.py line follows its train.py line, and every model of the pretrained table has a line."""
    commands = [command for command in page_commands("README.md") if command.run and command.tool != "make"]
    tools = [command.tool for command in commands]
    assert tools[:2] == ["train", "enjoy"] and commands[0].argv[:4] == commands[1].argv[:4]  # --algo X --env
    runs = {command.argv[command.argv.index("--run") + 1] for command in commands if "--run" in command.argv}
    table = re.findall(r"^\| `([\w./-]+)`(?:, `([\w./-]+)`)? \|", README.read_text(), flags=re.M)
    named = {name for row in table for name in row if name}
    for name in named:
        assert any(run.startswith(f"results/{name}/seed") for run in runs), f"no enjoy.py --run line for {name}"
    for run in runs:
        assert (ROOT / run / "model.zip").is_file() and (ROOT / run / "result.json").is_file(), run


def test_the_clone_weight_note_holds() -> None:
    """The README's lighter clone brings back the headline models ``make demo`` replays, and no finished run keeps its
    checkpoint in the tree (the runner deletes it once ``result.json`` is written: only unfinished runs carry one)."""
    note = README.read_text().split("**What a clone weighs.**", 1)[1].split("\n## ", 1)[0]
    added = re.findall(r"^git sparse-checkout add (.+?)\s+#", note, flags=re.M)
    assert len(added) == 1, "the note lost its sparse-checkout line"
    folders = {folder.strip("/") for folder in added[0].split()}
    assert folders == {f"results/{variant}" for variant in demo.HEADLINE.values()}
    for folder in folders:
        assert list((ROOT / folder).glob("seed*/model.zip")), folder
    for checkpoint in (ROOT / "results").rglob("checkpoint"):
        if checkpoint.is_dir():
            assert not (checkpoint.parent / "result.json").exists(), f"{checkpoint}: a finished run kept its checkpoint"


def test_the_thread_default_is_said_where_a_user_looks() -> None:
    """The README's quick start and cli.md say the thread rule of sb3_pearl.common.threads, with its numbers, and no
    documented train.py / enjoy.py command sets --num-threads (the default is the fast count, which a documented flag
    would override)."""
    from sb3_pearl.common.threads import MAX_THREADS, WIDE_LAYER

    quick_start = _section(README.read_text(), "Quick start")
    for where, text in (("README's quick start", quick_start), ("docs/cli.md", (ROOT / "docs" / "cli.md").read_text())):
        flat = " ".join(text.split())
        assert f"one torch thread for networks narrower than {WIDE_LAYER} units" in flat or (
            f"one thread for networks narrower than {WIDE_LAYER} units" in flat
        ), where
        assert f"up to {MAX_THREADS}" in flat and "OMP_NUM_THREADS" in flat, where
    for page in COMMAND_PAGES:
        for command in page_commands(page):
            if command.tool in ("train", "enjoy"):
                assert "--num-threads" not in command.argv, f"{page}:{command.line}: the default already picks the count"


# ----------------------------------------------------------------------------------------------
# make demo
# ----------------------------------------------------------------------------------------------
def test_make_demo_defaults_are_runnable() -> None:
    """``make demo`` is ``python -m pearl_paper.demo`` with no argument, and its defaults fit: the seeds it replays are
    committed (model and result), its tasks and draws are within their committed meta-test, its train.py line parses."""
    assert re.search(r"^demo: setup\n\t\$\(BIN\)/python -m pearl_paper\.demo\n", (ROOT / "Makefile").read_text(), flags=re.M)
    args = demo.demo_parser().parse_args([])
    runs = demo.headline_runs(demo.default_results_dir())
    assert set(runs) == set(demo.HEADLINE) and args.replay_seeds
    for label, seeds in runs.items():
        assert set(args.replay_seeds) <= set(seeds), f"{label}: seeds {args.replay_seeds} not all committed"
        for seed in args.replay_seeds:
            assert (seeds[seed] / "model.zip").is_file()
            committed, _ = demo.committed_meta_test(seeds[seed])
            assert len(committed.tasks) >= args.n_tasks and committed.config["n_repeats"] >= args.n_repeats
    parse_train(demo.training_argv(args))


def test_demo_at_a_small_size(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """The whole demo with its defaults but the size: one seed of each headline model on two tasks, 300 env steps."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    logs = tmp_path / "logs"
    summary = demo.main(["--replay-seeds", "0", "--n-tasks", "2", "--n-repeats", "1", "-n", SMOKE_STEPS, "-f", str(logs)])
    out = capsys.readouterr().out
    same, total = summary["matching"]
    assert total == len(demo.HEADLINE) * 2 * 1 * 6 and same == total  # 2 tasks x 1 draw x k = 0..5, as committed
    assert f"{same} of {total} replayed trajectories identical to their committed result.json rows" in out
    assert "PEARL+ - PEARL" in out and "k = 0 (prior)" in out and "Violation rate, % [95% interval]" in out
    assert [Path(path).name for path in summary["figures"]] == ["headline.png", "headline_violations.png"]
    assert all(Path(path).is_file() for path in summary["figures"])
    assert (logs / "pearlplus" / f"{demo.TRAIN_ENV_ID}_1" / "meta_test.json").is_file()
    # the README's headline verdicts (re-measured meta-test, pre-written rules), printed as docs/results.md writes them
    assert "Table I decided" in out and any(line.startswith("- **Safer prior**") for line in summary["decided"])
    assert all(line in out for line in summary["decided"])
    # the headline table is the README's: the re-measured meta-test, whose paired differences are the rules' intervals
    from pearl_paper.reproduce.table1_verdicts import decide_family

    assert "re-measured on Table I's design" in out
    decision = decide_family("highway-merge", demo.default_results_dir())
    assert decision.prior_interval is not None and decision.adapted_interval is not None
    prior, adapted = decision.prior_interval, decision.adapted_interval
    violations, returns = [line.split() for line in out.splitlines() if line.startswith("PEARL+ - PEARL")]  # the headline's
    # cells k = 0, 1, 3, 5 of 3 words each after the label's 3: k = 0 of the violation row, k = 5 of the return row
    assert " ".join(violations[3:6]) == f"{100 * prior.mean:+.1f} [{100 * prior.low:+.1f}, {100 * prior.high:+.1f}]"
    assert " ".join(returns[-3:]) == f"{adapted.mean:+.1f} [{adapted.low:+.1f}, {adapted.high:+.1f}]"
    pooled = {label: demo.pool(list(seeds.values())).summary_at(0) for label, seeds in summary["headline"].items()}
    assert {entry["n"] for entry in pooled.values()} == {1000 * len(decision.paired_seeds)}  # 100 tasks x 10 draws a seed


@pytest.mark.slow
def test_make_demo_as_is(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``python -m pearl_paper.demo`` exactly as ``make demo`` runs it: within the 5 minutes the README promises on 2 cores."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    start = time.time()
    summary = demo.main([])
    assert summary["matching"][0] == summary["matching"][1] > 0 and "training" in summary
    assert time.time() - start < 300


@pytest.mark.parametrize("family, row_start", [("highway-merge", "| Highway-Merge"), ("walker2d-vel-long", "| Walker2D-vel")])
def test_the_headline_holds_the_decided_numbers(family: str, row_start: str) -> None:
    """The README's headline (and the PEARL page's copy) holds Table I's verdict on each decided family as the rules
    compute it from the committed results: the paired k = 0 and k = 5 intervals and the verdict words."""
    from pearl_paper.reproduce.table1_verdicts import decide_family

    decision = decide_family(family, demo.default_results_dir())
    assert decision.prior_interval is not None and decision.adapted_interval is not None
    prior, adapted = decision.prior_interval, decision.adapted_interval
    prior_text = f"{100 * prior.mean:+.1f} points [{100 * prior.low:+.1f}, {100 * prior.high:+.1f}]".lstrip("+")
    adapted_text = f"{adapted.mean:+.2f} [{adapted.low:+.2f}, {adapted.high:+.2f}]".lstrip("+")
    readme = README.read_text()
    headline = readme[readme.index("<!-- headline:begin") : readme.index("<!-- headline:end")]
    row = next(line for line in headline.splitlines() if line.startswith(row_start))
    for text in (row, (ROOT / "docs" / "pearl.md").read_text()):
        assert prior_text in text and adapted_text in text and f"margin -{decision.adapted_margin:.2f}" in text
    verdict = row.rsplit("|", 2)[1]
    assert ("**safer prior**" in verdict) == (decision.prior_verdict == "safer")
    assert f"adapted as good: {decision.adapted_verdict}" in verdict or (
        decision.adapted_verdict == "as good" and "**adapted as good**" in verdict
    )


def test_the_demo_reads_the_remeasured_record_or_falls_back_for_every_run(tmp_path: Path) -> None:
    """The headline table rests on each seed's re-measured meta-test (k = 0: 100 tasks x 10 draws; k >= 1: the adapted
    pass's 2 draws), only if every run has one; a record in another seed's folder is refused."""
    import shutil

    found = {}
    for seed in (0, 1):
        folder = tmp_path / demo.HEADLINE["PEARL+"] / f"seed{seed}"
        folder.mkdir(parents=True)
        for name in ("result.json", "meta_test_large.json"):
            shutil.copy(demo.default_results_dir() / demo.HEADLINE["PEARL+"] / f"seed{seed}" / name, folder / name)
        found[seed] = folder
    result = demo.remeasured_meta_test(found[0])
    assert result is not None and result.summary_at(0)["n"] == 1000
    assert sum(row["k"] == 0 for row in result.rows) == 1000 and sum(row["k"] == 1 for row in result.rows) == 200
    assert result.config["n_repeats"] == 10 and result.config["adapted_repeats"] == 2
    tests, remeasured = demo.headline_meta_tests({"PEARL+": found})
    assert remeasured and tests["PEARL+"][1].summary_at(0)["n"] == 1000
    (found[1] / "meta_test_large.json").unlink()  # one run without its record: every run's own meta-test instead
    tests, remeasured = demo.headline_meta_tests({"PEARL+": found})
    own = demo.committed_meta_test(found[0])[0]
    assert not remeasured and tests["PEARL+"][0].summary_at(0)["n"] == own.summary_at(0)["n"] < 1000
    shutil.copy(found[0] / "meta_test_large.json", found[1] / "meta_test_large.json")  # seed 0's record as seed 1's
    with pytest.raises(ValueError, match="its folder says 'seed1'"):
        demo.remeasured_meta_test(found[1])


def test_the_headline_holds_the_fresh_seed_confirmation() -> None:
    """The README's confirmation row holds the fresh-seed verdict as the rules compute it from seeds 10-19 alone."""
    from pearl_paper.reproduce.table1_verdicts import decide_confirmation

    decision = decide_confirmation(demo.default_results_dir())
    assert decision.paired_seeds == list(range(10, 20))
    assert decision.prior_interval is not None and decision.adapted_interval is not None
    prior, adapted = decision.prior_interval, decision.adapted_interval
    readme = README.read_text()
    headline = readme[readme.index("<!-- headline:begin") : readme.index("<!-- headline:end")]
    row = next(line for line in headline.splitlines() if line.startswith("| Highway-Merge confirmed on fresh seeds"))
    assert f"{100 * prior.mean:+.1f} points [{100 * prior.low:+.1f}, {100 * prior.high:+.1f}]".lstrip("+") in row
    assert f"{adapted.mean:+.2f} [{adapted.low:+.2f}, {adapted.high:+.2f}]".lstrip("+") in row
    assert f"margin -{decision.adapted_margin:.2f}" in row
    verdict = row.rsplit("|", 2)[1]
    assert ("**safer prior**" in verdict) == (decision.prior_verdict == "safer")
    assert ("**adapted as good**" in verdict) == (decision.adapted_verdict == "as good")


@pytest.mark.parametrize(("family", "table"), [("highway-merge", "Highway-Merge"), ("walker2d-vel-long", "Walker2D-vel")])
def test_the_headline_holds_table_1s_four_columns(family: str, table: str) -> None:
    """The README's four-column table of a family holds, per column, the committed runs' own meta-test numbers as the
    report's cells compute them: the seed count, k = 0 and k = 5 failure rates with their intervals, the k = 5 return
    with its t interval over seeds (the value alone at one seed), and the paper's cells; a column without runs says
    that it is pending."""
    from pearl_paper.experiments.table1 import TABLE1
    from pearl_paper.reproduce.table1_verdicts import decide, rate_cell, return_cell

    decision = next(d for d in decide(demo.default_results_dir()) if d.family == family)
    columns = {"Fine-Tune": decision.columns["finetune"], "MAML": decision.columns["maml"]}
    columns |= {"PEARL": decision.runs[decision.variants[0]], "PEARL+": decision.runs[decision.variants[1]]}
    paper_names = {"Fine-Tune": "finetune", "MAML": "maml", "PEARL": "pearl", "PEARL+": "pearlplus"}
    paper_family = "walker2d-vel" if family.startswith("walker2d-vel") else family
    readme = README.read_text()
    headline = readme[readme.index("<!-- headline:begin") : readme.index("<!-- headline:end")]
    lines = headline.splitlines()
    first = next(i for i, line in enumerate(lines) if line.startswith(f"| {table} column (seeds) |"))
    rows = list(itertools.takewhile(lambda line: line.startswith("|"), lines[first:]))
    assert len(rows) == 2 + len(columns), table
    for label, runs in columns.items():
        paper = {c.k: c.value for c in TABLE1.paper if c.family == paper_family and c.variant == paper_names[label]}
        paper_cell = f"{100 * paper[0]:.1f} / {100 * paper[5]:.1f}"
        if not runs:
            row = next(line for line in rows if line.startswith(f"| {label} (pending) |"))
            assert [cell.strip() for cell in row.strip("|").split("|")][1:] == ["pending"] * 3 + [paper_cell], label
            continue
        row = next(line for line in rows if line.startswith(f"| {label} ({len(runs)}) |"))
        cells = [cell.strip() for cell in row.strip("|").split("|")][1:]
        assert cells == [
            rate_cell([run.own_summary[0] for run in runs.values()]),
            rate_cell([run.own_summary[5] for run in runs.values()]),
            return_cell([run.own_summary[5] for run in runs.values()]),
            paper_cell,
        ], label
