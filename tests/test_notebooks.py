"""Both notebooks run top to bottom on this install with small budgets set in their parameter cell."""

from __future__ import annotations

import json
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"
RECIPES = Path(__file__).resolve().parents[1] / "recipes"


def run_notebook(name: str, parameters: str, folder: Path) -> nbformat.NotebookNode:
    """Execute a notebook in ``folder`` with its parameter cell (tagged ``parameters``) replaced."""
    notebook = nbformat.read(NOTEBOOKS / name, as_version=4)
    (cell,) = [cell for cell in notebook.cells if "parameters" in cell.metadata.get("tags", [])]
    cell.source = parameters
    NotebookClient(notebook, timeout=900, kernel_name="python3", resources={"metadata": {"path": str(folder)}}).execute()
    return notebook


def outputs(notebook: nbformat.NotebookNode, kind: str) -> list[dict]:
    return [
        output for cell in notebook.cells if cell.cell_type == "code" for output in cell.outputs if output.output_type == kind
    ]


@pytest.mark.slow
def test_quickstart_notebook_trains_evaluates_plots_and_animates(tmp_path: Path) -> None:
    parameters = "RECIPE = 'residual-ch5-bearing'\nSTEPS = 1\nN_ENVS = 1\nEVAL_EPISODES = 2\nMAX_STEPS = 40\nSEED = 0"
    notebook = run_notebook("01_quickstart.ipynb", parameters, tmp_path)
    text = "".join(output["text"] for output in outputs(notebook, "stream"))
    assert "12 slots = 2 teams x 6 agents" in text and "trained residual-ch5-bearing into runs/notebook/" in text
    rows = [line.split() for line in text.splitlines() if line.startswith(("trained ", "shipped ")) and "%" in line]
    assert [row[0] for row in rows] == ["trained", "shipped"] and all(row[1].endswith("%") for row in rows)
    assert len(list((tmp_path / "runs" / "notebook").glob("residual-ch5-bearing_6a_s0_*/final_model.zip"))) == 1
    figures = [output for output in outputs(notebook, "execute_result") if "image/png" in output["data"]]
    assert len(figures) == 2  # the trajectory and the error curves
    gifs = [output for output in outputs(notebook, "display_data") if "image/gif" in output["data"]]
    assert len(gifs) == 1 and (tmp_path / "runs" / "notebook" / "episode.gif").is_file()


@pytest.mark.slow
def test_thesis_results_notebook_runs_sweeps_and_shows_the_thesis_numbers(tmp_path: Path) -> None:
    parameters = (
        "RECIPE_FILES = ['quick-ch4-team', 'quick-ch5-angle']\nSEEDS = [0]\n"
        f"RECIPES_DIR = {str(RECIPES)!r}\nLOGDIR = 'sweeps'\nRUN_MISSING = True"
    )
    notebook = run_notebook("02_thesis_results.ipynb", parameters, tmp_path)
    for name in ("quick-ch4-team", "quick-ch5-angle"):
        assert json.loads((tmp_path / "sweeps" / name / "aggregate.json").read_text())["seeds"] == [0]
    markdown = "".join(output["data"].get("text/markdown", "") for output in outputs(notebook, "display_data"))
    assert "| quick-ch4-team | 1 |" in markdown and "| 7% |" in markdown  # the thesis's ch4-team success rate
    assert "| quick-ch5-angle | 1 |" in markdown and "| 8% |" in markdown
    assert any("image/png" in output["data"] for output in outputs(notebook, "execute_result"))  # training curves
