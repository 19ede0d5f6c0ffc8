"""Benchmark `constrained_jax.extremize` against SciPy, at matched accuracy.

Two problems:

1. **A batch of small problems**: 10,000 instances of the cylinder-volume scene
   (`constrained_jax.scenes.cylinder_volume`, `n = 2` unknowns, `k = 1` constraint,
   a 3 x 3 KKT system) with `b` log-uniform in `[1e-2, 1e2]` and `l` log-uniform in
   `[1e-1, 1e1]`, solved by one `jax.jit(jax.vmap(...))` call. Compared with a Python
   loop of `scipy.optimize.minimize` (SLSQP and trust-constr, analytic derivatives,
   tolerances tightened until the error against the closed form is comparable),
   timed on a subset and reported as throughput (problems per second). Ablation: the
   same batch with `DenseLU(unroll_max=0)`, which factors the KKT matrix with LAPACK
   instead of the unrolled elimination.
2. **One large problem**: the maximum-entropy distribution over `n` states with
   energies `E = linspace(0, 1, n)` and prescribed first and second moments, solved
   matrix-free (`Newton(linear_solver=MINRES(...))`) for `n` up to 100,000, against a
   dense `Newton()` and SciPy's SLSQP at small `n`. The reference is the Boltzmann-like
   solution `p ~ exp(-b E - g E^2)`, with `(b, g)` from a Newton iteration on the
   convex dual.

Every JAX time is measured after compilation (ahead-of-time `lower().compile()`, one
warm-up call, then the median of several calls, each ended by `block_until_ready`);
compile times are reported separately. Run with `--quick` for a smoke test.

    python benchmarks/extremize.py [--quick] [--out benchmarks/results]
"""

import argparse
import json
import os
import time
import warnings

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import scipy  # noqa: E402
import scipy.optimize  # noqa: E402
from _common import machine_info, time_jax, time_loop  # noqa: E402

import constrained_jax as cjax  # noqa: E402
from constrained_jax.scenes import cylinder_volume as cyl  # noqa: E402


SEED = 0

# SciPy settings, tightened by hand until SciPy's error against the reference is
# about 1e-8 or better where it gets there. SciPy's stopping tests are
# absolute in the objective, so the objective is scaled to be O(1) at the start point
# (a per-problem constant that does not use the solution).
SLSQP_OPTIONS = {"ftol": 1e-16, "maxiter": 1000}
# A looser SLSQP, to show what the last digits of accuracy cost SciPy.
SLSQP_LOOSE_OPTIONS = {"ftol": 1e-14, "maxiter": 1000}
TRUST_CONSTR_OPTIONS = {"gtol": 1e-12, "xtol": 1e-12, "maxiter": 1000}
MAXENT_SLSQP_OPTIONS = {"ftol": 1e-16, "maxiter": 1000}

# The maximum-entropy problem: moments <E> and <E^2>.
MEAN_ENERGY = 0.35
MEAN_SQUARE_ENERGY = 0.2


# ---------------------------------------------------------------------------------
# Errors (timing helpers: benchmarks/_common.py)
# ---------------------------------------------------------------------------------


def relative_error(value, reference):
    value, reference = np.asarray(value), np.asarray(reference)
    return np.abs(value - reference) / np.abs(reference)


# ---------------------------------------------------------------------------------
# 1-3. The cylinder batch
# ---------------------------------------------------------------------------------


def cylinder_problems(num: int):
    rng = np.random.default_rng(SEED)
    b = 10.0 ** rng.uniform(-2.0, 2.0, num)
    l = 10.0 ** rng.uniform(-1.0, 1.0, num)
    return b, l


def cylinder_reference(b, l) -> dict:
    ref = cyl.closed_form(b, l)
    return {name: np.asarray(value) for name, value in ref.items()}


def cylinder_errors(a, h, multiplier, volume, ref) -> dict:
    errors = {
        "a": float(np.max(relative_error(a, ref["a"]))),
        "h": float(np.max(relative_error(h, ref["h"]))),
        "multiplier": float(np.max(relative_error(multiplier, ref["multiplier"]))),
        "volume": float(np.max(relative_error(volume, ref["volume"]))),
    }
    errors["max"] = max(errors.values())
    return errors


