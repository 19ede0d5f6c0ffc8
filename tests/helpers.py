"""Shared test helpers: tree comparison, finite differences, trace counting, a fresh
Python process, the one-constraint cases of the saddle-point solvers."""

import functools as ft
import os
import pathlib
import subprocess
import sys

import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

import constrained_jax as cjax
from constrained_jax._solver.saddle_point import solve as solve_saddle_point


def tree_allclose(x, y, *, rtol=1e-10, atol=1e-12) -> bool:
    """Same structure and every leaf close (NaNs never close)."""
    if jtu.tree_structure(x) != jtu.tree_structure(y):
        return False
    return all(
        np.shape(a) == np.shape(b) and np.allclose(a, b, rtol=rtol, atol=atol)
        for a, b in zip(jtu.tree_leaves(x), jtu.tree_leaves(y), strict=True)
    )


def solve_with(solver, fill: float = 0.0):
    """`(mass, jac, rhs, bias) -> (x, lambda, singular)`: `solver` on the saddle-point
    system of these blocks (dense arrays, or `SparseMatrix`es with their patterns),
    through the library's one solve (implicit derivative, refusal, `fill`)."""

    def solve(mass, jac, rhs, bias):
        system = cjax.SaddlePointSystem(mass, jac, rhs, bias)
        return solve_saddle_point(solver, system, fill)

    return solve


def finite_difference_grad(fn, x, *, rel_step=1e-6):
    """Central-difference gradient of a scalar `fn` at the array `x` (float64).

    The step is relative to each component (absolute for zero components), so the
    truncation error is O(step^2) and the round-off error O(eps / step).
    """
    x = np.asarray(x, dtype=np.float64)
    grad = np.zeros_like(x)
    flat = x.reshape(-1)
    for i in range(flat.size):
        h = rel_step * max(abs(flat[i]), 1.0)
        up, down = flat.copy(), flat.copy()
        up[i] += h
        down[i] -= h
        f_up = float(fn(jnp.asarray(up.reshape(x.shape))))
        f_down = float(fn(jnp.asarray(down.reshape(x.shape))))
        grad.reshape(-1)[i] = (f_up - f_down) / (2 * h)
    return grad


class TraceCounter:
    """Wraps a function and counts how often JAX traces it (i.e. compiles anew)."""

    def __init__(self, fn):
        self.fn = fn
        self.count = 0
        ft.update_wrapper(self, fn)

    def __call__(self, *args, **kwargs):
        self.count += 1
        return self.fn(*args, **kwargs)


def run_python(
    code: str, *, timeout: float, cwd=None, **environ
) -> subprocess.CompletedProcess:
    """`code` run by a new Python process that imports this checkout's
    `constrained_jax` (its folder first on `PYTHONPATH`), in the folder `cwd` (by
    default this one), with `environ` added to the environment (a value `None`
    removes the variable); output captured as text. Raises
    `subprocess.TimeoutExpired` after `timeout` seconds."""
    env = dict(os.environ)
    for name, value in environ.items():
        if value is None:
            env.pop(name, None)
        else:
            env[name] = value
    root = str(pathlib.Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = os.pathsep.join([root, env.get("PYTHONPATH", "")])
    return subprocess.run(
        [sys.executable, "-c", code],
        env=env,
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def assert_one_constraint_cases(solver, mass, rhs, bias, reference, rtol):
    """A saddle-point solver with one constraint (a `1 x 1` Schur complement, solved
    without a pivot test): rows of `A` that make it zero, overflow it to inf or make
    it NaN are refused (`singular`, zeros), alone and in a batch; tiny and huge but
    finite rows are solved, to `reference(jac) -> (x, lambda)` (NumPy) within
    `rtol` (the absolute error of `x` relative to its largest entry). In the
    diagonal fast path, without the mapping of an infinite Schur complement to NaN,
    the overflowing row would come back as `lambda = 0`, successful (checked: the
    test then fails); `RangeSpaceLDL`'s augmentation turns that row into NaN
    earlier."""
    singular_rows = [[0.0, 0.0, 0.0], [1e200, 0.0, 1.0], [np.nan, 1.0, 1.0]]
    solvable_rows = [[1e-100, 1e-100, 0.0], [1e150, 0.0, 0.0], [1.0, -2.0, 0.5]]
    jacs = jnp.asarray(singular_rows + solvable_rows)[:, None, :]
    solve = jax.jit(solve_with(solver))
    x_b, lam_b, singular_b = jax.jit(
        jax.vmap(solve_with(solver), in_axes=(None, 0, None, None))
    )(mass, jacs, rhs, bias)
    for i, jac in enumerate(jacs):
        for x, lam, singular in (
            solve(mass, jac, rhs, bias),
            (x_b[i], lam_b[i], singular_b[i]),
        ):
            if i < len(singular_rows):
                assert singular, jac
                assert jnp.all(x == 0) and jnp.all(lam == 0)
                continue
            assert not singular, jac
            x_ref, lam_ref = reference(np.asarray(jac))
            scale = np.max(np.abs(x_ref))
            np.testing.assert_allclose(lam, lam_ref, rtol=rtol)
            np.testing.assert_allclose(x, x_ref, rtol=rtol, atol=rtol * scale)
