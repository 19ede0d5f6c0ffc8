"""Constrained Lagrangian mechanics: the equations of motion and the multipliers.

For a Lagrangian `L(q, qdot, t)` with constraints `A(q, t) qdot + a(q, t) = 0` (see
`_constraints.py`) and generalised forces `Q(q, qdot, t)`, the lecture's equations

    d/dt (dL/dqdot_sigma) - dL/dq_sigma = sum_j lambda_j g_{j sigma} + Q_sigma

expand, with `M = d^2 L / dqdot^2` and `c = (dp/dq) qdot + dp/dt - dL/dq`
(`p = dL/dqdot`), into the saddle-point system

    [[M, -A^T], [A, 0]] [qddot; lambda] = [Q - c; -(Adot qdot + adot)].

`M` may be singular (a massless direction) as long as the KKT matrix is not, i.e. `M`
is positive definite on the null space of `A`. A direction with no inertia that the
constraints leave free and that no force acts on is a free gauge: its acceleration is
set to zero (see `LagrangianSystem.accelerations`). The force of constraint is
`Q^c = A^T lambda`.
"""

import functools
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from ._constraints import AbstractConstraint
from ._misc import check_signature, full_precision, inexact_asarray
from ._results import error_if
from ._solver.automatic import Automatic
from ._solver.saddle_point import (
    AbstractSaddlePointSolver,
    KKTForm,
    SaddlePointSystem,
    solve as solve_saddle_point,
)
from ._solver.sparse import SparseMatrix
from ._structure import colouring, dense_structure, detect, probe_vector, Structure


PATTERN_MISMATCH_MESSAGE = (
    "The sparsity pattern of the mass matrix M or of the constraint Jacobian A, "
    "detected at random states when the system was traced, misses an entry that is "
    "nonzero at this state (a coupling switched on by `jnp.where`, by `t` or by a "
    "parameter value the random draws did not hit), so the structured equations of "
    "motion would be wrong and the solve is refused. Pass "
    "`saddle_point_solver=cjax.FullKKTLU()` (or `cjax.RangeSpaceLDL(sparse=False)`) "
    "to the `LagrangianSystem`: these use dense matrices and no detected pattern."
)


# Up to this many entries (or directions), the compressed products are taken apart
# on scalars and the directional derivatives pushed one by one: code that XLA fuses
# into one loop under `jax.vmap` (batched gathers, `dot`s and small reductions are
# not fused on CPU). Larger systems use vmapped, array-level code, and so do those
# whose saddle-point solver does not take scalar code (`KKTForm.unroll`: LAPACK or
# `SparseSchur` do not fuse either, and the scalar assembly is larger to compile).
_UNROLL = 24


def off_constraints(system, q, qd, t, args, tol) -> Bool[Array, ""]:
    """Whether `(q, qd)` violates the holonomic constraints or `A qd + a = 0` beyond
    `tol`, relative to `1 + max|q|` and `1 + max|qd|`: the test `simulate` makes of
    its start (`consistency_tol`), also used by `consistent_initial_state`,
    `linearize` and `Reduction.full_multipliers`. A NaN residual (a constraint
    Jacobian not defined there) counts as a violation."""
    if system.active is None:
        position = system.holonomic_residual(q, t, args)
    else:
        # The rows that hold (position residuals of all rows, 0 for Pfaffian ones).
        position = jnp.where(system.active, system.position_residual(q, t, args), 0)
    velocity = system.velocity_residual(q, qd, t, args)
    if system.active is not None:
        velocity = jnp.where(system.active, velocity, 0)
    on = jnp.all(jnp.abs(position) <= tol * (1 + jnp.max(jnp.abs(q)))) & jnp.all(
        jnp.abs(velocity) <= tol * (1 + jnp.max(jnp.abs(qd)))
    )
    return jnp.invert(on)


