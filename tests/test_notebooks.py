"""Every notebook in `notebooks/` runs top to bottom without an error.

The notebooks are stored without outputs; here each one is executed in a fresh
kernel (nbclient) from a temporary working directory, with matplotlib's non-GUI
backend. Their own cells assert their closed-form checks, so a wrong number fails
here too.
"""

import os
import pathlib

import pytest

from .conftest import USER_XLA_FLAGS


nbclient = pytest.importorskip("nbclient")
nbformat = pytest.importorskip("nbformat")

NOTEBOOKS = sorted((pathlib.Path(__file__).parents[1] / "notebooks").glob("*.ipynb"))


def test_there_are_notebooks():
    assert len(NOTEBOOKS) >= 5, NOTEBOOKS


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path, tmp_path, monkeypatch):
    monkeypatch.setenv("MPLBACKEND", "Agg")
    monkeypatch.setenv("TQDM_DISABLE", "1")
    nb = nbformat.read(path, as_version=4)
    for cell in nb.cells:
        if cell.cell_type == "code":
            assert not cell.outputs, f"{path.name}: store notebooks without outputs"
    client = nbclient.NotebookClient(
        nb,
        timeout=600,
        kernel_name="python3",
        resources={"metadata": {"path": str(tmp_path)}},
    )
    # The kernel gets the user's `XLA_FLAGS` (none in CI: XLA's defaults, what a
    # notebook user runs), not the flags `conftest.py` adds for this worker.
    env = dict(os.environ)
    env["XLA_FLAGS"] = USER_XLA_FLAGS
    client.execute(env=env)
