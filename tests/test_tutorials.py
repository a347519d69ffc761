"""Every tutorial notebook runs from top to bottom (a broken tutorial fails here) and saves its figures."""

from __future__ import annotations

import os
import time
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

ROOT = Path(__file__).resolve().parents[1]
TUTORIALS = ROOT / "tutorials"
NOTEBOOKS = sorted(TUTORIALS.glob("*.ipynb"))
CELL_TIMEOUT = 240  # seconds; each notebook takes well under a minute on 2 cores when the machine is idle


def test_the_six_tutorials_are_there_without_outputs():
    assert [p.name[:3] for p in NOTEBOOKS] == ["01_", "02_", "03_", "04_", "05_", "06_"]
    for path in NOTEBOOKS:
        nb = nbformat.read(path, as_version=4)
        nbformat.validate(nb)
        code = [c for c in nb.cells if c.cell_type == "code"]
        assert code and all(not c.outputs and c.execution_count is None for c in code), \
            f"{path.name}: commit notebooks without outputs"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_tutorial_runs(path, monkeypatch):
    # the kernel imports this checkout of o3dvis, installed or not
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    monkeypatch.setenv("MPLBACKEND", "Agg")
    nb = nbformat.read(path, as_version=4)
    start = time.time()
    NotebookClient(nb, timeout=CELL_TIMEOUT, kernel_name="python3",
                   resources={"metadata": {"path": str(TUTORIALS)}}).execute()
    saved = [Path(TUTORIALS, name) for name in _saved_figures(nb)]
    assert saved, f"{path.name} saves no figure"
    for figure in saved:
        assert figure.is_file() and figure.stat().st_mtime >= start - 1, f"{figure} was not written"


def _saved_figures(nb) -> list[str]:
    """The figure paths a notebook's code names (``FIGURES / "name.png"``)."""
    import re

    names = []
    for cell in nb.cells:
        if cell.cell_type == "code":
            names += re.findall(r'FIGURES / "([^"]+\.png)"', cell.source)
    return [f"figures/{n}" for n in names]
