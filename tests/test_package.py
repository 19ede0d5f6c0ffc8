"""The shape of the package: its import graph has no cycle, and its docstrings and
comments state rules, not measurements (numbers live in `benchmarks/README.md`)."""

import ast
import io
import pathlib
import re
import tokenize

import pytest


PACKAGE = pathlib.Path(__file__).resolve().parents[1] / "constrained_jax"


def _module_name(path: pathlib.Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imports(path: pathlib.Path, modules) -> set[str]:
    """The package's modules that `path` imports, at any depth of its code (a
    function-level import counts: it is a cycle all the same)."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            # `from .pkg import mod` imports the submodule; `from .pkg import name`
            # the package (its `__init__`).
            for alias in node.names:
                sub = f"{module}.{alias.name}"
                found.add(sub if sub in modules else module)
    return {m for m in found if m.split(".")[0] == "constrained_jax"}


def _graph() -> dict[str, set[str]]:
    modules = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
    return {
        name: {m for m in _imports(path, modules) if m in modules and m != name}
        for name, path in modules.items()
    }


def test_import_graph_has_no_cycle():
    """Modules import downwards only. A package's `__init__` re-exporting its
    children is an edge like any other, so a child importing its package's
    `__init__` (rather than a sibling module) is a cycle too."""
    graph = _graph()
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node):
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycle = stack[stack.index(nxt) :] + [nxt]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node)


# A measured time or speed: a number (or a range of numbers) with a unit of time, or
# a factor or percentage "faster"/"slower". Units directly followed by an operator
# are algebra (`3 s + k`, `4 s^2`), not measurements.
_NUMBER = r"\d+(?:[.,]\d+)*(?:\s*(?:-|to|->)\s*\d+(?:[.,]\d+)*)?"
_MEASURED = re.compile(
    rf"\b{_NUMBER}\s?(?:ms|us|µs|ns|s|sec|seconds|min|minutes)\b(?!\s*[\^*/+(])"
    rf"|\b{_NUMBER}\s?(?:x|%)\s+(?:faster|slower|the time|as fast|as slow)"
    rf"|(?<![\w.]){_NUMBER}x(?=[\s,;:)]|$)",
)


def _comments_and_strings(source: str):
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type in (tokenize.COMMENT, tokenize.STRING):
            yield token.start[0], token.string


def test_no_measured_times_in_docstrings_or_comments():
    """Docstrings and comments state the rule (and may point to the benchmark that
    measures it); measured times belong to `benchmarks/README.md`."""
    hits = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for line, text in _comments_and_strings(path.read_text()):
            for match in _MEASURED.finditer(text):
                where = path.relative_to(PACKAGE.parent)
                hits.append(f"{where}:{line}: {match.group(0)!r}")
    assert not hits, "measured times in the source:\n" + "\n".join(hits)


def test_the_measurement_pattern_has_teeth():
    for measured in (
        "took 1.5 s instead of 2.5 s",
        "3.9 against 3.4 us per step",
        "0.9 -> 1.5 ms",
        "24-27 s",
        "1.7-5x faster",
        "27 % slower",
        "costs about 5x the solve",
        "(7.3x before",
    ):
        assert _MEASURED.search(measured), measured
    for rule in (
        "`3 s + k` products",
        "`4 s^2 / (3a)`",
        "1e-8 in float64",
        "n = 64",
        r"re.compile(r'0x[0-9a-f]+')",
        "an n x n matrix",
    ):
        assert not _MEASURED.search(rule), rule


def test_one_implicit_derivative_wrapper():
    """Every constrained nonlinear solve (`extremize`, `solve_functional`, the
    variational integrator's steps) goes through `kkt_solve`, the one caller of the
    implicit derivative; and every saddle-point solve of mechanics through
    `_solver/saddle_point.solve`, the one `custom_jvp` of it."""
    calls = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if path.name == "_implicit.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "id", "") == (
                "implicit_jvp"
            ):
                calls.append(path.relative_to(PACKAGE).as_posix())
    assert calls == ["_kkt.py"], calls


def test_dependencies_are_ranges_and_the_tested_set_is_pinned():
    """Installable beside other JAX libraries: every runtime dependency is a range
    with a lower bound (no `==`, no upper bound unless a comment in pyproject.toml
    names the incompatibility); `constraints.txt` pins each of them exactly, at its
    lower bound or above."""
    import tomllib

    root = pathlib.Path(__file__).resolve().parents[1]
    project = tomllib.loads((root / "pyproject.toml").read_text())["project"]
    pinned = {}
    for line in (root / "constraints.txt").read_text().splitlines():
        if line and not line.startswith("#"):
            name, version = line.split("==")
            pinned[name.lower().replace("_", "-")] = version
    for spec in project["dependencies"]:
        match = re.fullmatch(r"([A-Za-z0-9_.-]+)>=([0-9.]+)", spec)
        assert match, f"{spec!r}: a lower bound only"
        name, lower = match.group(1).lower(), match.group(2)
        assert name in pinned, f"{name} is not in constraints.txt"
        as_tuple = lambda v: tuple(int(x) for x in v.split(".")[:3])
        assert as_tuple(pinned[name]) >= as_tuple(lower), name
