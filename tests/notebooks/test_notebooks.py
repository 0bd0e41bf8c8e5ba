"""The notebooks under ``notebooks/``: each jupytext pair is in sync and each notebook runs.

Every notebook is a percent-format ``.py`` file (the source of truth) paired with an
``.ipynb`` stripped of outputs (``notebooks/jupytext.toml``). For each pair this checks

(a) the ``.ipynb`` has no outputs or execution counts, and its cells (type and source) equal
    those jupytext reads from the ``.py``;
(b) the ``.py`` executes top to bottom with nbclient in a fresh ``python3`` kernel of the
    interpreter running pytest, in a temporary working directory, with outputs written
    under a temporary folder (``CALENDARING_NOTEBOOK_OUT``) and the checkout first on
    ``PYTHONPATH``. A failing cell fails the test with that cell's source and traceback.

Limits: ``CELL_TIMEOUT`` seconds per cell and ``NOTEBOOK_CAP`` seconds per notebook (the
notebooks are sized for about 3 minutes on 2 CPU cores; the cap is enforced while running,
each cell's limit being what is left of it). The executions are marked ``slow`` (about 10
minutes in all; ``-m "not slow"`` leaves them out). Wall times are printed (``-s``) and kept
in ``<pytest tmp>/notebook_times.json``.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import pytest

jupytext = pytest.importorskip("jupytext")
nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

ROOT = Path(__file__).resolve().parents[2]
NB_DIR = ROOT / "notebooks"
NOTEBOOKS = sorted(p.stem for p in NB_DIR.glob("[0-9][0-9]_*.py"))
CELL_TIMEOUT = 240  # s, one cell
NOTEBOOK_CAP = 300  # s, a whole notebook
KERNEL = "python3"


def test_notebooks_present():
    """The notebook set of the project (a missing pair is an error, not a skip)."""
    expected = {"00_quickstart", "10_contact_law_validation", "20_calendering_run",
                "30_breakage_statistics", "40_surrogate", "50_inverse_calibration",
                "60_sobol_and_trends", "70_microstructure", "80_psd_robustness",
                "90_posterior_refinement"}
    assert expected <= set(NOTEBOOKS), f"missing notebooks: {sorted(expected - set(NOTEBOOKS))}"
    for name in NOTEBOOKS:
        assert (NB_DIR / f"{name}.ipynb").is_file(), f"{name}.ipynb is missing (run jupytext)"


def _cells(nb) -> list[tuple[str, str]]:
    return [(c.cell_type, c.source.strip()) for c in nb.cells]


@pytest.mark.parametrize("name", NOTEBOOKS)
def test_pair_in_sync_and_stripped(name):
    py = jupytext.read(NB_DIR / f"{name}.py")
    ipynb = nbformat.read(NB_DIR / f"{name}.ipynb", as_version=4)
    for k, cell in enumerate(ipynb.cells):
        if cell.cell_type == "code":
            assert not cell.get("outputs"), f"{name}.ipynb cell {k} has outputs: strip them"
            assert cell.get("execution_count") is None, \
                f"{name}.ipynb cell {k} has an execution count: strip it"
    assert _cells(py) == _cells(ipynb), (
        f"{name}.ipynb is out of sync with {name}.py: run "
        f"`jupytext --to ipynb notebooks/{name}.py`")
    first = py.cells[0]
    assert first.cell_type == "markdown" and "run time" in first.source.lower(), \
        f"{name}: the first cell must be markdown stating purpose, inputs and run time"


@pytest.fixture(scope="session")
def kernel_env(tmp_path_factory):
    """A ``python3`` kernelspec for this interpreter, found first on JUPYTER_PATH."""
    base = tmp_path_factory.mktemp("jupyter")
    spec = base / "kernels" / KERNEL
    spec.mkdir(parents=True)
    (spec / "kernel.json").write_text(json.dumps({
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": f"Python 3 ({sys.executable})", "language": "python"}))
    return base


@pytest.mark.slow
@pytest.mark.parametrize("name", NOTEBOOKS)
def test_notebook_executes(name, tmp_path, kernel_env, monkeypatch):
    from nbclient import NotebookClient
    from nbclient.exceptions import CellExecutionError, CellTimeoutError, DeadKernelError

    nb = jupytext.read(NB_DIR / f"{name}.py")
    out = tmp_path / "out"
    monkeypatch.setenv("JUPYTER_PATH", os.pathsep.join(
        [str(kernel_env), os.environ.get("JUPYTER_PATH", "")]).rstrip(os.pathsep))
    monkeypatch.setenv("CALENDARING_NOTEBOOK_OUT", str(out))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(
        [str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))
    monkeypatch.setenv("MPLBACKEND", "module://matplotlib_inline.backend_inline")
    t0 = time.perf_counter()
    deadline = t0 + NOTEBOOK_CAP

    def cell_timeout(cell) -> int:  # the per-cell limit, never past the notebook's cap
        return max(1, int(min(CELL_TIMEOUT, deadline - time.perf_counter())))

    client = NotebookClient(nb, kernel_name=KERNEL, timeout_func=cell_timeout,
                            resources={"metadata": {"path": str(tmp_path)}},
                            allow_errors=False, record_timing=True)
    try:
        client.execute()
    except CellExecutionError as err:  # its text holds the cell's source and traceback
        pytest.fail(f"{name}: a cell failed\n{err}", pytrace=False)
    except (CellTimeoutError, DeadKernelError) as err:
        pytest.fail(f"{name}: {type(err).__name__}: {err}", pytrace=False)
    wall = time.perf_counter() - t0
    times = tmp_path.parent / "notebook_times.json"
    old = json.loads(times.read_text()) if times.exists() else {}
    times.write_text(json.dumps({**old, name: round(wall, 1)}, indent=1))
    print(f"\n{name}: executed in {wall:.1f} s")  # the cap is enforced by the cell timeouts