def _push(fn, primals, tangents: list, unroll: bool = True):
    """`(fn(*primals), [jvp of fn along each tangent])`: one linearisation per set of
    perturbed arguments, then the linear map applied to each tangent (unrolled when
    few, else vmapped).

    A tangent's entry `None` is a symbolic zero: that argument is closed over, not
    linearised, so no product with a zero tangent is traced (XLA keeps `0 * x`,
    which IEEE arithmetic does not make `0`). The primal computations that the
    linearisations repeat are identical, and XLA merges them."""
    groups: dict = {}
    for i, tangent in enumerate(tangents):
        mask = tuple(x is not None for x in tangent)
        groups.setdefault(mask, []).append(i)
    out = None
    d_out: list = [None] * len(tangents)
    for mask, members in groups.items():

        def restricted(*live, mask=mask):
            it = iter(live)
            full = [next(it) if m else p for m, p in zip(mask, primals, strict=True)]
            return fn(*full)

        live = tuple(p for m, p in zip(mask, primals, strict=True) if m)
        live_tangents = [[x for x in tangents[i] if x is not None] for i in members]
        if unroll and len(tangents) * primals[0].shape[0] <= _UNROLL:
            out, linear = jax.linearize(restricted, *live)
            for i, tangent in zip(members, live_tangents, strict=True):
                d_out[i] = linear(*tangent)
            continue
        stacked = [jnp.stack(parts) for parts in zip(*live_tangents, strict=True)]
        along = lambda *tangent, f=restricted, x=live: jax.jvp(f, x, tangent)
        out, d_group = jax.vmap(along, out_axes=(None, 0))(*stacked)
        for j, i in enumerate(members):
            d_out[i] = jax.tree_util.tree_map(lambda x, j=j: x[j], d_group)
    return out, d_out


def _seeds(pattern: np.ndarray, dtype):
    """The seed directions of a column colouring of `pattern`, shape
    `(num_colours, n)`, and the colour of each column."""
    n = pattern.shape[1]
    colours = colouring(pattern) if n else np.zeros((0,), int)
    num = int(colours.max()) + 1 if n else 0
    seeds = np.zeros((num, n))
    seeds[colours, np.arange(n)] = 1.0
    return seeds, colours


def _decompress(
    compressed, pattern: np.ndarray, colours: np.ndarray, unroll: bool = True
) -> SparseMatrix:
    """The matrix from its compressed products `compressed[c] = sum over the columns
    j of colour c of column j`, with the static `pattern` (full: the dense matrix)."""
    if pattern.all():
        # Every column has its own colour: the Jacobian itself, its rows in the
        # order of the columns. Static indices, not a gather, which XLA:CPU would
        # materialise as a separate pass over a batch.
        order = np.argsort(colours)
        if np.array_equal(order, np.arange(order.shape[0])):
            return SparseMatrix.dense(compressed.T)
        return SparseMatrix.dense(jnp.stack([compressed[int(c)] for c in order]).T)
    rows, cols = np.nonzero(pattern)
    if unroll and len(rows) <= _UNROLL:
        # Static slices (fused under vmap) rather than a gather.
        values = jnp.stack(
            [compressed[colours[j], i] for i, j in zip(rows, cols, strict=True)]
        )
    else:
        values = compressed[colours[cols], rows]
    return SparseMatrix(
        values,
        tuple(int(r) for r in rows),
        tuple(int(c) for c in cols),
        tuple(int(s) for s in pattern.shape),
    )


def _probe_mismatch(compressed_t, pattern, colours, product, unroll: bool = True):
    """Whether `product` (the matrix times the probe, by autodiff) differs beyond
    round-off from the sparse reconstruction times the probe.

    `compressed_t[i, c]` is entry `(i, j)` for the unique column `j` of colour `c` in
    row `i`'s pattern, so the reconstruction is `sum_c compressed_t[i, c] w[i, c]`
    with the static weights `w[i, c] = probe[j]`: elementwise, no dense matrix."""
    rows, num_cols = pattern.shape
    probe = probe_vector(num_cols)
    weights = np.zeros((rows, compressed_t.shape[1]))
    i, j = np.nonzero(pattern)
    weights[i, colours[j]] = probe[j]
    eps = jnp.finfo(compressed_t.dtype).eps
    tol = 100 * (num_cols + 1) * eps
    if not unroll or rows * weights.shape[1] > _UNROLL:
        terms = compressed_t * jnp.asarray(weights, compressed_t.dtype)
        reconstruction = jnp.sum(terms, axis=1)
        scale = jnp.max(jnp.sum(jnp.abs(terms), axis=1)) + jnp.max(jnp.abs(product))
        return jnp.max(jnp.abs(reconstruction - product)) > tol * scale
    # Small: on scalars, so that it fuses with the rest under vmap.
    error, scale = [], []
    for r in range(rows):
        terms = [
            compressed_t[r, c] * float(w) for c, w in enumerate(weights[r]) if w != 0
        ]
        recon = sum(terms[1:], terms[0]) if terms else 0.0
        error.append(jnp.abs(recon - product[r]))
        scale.append(sum(jnp.abs(v) for v in terms) + jnp.abs(product[r]))
    maximum = lambda xs: functools.reduce(jnp.maximum, xs)
    return maximum(error) > tol * maximum(scale)


