"""The documentation site builds with `mkdocs build --strict` (every cross-reference
resolves, every page is in the nav, no warning), documents every public name, loads
nothing from the network, and shows the notebooks executed. (`test_docs_browser.py`
opens the built pages in a browser.)"""

import ast
import importlib.util
import json
import os
import pathlib
import re
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
        "getting-started.html",
        "conventions.html",
        "extremize.html",
        "functionals.html",
        "mechanics.html",
        "choosing-a-solver.html",
        "sharp-edges.html",
        "architecture.html",
        "notebooks/03_two_cylinders.html",
        "images/work_precision.png",
        "_static/mathjax/tex-svg.js",  # MathJax, shipped with the site
        "_static/mathjax/LICENSE",
    ):
        assert (site / page).is_file(), page
    assert "Apache License" in (site / "_static/mathjax/LICENSE").read_text()

    # The API reference is generated from the docstrings.
    import constrained_jax as cjax

    api = (site / "api" / "extremize.html").read_text()
    first_words = cjax.extremize.__doc__.split("`")[0].strip()
    assert first_words and first_words in api
    assert 'id="constrained_jax.extremize"' in api
    results = (site / "api" / "results.html").read_text()
    assert "singular_kkt" in results

    # No page loads a script, a stylesheet, a font or an image from the network
    # (the pages render offline, behind a firewall, opened from the folder).
    pages = sorted(site.rglob("*.html"))
    assert len(pages) > 20
    for page in pages:
        html = page.read_text()
        for tag in re.findall(r"<(?:script|link|img|iframe)\b[^>]*>", html):
            assert not re.search(r'(?:src|href)="(?:https?:)?//', tag), (page, tag)
        assert "fonts.googleapis" not in html, page

    # The notebook pages show outputs and figures (every code cell executed).
    for name in NOTEBOOKS:
        html = (site / "notebooks" / f"{name}.html").read_text()
        assert not re.search(r"In\s\[\s\]:", html), f"{name}: a cell not executed"
        assert html.count('src="data:image/png;base64,') >= 1, f"{name}: no figure"
    notebook = (site / "notebooks" / "03_two_cylinders.html").read_text()
    assert "Unilateral" in notebook


NOTEBOOKS = sorted(p.stem for p in (ROOT / "notebooks").glob("*.ipynb"))


@pytest.mark.parametrize("name", NOTEBOOKS)
def test_site_shows_executed_copies_of_the_notebooks(name):
    """`docs/notebooks/<name>.ipynb` (what the site shows) is `notebooks/<name>.ipynb`
    executed top to bottom in one kernel (`python notebooks/_execute.py`): the same
    cells, every code cell run in order, no error, and figures."""
    source = json.loads((ROOT / "notebooks" / f"{name}.ipynb").read_text())
    path = ROOT / "docs" / "notebooks" / f"{name}.ipynb"
    rerun = f"run `python notebooks/_execute.py {name[:2]}`"
    assert path.is_file() and not path.is_symlink(), f"{path} missing: {rerun}"
    copy = json.loads(path.read_text())
    cells = lambda nb: [(c["cell_type"], "".join(c["source"])) for c in nb["cells"]]
    assert cells(copy) == cells(source), f"{path.name} is out of date: {rerun}"
    code = [c for c in copy["cells"] if c["cell_type"] == "code"]
    assert [c["execution_count"] for c in code] == list(range(1, len(code) + 1)), rerun
    outputs = [o for c in code for o in c["outputs"]]
    assert not [o for o in outputs if o["output_type"] == "error"], rerun
    assert any("image/png" in o.get("data", {}) for o in outputs), f"{name}: no figure"


def _public_callables():
    import types

    import constrained_jax as cjax

    for module in (cjax, cjax.settings, cjax.plot):
        for name, obj in sorted(vars(module).items()):
            if name.startswith("_") or not isinstance(obj, (type, types.FunctionType)):
                continue
            if obj.__module__.startswith("constrained_jax"):
                yield f"{module.__name__}.{name}", obj


