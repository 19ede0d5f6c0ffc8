"""A structured linear solver for the KKT systems of low-order meshes.

A functional discretized on a mesh of piecewise-linear elements couples the unknowns
of a node only to those of its two neighbours. Ordering the unknowns node by node,
`(y_i, mu_i)` (the `n` values and the `m` pointwise holonomic multipliers of node
`i`), followed by the `k` multipliers of the integral constraints, the KKT matrix is
*bordered block tridiagonal*:

    K = [[T, B  ],        T block tridiagonal, blocks of size s = n + m,
         [B^T, C]]        B dense (N s x k), C (k x k).

[`constrained_jax.BorderedBlockTridiagonal`][] recovers the blocks of `K` from
`3 s + k` matrix-vector products (products with a Jacobian are Jacobian-vector
products: no matrix is formed by autodiff), factors `T` by block Gaussian elimination
(the block Thomas algorithm, one `lax.scan` over the nodes) and eliminates the border
with the `k x k` Schur complement `C - B^T T^{-1} B`. Work and memory are linear in the
number of nodes.
"""

from typing import Any

import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jaxtyping import Array, Bool, Float

from .dense_lu import dense_factor, dense_solve, lu_factor_unrolled, lu_solve_unrolled


def _block_inverse(a: Float[Array, "s s"]) -> tuple[Float[Array, "s s"], Bool]:
    """Inverse of a small block by unrolled LU with partial pivoting."""
    s = a.shape[-1]
    lu, perm, singular = lu_factor_unrolled(a)
    safe = jnp.where(singular, jnp.eye(s, dtype=a.dtype), lu)
    eye = jnp.eye(s, dtype=a.dtype)
    inv = jnp.stack([lu_solve_unrolled(safe, perm, eye[:, j]) for j in range(s)], 1)
    return inv, singular


def block_tridiagonal_factor(lower, diag, upper):
    """Block LU factorisation of a block tridiagonal matrix (no pivoting across blocks).

    With `S_0 = D_0`, `E_i = S_i^{-1} U_i` and `S_i = D_i - L_i E_{i-1}`, the matrix
    is the product of a block lower bidiagonal factor (diagonal `S_i`, subdiagonal
    `L_i`) and a block upper bidiagonal one (unit diagonal, superdiagonal `E_i`).

    **Arguments:** `lower[i] = T[i, i-1]` (`lower[0]` unused), `diag[i] = T[i, i]`,
    `upper[i] = T[i, i+1]` (the last one unused), each of shape `(N, s, s)`.

    **Returns:** `(S_inverse, E, singular)`.
    """

    def step(e_prev, blocks):
        l, d, u = blocks
        s_i = d - l @ e_prev
        s_inv, singular = _block_inverse(s_i)
        e_i = s_inv @ u
        return e_i, (s_inv, e_i, singular)

    s = diag.shape[-1]
    e0 = jnp.zeros((s, s), diag.dtype)
    _, (s_inv, e, singular) = lax.scan(step, e0, (lower, diag, upper))
    return s_inv, e, jnp.any(singular)


def block_tridiagonal_solve(factors, lower, rhs: Float[Array, "N s r"]):
    """Solve `T u = rhs` with the output of `block_tridiagonal_factor`."""
    s_inv, e = factors

    def forward(g_prev, blocks):
        si, l, f = blocks
        g = si @ (f - l @ g_prev)
        return g, g

    g0 = jnp.zeros(rhs.shape[1:], rhs.dtype)
    _, g = lax.scan(forward, g0, (s_inv, lower, rhs))

    def backward(u_next, blocks):
        g_i, e_i = blocks
        u = g_i - e_i @ u_next
        return u, u

    _, u = lax.scan(backward, g0, (g, e), reverse=True)
    return u


# Up to this many blocks the probe and index arrays are NumPy constants (gathers with
# constant indices, as fast as before); above, they are built from iota in the
# program, so that compile time does not grow with the mesh.
CONSTANT_INDICES_MAX = 10_000


