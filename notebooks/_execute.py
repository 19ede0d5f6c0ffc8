"""Write the executed copies of the notebooks that the documentation site shows:
`docs/notebooks/<name>.ipynb`, the notebook of `notebooks/` with its outputs and
figures.

python notebooks/_execute.py            # every notebook
python notebooks/_execute.py 02 04      # those whose names start with 02 or 04

Run it after changing a notebook (after its `_make_NN.py`);
`tests/test_notebooks.py` checks that each copy has the cells of its notebook, every
code cell executed, no error and figures. Each notebook runs in a fresh kernel from a
temporary working directory, as in `tests/test_notebooks.py`, but with the kernel's
inline matplotlib backend, which stores each figure in the notebook as a PNG (written
here with a 256-colour palette: the same picture for these line plots, in about a
third of the bytes).
"""

import base64
import io
import os
import pathlib
import sys
import tempfile

import nbclient
import nbformat
from PIL import Image


HERE = pathlib.Path(__file__).parent
DOCS = HERE.parent / "docs" / "notebooks"


def execute(path: pathlib.Path) -> pathlib.Path:
    nb = nbformat.read(path, as_version=4)
    env = dict(os.environ, TQDM_DISABLE="1")
    env.pop("MPLBACKEND", None)  # the kernel's inline backend keeps the figures
    # The kernel imports `constrained_jax` from this checkout.
    env["PYTHONPATH"] = os.pathsep.join(
        [str(HERE.parent), *filter(None, [os.environ.get("PYTHONPATH")])]
    )
    with tempfile.TemporaryDirectory() as tmp:
        client = nbclient.NotebookClient(
            nb,
            timeout=1200,
            kernel_name="python3",
            record_timing=False,  # no timestamps: re-running gives no spurious diff
            resources={"metadata": {"path": tmp}},
        )
        client.execute(env=env)
    shrink_figures(nb)
    out = DOCS / path.name
    if out.is_symlink():
        out.unlink()
    nbformat.write(nb, out)
    return out


def shrink_figures(nb):
    for cell in nb.cells:
        for output in cell.get("outputs", []):
            data = output.get("data", {})
            if "image/png" in data:
                raw = base64.b64decode(data["image/png"])
                with Image.open(io.BytesIO(raw)) as image:
                    image = image.convert("RGBA").quantize(
                        256, method=Image.Quantize.FASTOCTREE
                    )
                png = io.BytesIO()
                image.save(png, "PNG", optimize=True)
                data["image/png"] = base64.b64encode(png.getvalue()).decode("ascii")


if __name__ == "__main__":
    prefixes = sys.argv[1:]
    for path in sorted(HERE.glob("*.ipynb")):
        if not prefixes or path.name.startswith(tuple(prefixes)):
            print("wrote", execute(path), flush=True)
