"""Timing and provenance helpers shared by the benchmark scripts.

Every JAX time is taken after ahead-of-time compilation
(`jax.jit(fn).lower().compile()`) and one warm-up call, each call ended by
`block_until_ready`; compile time is reported separately.
"""

import datetime
import os
import platform
import re
import statistics
import subprocess
import time

import jax
import jaxlib
import numpy as np

import constrained_jax as cjax


def fresh_caches() -> None:
    """Forget every compiled program and traced function (`jax.clear_caches()`) and
    the library's cache of detected sparsity patterns, so that the next call of a
    system is a first call: its trace includes structure detection."""
    from constrained_jax import _structure

    jax.clear_caches()
    with _structure._LOCK:
        _structure._CACHE.clear()


def memory_analysis(compiled) -> dict:
    try:
        stats = compiled.memory_analysis()
    except Exception:  # not every backend reports it
        return {}
    if stats is None:
        return {}
    out = {}
    for name in (
        "argument_size_in_bytes",
        "output_size_in_bytes",
        "temp_size_in_bytes",
    ):
        value = getattr(stats, name, None)
        if value is not None:
            out[name] = int(value)
    return out


def time_jax(fn, *args, repeats: int):
    """AOT-compile `jax.jit(fn)` for `args`, then time `repeats` calls after a warm-up.

    Returns `(output, info)`; `info` holds the trace/lower and compile times, the
    first-call time (trace + lower + compile + first run, what a user waits for on
    the first call), the median and all post-compilation times, and XLA's buffer
    sizes.
    """
    t0 = time.perf_counter()
    lowered = jax.jit(fn).lower(*args)
    t1 = time.perf_counter()
    compiled = lowered.compile()
    t2 = time.perf_counter()
    out = jax.block_until_ready(compiled(*args))
    t3 = time.perf_counter()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        out = jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - start)
    info = {
        "trace_lower_s": t1 - t0,
        "compile_s": t2 - t1,
        "first_call_s": t3 - t0,
        "median_s": statistics.median(times),
        "times_s": times,
        "xla_memory": memory_analysis(compiled),
        "lapack_calls_in_hlo": sorted(
            set(re.findall(r"custom_call @(lapack_\w+)", lowered.as_text()))
        ),
    }
    return out, info


def time_jax_interleaved(fns: dict, *args, repeats: int, block: int = 1):
    """Like `time_jax` for several functions of the same inputs, timed in turn.

    All are compiled first; then each of the `repeats` rounds calls every function
    once (every other round in reverse order), so that a slow period of a shared,
    noisy machine hits all of them alike and the ratios of the medians stay
    meaningful. Returns `(outputs, infos)`, dicts keyed like `fns`.

    With `block > 1` each round calls every function `block` times in a row and
    records all but the first of them: each function's time in its own steady state,
    as a loop or a sweep calling it sees it. With XLA's threads a single call's time
    depends on the program called before it. Neither the reversed rounds nor blocks
    remove that entirely (identical programs can differ within one process): compare
    such programs over several processes.
    """
    if block < 1:
        raise ValueError(f"block must be >= 1, got {block}")
    compiled, infos, outputs = {}, {}, {}
    for name, fn in fns.items():
        t0 = time.perf_counter()
        lowered = jax.jit(fn).lower(*args)
        t1 = time.perf_counter()
        compiled[name] = lowered.compile()
        t2 = time.perf_counter()
        outputs[name] = jax.block_until_ready(compiled[name](*args))
        t3 = time.perf_counter()
        infos[name] = {
            "trace_lower_s": t1 - t0,
            "compile_s": t2 - t1,
            "first_call_s": t3 - t0,
            "times_s": [],
            "xla_memory": memory_analysis(compiled[name]),
            "lapack_calls_in_hlo": sorted(
                set(re.findall(r"custom_call @(lapack_\w+)", lowered.as_text()))
            ),
        }
    names = list(fns)
    for r in range(repeats):
        # Every other round in reverse order, so that each function follows each
        # of its neighbours (a call's time can depend on the call before it).
        for name in names if r % 2 == 0 else names[::-1]:
            for call in range(block):
                start = time.perf_counter()
                jax.block_until_ready(compiled[name](*args))
                if block == 1 or call > 0:
                    infos[name]["times_s"].append(time.perf_counter() - start)
    for info in infos.values():
        info["block"] = block
        info["median_s"] = statistics.median(info["times_s"])
    return outputs, infos


def time_loop(solve_one, problems, repeats: int):
    """Median wall time of `[solve_one(p) for p in problems]` over `repeats` runs."""
    times = []
    results = None
    for _ in range(repeats):
        start = time.perf_counter()
        results = [solve_one(p) for p in problems]
        times.append(time.perf_counter() - start)
    return results, statistics.median(times), times


def machine_info(**versions: str) -> dict:
    """The machine, the versions (plus `versions`, e.g. `scipy=...`), the commit."""
    try:
        commit = subprocess.run(
            ["git", "describe", "--always", "--dirty"],
            capture_output=True,
            text=True,
            check=False,
            cwd=os.path.dirname(os.path.abspath(__file__)),
        ).stdout.strip()
    except OSError:
        commit = ""
    return {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "python": platform.python_version(),
        "cpu_count": os.cpu_count(),
        "jax_backend": jax.default_backend(),
        "jax_devices": [str(d) for d in jax.devices()],
        "versions": {
            "jax": jax.__version__,
            "jaxlib": jaxlib.__version__,
            "numpy": np.__version__,
            "constrained_jax": cjax.__version__,
            **versions,
        },
        "git": commit,
    }


def write_cases(path, cases: dict) -> None:
    """Writes `{"machine": machine_info(), "cases": cases}` as JSON to `path` (a
    `pathlib.Path`, its folder created) and says so."""
    import json

    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(
        json.dumps({"machine": machine_info(), "cases": cases}, indent=2) + "\n"
    )
    print(f"wrote {path}")


def pyplot():
    """`matplotlib.pyplot` with the non-GUI backend, or `None` (and a message)
    without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("no matplotlib: no plot")
        return None
    return plt
