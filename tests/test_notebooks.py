"""Every notebook in notebooks/ executes top to bottom (its cells assert what they show).

A notebook runs in a scratch folder, in a kernel that inherits this process's environment:
``JAXREFL_REPO`` names the checkout (for files such as ``paper_figures/...``), and a notebook
whose code reads ``JAXREFL_SHARED_DATA`` receives the data folder this test run resolved (the
``shared_data`` fixture: skipped with its reason when the folder is missing, outside CI).
"""

from __future__ import annotations

from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


def _reads_shared_data(nb) -> bool:
    """Whether a code cell of the notebook looks up the shared data folder."""
    return any(c.cell_type == "code" and "JAXREFL_SHARED_DATA" in c.source for c in nb.cells)


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_executes(path, tmp_path, monkeypatch, request):
    nb = nbformat.read(path, as_version=4)
    monkeypatch.setenv("JAXREFL_REPO", str(path.resolve().parents[1]))
    if _reads_shared_data(nb):
        data = request.getfixturevalue("shared_data")
        monkeypatch.setenv("JAXREFL_SHARED_DATA", str(Path(data).resolve()))
    NotebookClient(
        nb, timeout=900, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    ).execute()


def test_notebooks_exist():
    assert NOTEBOOKS, "notebooks/ holds no notebook"


def test_data_notebooks_are_recognised():
    # The notebooks that read the measured data get the fixture's folder (and skip without it).
    reads = {p.name for p in NOTEBOOKS if _reads_shared_data(nbformat.read(p, as_version=4))}
    assert {"fit_bath_tile.ipynb", "measured_cornell.ipynb", "posterior_bath_tile.ipynb"} <= reads
    assert "brdf_models.ipynb" not in reads
