"""Benchmark `extremize` with inequalities against SciPy's SLSQP and trust-constr, at
matched accuracy.

The problem: the Euclidean projection of `c / 2` onto the probability simplex,

    minimize  sum_i p_i^2 - c . p   subject to  sum_i p_i = 1,  p >= 0,

(the "Gini" maximum-entropy distribution with a linear term strong enough that
about half of the `p_i` are zero), whose exact solution is the sort-based simplex
projection (Held, Wolfe and Crowder 1974; Duchi et al. 2008). For `n` states:

1. one problem: our `jit`-compiled `extremize(..., lower=0)` (after compilation,
   median of repeats) against `scipy.optimize.minimize` with analytic gradients and
   Hessians, the error of each against the exact solution reported beside its time
   (SciPy up to n = 200; n = 2,000 and 10,000 ours alone: the bounds are diagonal
   rows, eliminated in each step, so they scale like equality constraints);
2. batches of 100 and 1,000 problems with different `c`: one
   `jax.jit(jax.vmap(...))` call against a SciPy loop (timed on 20 and scaled).

SciPy's tolerances are tightened until its error is about 1e-8 or better (its tests
are absolute; the objective is O(1) here).

    python benchmarks/inequalities.py [--quick] [--out benchmarks/results]
"""

import argparse
import json
import os
import statistics
import time
import warnings

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import scipy  # noqa: E402
import scipy.optimize  # noqa: E402
from _common import machine_info, time_jax  # noqa: E402

import constrained_jax as cjax  # noqa: E402


SEED = 0
SLSQP_OPTIONS = {"ftol": 1e-15, "maxiter": 1000}
TRUST_CONSTR_OPTIONS = {"gtol": 1e-12, "xtol": 1e-12, "maxiter": 2000}


def objective(p, c):
    return jnp.sum(p**2) - jnp.dot(c, p)


def exact(c: np.ndarray) -> np.ndarray:
    """The projection of `c / 2` onto the simplex (sort-based, exact)."""
    v = c / 2
    u = np.sort(v)[::-1]
    cumulative = np.cumsum(u) - 1
    rho = np.nonzero(u - cumulative / np.arange(1, v.size + 1) > 0)[0][-1]
    return np.maximum(v - cumulative[rho] / (rho + 1), 0.0)


def ours(c, p0):
    return cjax.extremize(
        objective,
        p0,
        c,
        constraints=lambda p, c: jnp.sum(p) - 1.0,
        lower=0.0,
        sense="minimize",
        throw=False,
    )


def scipy_solve(c: np.ndarray, method: str) -> np.ndarray:
    n = c.size
    fun = lambda p: float(p @ p - c @ p)
    jac = lambda p: 2 * p - c
    hess = lambda p: 2 * np.eye(n)
    equality = {
        "type": "eq",
        "fun": lambda p: p.sum() - 1,
        "jac": lambda p: np.ones((1, n)),
    }
    bounds = [(0.0, None)] * n
    p0 = np.full(n, 1.0 / n)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if method == "SLSQP":
            res = scipy.optimize.minimize(
                fun, p0, jac=jac, method="SLSQP", bounds=bounds,
                constraints=[equality], options=SLSQP_OPTIONS,
            )  # fmt: skip
        else:
            res = scipy.optimize.minimize(
                fun, p0, jac=jac, hess=hess, method="trust-constr", bounds=bounds,
                constraints=[scipy.optimize.LinearConstraint(np.ones((1, n)), 1, 1)],
                options=TRUST_CONSTR_OPTIONS,
            )  # fmt: skip
    return res.x


def problem(n: int, rng) -> np.ndarray:
    # Spread on the scale 1 / n of the answer, so that a good part of the states
    # is empty at the optimum.
    return (2.0 + 4.0 * rng.normal(size=n)) / n


SCIPY_MAX_N = 200