def cylinder_jax_batch(b, l, solver, repeats):
    args = {"b": jnp.asarray(b), "l": jnp.asarray(l)}
    batched = jax.vmap(
        lambda args: cjax.extremize(
            cyl.volume,
            cyl.initial_guess(args["b"], args["l"]),
            args,
            constraints=cyl.constraint,
            solver=solver,
        )
    )
    sol, info = time_jax(batched, args, repeats=repeats)
    ref = cylinder_reference(b, l)
    x = np.asarray(sol.x)
    info["errors"] = cylinder_errors(
        x[:, 0], x[:, 1], np.asarray(sol.multipliers)[:, 0], np.asarray(sol.value), ref
    )
    info["num_problems"] = len(b)
    info["throughput_per_s"] = len(b) / info["median_s"]
    info["all_successful"] = bool(np.all(sol.result == cjax.RESULTS.successful))
    info["all_maxima"] = bool(np.all(sol.kind == cjax.EXTREMUM.maximum))
    steps = np.asarray(sol.stats["num_steps"])
    info["newton_steps"] = {"median": float(np.median(steps)), "max": int(steps.max())}
    return info


def cylinder_jax_loop(b, l, repeats):
    """The same solve, jitted for one problem, called once per problem from Python."""
    solve = jax.jit(
        lambda args: cjax.extremize(
            cyl.volume,
            cyl.initial_guess(args["b"], args["l"]),
            args,
            constraints=cyl.constraint,
        )
    )
    problems = [
        {"b": jnp.asarray(bi), "l": jnp.asarray(li)}
        for bi, li in zip(b, l, strict=True)
    ]
    start = time.perf_counter()
    jax.block_until_ready(solve(problems[0]))
    first_call = time.perf_counter() - start
    sols, median, times = time_loop(
        lambda p: jax.block_until_ready(solve(p)), problems, repeats
    )
    ref = cylinder_reference(b, l)
    x = np.stack([np.asarray(s.x) for s in sols])
    lam = np.array([float(s.multipliers[0]) for s in sols])
    vol = np.array([float(s.value) for s in sols])
    return {
        "num_problems": len(b),
        "first_call_s": first_call,
        "median_s": median,
        "times_s": times,
        "throughput_per_s": len(b) / median,
        "errors": cylinder_errors(x[:, 0], x[:, 1], lam, vol, ref),
    }


def _cylinder_numpy(b, l):
    """`-V / V0` and its derivatives, `G` and its derivatives, in NumPy."""
    x0 = np.array([l / (4 * np.pi), np.sqrt(b * l / 2)])
    scale = 1.0 / (np.pi * x0[0] ** 2 * x0[1])

    def objective(x):
        return -scale * np.pi * x[0] ** 2 * x[1]

    def gradient(x):
        return -scale * np.pi * np.array([2 * x[0] * x[1], x[0] ** 2])

    def hessian(x):
        return -scale * np.pi * np.array([[2 * x[1], 2 * x[0]], [2 * x[0], 0.0]])

    def constraint(x):
        return np.array([2 * np.pi * x[0] + x[1] ** 2 / b - l])

    def constraint_jacobian(x):
        return np.array([[2 * np.pi, 2 * x[1] / b]])

    def constraint_hessian(x, v):
        return v[0] * np.array([[0.0, 0.0], [0.0, 2.0 / b]])

    return {
        "x0": x0,
        "scale": scale,
        "objective": objective,
        "gradient": gradient,
        "hessian": hessian,
        "constraint": constraint,
        "constraint_jacobian": constraint_jacobian,
        "constraint_hessian": constraint_hessian,
    }


