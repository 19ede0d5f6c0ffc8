"""GPU against the same machine's CPU, in one run: where the accelerator pays.

Every row runs the same program twice, once on the first GPU (`jax.devices("gpu")[0]`)
and once on the first CPU device of the same process (`jax.devices("cpu")[0]`, XLA:CPU
with all the machine's cores in its thread pool), and reports the GPU's speed-up
`CPU time / GPU time` (above 1: the GPU is faster). Float64 throughout (as the tests).

1. **Batched simulation.** `jit(vmap(simulate))` of the two cylinders (attached,
   Tsit5, `rtol = atol = 1e-8`, `t in [0, 0.8]`, `dynamics.py`'s `_final_state`) over
   `10^2 ... 10^5` parameter sets `(theta0, alpha)`, `theta0 ~ U(0.2, 0.3)`,
   `alpha ~ U(0.5, 1)` (the inertia `I = alpha M a^2` varies per row, so `args` is
   batched too). Every final state is checked against the closed form (Jacobi `sn`).
2. **Equations of motion.** `jit(vmap(...))` over `10^4` and `10^6` random states
   (`dynamics.random_states`) of the two cylinders and the Cartesian pendulum:
   `solve_accelerations`, the checked `accelerations` and the hand-written closed form
   (`dynamics.py`); the GPU's answers are compared with the CPU's.
3. **The N-link chain** (`chain.py`), `N = 16, 64, 256`, default saddle-point solver:
   one state per call (`jit(solve_accelerations)`: latency) and batches of 1,000 and
   10,000 states; XLA's scratch memory (`compiled.memory_analysis()`) and, on the GPU,
   the allocator's peak (`device.memory_stats()`).
4. **Compile time** of the first `jit(simulate)` of the two cylinders
   (`compile_time.py`'s case (a), `jax.clear_caches()` before each) and of the tour's
   two-cylinder program with the release event (case (b)), on each backend.
5. **`cjax.sweep`** of the simulation of (1) over `10^5` parameter sets and of the
   pendulum accelerations (`sweep.py`) over `10^6`: on the GPU against the CPU split
   into one XLA device per core (`--xla_force_host_platform_device_count`, set by this
   script), the first call (trace and compile included) and a second one (the kept
   program).

Timing as in the other scripts (`_common.time_jax`): ahead-of-time compilation, one
warm-up call, the median of several calls each ended by `block_until_ready`; compile
time reported apart. On a machine without a GPU every GPU row is skipped with a message
and the CPU rows still run. `--budget-s` bounds the run: a CPU row predicted to end past
it is skipped (and says so); the JSON is rewritten after every section.

    python benchmarks/gpu.py [--quick] [--budget-s 540] [--out benchmarks/results]

Writes `results/gpu.json` and `results/gpu.png`.
"""

import os


# One XLA:CPU device per core, for the sharded CPU sweep of section 5 (set before JAX
# starts its CPU backend). The single-device CPU rows use the first of them; its thread
# pool still spans all the cores.
if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "")
        + f" --xla_force_host_platform_device_count={os.cpu_count() or 1}"
    ).strip()

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402

import jax  # noqa: E402


jax.config.update("jax_enable_x64", True)
jax.config.update("jax_enable_compilation_cache", False)

import chain as chain_bench  # noqa: E402
import compile_time  # noqa: E402
import diffrax  # noqa: E402
import dynamics  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import scipy.special  # noqa: E402
import sweep as sweep_bench  # noqa: E402
from _common import (  # noqa: E402
    machine_info,
    memory_analysis,
    time_jax,
    time_jax_interleaved,
)

from constrained_jax.scenes import (  # noqa: E402
    chain,
    pendulum as pend,
    two_cylinders as cyl,
)


SEED = 0
THETA0 = (0.2, 0.3)
ALPHA = (0.5, 1.0)
T1 = dynamics.CYLINDERS_T1
TOL = dynamics.JAX_TOLERANCES["cylinders"]

_START = time.perf_counter()
_BUDGET = [float("inf")]


def elapsed() -> float:
    return time.perf_counter() - _START


def remaining() -> float:
    return _BUDGET[0] - elapsed()


# ---------------------------------------------------------------------------------
# Devices
# ---------------------------------------------------------------------------------


