"""What a tour entry declares (`Scene`, its `Job`s and their `Program`s) and what
the entries share: the rows of the table (`Check`, `Row`), the table itself
(`Table`) and the pictures' figure."""

import sys
import textwrap
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import diffrax
import jax.numpy as jnp

import constrained_jax as cjax


@dataclass(frozen=True)
class Check:
    """A computed number against its closed form, within `tolerance` on the relative
    error; `scale` divides the error where the closed form vanishes."""

    quantity: str
    computed: Any
    reference: Any
    tolerance: float
    scale: float | None = None


@dataclass(frozen=True)
class Row:
    """One line of the table: a `Check` of the scene `scene`."""

    scene: str
    quantity: str
    computed: float
    reference: float
    tolerance: float
    scale: float | None = None  # for a closed form that vanishes

    @property
    def rel_error(self) -> float:
        scale = abs(self.reference) if self.scale is None else self.scale
        return abs(self.computed - self.reference) / max(scale, 1e-300)

    @property
    def passed(self) -> bool:
        # A NaN compares False: it never passes.
        return self.rel_error <= self.tolerance


@dataclass(eq=False)
class Program:
    """A compiled function, built once per process: a second run with other inputs
    (traced) does not recompile. Jobs may share one.

    **Arguments:**

    - `name`: how the compilation times name it.
    - `make`: returns the function to compile.

    The tour compiles its programs in the order of the table, so that the first
    scenes' rows come first.
    """

    name: str
    make: Callable[[], Callable]

    @cached_property
    def fn(self) -> Callable:
        import equinox as eqx

        return eqx.filter_jit(self.make())


Pictures = dict[str, Callable]  # file name -> draws on a matplotlib Figure


@dataclass(eq=False)
class Job:
    """One compiled solve and its checks.

    `finish(out)` returns the checks of the program's output and its pictures;
    `label` names the rows (the scene and its changed parameters) and the warning if
    the solver reports a failure (`out.result`); `note`, printed beside the label,
    says why a row that is not a scene on its defaults is in the table. `seconds`:
    the median wall clock of `repeats` calls of the compiled solve, once timed.
    """

    label: str
    program: Program
    inputs: tuple
    finish: Callable[[Any], tuple[list[Check], Pictures]]
    repeats: int = 3
    draw: bool = True  # keep its pictures
    note: str = ""
    seconds: float | None = None
    refused: bool = False  # a refusal is what it checks: no warning for it

    def rows(self, out) -> tuple[list[Row], Pictures]:
        """The finished checks as rows; warns when the solver reports a failure (it
        shows up in the checks as a wrong number or NaN, too)."""
        if out.result != cjax.RESULTS.successful and not self.refused:
            print(f"warning: {self.label}: {cjax.RESULTS[out.result]}", file=sys.stderr)
        checks, pictures = self.finish(out)
        rows = [
            Row(
                self.label,
                c.quantity,
                float(c.computed),
                float(c.reference),
                c.tolerance,
                c.scale,
            )
            for c in checks
        ]
        return rows, pictures


@dataclass(frozen=True)
class Param:
    """A scene's parameter: its default and what it is."""

    default: float
    help: str


@dataclass(frozen=True)
class Scene:
    """One scene of the tour, declared once.

    **Arguments:**

    - `name`: the command line's `scene NAME`.
    - `doc`: one sentence: what is solved and checked.
    - `params`: name -> `Param`, in the order `--help` lists them.
    - `build`: `build(label, **values) -> list[Job]`, every parameter given; raises
        `ValueError` with the reason for impossible parameters.
    - `picture`: what its picture shows (for `tour --help`), if it draws one.
    - `title`: a few words for the table's heading: what the scene is.
    """

    name: str
    doc: str
    params: dict[str, Param]
    build: Callable[..., list[Job]]
    picture: str = ""
    title: str = ""

    def label(self, values: dict) -> str:
        """The name, with the parameters that differ from their defaults."""
        changed = {k: v for k, v in values.items() if v != self.params[k].default}
        if not changed:
            return self.name
        return f"{self.name}({', '.join(f'{k}={v:g}' for k, v in changed.items())})"

    def jobs(self, **values: float) -> list[Job]:
        """The jobs on these parameters (the others at their defaults)."""
        values = {k: values.get(k, p.default) for k, p in self.params.items()}
        label = self.label(values)
        try:
            jobs = self.build(label, **values)
        except ValueError as e:
            raise SystemExit(f"{label}: {e}") from None
        for job in jobs:
            if job.label == label and not job.note:
                job.note = self.title
        return jobs


def arrays(*values) -> tuple:
    return tuple(jnp.asarray(v, float) for v in values)


def simulate(system, t1, q0, qd0, args, saveat, **kwargs) -> cjax.Trajectory:
    """`cjax.simulate` from 0 to `t1` at rtol = atol = 1e-10 (or `kwargs`), failures
    reported in `result`."""
    kwargs.setdefault(
        "stepsize_controller", diffrax.PIDController(rtol=1e-10, atol=1e-10)
    )
    return cjax.simulate(
        system, (0.0, t1), q0, qd0, args, saveat=saveat, throw=False, **kwargs
    )


WIDTH = 100  # the most columns a line of the tour takes


class Table:
    """The table, printed as it grows: a legend and the column names once, then for
    each job its label (with its note) and its rows, flushed, so that a scene's rows
    show as soon as it is solved. A row is indented under its label; its columns are
    separated by at least two spaces."""

    QUANTITY = 32  # the quantity's column

    def __init__(self):
        self.heading = None
        self.ok = True

    def start(self) -> None:
        print(
            textwrap.fill(
                "Each row checks a computed number against the closed form: rel. "
                "error = |computed - closed form| / |closed form| (a quantity marked "
                "(/l), (/R), ... has the closed form 0 and is divided by that scale), "
                "and passes if it is at most tol.",
                WIDTH,
            )
        )
        print(
            f"\n  {'quantity':<{self.QUANTITY}}  {'computed':>17}  "
            f"{'closed form':>17}  {'rel. error':>10}  {'tol.':>5}  check"
        )

    def add(self, label: str, rows: list[Row], note: str = "") -> bool:
        """Prints `rows` under `label` (and `note`, for a new heading); whether they
        all passed."""
        heading = f"{label}: {note}" if note else label
        if rows and heading != self.heading:
            print(textwrap.fill(heading, WIDTH, subsequent_indent="    "))
            self.heading = heading
        ok = True
        for row in rows:
            ok &= row.passed
            print(
                f"  {row.quantity:<{self.QUANTITY}}  {row.computed:>17.11g}  "
                f"{row.reference:>17.11g}  {row.rel_error:>10.2e}  "
                f"{row.tolerance:>5.0e}  {'ok' if row.passed else 'FAIL'}"
            )
        sys.stdout.flush()
        self.ok &= ok
        return ok


def save(out: Path, name: str, draw: Callable) -> Path:
    """Draws a picture on an 8 x 5.5 in figure and writes it to `out / name`."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 5.5), layout="constrained")
    draw(fig)
    out.mkdir(parents=True, exist_ok=True)
    path = out / name
    fig.savefig(path, dpi=100)
    return path
