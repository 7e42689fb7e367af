"""The analysis notebooks execute top to bottom on smoke data."""

from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_executes(path, smoke_cache, smoke_compare, tmp_path, monkeypatch):
    monkeypatch.setenv("GPG_CACHE_DIR", str(smoke_cache))
    monkeypatch.setenv("GPG_RESULTS_DIR", str(smoke_compare[0]))
    nb = nbformat.read(path, as_version=4)
    # Raises CellExecutionError on the first cell that fails.
    NotebookClient(
        nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    ).execute()


def test_notebooks_present():
    assert {p.stem for p in NOTEBOOKS} >= {
        "01_dataset_exploration",
        "02_model_comparison",
        "03_closed_loop",
    }
