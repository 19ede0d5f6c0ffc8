"""Benchmark `constrained_jax.sweep`: chunking overhead, memory bound, checkpoints.

`cjax.sweep(fn, inputs, batch_size=B)` evaluates `fn` over `N` inputs in chunks of
`B` rows with one compiled `jax.jit(jax.vmap(fn))`, moving every chunk's outputs to
host numpy before the next one is sent. Two functions of one input each:

- **pendulum accelerations** (cheap, a few microseconds per input): `(theta,
  thetadot) -> (qdd, lambda)` of the Cartesian pendulum (`cjax.scenes.pendulum`),
  by `LagrangianSystem.solve_accelerations`; the worst case for per-chunk overhead.
- **cylinder extremize** (costlier): one `cjax.extremize` of
  `cjax.scenes.cylinder_volume` per `(b, l)`, returning `(a, h)` and the multiplier.

Three measurements, in one run:

1. **Overhead.** The time of a whole `cjax.sweep(fn, inputs, batch_size=B,
   progress=False)` call against one AOT-compiled `jax.jit(jax.vmap(fn))` on all `N`
   inputs at once (numpy in, `device_put`, call, `np.asarray` out: host to host like
   `sweep`; its compile is excluded). `sweep` traces and compiles its chunk program
   on its first call with a given `fn` (later calls reuse it; the repetitions here
   pass the same `fn`, so the medians are of such calls); its time is split: a
   timing wrapper around `jax.stages.Lowered.compile` (it only records when the
   compilation `sweep` starts returns; nothing else changes) gives the setup
   (input checks, trace, lower, compile; with a checkpoint also the fingerprints)
   and the chunk loop after it.
   Both are reported, as ratios to the plain call.
2. **Memory.** XLA's buffer sizes (`compiled.memory_analysis()`: arguments, outputs,
   temporaries) of the chunk program that `sweep` itself compiled (caught by the same
   wrapper) against those of the plain `jit(vmap(fn))` compiled for all `N`, for
   several `N` at `B = 1024`. (The host-side result, `N` rows of numpy, grows with `N`
   in both cases; this is device memory.)
3. **Checkpoint overhead.** The same sweep with `checkpoint=<a fresh temporary
   folder>` (one `.npz` per chunk, written atomically with `fsync`) against none, and
   the time to resume from a complete checkpoint (every chunk read back and checked).

Medians of several repetitions, the variants interleaved within each repetition so
that a slow period of a shared machine hits all alike. Outputs are checked against
the plain call (and the closed forms). Run with `--quick` for a smoke test.

    python benchmarks/sweep.py [--quick] [--out benchmarks/results]
"""

import argparse
import json
import os
import statistics
import tempfile
import time

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import machine_info, memory_analysis  # noqa: E402

import constrained_jax as cjax  # noqa: E402
from constrained_jax.scenes import (  # noqa: E402
    cylinder_volume as cylv,
    pendulum as pend,
)


SEED = 0


# ---------------------------------------------------------------------------------
# The functions swept and their inputs
# ---------------------------------------------------------------------------------


def pendulum_fn():
    system = pend.system()
    args = pend.default_args()
    t = jnp.asarray(0.0)

    def fn(x):
        q, qd = pend.state(x["theta"], x["thetadot"], args)
        qdd, lam = system.solve_accelerations(q, qd, t, args)[:2]
        return {"qdd": qdd, "multiplier": lam}

    return fn


def pendulum_inputs(n):
    rng = np.random.default_rng(SEED)
    return {
        "theta": rng.uniform(-2.0, 2.0, n),
        "thetadot": rng.normal(0.0, 2.0, n),
    }


def pendulum_check(inputs, out) -> float:
    """Max abs deviation from the closed forms: `thetaddot = -(g/l) sin theta`
    (tangential component of qdd) and `lambda = -T`."""
    args = pend.default_args()
    theta, thetadot = inputs["theta"], inputs["thetadot"]
    tangent = np.stack([np.cos(theta), np.sin(theta)], axis=1)
    thetaddot = np.sum(out["qdd"] * tangent, axis=1)
    expected = np.asarray(pend.angular_acceleration(theta, args))
    tension = np.asarray(pend.tension(theta, thetadot, args))
    return float(
        max(
            np.max(np.abs(thetaddot - expected)),
            np.max(np.abs(out["multiplier"][:, 0] + tension) / (1 + tension)),
        )
    )