class LagrangianSystem(eqx.Module):
    """A mechanical system: a Lagrangian, constraints and generalised forces.

    **Arguments:**

    - `lagrangian`: `L(q, qd, t, args) -> scalar`, any JAX function (not only `T - V`
        with a constant mass matrix).
    - `constraints`: a sequence of [`constrained_jax.Holonomic`][] and
        [`constrained_jax.Pfaffian`][] objects (or a single one). Their rows are stacked
        in the order given; so are the multipliers.
    - `forces`: `Q(q, qd, t, args) -> (n,)`, generalised non-conservative forces, or
        `None`.
    - `saddle_point_solver`: how the KKT system is solved, an
        `AbstractSaddlePointSolver`. The default, `Automatic()`, is chosen at trace
        time from the structure and size: the sparsity-aware unrolled
        [`constrained_jax.RangeSpaceLDL`][] for small systems, the sparse range-space
        method ([`constrained_jax.SparseSchur`][]) for large ones with a
        block-diagonal mass matrix, [`constrained_jax.FullKKTLU`][] (LAPACK's LU of
        the whole KKT matrix) otherwise (any positive semidefinite `M`, even a
        singular one). Or
        [`constrained_jax.FullKKTLU`][] (pivoted LU of the whole, dense KKT matrix,
        also for indefinite `M`), or `RangeSpaceLDL(sparse=False)` (dense).

    **Structure.** With a solver that takes sparse matrices (`RangeSpaceLDL()`,
    `SparseSchur()`, and `Automatic()`, the default, where it chooses them), the
    sparsity patterns of `M` and `A` are found once at
    trace time, and `M` and `A` are then built from one forward-mode product per
    colour of a column colouring (a diagonal `M` costs one product, not `n`). They
    are read from the traced program (data flow from `qdot_j` to the momentum `p_i`
    and from `q_j` to a holonomic `G_i`, exact zeros of a Pfaffian `g`): proven, no
    state can fill another entry. Where that reading is only a bound (`lax.cond`,
    loops, gathers in the Lagrangian), they are detected at random states, and a
    fixed probe checks a pattern the bound does not prove at every state: if an
    entry the detection missed is nonzero (a coupling switched on by a parameter
    value), the solve is refused (`accelerations` raises, `solve_accelerations`
    reports `singular`), never wrong.

    Coordinates `q` are arrays of shape `(n,)`; `t` is a scalar.
    """

    lagrangian: Callable
    constraints: tuple[AbstractConstraint, ...] = ()
    forces: Callable | None = None
    saddle_point_solver: AbstractSaddlePointSolver = Automatic()
    active: Bool[Array, " k"] | None = None
    slip: Float[Array, " k"] | None = None

    def __init__(
        self,
        lagrangian: Callable,
        constraints: AbstractConstraint | Sequence[AbstractConstraint] = (),
        forces: Callable | None = None,
        *,
        saddle_point_solver: AbstractSaddlePointSolver = Automatic(),
    ):
        check_signature(lagrangian, "The Lagrangian", "L(q, qd, t, args)")
        if isinstance(constraints, AbstractConstraint):
            constraints = (constraints,)
        elif callable(constraints) or not isinstance(constraints, Sequence):
            constraints = (constraints,)  # refused below, with what to do
        constraints = tuple(constraints)
        for c in constraints:
            if not isinstance(c, AbstractConstraint):
                what = "a function" if callable(c) else f"a {type(c).__name__}"
                raise ValueError(
                    "`constraints` of `cjax.LagrangianSystem` must be constraint "
                    "objects, `cjax.Holonomic(G)` or `cjax.Pfaffian(g, h)` (or "
                    f"`cjax.Unilateral(...)`), or a sequence of them; got {what}. Wrap "
                    "a function G(q, t, args) whose zeros are the constraint as "
                    "`constraints=cjax.Holonomic(G)`, and the rows g(q, t, args) of "
                    "`g qdot + h = 0` as `cjax.Pfaffian(g, h)`."
                )
        if forces is not None:
            check_signature(forces, "`forces`", "Q(q, qd, t, args)")
        self.lagrangian = lagrangian
        self.constraints = constraints
        if not isinstance(saddle_point_solver, AbstractSaddlePointSolver):
            raise ValueError(
                "`saddle_point_solver` must be `cjax.Automatic()`, "
                "`cjax.RangeSpaceLDL()`, `cjax.FullKKTLU()` or "
                f"`cjax.SparseSchur()`, got {type(saddle_point_solver).__name__}."
            )
        self.forces = forces
        self.saddle_point_solver = saddle_point_solver
        self.active = None
        self.slip = None

    def with_active(
        self, active: Bool[Array, " k"] | None, slip: Float[Array, " k"] | None = None
    ) -> "LagrangianSystem":
        """The same system with only the constraint rows where `active` (shape
        `(k,)`, traced) holding: the others (a released contact) are solved as
        trivial rows with zero multipliers, and their residuals are not held to
        zero. `None`: every row holds. One compiled program serves every mask.

        `slip` (shape `(k,)`, traced, or `None`): on the tangential row of a contact
        with [`constrained_jax.Coulomb`][] friction that slips, the sign of its slip
        velocity (the row is then inactive, and the kinetic friction force acts
        along it); `0` elsewhere."""
        return eqx.tree_at(
            lambda s: (s.active, s.slip),
            self,
            (active, slip),
            is_leaf=lambda x: x is None,
        )

    def friction_pairs(self, n: int, args, dtype) -> list:
        """Per contact with friction: `(normal row, tangential row, sign, Coulomb)`,
        rows of `A` (static)."""
        out, start = [], 0
        for c in self.constraints:
            size = c.num_constraints(n, args, dtype)
            if getattr(c, "friction", None) is not None:
                out.append((start, start + size - 1, c.sign, c.friction))
            start += size
        return out

    # ------------------------------------------------------------------ structure

    def check(self, q, qd, t, args) -> tuple[int, int]:
        """Validate shapes at trace time; return `(n, k)`."""
        q, qd = jnp.asarray(q), jnp.asarray(qd)
        if q.ndim != 1 or qd.shape != q.shape:
            raise ValueError(
                "Coordinates q and velocities qd must be arrays of the same shape "
                f"(n,); got {q.shape} and {qd.shape}."
            )
        n = q.shape[0]
        out = jax.eval_shape(self.lagrangian, q, qd, t, args)
        if not isinstance(out, jax.ShapeDtypeStruct) or out.shape != ():
            raise ValueError(
                "The Lagrangian L(q, qd, t, args) must return a scalar, got "
                f"{getattr(out, 'shape', type(out).__name__)}. Sum kinetic and "
                "potential energies into one number."
            )
        k = sum(c.num_constraints(n, args, q.dtype) for c in self.constraints)
        if k > n:
            raise ValueError(
                f"There are more constraints (k = {k}) than coordinates (n = {n}); at "
                "most n can be independent. Remove the redundant ones."
            )
        if self.forces is not None:
            f_out = jax.eval_shape(self.forces, q, qd, t, args)
            if getattr(f_out, "shape", None) != (n,):
                raise ValueError(
                    f"forces Q(q, qd, t, args) must return shape (n,) = ({n},), got "
                    f"{getattr(f_out, 'shape', type(f_out).__name__)}."
                )
        return n, k

    def without(self, index: int) -> "LagrangianSystem":
        """The same system with its constraint number `index` removed (released)."""
        constraints = self.constraints[:index] + self.constraints[index + 1 :]
        return LagrangianSystem(
            self.lagrangian,
            constraints,
            self.forces,
            saddle_point_solver=self.saddle_point_solver,
        )

    # ------------------------------------------------------------------ physics

    def momentum(self, q, qd, t, args) -> Float[Array, " n"]:
        """Generalised momenta `p = dL/dqdot`."""
        return jax.grad(self.lagrangian, argnums=1)(q, qd, t, args)

    def mass_matrix(self, q, qd, t, args) -> Float[Array, "n n"]:
        """`M = d^2 L / dqdot^2` (may be singular; see the module docstring)."""
        return jax.jacfwd(self.momentum, argnums=1)(q, qd, t, args)

    def energy(self, q, qd, t, args) -> Float[Array, ""]:
        """The energy function (Jacobi integral) `h = qdot . dL/dqdot - L`.

        Conserved when `L`, the constraints and the forces do not depend on `t` and
        the forces do no work (ideal constraints do none).
        """
        # `L` and `p` from one trace of the Lagrangian (its gradient's forward pass
        # computes `L` with the same operations as a call).
        value, p = jax.value_and_grad(self.lagrangian, argnums=1)(q, qd, t, args)
        return jnp.dot(qd, p) - value

    def constraint_jacobian(self, q, t, args) -> Float[Array, "k n"]:
        """`A = (g_{j sigma})`, the stacked rows of every constraint."""
        n = q.shape[0]
        if not self.constraints:
            return jnp.zeros((0, n), q.dtype)
        return jnp.concatenate(
            [c.velocity_form(q, t, args)[0] for c in self.constraints]
        )

    def velocity_residual(self, q, qd, t, args) -> Float[Array, " k"]:
        """`A qdot + a` for every constraint (zero on admissible motions)."""
        if not self.constraints:
            return jnp.zeros((0,), q.dtype)
        return jnp.concatenate(
            [c.velocity_residual(q, qd, t, args) for c in self.constraints]
        )

    def holonomic_residual(self, q, t, args) -> Float[Array, " k_holonomic"]:
        """`G(q, t)` for the holonomic constraints (nonholonomic ones have none)."""
        parts = [c.holonomic_residual(q, t, args) for c in self.constraints]
        if not parts:
            return jnp.zeros((0,), q.dtype)
        return jnp.concatenate(parts)

    def acceleration_bias(self, q, qd, t, args) -> Float[Array, " k"]:
        """`Adot qdot + adot`: constraints at acceleration level read
        `A qddot + bias = 0`."""
        if not self.constraints:
            return jnp.zeros((0,), q.dtype)
        return jnp.concatenate(
            [c.acceleration_bias(q, qd, t, args) for c in self.constraints]
        )

    def num_constraints(self, n: int, args, dtype=None) -> int:
        """`k`, the number of constraint rows (by shape evaluation)."""
        return sum(c.num_constraints(n, args, dtype) for c in self.constraints)

    def structure(self, q, t, args, sparse: bool = True) -> Structure:
        """The sparsity patterns of `M` and `A`: detected once at trace time (cached;
        see `constrained_jax._structure`) when `sparse`, else dense (full)."""
        n = q.shape[0]
        k = self.num_constraints(n, args, q.dtype)
        if not sparse:
            return dense_structure(n, k)
        return detect(self, q, t, args, n, k)

    def form(self, q, args) -> KKTForm:
        """The form of the blocks the saddle-point solver takes (static)."""
        n = q.shape[0]
        return self.saddle_point_solver.form(n, self.num_constraints(n, args, q.dtype))

    def saddle_point_system(
        self, q, qd, t, args, bias_correction=None, form: KKTForm | None = None
    ) -> SaddlePointSystem:
        """The equations of motion at `(q, qd, t)` as a
        [`constrained_jax.SaddlePointSystem`][]:
        `[[M, -A^T], [A, 0]] [qddot; lambda] = [Q - c; -(Adot qdot + adot)]`, with
        `bias_correction` (shape `(k,)`, as Baumgarte stabilization gives it) added
        to the bias, in `form` (default: the one the system's saddle-point solver
        takes).

        Each part is built in one pass. With a sparse form, `M` and `A` have the
        patterns detected at trace time, and their nonzeros come from a column
        colouring: one forward-mode product per colour (a diagonal `M` needs one,
        not `n`), all pushed through one traced copy of the gradient of the
        Lagrangian (and of each constraint) together with the directions that give
        the bias terms. With a pattern that the traced program does not prove (see
        `constrained_jax._sparsity`) one more direction, a fixed probe `v`, checks
        the pattern at the actual state: `mismatch` is true when `M v` or `A v`
        differs from the product of the sparse matrix with `v` beyond round-off (an
        entry the detection at random states missed), and the solve is refused.
        """
        t = jnp.asarray(t, q.dtype)
        form = self.form(q, args) if form is None else form
        structure = self.structure(q, t, args, form.sparse)
        mass, rhs, mismatch_m = self._lagrangian_pass(
            q, qd, t, args, structure, form.unroll
        )
        jac, bias, mismatch_a = self._constraint_pass(
            q, qd, t, args, structure, form.unroll
        )
        if bias_correction is not None:
            bias = bias + bias_correction
        mismatch = _either(mismatch_m, mismatch_a)
        return SaddlePointSystem(mass, jac, rhs, bias, mismatch, active=self.active)

    def _lagrangian_pass(self, q, qd, t, args, structure: Structure, unroll: bool):
        """`(M, Q - c, mismatch)`: `grad_q L` and `p = grad_qd L`, and the forward
        products of `(grad_q L, p)` along `(0, seed, 0)` (the columns of `M`),
        `(qdot, 0, 1)` (the terms `dp/dq qdot + dp/dt` of `c`) and, for a pattern
        not proven, `(0, probe, 0)`, all in one traced pass. `mismatch` is `None`
        when nothing is checked."""
        n, dtype = q.shape[0], q.dtype
        checked = not (structure.mass_is_dense or structure.mass_proven)
        seeds, colours = _seeds(structure.mass, dtype)
        num = seeds.shape[0]

        def gradient(q_, qd_, t_):
            return jax.grad(self.lagrangian, argnums=(0, 1))(q_, qd_, t_, args)

        tangents = [(None, jnp.asarray(seed, dtype), None) for seed in seeds]
        tangents.append((qd, None, jnp.ones((), dtype)))
        if checked:
            tangents.append((None, jnp.asarray(probe_vector(n), dtype), None))
        (grad_q, _), d_out = _push(gradient, (q, qd, t), tangents, unroll)
        # The columns of M stacked apart from the other directions: under `jax.vmap`
        # a mass matrix that depends on `args` only then stays unbatched.
        columns = jnp.stack([d[1] for d in d_out[:num]])
        rhs = grad_q - d_out[num][1]
        if self.forces is not None:
            rhs = rhs + self.forces(q, qd, t, args)
        mass = _decompress(columns, structure.mass, colours, unroll)
        mismatch = None
        if checked:
            mismatch = _probe_mismatch(
                columns.T, structure.mass, colours, d_out[-1][1], unroll
            )
        return mass, rhs, mismatch

    def _constraint_pass(self, q, qd, t, args, structure: Structure, unroll: bool):
        """`(A, bias, mismatch)`: the products of `A` with the seeds of its column
        colouring (and a probe, for a pattern not proven) and the acceleration bias,
        one traced pass per constraint. `mismatch` is `None` when nothing is
        checked."""
        n, dtype = q.shape[0], q.dtype
        k = structure.jac.shape[0]
        if k == 0:
            jac = SparseMatrix.dense(jnp.zeros((0, n), dtype))
            return jac, jnp.zeros((0,), dtype), None
        checked = not (structure.jac_is_dense or structure.jac_proven)
        seeds, colours = _seeds(structure.jac, dtype)
        num = seeds.shape[0]
        directions = np.asarray(seeds)
        if checked:
            directions = np.concatenate([directions, probe_vector(n)[None]])
        products, bias = [], []
        for c in self.constraints:
            products_c, bias_c = c.jacobian_products(q, qd, t, args, directions)
            products.append(products_c)
            bias.append(bias_c)
        products, bias = jnp.concatenate(products), jnp.concatenate(bias)
        jac = _decompress(products[:, :num].T, structure.jac, colours, unroll)
        mismatch = None
        if checked:
            mismatch = _probe_mismatch(
                products[:, :num], structure.jac, colours, products[:, -1], unroll
            )
        return jac, bias, mismatch

    def position_residual(self, q, t, args) -> Float[Array, " k"]:
        """`G_j(q, t)` for holonomic rows and `0` for Pfaffian ones, stacked like the
        rows of `A`: the position-level residual used by stabilization."""
        if not self.constraints:
            return jnp.zeros((0,), q.dtype)
        return jnp.concatenate(
            [c.position_residual(q, t, args) for c in self.constraints]
        )

    @full_precision
    def solve_accelerations(
        self, q, qd, t, args, bias_correction=None
    ) -> tuple[Float[Array, " n"], Float[Array, " k"], Bool[Array, ""]]:
        """`(qddot, lambda, singular)`: the KKT solve without raising.

        `singular` flags a KKT system without a solution, or a detected sparsity
        pattern that missed an entry at this state (then `qddot`, `lambda` are
        zeros); free gauge directions (no inertia, no force) are not singular, their
        accelerations are zero (see `accelerations`). The solve is
        `self.saddle_point_solver`'s. `bias_correction` (shape `(k,)`) is added to
        the acceleration bias, as Baumgarte stabilization does.
        """
        return solve_dynamics(self, q, qd, t, args, bias_correction)

    @full_precision
    def accelerations(self, q, qd, t, args=None):
        """Solve the equations of motion for `(qddot, multipliers)`.

        `[[M, -A^T], [A, 0]] [qddot; lambda] = [Q - c; -(Adot qdot + adot)]`, in the
        convention `d/dt(dL/dqdot) - dL/dq = A^T lambda + Q`.

        **Free gauge directions.** A velocity direction `v` with no inertia
        (`M v = 0`) that the constraints leave free (`A v = 0`) makes the KKT matrix
        singular. If no force acts along it (`(Q - c) . v = 0` to round-off), the
        equations hold whatever its acceleration: it is a free gauge, and its
        acceleration is set to zero (the unknown at the vanishing pivot of the
        elimination is 0; for a massless coordinate, e.g. the spin `theta2` of the
        rolling cylinder with `I = 0` after it lets go, `qddot` of that coordinate is
        0, so its velocity is held). See
        [`constrained_jax.AbstractSaddlePointSolver`][].

        Also raises if the sparsity patterns of `M` and `A`, found at random states
        when the system is first traced, miss an entry that is nonzero at this state
        (a coupling switched on by `jnp.where`, by `t` or by an integer parameter):
        pass `saddle_point_solver=cjax.FullKKTLU()` (dense, no pattern) then.

        Raises (at run time, also under `jit`) if the equations have no solution or
        no unique multipliers: a force acts along a direction without inertia that
        the constraints leave free (e.g. a massless coordinate with a potential
        gradient), or the constraints are redundant.
        """
        q, qd = inexact_asarray(q), inexact_asarray(qd)
        self.check(q, qd, t, args)
        system = self.saddle_point_system(q, qd, t, args)
        qdd, lam, singular = solve_saddle_point(self.saddle_point_solver, system)
        if system.mismatch is not None:
            qdd, lam = error_if((qdd, lam), system.mismatch, PATTERN_MISMATCH_MESSAGE)
        qdd, lam = error_if(
            (qdd, lam),
            singular,
            "The KKT matrix [[M, -A^T], [A, 0]] is singular and the equations of "
            "motion have no solution: a force acts along a velocity direction that "
            "has no inertia and that the constraints leave free (M is singular on "
            "the null space of A, e.g. a massless coordinate with a potential "
            "gradient), or the constraints are redundant. (A direction with no "
            "inertia and no force is a free gauge and gets zero acceleration, except "
            "with `cjax.SparseSchur`, which the default `cjax.Automatic()` uses for "
            "systems of more than 6 unknowns with a block-diagonal M and which needs "
            "every mass pivot nonzero: for a massless coordinate there, pass "
            "`saddle_point_solver=cjax.FullKKTLU()`.) Check the mass matrix and the "
            "forces, and remove dependent constraints.",
        )
        return qdd, lam

    @full_precision
    def constraint_forces(self, q, qd, t, args=None) -> Float[Array, " n"]:
        """The generalised force of constraint `Q^c = A^T lambda`."""
        q, qd = inexact_asarray(q), inexact_asarray(qd)
        _, lam = self.accelerations(q, qd, t, args)
        jac = self.constraint_jacobian(q, jnp.asarray(t, q.dtype), args)
        return jac.T @ lam