def one(n: int, repeats: int) -> dict:
    rng = np.random.default_rng(SEED + n)
    c = problem(n, rng)
    reference = exact(c)
    p0 = jnp.full((n,), 1.0 / n)
    out, info = time_jax(ours, jnp.asarray(c), p0, repeats=repeats)
    assert out.result == cjax.RESULTS.successful, cjax.RESULTS[out.result]
    row = {
        "n": n,
        "zeros": int(np.sum(reference == 0)),
        "ours": {
            "median_s": info["median_s"],
            "compile_s": info["trace_lower_s"] + info["compile_s"],
            "error": float(np.max(np.abs(np.asarray(out.x) - reference))),
            "steps": int(out.stats["num_steps"]),
        },
    }
    peers = ("SLSQP", "trust-constr") if n <= SCIPY_MAX_N else ()
    for method in peers:
        times = []
        for _ in range(max(1, repeats // 3)):
            start = time.perf_counter()
            x = scipy_solve(c, method)
            times.append(time.perf_counter() - start)
        row[method] = {
            "median_s": statistics.median(times),
            "error": float(np.max(np.abs(x - reference))),
        }
    print(
        f"n = {n:4d} ({row['zeros']} zeros): "
        f"ours {row['ours']['median_s'] * 1e3:8.2f} ms "
        f"(error {row['ours']['error']:.1e}, compile {row['ours']['compile_s']:.1f} s)"
        + "".join(
            f", {m} {row[m]['median_s'] * 1e3:8.2f} ms (error {row[m]['error']:.1e})"
            for m in peers
        )
    )
    return row


def batch(n: int, size: int, scipy_size: int, repeats: int) -> dict:
    rng = np.random.default_rng(SEED + 1000 + n)
    cs = np.stack([problem(n, rng) for _ in range(size)])
    references = np.stack([exact(c) for c in cs])
    p0 = jnp.full((size, n), 1.0 / n)
    out, info = time_jax(jax.vmap(ours), jnp.asarray(cs), p0, repeats=repeats)
    assert np.all(np.asarray(out.result._value) == cjax.RESULTS.successful._value)
    row = {
        "n": n,
        "size": size,
        "ours": {
            "per_problem_s": info["median_s"] / size,
            "error": float(np.max(np.abs(np.asarray(out.x) - references))),
        },
    }
    for method in ("SLSQP", "trust-constr"):
        start = time.perf_counter()
        xs = [scipy_solve(c, method) for c in cs[:scipy_size]]
        elapsed = time.perf_counter() - start
        row[method] = {
            "per_problem_s": elapsed / scipy_size,
            "error": float(np.max(np.abs(np.stack(xs) - references[:scipy_size]))),
        }
    print(
        f"batch of {size}, n = {n}: "
        f"ours {row['ours']['per_problem_s'] * 1e6:8.1f} us per problem "
        f"(error {row['ours']['error']:.1e})"
        + "".join(
            f", {m} {row[m]['per_problem_s'] * 1e6:8.1f} us "
            f"(error {row[m]['error']:.1e})"
            for m in ("SLSQP", "trust-constr")
        )
    )
    return row


def plot(results: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), layout="constrained")
    for name in ("ours", "SLSQP", "trust-constr"):
        rows = [r for r in results["one"] if name in r]
        ax.loglog(
            [r["n"] for r in rows],
            [r[name]["median_s"] for r in rows],
            "o-",
            label=name,
        )
    ax.set_xlabel("n (states)")
    ax.set_ylabel("time per solve [s] (after compilation)")
    ax.set_title("projection onto the simplex (p >= 0, sum p = 1)")
    ax.legend()
    fig.savefig(path, dpi=100)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument(
        "--out",
        default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results"),
    )
    opts = parser.parse_args()
    sizes = [10, 50] if opts.quick else [10, 50, 200, 2000, 10000]
    repeats = 3 if opts.quick else 9
    results = {
        "machine": machine_info(scipy=scipy.__version__),
        "one": [one(n, repeats) for n in sizes],
        "batch": [batch(10, size, 20, repeats) for size in (100, 1000)],
    }
    os.makedirs(opts.out, exist_ok=True)
    with open(os.path.join(opts.out, "inequalities.json"), "w") as f:
        json.dump(results, f, indent=1)
    plot(results, os.path.join(opts.out, "inequalities.png"))


if __name__ == "__main__":
    main()
