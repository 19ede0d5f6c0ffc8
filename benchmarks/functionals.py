"""Benchmark `constrained_jax.solve_functional` on the hanging rope (catenary).

Case: ends (0, 0) and (1, 0.5), length C = 2, rho g = 2.5; reference: the closed form
(`scenes.catenary.closed_form`). Error = max |y - y_exact| over 201 points (the
interpolant) and the relative error of lambda.

1. Work-precision: error and time against the number of nodes for `Chebyshev(N)`
   and `PiecewiseLinear(N)` (up to 100,001 nodes), and the shooting method.
2. Time to reach 1e-10: the smallest Chebyshev grid that does, against SciPy's
   `solve_bvp` (y'' = rho g (1 + y'^2) / (rho g y + lambda), s' = sqrt(1 + y'^2),
   lambda an unknown parameter, tolerance scanned down until the error is <= 1e-10)
   and `scipy.optimize.minimize(method="SLSQP")` on the same Chebyshev
   discretization (objective, constraint and their gradients jitted JAX functions).

JAX times: after compilation (benchmarks/_common.py), median of repeats.

    python benchmarks/functionals.py [--quick] [--out benchmarks/results]
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
import scipy.integrate  # noqa: E402
import scipy.optimize  # noqa: E402
from _common import machine_info, time_jax, time_loop  # noqa: E402

import constrained_jax as cjax  # noqa: E402
from constrained_jax.scenes import catenary as cat  # noqa: E402


XL, YL, XR, YR, LENGTH, RHO_G = 0.0, 0.0, 1.0, 0.5, 2.0, 2.5
REF = cat.closed_form(XL, YL, XR, YR, LENGTH, RHO_G)
XS = np.linspace(XL, XR, 201)
FUN = cat.functional(XL, YL, XR, YR)


def args():
    return {"rho_g": jnp.asarray(RHO_G), "length": jnp.asarray(LENGTH)}


def errors(y_at_xs, lam):
    return {
        "y": float(np.max(np.abs(np.asarray(y_at_xs) - REF["y"](XS)))),
        "multiplier": float(abs(lam - REF["multiplier"]) / abs(REF["multiplier"])),
    }


def direct(discretization, repeats):
    guess = cat.initial_guess(XL, YL, XR, YR, LENGTH)

    def solve(a):
        sol = cjax.solve_functional(FUN, a, discretization=discretization, y0=guess)
        return sol(jnp.asarray(XS)), sol.multipliers.integral[0], sol.stats["num_steps"]

    (y, lam, steps), info = time_jax(solve, args(), repeats=repeats)
    info["errors"] = errors(y, float(lam))
    info["newton_steps"] = int(steps)
    return info


def shooting(repeats, tol):
    coarse = cjax.solve_functional(
        FUN,
        args(),
        discretization=cjax.PiecewiseLinear(21),
        y0=cat.initial_guess(XL, YL, XR, YR, LENGTH),
    )
    slope0, lam0 = coarse.derivative(0.0), coarse.multipliers.integral

    def solve(a):
        sol = cjax.solve_shooting(
            FUN, a, slope0=slope0, multipliers0=lam0, rtol=tol, atol=tol
        )
        return sol(jnp.asarray(XS)), sol.multipliers.integral[0]

    (y, lam), info = time_jax(solve, args(), repeats=repeats)
    info["errors"] = errors(y, float(lam))
    info["tol"] = tol
    return info


def solve_bvp(tol, repeats):
    def rhs(x, s, p):
        y, yp, _ = s
        return np.vstack(
            [yp, RHO_G * (1 + yp**2) / (RHO_G * y + p[0]), np.sqrt(1 + yp**2)]
        )

    def bc(sa, sb, p):
        return np.array([sa[0] - YL, sb[0] - YR, sa[2], sb[2] - LENGTH])

    x0 = np.linspace(XL, XR, 11)
    guess = np.asarray(jax.vmap(cat.initial_guess(XL, YL, XR, YR, LENGTH))(x0))
    s0 = np.vstack([guess, np.gradient(guess, x0), np.linspace(0, LENGTH, 11)])

    def one(_):
        return scipy.integrate.solve_bvp(rhs, bc, x0, s0, p=[2.0], tol=tol)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        results, median, times = time_loop(one, [None], repeats)
    res = results[0]
    return {
        "tol": tol,
        "median_s": median,
        "times_s": times,
        "success": bool(res.success),
        "mesh_nodes": int(res.x.size),
        "errors": errors(res.sol(XS)[0], float(res.p[0])),
    }


def slsqp(num_nodes, repeats):
    disc = cjax.Chebyshev(num_nodes)
    nodes = disc.nodes((jnp.asarray(XL), jnp.asarray(XR)))
    a = args()

    def full(inner):
        return jnp.concatenate([jnp.array([YL]), inner, jnp.array([YR])])[:, None]

    def energy(inner):
        lag = lambda y, yp, x: cat.potential_energy(y[0], yp[0], x, a)
        return disc.integrate(lag, full(inner), (nodes[0], nodes[-1]))

    def length(inner):
        arc = lambda y, yp, x: cat.arc_length(y[0], yp[0], x, a)
        return disc.integrate(arc, full(inner), (nodes[0], nodes[-1])) - LENGTH

    f, g = jax.jit(energy), jax.jit(jax.grad(energy))
    c, dc = jax.jit(length), jax.jit(jax.grad(length))
    x0 = np.asarray(jax.vmap(cat.initial_guess(XL, YL, XR, YR, LENGTH))(nodes))[1:-1]
    f(x0), g(x0), c(x0), dc(x0)  # compile

    def one(_):
        return scipy.optimize.minimize(
            lambda x: float(f(x)),
            x0,
            jac=lambda x: np.asarray(g(x)),
            method="SLSQP",
            constraints=[
                {
                    "type": "eq",
                    "fun": lambda x: float(c(x)),
                    "jac": lambda x: np.asarray(dc(x))[None],
                }
            ],
            options={"ftol": 1e-16, "maxiter": 1000},
        )

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        results, median, times = time_loop(one, [None], repeats)
    res = results[0]
    values = np.concatenate([[YL], res.x, [YR]])
    y = jax.vmap(lambda x: disc.interpolate((nodes[0], nodes[-1]), values, x))(XS)
    # SciPy: grad U = mu grad C, i.e. lambda = -mu.
    return {
        "num_nodes": num_nodes,
        "median_s": median,
        "times_s": times,
        "success": bool(res.success),
        "iterations": int(res.nit),
        "errors": errors(y, -float(res.multipliers[0])),
    }


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true")
    parser.add_argument(
        "--out", default=os.path.join(os.path.dirname(__file__), "results")
    )
    opts = parser.parse_args()
    repeats = 3 if opts.quick else 11
    start = time.perf_counter()
    out = {
        "machine": machine_info(scipy=scipy.__version__),
        "case": {"ends": [[XL, YL], [XR, YR]], "length": LENGTH, "rho_g": RHO_G},
    }
    cheb_sizes = (
        [8, 12, 16, 20, 24, 32] if opts.quick else [8, 12, 16, 20, 24, 32, 48, 64]
    )
    mesh_sizes = [101, 1001, 10_001] if opts.quick else [101, 1001, 10_001, 100_001]
    out["chebyshev"] = {n: direct(cjax.Chebyshev(n), repeats) for n in cheb_sizes}
    out["piecewise_linear"] = {
        n: direct(cjax.PiecewiseLinear(n), max(3, repeats // 3)) for n in mesh_sizes
    }
    out["shooting"] = {tol: shooting(repeats, tol) for tol in (1e-8, 1e-11)}
    out["solve_bvp"] = {
        tol: solve_bvp(tol, repeats) for tol in (1e-6, 1e-8, 1e-10, 1e-11)
    }
    # The smallest Chebyshev grid reaching 1e-10, and SLSQP on it.
    target = 1e-10
    best = min(n for n, r in out["chebyshev"].items() if r["errors"]["y"] <= target)
    out["slsqp"] = slsqp(best, max(3, repeats // 3))
    bvp_ok = [
        r
        for r in out["solve_bvp"].values()
        if r["success"] and r["errors"]["y"] <= target
    ]
    out["time_to_1e-10"] = {
        "chebyshev_nodes": best,
        "chebyshev_s": out["chebyshev"][best]["median_s"],
        "solve_bvp_s": min(r["median_s"] for r in bvp_ok) if bvp_ok else None,
        "slsqp_s": out["slsqp"]["median_s"],
        "slsqp_error": out["slsqp"]["errors"]["y"],
    }
    out["wall_s"] = time.perf_counter() - start
    os.makedirs(opts.out, exist_ok=True)
    with open(os.path.join(opts.out, "functionals.json"), "w") as fh:
        json.dump(out, fh, indent=1, default=str)
    plot(out, os.path.join(opts.out, "functionals.png"))
    for name in ("chebyshev", "piecewise_linear"):
        for n, r in out[name].items():
            print(
                f"{name:17s} N={n:6d} err={r['errors']['y']:.2e} "
                f"lam={r['errors']['multiplier']:.1e} t={r['median_s'] * 1e3:8.2f} ms "
                f"compile={r['compile_s']:.1f} s"
            )
    for tol, r in out["shooting"].items():
        print(
            f"shooting tol={tol:.0e} err={r['errors']['y']:.2e} "
            f"t={r['median_s'] * 1e3:.2f} ms"
        )
    for tol, r in out["solve_bvp"].items():
        print(
            f"solve_bvp tol={tol:.0e} err={r['errors']['y']:.2e} "
            f"t={r['median_s'] * 1e3:.2f} ms "
            f"nodes={r['mesh_nodes']} success={r['success']}"
        )
    r = out["slsqp"]
    print(
        f"SLSQP N={r['num_nodes']} err={r['errors']['y']:.2e} "
        f"t={r['median_s'] * 1e3:.2f} ms "
        f"success={r['success']} iterations={r['iterations']}"
    )
    print(out["time_to_1e-10"], f"wall {out['wall_s']:.0f} s")


def plot(out, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for name, marker in (("chebyshev", "o-"), ("piecewise_linear", "s-")):
        rs = list(out[name].items())
        ax.loglog(
            [r["median_s"] for _, r in rs],
            [max(r["errors"]["y"], 1e-16) for _, r in rs],
            marker,
            label=name,
        )
        for n, r in rs:
            ax.annotate(
                str(n), (r["median_s"], max(r["errors"]["y"], 1e-16)), fontsize=7
            )
    for name, marker in (("shooting", "^"), ("solve_bvp", "v")):
        rs = list(out[name].values())
        ax.loglog(
            [r["median_s"] for r in rs],
            [r["errors"]["y"] for r in rs],
            marker,
            label=name if name == "shooting" else "scipy solve_bvp",
        )
    r = out["slsqp"]
    ax.loglog(
        [r["median_s"]],
        [r["errors"]["y"]],
        "D",
        label=f"SLSQP (Chebyshev {r['num_nodes']})",
    )
    ax.set_xlabel("time per solve [s] (after compilation)")
    ax.set_ylabel("max |y - y_exact|")
    ax.set_title("Catenary: work-precision")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    main()