def _either(a, b):
    """`a | b` for flags that may be `None` (nothing checked)."""
    if a is None:
        return b
    if b is None:
        return a
    return a | b


def solve_dynamics(
    system: LagrangianSystem, q, qd, t, args, bias_correction=None, fill: float = 0.0
):
    """`(qddot, lambda, singular)` of `system` at `(q, qd, t)`: its saddle-point
    system solved by its solver, differentiated by the implicit rule; `qddot` is
    `fill` where `singular` (NaN inside a time integration: the step is then
    rejected). With slipping contacts, the coupled solve of `friction_dynamics`."""
    return friction_dynamics(system, q, qd, t, args, bias_correction, fill)[:3]


def friction_dynamics(
    system: LagrangianSystem, q, qd, t, args, bias_correction=None, fill: float = 0.0
):
    """`(qddot, lambda, singular, consistency)`: `solve_dynamics` with the kinetic
    friction of the contacts that slip (`system.slip`), and per contact with
    friction the coefficient `D_jj` of its normal multiplier in the coupled system
    (`1` for one that does not slip; `<= 0`: the Painleve paradox).

    The friction force of a slipping contact `j` is `f_j = -mu_k s_j N_j` along its
    tangential row `a_j` (`N_j = sign_j lambda_n_j`, `s_j` the slip direction), a
    generalised force `a_j^T f_j` on the right-hand side. The solve is linear in the
    right-hand side, so with `(x_0, lambda_0)` the solve without friction and
    `(x_j, lambda_j)` the solve for the force `a_j^T` alone (no bias), the normal
    multipliers satisfy `lambda_n = lambda_n0 + S f`, `S_ij = lambda_j[n_i]`, and
    `f = C lambda_n`, `C = diag(-mu_k s_j sign_j)`: `(I - S C) lambda_n =
    lambda_n0`, one small solve, exact (not a lagged force). Where `D = I - S C`
    has a non-positive diagonal the coupled system has no solution or several
    (a slender rod on a rough floor): the solve is `singular`."""
    kkt = system.saddle_point_system(q, qd, t, args, bias_correction)
    solver = system.saddle_point_solver
    x, lam, singular = solve_saddle_point(solver, kkt, fill)
    pairs = []
    if system.slip is not None:
        pairs = system.friction_pairs(q.shape[0], args, q.dtype)
    if not pairs:
        return x, lam, singular, jnp.ones((len(pairs),), q.dtype)
    t = jnp.asarray(t, q.dtype)
    normals = np.asarray([p[0] for p in pairs])
    tangents = np.asarray([p[1] for p in pairs])
    signs = jnp.asarray([p[2] for p in pairs], q.dtype)
    mu_k = jnp.stack([jnp.asarray(p[3].coefficients(args)[1], q.dtype) for p in pairs])
    coupling = -mu_k * system.slip[tangents] * signs
    zeros = jnp.zeros_like(kkt.bias)
    xs, lams = [], []
    for _, _, _, coulomb in pairs:
        row = jnp.reshape(coulomb.tangent.velocity_form(q, t, args)[0], (-1,))
        unit = SaddlePointSystem(
            kkt.mass, kkt.jac, row.astype(q.dtype), zeros, kkt.mismatch, kkt.active
        )
        x_j, lam_j, singular_j = solve_saddle_point(solver, unit, fill)
        xs.append(x_j)
        lams.append(lam_j)
        singular = singular | singular_j
    xs, lams = jnp.stack(xs), jnp.stack(lams)
    response = lams[:, normals].T  # S: normal multipliers per unit tangential force
    coefficients = jnp.eye(len(pairs), dtype=q.dtype) - response * coupling[None, :]
    consistency = jnp.diagonal(coefficients)
    lam_n = jnp.linalg.solve(coefficients, lam[normals])
    force = coupling * lam_n
    x = x + force @ xs
    lam = (lam + force @ lams).at[tangents].add(force)
    # (The solution is kept where `D` is not positive: inside a time integration a
    # NaN would make every step fail before the phase's Painleve event is found.)
    singular = singular | jnp.any(consistency <= 0)
    return x, lam, singular, consistency