def cylinder_fn():
    def fn(x):
        sol = cylv.solve(x["b"], x["l"], throw=False)
        return {"x": sol.x, "multiplier": sol.multipliers, "volume": sol.value}

    return fn


def cylinder_inputs(n):
    rng = np.random.default_rng(SEED)
    return {
        "b": 10.0 ** rng.uniform(-2.0, 2.0, n),
        "l": 10.0 ** rng.uniform(-1.0, 1.0, n),
    }


def cylinder_check(inputs, out) -> float:
    """Max relative deviation of `a`, `h`, `lambda`, `V` from the closed form."""
    ref = cylv.closed_form(inputs["b"], inputs["l"])
    errors = [
        np.abs(out["x"][:, 0] - ref["a"]) / np.abs(ref["a"]),
        np.abs(out["x"][:, 1] - ref["h"]) / np.abs(ref["h"]),
        np.abs(out["multiplier"][:, 0] - ref["multiplier"]) / np.abs(ref["multiplier"]),
        np.abs(out["volume"] - ref["volume"]) / np.abs(ref["volume"]),
    ]
    return float(max(np.max(e) for e in errors))


FUNCTIONS = {
    "pendulum accelerations": (pendulum_fn, pendulum_inputs, pendulum_check),
    "cylinder extremize": (cylinder_fn, cylinder_inputs, cylinder_check),
}


# ---------------------------------------------------------------------------------
# Timing
# ---------------------------------------------------------------------------------


class CompileWatch:
    """Records when each `jax.stages.Lowered.compile` returns, and what it compiled.

    Installed around `cjax.sweep` calls only, to split a call into setup (up to the
    end of its compilation) and the chunk loop; the wrapped method is unchanged.
    """

    def __init__(self):
        self.original = jax.stages.Lowered.compile
        self.ends = []
        self.compiled = []

    def __enter__(self):
        original = self.original
        watch = self

        def compile(self, *args, **kwargs):
            out = original(self, *args, **kwargs)
            watch.ends.append(time.perf_counter())
            watch.compiled.append(out)
            return out

        jax.stages.Lowered.compile = compile
        return self

    def __exit__(self, *exc):
        jax.stages.Lowered.compile = self.original


def timed_sweep(fn, inputs, **kwargs):
    """`(outputs, total_s, loop_s, compiled)` of one `cjax.sweep` call."""
    with CompileWatch() as watch:
        start = time.perf_counter()
        out = cjax.sweep(fn, inputs, progress=False, **kwargs)
        end = time.perf_counter()
    if len(watch.ends) > 1:
        raise AssertionError(f"sweep compiled {len(watch.ends)} programs, not one")
    if watch.ends:
        return out, end - start, end - watch.ends[0], watch.compiled[0]
    return out, end - start, None, None  # everything read from a checkpoint


def plain_program(fn, inputs):
    """AOT `jax.jit(jax.vmap(fn))` for all of `inputs`, and its compile time."""
    start = time.perf_counter()
    compiled = jax.jit(jax.vmap(fn)).lower(inputs).compile()
    return compiled, time.perf_counter() - start


def plain_call(compiled, inputs):
    """Host to host: `device_put`, the call, outputs to numpy."""
    out = compiled(jax.device_put(inputs))
    return jax.tree.map(np.asarray, out)


def max_diff(a, b) -> float:
    return float(
        max(
            np.max(np.abs(x - y))
            for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True)
        )
    )


