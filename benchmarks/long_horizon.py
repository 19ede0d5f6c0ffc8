"""Benchmark: long-horizon energy and constraint errors, and cost per simulated time.

The Cartesian pendulum (`constrained_jax.scenes.pendulum`: `q = (x, y)`, holonomic
`r = l`; `m = 1`, `g = 9.81`, `l = 1`), released from rest at `theta0 = 1.0`, run for
10,000 periods (21,400 s of simulated time; `--quick`: 500 periods) at a fixed step
`h` of 1/20 of the period (0.107 s), saved every 99 steps (`--quick`: 7; not a whole
number of periods, so every phase of the oscillation is sampled). Methods:

- `cjax.simulate(..., solver=diffrax.Tsit5(), stepsize_controller=ConstantStepSize(),
  dt0=h)` with each stabilization: `Unstabilized()`, `Baumgarte(alpha=10, beta=10)`,
  `Projection()`;
- `cjax.simulate(..., solver=diffrax.Heun(), ..., stabilization=Projection())` at
  `h/5` (at `h` and `h/2` Heun's energy grows until the run breaks down);
- `cjax.integrate_variational(cjax.VariationalIntegrator(), ...)` (RATTLE) at `h` and
  at `h/4`. (`Midpoint()` gives the same numbers here: for a potential linear in `q`,
  like `m g y`, the two discrete Lagrangians coincide.)

Measured: the energy error `|E(t) - E(0)|` relative to `m g l`, its largest value in
the first and in the last tenth of the run, the position (`|r - l|`) and velocity
(`|q . qdot|`) constraint violations, and the wall time per unit of simulated time
(median of several runs after compilation; `benchmarks/_common.py`).

    python benchmarks/long_horizon.py [--quick] [--out benchmarks/results]
"""

import argparse
import json
import os

import jax


jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import machine_info, time_jax  # noqa: E402

import constrained_jax as cjax  # noqa: E402
from constrained_jax.scenes import pendulum as pend  # noqa: E402


THETA0 = 1.0
STEPS_PER_PERIOD = 20
# Saves every 99 steps (7 with --quick): coprime with 20, so that every tenth of the
# run samples every phase of the oscillation.
SAVE_EVERY = {False: 99, True: 7}


def simulate_fn(solver, stabilization, dt0, ts, max_steps):
    system = pend.system()

    def run(q0, qd0, args):
        traj = cjax.simulate(
            system,
            (0.0, ts[-1]),
            q0,
            qd0,
            args,
            solver=solver,
            stabilization=stabilization,
            stepsize_controller=diffrax.ConstantStepSize(),
            dt0=dt0,
            max_steps=max_steps,
            saveat=cjax.SaveAt(ts=ts, multipliers=False),
            throw=False,
        )
        return traj.q, traj.qd, traj.result._value, traj.stats["num_steps"]

    return run


def variational_fn(integrator, dt0, ts, max_steps):
    system = pend.system()

    def run(q0, qd0, args):
        sol = cjax.integrate_variational(
            integrator,
            system,
            0.0,
            ts[-1],
            dt0,
            q0,
            qd0,
            args,
            ts_save=ts,
            max_steps=max_steps,
            throw=False,
        )
        return sol.q, sol.qd, sol.result._value, sol.stats["num_steps"]

    return run