def the_devices() -> dict:
    """`{"gpu": device or None, "cpu": device}` and a message if there is no GPU."""
    cpu = jax.devices("cpu")[0]
    try:
        gpu = jax.devices("gpu")[0]
    except RuntimeError as error:
        print(f"no GPU: every GPU row is skipped ({error})")
        gpu = None
    return {"gpu": gpu, "cpu": cpu}


def memory_stats(device) -> dict:
    try:
        stats = device.memory_stats()
    except Exception:  # not every backend reports it
        return {}
    if not stats:
        return {}
    keys = ("bytes_in_use", "peak_bytes_in_use", "bytes_limit", "largest_alloc_size")
    return {k: int(stats[k]) for k in keys if k in stats}


def where(out) -> str:
    leaves = jax.tree.leaves(out)
    return str(sorted(str(d) for d in leaves[0].devices())) if leaves else ""


def on_device(device, fn, *args, repeats: int) -> tuple:
    """`time_jax(fn, *args)` with the inputs committed to `device` (so the program is
    compiled for and runs on it)."""
    args = jax.device_put(args, device)
    with jax.default_device(device):
        out, info = time_jax(fn, *args, repeats=repeats)
    info.pop("lapack_calls_in_hlo", None)
    info["ran_on"] = where(out)
    info["device_memory"] = memory_stats(device)
    return out, info


def guarded(label: str, thunk):
    """`thunk()`, or `{"error": ...}` (printed) if it raises: a failure on one device
    is a result, not the end of the run."""
    try:
        return thunk()
    except Exception as error:  # noqa: BLE001
        traceback.print_exc()
        print(f"!! {label}: {type(error).__name__}: {str(error)[:500]}")
        return {"error": f"{type(error).__name__}: {str(error)[:2000]}"}


def speedup(block: dict) -> float | None:
    gpu, cpu = block.get("gpu") or {}, block.get("cpu") or {}
    if "median_s" in gpu and "median_s" in cpu:
        return cpu["median_s"] / gpu["median_s"]
    return None


def fmt_s(x) -> str:
    if x is None:
        return "–"
    if x >= 1:
        return f"{x:.3g} s"
    if x >= 1e-3:
        return f"{x * 1e3:.3g} ms"
    return f"{x * 1e6:.3g} us"


def fmt_x(x) -> str:
    return "–" if x is None else f"{x:.3g}x"


# ---------------------------------------------------------------------------------
# 1. Batched simulation of the two cylinders over parameter sets
# ---------------------------------------------------------------------------------


def parameter_sets(num: int) -> tuple:
    rng = np.random.default_rng(SEED)
    theta0 = rng.uniform(*THETA0, num)
    alpha = rng.uniform(*ALPHA, num)
    return theta0, alpha


def batched_args(alpha) -> dict:
    """`cyl.default_args` with one row per `alpha` (every leaf batched)."""
    args = cyl.default_args()
    alpha = jnp.asarray(alpha)
    out = {k: jnp.broadcast_to(v, alpha.shape) for k, v in args.items()}
    out["I"] = alpha * args["M"] * args["a"] ** 2
    return out


def simulate_one():
    """`(theta0, args) -> (q(t1), qd(t1), steps)`, `dynamics.py`'s program."""
    return dynamics._final_state("cylinders", TOL)


def closed_form_final(theta0, alpha) -> tuple:
    """The attached motion's state at `T1`, per row (`dynamics.cylinders_theta1` with
    a per-row `alpha`)."""
    args = {k: float(v) for k, v in cyl.default_args().items()}
    g, big_r, a = args["g"], args["R"], args["a"]
    k = g / ((1 + alpha) * (big_r + a))
    m = np.cos(theta0 / 2) ** 2
    sn, _, _, _ = scipy.special.ellipj(scipy.special.ellipk(m) - np.sqrt(k) * T1, m)
    theta1 = np.pi - 2 * np.arcsin(np.sqrt(m) * sn)
    theta1d = np.sqrt(2 * k * (np.cos(theta0) - np.cos(theta1)))
    ratio = 1 + big_r / a
    q = np.stack([np.full_like(theta1, big_r + a), theta1, ratio * theta1], axis=1)
    qd = np.stack([np.zeros_like(theta1), theta1d, ratio * theta1d], axis=1)
    return q, qd


