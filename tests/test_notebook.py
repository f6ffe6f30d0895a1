"""The tour notebook runs top to bottom on small sizes.  Its cells assert
what it shows: the flip interval against the exact solution, the fitted
orders 2 (NaiveLieRK4) and 4 (RKMK4), accuracy bought by tighter tolerances,
vmap against plain calls, and jacfwd against finite differences."""

from pathlib import Path

import nbformat
import pytest

nbclient = pytest.importorskip("nbclient")

NOTEBOOK = Path(__file__).resolve().parents[1] / "notebooks" / "tour.ipynb"


def test_tour_notebook_runs_and_shows_its_figures(monkeypatch):
    monkeypatch.setenv("LIERK_NOTEBOOK_SMALL", "1")
    nb = nbformat.read(NOTEBOOK, as_version=4)
    client = nbclient.NotebookClient(
        nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(NOTEBOOK.parent)}}
    )
    client.execute()  # raises CellExecutionError if any cell (or its asserts) fails

    outputs = [o for cell in nb.cells if cell.cell_type == "code" for o in cell.get("outputs", [])]
    images = [o for o in outputs if "image/png" in o.get("data", {})]
    assert len(images) == 5  # flip, order, work-precision, sweep, sensitivity
    text = "".join(o.get("text", "") for o in outputs if o.get("output_type") == "stream")
    assert "flip interval (exact): 23.631 s" in text
    assert "'NaiveLieRK4': 2.0" in text or "'NaiveLieRK4': 1.9" in text
