"""Every notebook in notebooks/ runs top to bottom at small size, imports only jaxland's public
names, and is committed executed, with its figures.

The notebooks are run by notebooks/execute.py (code cells in order in one namespace, no Jupyter
kernel needed, JAXLAND_NOTEBOOK_SMALL=1, matplotlib's Agg backend), the same runner that writes
the committed outputs (`python notebooks/execute.py --write`).
"""

import json
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
sys.path.insert(0, str(ROOT / "notebooks"))

import execute  # noqa: E402


def _code(path):
    return [c for c in json.loads(path.read_text())["cells"] if c["cell_type"] == "code"]


def test_there_are_notebooks():
    assert NOTEBOOKS


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_runs(path, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("JAXLAND_NOTEBOOK_SMALL", "1")
    nb = execute.run(path)
    assert all(c.get("execution_count") for c in nb["cells"] if c["cell_type"] == "code")


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_uses_public_names_only(path):
    private = [line.strip() for c in _code(path) for line in c["source"]
               if re.search(r"\bjaxland\._(?!_)|from jaxland import _|\bjl\._(?!_)|import bench_",
                                                line)]
    assert not private, f"{path.name} reaches into private code: {private}"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_is_committed_executed_with_figures(path):
    cells = _code(path)
    assert all(c.get("execution_count") for c in cells), f"{path.name}: not executed"
    plots = any("plt." in "".join(c["source"]) for c in cells)
    figures = sum("image/png" in o.get("data", {}) for c in cells for o in c.get("outputs", []))
    assert figures or not plots, f"{path.name}: plots, but no figure is committed"
    errors = [o for c in cells for o in c.get("outputs", []) if o["output_type"] == "error"]
    assert not errors