def overhead_benchmark(name, n, batch_sizes, repeats, checkpoint_batch) -> dict:
    make_fn, make_inputs, check = FUNCTIONS[name]
    fn = make_fn()
    inputs = make_inputs(n)
    compiled, plain_compile_s = plain_program(fn, inputs)
    reference = plain_call(compiled, inputs)  # warm-up
    closed_form_error = check(inputs, reference)

    variants = [f"sweep B={b}" for b in batch_sizes] + [
        f"sweep B={checkpoint_batch} checkpoint",
        f"sweep B={checkpoint_batch} resume (complete checkpoint)",
    ]
    times = {"plain jit(vmap)": []}
    times.update({v: [] for v in variants})
    loops = {v: [] for v in variants}
    agreement = {}
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(repeats):
            start = time.perf_counter()
            plain_call(compiled, inputs)
            times["plain jit(vmap)"].append(time.perf_counter() - start)
            for b in batch_sizes:
                out, total, loop, _ = timed_sweep(fn, inputs, batch_size=b)
                times[f"sweep B={b}"].append(total)
                loops[f"sweep B={b}"].append(loop)
                agreement[f"sweep B={b}"] = max_diff(out, reference)
            folder = os.path.join(tmp, f"rep{rep}")  # fresh: nothing to resume
            out, total, loop, _ = timed_sweep(
                fn, inputs, batch_size=checkpoint_batch, checkpoint=folder
            )
            times[variants[-2]].append(total)
            loops[variants[-2]].append(loop)
            agreement[variants[-2]] = max_diff(out, reference)
            out, total, loop, _ = timed_sweep(
                fn, inputs, batch_size=checkpoint_batch, checkpoint=folder
            )
            if loop is not None:
                raise AssertionError("resuming a complete checkpoint compiled")
            times[variants[-1]].append(total)
            agreement[variants[-1]] = max_diff(out, reference)
    plain = statistics.median(times["plain jit(vmap)"])
    rows = {
        "plain jit(vmap)": {
            "median_s": plain,
            "times_s": times["plain jit(vmap)"],
            "compile_s (excluded)": plain_compile_s,
        }
    }
    for v in variants:
        total = statistics.median(times[v])
        row = {
            "median_total_s": total,
            "total_ratio_to_plain": total / plain,
            "times_total_s": times[v],
            "max_abs_diff_to_plain": agreement[v],
        }
        if loops[v]:
            loop = statistics.median(loops[v])
            row.update(
                {
                    "median_loop_s": loop,
                    "loop_ratio_to_plain": loop / plain,
                    "median_setup_incl_compile_s": statistics.median(
                        [t - x for t, x in zip(times[v], loops[v], strict=True)]
                    ),
                    "times_loop_s": loops[v],
                }
            )
        rows[v] = row
    ck, no_ck = rows[variants[-2]], rows[f"sweep B={checkpoint_batch}"]
    return {
        "n": n,
        "closed_form_max_error": closed_form_error,
        "rows": rows,
        "checkpoint_total_ratio": ck["median_total_s"] / no_ck["median_total_s"],
        "checkpoint_loop_ratio": ck["median_loop_s"] / no_ck["median_loop_s"],
    }


def memory_benchmark(name, sizes, batch_size) -> dict:
    make_fn, make_inputs, _ = FUNCTIONS[name]
    fn = make_fn()
    rows = []
    for n in sizes:
        inputs = make_inputs(n)
        compiled, _ = plain_program(fn, inputs)
        _, _, _, chunk_program = timed_sweep(fn, inputs, batch_size=batch_size)
        rows.append(
            {
                "n": n,
                "plain jit(vmap)": memory_analysis(compiled),
                "sweep chunk program": memory_analysis(chunk_program),
            }
        )
    return {"batch_size": batch_size, "rows": rows}


def total_bytes(stats: dict) -> int:
    return sum(stats.values())


# ---------------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------------


