"""The README's Python examples run as written."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


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
