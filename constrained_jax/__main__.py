"""Command line: `python -m constrained_jax` (also the `constrained-jax` script).

- `tour`: solve every built-in scene on its default parameters, print the table of
  checks (under each scene: quantity, computed, closed form, relative error,
  tolerance), write the pictures into `--out` (default `./constrained_jax_tour/`) and
  a work-precision diagram of the pendulum. Exit status 1 if any check fails.
- `scene NAME [--param value ...]`: run one scene (and draw its picture, if it has
  one); `scene NAME --help` lists its parameters with their defaults.
- `list`: the scenes and their parameters.

Every check compares a computed number with the scene's closed form. The relative
error is `|computed - closed form| / |closed form|`, or, for a quantity whose closed
form is zero, divided by the scale named in the row (`/l`: a length, `/sqrt(gl)`: a
speed). Each row states its tolerance, chosen from the accuracy the method promises
(the integrator's tolerance, spectral accuracy), not from the result. A row that is
not a scene on its defaults says why it is there (its heading's note). Every line
fits 100 columns.

Before it compiles, the tour says what the first run costs and that later runs read
the programs from the compilation cache. The programs compile `--jobs` at a time, in
threads (XLA compiles without holding Python's lock), in the order of the table, and
each scene's rows are printed as soon as its programs have compiled. Once all have,
each solve is timed (wall clock, the median of a few runs of the compiled solve,
listed below the table with the first call of each program: tracing, compilation
and one run). Compilation dominates the tour's run time (seconds per program; the
solves take milliseconds).

Compiled programs are kept in JAX's persistent compilation cache
(`constrained_jax.enable_compilation_cache`: `$XDG_CACHE_HOME/constrained_jax/jax` or
`~/.cache/constrained_jax/jax`), so a second run skips nearly all of the compilation;
`--no-compilation-cache` (or `CONSTRAINED_JAX_COMPILATION_CACHE=0`) turns it off.
Programs are compiled with XLA:CPU's older code generator
(`constrained_jax.settings.use_fast_compilation`: faster to compile, the same results
to round-off, some programs slower to run), and small loops (a single trajectory) into
one function each (`constrained_jax.settings.use_loop_kernels`: faster single
trajectories, and faster compilation too); `--xla-defaults` keeps XLA's defaults
(`benchmarks/README.md`, "XLA:CPU settings", measures both). The
diffrax solves are traced with the library's diffrax patch
(`constrained_jax.settings.use_diffrax_patch`: smaller programs, which the
compilation cache stores, for the diffrax release it was written for);
`--diffrax-defaults` runs diffrax unchanged.

Pictures need matplotlib (`pip install "constrained_jax[plot]"`); without it the
checks still run, and the pictures are skipped with a message saying so.
"""

import argparse
import importlib.util
import os
import statistics
import sys
import textwrap
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from . import tour


_DEFAULT_OUT = "constrained_jax_tour"
# What the tour's first run and a run with the compilation cache cost, as the tour
# says before it compiles: measured from a fresh clone on the machine named (the
# README's main-job command, then `constrained-jax tour` again; README.md quotes
# the run).
_FIRST_RUN_MINUTES = (1, 2)
_CACHED_SECONDS = (20, 40)
_MEASURED_ON = "2-core x86_64 CPU"


def _programs(jobs: list[tour.Job]) -> dict[tour.Program, tour.Job]:
    """Each program, in the order of the table, with the first job that calls it."""
    first = {}
    for job in jobs:
        first.setdefault(job.program, job)
    return first


def _first_call(program: tour.Program, job: tour.Job) -> float:
    """The seconds of the program's first call (tracing, compilation, one run)."""
    import jax

    start = time.perf_counter()
    jax.block_until_ready(program.fn(*job.inputs))
    return time.perf_counter() - start


def _time(job: tour.Job) -> float:
    """The median wall clock of `job.repeats` calls of the job's compiled solve."""
    import jax

    fn = job.program.fn
    times = []
    for _ in range(job.repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*job.inputs))
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def _first_run(programs: int, cache: Path | None, whole_tour: bool = True) -> str:
    """What the first run costs and that later runs reuse the compilation cache (in
    `cache`; `None`: off), said before the first compile."""
    text = f"The first run compiles {programs} programs"
    if whole_tour:
        low, high = _FIRST_RUN_MINUTES
        text += f": about {low}-{high} minutes on a {_MEASURED_ON}. "
    else:
        text += " (seconds each). "
    if cache is None:
        text += "The compilation cache is off: every run compiles them."
    else:
        text += f"Later runs read them from the compilation cache ({cache})"
        low, high = _CACHED_SECONDS
        text += f" and take about {low}-{high} seconds." if whole_tour else "."
    return textwrap.fill(text, tour.WIDTH)


