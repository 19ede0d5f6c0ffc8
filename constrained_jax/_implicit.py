"""Derivatives of a solve by the implicit function theorem that never raise.

`optimistix.internal.implicit_jvp` solves the tangent system with
`lineax.linear_solve(..., throw=True)`, and in reverse mode Lineax transposes that
solve with `throw=True` unconditionally: a failed linear solve in the backward pass
(a singular KKT matrix at a point where the primal solve already failed, a Krylov
solver out of iterations) raises from inside `jax.grad`, even when the user asked for
`throw=False` and would have read the failure from `result`. A library that reports
failures as statuses must not crash the derivative of a failed solve.

So the tangent solve here goes through `jax.lax.custom_linear_solve`, whose solve
(and transposed solve) are ordinary primal functions: they call Lineax with
`throw=False` and turn a failed solve into NaN. The derivative of a solve whose
primal `result` is not successful is NaN too (a failed solve has no derivative), so
that, e.g., [`constrained_jax.fit`][] stops with `RESULTS.nonfinite` and keeps its
last finite parameters instead of following a meaningless gradient.

Successful solves get exactly the derivative optimistix would give:
`-(d rewrite / d root)^-1 d rewrite / d inputs`.

This adapter is the library's only copy of optimistix's private `implicit_jvp`
(`optimistix/_ad.py`, reached as `optimistix.internal`, which has no stability
promise). Every constrained solve differentiates through it, and only from one
place: `constrained_jax._kkt.kkt_solve` (extremize with and without inequalities,
solve_functional, the Newton solves of the variational integrator).
"""

from collections.abc import Callable
from typing import TypeVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import lineax as lx
from jaxtyping import Array, Bool, PyTree

from ._results import RESULTS


_Inputs = TypeVar("_Inputs")
_Root = TypeVar("_Root")


def implicit_jvp(
    fn_primal: Callable[[_Inputs], tuple[_Root, tuple[RESULTS, PyTree]]],
    fn_rewrite: Callable[[_Root, tuple[RESULTS, PyTree], _Inputs], PyTree],
    inputs: _Inputs,
    tags: frozenset[object],
    linear_solver: lx.AbstractLinearSolver,
) -> tuple[_Root, tuple[RESULTS, PyTree]]:
    """`optimistix.internal.implicit_jvp` whose derivatives are NaN, never an error,
    when a solve fails.

    **Arguments:** as `optimistix.internal.implicit_jvp`, with one convention:
    `fn_primal(inputs)` returns `(root, (result, aux))`, `result` a
    [`constrained_jax.RESULTS`][] member.

    **Returns:** `fn_primal(inputs)`. The root's tangents are
    `-(d(fn_rewrite)/d(root))^-1 d(fn_rewrite)/d(inputs)`; they are NaN where `result`
    is not successful or where that linear solve fails.
    """
    root, residual = _implicit_impl(fn_primal, fn_rewrite, inputs, tags, linear_solver)
    return root, jtu.tree_map(jax.lax.stop_gradient, residual)


@eqx.filter_custom_jvp
def _implicit_impl(fn_primal, fn_rewrite, inputs, tags, linear_solver):
    del fn_rewrite, tags, linear_solver
    return jtu.tree_map(jnp.asarray, fn_primal(inputs))


def _is_none(x):
    return x is None


def _for_jac(root, args):
    fn_rewrite, residual, inputs = args
    return fn_rewrite(root, residual, inputs)


@_implicit_impl.def_jvp
def _implicit_impl_jvp(primals, tangents):
    fn_primal, fn_rewrite, inputs, tags, linear_solver = primals
    t_inputs = tangents[2]
    no_tangent = jtu.tree_map(_is_none, t_inputs, is_leaf=_is_none)
    nondiff, diff = eqx.partition(inputs, no_tangent, is_leaf=_is_none)

    root, residual = implicit_jvp(fn_primal, fn_rewrite, inputs, tags, linear_solver)
    failed = residual[0] != RESULTS.successful

    def rewrite_of_diff(diff_):
        return fn_rewrite(root, residual, eqx.combine(diff_, nondiff))

    operator = lx.JacobianLinearOperator(
        _for_jac, root, (fn_rewrite, residual, inputs), tags=tags
    )
    _, jvp_diff = jax.jvp(rewrite_of_diff, (diff,), (t_inputs,))
    t_root = jtu.tree_map(
        jnp.negative, _solve_or_nan(operator, jvp_diff, linear_solver)
    )
    t_root = _nan_where(t_root, failed)
    t_residual = jax.custom_derivatives.zero_from_primal(  # pyright: ignore
        residual, symbolic_zeros=True
    )
    return (root, residual), (t_root, t_residual)


