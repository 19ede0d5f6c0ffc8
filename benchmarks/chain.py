"""The N-link chain (`constrained_jax.scenes.chain`): how cost grows with the system.

`N` masses in Cartesian coordinates (`n = 2N`, `k = N` rod constraints); the mass
matrix is diagonal and the Schur complement `A M^-1 A^T` tridiagonal. For each `N`:

1. **Equations of motion per state**: `jax.jit(jax.vmap(system.solve_accelerations))`
   over a batch of random admissible states (random link angles and rates), for each
   saddle-point solver: the default (chosen from the structure and the size), the
   dense pivoted LU of the whole KKT matrix (`FullKKTLU(unroll_max=0)`, LAPACK) and,
   while `n + k <= 12`, the unrolled `RangeSpaceLDL`. Time per state (the batch's
   median time over its size), compile time, XLA scratch memory, and the largest
   difference from the dense answer.
2. **One trajectory**: `simulate` over `t in [0, 1]` from a straight chain at 0.5 rad,
   released from rest (Tsit5, `rtol = atol = 1e-8`), for the default and (up to
   `--dense-trajectory-max`) the dense solver: run and compile time, steps, the
   energy drift and the largest rod-length error at the end.

Growth exponents are fitted by least squares to `log(time)` against `log(N)` over the
largest sizes. Run by `dynamics.py` (section "chain") or alone:

    python benchmarks/chain.py [--quick] [--out benchmarks/results]
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
from _common import fresh_caches, machine_info, memory_analysis  # noqa: E402

import constrained_jax as cjax  # noqa: E402
from constrained_jax.scenes import chain  # noqa: E402


SEED = 0
THETA0 = 0.5
T1 = 1.0
TOL = 1e-8
# Dense KKT matrices per state are (3N)^2 doubles: bound the dense batch's scratch.
DENSE_BATCH_BYTES = 2e9


def solvers(n_links: int) -> dict:
    out = {
        "default": None,
        "dense LU (LAPACK, FullKKTLU(unroll_max=0))": cjax.FullKKTLU(unroll_max=0),
    }
    if 3 * n_links <= 12:
        out["unrolled RangeSpaceLDL"] = cjax.RangeSpaceLDL()
    return out


def make_system(solver):
    if solver is None:
        return chain.system()
    return chain.system(saddle_point_solver=solver)


def random_states(n_links: int, num: int):
    """Admissible states: link angles `phi ~ U(-1, 1)`, rates `~ N(0, 1)`."""
    # One generator each, so that the first states of batches of any size agree.
    phi = np.random.default_rng(SEED).uniform(-1.0, 1.0, (num, n_links))
    rate = np.random.default_rng(SEED + 1).normal(0.0, 1.0, (num, n_links))
    x = np.cumsum(np.sin(phi), axis=1)
    y = -np.cumsum(np.cos(phi), axis=1)
    xd = np.cumsum(np.cos(phi) * rate, axis=1)
    yd = np.cumsum(np.sin(phi) * rate, axis=1)
    q = np.stack([x, y], axis=2).reshape(num, -1)
    qd = np.stack([xd, yd], axis=2).reshape(num, -1)
    return jnp.asarray(q), jnp.asarray(qd)


def _median_time(compiled, *args, repeats):
    jax.block_until_ready(compiled(*args))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - start)
    return statistics.median(times), times


def _compile(fn, *args):
    # A first call: nothing compiled, traced or detected before it.
    fresh_caches()
    t0 = time.perf_counter()
    lowered = jax.jit(fn).lower(*args)
    t1 = time.perf_counter()
    compiled = lowered.compile()
    t2 = time.perf_counter()
    return compiled, t1 - t0, t2 - t1


def eom(n_links: int, batch: int, repeats: int) -> dict:
    args = chain.default_args()
    t = jnp.asarray(0.0)
    rows, outputs = {}, {}
    for name, solver in solvers(n_links).items():
        system = make_system(solver)
        num = batch
        if name.startswith("dense"):
            per_state = 4 * 8 * (3 * n_links) ** 2
            num = int(max(1, min(batch, DENSE_BATCH_BYTES // per_state)))
        q, qd = random_states(n_links, num)
        fn = lambda q, qd, args, system=system: jax.vmap(
            lambda a, b: system.solve_accelerations(a, b, t, args)
        )(q, qd)
        compiled, lower_s, compile_s = _compile(fn, q, qd, args)
        median, times = _median_time(compiled, q, qd, args, repeats=repeats)
        qdd, lam, singular = compiled(q, qd, args)
        outputs[name] = (num, np.asarray(qdd), np.asarray(lam), np.asarray(singular))
        rows[name] = {
            "batch": num,
            "median_s": median,
            "per_state_s": median / num,
            "times_s": times,
            "trace_lower_s": lower_s,
            "compile_s": compile_s,
            "xla_memory": memory_analysis(compiled),
            "any_singular": bool(np.any(singular)),
        }
    dense = outputs["dense LU (LAPACK, FullKKTLU(unroll_max=0))"]
    for name, (num, qdd, lam, _) in outputs.items():
        m = min(num, dense[0])
        scale = 1.0 + np.max(np.abs(dense[1][:m]))
        rows[name]["max_rel_diff_to_dense"] = float(
            max(
                np.max(np.abs(qdd[:m] - dense[1][:m])) / scale,
                np.max(np.abs(lam[:m] - dense[2][:m]))
                / (1.0 + np.max(np.abs(dense[2][:m]))),
            )
        )
    return rows


def trajectory(n_links: int, solver, repeats: int) -> dict:
    args = chain.default_args()
    system = make_system(solver)
    q0, qd0 = chain.state(n_links, THETA0, args)
    saveat = cjax.SaveAt(t1=True, multipliers=False, energy=False, violation=False)

    def run(q0, qd0, args):
        traj = cjax.simulate(
            system,
            (0.0, T1),
            q0,
            qd0,
            args,
            solver=diffrax.Tsit5(),
            stepsize_controller=diffrax.PIDController(rtol=TOL, atol=TOL),
            saveat=saveat,
        )
        return traj.q[-1], traj.qd[-1], traj.stats["num_steps"]

    compiled, lower_s, compile_s = _compile(run, q0, qd0, args)
    median, times = _median_time(compiled, q0, qd0, args, repeats=repeats)
    q1, qd1, steps = compiled(q0, qd0, args)
    e0 = float(chain.energy(q0, qd0, args))
    return {
        "median_s": median,
        "times_s": times,
        "trace_lower_s": lower_s,
        "compile_s": compile_s,
        "num_steps": int(steps),
        "energy_drift": abs(float(chain.energy(q1, qd1, args)) - e0) / abs(e0),
        "rod_length_error": float(
            np.max(np.abs(np.asarray(chain.link_lengths(q1)) - float(args["l"])))
        ),
        "q1": np.asarray(q1).tolist() if n_links <= 8 else None,
        "xla_memory": memory_analysis(compiled),
    }


def growth_exponent(sizes, times) -> float | None:
    sizes, times = np.asarray(sizes, float), np.asarray(times, float)
    keep = sizes >= max(16, sizes.max() / 16)
    if keep.sum() < 2:
        return None
    return float(np.polyfit(np.log(sizes[keep]), np.log(times[keep]), 1)[0])


def run(sizes, batch, repeats, dense_trajectory_max, trajectory_max) -> dict:
    out = {"sizes": list(sizes), "eom": {}, "trajectory": {}}
    for n_links in sizes:
        rows = eom(n_links, batch, repeats)
        out["eom"][n_links] = rows
        for name, row in rows.items():
            print(
                f"chain N={n_links:4d} EOM {name:45s} {row['per_state_s'] * 1e6:10.2f}"
                f" us/state (batch {row['batch']}), compile {row['compile_s']:.2f} s, "
                f"diff {row['max_rel_diff_to_dense']:.1e}"
            )
    for n_links in sizes:
        if n_links > trajectory_max:
            continue
        block = {}
        for name, solver in solvers(n_links).items():
            if name.startswith("dense") and n_links > dense_trajectory_max:
                continue
            reps = repeats if n_links <= 64 else max(1, repeats // 3)
            block[name] = trajectory(n_links, solver, reps)
            row = block[name]
            print(
                f"chain N={n_links:4d} simulate {name:45s} {row['median_s']:9.4g} s, "
                f"compile {row['trace_lower_s'] + row['compile_s']:.2f} s, "
                f"{row['num_steps']} steps, energy drift {row['energy_drift']:.1e}"
            )
        out["trajectory"][n_links] = block
    names = list(out["eom"][sizes[-1]])
    out["growth_exponents"] = {
        "eom_per_state": {
            name: growth_exponent(
                [n for n in sizes if name in out["eom"][n]],
                [
                    out["eom"][n][name]["per_state_s"]
                    for n in sizes
                    if name in out["eom"][n]
                ],
            )
            for name in names
        },
        "trajectory": {
            name: growth_exponent(
                [n for n in out["trajectory"] if name in out["trajectory"][n]],
                [
                    out["trajectory"][n][name]["median_s"]
                    for n in out["trajectory"]
                    if name in out["trajectory"][n]
                ],
            )
            for name in names
        },
    }
    print("growth exponents:", json.dumps(out["growth_exponents"]))
    return out


def plot(results: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(17, 5))
    sizes = results["sizes"]
    for ax, key, label in (
        (axes[0], "per_state_s", "EOM per state (s), jit(vmap)"),
        (axes[1], "compile_s", "EOM compile (s)"),
    ):
        for name in results["eom"][sizes[0]]:
            xs = [n for n in sizes if name in results["eom"][n]]
            ax.loglog(xs, [results["eom"][n][name][key] for n in xs], "o-", label=name)
        ax.set_xlabel("N (links)")
        ax.set_title(label)
        ax.legend(fontsize=7)
    ax = axes[2]
    traj = results["trajectory"]
    for name in results["eom"][sizes[0]]:
        xs = [n for n in traj if name in traj[n]]
        if xs:
            ax.loglog(xs, [traj[n][name]["median_s"] for n in xs], "o-", label=name)
    ax.set_xlabel("N (links)")
    ax.set_title(f"simulate, t in [0, {T1:g}], Tsit5 rtol {TOL:g} (s)")
    ax.legend(fontsize=7)
    fig.suptitle("N-link chain in Cartesian coordinates (n = 2N, k = N)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument(
        "--out",
        default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results"),
    )
    parser.add_argument("--sizes", type=int, nargs="+")
    parser.add_argument("--dense-trajectory-max", type=int, default=32)
    parser.add_argument("--trajectory-max", type=int, default=256)
    opts = parser.parse_args()
    if opts.quick:
        sizes = opts.sizes or [1, 2, 4, 8, 16]
        batch, repeats = 100, 3
    else:
        sizes = opts.sizes or [1, 2, 4, 8, 16, 32, 64, 128, 256]
        batch, repeats = 1000, 9
    results = {"machine": machine_info(diffrax=diffrax.__version__)}
    results.update(
        run(sizes, batch, repeats, opts.dense_trajectory_max, opts.trajectory_max)
    )
    os.makedirs(opts.out, exist_ok=True)
    path = os.path.join(opts.out, "chain.json")
    with open(path, "w") as f:
        json.dump(results, f, indent=1, default=str)
    plot(results, os.path.join(opts.out, "chain.png"))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