def slsqp_cylinder(problem, options=SLSQP_OPTIONS):
    b, l = problem
    p = _cylinder_numpy(b, l)
    constraint = {"type": "eq", "fun": p["constraint"], "jac": p["constraint_jacobian"]}
    res = scipy.optimize.minimize(
        p["objective"],
        p["x0"],
        jac=p["gradient"],
        method="SLSQP",
        constraints=[constraint],
        options=options,
    )
    # SciPy: grad(-V/V0) = mu grad G, i.e. grad V + (mu V0) grad G = 0.
    return res.x, res.multipliers[0] / p["scale"], bool(res.success), res.nit


def trust_constr_cylinder(problem):
    b, l = problem
    p = _cylinder_numpy(b, l)
    constraint = scipy.optimize.NonlinearConstraint(
        p["constraint"],
        0.0,
        0.0,
        jac=p["constraint_jacobian"],
        hess=p["constraint_hessian"],
    )
    res = scipy.optimize.minimize(
        p["objective"],
        p["x0"],
        jac=p["gradient"],
        hess=p["hessian"],
        method="trust-constr",
        constraints=[constraint],
        options=TRUST_CONSTR_OPTIONS,
    )
    # SciPy: grad(-V/V0) + v grad G = 0, i.e. grad V - (v V0) grad G = 0.
    return res.x, -res.v[0][0] / p["scale"], bool(res.success), res.nit


def cylinder_scipy(solve_one, b, l, repeats):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        results, median, times = time_loop(
            solve_one, list(zip(b, l, strict=True)), repeats
        )
    x = np.stack([r[0] for r in results])
    lam = np.array([r[1] for r in results])
    vol = np.pi * x[:, 0] ** 2 * x[:, 1]
    iterations = np.array([r[3] for r in results])
    return {
        "num_problems": len(b),
        "median_s": median,
        "times_s": times,
        "throughput_per_s": len(b) / median,
        "errors": cylinder_errors(x[:, 0], x[:, 1], lam, vol, cylinder_reference(b, l)),
        "num_successful": int(sum(r[2] for r in results)),
        "iterations": {
            "median": float(np.median(iterations)),
            "max": int(iterations.max()),
        },
    }


# ---------------------------------------------------------------------------------
# 4. Maximum entropy
# ---------------------------------------------------------------------------------


def entropy(p, args):
    """`S = -sum_i p_i log p_i`."""
    return -jnp.sum(p * jnp.log(p))


def moments(p, args):
    """`G = (sum p - 1, sum p E - <E>, sum p E^2 - <E^2>)`."""
    energy = args["energy"]
    return jnp.stack(
        [
            jnp.sum(p) - 1.0,
            jnp.dot(p, energy) - args["mean"],
            jnp.dot(p, energy**2) - args["mean_square"],
        ]
    )


def maxent_reference(energy: np.ndarray, tol: float = 1e-14):
    """`p ~ exp(-b E - g E^2)`, `(b, g)` minimising `log Z + b <E> + g <E^2>`.

    The dual is convex with gradient `(<E>, <E^2>) - E_p[(E, E^2)]` and Hessian the
    covariance of `(E, E^2)` under `p`: Newton's method with a backtracking line
    search, stopped when the step is below `tol`.
    """
    features = np.stack([energy, energy**2])
    target = np.array([MEAN_ENERGY, MEAN_SQUARE_ENERGY])

    def parts(theta):
        s = -(theta @ features)
        shift = s.max()
        w = np.exp(s - shift)
        z = w.sum()
        p = w / z
        mean = features @ p
        cov = (features * p) @ features.T - np.outer(mean, mean)
        dual = np.log(z) + shift + theta @ target
        return dual, target - mean, cov, p

    theta = np.zeros(2)
    iterations = 0
    for _ in range(100):
        iterations += 1
        dual, grad, hess, _ = parts(theta)
        step = -np.linalg.solve(hess, grad)
        t = 1.0
        while (
            parts(theta + t * step)[0] > dual + 1e-4 * t * (grad @ step) and t > 1e-12
        ):
            t *= 0.5
        theta = theta + t * step
        if np.max(np.abs(t * step)) <= tol * max(1.0, np.max(np.abs(theta))):
            break
    _, grad, _, p = parts(theta)
    return p, {
        "b": float(theta[0]),
        "g": float(theta[1]),
        "dual_iterations": iterations,
        "dual_gradient_norm": float(np.max(np.abs(grad))),
    }


