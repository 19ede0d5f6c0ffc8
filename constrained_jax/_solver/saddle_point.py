"""The saddle-point system of constrained mechanics as a value, the protocol of its
solvers, and `solve`: the one function through which every caller solves it.

    [[M, -A^T], [A, 0]] [x; lambda] = [f; -b]

[`constrained_jax.LagrangianSystem`][] assembles the system at a state (the equations
of motion; with other right-hand sides, the projection onto the constraint manifold
and the impact law) as a [`constrained_jax.SaddlePointSystem`][]. A solver
([`constrained_jax.AbstractSaddlePointSolver`][]) names the form in which it wants the
blocks (`form`: sparse patterns or dense, scalar code or arrays) and solves the
system it is given (`solve`). `solve` below owns what every caller needs and no
solver repeats: the implicit derivative, the refusal of a system whose detected
sparsity pattern missed an entry, and the value of `x` where the system is singular.
"""

import abc
import functools
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .sparse import SparseMatrix


class KKTForm(NamedTuple):
    """The form in which a saddle-point solver takes the blocks of a system (static).

    - `sparse`: `M` and `A` with the sparsity patterns of the system, found once at
        trace time ([`constrained_jax.LagrangianSystem`][]); where the traced program
        does not prove a pattern, it is checked at run time and a missed entry
        refuses the solve. `False`: full patterns (dense blocks), nothing detected and
        nothing checked.
    - `unroll`: the blocks are assembled on scalars, which XLA fuses with an unrolled
        solve under `jax.vmap`; `False`: on arrays, a smaller program to compile.
    """

    sparse: bool
    unroll: bool


class SaddlePointSystem(eqx.Module):
    """The saddle-point (KKT) system of constrained mechanics at one state,

        M x - A^T lambda = f,    A x = -b,

    with `M` (`n x n`, symmetric) and `A` (`k x n`) as
    `constrained_jax._solver.sparse.SparseMatrix` blocks (a static pattern; a full
    pattern holds the dense matrix; dense arrays given here are taken as such). For
    the equations of motion `x` is `qddot`, `f = Q - c` and `b = Adot qdot + adot`
    (see [`constrained_jax.LagrangianSystem`][]).

    **Attributes:**

    - `mass`, `jac`: `M` and `A`.
    - `rhs`, `bias`: `f`, shape `(n,)`, and `b`, shape `(k,)`.
    - `mismatch`: `None` where the patterns of `M` and `A` are proven by the traced
        program (or full); else the run-time check of the detected patterns, true
        when an entry outside them is nonzero at this state: the blocks are then
        wrong and [`constrained_jax._solver.saddle_point.solve`] refuses the system.
    - `active`: `None` (every row holds), or per row of `A` whether it holds. An
        inactive row `j` is replaced by `lambda_j = 0`: its entries of `A` and `b`
        are ignored, whatever they hold (NaN included), and the solution is that of
        the system without those rows, with zeros at their multipliers. The patterns
        are unchanged (they include every row): `active` is a run-time value, so one
        program serves every combination of rows (under `jax.vmap` it may differ
        from one element of the batch to the next).
    """

    mass: SparseMatrix
    jac: SparseMatrix
    rhs: Float[Array, " n"]
    bias: Float[Array, " k"]
    mismatch: Bool[Array, ""] | None = None
    active: Bool[Array, " k"] | None = None

    def __init__(self, mass, jac, rhs, bias, mismatch=None, active=None):
        # (Dense arrays are taken as blocks with the full pattern.)
        self.mass = mass if isinstance(mass, SparseMatrix) else SparseMatrix.dense(mass)
        self.jac = jac if isinstance(jac, SparseMatrix) else SparseMatrix.dense(jac)
        self.rhs = rhs
        self.bias = bias
        self.mismatch = mismatch
        self.active = None if active is None else jnp.asarray(active, bool)

    @property
    def n(self) -> int:
        return self.rhs.shape[0]

    @property
    def k(self) -> int:
        return self.bias.shape[0]


