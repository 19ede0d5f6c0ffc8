"""What one KKT solve costs XLA to compile, part by part.

A `simulate` program holds one copy of the equations of motion per place that calls
them (the stages, the initial step, the release event and its root find, the samples
of the watched multiplier, the saved multipliers): the release program of the tour
has nine. This script compiles one solve of the two cylinders (3 + 2 unknowns,
diagonal `M`, the default `cjax.Automatic()`) and its parts, each alone:

- `default`: `system.solve_accelerations` as `simulate` calls it;
- `assembly`: `M`, `Q - c`, `A`, the bias and the pattern check only;
- `fast path`: the assembly and the diagonal range-space method, no fallback;
- `cond, trivial fallback`: the diagonal solve with its `lax.cond` and a fallback
  that returns zeros (the cost of the branch itself);
- `cond, RangeSpaceLDL fallback`: the same with the default's fallback (the unrolled
  range-space method, for a coupled mass that vanishes at run time);
- `cond, LAPACK fallback`: the same with `FullKKTLU(unroll_max=0)` as the fallback.

Medians of `--repeats` compilations (`jax.clear_caches()` before each; XLA's own
flags as the user has them), and the optimized HLO's instruction count.

    python benchmarks/dev/solve_compile.py [--repeats 5]

Writes `benchmarks/dev/results/solve_compile.json`.
"""

import argparse
import statistics
import sys
import time
from pathlib import Path

import jax


jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/

import jax.numpy as jnp  # noqa: E402
from _common import write_cases  # noqa: E402
from compile_time import hlo_counts  # noqa: E402

import constrained_jax as cjax  # noqa: E402
from constrained_jax._solver import diagonal  # noqa: E402
from constrained_jax.scenes import two_cylinders  # noqa: E402


RESULTS = Path(__file__).parent / "results" / "solve_compile.json"


def _cases(system):
    t = jnp.asarray(0.0)

    def with_fallback(fallback):
        def fn(q, qd, args):
            mass, rhs, jac, bias, _ = system._equations(q, qd, t, args)
            return diagonal.diagonal_solve(mass, jac, rhs, bias, fallback)

        return fn

    def trivial(mass, jac, rhs, bias):
        return jnp.zeros_like(rhs), jnp.zeros_like(bias), jnp.array(True)

    def fast_path(q, qd, args):
        mass, rhs, jac, bias, _ = system._equations(q, qd, t, args)
        return diagonal.diagonal_range_space(mass, jac, rhs, bias)

    return {
        "default": lambda q, qd, args: system.solve_accelerations(q, qd, t, args),
        "assembly": lambda q, qd, args: system._equations(q, qd, t, args),
        "fast path": fast_path,
        "cond, trivial fallback": with_fallback(trivial),
        "cond, RangeSpaceLDL fallback": with_fallback(cjax.RangeSpaceLDL().solve),
        "cond, LAPACK fallback": with_fallback(cjax.FullKKTLU(unroll_max=0).solve),
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", type=Path, default=RESULTS)
    ns = parser.parse_args()
    jax.config.update("jax_enable_compilation_cache", False)
    args = two_cylinders.default_args()
    q0, qd0 = two_cylinders.state(jnp.asarray(0.2), jnp.asarray(0.0), args)
    system = two_cylinders.system()
    results = {}
    for name, fn in _cases(system).items():
        times = []
        for _ in range(ns.repeats):
            jax.clear_caches()
            lowered = jax.jit(fn).lower(q0, qd0, args)
            start = time.perf_counter()
            compiled = lowered.compile()
            times.append(time.perf_counter() - start)
        results[name] = {
            "compile_s": statistics.median(times),
            "times_s": times,
            "hlo_instructions": hlo_counts(compiled.as_text())["hlo_instructions"],
        }
        print(
            f"{name:32s} compile {results[name]['compile_s']:.3f} s, "
            f"{results[name]['hlo_instructions']} HLO instructions"
        )
    write_cases(ns.out, results)


if __name__ == "__main__":
    main()