# The phrases by which a docstring states a default: "`value` (default)",
# "`name=value` (the default)", "default `value`", "The default, `value`,".
_STATED = (
    r"`(?P<value>[^`]+)` \((?:the )?default\)",
    r"\bdefault `(?P<value>[^`]+)`",
    r"\bThe default, `(?P<value>[^`]+)`",
)


def _stated_defaults(doc: str, parameters) -> list[tuple[str, str]]:
    """`(parameter, value)` for each default a docstring states: in a parameter's
    `- `name`: ...` item, or as `name=value` anywhere."""
    found = []
    items = re.split(r"^\s*- `", doc, flags=re.M)[1:]
    for item in items:
        name = item.split("`", 1)[0]
        text = " ".join(item.split())
        if name not in parameters:
            continue
        for pattern in _STATED:
            for match in re.finditer(pattern, text):
                value = match.group("value")
                if "=" not in value:
                    found.append((name, value))
    text = " ".join(doc.split())
    for pattern in _STATED:
        for match in re.finditer(pattern, text):
            name, eq, value = match.group("value").partition("=")
            if eq and name in parameters:
                found.append((name, value))
    return found


def _check_defaults(qualname, obj, namespace) -> tuple[int, list[str]]:
    import inspect

    doc = inspect.getdoc(obj) or ""
    parameters = inspect.signature(obj).parameters
    wrong, count = [], 0
    for name, value in _stated_defaults(doc, parameters):
        default = parameters[name].default
        if default is inspect.Parameter.empty:
            wrong.append(f"{qualname}: `{name}` has no default, docstring: {value}")
            continue
        if default is None and value != "None":
            continue  # `None` stands for a default computed in the call
        count += 1
        if (qualname, name) in _NO_EQUALITY:
            continue
        try:
            stated = eval(value, namespace)  # noqa: S307
        except Exception:
            wrong.append(f"{qualname}: `{name}`: cannot read `{value}`")
            continue
        if type(stated) is not type(default) or not bool(stated == default):
            wrong.append(f"{qualname}: `{name}` defaults to {default!r}, docs: {value}")
    return count, wrong


# Defaults that do not compare by `==` (an optax optimizer is a pair of closures):
# checked by hand in `test_stated_defaults_are_the_signatures`.
_NO_EQUALITY = {("constrained_jax.fit", "optimizer")}


def _namespace():
    import diffrax
    import jax
    import optax

    import constrained_jax as cjax

    return {**vars(cjax), "cjax": cjax, "jax": jax, "diffrax": diffrax, "optax": optax}


def test_stated_defaults_are_the_signatures():
    """Where a public docstring states a parameter's default ("`None` (default)",
    "default `0.0`", "`method="auto"` (the default)", "The default,
    `Automatic()`"), it is the signature's (a `None` default may stand for a
    computed one, which the docstring then describes)."""
    namespace = _namespace()
    count, wrong = 0, []
    for qualname, obj in _public_callables():
        n, w = _check_defaults(qualname, obj, namespace)
        count += n
        wrong += w
    assert not wrong, "\n".join(wrong)
    assert count >= 12  # the phrases are found
    # `fit`: "by default `optax.adam(1e-2)`".
    import inspect

    import constrained_jax as cjax
    from constrained_jax import _fit

    assert _fit.DEFAULT_LEARNING_RATE == 1e-2
    optimizer = inspect.signature(cjax.fit).parameters["optimizer"].default
    assert optimizer is _fit._DEFAULT_OPTIMIZER
    assert "by default `optax.adam(1e-2)`" in " ".join(cjax.fit.__doc__.split())


def test_the_default_check_has_teeth():
    def fn(x, method="auto", solver=None, tol=1e-8):
        """**Arguments:**

        - `method`: `"levels"` (default) or `"auto"`.
        - `solver`: `None` (default): chosen for you.
        - `tol`: default `1e-6`.
        """

    count, wrong = _check_defaults("fn", fn, _namespace())
    assert count == 3
    assert len(wrong) == 2 and "method" in wrong[0] and "tol" in wrong[1]
