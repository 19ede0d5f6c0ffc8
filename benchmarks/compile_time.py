"""Where the compile time of `simulate` goes.

For three programs -- (a) `jit(simulate)` of the two cylinders, attached (Tsit5) (and
(a') the same without the derived quantities, as `benchmarks/dynamics.py` saves, and
its floor: a plain `diffrax.diffeqsolve` of the hand-written right-hand side), (b)
the tour's two-cylinder program with the release event, (c) the tour's pendulum
program (Tsit5) -- reports the seconds of tracing + lowering
(`jax.jit(fn).lower(...)`) and of XLA's compilation (`.compile()`), wall clock and
CPU time of the process (less sensitive to a busy machine), the size of the
optimized HLO module (instructions, `while` loops, `conditional`s) and how many
times the Lagrangian is traced (calls of a Python wrapper around it while tracing).
Medians of `--repeats` runs, `jax.clear_caches()` and the library's cache of detected
sparsity patterns cleared before each (and no persistent compilation cache).

    python benchmarks/compile_time.py [--repeats 3] [--only a,a',floor,b,c]
        [--fast-compilation]

`--fast-compilation` calls `cjax.settings.use_fast_compilation()` (XLA:CPU's older code
generator) after the imports, before the first computation.

Writes `benchmarks/results/compile_time.json`.
"""

import argparse
import re
import statistics
import time
from pathlib import Path

import jax


jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from _common import fresh_caches, write_cases  # noqa: E402

import constrained_jax as cjax  # noqa: E402
from constrained_jax.scenes import (  # noqa: E402
    pendulum as pendulum_scene,
    two_cylinders as cylinders_scene,
)
from constrained_jax.tour import (  # noqa: E402
    pendulum as pendulum_tour,
    two_cylinders as cylinders_tour,
)


RESULTS = Path(__file__).parent / "results" / "compile_time.json"


class _Counted:
    """Patches `module.lagrangian` with a wrapper that counts its calls (made while
    tracing only: the compiled program does not call Python)."""

    def __init__(self, module):
        self.module = module
        self.calls = 0

    def __enter__(self):
        self.original = original = self.module.lagrangian

        def counted(*args):
            self.calls += 1
            return original(*args)

        self.module.lagrangian = counted
        return self

    def __exit__(self, *exc):
        self.module.lagrangian = self.original


def _cylinders_attached(saveat=cjax.SaveAt(t1=True)):
    args = cylinders_scene.default_args()
    q0, qd0 = cylinders_scene.state(jnp.asarray(0.2), jnp.asarray(0.0), args)

    def run(q0, qd0, args):
        return cjax.simulate(
            cylinders_scene.system(),
            (0.0, 0.8),
            q0,
            qd0,
            args,
            solver=diffrax.Tsit5(),
            stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-10),
            saveat=saveat,
        )

    return cylinders_scene, run, (q0, qd0, args)


def _cylinders_lean():
    # (a) with `benchmarks/dynamics.py`'s `SaveAt`: nothing derived is computed.
    return _cylinders_attached(
        cjax.SaveAt(t1=True, multipliers=False, energy=False, violation=False)
    )


def _cylinders_floor():
    # The floor: a plain `diffrax.diffeqsolve` of the hand-written right-hand side,
    # with the solver, controller and saves of (a').
    from dynamics import cylinders_accelerations_by_hand

    module, _, inputs = _cylinders_attached()

    def field(t, y, args):
        q, qd = y
        return qd, cylinders_accelerations_by_hand(q, qd, args)[0]

    def run(q0, qd0, args):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(field),
            diffrax.Tsit5(),
            0.0,
            0.8,
            None,
            (q0, qd0),
            args,
            stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-10),
            saveat=diffrax.SaveAt(t1=True),
            throw=False,
        )
        return sol

    return module, run, inputs


def _cylinders_release():
    # The tour's program and the inputs of its default job.
    (job,) = cylinders_tour.SCENE.jobs()
    return cylinders_scene, job.program.make(), job.inputs


def _pendulum():
    job = next(
        job for job in pendulum_tour.SCENE.jobs() if job.program is pendulum_tour.TSIT5
    )
    return pendulum_scene, job.program.make(), job.inputs


CASES = {
    "a": ("two cylinders attached, Tsit5", _cylinders_attached),
    "a'": ("two cylinders attached, Tsit5, nothing derived saved", _cylinders_lean),
    "floor": ("floor of (a'): diffeqsolve of the hand-written field", _cylinders_floor),
    "b": ("two cylinders with the release event (tour)", _cylinders_release),
    "c": ("pendulum, Tsit5 (tour)", _pendulum),
}


def hlo_counts(text: str) -> dict:
    """Instructions, `while` loops and `conditional`s of an optimized HLO module."""
    pattern = re.compile(r"\s+(ROOT )?%?[\w.\-]+ = ")
    instructions = [line for line in text.splitlines() if pattern.match(line)]
    return {
        "hlo_instructions": len(instructions),
        "hlo_while": sum(" while(" in line for line in instructions),
        "hlo_conditional": sum(" conditional(" in line for line in instructions),
        "hlo_lines": len(text.splitlines()),
    }


def measure(make, repeats: int) -> dict:
    runs = []
    for _ in range(repeats):
        fresh_caches()
        module, fn, inputs = make()
        with _Counted(module) as counter:
            start, cpu_start = time.perf_counter(), time.process_time()
            lowered = jax.jit(fn).lower(*inputs)
            traced, cpu_traced = time.perf_counter(), time.process_time()
            compiled = lowered.compile()
            done, cpu_done = time.perf_counter(), time.process_time()
        runs.append(
            {
                "trace_lower_s": traced - start,
                "compile_s": done - traced,
                "trace_lower_cpu_s": cpu_traced - cpu_start,
                "compile_cpu_s": cpu_done - cpu_traced,
                "lagrangian_traces": counter.calls,
                **hlo_counts(compiled.as_text()),
            }
        )
        out = jax.block_until_ready(compiled(*inputs))
        plain = isinstance(out, diffrax.Solution)
        success = (diffrax if plain else cjax).RESULTS.successful
        assert out.result == success, out.result
    summary = {
        key: statistics.median(run[key] for run in runs)
        for key in ("trace_lower_s", "compile_s", "trace_lower_cpu_s", "compile_cpu_s")
    }
    summary["total_s"] = summary["trace_lower_s"] + summary["compile_s"]
    summary |= {k: v for k, v in runs[-1].items() if not k.endswith("_s")}
    summary["runs"] = runs
    return summary


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--only", default="a,a',floor,b,c")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument(
        "--fast-compilation",
        action="store_true",
        help="XLA:CPU's older code generator (cjax.settings.use_fast_compilation())",
    )
    ns = parser.parse_args()
    if ns.fast_compilation:
        assert cjax.settings.use_fast_compilation()
    jax.config.update("jax_enable_compilation_cache", False)
    results = {}
    for key in ns.only.split(","):
        name, make = CASES[key]
        results[key] = {"name": name, **measure(make, ns.repeats)}
        r = results[key]
        print(
            f"({key}) {name}: trace+lower {r['trace_lower_s']:.2f} s, compile "
            f"{r['compile_s']:.2f} s (CPU {r['trace_lower_cpu_s']:.2f} s, "
            f"{r['compile_cpu_s']:.2f} s), {r['hlo_instructions']} HLO instructions, "
            f"{r['hlo_while']} while, {r['hlo_conditional']} conditional, "
            f"Lagrangian traced {r['lagrangian_traces']} times"
        )
    write_cases(ns.out, results)


if __name__ == "__main__":
    main()
