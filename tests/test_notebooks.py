"""The analysis notebooks execute top to bottom on smoke data."""

from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))


# All six run with `make test-slow`: their steps are covered in the fast set elsewhere (the
# tutorial's by tests/data/test_dataset.py's CSV import, tests/quadrotor/test_vehicle.py's
# minimal vehicle, tests/test_checkpoint.py and tests/quadrotor/test_dynamics.py; the analysis
# notebooks' by the compare and simulate runs), and each costs tens of seconds.
FAST: set[str] = set()
PARAMS = [p if p.stem in FAST else pytest.param(p, marks=pytest.mark.slow) for p in NOTEBOOKS]


@pytest.mark.parametrize("path", PARAMS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_executes(path, smoke_cache, tmp_path, monkeypatch, request):
    monkeypatch.setenv("GPG_CACHE_DIR", str(smoke_cache))
    monkeypatch.setenv("GPG_NOTEBOOK_POINTS", "40")
    monkeypatch.setenv("GPG_NOTEBOOK_ITERATIONS", "40")
    # The kernel runs in tmp_path: the checkout's experiments/ (02 and 06 run its code) are
    # found on the path, as from the repository's root.
    monkeypatch.setenv("PYTHONPATH", str(ROOT))
    if path.stem == "02_model_comparison":
        monkeypatch.setenv("GPG_RESULTS_DIR", str(request.getfixturevalue("smoke_compare")[0]))
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
        "04_your_own_vehicle",
        "05_learning_a_policy",
        "06_real_flights",
    }
