"""The documentation site builds with `mkdocs build --strict` (every cross-reference
resolves, every page is in the nav, no warning), and documents every public name."""

import ast
import importlib.util
import os
import pathlib
import subprocess
import sys

import pytest


ROOT = pathlib.Path(__file__).parents[1]
_DOCS_PACKAGES = (
    "mkdocs",
    "material",
    "mkdocstrings",
    "mkdocstrings_handlers.python",
    "mkdocs_jupyter",
)


def _missing_docs_packages() -> list[str]:
    missing = []
    for name in _DOCS_PACKAGES:
        try:
            if importlib.util.find_spec(name) is None:
                missing.append(name)
        except ModuleNotFoundError:
            missing.append(name)
    return missing


needs_mkdocs = pytest.mark.skipif(
    bool(_missing_docs_packages()),
    reason=f"the docs stack is not installed ({', '.join(_missing_docs_packages())}): "
    'pip install -e ".[docs]" (the `test` extra includes it, so CI has it)',
)


def _public_names() -> set[str]:
    """The names `constrained_jax/__init__.py` re-exports (`import x as x`)."""
    tree = ast.parse((ROOT / "constrained_jax" / "__init__.py").read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            names |= {a.asname for a in node.names if a.asname == a.name}
    return names


def test_every_public_name_is_in_the_api_reference():
    documented = set()
    for page in (ROOT / "docs" / "api").glob("*.md"):
        for line in page.read_text().splitlines():
            if line.startswith("::: constrained_jax."):
                documented.add(line.split()[1].removeprefix("constrained_jax."))
    public = _public_names()
    assert {"extremize", "simulate", "RESULTS", "plot", "scenes"} <= public
    assert not public - documented, (
        f"public names missing from docs/api/*.md: {sorted(public - documented)}"
    )


def test_readme_points_to_the_docs_not_to_shared():
    readme = (ROOT / "README.md").read_text()
    assert "../shared/" not in readme
    assert "docs/architecture.md" in readme
    assert "mkdocs serve" in readme


@needs_mkdocs
def test_site_builds_strict(tmp_path):
    site = tmp_path / "site"
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "mkdocs",
            "build",
            "--strict",
            "--config-file",
            str(ROOT / "mkdocs.yml"),
            "--site-dir",
            str(site),
        ],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr

    for page in (
        "index.html",
        "getting-started/index.html",
        "conventions/index.html",
        "extremize/index.html",
        "functionals/index.html",
        "mechanics/index.html",
        "choosing-a-solver/index.html",
        "sharp-edges/index.html",
        "architecture/index.html",
        "notebooks/03_two_cylinders/index.html",
        "images/work_precision.png",
    ):
        assert (site / page).is_file(), page

    # The API reference is generated from the docstrings.
    import constrained_jax as cjax

    api = (site / "api" / "extremize" / "index.html").read_text()
    first_words = cjax.extremize.__doc__.split("`")[0].strip()
    assert first_words and first_words in api
    assert 'id="constrained_jax.extremize"' in api
    results = (site / "api" / "results" / "index.html").read_text()
    assert "singular_kkt" in results
    notebook = (site / "notebooks" / "03_two_cylinders" / "index.html").read_text()
    assert "Unilateral" in notebook