def _code_generator(xla_defaults: bool) -> str:
    """Turns on XLA:CPU's older code generator and single-function loops unless
    `xla_defaults` (or the user's `XLA_FLAGS` choose), and says what compiles."""
    from ._code_generator import (
        _extra_options,
        _LOOP_OPTION,
        _user_choice,
        use_fast_compilation,
        use_loop_kernels,
    )

    if not xla_defaults:
        for turn_on in (use_fast_compilation, use_loop_kernels):
            with warnings.catch_warnings():
                # The user's `XLA_FLAGS` choose otherwise, or this jaxlib does not
                # know the flag: XLA's default, as the line printed says.
                warnings.simplefilter("ignore")
                try:
                    turn_on()
                except RuntimeError:
                    # `main` called in a process whose JAX backend has already
                    # started (a notebook, a test): its settings stay as they are.
                    pass
    flags = os.environ.get("XLA_FLAGS", "")
    parts = []
    if _user_choice(flags):
        parts.append("XLA:CPU's older code generator")
    limit = _extra_options(flags)[1].get(_LOOP_OPTION, "").strip()
    if limit not in ("", "0"):
        parts.append(f"loops up to {limit} bytes as one function")
    if not parts:
        return "XLA's defaults"
    return " and ".join(parts) + " (--xla-defaults: XLA's defaults)"


def _diffrax_patch(diffrax_defaults: bool) -> str:
    """Turns on the library's diffrax patch unless `diffrax_defaults`, and says
    whether diffrax runs patched."""
    from ._diffrax_integrate import diffrax_patch_on, use_diffrax_patch

    if not diffrax_defaults:
        with warnings.catch_warnings():
            # Another diffrax release: unchanged, as the line printed says.
            warnings.simplefilter("ignore")
            use_diffrax_patch()
    if diffrax_patch_on():
        return "diffrax patched (--diffrax-defaults: unchanged)"
    return "diffrax unchanged"


def _have_matplotlib() -> bool:
    return importlib.util.find_spec("matplotlib") is not None


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="constrained-jax",
        description=(
            "Constrained extremization, variational problems and constrained "
            "mechanics in JAX: the built-in scenes, each checked against its closed "
            "form."
        ),
        epilog=(
            "Each row of the table compares a computed number with the closed form "
            "and states its tolerance on the relative error (divided by the named "
            "scale where the closed form is zero); the exit status is 1 if any check "
            "fails. Pictures need matplotlib: pip install 'constrained_jax[plot]'. "
            "Compiled programs are kept in JAX's persistent compilation cache, so a "
            "second run skips most of the compilation (--no-compilation-cache), and "
            "compiled with XLA:CPU's older code generator, faster to compile, "
            "small loops into one function each (--xla-defaults), diffrax patched "
            "for smaller programs (--diffrax-defaults)."
        ),
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def output_options(p):
        p.add_argument(
            "--out",
            type=Path,
            default=Path(_DEFAULT_OUT),
            help=f"folder for the pictures (default ./{_DEFAULT_OUT}/)",
        )
        p.add_argument("--no-plots", action="store_true", help="draw no pictures")
        p.add_argument(
            "--no-compilation-cache",
            action="store_true",
            help=(
                "do not use JAX's persistent compilation cache (default: on, in "
                "$XDG_CACHE_HOME/constrained_jax/jax or ~/.cache/constrained_jax/jax;"
                " the environment variable CONSTRAINED_JAX_COMPILATION_CACHE=0 does "
                "the same)"
            ),
        )
        p.add_argument(
            "--xla-defaults",
            action="store_true",
            help=(
                "compile with XLA's default CPU settings (default: its older code "
                "generator, faster to compile, and small loops into one "
                "function each; see constrained_jax.settings.use_fast_compilation "
                "and constrained_jax.settings.use_loop_kernels)"
            ),
        )
        p.add_argument(
            "--diffrax-defaults",
            action="store_true",
            help=(
                "run diffrax unchanged (default: the library's diffrax patch, for "
                "the diffrax release it was written for: a smaller t1 floor and no "
                "host callbacks for save times the library has checked, so the "
                "compilation cache stores the dynamics programs; see "
                "constrained_jax.settings.use_diffrax_patch)"
            ),
        )
        p.add_argument(
            "--jobs",
            type=int,
            default=2,
            help="programs compiled at a time, in threads (default 2; 1: one by one)",
        )

    pictures = [s.picture for s in tour.SCENES.values() if s.picture]
    pictures.append(tour.WorkPrecision.picture)
    tour_parser = sub.add_parser(
        "tour",
        help="solve every built-in scene, check the closed forms, draw the pictures",
        description=(
            "Solve every built-in scene on its default parameters, print the table "
            "of checks as the scenes finish (quantity, computed, closed form, "
            "relative error, tolerance), the time of each compiled solve, write the "
            f"pictures ({', '.join(pictures)}) "
            "and exit with status 1 if any check fails. Compilation dominates the "
            "run time (seconds per program; the solves take milliseconds)."
        ),
    )
    output_options(tour_parser)
    scene_parser = sub.add_parser(
        "scene",
        help="run one scene with chosen parameters",
        description="Run one scene; `scene NAME --help` lists its parameters.",
    )
    scene_sub = scene_parser.add_subparsers(dest="name", required=True, metavar="NAME")
    for name, scene in tour.SCENES.items():
        p = scene_sub.add_parser(name, help=scene.doc, description=scene.doc)
        for param, declared in scene.params.items():
            p.add_argument(
                f"--{param}",
                type=float,
                default=declared.default,
                help=f"{declared.help} (default {declared.default:g})",
            )
        output_options(p)
    sub.add_parser("list", help="list the built-in scenes and their parameters")
    return parser


