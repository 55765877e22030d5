"""The Python code of README.md and docs/python.md runs as written, from the
repository root."""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys

import pytest

from conftest import REPO


def python_blocks(path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", path.read_text(), flags=re.S)


def run_script(code: str, tmp_path) -> str:
    # The scripts' temporary directories go under pytest's, which cleans up.
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    p = subprocess.run(
        [sys.executable, "-c", code],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
        env=env,
    )
    assert p.returncode == 0, f"exit {p.returncode}\n{p.stdout}\n{p.stderr}"
    return p.stdout


def test_readme_python_quick_start(tmp_path):
    blocks = python_blocks(REPO / "README.md")
    assert len(blocks) == 1
    out = run_script(blocks[0], tmp_path)
    lines = out.splitlines()
    assert len(lines) == 12
    assert all(re.match(r"0000\d\d\.png: contact \d+ at x = -?\d+\.\d mm, F = \(", l) for l in lines)


def _docs_script(with_plot: bool) -> str:
    blocks = python_blocks(REPO / "docs" / "python.md")
    assert len(blocks) >= 3
    # The walk-through's blocks share one namespace, as in a notebook.
    return "\n".join(b for b in blocks if with_plot or "import matplotlib" not in b)


def test_docs_python_md_runs(tmp_path):
    out = run_script(_docs_script(with_plot=False), tmp_path)
    assert "test split errors:" in out
    assert len(re.findall(r"^x .* mm \(true .*Fz .* N \(true", out, flags=re.M)) == 2
    assert re.search(r"^\d+ contacts matched, \d+ missed, 0 false: location ", out, flags=re.M)


@pytest.mark.skipif(
    importlib.util.find_spec("matplotlib") is None, reason="matplotlib is not installed"
)
def test_docs_python_md_plot_runs(tmp_path):
    run_script(_docs_script(with_plot=True), tmp_path)
