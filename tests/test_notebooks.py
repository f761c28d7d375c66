"""Every notebook in notebooks/ executes top to bottom (its cells assert what they show)."""

from __future__ import annotations

from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_executes(path, tmp_path, monkeypatch):
    # Notebooks run in a scratch folder; they find the checkout's files (paper_figures/...)
    # through JAXREFL_REPO, which the kernel inherits.
    monkeypatch.setenv("JAXREFL_REPO", str(path.resolve().parents[1]))
    nb = nbformat.read(path, as_version=4)
    NotebookClient(
        nb, timeout=900, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    ).execute()


def test_notebooks_exist():
    assert NOTEBOOKS, "notebooks/ holds no notebook"