def maxent_errors(p, reference) -> dict:
    p = np.asarray(p)
    return {
        "max_pointwise": float(np.max(relative_error(p, reference))),
        "norm": float(np.linalg.norm(p - reference) / np.linalg.norm(reference)),
    }


def maxent_jax(n, solver, solver_name, repeats):
    energy = np.linspace(0.0, 1.0, n)
    reference, _ = maxent_reference(energy)
    args = {
        "energy": jnp.asarray(energy),
        "mean": jnp.asarray(MEAN_ENERGY),
        "mean_square": jnp.asarray(MEAN_SQUARE_ENERGY),
    }
    p0 = jnp.full((n,), 1.0 / n)
    fn = lambda p0, args: cjax.extremize(
        entropy, p0, args, constraints=moments, solver=solver, throw=False
    )
    sol, info = time_jax(fn, p0, args, repeats=repeats)
    info.update(
        n=n,
        method=f"constrained_jax {solver_name}",
        errors=maxent_errors(sol.x, reference),
        successful=bool(sol.result == cjax.RESULTS.successful),
        maximum=bool(sol.kind == cjax.EXTREMUM.maximum),
        newton_steps=int(sol.stats["num_steps"]),
        kkt_residual_rms=float(sol.stats["kkt_residual"]),
        dense_kkt_bytes=n * n * 8,
    )
    return info


def maxent_slsqp(n, repeats):
    energy = np.linspace(0.0, 1.0, n)
    reference, _ = maxent_reference(energy)
    a = np.stack([np.ones(n), energy, energy**2])
    m = np.array([1.0, MEAN_ENERGY, MEAN_SQUARE_ENERGY])
    # Minimise n sum p log p: the factor n makes the objective's curvature O(1) in
    # the scaled unknowns n p, so that `ftol` (absolute) is meaningful.
    objective = lambda p: n * np.sum(p * np.log(p))
    gradient = lambda p: n * (np.log(p) + 1.0)

    def solve(_):
        return scipy.optimize.minimize(
            objective,
            np.full(n, 1.0 / n),
            jac=gradient,
            method="SLSQP",
            bounds=[(1e-12, 1.0)] * n,
            constraints=[
                {"type": "eq", "fun": lambda p: a @ p - m, "jac": lambda p: a}
            ],
            options=MAXENT_SLSQP_OPTIONS,
        )

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        results, median, times = time_loop(solve, [None], repeats)
    res = results[0]
    return {
        "n": n,
        "method": "scipy SLSQP",
        "median_s": median,
        "times_s": times,
        "errors": maxent_errors(res.x, reference),
        "successful": bool(res.success),
        "iterations": int(res.nit),
        "dense_kkt_bytes": n * n * 8,
    }


# ---------------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------------


def _short(name: str) -> str:
    """A short label for a method, for the plot's axis."""
    table = {
        "cjax vmap, DenseLU unrolled (default)": "cjax vmap\nunrolled LU",
        "cjax vmap, DenseLU(unroll_max=0): LAPACK": "cjax vmap\nLAPACK LU",
        "cjax jit, Python loop": "cjax jit\nPython loop",
        "scipy SLSQP, Python loop": "SLSQP\nPython loop",
        "scipy SLSQP ftol=1e-14, Python loop": "SLSQP ftol=1e-14\nPython loop",
        "scipy trust-constr, Python loop": "trust-constr\nPython loop",
        "constrained_jax Newton() [DenseLU]": "cjax dense",
        "constrained_jax Newton(MINRES)": "cjax MINRES",
        "scipy SLSQP": "SLSQP",
    }
    return table.get(name, name)


