"""Inequality constraints `H(x) <= 0`: the complementarity rows of a
[`constrained_jax._kkt.KKTProblem`][], their check, and the inequality arguments of
[`constrained_jax.extremize`][] (`inequalities`, `lower`, `upper`).

The KKT conditions of

    extremize F(x)  subject to  G(x) = 0,  H(x) <= 0,

in the convention `grad F + lambda . grad G + mu . grad H = 0`, `mu . H = 0`, with
`s mu >= 0` (`s = +1` to minimize, `-1` to maximize), are a square nonsmooth system:
complementarity `s mu_i >= 0, -H_i >= 0, s mu_i H_i = 0` holds exactly where the
Fischer-Burmeister function `phi(a, b) = a + b - sqrt(a^2 + b^2)` of `(s mu_i, -H_i)`
vanishes, so the unknowns `z = (x, lambda, mu)` solve the `n + k + m` equations

    grad F + J^T lambda + A^T mu = 0,    G = 0,    phi(s mu, -H) = 0

(`J = dG/dx`, `A = dH/dx`), by [`constrained_jax.SemismoothNewton`][]. A point where
that iteration stops is then checked against the KKT conditions themselves
(`complementarity_check`), so that a stop is never mistaken for a solution.

**References:** A. Fischer, *A special Newton-type optimization method*,
Optimization 24 (1992) 269-284; T. De Luca, F. Facchinei and C. Kanzow, *A semismooth
equation approach to the solution of nonlinear complementarity problems*,
Math. Programming 75 (1996) 407-439.
"""

import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jaxtyping import Array


# ---------------------------------------------------------------------------------
# The complementarity function
# ---------------------------------------------------------------------------------


@jax.custom_jvp
def fischer_burmeister(a: Array, b: Array) -> Array:
    """`phi(a, b) = a + b - sqrt(a^2 + b^2)`: zero exactly where `a >= 0`, `b >= 0`
    and `a b = 0`.

    Evaluated without cancellation (`2ab / (a + b + sqrt(a^2 + b^2))` where
    `a + b > 0`). Its derivative at the kink `a = b = 0` is taken as `(1, 0)`, the
    element of the B-subdifferential of an inactive constraint (`b > 0`, `a = 0`), so
    that it is always defined.
    """
    r = jnp.hypot(a, b)
    s = a + b
    safe = jnp.where(s > 0, s + r, 1.0)
    return jnp.where(s > 0, 2 * a * b / safe, s - r)


@fischer_burmeister.defjvp
def _fischer_burmeister_jvp(primals, tangents):
    a, b = primals
    ta, tb = tangents
    r = jnp.hypot(a, b)
    kink = r == 0
    safe = jnp.where(kink, 1.0, r)
    da = jnp.where(kink, 1.0, 1 - a / safe)
    db = jnp.where(kink, 0.0, 1 - b / safe)
    return fischer_burmeister(a, b), da * ta + db * tb


# ---------------------------------------------------------------------------------
# The check of the KKT conditions
# ---------------------------------------------------------------------------------


def _scales(problem, z, args):
    """Units in which the KKT conditions are checked: of the multipliers `mu`
    (`max(1, |mu|)`), of each `H_i` (`max(1, |x|) |grad H_i|`, floored at 1)
    and of the stationarity (`max(1, |grad F|)`, `grad F` the stationarity rows
    at zero multipliers), all max-norms."""
    x, _, mu = problem.split(z)
    if problem.bounds:
        row_size = jnp.abs(problem.bound_derivatives(x, args)).ravel()
    else:
        row_size = jnp.max(jnp.abs(jax.jacrev(problem.inequalities)(x, args)), axis=1)
    zero = jnp.zeros((z.shape[0] - x.shape[0],), z.dtype)
    grad_f = problem.equations(jnp.concatenate([x, zero]), args)[: problem.n]
    x_scale = jnp.maximum(1.0, jnp.max(jnp.abs(x)))
    h_scale = jnp.maximum(1.0, x_scale * row_size)
    mu_scale = jnp.maximum(1.0, jnp.max(jnp.abs(mu), initial=0.0))
    stat_scale = jnp.maximum(1.0, jnp.max(jnp.abs(grad_f)))
    return mu_scale, h_scale, stat_scale


def complementarity_check(problem, z, args, tol) -> dict[str, Array]:
    """The KKT conditions of `problem` (a `KKTProblem` with `m > 0`) at `z`, in the
    units of `_scales` (`a = s mu_i`, `b = -H_i`, each relative):

    - `active` where `H_i` is the zero of the complementary pair: `b <= max(a,
        tol^2)` (`tol^2` is the solver's own tolerance, `max(rtol, atol, 100 eps)`);
    - `strict` where also `a > tol^2`: active with a nonzero multiplier.
        `active & ~strict` are the weakly active (degenerate) inequalities;
    - `violation`: the largest violation of the KKT conditions (stationarity,
        `G = 0`, and `|min(a, b)|`, which covers feasibility, the sign of `mu` and
        complementarity);
    - `infeasibility`: the largest `H_i > 0`.
    """
    n = problem.n
    x, _, mu = problem.split(z)
    mu_scale, h_scale, stat_scale = _scales(problem, z, args)
    e = problem.equations(z, args)
    grad_star, g = e[:n], e[n:]
    h = problem.inequalities(x, args)
    a = problem.sign * mu / mu_scale
    b = -h / h_scale
    fine = tol * tol
    active = b <= jnp.maximum(a, fine)
    strict = active & (a > fine)
    complementarity = jnp.max(jnp.abs(jnp.minimum(a, b)), initial=0.0)
    stationarity = jnp.max(jnp.abs(grad_star)) / stat_scale
    x_scale = jnp.maximum(1.0, jnp.max(jnp.abs(x)))
    feasibility = jnp.max(jnp.abs(g), initial=0.0) / x_scale
    violation = jnp.maximum(jnp.maximum(complementarity, stationarity), feasibility)
    infeasibility = jnp.max(-b, initial=0.0)
    return {
        "active": active,
        "strict": strict,
        "violation": violation,
        "infeasibility": infeasibility,
    }