def plot(results: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(13, 5))
    ax = axes[0]
    for i, (name, block) in enumerate(results["overhead"].items()):
        bs = results["settings"]["batch_sizes"]
        rows = block["rows"]
        total = [rows[f"sweep B={b}"]["total_ratio_to_plain"] for b in bs]
        loop = [rows[f"sweep B={b}"]["loop_ratio_to_plain"] for b in bs]
        ax.plot(bs, total, "o-", color=f"C{i}", label=f"{name}: whole call")
        ax.plot(bs, loop, "s--", color=f"C{i}", label=f"{name}: chunk loop only")
    ax.axhline(1.0, color="k", lw=0.8)
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("chunk size B")
    ax.set_ylabel("sweep time / plain jit(vmap) time (host to host)")
    n = results["settings"]["n"]
    ax.set_title(f"N = {n:,}: whole call (incl. compile) and loop after compile")
    ax.legend(fontsize=7)

    ax = axes[1]
    for i, (name, block) in enumerate(results["memory"].items()):
        ns = [r["n"] for r in block["rows"]]
        plain = [total_bytes(r["plain jit(vmap)"]) for r in block["rows"]]
        chunk = [total_bytes(r["sweep chunk program"]) for r in block["rows"]]
        ax.plot(ns, plain, "o-", color=f"C{i}", label=f"{name}: plain jit(vmap)")
        ax.plot(
            ns,
            chunk,
            "s--",
            color=f"C{i}",
            label=f"{name}: sweep chunk (B={block['batch_size']})",
        )
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("number of inputs N")
    ax.set_ylabel("XLA argument + output + temp bytes")
    ax.set_title("Device buffers of the compiled program")
    ax.legend(fontsize=7)
    fig.suptitle(
        f"cjax.sweep, jax {results['machine']['versions']['jax']}, "
        f"{results['machine']['cpu_count']}-core CPU (shared, noisy)",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--quick", action="store_true", help="smaller sizes (smoke test)"
    )
    parser.add_argument("--out", default=os.path.join("benchmarks", "results"))
    opts = parser.parse_args()
    if opts.quick:
        n, batch_sizes, repeats, memory_sizes = 4096, (256, 1024), 2, (1024, 4096)
    else:
        n, batch_sizes, repeats = 16_384, (256, 1024, 4096), 5
        memory_sizes = (4096, 16_384, 65_536)
    checkpoint_batch = 1024
    os.makedirs(opts.out, exist_ok=True)
    results = {
        "machine": machine_info(),
        "quick": opts.quick,
        "settings": {
            "n": n,
            "batch_sizes": list(batch_sizes),
            "repeats": repeats,
            "checkpoint_batch_size": checkpoint_batch,
            "memory_sizes": list(memory_sizes),
            "memory_batch_size": 1024,
            "devices": [str(d) for d in jax.local_devices()],
            "seed": SEED,
        },
        "overhead": {},
        "memory": {},
    }
    print(json.dumps(results["machine"], indent=1))
    for name in FUNCTIONS:
        block = overhead_benchmark(name, n, batch_sizes, repeats, checkpoint_batch)
        results["overhead"][name] = block
        print(
            f"\n== {name}, N = {n} (closed-form error "
            f"{block['closed_form_max_error']:.1e}) =="
        )
        for v, row in block["rows"].items():
            if "median_s" in row:
                print(f"{v:48s} {row['median_s'] * 1e3:9.2f} ms")
                continue
            line = (
                f"{v:48s} {row['median_total_s'] * 1e3:9.2f} ms total "
                f"({row['total_ratio_to_plain']:.3g}x)"
            )
            if "median_loop_s" in row:
                line += (
                    f", loop {row['median_loop_s'] * 1e3:8.2f} ms "
                    f"({row['loop_ratio_to_plain']:.3g}x)"
                )
            print(line + f", max diff {row['max_abs_diff_to_plain']:.1e}")
        print(
            f"checkpoint / none: total {block['checkpoint_total_ratio']:.3g}x, "
            f"loop {block['checkpoint_loop_ratio']:.3g}x"
        )
        mem = memory_benchmark(name, memory_sizes, 1024)
        results["memory"][name] = mem
        for r in mem["rows"]:
            print(
                f"N = {r['n']:6d}: plain {r['plain jit(vmap)']}, "
                f"chunk {r['sweep chunk program']}"
            )
    json_path = os.path.join(opts.out, "sweep.json")
    with open(json_path, "w") as f:
        json.dump(results, f, indent=1)
    png_path = os.path.join(opts.out, "sweep.png")
    plot(results, png_path)
    print(f"\nwrote {json_path} and {png_path}")


if __name__ == "__main__":
    main()
