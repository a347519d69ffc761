"""Every tutorial notebook runs from top to bottom (a broken tutorial fails here) and saves its figures."""

from __future__ import annotations

import os
import re
import time
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

ROOT = Path(__file__).resolve().parents[1]
TUTORIALS = ROOT / "tutorials"
NOTEBOOKS = sorted(TUTORIALS.glob("*.ipynb"))
# the command line, and for the training tutorial the training side (o3dvis.training, formerly o3dvis.data)
PUBLIC_MODULES = {"cli", "data", "training"}
CELL_TIMEOUT = 240  # seconds; each notebook takes well under a minute on 2 cores when the machine is idle


def test_the_tutorials_are_there_without_outputs():
    assert [p.name[:3] for p in NOTEBOOKS] == ["01_", "02_", "03_", "04_", "05_", "06_", "07_", "08_"]
    for path in NOTEBOOKS:
        nb = nbformat.read(path, as_version=4)
        nbformat.validate(nb)
        code = [c for c in nb.cells if c.cell_type == "code"]
        assert code and all(not c.outputs and c.execution_count is None for c in code), \
            f"{path.name}: commit notebooks without outputs"


def test_tutorials_use_the_public_api():
    import o3dvis

    for path in NOTEBOOKS:
        code = "\n".join(c.source for c in nbformat.read(path, as_version=4).cells if c.cell_type == "code")
        for module in re.findall(r"^\s*(?:from|import) o3dvis\.(\w+)", code, re.M):
            assert module in PUBLIC_MODULES, f"{path.name} imports o3dvis.{module}, not public API"
        for name in re.findall(r"\bo3dvis\.(\w+)", code):
            assert name in o3dvis.__all__ or name in PUBLIC_MODULES, \
                f"{path.name} uses o3dvis.{name}, not in o3dvis.__all__"


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
    """The figure paths a notebook's code names: ``FIGURES / "name.png"`` in its own ``FIGURES`` folder."""
    code = "\n".join(cell.source for cell in nb.cells if cell.cell_type == "code")
    folders = re.findall(r'^FIGURES = Path\("([^"]+)"\)', code, re.M)
    assert len(folders) == 1, "a tutorial names its figures folder once: FIGURES = Path(\"...\")"
    return [f"{folders[0]}/{name}" for name in re.findall(r'FIGURES / "([^"]+\.png)"', code)]
