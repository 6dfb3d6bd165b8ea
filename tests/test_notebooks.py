"""Execute every research notebook top to bottom (nbclient) and check they are stored stripped.

The notebooks assert their own numbers (patch values, Jacobian agreement, waypoints reached),
so an execution error is a failed check, not only a crash. They run here at a smaller size
(``JAXRKPM_NOTEBOOK_QUICK=1``: fewer increments, iterations and waypoints; the same asserts),
the users' default sizes being those of the studies they show.
"""
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
CELL_TIMEOUT_S = 600   # a hang guard, not a speed check (no test asserts a wall-clock time)


def test_notebooks_exist():
    names = {p.name for p in NOTEBOOKS}
    assert {"01_quickstart.ipynb", "02_tracking.ipynb", "03_paddle_sweeps.ipynb", "04_autodiff_vs_fd.ipynb",
            "05_rig_sim.ipynb", "06_mesh_objects.ipynb"} <= names


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_stored_without_outputs(path):
    nb = nbformat.read(path, as_version=4)
    for cell in nb.cells:
        if cell.cell_type == "code":
            assert cell.outputs == [] and cell.execution_count is None, \
                f"{path.name}: cell {cell.get('id')} has outputs; strip them before committing"


# the notebooks that replay a study (tracking, paddle sweeps, the rig, mesh objects) run in the slow
# set: their computations are each tested in the default run (tests/control, tests/thesis, tests/discretise)
STUDY_NOTEBOOKS = {"02_tracking", "03_paddle_sweeps", "05_rig_sim", "06_mesh_objects"}
RUNS = [pytest.param(p, id=p.stem, marks=pytest.mark.slow(reason="replays a study notebook end to end"))
        if p.stem in STUDY_NOTEBOOKS else pytest.param(p, id=p.stem) for p in NOTEBOOKS]


@pytest.mark.parametrize("path", RUNS)
def test_notebook_runs(path, monkeypatch):
    monkeypatch.setenv("MPLBACKEND", "Agg")
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "1")
    monkeypatch.setenv("JAXRKPM_NOTEBOOK_QUICK", "1")     # the notebooks' small sizes (module docstring)
    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(nb, timeout=CELL_TIMEOUT_S, kernel_name="python3",
                                     resources={"metadata": {"path": str(ROOT)}})
    client.execute()   # raises CellExecutionError with the failing cell's traceback