def errors(q, qd, args, ts):
    system = pend.system()
    energy = jax.vmap(lambda a, b: system.energy(a, b, 0.0, args))(q, qd)
    scale = float(args["m"] * args["g"] * args["l"])
    energy_error = np.abs(np.asarray(energy - energy[0])) / scale
    position = np.abs(np.asarray(jnp.linalg.norm(q, axis=1) - args["l"]))
    velocity = np.abs(np.asarray(jnp.sum(q * qd, axis=1)))
    tenth = max(len(ts) // 10, 1)
    finite = bool(np.all(np.isfinite(energy_error)))
    return {
        "energy_error_max": float(np.max(energy_error)) if finite else float("inf"),
        "energy_error_first_tenth": float(np.max(energy_error[:tenth])),
        "energy_error_last_tenth": float(np.max(energy_error[-tenth:]))
        if finite
        else float("inf"),
        "position_violation_max": float(np.max(position)) if finite else float("inf"),
        "velocity_violation_max": float(np.max(velocity)) if finite else float("inf"),
        "series": {
            "energy_error": energy_error.tolist(),
            "position_violation": position.tolist(),
        },
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="500 periods, 1 repeat")
    parser.add_argument("--out", default=os.path.join("benchmarks", "results"))
    opts = parser.parse_args()
    periods, repeats = (500, 1) if opts.quick else (10_000, 3)

    args = pend.default_args()
    theta0 = jnp.asarray(THETA0)
    period = float(pend.period(theta0, args))
    h = period / STEPS_PER_PERIOD
    save_every = SAVE_EVERY[opts.quick]
    num_saves = periods * STEPS_PER_PERIOD // save_every + 1
    ts = h * save_every * jnp.arange(float(num_saves))
    t1 = float(ts[-1])
    steps = (num_saves - 1) * save_every
    q0, qd0 = pend.state(theta0, jnp.asarray(0.0), args)

    methods = {
        "Tsit5 + Unstabilized": simulate_fn(
            diffrax.Tsit5(), cjax.Unstabilized(), h, ts, steps + 10
        ),
        "Tsit5 + Baumgarte(10, 10)": simulate_fn(
            diffrax.Tsit5(), cjax.Baumgarte(alpha=10.0, beta=10.0), h, ts, steps + 10
        ),
        "Tsit5 + Projection": simulate_fn(
            diffrax.Tsit5(), cjax.Projection(), h, ts, steps + 10
        ),
        "Heun + Projection (h/5)": simulate_fn(
            diffrax.Heun(), cjax.Projection(), h / 5, ts, 5 * steps + 10
        ),
        "VariationalIntegrator (RATTLE)": variational_fn(
            cjax.VariationalIntegrator(), h, ts, steps + 10
        ),
        "VariationalIntegrator (RATTLE, h/4)": variational_fn(
            cjax.VariationalIntegrator(), h / 4, ts, 4 * steps + 10
        ),
    }
    results = {
        "machine": machine_info(diffrax=diffrax.__version__),
        "quick": opts.quick,
        "settings": {
            "args": {k: float(v) for k, v in args.items()},
            "theta0": THETA0,
            "period_s": period,
            "periods": t1 / period,
            "t1_s": t1,
            "step_s": h,
            "steps_per_period": STEPS_PER_PERIOD,
            "save_every_steps": save_every,
            "num_saves": num_saves,
            "repeats": repeats,
        },
        "methods": {},
    }
    print(json.dumps(results["settings"], indent=1))
    for name, fn in methods.items():
        (q, qd, result, num_steps), info = time_jax(fn, q0, qd0, args, repeats=repeats)
        row = errors(q, qd, args, ts)
        row.update(
            result=int(result),
            num_steps=int(num_steps),
            median_s=info["median_s"],
            times_s=info["times_s"],
            compile_s=info["compile_s"],
            trace_lower_s=info["trace_lower_s"],
            wall_per_simulated_second_s=info["median_s"] / t1,
            wall_per_step_us=info["median_s"] / int(num_steps) * 1e6,
        )
        results["methods"][name] = row
        print(
            f"{name:36s} E err first/last tenth {row['energy_error_first_tenth']:.2e}"
            f" / {row['energy_error_last_tenth']:.2e}  |r-l| "
            f"{row['position_violation_max']:.1e}  {info['median_s']:.2f} s "
            f"({row['wall_per_step_us']:.1f} us/step, {int(num_steps)} steps, "
            f"result {int(result)}, compile {info['compile_s']:.1f} s)"
        )

    os.makedirs(opts.out, exist_ok=True)
    with open(os.path.join(opts.out, "long_horizon.json"), "w") as f:
        json.dump(results, f, indent=1)
    plot(results, np.asarray(ts) / period, os.path.join(opts.out, "long_horizon.png"))


def plot(results, periods, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(15, 5.5))
    for name, row in results["methods"].items():
        energy = np.asarray(row["series"]["energy_error"])
        position = np.asarray(row["series"]["position_violation"])
        label = f"{name} ({row['wall_per_step_us']:.0f} us/step)"
        axes[0].plot(periods[1:], energy[1:], label=label, lw=0.8)
        axes[1].plot(periods[1:], np.maximum(position[1:], 1e-17), label=name, lw=0.8)
    axes[0].set(
        xscale="log",
        yscale="log",
        xlabel="periods",
        ylabel="|E(t) - E(0)| / (m g l)",
        title="energy error (fixed step h = period/20 unless noted)",
    )
    axes[1].set(
        xscale="log",
        yscale="log",
        xlabel="periods",
        ylabel="| |q| - l |",
        title="position constraint violation (floored at 1e-17)",
    )
    axes[0].legend(fontsize=8)
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