def simulate_batches(devs, sizes, repeats) -> dict:
    fn = jax.vmap(simulate_one(), in_axes=(0, 0))
    out = {}
    cpu_last = None  # (size, median) of the last CPU row, to predict the next
    for num in sizes:
        theta0, alpha = parameter_sets(num)
        q_ref, qd_ref = closed_form_final(theta0, alpha)
        inputs = (jnp.asarray(theta0), batched_args(alpha))
        reps = repeats if num <= 10_000 else max(2, repeats // 2)
        block = {"num": num, "repeats": reps}
        for name, device in devs.items():
            if device is None:
                block[name] = {"skipped": "no GPU on this machine"}
                continue
            if name == "cpu" and cpu_last is not None:
                predicted = cpu_last[1] * num / cpu_last[0] * (reps + 2) + 30
                if predicted > remaining():
                    msg = f"predicted {predicted:.0f} s > {remaining():.0f} s left"
                    print(f"(1) simulate {num}: CPU skipped, {msg}")
                    block[name] = {"skipped": msg}
                    continue

            def measure(
                device=device, inputs=inputs, reps=reps, ref=(q_ref, qd_ref), num=num
            ):
                (q, qd, steps), info = on_device(device, fn, *inputs, repeats=reps)
                err = dynamics.state_error(np.asarray(q), np.asarray(qd), *ref)
                info["max_error_vs_closed_form"] = float(err.max())
                info["steps"] = {"median": float(np.median(steps)),
                                 "max": int(np.max(steps))}  # fmt: skip
                info["per_trajectory_s"] = info["median_s"] / num
                return info

            block[name] = guarded(f"simulate {num} on {name}", measure)
            if name == "cpu" and "median_s" in block[name]:
                cpu_last = (num, block[name]["median_s"])
        block["gpu_speedup"] = speedup(block)
        out[str(num)] = block
        print(
            f"(1) simulate x{num:>7}: GPU {fmt_s(block['gpu'].get('median_s'))}, "
            f"CPU {fmt_s(block['cpu'].get('median_s'))}, speed-up "
            f"{fmt_x(block['gpu_speedup'])}; compile GPU "
            f"{fmt_s(block['gpu'].get('compile_s'))}, CPU "
            f"{fmt_s(block['cpu'].get('compile_s'))}; error GPU "
            f"{block['gpu'].get('max_error_vs_closed_form', float('nan')):.1e}",
            flush=True,
        )
    return out


# ---------------------------------------------------------------------------------
# 2. Equations of motion over many states
# ---------------------------------------------------------------------------------


def eom_variants(scene: str) -> dict:
    names = {
        "autodiff solve_accelerations": "solve_accelerations",
        "autodiff accelerations (checked)": "accelerations (checked)",
        "hand-written": "hand-written",
    }
    return {names[k]: fn for k, fn in dynamics.eom_variants(scene, 0.0).items()}


def eom(devs, sizes, repeats) -> dict:
    out = {}
    for scene in ("cylinders", "pendulum"):
        module = pend if scene == "pendulum" else cyl
        variants = eom_variants(scene)
        args = module.default_args()
        for num in sizes:
            q, qd = dynamics.random_states(scene, num)
            q, qd = np.asarray(q), np.asarray(qd)
            block = {"scene": scene, "num": num}
            outputs = {}
            for name, device in devs.items():
                if device is None:
                    block[name] = {"skipped": "no GPU on this machine"}
                    continue

                def measure(
                    device=device,
                    name=name,
                    data=(q, qd, args),
                    variants=variants,
                    num=num,
                    outputs=outputs,
                ):
                    inputs = jax.device_put(data, device)
                    with jax.default_device(device):
                        outs, infos = time_jax_interleaved(
                            variants, *inputs, repeats=repeats
                        )
                    for info in infos.values():
                        info.pop("lapack_calls_in_hlo", None)
                        info["per_state_s"] = info["median_s"] / num
                    infos["ran_on"] = where(outs["solve_accelerations"])
                    outputs[name] = jax.tree.map(np.asarray, outs)
                    return infos

                block[name] = guarded(f"EOM {scene} {num} on {name}", measure)
            for variant in variants:
                gpu, cpu = block["gpu"].get(variant), block["cpu"].get(variant)
                if gpu and cpu:
                    block.setdefault("gpu_speedup", {})[variant] = (
                        cpu["median_s"] / gpu["median_s"]
                    )
            if "gpu" in outputs and "cpu" in outputs:
                block["max_rel_diff_gpu_cpu"] = {
                    variant: float(
                        max(
                            np.max(np.abs(x - y) / (1 + np.abs(y)))
                            for x, y in zip(
                                jax.tree.leaves(outputs["gpu"][variant]),
                                jax.tree.leaves(outputs["cpu"][variant]),
                                strict=True,
                            )
                        )
                    )
                    for variant in variants
                }
            out[f"{scene} {num}"] = block
            diff = block.get("max_rel_diff_gpu_cpu", {})
            for variant in variants:
                print(
                    f"(2) EOM {scene:9s} x{num:>8} {variant:24s}: GPU "
                    f"{fmt_s(block['gpu'].get(variant, {}).get('median_s'))}, CPU "
                    f"{fmt_s(block['cpu'].get(variant, {}).get('median_s'))}, "
                    f"speed-up {fmt_x(block.get('gpu_speedup', {}).get(variant))}, "
                    f"GPU-CPU diff {diff.get(variant, float('nan')):.1e}",
                    flush=True,
                )
    return out


# ---------------------------------------------------------------------------------
# 3. The N-link chain
# ---------------------------------------------------------------------------------


def chain_rows(devs, sizes, batches, repeats) -> dict:
    system = chain.system()
    args = chain.default_args()
    t = 0.0

    def one(q, qd, args):
        return system.solve_accelerations(q, qd, t, args)[:2]

    def many(q, qd, args):
        return jax.vmap(lambda a, b: system.solve_accelerations(a, b, t, args)[:2])(
            q, qd
        )

    out = {}
    for n_links in sizes:
        q, qd = chain_bench.random_states(n_links, max(batches))
        q, qd = np.asarray(q), np.asarray(qd)
        for batch in (1, *batches):
            block = {"N": n_links, "batch": batch}
            results = {}
            for name, device in devs.items():
                if device is None:
                    block[name] = {"skipped": "no GPU on this machine"}
                    continue

                def measure(
                    device=device, name=name, batch=batch, q=q, qd=qd, results=results
                ):
                    if batch == 1:
                        res, info = on_device(
                            device, one, q[0], qd[0], args, repeats=repeats
                        )
                    else:
                        res, info = on_device(
                            device,
                            many,
                            q[:batch],
                            qd[:batch],
                            args,
                            repeats=repeats,
                        )
                    info["per_state_s"] = info["median_s"] / batch
                    results[name] = jax.tree.map(np.asarray, res)
                    return info

                block[name] = guarded(f"chain {n_links} x{batch} on {name}", measure)
            block["gpu_speedup"] = speedup(block)
            if "gpu" in results and "cpu" in results:
                block["max_rel_diff_gpu_cpu"] = float(
                    max(
                        np.max(np.abs(x - y)) / (1 + np.max(np.abs(y)))
                        for x, y in zip(
                            jax.tree.leaves(results["gpu"]),
                            jax.tree.leaves(results["cpu"]),
                            strict=True,
                        )
                    )
                )
            out[f"{n_links} x{batch}"] = block
            gpu_mem = block["gpu"].get("xla_memory", {}).get("temp_size_in_bytes")
            cpu_mem = block["cpu"].get("xla_memory", {}).get("temp_size_in_bytes", 0)
            print(
                f"(3) chain N={n_links:4d} batch {batch:>6}: per state GPU "
                f"{fmt_s(block['gpu'].get('per_state_s'))}, CPU "
                f"{fmt_s(block['cpu'].get('per_state_s'))}, speed-up "
                f"{fmt_x(block['gpu_speedup'])}; XLA temp GPU "
                f"{'–' if gpu_mem is None else f'{gpu_mem / 1e6:.3g} MB'}, CPU "
                f"{cpu_mem / 1e6:.3g} MB",
                flush=True,
            )
    return out


# ---------------------------------------------------------------------------------
# 4. Compile time
# ---------------------------------------------------------------------------------


def compile_rows(devs, cases) -> dict:
    out = {}
    for key, repeats in cases:
        name, make = compile_time.CASES[key]
        block = {"case": key, "name": name, "repeats": repeats}
        for dev_name, device in devs.items():
            if device is None:
                block[dev_name] = {"skipped": "no GPU on this machine"}
                continue

            def measure(device=device, make=make, repeats=repeats):
                with jax.default_device(device):
                    summary = compile_time.measure(make, repeats)
                return {k: summary[k] for k in summary if k != "runs"} | {
                    "runs_total_s": [r["trace_lower_s"] + r["compile_s"]
                                     for r in summary["runs"]]}  # fmt: skip

            block[dev_name] = guarded(f"compile {key} on {dev_name}", measure)
        gpu, cpu = block["gpu"], block["cpu"]
        if "total_s" in gpu and "total_s" in cpu:
            block["gpu_over_cpu"] = gpu["total_s"] / cpu["total_s"]
            block["gpu_over_cpu_compile_only"] = gpu["compile_s"] / cpu["compile_s"]
        out[key] = block
        print(
            f"(4) compile ({key}) {name}: GPU trace+lower "
            f"{fmt_s(gpu.get('trace_lower_s'))} + compile {fmt_s(gpu.get('compile_s'))}"
            f"; CPU {fmt_s(cpu.get('trace_lower_s'))} + "
            f"{fmt_s(cpu.get('compile_s'))}",
            flush=True,
        )
    return out


# ---------------------------------------------------------------------------------
# 5. sweep
# ---------------------------------------------------------------------------------


def simulate_sweep_fn():
    final_state = simulate_one()

    def fn(x):
        q, qd, steps = final_state(x["theta0"], batched_args(x["alpha"]))
        return {"q": q, "qd": qd, "steps": steps}

    return fn


def sweep_rows(devs, sim_n, pend_n, sim_batch, pend_batch) -> dict:
    theta0, alpha = parameter_sets(sim_n)
    q_ref, qd_ref = closed_form_final(theta0, alpha)
    cases = {
        "simulate two cylinders": (
            simulate_sweep_fn(),
            {"theta0": theta0, "alpha": alpha},
            sim_batch,
            lambda out: float(
                dynamics.state_error(out["q"], out["qd"], q_ref, qd_ref).max()
            ),
        ),
        "pendulum accelerations": (
            sweep_bench.pendulum_fn(),
            sweep_bench.pendulum_inputs(pend_n),
            pend_batch,
            None,
        ),
    }
    placements = {}
    if devs["gpu"] is not None:
        placements["gpu"] = [devs["gpu"]]
    placements["cpu (one XLA device per core)"] = jax.devices("cpu")
    out = {}
    for case, (fn, inputs, batch, check) in cases.items():
        n = len(next(iter(inputs.values())))
        block = {"num": n, "batch_size": batch}
        if devs["gpu"] is None:
            block["gpu"] = {"skipped": "no GPU on this machine"}
        for name, devices in placements.items():

            def measure(
                fn=fn, inputs=inputs, batch=batch, devices=devices, check=check
            ):
                first = sweep_bench.timed_sweep(
                    fn, inputs, batch_size=batch, devices=devices
                )
                second = sweep_bench.timed_sweep(
                    fn, inputs, batch_size=batch, devices=devices
                )
                info = {
                    "devices": len(devices),
                    "first_call_s": first[1],
                    "first_call_chunk_loop_s": first[2],
                    "second_call_s": second[1],
                    "second_call_chunk_loop_s": second[2],
                    "chunk_program_memory": memory_analysis(first[3])
                    if first[3] is not None
                    else {},
                    # Setup: checks, trace (or the kept trace), lower, and the
                    # compile (JAX's in-memory cache on the second call).
                    "first_call_setup_s": first[1] - (first[2] or 0.0),
                    "second_call_setup_s": second[1] - (second[2] or 0.0),
                }
                if check is not None:
                    info["max_error_vs_closed_form"] = check(second[0])
                return info

            block[name] = guarded(f"sweep {case} on {name}", measure)
        gpu = block.get("gpu", {})
        cpu = block["cpu (one XLA device per core)"]
        if "second_call_s" in gpu and "second_call_s" in cpu:
            for call in ("first", "second"):
                block[f"gpu_speedup_{call}_call"] = (
                    cpu[f"{call}_call_s"] / gpu[f"{call}_call_s"]
                )
        out[case] = block
        print(
            f"(5) sweep {case} x{n}: GPU first {fmt_s(gpu.get('first_call_s'))}, "
            f"second {fmt_s(gpu.get('second_call_s'))}; CPU x{len(jax.devices('cpu'))} "
            f"first {fmt_s(cpu.get('first_call_s'))}, second "
            f"{fmt_s(cpu.get('second_call_s'))}; speed-up (second) "
            f"{fmt_x(block.get('gpu_speedup_second_call'))}",
            flush=True,
        )
    return out


# ---------------------------------------------------------------------------------
# Plot, table, main
# ---------------------------------------------------------------------------------


def plot(results: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(22, 5))
    ax = axes[0]
    sim = results.get("simulate", {})
    for dev, style in (("gpu", "o-"), ("cpu", "s--")):
        xs = [int(k) for k, b in sim.items() if "median_s" in b.get(dev, {})]
        ys = [sim[str(x)][dev]["median_s"] for x in xs]
        if xs:
            ax.loglog(xs, ys, style, label=dev.upper())
    ax.set_xlabel("parameter sets (trajectories)")
    ax.set_title("two cylinders, jit(vmap(simulate)) (s per batch)")
    ax.legend(fontsize=8)

    ax = axes[1]
    labels, values = [], []
    for key, block in results.get("eom", {}).items():
        for variant, value in block.get("gpu_speedup", {}).items():
            labels.append(f"{key} {variant}")
            values.append(value)
    if values:
        ax.barh(range(len(values)), values)
        ax.set_yticks(range(len(values)), labels, fontsize=6)
        ax.set_xscale("log")
        ax.axvline(1.0, color="k", lw=0.8)
    ax.set_title("EOM jit(vmap): GPU speed-up (CPU time / GPU time)")

    ax = axes[2]
    ch = results.get("chain", {})
    batches = sorted({b["batch"] for b in ch.values()})
    for batch in batches:
        for dev, style in (("gpu", "o-"), ("cpu", "s--")):
            rows = [b for b in ch.values() if b["batch"] == batch and
                    "per_state_s" in b.get(dev, {})]  # fmt: skip
            if rows:
                ax.loglog([b["N"] for b in rows], [b[dev]["per_state_s"] for b in rows],
                          style, label=f"{dev.upper()} batch {batch}")  # fmt: skip
    ax.set_xlabel("N (links)")
    ax.set_title("N-link chain EOM, time per state (s)")
    ax.legend(fontsize=7)

    ax = axes[3]
    comp = results.get("compile", {})
    keys = [k for k, b in comp.items() if "total_s" in b.get("gpu", {}) or
            "total_s" in b.get("cpu", {})]  # fmt: skip
    for i, dev in enumerate(("gpu", "cpu")):
        vals = [comp[k].get(dev, {}).get("total_s", 0.0) for k in keys]
        ax.bar(np.arange(len(keys)) + 0.4 * i, vals, width=0.4, label=dev.upper())
    ax.set_xticks(np.arange(len(keys)) + 0.2, [comp[k]["name"][:40] for k in keys],
                  fontsize=6)  # fmt: skip
    ax.set_title("compile (trace + lower + compile, s)")
    ax.legend(fontsize=8)
    machine = results["machine"]
    fig.suptitle(
        f"GPU vs CPU, float64: {machine.get('gpu_kind', 'no GPU')} vs "
        f"{machine['cpu_count']} CPU cores; jax {machine['versions']['jax']}",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def table(results: dict) -> str:
    lines = ["| row | GPU | CPU | GPU speed-up (CPU / GPU) |", "|---|---:|---:|---:|"]
    for num, b in results.get("simulate", {}).items():
        lines.append(
            f"| (1) simulate two cylinders, {int(num):,} parameter sets | "
            f"{fmt_s(b['gpu'].get('median_s'))} | {fmt_s(b['cpu'].get('median_s'))} | "
            f"{fmt_x(b['gpu_speedup'])} |"
        )
    for key, b in results.get("eom", {}).items():
        for variant in eom_variants("pendulum"):
            scene, num = key.split()
            lines.append(
                f"| (2) EOM {scene}, {int(num):,} states, {variant} "
                f"| {fmt_s(b['gpu'].get(variant, {}).get('median_s'))} | "
                f"{fmt_s(b['cpu'].get(variant, {}).get('median_s'))} | "
                f"{fmt_x(b.get('gpu_speedup', {}).get(variant))} |"
            )
    for b in results.get("chain", {}).values():
        what = "one state per call" if b["batch"] == 1 else f"batch {b['batch']:,}"
        lines.append(
            f"| (3) chain N = {b['N']}, {what}, per state | "
            f"{fmt_s(b['gpu'].get('per_state_s'))} | "
            f"{fmt_s(b['cpu'].get('per_state_s'))} | {fmt_x(b['gpu_speedup'])} |"
        )
    for b in results.get("compile", {}).values():
        gpu, cpu = b["gpu"].get("total_s"), b["cpu"].get("total_s")
        ratio = None if gpu is None or cpu is None else cpu / gpu
        lines.append(
            f"| (4) compile ({b['case']}) {b['name']} | {fmt_s(gpu)} | {fmt_s(cpu)} | "
            f"{fmt_x(ratio)} |"
        )
    for case, b in results.get("sweep", {}).items():
        cpu = b.get("cpu (one XLA device per core)", {})
        for call in ("first", "second"):
            lines.append(
                f"| (5) sweep {case}, {b['num']:,} inputs, {call} call | "
                f"{fmt_s(b.get('gpu', {}).get(f'{call}_call_s'))} | "
                f"{fmt_s(cpu.get(f'{call}_call_s'))} "
                f"({cpu.get('devices', '?')} devices)"
                f" | {fmt_x(b.get(f'gpu_speedup_{call}_call'))} |"
            )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--budget-s", type=float, default=float("inf"))
    parser.add_argument("--only", default="simulate,eom,chain,compile,sweep")
    parser.add_argument(
        "--out",
        default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results"),
    )
    opts = parser.parse_args()
    _BUDGET[0] = opts.budget_s
    only = opts.only.split(",")
    devs = the_devices()
    if opts.quick:
        settings = {
            "simulate_sizes": [100, 1000], "eom_sizes": [10_000], "chain_sizes": [16],
            "chain_batches": [100], "compile_cases": [("a", 1)], "sweep_sim_n": 1000,
            "sweep_pend_n": 10_000, "sweep_sim_batch": 256, "sweep_pend_batch": 4096,
            "repeats": 3,
        }  # fmt: skip
    else:
        settings = {
            "simulate_sizes": [100, 1000, 10_000, 100_000],
            "eom_sizes": [10_000, 1_000_000], "chain_sizes": [16, 64, 256],
            "chain_batches": [1000, 10_000], "compile_cases": [("a", 3), ("b", 1)],
            "sweep_sim_n": 100_000, "sweep_pend_n": 1_000_000,
            "sweep_sim_batch": 16_384, "sweep_pend_batch": 131_072, "repeats": 7,
        }  # fmt: skip
    machine = machine_info(diffrax=diffrax.__version__)
    if devs["gpu"] is not None:
        machine["gpu_kind"] = devs["gpu"].device_kind
        machine["gpu_memory"] = memory_stats(devs["gpu"])
    results = {"machine": machine, "settings": settings, "skipped_sections": []}
    os.makedirs(opts.out, exist_ok=True)
    path = os.path.join(opts.out, "gpu.json")

    def save():
        results["elapsed_s"] = elapsed()
        with open(path, "w") as f:
            json.dump(results, f, indent=1, default=lambda x: np.asarray(x).tolist())

    reps = settings["repeats"]
    sections = {
        "simulate": lambda: simulate_batches(devs, settings["simulate_sizes"], reps),
        "eom": lambda: eom(devs, settings["eom_sizes"], reps),
        "chain": lambda: chain_rows(
            devs, settings["chain_sizes"], settings["chain_batches"], reps
        ),
        "compile": lambda: compile_rows(devs, settings["compile_cases"]),
        "sweep": lambda: sweep_rows(
            devs,
            settings["sweep_sim_n"],
            settings["sweep_pend_n"],
            settings["sweep_sim_batch"],
            settings["sweep_pend_batch"],
        ),
    }
    for name, section in sections.items():
        if name not in only:
            continue
        if remaining() < 20:
            print(f"section {name} skipped: {remaining():.0f} s of the budget left")
            results["skipped_sections"].append(name)
            continue
        start = time.perf_counter()
        results[name] = guarded(f"section {name}", section)
        print(f"== section {name}: {time.perf_counter() - start:.1f} s", flush=True)
        save()
    save()
    print("\n" + table(results))
    try:
        plot(results, os.path.join(opts.out, "gpu.png"))
    except Exception:  # noqa: BLE001
        traceback.print_exc()
    print(f"wrote {path} ({elapsed():.0f} s)")


if __name__ == "__main__":
    main()