def project(
    system: LagrangianSystem, q, qd, t, args, iterations: int, velocity_scale=None
):
    """The closest admissible state in the kinetic-energy metric: `(q, qd+, Lambda,
    singular)`.

    Positions: `iterations` Gauss-Newton steps of `[[M, -A^T], [A, 0]] [dq; mu] =
    [0; -G]` on the holonomic rows (Pfaffian rows get `0`: the correction is a
    virtual displacement), `M` at the given state and `A` at each iterate.
    Velocities: one solve of `[[M, -A^T], [A, 0]] [dv; Lambda] = [0; -s (A qd + a)]`,
    `s = velocity_scale` (shape `(k,)`, default 1): with `s = 1` the velocities are
    projected onto `A qd + a = 0`; with `s = 1 + e` on an impacting group's rows, it
    is Newton's impact law (the residual reversed and scaled by `e`), and `Lambda` is
    the impulse, `M (qd+ - qd) = A^T Lambda`.

    Each solve is the system's saddle-point solve (`M` and `A` as for the equations
    of motion, the same solver, differentiated by the implicit rule). `singular`
    flags a singular solve or a detected pattern that missed an entry at one of the
    states.
    """
    t = jnp.asarray(t, q.dtype)
    form = system.form(q, args)
    structure = system.structure(q, t, args, form.sparse)
    mass, _, mismatch = system._lagrangian_pass(q, qd, t, args, structure, form.unroll)
    zeros = jnp.zeros(q.shape, q.dtype)
    flags = [] if mismatch is None else [mismatch]

    def solve(q_, target):
        # [[M, -A^T], [A, 0]] [x; Lambda] = [0; target]: M x = A^T Lambda, A x = target.
        jac, _, mismatch_a = system._constraint_pass(
            q_, qd, t, args, structure, form.unroll
        )
        kkt = SaddlePointSystem(
            mass, jac, zeros, -target, mismatch_a, active=system.active
        )
        x, lam, singular = solve_saddle_point(system.saddle_point_solver, kkt)
        flags.append(singular)
        return x, lam

    for _ in range(iterations):
        step, _ = solve(q, -system.position_residual(q, t, args))
        q = q + step
    residual = system.velocity_residual(q, qd, t, args)
    if velocity_scale is not None:
        residual = velocity_scale * residual
    jump, impulse = solve(q, -residual)
    singular = functools.reduce(jnp.logical_or, flags)
    return q, qd + jump, impulse, singular
