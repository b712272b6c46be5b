"""Every notebook in notebooks/ runs top to bottom at small size, so none of them rots.

Code cells are executed in order in one namespace (no Jupyter kernel needed), with
JAXLAND_NOTEBOOK_SMALL=1 and a non-interactive matplotlib backend.
"""

import json
import os
from pathlib import Path

import pytest

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_runs(path, tmp_path, monkeypatch):
    monkeypatch.setenv("JAXLAND_NOTEBOOK_SMALL", "1")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    monkeypatch.chdir(tmp_path)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cells = json.loads(path.read_text())["cells"]
    namespace = {"__name__": "__main__"}
    try:
        for i, cell in enumerate(cells):
            if cell["cell_type"] == "code":
                src = "".join(cell["source"])
                exec(compile(src, f"{path.name}[cell {i}]", "exec"), namespace)
    finally:
        plt.close("all")
    assert os.environ["JAXLAND_NOTEBOOK_SMALL"] == "1"


def test_there_are_notebooks():
    assert NOTEBOOKS
