"""The brachistochrone on `Graded(Chebyshev(N), left=3)`: why some sizes stall.

For each `N`, three rows against the cycloid (time relative to its closed form, max
error at 401 points and 60 down to `x = 1e-12`):

- `default`: `solve_functional` with no `y0` (status, steps, estimate, tolerance);
- `floor`: where Newton (the same natural-monotonicity line search, written out in
  NumPy on the gradient of the discrete functional) stops, Levenberg-Marquardt on
  the gradient's norm: a floor well above round-off (with a nearly singular
  Hessian: a minimum of `|grad|` that is not a root) means that the discrete problem
  has no stationary point near the cycloid, which no globalisation or continuation
  can find;
- `slope 0`: the same discrete problem with the end slope in the graded variable
  eliminated (`Y_u(0) = 0`, which the cycloid has: `y ~ x^(2/3)`, `x ~ s^3`), by
  Newton from the default start projected onto it (it may end at another
  stationary point: at 24 nodes a saddle, 1e-5 above the minimum time).

The end slope's first variation at the cycloid is not zero (the cusp is a boundary
minimum in it: a steeper start costs time at first order, a shallower one leaves
`y <= 0`); without the elimination the discrete problem has stationary points only
where the quadrature's error near the cusp balances it.

    python benchmarks/dev/graded_cusp.py 16 24 32 64 [--no-floor]
"""

import argparse
import math

import equinox as eqx
import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import scipy.linalg  # noqa: E402
import scipy.optimize  # noqa: E402

import constrained_jax as cjax  # noqa: E402
from constrained_jax._discretization import (  # noqa: E402
    barycentric_weights,
    differentiation_matrix,
)
from constrained_jax._functional import _line, _objective, _Problem  # noqa: E402


G = 9.81
END = (1.0, -0.6)


def _lagrangian(y, yp, x, args):
    return jnp.sqrt((1 + yp**2) / (2 * G * (-y)))


FUNCTIONAL = cjax.Functional(_lagrangian, (0.0, END[0]), (0.0, END[1]))
T_END = scipy.optimize.brentq(
    lambda t: (1 - math.cos(t)) / (t - math.sin(t)) + END[1] / END[0],
    1e-6,
    2 * math.pi,
)
A = END[0] / (T_END - math.sin(T_END))
T_MIN = T_END * math.sqrt(A / G)


def cycloid(xs):
    def one(x):
        if x <= 0:
            return 0.0
        t = scipy.optimize.brentq(lambda t: A * (t - math.sin(t)) - x, 0.0, T_END)
        return -A * (1 - math.cos(t))

    return np.array([one(x) for x in xs])


XS = np.concatenate([np.linspace(0.0, END[0], 401), np.geomspace(1e-12, 1e-2, 60)])
EXACT = cycloid(XS)


def _error(disc, inner):
    full = jnp.asarray(np.concatenate([[0.0], inner, [END[1]]]))[:, None]
    fn = jax.vmap(lambda x: disc.interpolate(FUNCTIONAL.interval, full, x))
    return float(np.max(np.abs(np.asarray(fn(jnp.asarray(XS)))[:, 0] - EXACT)))


def _newton(grad, hess, w, steps=80):
    """Newton with the natural monotonicity test (as `cjax.Newton`), unscaled."""
    for _ in range(steps):
        r, k = np.asarray(grad(w)), np.asarray(hess(w))
        dw = -np.linalg.solve(k, r)
        size, alpha = np.linalg.norm(dw), 1.0
        for _ in range(40):
            r_trial = np.asarray(grad(w + alpha * dw))
            simplified = np.linalg.solve(k, r_trial)
            if (
                np.all(np.isfinite(r_trial))
                and np.linalg.norm(simplified) <= (1 - alpha / 4) * size
            ):
                break
            alpha /= 2
        else:
            return w, False
        w = w + alpha * dw
        if size < 1e-13 * (1 + np.linalg.norm(w)):
            return w, True
    return w, False