class AbstractSaddlePointSolver(eqx.Module):
    """A method for the saddle-point system of constrained mechanics,

        M x - A^T lambda = f,    A x = -b,

    with `M` (n x n) symmetric and `A` (k x n). The system is nonsingular exactly when
    `A` has full row rank and `M` is positive definite on the null space of `A`; `M`
    itself may be singular.

    A solver implements two methods: `form(n, k)`, the form in which it takes the
    blocks (a [`constrained_jax.KKTForm`][]), and `solve(system, fill)`, which
    solves a [`constrained_jax.SaddlePointSystem`][] given in that form. Callers never
    call `solve` directly: the library's one entry point differentiates it by the
    implicit rule (the tangents solve the same system, `solve` is not differentiated
    through), refuses a system whose detected sparsity pattern missed an entry, and
    passes `fill`.

    **The contract of `solve`.** It returns `(x, lambda, singular)`. Where
    `singular`, `x` is `fill` (`0.0`, or NaN inside a time integration, which then
    rejects the step) and `lambda` is zero. A solution that is not finite (NaN or
    inf in the inputs, or an overflow) is `singular`. The map from `(f, b)` to
    `(x, lambda)` must be linear at fixed `M`, `A` (flags decided from `M`, `A`
    only), as the implicit derivative linearises it.

    **Inactive rows.** Where `system.active` is given, a row `j` with `active[j]`
    false is solved as `lambda_j = 0` and its entries of `A` and `b` are ignored
    (see [`constrained_jax.SaddlePointSystem`][]). A solver masks those entries to
    zero (a `where`, so that NaN does not leak) and puts a positive entry `c` on the
    `(2, 2)` block at those rows: the Schur complement becomes `A M^-1 A^T + C`,
    whose row `j` is `c lambda_j = 0`. `c` is in the units of that block (the
    largest diagonal entry of the Schur complement, or of the scaled KKT matrix, and
    1 where it is zero), so that a relative pivot test (`10 k eps max|S|`) neither
    takes an active row's pivot for zero (masses of `1e300`) nor an inactive row's
    for a breakdown, and the scale of the test is unchanged. With `active=None`
    nothing of this is traced.

    **Free gauge directions.** A direction `v` with `M v = 0` and `A v = 0` (no
    inertia, and free of the constraints: a massless coordinate that nothing couples
    to, like the spin of the rolling cylinder with `I = 0` once it has let go) makes
    the system singular, but it need not make it unsolvable. If no force acts along it
    (`f . v = 0` to round-off) the equations hold for every component of `x` along `v`:
    such a direction is a free gauge, and the library's solvers return the solution
    whose unknown at the vanishing pivot is zero (for a massless coordinate: its
    acceleration is zero, so its velocity is held). If a force acts along it
    (`f . v != 0`, e.g. a potential gradient on a massless coordinate) the equations
    are inconsistent and the solve reports `singular`. Redundant constraints (`A`
    rank-deficient) are always reported `singular`: their multipliers are not unique.
    """

    @abc.abstractmethod
    def form(self, n: int, k: int) -> KKTForm:
        """The form of the blocks this solver takes for `n` unknowns and `k`
        constraints (static)."""

    @abc.abstractmethod
    def solve(
        self, system: SaddlePointSystem, fill: float
    ) -> tuple[Float[Array, " n"], Float[Array, " k"], Bool[Array, ""]]:
        """`(x, lambda, singular)`, with the contract of the class docstring."""


def mask_singular(sol: Array, n: int, singular, fill: float) -> Array:
    """`sol = [x; lambda]` with `x = fill` and `lambda = 0` where `singular` (one
    `where` on both parts)."""
    if fill == 0:
        return jnp.where(singular, 0.0, sol)
    fills = jnp.concatenate(
        [jnp.full((n,), fill, sol.dtype), jnp.zeros((sol.shape[0] - n,), sol.dtype)]
    )
    return jnp.where(singular, fills, sol)


def solve(
    solver: AbstractSaddlePointSolver, system: SaddlePointSystem, fill: float = 0.0
) -> tuple[Float[Array, " n"], Float[Array, " k"], Bool[Array, ""]]:
    """`(x, lambda, singular)`: the one way the library solves a saddle-point system.

    - **Derivative.** The solution moves with its inputs as
        `K dz = [df - dM x + dA^T lambda; -(db + dA x)]`, `K = [[M, -A^T], [A, 0]]`:
        the tangent solves the same system with another right-hand side. The
        solver's map from right-hand side to solution, linearised at the primal
        (`jax.linearize` with `M` and `A` fixed), is applied to the tangent
        right-hand side, in forward and (transposed) in reverse mode; the
        factorisation (unrolled elimination, pivots, `where`s) is never
        differentiated. Singular systems have zero tangents; a free gauge direction
        keeps its convention (the linearised map drops the right-hand side's
        component at the pivot as the solve does). Second derivatives differentiate
        the rule itself.
    - **Refusal.** Where `system.mismatch` (a detected pattern missed an entry), the
        system is `singular`: `x = fill`, `lambda = 0`.
    - **Singular systems.** `x` is `fill` and `lambda` zero (the solver's contract).
    - **Inactive rows** (`system.active`): solved as `lambda_j = 0`, their entries
        of `A` and `b` ignored; the tangents are those of the system without them
        (the rows of `dA` masked, `d lambda_j = 0`), and no cotangent reaches them.

    `system` must be in the solver's form (`solver.form(n, k)`).
    """
    mismatch = system.mismatch
    system = SaddlePointSystem(
        system.mass, system.jac, system.rhs, system.bias, active=system.active
    )
    x, lam, singular = _solve(solver, fill, system)
    if mismatch is not None:
        x = jnp.where(mismatch, jnp.asarray(fill, x.dtype), x)
        lam = jnp.where(mismatch, 0.0, lam)
        singular = singular | mismatch
    return x, lam, singular


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def _solve(solver, fill, system):
    return solver.solve(system, fill)


@_solve.defjvp
def _solve_jvp(solver, fill, primals, tangents):
    (system,), (d,) = primals, tangents
    active = system.active

    def solution(rhs, bias):
        x, lam, singular = solver.solve(
            SaddlePointSystem(system.mass, system.jac, rhs, bias, active=active), 0.0
        )
        return (x, lam), singular

    (x, lam), linear, singular = jax.linearize(
        solution, system.rhs, system.bias, has_aux=True
    )
    # K dz = [df - dM x + dA^T lambda; -(db + dA x)]. An inactive row's `dA` is
    # dropped (`lambda_j = 0` would not cancel a NaN in it); its `db` the solve
    # ignores.
    djac = d.jac if active is None else d.jac.mask_rows(active)
    tangent_rhs = d.rhs - d.mass.matvec(x) + djac.matvec(lam, transpose=True)
    tangent_bias = d.bias + djac.matvec(x)
    dx, dlam = linear(tangent_rhs, tangent_bias)
    dx, dlam = (jnp.where(singular, 0.0, t) for t in (dx, dlam))
    d_singular = np.zeros(singular.shape, jax.dtypes.float0)
    if fill != 0:
        x = jnp.where(singular, jnp.asarray(fill, x.dtype), x)
    return (x, lam, singular), (dx, dlam, d_singular)