class BorderedBlockTridiagonal(lx.AbstractLinearSolver):
    """Direct solver for a symmetric bordered block tridiagonal KKT matrix.

    The unknowns `z` (a flat vector) are laid out as a discretized functional lays
    them out: the `num_blocks * num_primal` nodal values (node-major), then the
    `num_blocks * num_dual` pointwise multipliers (node-major), then the `border`
    global multipliers. Node `i`'s values and multipliers form block `i`; a block
    couples only to its neighbours; the border couples to everything.

    `init` probes the operator with `3 s + border` vectors (`s = num_primal +
    num_dual`): columns of blocks three apart never share a row, so one product
    recovers a column of every third block. It then factors the block tridiagonal part
    and the Schur complement of the border. Each `compute` is two sweeps over the
    nodes. Cost `O(N s^3 + N s k^2)` in time and `O(N s (s + k))` in memory.

    Singular diagonal blocks (in the elimination order) or a singular Schur complement
    are reported as `lineax.RESULTS.singular`.

    !!! note

        There is no pivoting between blocks. This is stable when the Hessian of the
        discretized `F*` is definite on the nodal values (a minimum or a maximum of
        the functional, the usual case in the calculus of variations) and the pointwise
        constraint gradients do not vanish; the KKT matrix of a saddle of the
        functional may need [`constrained_jax.DenseLU`][] instead.
    """

    num_blocks: int = eqx.field(static=True)
    num_primal: int = eqx.field(static=True)
    num_dual: int = eqx.field(static=True)
    border: int = eqx.field(static=True)

    def __check_init__(self):
        if self.num_blocks < 1 or self.num_primal < 1:
            raise ValueError(
                "`BorderedBlockTridiagonal` needs at least one block of at least one "
                "unknown."
            )
        if self.num_dual < 0 or self.border < 0:
            raise ValueError("`num_dual` and `border` must be non-negative.")

    @property
    def size(self) -> int:
        return self.num_blocks * (self.num_primal + self.num_dual) + self.border

    def _to_blocks(self, v):
        """Flat layout -> `(blocks (N, s, ...), border (k, ...))`."""
        nb, n, m = self.num_blocks, self.num_primal, self.num_dual
        rest = v.shape[1:]
        y = v[: nb * n].reshape(nb, n, *rest)
        mu = v[nb * n : nb * (n + m)].reshape(nb, m, *rest)
        return jnp.concatenate([y, mu], axis=1), v[nb * (n + m) :]

    def _from_blocks(self, blocks, border):
        nb, n = self.num_blocks, self.num_primal
        rest = blocks.shape[2:]
        y = blocks[:, :n].reshape(nb * n, *rest)
        mu = blocks[:, n:].reshape(-1, *rest)
        return jnp.concatenate([y, mu, border], axis=0)

    def init(self, operator: lx.AbstractLinearOperator, options: dict[str, Any]):
        del options
        structure = operator.in_structure()
        if (
            not isinstance(structure, jax.ShapeDtypeStruct)
            or structure.shape != (self.size,)
            or operator.out_structure() != structure
        ):
            raise ValueError(
                "`BorderedBlockTridiagonal` expects a square operator on a flat vector "
                f"of size {self.size} (num_blocks * (num_primal + num_dual) + border), "
                f"got {structure}."
            )
        nb, s, k = self.num_blocks, self.num_primal + self.num_dual, self.border
        dtype = structure.dtype
        # Probe vectors: colour (r, j) = position j of every block b = r (mod 3); then
        # one unit vector per border unknown. (Above CONSTANT_INDICES_MAX blocks built
        # from iota, like the indices below: no size-num_blocks constants.)
        xp = np if nb <= CONSTANT_INDICES_MAX else jnp
        r, j, block, col = xp.ix_(
            xp.arange(3), xp.arange(s), xp.arange(nb), xp.arange(s)
        )
        colour = ((block % 3 == r) & (col == j)).reshape(3 * s, nb, s)
        probes_blocks = jnp.asarray(colour, dtype)
        probes = jax.vmap(lambda b: self._from_blocks(b, jnp.zeros((k,), dtype)))(
            probes_blocks
        )
        if k > 0:
            border_probes = jax.vmap(
                lambda e: self._from_blocks(jnp.zeros((nb, s), dtype), e)
            )(jnp.eye(k, dtype=dtype))
            probes = jnp.concatenate([probes, border_probes], axis=0)
        outputs = jax.vmap(operator.mv)(probes)  # (3s + k, size)
        out_blocks, out_border = jax.vmap(self._to_blocks)(outputs)
        tri = out_blocks[: 3 * s].reshape(3, s, nb, s)  # [r, col j, block i, row]
        i = xp.arange(nb)
        # T[i, b][row, j] = tri[b % 3, j, i, row] for b in {i-1, i, i+1}.
        diag = jnp.transpose(tri[i % 3, :, i, :], (0, 2, 1))
        lower = jnp.transpose(tri[(i - 1) % 3, :, i, :], (0, 2, 1))
        upper = jnp.transpose(tri[(i + 1) % 3, :, i, :], (0, 2, 1))
        lower = lower.at[0].set(0.0)
        upper = upper.at[-1].set(0.0)
        s_inv, e, singular = block_tridiagonal_factor(lower, diag, upper)
        if k > 0:
            b = jnp.transpose(out_blocks[3 * s :], (1, 2, 0))  # (nb, s, k)
            c = out_border[3 * s :].T  # (k, k)
            w = block_tridiagonal_solve((s_inv, e), lower, b)
            schur = c - jnp.einsum("isk,isl->kl", b, w)
            schur_factors = dense_factor(schur, unroll_max=12)
            singular = singular | schur_factors[2]
        else:
            b = w = jnp.zeros((nb, s, 0), dtype)
            schur_factors = None
        return (s_inv, e, lower, b, w, schur_factors, singular)

    def compute(self, state, vector, options: dict[str, Any]):
        del options
        s_inv, e, lower, b, w, schur_factors, singular = state
        f, g = self._to_blocks(vector)
        u0 = block_tridiagonal_solve((s_inv, e), lower, f[..., None])[..., 0]
        if self.border > 0:
            rhs = g - jnp.einsum("isk,is->k", b, u0)
            v = dense_solve(schur_factors, rhs, unroll_max=12)
            u = u0 - jnp.einsum("isk,k->is", w, v)
        else:
            v, u = g, u0
        x = self._from_blocks(u, v)
        x = jnp.where(singular, 0.0, x)
        result = lx.RESULTS.where(singular, lx.RESULTS.singular, lx.RESULTS.successful)
        return x, result, {}

    def transpose(self, state, options: dict[str, Any]):
        # The KKT matrix is symmetric (it is a Hessian of F* = F + lambda . G).
        return state, options

    def conj(self, state, options: dict[str, Any]):
        return state, options

    def assume_full_rank(self):
        return True


BorderedBlockTridiagonal.__init__.__doc__ = """**Arguments:**

- `num_blocks`: the number of nodes carrying unknowns.
- `num_primal`: values per node (the number of functions `n`).
- `num_dual`: pointwise multipliers per node (the number of holonomic constraints).
- `border`: global unknowns coupled to every node (the integral multipliers).
"""