# ---------------------------------------------------------------------------------
# The inequality arguments of extremize
# ---------------------------------------------------------------------------------


def flat_bound(bound, x0, name: str, dtype):
    """`lower` or `upper` as a flat array matching `ravel_pytree(x0)`: a scalar or an
    array broadcast to every leaf, or a pytree with the structure of `x0` whose
    leaves broadcast to its leaves."""
    if bound is None:
        return None
    x_leaves, x_def = jtu.tree_flatten(x0)
    b_leaves, b_def = jtu.tree_flatten(bound)
    if b_def == x_def:
        pairs = list(zip(b_leaves, x_leaves, strict=True))
    elif len(b_leaves) == 1 and (len(x_leaves) == 1 or jnp.ndim(b_leaves[0]) == 0):
        pairs = [(b_leaves[0], leaf) for leaf in x_leaves]
    else:
        raise ValueError(
            f"`{name}` must be a scalar, an array that broadcasts to `x0`, or a pytree "
            f"with the structure of `x0` ({x_def}), got {b_def}."
        )
    flat = []
    for b, leaf in pairs:
        b = jnp.asarray(b)
        if not (jnp.issubdtype(b.dtype, jnp.number) and not jnp.iscomplexobj(b)):
            raise ValueError(f"`{name}` must hold real numbers, got dtype {b.dtype}.")
        try:
            shape = np.broadcast_shapes(b.shape, leaf.shape)
        except ValueError:
            shape = None
        if shape != leaf.shape:
            raise ValueError(
                f"`{name}` has shape {b.shape}, which does not broadcast to the shape "
                f"{leaf.shape} of `x0`: pass a scalar or an array of shape "
                f"{leaf.shape} (an entry with no bound is `-inf` in `lower`, `inf` in "
                "`upper`)."
            )
        flat.append(jnp.broadcast_to(b.astype(dtype), leaf.shape).ravel())
    return jnp.concatenate(flat)


def flat_inequalities(inequalities, unravel, m_user, lower, upper):
    """`H(x, (args, lower, upper))` on flat `x`: the user's rows, then `lower - x`,
    then `x - upper`; an infinite bound gives the row `-1` (never active)."""

    def h(x, aug):
        args, lo, up = aug
        rows = []
        if m_user:
            rows.append(jnp.atleast_1d(inequalities(unravel(x), args)))
        if lower is not None:
            rows.append(jnp.where(jnp.isfinite(lo), lo - x, -1.0))
        if upper is not None:
            rows.append(jnp.where(jnp.isfinite(up), x - up, -1.0))
        return jnp.concatenate(rows)

    return h


def check_inequalities(inequalities, x_flat, unravel, args):
    """The number of the user's inequalities, checked like `G`."""
    if inequalities is None:
        return 0
    h_struct = jax.eval_shape(lambda x: inequalities(unravel(x), args), x_flat)
    if not isinstance(h_struct, jax.ShapeDtypeStruct) or h_struct.ndim > 1:
        shape = getattr(h_struct, "shape", type(h_struct).__name__)
        raise ValueError(
            "The inequalities H(x, args) must return an array of shape (m,) (or a "
            f"scalar for a single inequality H <= 0), but returned {shape}. Stack "
            "them into one vector, e.g. `jnp.stack([h1, h2])` or `h.ravel()`."
        )
    if not jnp.issubdtype(h_struct.dtype, jnp.floating):
        raise ValueError(
            f"The inequalities H(x, args) must be floating point, got {h_struct.dtype}."
        )
    m = 1 if h_struct.ndim == 0 else h_struct.shape[0]
    if m == 0:
        raise ValueError(
            "The inequalities returned an empty array: pass `inequalities=None`."
        )
    return m


def check_concrete_bounds(lower, upper) -> None:
    """`lower > upper` anywhere, when both are known outside any trace: ValueError.
    (Traced bounds that cross give `RESULTS.infeasible_inequalities`.)"""
    if lower is None or upper is None:
        return
    lo_leaves, up_leaves = jtu.tree_leaves(lower), jtu.tree_leaves(upper)
    if any(isinstance(v, jax.core.Tracer) for v in lo_leaves + up_leaves):
        return
    if len(lo_leaves) != len(up_leaves):
        return  # The shape check inside says what is wrong.
    for lo, up in zip(lo_leaves, up_leaves, strict=True):
        try:
            crossed = np.any(np.asarray(lo) > np.asarray(up))
        except ValueError:
            return  # Shapes that do not broadcast: reported inside.
        if crossed:
            raise ValueError(
                "`lower > upper` for some entries: no x satisfies the bounds. Check "
                "the bounds (an entry with no bound is `-inf` in `lower` or `inf` in "
                "`upper`)."
            )
