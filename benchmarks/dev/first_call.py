"""The first call of a program in a fresh process, for two git revisions.

What a user waits for when a notebook or a script starts: tracing and lowering
(`jax.jit(fn).lower(...)`) and XLA's compilation (`.compile()`) of the first program
that uses a system, with nothing cached yet - not JAX's caches, not the library's
structure detection (`compile_time.py` takes medians of repeats in one process, so
only its first repeat detects the structure). Each measurement is a new Python process
(after a warm-up `jit` of a tiny program, so that JAX's own start is not counted),
alternating between revision A and B, each exported with `git archive` (as in
`ab.py`) into a folder of its own that the process puts first on its path.

Cases:

- `cylinders`: `simulate` of the two cylinders attached (Tsit5, `SaveAt(t1=True)`
  with everything derived), `compile_time.py`'s (a);
- `pendulum`: the tour's pendulum program, `compile_time.py`'s (c);
- `release`: the tour's two-cylinder program with the release, `compile_time.py`'s
  (b);
- `floor`: `diffeqsolve` of the hand-written two-cylinder field, `compile_time.py`'s
  floor (the same in both revisions: it shows the machine's drift);
- `chain4`, `chain4-lapack`: one trajectory of the 4-link chain (`chain.py`) with the
  default saddle-point solver and with LAPACK's LU (`FullKKTLU(unroll_max=0)`), in one
  process, that order (`targets.py`'s compile ratio).

    python benchmarks/dev/first_call.py --a REV --b HEAD [--processes 3]

Writes `benchmarks/dev/results/first_call.json`: every process's seconds and the
medians.
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from ab import export


HERE = Path(__file__).resolve().parent
BENCHMARKS = HERE.parent  # `compile_time.py`, `chain.py`

_CHILD = r"""
import json, sys, time
sys.path.insert(0, {bench!r})
sys.path.insert(0, {folder!r})
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import constrained_jax as cjax
assert cjax.__file__.startswith({folder!r}), cjax.__file__
jax.jit(lambda x: jax.lax.fori_loop(0, 3, lambda i, c: jnp.sin(c) @ c, x))(
    jnp.ones((4, 4))
).block_until_ready()
import compile_time, chain


def first(make):
    module, fn, inputs = make()
    jax.block_until_ready(inputs)
    start = time.perf_counter()
    lowered = jax.jit(fn).lower(*inputs)
    traced = time.perf_counter()
    lowered.compile()
    done = time.perf_counter()
    return {{"trace_lower_s": traced - start, "compile_s": done - traced}}


out = {{}}
case = {case!r}
if case == "cylinders":
    out[case] = first(compile_time.CASES["a"][1])
elif case == "pendulum":
    out[case] = first(compile_time.CASES["c"][1])
elif case == "release":
    out[case] = first(compile_time.CASES["b"][1])
elif case == "floor":
    out[case] = first(compile_time.CASES["floor"][1])
else:
    default = chain.trajectory(4, None, 3)
    lapack = chain.trajectory(4, cjax.FullKKTLU(unroll_max=0), 3)
    for key, row in (("chain4", default), ("chain4-lapack", lapack)):
        out[key] = {{k: row[k] for k in ("trace_lower_s", "compile_s")}}
print("RESULT" + json.dumps(out))
"""


def run_child(folder: str, case: str) -> dict:
    code = _CHILD.format(bench=str(BENCHMARKS), folder=folder, case=case)
    env = {**os.environ, "JAX_ENABLE_COMPILATION_CACHE": "false"}
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env
    )
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT")]
    if proc.returncode or not lines:
        raise RuntimeError(proc.stderr[-3000:])
    return json.loads(lines[-1][len("RESULT") :])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--a", required=True)
    parser.add_argument("--b", default="HEAD")
    parser.add_argument("--processes", type=int, default=3)
    parser.add_argument("--cases", default="cylinders,pendulum,chain")
    parser.add_argument(
        "--out", type=Path, default=HERE / "results" / "first_call.json"
    )
    opts = parser.parse_args()
    runs: dict = {"a": [], "b": []}
    with tempfile.TemporaryDirectory() as folder:
        for rev in ("a", "b"):
            # Each revision in a folder of its own, under its own name: every
            # measurement is a process of its own, which imports one of them.
            os.makedirs(os.path.join(folder, rev))
            export(getattr(opts, rev), "constrained_jax", os.path.join(folder, rev))
        for _ in range(opts.processes):
            for case in opts.cases.split(","):
                for rev in ("a", "b"):
                    result = run_child(os.path.join(folder, rev), case)
                    runs[rev].append(result)
                    for key, row in result.items():
                        tl, c = row["trace_lower_s"], row["compile_s"]
                        print(
                            f"{rev} {key:14s} trace+lower {tl:5.2f} s  compile"
                            f" {c:5.2f} s  total {tl + c:5.2f} s",
                            flush=True,
                        )
    medians: dict = {}
    for rev, results in runs.items():
        keys = sorted({k for r in results for k in r})
        for key in keys:
            rows = [r[key] for r in results if key in r]
            medians.setdefault(key, {})[rev] = {
                part: statistics.median(row[part] for row in rows)
                for part in ("trace_lower_s", "compile_s")
            }
    print(
        "\n| case | A: trace+lower / compile | B: trace+lower / compile | total B / A |"
    )
    print("|---|---:|---:|---:|")
    for key, by_rev in medians.items():
        a, b = by_rev["a"], by_rev["b"]
        ratio = (b["trace_lower_s"] + b["compile_s"]) / (
            a["trace_lower_s"] + a["compile_s"]
        )
        print(
            f"| {key} | {a['trace_lower_s']:.2f} / {a['compile_s']:.2f} s"
            f" | {b['trace_lower_s']:.2f} / {b['compile_s']:.2f} s | {ratio:.2f} |"
        )
    opts.out.parent.mkdir(parents=True, exist_ok=True)
    opts.out.write_text(
        json.dumps(
            {"a": opts.a, "b": opts.b, "runs": runs, "medians": medians}, indent=1
        )
    )
    print(f"wrote {opts.out}")


if __name__ == "__main__":
    main()
