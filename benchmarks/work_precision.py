"""Work-precision diagrams: error against run time, for choosing an integrator.

Two scenes, each integrated by Tsit5 (order 5), Dopri8 (order 8), Kvaerno5 (implicit,
order 5; for stiff parameters) over a range of tolerances `rtol = atol`, and by the
variational integrator (`cjax.VariationalIntegrator`, order 2, symplectic) over a
range of fixed steps:

- **Two cylinders** (`scenes.two_cylinders`, attached, `theta0 = 0.3`,
  `t in [0, 0.8]`): error of `(theta1, theta1dot)` at `t = 0.8` against the closed
  form (Jacobi `sn`, see `dynamics.py`).
- **N-link chain** (`scenes.chain`, `N = 8`, straight at 0.5 rad, released from rest,
  `t in [0, 1]`): error of the final state against a Dopri8 run at `rtol = 1e-13`
  (itself checked against Tsit5 at `1e-13`: the reference's own error is recorded).

Each method is compiled once (the tolerance or the step is a traced argument), then
each setting is timed after a warm-up (median of `--repeats`).

    python benchmarks/work_precision.py [--quick] [--out benchmarks/results]
"""

import argparse
import json
import os
import statistics
import time

import jax


jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import machine_info  # noqa: E402
from dynamics import CYLINDERS_T1, CYLINDERS_THETA0, cylinders_theta1  # noqa: E402

import constrained_jax as cjax  # noqa: E402
from constrained_jax.scenes import chain, two_cylinders as cyl  # noqa: E402


CHAIN_LINKS = 8
CHAIN_THETA0 = 0.5
CHAIN_T1 = 1.0
SAVE = cjax.SaveAt(t1=True, multipliers=False, energy=False, violation=False)
TOLERANCES = [1e-4, 1e-6, 1e-8, 1e-10, 1e-12]
ADAPTIVE = {
    "Tsit5": diffrax.Tsit5(),
    "Dopri8": diffrax.Dopri8(),
    "Kvaerno5 (implicit)": diffrax.Kvaerno5(),
}


def scene(name: str):
    if name == "two cylinders":
        args = cyl.default_args()
        q0, qd0 = cyl.state(jnp.asarray(CYLINDERS_THETA0), jnp.asarray(0.0), args)
        return cyl.system(), q0, qd0, args, CYLINDERS_T1
    args = chain.default_args()
    q0, qd0 = chain.state(CHAIN_LINKS, CHAIN_THETA0, args)
    return chain.system(), q0, qd0, args, CHAIN_T1


def runner(name: str, solver, variational: bool):
    system, q0, qd0, args, t1 = scene(name)

    def run(setting):
        if variational:  # a fixed step `dt0`
            options = {"dt0": setting}
        else:  # a tolerance
            controller = diffrax.PIDController(rtol=setting, atol=setting)
            options = {"stepsize_controller": controller}
        traj = cjax.simulate(
            system, (0.0, t1), q0, qd0, args, solver=solver, saveat=SAVE,
            max_steps=1_000_000, **options,
        )  # fmt: skip
        return traj.q[-1], traj.qd[-1]

    return jax.jit(run)


def reference(name: str):
    if name == "two cylinders":
        theta1, theta1d = cylinders_theta1(
            CYLINDERS_THETA0, CYLINDERS_T1, cyl.default_args()
        )
        return np.array([float(theta1), float(theta1d)]), 0.0
    ref = runner(name, diffrax.Dopri8(), False)(jnp.asarray(1e-13))
    check = runner(name, diffrax.Tsit5(), False)(jnp.asarray(1e-13))
    ref = np.concatenate([np.asarray(ref[0]), np.asarray(ref[1])])
    check = np.concatenate([np.asarray(check[0]), np.asarray(check[1])])
    return ref, float(np.max(np.abs(ref - check)))


def error(name: str, out, ref) -> float:
    q, qd = np.asarray(out[0]), np.asarray(out[1])
    if name == "two cylinders":
        return float(max(abs(q[1] - ref[0]), abs(qd[1] - ref[1])))
    return float(np.max(np.abs(np.concatenate([q, qd]) - ref)))


def measure(name, label, fn, settings, ref, repeats) -> dict:
    start = time.perf_counter()
    jax.block_until_ready(fn(jnp.asarray(settings[0])))
    compile_s = time.perf_counter() - start
    rows = []
    for setting in settings:
        x = jnp.asarray(setting)
        out = jax.block_until_ready(fn(x))
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(fn(x))
            times.append(time.perf_counter() - t0)
        rows.append(
            {
                "setting": setting,
                "median_s": statistics.median(times),
                "error": error(name, out, ref),
            }
        )
        print(
            f"{name:14s} {label:22s} {setting:9.2e} {rows[-1]['median_s']:10.3e} s"
            f"  err {rows[-1]['error']:.2e}"
        )
    return {"compile_and_first_s": compile_s, "rows": rows}


def run(repeats: int, quick: bool) -> dict:
    out = {}
    for name in ("two cylinders", "chain"):
        ref, ref_error = reference(name)
        block = {"reference_error_estimate": ref_error, "methods": {}}
        tolerances = TOLERANCES[::2] if quick else TOLERANCES
        for label, solver in ADAPTIVE.items():
            settings = tolerances
            block["methods"][label] = measure(
                name, label, runner(name, solver, False), settings, ref, repeats
            )
        steps = [0.02, 0.01, 0.005, 0.0025, 0.00125]
        block["methods"]["variational (order 2)"] = measure(
            name,
            "variational (order 2)",
            runner(name, cjax.VariationalIntegrator(), True),
            steps[::2] if quick else steps,
            ref,
            repeats,
        )
        out[name] = block
    return out


def plot(results: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 5))
    for ax, (name, block) in zip(axes, results["scenes"].items(), strict=True):
        for label, method in block["methods"].items():
            rows = method["rows"]
            ax.loglog(
                [r["median_s"] for r in rows],
                [r["error"] for r in rows],
                "o-",
                label=label,
            )
        ax.set_xlabel("run time (s, after compilation, median)")
        ax.set_ylabel("final-state error")
        title = (
            "two cylinders (closed form)"
            if name == "two cylinders"
            else (f"{CHAIN_LINKS}-link chain (reference Dopri8 1e-13)")
        )
        ax.set_title(title)
        ax.legend(fontsize=8)
        ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument(
        "--out",
        default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results"),
    )
    opts = parser.parse_args()
    results = {"machine": machine_info(diffrax=diffrax.__version__)}
    results["scenes"] = run(3 if opts.quick else opts.repeats, opts.quick)
    os.makedirs(opts.out, exist_ok=True)
    path = os.path.join(opts.out, "work_precision.json")
    with open(path, "w") as f:
        json.dump(results, f, indent=1)
    plot(results, os.path.join(opts.out, "work_precision.png"))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