def plot(results: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(14, 5.5))

    cyl_rows = results["cylinder"]["methods"]
    names = list(cyl_rows)
    values = [cyl_rows[k]["throughput_per_s"] for k in names]
    colors = ["C3" if "scipy" in k else "C0" for k in names]
    bars = left.bar(range(len(names)), values, color=colors)
    left.set_yscale("log")
    left.set_xticks(range(len(names)), [_short(k) for k in names], fontsize=8)
    left.set_ylabel("problems per second (after compilation)")
    left.set_title(
        f"Cylinder volume, {results['cylinder']['num_problems']:,} problems (n=2, k=1)"
    )
    for bar, k in zip(bars, names, strict=True):
        left.annotate(
            f"{values[names.index(k)]:.3g}/s\nerr {cyl_rows[k]['errors']['max']:.1e}",
            (bar.get_x() + bar.get_width() / 2, bar.get_height()),
            ha="center",
            va="bottom",
            fontsize=8,
        )
    left.set_ylim(top=max(values) * 20)

    rows = results["maxent"]["runs"]
    labels = [f"{_short(r['method'])}\nn={r['n']:,}" for r in rows]
    times = [r["median_s"] for r in rows]
    colors = ["C3" if "scipy" in r["method"] else "C0" for r in rows]
    bars = right.bar(range(len(rows)), times, color=colors)
    right.set_yscale("log")
    right.set_xticks(range(len(rows)), labels, fontsize=7)
    right.set_ylabel("seconds per solve (after compilation)")
    right.set_title("Maximum entropy with 3 moment constraints")
    for bar, r in zip(bars, rows, strict=True):
        right.annotate(
            f"{r['median_s']:.2g}s\nerr {r['errors']['max_pointwise']:.1e}",
            (bar.get_x() + bar.get_width() / 2, bar.get_height()),
            ha="center",
            va="bottom",
            fontsize=7,
        )
    right.set_ylim(top=max(times) * 20)

    fig.suptitle(
        f"constrained_jax.extremize, jax {results['machine']['versions']['jax']}, "
        f"{results['machine']['cpu_count']}-core CPU; errors are max relative errors "
        "against the exact solution",
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
    parser.add_argument(
        "--maxent-slsqp-n",
        type=int,
        nargs="*",
        default=None,
        help="sizes n at which to run SLSQP on the maximum-entropy problem "
        "(default 200, or 100 with --quick; n = 1000 takes minutes)",
    )
    opts = parser.parse_args()

    if opts.quick:
        num, num_slsqp, num_trust, num_loop = 1_000, 100, 50, 100
        repeats, scipy_repeats = 3, 1
        maxent_sizes = [
            (100, ("dense", "minres")),
            (1_000, ("dense", "minres")),
            (10_000, ("minres",)),
        ]
        slsqp_sizes = [100]
    else:
        num, num_slsqp, num_trust, num_loop = 10_000, 1_000, 300, 1_000
        repeats, scipy_repeats = 7, 3
        maxent_sizes = [
            (200, ("dense", "minres")),
            (1_000, ("dense", "minres")),
            (10_000, ("minres",)),
            (100_000, ("minres",)),
        ]
        slsqp_sizes = [200]
    if opts.maxent_slsqp_n is not None:
        slsqp_sizes = opts.maxent_slsqp_n
    os.makedirs(opts.out, exist_ok=True)
    results = {"machine": machine_info(scipy=scipy.__version__), "quick": opts.quick}
    print(json.dumps(results["machine"], indent=1))

    # 1-3. Cylinder batch.
    b, l = cylinder_problems(num)
    methods = {}
    print(f"\n== cylinder: {num} problems ==")
    methods["cjax vmap, DenseLU unrolled (default)"] = cylinder_jax_batch(
        b, l, cjax.Newton(), repeats
    )
    methods["cjax vmap, DenseLU(unroll_max=0): LAPACK"] = cylinder_jax_batch(
        b, l, cjax.Newton(linear_solver=cjax.DenseLU(unroll_max=0)), repeats
    )
    methods["cjax jit, Python loop"] = cylinder_jax_loop(
        b[:num_loop], l[:num_loop], scipy_repeats
    )
    methods["scipy SLSQP, Python loop"] = cylinder_scipy(
        slsqp_cylinder, b[:num_slsqp], l[:num_slsqp], scipy_repeats
    )
    methods["scipy SLSQP ftol=1e-14, Python loop"] = cylinder_scipy(
        lambda problem: slsqp_cylinder(problem, SLSQP_LOOSE_OPTIONS),
        b[:num_slsqp],
        l[:num_slsqp],
        scipy_repeats,
    )
    methods["scipy trust-constr, Python loop"] = cylinder_scipy(
        trust_constr_cylinder, b[:num_trust], l[:num_trust], scipy_repeats
    )
    default = methods["cjax vmap, DenseLU unrolled (default)"]
    for name, row in methods.items():
        row["speedup_of_default_vmap"] = (
            default["throughput_per_s"] / row["throughput_per_s"]
        )
        print(
            f"{name:45s} {row['throughput_per_s']:12.4g} problems/s  "
            f"max rel err {row['errors']['max']:.2e}  "
            f"(default vmap is {row['speedup_of_default_vmap']:.3g}x)"
        )
    for name in list(methods)[:2]:
        row = methods[name]
        print(
            f"{name}: compile {row['compile_s']:.2f} s, trace+lower "
            f"{row['trace_lower_s']:.2f} s, first call {row['first_call_s']:.2f} s, "
            f"LAPACK calls {row['lapack_calls_in_hlo']}"
        )
    results["cylinder"] = {
        "num_problems": num,
        "seed": SEED,
        "distribution": "b log-uniform in [1e-2, 1e2], l log-uniform in [1e-1, 1e1]",
        "scipy_options": {
            "SLSQP": SLSQP_OPTIONS,
            "SLSQP ftol=1e-14": SLSQP_LOOSE_OPTIONS,
            "trust-constr": TRUST_CONSTR_OPTIONS,
        },
        "methods": methods,
    }

    # 4. Maximum entropy.
    print("\n== maximum entropy ==")
    solvers = {
        "dense": ("Newton() [DenseLU]", cjax.Newton()),
        "minres": (
            "Newton(MINRES)",
            cjax.Newton(linear_solver=cjax.MINRES(rtol=1e-12, atol=0.0, max_steps=500)),
        ),
    }
    runs = []
    jax_sizes = dict(maxent_sizes)
    for n in sorted(set(jax_sizes) | set(slsqp_sizes)):
        for kind in jax_sizes.get(n, ()):
            name, solver = solvers[kind]
            runs.append(maxent_jax(n, solver, name, repeats if n < 100_000 else 3))
        if n in slsqp_sizes:
            runs.append(maxent_slsqp(n, scipy_repeats))
    for run in runs:
        extra = (
            f"compile {run['compile_s']:.2f} s, XLA temp "
            f"{run['xla_memory'].get('temp_size_in_bytes', 0) / 1e6:.1f} MB, "
            f"steps {run['newton_steps']}, ok {run['successful']}"
            if "compile_s" in run
            else f"iterations {run['iterations']}, ok {run['successful']}"
        )
        print(
            f"n={run['n']:>7} {run['method']:30s} {run['median_s']:9.4f} s  "
            f"max rel err {run['errors']['max_pointwise']:.2e}  "
            f"(dense KKT would be {run['dense_kkt_bytes'] / 1e6:.3g} MB)  {extra}"
        )
    results["maxent"] = {
        "problem": (
            "maximize -sum p log p s.t. sum p = 1, sum p E = 0.35, sum p E^2 = 0.2, "
            "E = linspace(0, 1, n), p0 = 1/n"
        ),
        "references": {
            str(run["n"]): maxent_reference(np.linspace(0.0, 1.0, run["n"]))[1]
            for run in runs
        },
        "scipy_options": {"SLSQP": MAXENT_SLSQP_OPTIONS},
        "runs": runs,
    }

    json_path = os.path.join(opts.out, "extremize.json")
    with open(json_path, "w") as f:
        json.dump(results, f, indent=1)
    png_path = os.path.join(opts.out, "extremize.png")
    plot(results, png_path)
    print(f"\nwrote {json_path} and {png_path}")


if __name__ == "__main__":
    main()