def _levenberg_marquardt(grad, hess, w, steps=300):
    """Minimises `|grad|`: returns its floor and the Hessian's smallest |eigenvalue|
    relative to its largest."""
    mu = 1e-3
    for _ in range(steps):
        r, k = np.asarray(grad(w)), np.asarray(hess(w))
        while mu < 1e20:
            dw = -np.linalg.solve(k.T @ k + mu * np.eye(len(w)), k.T @ r)
            r_new = np.asarray(grad(w + dw))
            if np.all(np.isfinite(r_new)) and np.linalg.norm(r_new) < np.linalg.norm(r):
                w, mu = w + dw, max(mu / 3, 1e-20)
                break
            mu *= 4
        else:
            break
    eig = np.abs(np.linalg.eigvalsh(np.asarray(hess(w))))
    return w, np.linalg.norm(np.asarray(grad(w))), eig.min() / eig.max()


def _one(n, floor):
    disc = cjax.Graded(cjax.Chebyshev(n), left=3)
    sol = cjax.solve_functional(FUNCTIONAL, None, discretization=disc, throw=False)
    steps = int(sol.stats["num_steps"])
    print(
        f"N={n:3d} default  {sol.result!s:40} steps {steps:3d}"
        f"  T {(float(sol.value) - T_MIN) / T_MIN:+.1e}"
        f"  error {_error(disc, np.asarray(sol.y)[1:-1]):.1e}"
        f"  estimate {float(sol.stats['error_estimate']):.1e}"
        f"  tolerance {float(sol.stats['error_tolerance']):.1e}"
    )
    problem = _Problem(FUNCTIONAL, disc.tabulate())
    args = (problem, None)
    start = np.asarray(_line(problem, straight_in=disc)[1:-1, 0])

    # The discrete problem as it is.
    objective = lambda x: _objective(x, args)
    grad = eqx.filter_jit(jax.grad(objective))
    hess = eqx.filter_jit(jax.hessian(objective))
    x, converged = _newton(grad, hess, start)
    if not converged and floor:
        x, norm, ratio = _levenberg_marquardt(grad, hess, x)
        print(
            f"      floor    |grad| {norm:.1e} (from where Newton stops),"
            f" Hessian |eig| min / max {ratio:.1e},"
            f" T {(float(objective(x)) - T_MIN) / T_MIN:+.1e},"
            f" error {_error(disc, x):.1e}"
        )

    # The same with Y_u(0) = 0 eliminated.
    t = disc.discretization.reference_nodes()
    d0 = np.asarray(differentiation_matrix(t, barycentric_weights(t)))[0]
    a, rhs = d0[1:-1], -d0[-1] * END[1]
    basis = scipy.linalg.null_space(a[None, :])
    particular = a * rhs / (a @ a)
    inner = lambda w: jnp.asarray(particular) + jnp.asarray(basis) @ w
    reduced = lambda w: _objective(inner(w), args)
    grad = eqx.filter_jit(jax.grad(reduced))
    hess = eqx.filter_jit(jax.hessian(reduced))
    w, converged = _newton(grad, hess, basis.T @ (start - particular))
    x = np.asarray(inner(jnp.asarray(w)))
    full = jnp.asarray(np.concatenate([[0.0], x, [END[1]]]))[:, None]
    estimate = float(disc.error_estimate(full, FUNCTIONAL.interval))
    print(
        f"      slope 0  converged {converged!s:5}"
        f"  T {(float(reduced(w)) - T_MIN) / T_MIN:+.1e}"
        f"  error {_error(disc, x):.1e}  estimate {estimate:.1e}"
    )


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("sizes", type=int, nargs="+")
    parser.add_argument("--no-floor", action="store_true")
    options = parser.parse_args()
    for n in options.sizes:
        _one(n, not options.no_floor)


if __name__ == "__main__":
    main()
