"""Exactness and integrability of Pfaffian constraints; integrating an exact form.

A set of `k` constraints in the lecture's differential form

    sum_sigma g_{j sigma}(q, t) dq_sigma + h_j(q, t) dt = 0,        j = 1..k,

is, row by row, a 1-form `omega_j = w_{ja} dx_a` on the `(n + 1)`-dimensional space
`x = (q_1, ..., q_n, t)`, with coefficients `w_j = (g_{j1}, ..., g_{jn}, h_j)`. Its
exterior derivative `d omega_j = sum_{a<b} F_{jab} dx_a ^ dx_b` has the components

    F_{jab} = d w_{jb} / dx_a - d w_{ja} / dx_b,

computed here by one forward-mode Jacobian. Three questions, in increasing generality:

- **exact** (holonomic as written): `F_j = 0`, which are the lecture's conditions
  `dg_{j sigma}/dq_sigma' = dg_{j sigma'}/dq_sigma` and
  `dg_{j sigma}/dt = dh_j/dq_sigma`. Then `omega_j = dG_j` and the constraint is
  `G_j(q, t) = const`.
- **integrable** (holonomic after an integrating factor, Frobenius):
  `d omega_j ^ omega_1 ^ ... ^ omega_k = 0` for every `j`; for one constraint
  `omega ^ d omega = 0`. Then some combination `mu omega` is exact.
- otherwise **non-holonomic** (the rolling disk): no set of `k` functions `G_j(q, t)`
  describes the constraints; they restrict velocities, not only configurations.

`integrate_pfaffian` turns an exact form into a `Holonomic` constraint by integrating
along straight segments (the Poincare-lemma potential).

All tests here are *pointwise*: they evaluate derivatives at given points and so check
a necessary condition at those samples. A form that fails at one point is certainly not
exact (integrable); a form that passes at every sample point is very likely so, but
only on the samples, not proven.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from ._constraints import AbstractConstraint, Holonomic
from ._custom_types import Args, ScalarLike
from ._misc import (
    all_finite,
    as_traced_args,
    default_float_dtype,
    full_precision,
)


# ---------------------------------------------------------------------------------
# Structure checks (trace time)
# ---------------------------------------------------------------------------------


def _check_constraint(constraint, fn_name: str) -> None:
    if not isinstance(constraint, AbstractConstraint):
        raise ValueError(
            f"`{fn_name}` takes a constraint object, e.g. "
            "`constrained_jax.Pfaffian(g, h)` with `g(q, t, args)` of shape (k, n) and "
            f"`h(q, t, args)` of shape (k,) (or `None`); got "
            f"{type(constraint).__name__}. Wrap a bare function `g` as `Pfaffian(g)`."
        )


def _as_float(x: ArrayLike, name: str) -> Array:
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.inexact):
        x = x.astype(default_float_dtype())
    if jnp.issubdtype(x.dtype, jnp.complexfloating):
        raise ValueError(f"`{name}` must be real, got dtype {x.dtype}.")
    return x


def _points(q, t, fn_name: str):
    """`q` of shape `(n,)` or `(m, n)`, `t` a scalar or `(m,)`, as arrays of one dtype.

    Returns `(q, t, batched)` with `q` of shape `(m, n)` and `t` of shape `(m,)` when
    batched, else `(n,)` and `()`.
    """
    q = _as_float(q, "q")
    if q.ndim not in (1, 2) or q.shape[-1] == 0:
        raise ValueError(
            f"`{fn_name}`: `q` must have shape (n,) for one point or (m, n) for m "
            f"sample points, with n >= 1 coordinates; got shape {q.shape}."
        )
    t = jnp.asarray(t).astype(q.dtype)
    batched = q.ndim == 2
    if batched:
        m = q.shape[0]
        if t.ndim == 0:
            t = jnp.broadcast_to(t, (m,))
        elif t.shape != (m,):
            raise ValueError(
                f"`{fn_name}`: with m = {m} sample points `q` of shape {q.shape}, `t` "
                f"must be a scalar or have shape ({m},); got shape {t.shape}."
            )
    elif t.ndim != 0:
        raise ValueError(
            f"`{fn_name}`: `t` must be a scalar for one point `q` of shape {q.shape} "
            f"(give `q` a leading batch axis for several points); got shape {t.shape}."
        )
    return q, t, batched


def _default_rtol(rtol, dtype) -> float:
    return float(np.sqrt(np.finfo(dtype).eps)) if rtol is None else rtol


def _shape(out):
    return getattr(out, "shape", type(out).__name__)


def _check_form(constraint, n: int, dtype, args) -> int:
    """Shape-check `g` and `h` at the dtype of `q` (no FLOPs); return `k`."""
    return constraint.num_constraints(n, args, dtype)


# ---------------------------------------------------------------------------------
# The 1-forms and their exterior derivatives
# ---------------------------------------------------------------------------------


def _coefficients(constraint, args):
    """`x = (q, t) -> w(x)`, the `(k, n + 1)` coefficients `(g, h)` of the 1-forms."""

    def w(x):
        g, h = constraint.velocity_form(x[:-1], x[-1], args)
        h = jnp.broadcast_to(h, g.shape[:1]).astype(g.dtype)
        return jnp.concatenate([g, h[:, None]], axis=1)

    return w


def _form_and_derivative(constraint, q, t, args):
    """`(w, dw/dx)` at `x = (q, t)`: shapes `(k, N)` and `(k, N, N)`, `N = n + 1`.

    `jac[j, b, a] = d w_{jb} / dx_a`.
    """
    x = jnp.concatenate([q, t[None]])
    w_fn = _coefficients(constraint, args)
    jac, w = jax.jacfwd(lambda x_: (w_fn(x_), w_fn(x_)), has_aux=True)(x)
    return w, jac


def _exterior(jac):
    """`F_{jab} = d w_{jb}/dx_a - d w_{ja}/dx_b` from `jac[j, b, a] = d w_{jb}/dx_a`."""
    return jnp.swapaxes(jac, -1, -2) - jac


@full_precision
def exterior_derivative(
    constraint: AbstractConstraint,
    q: Float[ArrayLike, " n"],
    t: ScalarLike = 0.0,
    args: Args = None,
) -> Float[Array, "k n+1 n+1"]:
    """The exterior derivatives `d omega_j` of the constraint 1-forms at `(q, t)`.

    Each row `omega_j = sum_sigma g_{j sigma} dq_sigma + h_j dt` is a 1-form on the
    space `x = (q_1, ..., q_n, t)`. Returns the antisymmetric matrices

        F_{jab} = d w_{jb} / dx_a - d w_{ja} / dx_b,
        d omega_j = sum_{a<b} F_{jab} dx_a ^ dx_b,

    where `w_j = (g_{j1}, ..., g_{jn}, h_j)`; the last index (`n`) is time. By one
    forward-mode Jacobian of `(g, h)`.

    **Arguments:**

    - `constraint`: a [`constrained_jax.Pfaffian`][] (or any constraint; a
        [`constrained_jax.Holonomic`][] one gives `F = 0` up to round-off).
    - `q`: the point, shape `(n,)`.
    - `t`: the time, a scalar.
    - `args`: parameters passed last to `g` and `h`.

    **Returns:**

    `F`, shape `(k, n + 1, n + 1)`, antisymmetric in its last two axes. The form is
    closed at `(q, t)` exactly when `F = 0` there (the lecture's conditions).
    """
    _check_constraint(constraint, "exterior_derivative")
    q, t, batched = _points(q, t, "exterior_derivative")
    if batched:
        raise ValueError(
            "`exterior_derivative` takes one point `q` of shape (n,); use `jax.vmap` "
            f"for several. Got shape {q.shape}."
        )
    _check_form(constraint, q.shape[0], q.dtype, args)
    return _exterior_jit(constraint, q, t, as_traced_args(args))


@eqx.filter_jit
def _exterior_jit(constraint, q, t, args):
    _, jac = _form_and_derivative(constraint, q, t, args)
    return _exterior(jac)


# ---------------------------------------------------------------------------------
# Pointwise tests
# ---------------------------------------------------------------------------------


def _exact_at(constraint, q, t, args, rtol, atol):
    w, jac = _form_and_derivative(constraint, q, t, args)
    violation = jnp.max(jnp.abs(_exterior(jac)), axis=(1, 2))
    scale = jnp.max(jnp.abs(jac), axis=(1, 2))
    return violation <= atol + rtol * scale, all_finite((w, jac))


def _integrable_at(constraint, q, t, args, rtol, atol):
    w, jac = _form_and_derivative(constraint, q, t, args)
    ext = _exterior(jac)
    # Orthogonal projector onto the distribution D = ker W = {v : omega_j(v) = 0}.
    proj = jnp.eye(w.shape[1], dtype=w.dtype) - jnp.linalg.pinv(w) @ w
    restricted = proj @ ext @ proj  # d omega_j restricted to D, for every j
    violation = jnp.max(jnp.abs(restricted), axis=(1, 2))
    scale = jnp.max(jnp.abs(jac), axis=(1, 2))
    return violation <= atol + rtol * scale, all_finite((w, jac))


def _pointwise(test, constraint, q, t, args, rtol, atol, fn_name):
    _check_constraint(constraint, fn_name)
    q, t, _ = _points(q, t, fn_name)
    _check_form(constraint, q.shape[-1], q.dtype, args)
    rtol = _default_rtol(rtol, q.dtype)
    return _pointwise_jit(test, constraint, q, t, as_traced_args(args), rtol, atol)


@eqx.filter_jit
def _pointwise_jit(test, constraint, q, t, args, rtol, atol):
    at = lambda q_, t_: test(constraint, q_, t_, args, rtol, atol)
    if q.ndim == 2:  # sample points: the row must pass at every one
        flags, finite = jax.vmap(at)(q, t)
        flags, finite = jnp.all(flags, axis=0), jnp.all(finite)
    else:
        flags, finite = at(q, t)
    # A comparison with NaN is false: without this a non-finite point would "prove"
    # that a row is not exact (or not integrable).
    return eqx.error_if(
        flags,
        jnp.invert(finite),
        "The form or its derivatives are NaN or inf at a sample point (q, t) (or q, "
        "t, args are): the test cannot decide there. Drop such points (e.g. a "
        "singular point of the form).",
    )


@full_precision
def is_exact(
    constraint: AbstractConstraint,
    q: Float[ArrayLike, " n"] | Float[ArrayLike, "m n"],
    t: ScalarLike | Float[ArrayLike, " m"] = 0.0,
    args: Args = None,
    *,
    rtol: float | None = None,
    atol: float = 0.0,
) -> Bool[Array, " k"]:
    """Whether each constraint row is an exact differential `dG_j`, tested at points.

    Checks, by autodiff at `(q, t)`, the lecture's conditions for
    `sum_sigma g_{j sigma} dq_sigma + h_j dt` to integrate to a holonomic constraint
    `G_j(q, t) = 0` with `g_{j sigma} = dG_j/dq_sigma`, `h_j = dG_j/dt`:

        dg_{j sigma} / dq_sigma' = dg_{j sigma'} / dq_sigma,
        dg_{j sigma} / dt        = dh_j / dq_sigma,

    i.e. `d omega_j = 0` (see [`constrained_jax.exterior_derivative`][]). Row `j`
    passes when

        max_{a,b} |F_{jab}| <= atol + rtol * max_{a,b} |d w_{jb} / dx_a|,

    the size of the antisymmetric part of the Jacobian of `w_j = (g_j, h_j)` relative
    to the whole Jacobian.

    **Arguments:**

    - `constraint`: a [`constrained_jax.Pfaffian`][] `(g, h)`; `g(q, t, args)` of
        shape `(k, n)`, `h(q, t, args)` of shape `(k,)` or `None`.
    - `q`: one point, shape `(n,)`, or `m` sample points, shape `(m, n)`.
    - `t`: the time: a scalar, or shape `(m,)` with sample points.
    - `args`: parameters passed last to `g` and `h`.
    - `rtol`, `atol`: the tolerance above; `rtol` defaults to `sqrt(eps)` of the dtype
        of `q` (`1.5e-8` in float64, `3.5e-4` in float32).

    **Returns:**

    Flags of shape `(k,)`, one per constraint; with sample points, `True` only where the
    row passes at *every* sample.

    !!! note

        This is a pointwise test: a necessary condition, checked at the given points.
        A `False` proves the row is not exact; a `True` says only that it is closed at
        the samples (e.g. `dx - R cos(theta) dphi` passes at `theta = 0`). Test on a
        spread of points (a batch of `q`, times `t`) for confidence. Exactness also
        needs a simply connected domain: `(x dy - y dx)/(x^2 + y^2)` passes everywhere
        off the origin but is only locally `d(atan2(y, x))`.

    Composes with `jax.jit` and `jax.vmap` (`vmap` over single points gives per-point
    flags).
    """
    return _pointwise(_exact_at, constraint, q, t, args, rtol, atol, "is_exact")


@full_precision
def is_integrable(
    constraint: AbstractConstraint,
    q: Float[ArrayLike, " n"] | Float[ArrayLike, "m n"],
    t: ScalarLike | Float[ArrayLike, " m"] = 0.0,
    args: Args = None,
    *,
    rtol: float | None = None,
    atol: float = 0.0,
) -> Bool[Array, " k"]:
    """The Frobenius test: whether the constraints are holonomic up to integrating
    factors, tested at points.

    The `k` constraint 1-forms `omega_j = sum_sigma g_{j sigma} dq_sigma + h_j dt` on
    `x = (q, t)` define the distribution `D = {v : omega_j(v) = 0 for all j}` of
    allowed directions. By Frobenius' theorem `D` is integrable (the constraints are
    equivalent to `k` holonomic ones `G_j(q, t) = 0`, though the rows themselves may
    need integrating factors or recombination) if and only if

        d omega_j ^ omega_1 ^ ... ^ omega_k = 0,        j = 1..k.

    For one constraint this is `omega ^ d omega = 0`, whose components are the cyclic
    sums `w_a F_bc + w_b F_ca + w_c F_ab`. For linearly independent `omega`'s the
    condition is equivalent to `d omega_j` vanishing on `D`,

        P F_j P = 0,        P = I - W^+ W,

    with `W` the `(k, n + 1)` matrix of rows `w_j = (g_j, h_j)`, `P` the orthogonal
    projector onto `D = ker W`, and `F_j` the exterior derivative (see
    [`constrained_jax.exterior_derivative`][]); this is what is computed (for `k = 1`,
    `max |P F P|` is `|omega ^ d omega| / |omega|`). Row `j` passes when

        max_{a,b} |(P F_j P)_{ab}| <= atol + rtol * max_{a,b} |d w_{jb} / dx_a|.

    **Arguments:**

    - `constraint`: a [`constrained_jax.Pfaffian`][] `(g, h)`; `g(q, t, args)` of
        shape `(k, n)`, `h(q, t, args)` of shape `(k,)` or `None`.
    - `q`: one point, shape `(n,)`, or `m` sample points, shape `(m, n)`.
    - `t`: the time: a scalar, or shape `(m,)` with sample points.
    - `args`: parameters passed last to `g` and `h`.
    - `rtol`, `atol`: the tolerance above; `rtol` defaults to `sqrt(eps)` of the dtype
        of `q`.

    **Returns:**

    Flags of shape `(k,)`: flag `j` says `d omega_j` vanishes on the distribution of
    *all* `k` constraints. The constraints are holonomic (integrable) when every flag
    is `True`; for `k > 1` a single flag is not a statement about row `j` alone. With
    sample points, `True` only where the row passes at every sample.

    !!! note

        Pointwise, like [`constrained_jax.is_exact`][]: a necessary condition, checked
        at the given points. It assumes the rows are linearly independent there
        (constant rank); dependent rows are handled through the pseudo-inverse, i.e.
        the test is then about the distribution they actually span. Every exact form
        is integrable; `y dx - x dy` is integrable (`= -y^2 d(x/y)`) but not exact;
        the rolling disk's `dx - R cos(theta) dphi` is neither.
    """
    return _pointwise(
        _integrable_at, constraint, q, t, args, rtol, atol, "is_integrable"
    )


# ---------------------------------------------------------------------------------
# Integrating an exact form
# ---------------------------------------------------------------------------------


def _form_at(constraint, q, t, args):
    """`(g, h)` at `(q, t)`, with `h` broadcast to shape `(k,)` in the dtype of `g`."""
    g, h = constraint.velocity_form(q, t, args)
    return g, jnp.broadcast_to(h, g.shape[:1]).astype(g.dtype)


def _quadrature(q, t, q_ref, t_ref, rest):
    """The segment integral by the two Gauss-Legendre rules of `rest`, with the
    refusal: NaN in row `j` where the rules differ by more than `rtol` times the
    integral of `|omega_j|` along the segment."""
    constraint, args, nodes, weights, check_nodes, check_weights, rtol = rest
    dq, dt = q - q_ref, t - t_ref

    def integrand(s):
        g, h = _form_at(constraint, q_ref + s * dq, t_ref + s * dt, args)
        return g @ dq + h * dt

    values = jax.vmap(integrand)(jnp.concatenate([nodes, check_nodes]))
    values, check_values = values[: nodes.shape[0]], values[nodes.shape[0] :]
    integral = weights @ values
    if check_nodes.shape[0] == 0:  # `rtol=inf`: no check (NaN still propagates)
        return integral
    estimate = jnp.abs(integral - check_weights @ check_values)
    scale = weights @ jnp.abs(values)
    # `<=` is false for NaN, so a non-finite integrand is refused too; a zero-length
    # segment (estimate 0 <= 0) is not.
    return jnp.where(estimate <= rtol * scale, integral, jnp.nan)


@eqx.filter_custom_jvp
def _potential(q, t, q_ref, t_ref, rest):
    return _quadrature(q, t, q_ref, t_ref, rest)


@_potential.def_jvp
def _potential_jvp(primals, tangents):
    # The Poincare lemma, exactly: dG = g dq + h dt - g_ref dq_ref - h_ref dt_ref, by
    # the form itself and not by differentiating the quadrature (whose derivative
    # equals the form only to the quadrature's error). Derivatives with respect to
    # `args` (or arrays inside the constraint) go through the quadrature.
    q, t, q_ref, t_ref, rest = primals
    tq, tt, tq_ref, tt_ref, t_rest = tangents
    constraint, args = rest[0], rest[1]
    out = _potential(q, t, q_ref, t_ref, rest)
    t_out = jnp.zeros_like(out)
    for point, time, t_point, t_time, sign in (
        (q, t, tq, tt, 1),
        (q_ref, t_ref, tq_ref, tt_ref, -1),
    ):
        if t_point is not None or t_time is not None:
            g, h = _form_at(constraint, point, time, args)
            if t_point is not None:
                t_out = t_out + sign * (g @ t_point)
            if t_time is not None:
                t_out = t_out + sign * h * t_time
    differentiated = jtu.tree_map(
        lambda x: x is not None, t_rest, is_leaf=lambda x: x is None
    )
    if any(jtu.tree_leaves(differentiated)):
        diff, nondiff = eqx.partition(rest, differentiated)
        t_diff = eqx.filter(t_rest, differentiated, is_leaf=lambda x: x is None)
        integral = lambda d: _quadrature(q, t, q_ref, t_ref, eqx.combine(d, nondiff))
        t_out = t_out + jax.jvp(integral, (diff,), (t_diff,))[1]
    return out, t_out


class _SegmentIntegral(eqx.Module):
    """`G_j(q, t)`: the integral of `omega_j` on the segment from `(q_ref, t_ref)`."""

    constraint: AbstractConstraint
    q_ref: Float[Array, " n"]
    t_ref: Float[Array, ""]
    nodes: Float[Array, " p"]  # Gauss-Legendre nodes mapped to [0, 1]
    weights: Float[Array, " p"]  # the matching weights, summing to 1
    check_nodes: Float[Array, " r"]  # the rule one order lower (the error estimate)
    check_weights: Float[Array, " r"]
    rtol: float | None = eqx.field(static=True)

    def __call__(self, q, t, args) -> Float[Array, " k"]:
        q = _as_float(q, "q")
        return self._integral(q, jnp.asarray(t), as_traced_args(args))

    @eqx.filter_jit
    def _integral(self, q, t, args):
        if q.shape != self.q_ref.shape:
            raise ValueError(
                f"The integrated constraint was built for q of shape "
                f"{self.q_ref.shape} (that of `q_ref`); got shape {q.shape}."
            )
        t = jnp.asarray(t)
        if t.ndim != 0:
            raise ValueError(f"`t` must be a scalar, got shape {t.shape}.")
        dtype = q.dtype
        rtol = _default_rtol(self.rtol, dtype)
        cast = lambda x: x.astype(dtype)
        checked = rtol != float("inf")
        rest = (
            self.constraint,
            args,
            cast(self.nodes),
            cast(self.weights),
            cast(self.check_nodes) if checked else jnp.zeros((0,), dtype),
            cast(self.check_weights) if checked else jnp.zeros((0,), dtype),
            jnp.asarray(rtol, dtype),
        )
        return _potential(q, t.astype(dtype), cast(self.q_ref), cast(self.t_ref), rest)


@full_precision
def integrate_pfaffian(
    constraint: AbstractConstraint,
    q_ref: Float[ArrayLike, " n"],
    t_ref: ScalarLike = 0.0,
    args: Args = None,
    *,
    num_points: int = 16,
    rtol: float | None = None,
) -> Holonomic:
    """Integrate exact Pfaffian constraints to holonomic ones `G_j(q, t) = 0`.

    For an exact form `omega_j = sum_sigma g_{j sigma} dq_sigma + h_j dt`, returns the
    potential that vanishes at the reference point,

        G_j(q, t) = integral of omega_j along the straight segment
                    from (q_ref, t_ref) to (q, t)
                  = int_0^1 [g_j(x(s), tau(s)) . (q - q_ref)
                             + h_j(x(s), tau(s)) (t - t_ref)] ds,
        x(s) = q_ref + s (q - q_ref),    tau(s) = t_ref + s (t - t_ref),

    by Gauss-Legendre quadrature of fixed order `num_points` on the segment. Then
    `G_j(q_ref, t_ref) = 0`, and the derivatives are the form itself, exactly:
    `dG_j/dq_sigma = g_{j sigma}` and `dG_j/dt = h_j` (the Poincare lemma; the
    derivatives, of every order, are computed from `g` and `h`, not through the
    quadrature, so the constraint's Jacobian and acceleration bias in
    [`constrained_jax.simulate`][] carry no quadrature error and cost one evaluation
    of the form). Derivatives with respect to `args` go through the quadrature.

    The quadrature is exact when the integrand is a polynomial of degree
    `<= 2 num_points - 1` in `s` (for polynomial `g`, `h` of that degree in `(q, t)`),
    and converges spectrally (geometrically in `num_points`) for analytic
    coefficients; long segments over oscillatory coefficients need more points.

    **Right or refused.** Every evaluation also applies the rule with
    `num_points - 1` nodes (the trapezoid rule when `num_points = 1`), and row `j` of
    `G` is NaN where the two differ by more than `rtol` times the integral of
    `|omega_j|` along the segment: the quadrature does not resolve the form there.
    Since the difference estimates the error of the *lower* rule, a value that is
    returned is accurate well below `rtol` (relative to that scale) for analytic
    coefficients. A NaN `G` makes [`constrained_jax.simulate`][] refuse the start
    (`RESULTS.inconsistent_initial_state`) or the step; raise `num_points` (or
    choose `q_ref` near the motion). Cost: `2 num_points - 1` evaluations of the
    form per value of `G`.

    **Arguments:**

    - `constraint`: a [`constrained_jax.Pfaffian`][] `(g, h)` that is exact (check
        with [`constrained_jax.is_exact`][]).
    - `q_ref`: the reference configuration, shape `(n,)`: a point *on* the constraint
        surface, since `G(q, t) = 0` describes the surface through `(q_ref, t_ref)`.
    - `t_ref`: the reference time.
    - `args`: parameters the form will be evaluated with; used here only to check the
        shapes of `g` and `h`. The returned constraint takes its own `args` at call
        time.
    - `num_points`: the number of Gauss-Legendre nodes (static).
    - `rtol`: the refusal threshold above (static); defaults to `sqrt(eps)` of the
        dtype of `q`. `rtol=float("inf")` turns the refusal off, and with it the
        second rule (`num_points` evaluations per value; NaN integrands still give
        NaN): for a form known to be resolved, at your own risk.

    **Returns:**

    A [`constrained_jax.Holonomic`][] constraint whose `fn(q, t, args)` returns
    `G(q, t)`, shape `(k,)`. It is a pytree holding `q_ref` and `t_ref` as arrays, so it
    can be passed through `jax.jit` and differentiated with respect to them.

    !!! warning

        The result is meaningful only for exact forms. For a non-exact one the segment
        integral still returns numbers, but they depend on the path, `dG/dq != g`, and
        `G = 0` is not the constraint. Check first with
        [`constrained_jax.is_exact`][] (at several points). For a form that is exact
        only on a region that is not star-shaped about `q_ref` (e.g. the angle form
        `(x dy - y dx)/(x^2 + y^2)`), `G` is a potential only where the segments from
        `q_ref` stay in the region.
    """
    _check_constraint(constraint, "integrate_pfaffian")
    if (
        not isinstance(num_points, (int, np.integer))
        or isinstance(num_points, bool)
        or num_points < 1
    ):
        raise ValueError(f"`num_points` must be a positive int, got {num_points!r}.")
    q_ref, t_ref, batched = _points(q_ref, t_ref, "integrate_pfaffian")
    if batched:
        raise ValueError(
            f"`q_ref` must be one point of shape (n,); got shape {q_ref.shape}."
        )
    _check_form(constraint, q_ref.shape[0], q_ref.dtype, args)
    if rtol is not None and not (isinstance(rtol, (int, float)) and rtol >= 0):
        raise ValueError(f"`rtol` must be a non-negative float or None, got {rtol!r}.")
    nodes, weights = np.polynomial.legendre.leggauss(int(num_points))
    if num_points > 1:
        check_nodes, check_weights = np.polynomial.legendre.leggauss(
            int(num_points) - 1
        )
    else:
        check_nodes, check_weights = np.array([-1.0, 1.0]), np.array([1.0, 1.0])
    as_unit = lambda x: jnp.asarray(x, q_ref.dtype)
    integral = _SegmentIntegral(
        constraint,
        q_ref,
        t_ref,
        as_unit((nodes + 1) / 2),
        as_unit(weights / 2),
        as_unit((check_nodes + 1) / 2),
        as_unit(check_weights / 2),
        None if rtol is None else float(rtol),
    )
    return Holonomic(integral)
