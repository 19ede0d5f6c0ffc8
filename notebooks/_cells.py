"""Shared by the `_make_NN.py` scripts that write the notebooks (stored without
outputs; the test suite executes them)."""

import pathlib

import nbformat
from nbformat.v4 import new_code_cell, new_markdown_cell, new_notebook


def md(text):
    return new_markdown_cell(text.strip())


def code(text):
    return new_code_cell(text.strip())


def write(cells, name):
    """Write `cells` to `notebooks/<name>` with stable cell ids (regenerating gives
    no spurious diff) and the python3 kernel."""
    nb = new_notebook(cells=cells)
    for i, cell in enumerate(nb.cells):
        cell.id = f"cell-{i:02d}"
    nb.metadata["kernelspec"] = {
        "name": "python3",
        "display_name": "Python 3",
        "language": "python",
    }
    path = pathlib.Path(__file__).with_name(name)
    nbformat.write(nb, path)
    print("wrote", path)