def main(argv: list[str] | None = None) -> int:
    ns = _parser().parse_args(argv)

    if ns.command == "list":
        for name, scene in tour.SCENES.items():
            params = " ".join(f"--{k} {p.default:g}" for k, p in scene.params.items())
            print(f"{name}\n    {scene.doc}\n    parameters: {params}")
        return 0

    start = time.perf_counter()
    import jax

    from . import enable_compilation_cache

    code_generator = _code_generator(ns.xla_defaults)
    diffrax_patch = _diffrax_patch(ns.diffrax_defaults)
    cache = None
    if not ns.no_compilation_cache:
        cache = enable_compilation_cache()
    jax.config.update("jax_enable_x64", True)
    plots = not ns.no_plots
    if plots and not _have_matplotlib():
        print(
            "matplotlib is not installed: the checks run, the pictures are skipped.\n"
            "For the pictures: pip install 'constrained_jax[plot]'\n"
        )
        plots = False

    study = None
    if ns.command == "tour":
        study = tour.WorkPrecision()
        scene_jobs = tour.tour_jobs()
        jobs = scene_jobs + study.jobs()
    else:
        scene = tour.SCENES[ns.name]
        scene_jobs = jobs = scene.jobs(**{k: getattr(ns, k) for k in scene.params})
    programs = _programs(jobs)
    print(_first_run(len(programs), cache, study is not None), end="\n\n", flush=True)

    # The programs compile `--jobs` at a time, in threads (XLA compiles without
    # holding Python's lock), in the order of the table; each job's rows are printed
    # as soon as its program has compiled. The solves are timed once every program
    # has compiled, so that no compilation competes with them.
    for program in programs:
        _ = program.fn  # build the jitted functions in this thread
    table = tour.Table()
    table.start()
    pictures = {}
    with ThreadPoolExecutor(max_workers=max(ns.jobs, 1)) as pool:
        first_calls = {
            program: pool.submit(_first_call, program, job)
            for program, job in programs.items()
        }
        for job in jobs:
            first_calls[job.program].result()
            out = jax.block_until_ready(job.program.fn(*job.inputs))
            rows, new_pictures = job.rows(out)
            table.add(job.label, rows, job.note)
            if job.draw:
                pictures |= new_pictures
        first_calls = {p.name: f.result() for p, f in first_calls.items()}
    for job in jobs:
        job.seconds = _time(job)
    if study is not None:
        table.add("work-precision", study.rows(), study.note)
        pictures |= study.pictures()

    solves = {}
    for job in scene_jobs:
        solves[job.label] = solves.get(job.label, 0.0) + job.seconds
    print()
    _print_wrapped(
        "solve time (compiled, median of 3 runs; a label's solves added):",
        [f"{label} {s * 1e3:.2g} ms;" for label, s in solves.items()],
    )
    _print_wrapped(
        f"compilation (first call of each program, {ns.jobs} at a time):",
        [f"{p} {s:.1f} s," for p, s in first_calls.items()],
    )
    if study is not None:
        print(study.summary())
    if plots and pictures:
        print()
        for name, draw in pictures.items():
            print(f"picture: {tour.save(ns.out, name, draw)}")
    print(f"\ntotal {time.perf_counter() - start:.1f} s, compilation included")
    _print_wrapped(f"compiled with {code_generator}; {diffrax_patch}")
    print("all checks passed" if table.ok else "SOME CHECKS FAILED")
    return 0 if table.ok else 1


def _print_wrapped(text: str, items: list[str] = ()) -> None:
    """`text`, then `items` (each kept on one line), wrapped to the tour's width."""
    if items:
        items = [*items[:-1], items[-1][:-1]]  # no separator after the last
    words = [text] + [item.replace(" ", "\xa0") for item in items]
    wrapped = textwrap.fill(
        " ".join(words), tour.WIDTH, subsequent_indent="  ", break_on_hyphens=False
    )
    print(wrapped.replace("\xa0", " "))


if __name__ == "__main__":
    sys.exit(main())