def _nan_where(tree: PyTree[Array], failed: Bool[Array, ""]) -> PyTree[Array]:
    """`tree` times NaN where `failed`, times 1 elsewhere.

    A product (not `jnp.where`) so that it stays linear in `tree` and transposes to
    the same product: reverse mode then gets NaN cotangents too (the transpose of
    `where(failed, nan, t)` would send a zero cotangent instead).
    """

    def scale(leaf):
        return leaf * jnp.where(failed, jnp.nan, 1.0).astype(leaf.dtype)

    return jtu.tree_map(scale, tree)


def _solve_or_nan(operator, vector, linear_solver):
    """`operator^-1 vector` by `linear_solver`, NaN where the solve fails, never
    raising (also when transposed by reverse-mode autodiff)."""
    operator = lx.linearise(operator)

    def solve(op):
        def _solve(_, b):
            sol = lx.linear_solve(op, b, linear_solver, throw=False)
            return _nan_where(sol.value, sol.result != lx.RESULTS.successful)

        return _solve

    symmetric = lx.is_symmetric(operator)
    return jax.lax.custom_linear_solve(
        operator.mv,
        vector,
        solve(operator),
        None if symmetric else solve(operator.transpose()),
        symmetric=symmetric,
    )


def nan_tangent_where(tree: PyTree[Array], failed: Bool[Array, ""]) -> PyTree[Array]:
    """The identity on `tree`, with NaN derivatives (forward and reverse) where
    `failed`.

    For statuses decided after `implicit_jvp` (diagnostics that turn a converged
    iteration into a failure): the derivative of a failed solve is NaN.
    """
    return _nan_tangent_where(tree, failed)


def nan_derivatives_if_failed(
    outputs: PyTree, inputs: PyTree, failed: Bool[Array, ""]
) -> PyTree:
    """The identity on `outputs` (a `Trajectory`, a `FunctionalSolution`), whose
    derivatives with respect to `inputs` are NaN where `failed`, in forward and in
    reverse mode; the leaves that are not floating-point arrays pass through.

    For the end of a public solve. `throw=True`'s check rides on the primal output,
    so a program that keeps only a derivative (`jax.grad` of a loss, under
    `jax.vmap`) drops it; the NaN derivative still refuses the failed solve.
    Marking the output tangents alone is not enough in reverse mode: a cotangent that
    flows back through `where(reached, y, inf)` (a save time the failed run never
    reached) is zeroed by the `where`, and the gradient would read 0. So the tangent
    map gets a second term, `c * sum(t_inputs)` with `c = NaN` where `failed` and 0
    elsewhere: linear, and its transpose sends `c * sum(cotangents)` straight to
    every input.
    """
    out_f, out_rest = eqx.partition(outputs, eqx.is_inexact_array)
    in_f, _ = eqx.partition(inputs, eqx.is_inexact_array)
    return eqx.combine(_nan_derivatives(out_f, in_f, failed), out_rest)


@jax.custom_jvp
def _nan_derivatives(outputs, inputs, failed):
    del inputs, failed
    return outputs


@_nan_derivatives.defjvp
def _nan_derivatives_jvp(primals, tangents):
    outputs, _, failed = primals
    t_outputs, t_inputs, _ = tangents
    leaves = jtu.tree_leaves(t_inputs)
    # Inputs of several precisions (a float32 state, float64 parameters) are summed
    # in the widest, explicitly: strict dtype promotion refuses to mix them.
    with jax.numpy_dtype_promotion("standard"):
        wide = jnp.result_type(*(leaf.dtype for leaf in leaves), jnp.zeros(()).dtype)
    total = sum((jnp.sum(leaf).astype(wide) for leaf in leaves), jnp.zeros((), wide))

    def mark(leaf):
        dtype = leaf.dtype
        scale = jnp.where(failed, jnp.nan, 1.0).astype(dtype)
        from_inputs = jnp.where(failed, jnp.nan, 0.0).astype(dtype) * total.astype(
            dtype
        )
        return leaf * scale + from_inputs

    return outputs, jtu.tree_map(mark, t_outputs)


@jax.custom_jvp
def _nan_tangent_where(tree, failed):
    return tree


@_nan_tangent_where.defjvp
def _nan_tangent_where_jvp(primals, tangents):
    tree, failed = primals
    t_tree, _ = tangents
    return tree, _nan_where(t_tree, failed)
