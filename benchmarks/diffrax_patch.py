"""What the opt-in diffrax patch (`cjax.settings.use_diffrax_patch()`) buys: the first
call of `compile_time.py`'s programs with the patch off and on.

Each measurement is a new Python process (after a warm-up `jit` of a tiny program),
alternating off and on, of this checkout: the seconds of tracing and lowering
(`jax.jit(fn).lower(...)`) and of XLA's compilation (`.compile()`), wall clock and CPU
time of the process (steadier on a busy machine), the instructions of the optimised
HLO module, and the `nextafter`s of the lowered program (diffrax's `t1` floor: 100 per
solve with a traced end time, unpatched). Cases: `compile_time.py`'s (c) the tour's
pendulum, (b) the tour's two-cylinder release program, and `floor`, a plain
`diffrax.diffeqsolve` that the patch does not touch (the machine's drift). No
persistent compilation cache.

    python benchmarks/diffrax_patch.py [--processes 5] [--cases c,b,floor]

Writes `results/diffrax_patch.json`: every process's numbers and the medians.
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path


HERE = Path(__file__).parent

_CHILD = r"""
import json, sys, time
sys.path.insert(0, {bench!r})
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import constrained_jax as cjax
if {on!r}:
    assert cjax.settings.use_diffrax_patch()
jax.jit(lambda x: jax.lax.fori_loop(0, 3, lambda i, c: jnp.sin(c) @ c, x))(
    jnp.ones((4, 4))
).block_until_ready()
import compile_time
module, fn, inputs = compile_time.CASES[{case!r}][1]()
jax.block_until_ready(inputs)
wall, cpu = time.perf_counter(), time.process_time()
lowered = jax.jit(fn).lower(*inputs)
wall_lowered, cpu_lowered = time.perf_counter(), time.process_time()
compiled = lowered.compile()
wall_compiled, cpu_compiled = time.perf_counter(), time.process_time()
print("RESULT" + json.dumps({{
    "trace_lower_s": wall_lowered - wall,
    "trace_lower_cpu_s": cpu_lowered - cpu,
    "compile_s": wall_compiled - wall_lowered,
    "compile_cpu_s": cpu_compiled - cpu_lowered,
    "hlo_instructions": compile_time.hlo_counts(compiled.as_text())["hlo_instructions"],
    "nextafter": lowered.as_text().count("next_after"),
}}))
"""


def run_child(case: str, on: bool) -> dict:
    code = _CHILD.format(bench=str(HERE), on=on, case=case)
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
    parser.add_argument("--processes", type=int, default=5)
    parser.add_argument("--cases", default="c,b,floor")
    parser.add_argument(
        "--out", type=Path, default=HERE / "results" / "diffrax_patch.json"
    )
    opts = parser.parse_args()
    runs: dict = {}
    for _ in range(opts.processes):
        for case in opts.cases.split(","):
            for on in (False, True):
                row = run_child(case, on)
                runs.setdefault(f"{case} {'on' if on else 'off'}", []).append(row)
                print(
                    f"{case:6s} {'on ' if on else 'off'} "
                    + "  ".join(f"{k} {v:.2f}" for k, v in row.items()),
                    flush=True,
                )
    medians = {
        key: {k: statistics.median(r[k] for r in rows) for k in rows[0]}
        for key, rows in runs.items()
    }
    print(
        "\n| case | patch | trace+lower wall / CPU | compile wall / CPU "
        "| HLO instructions | nextafter |"
    )
    print("|---|---|---:|---:|---:|---:|")
    for key, m in medians.items():
        case, on = key.split()
        print(
            f"| {case} | {on} | {m['trace_lower_s']:.2f} / "
            f"{m['trace_lower_cpu_s']:.2f} s | {m['compile_s']:.2f} / "
            f"{m['compile_cpu_s']:.2f} s | {m['hlo_instructions']:.0f} "
            f"| {m['nextafter']:.0f} |"
        )
    opts.out.parent.mkdir(parents=True, exist_ok=True)
    opts.out.write_text(json.dumps({"runs": runs, "medians": medians}, indent=1))
    print(f"wrote {opts.out}")


if __name__ == "__main__":
    main()
