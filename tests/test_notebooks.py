"""The course's notebooks (notebooks/*.py, jupytext percent format) run top to bottom at their
quick budget (``DRIVELAB_NOTEBOOK_BUDGET=quick``), each in a fresh Jupyter kernel, as a student
would run them; any error in any cell fails the test."""

from __future__ import annotations

import os
from pathlib import Path

import jupytext
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.py"))


def test_there_are_notebooks():
    assert NOTEBOOKS


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_runs_top_to_bottom_at_its_quick_budget(path, monkeypatch, tmp_path):
    monkeypatch.setenv("DRIVELAB_NOTEBOOK_BUDGET", "quick")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    notebook = jupytext.read(path)
    first = notebook.cells[0]
    assert first.cell_type == "markdown" and "seed lesson" in first.source and "result it reproduces" in first.source
    NotebookClient(notebook, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}).execute()
    errors = [out for cell in notebook.cells if cell.cell_type == "code" for out in cell.get("outputs", [])
              if out.get("output_type") == "error"]
    assert errors == [], errors


def test_every_notebook_is_a_page_of_the_course():
    """The site renders each notebook (mkdocs.yml's nav, through the docs/notebooks link) and the
    course's overview names it, with the result its full budget measured."""
    mkdocs = (NOTEBOOKS[0].parents[1] / "mkdocs.yml").read_text()
    course = (NOTEBOOKS[0].parents[1] / "docs" / "course.md").read_text()
    assert (NOTEBOOKS[0].parents[1] / "docs" / "notebooks").resolve() == NOTEBOOKS[0].parent
    for path in NOTEBOOKS:
        assert f"notebooks/{path.name}" in mkdocs, f"{path.name} is not in mkdocs.yml's nav"
        assert f"notebooks/{path.name}" in course, f"docs/course.md does not name {path.name}"
