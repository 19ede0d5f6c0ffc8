"""Constraints of a mechanical system, in the lecture's differential (Pfaffian) form.

Every constraint is written at the velocity level as

    sum_sigma g_{j sigma}(q, t) qdot_sigma + h_j(q, t) = 0,        j = 1..k,

i.e. `A(q, t) qdot + a(q, t) = 0`. A holonomic constraint `G_j(q, t) = 0` has
`g_{j sigma} = dG_j/dq_sigma` and `h_j = dG_j/dt`. Differentiating once more along the
motion gives the acceleration-level form used by the equations of motion,

    A qddot + (Adot qdot + adot) = 0,

where `Adot qdot + adot` is the derivative of `A qdot + a` along `(qdot, 1)` in
`(q, t)` at fixed `qdot`, one forward-mode pass.
"""

import abc
from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PyTree

from ._misc import check_signature, default_float_dtype


class AbstractConstraint(eqx.Module):
    """A set of `k` constraints, holonomic or not, in velocity form `A qdot + a = 0`.

    Two position-level residuals: `position_residual(q, t, args)`, shape `(k,)`, one
    per row of `A` (`G_j` for a holonomic row, `0` for a Pfaffian one); and
    `holonomic_residual(q, t, args)`, the holonomic rows `G` only.

    `unilateral`: whether the constraint can let go (a contact group, `Unilateral`:
    released where its multiplier would pull, re-made where its gap closes).
    """

    unilateral: ClassVar[bool] = False

    @abc.abstractmethod
    def velocity_form(
        self, q: Float[Array, " n"], t: Float[Array, ""], args: PyTree
    ) -> tuple[Float[Array, "k n"], Float[Array, " k"]]:
        """`(A, a)`: the coefficients `g_{j sigma}` and `h_j` at `(q, t)`."""

    @abc.abstractmethod
    def num_constraints(self, n: int, args: PyTree, dtype=None) -> int:
        """`k`, found by shape evaluation (no FLOPs), for coordinates of `dtype`."""

    def velocity_residual(self, q, qd, t, args) -> Float[Array, " k"]:
        """`A qdot + a`: zero on admissible motions."""
        jac, a = self.velocity_form(q, t, args)
        return jac @ qd + a

    def acceleration_bias(self, q, qd, t, args) -> Float[Array, " k"]:
        """`Adot qdot + adot`, so that the constraint at acceleration level reads
        `A qddot + bias = 0`."""
        fn = lambda q_, t_: self.velocity_residual(q_, qd, t_, args)
        return jax.jvp(fn, (q, t), (qd, jnp.ones_like(t)))[1]

    def jacobian_products(
        self, q, qd, t, args, directions: Float[Array, "s n"]
    ) -> tuple[Float[Array, "k s"], Float[Array, " k"]]:
        """`(A @ directions.T, Adot qdot + adot)` in one pass: the products of the
        Jacobian with a few directions (the seeds of a column colouring, a probe)
        and the acceleration bias."""
        jac, _ = self.velocity_form(q, t, args)
        directions = np.asarray(directions)
        if directions.size <= 24:
            # Static directions on scalars: fused under vmap (no batched `dot`).
            columns = [
                sum(jac[:, j] * float(v) for j, v in enumerate(row) if v != 0)
                for row in directions
            ]
            products = jnp.stack(
                [
                    jnp.zeros(jac.shape[0], jac.dtype) if isinstance(c, int) else c
                    for c in columns
                ],
                axis=1,
            )
        else:
            products = jac @ jnp.asarray(directions.T, jac.dtype)
        return products, self.acceleration_bias(q, qd, t, args)

    def position_residual(self, q, t, args) -> Float[Array, " k"]:
        """`G_j(q, t)` for holonomic rows and `0` for the others, one per row of `A`:
        the position-level residual that stabilization drives to zero."""
        return jnp.zeros((self.num_constraints(q.shape[0], args, q.dtype),), q.dtype)

    def holonomic_residual(self, q, t, args) -> Float[Array, " k_holonomic"]:
        """`G(q, t)` of the holonomic rows only (none for Pfaffian constraints)."""
        return jnp.zeros((0,), q.dtype)

    def discrete_residual(self, q0, q1, t0, h, args) -> Float[Array, " k"]:
        """The rows as a variational integrator's step from `(q0, t0)` to
        `(q1, t0 + h)` enforces them: in velocity form at the midpoint,
        `A(q_m, t_m) (q1 - q0) / h + a(q_m, t_m)`."""
        q_mid, t_mid = 0.5 * (q0 + q1), t0 + 0.5 * h
        return self.velocity_residual(q_mid, (q1 - q0) / h, t_mid, args)


# The most directions (colours of `A`, the probe and the bias) that `jacobian_products`
# applies one by one; more are pushed together by `jax.vmap`.
_FEW_DIRECTIONS = 8


class Holonomic(AbstractConstraint):
    """Holonomic constraints `G(q, t, args) = 0`, shape `(k,)` (a scalar is `k = 1`).

    Their velocity form has `g = dG/dq`, `h = dG/dt` (by autodiff); they can also be
    enforced at the position level (projection, stabilization), and their violation
    `G` is reported.
    """

    fn: Callable

    def __check_init__(self):
        check_signature(self.fn, "The function of `cjax.Holonomic`", "G(q, t, args)")

    def position_residual(self, q, t, args) -> Float[Array, " k"]:
        """`G(q, t)` (every row is holonomic); a list or tuple of rows is stacked."""
        return jnp.atleast_1d(_as_array(self.fn(q, t, args), q.dtype))

    def holonomic_residual(self, q, t, args):
        return self.position_residual(q, t, args)

    def discrete_residual(self, q0, q1, t0, h, args):
        """`G(q1, t0 + h)`: holonomic rows hold at the step's end."""
        return self.position_residual(q1, t0 + h, args)

    def velocity_form(self, q, t, args):
        fn = lambda q_, t_: self.position_residual(q_, t_, args)
        jac_q, jac_t = jax.jacfwd(fn, argnums=(0, 1))(q, t)
        return jac_q, jac_t

    def velocity_residual(self, q, qd, t, args):
        # One forward pass instead of the Jacobian: dG/dq qdot + dG/dt.
        fn = lambda q_, t_: self.position_residual(q_, t_, args)
        return jax.jvp(fn, (q, t), (qd, jnp.ones_like(t)))[1]

    def jacobian_products(self, q, qd, t, args, directions):
        # One traced copy of G with two nested forward passes: the outer tangent
        # (v, 0) gives dG/dq v = A v; the outer tangent (qdot, 1) applied to the
        # velocity residual (the inner pass) gives the bias. Few directions one by
        # one, many at once (below).
        fn = lambda q_, t_: self.position_residual(q_, t_, args)

        def with_velocity(q_, t_):
            return jax.jvp(fn, (q_, t_), (qd, jnp.ones_like(t_)))

        def along(dq, dt):
            return jax.jvp(with_velocity, (q, t), (dq, dt))[1]

        s = directions.shape[0]
        t = jnp.asarray(t, q.dtype)
        if (s + 1) * q.shape[0] <= 24 or s + 1 <= _FEW_DIRECTIONS:
            # Few directions: one linearisation, its linear map applied to each
            # (fused under vmap; on arrays, each application keeps its temporaries
            # the size of `q`, where `jax.vmap` over the directions makes them
            # `s + 1` times larger, which a batch of states then streams through
            # memory). The directions stay constants: stacked with `qdot`, they
            # would be copied for every state of a batch.
            _, linear = jax.linearize(with_velocity, q, t)
            zero_t = jnp.zeros((), q.dtype)
            columns = [linear(jnp.asarray(d, q.dtype), zero_t)[0] for d in directions]
            bias = linear(qd, jnp.ones((), q.dtype))[1]
            return jnp.stack(columns, axis=1), bias
        dqs = jnp.concatenate([jnp.asarray(directions, q.dtype), qd[None]])
        dts = jnp.concatenate([jnp.zeros((s,), q.dtype), jnp.ones((1,), q.dtype)])
        d_position, d_velocity = jax.vmap(along)(dqs, dts)
        return d_position[:s].T, d_velocity[s]

    def num_constraints(self, n, args, dtype=None):
        dtype = default_float_dtype() if dtype is None else dtype
        q = jax.ShapeDtypeStruct((n,), dtype)
        t = jax.ShapeDtypeStruct((), dtype)
        out = jax.eval_shape(
            lambda q_, t_: _as_array(self.fn(q_, t_, args), q_.dtype), q, t
        )
        return _check_shape("Holonomic", "G(q, t, args)", out, n, ndim=(0, 1))


class Pfaffian(AbstractConstraint):
    """Constraints in the lecture's differential form
    `sum_sigma g_{j sigma} dq_sigma + h_j dt = 0`.

    `g(q, t, args)` has shape `(k, n)`; `h(q, t, args)` shape `(k,)`, or `None` for
    `h = 0` (scleronomic). Holonomic or not: use `constrained_jax.is_exact` to test
    whether they integrate to `G(q, t) = 0`.
    """

    g: Callable
    h: Callable | None = None

    def __check_init__(self):
        check_signature(self.g, "The function `g` of `cjax.Pfaffian`", "g(q, t, args)")
        if self.h is not None:
            check_signature(
                self.h, "The function `h` of `cjax.Pfaffian`", "h(q, t, args)"
            )

    def _g(self, q, t, args):
        return _as_array(self.g(q, t, args), q.dtype)

    def _h(self, q, t, args):
        return _as_array(self.h(q, t, args), q.dtype)

    def velocity_form(self, q, t, args):
        jac = self._g(q, t, args)
        if self.h is None:
            a = jnp.zeros(jac.shape[0], jac.dtype)
        else:
            a = self._h(q, t, args)
        return jac, a

    def num_constraints(self, n, args, dtype=None):
        dtype = default_float_dtype() if dtype is None else dtype
        q = jax.ShapeDtypeStruct((n,), dtype)
        t = jax.ShapeDtypeStruct((), dtype)
        out = jax.eval_shape(lambda q_, t_: self._g(q_, t_, args), q, t)
        if not isinstance(out, jax.ShapeDtypeStruct) or out.ndim != 2:
            raise ValueError(
                "Pfaffian g(q, t, args) must return an array of shape (k, n), one row "
                f"per constraint; got {getattr(out, 'shape', type(out).__name__)}."
            )
        if out.shape[1] != n:
            raise ValueError(
                f"Pfaffian g(q, t, args) has {out.shape[1]} columns but there are "
                f"n = {n} coordinates: g must have shape (k, n)."
            )
        k = out.shape[0]
        if self.h is not None:
            h_out = jax.eval_shape(lambda q_, t_: self._h(q_, t_, args), q, t)
            if getattr(h_out, "shape", None) != (k,):
                raise ValueError(
                    f"Pfaffian h(q, t, args) must return shape (k,) = ({k},), got "
                    f"{getattr(h_out, 'shape', type(h_out).__name__)}."
                )
        return k


def _as_array(value, dtype):
    """A constraint's value as an array: a (nested) list or tuple of rows, as NumPy
    users write them, becomes one array of the coordinates' `dtype`."""
    if isinstance(value, (list, tuple)):
        return jnp.asarray(value, dtype=dtype)
    return value


def _check_shape(kind, signature, out, n, ndim):
    if not isinstance(out, jax.ShapeDtypeStruct) or out.ndim not in ndim:
        raise ValueError(
            f"{kind}: {signature} must return an array of shape (k,) (a scalar for a "
            f"single constraint); got {getattr(out, 'shape', type(out).__name__)}."
        )
    return 1 if out.ndim == 0 else out.shape[0]


class Coulomb(eqx.Module):
    """Coulomb friction on the tangential row of a contact: the `friction` of a
    [`constrained_jax.Unilateral`][].

    The contact sticks while the tangential multiplier stays inside the friction
    cone, `|lambda_t| <= mu_s N` (`N = sign * lambda_1 >= 0` the contact's pushing
    normal multiplier): `tangent` is then a constraint, `v_t = 0`. Where
    `|lambda_t|` reaches `mu_s N`, the contact slips: the tangential row is dropped
    and replaced by the kinetic friction force `lambda_t = -mu_k N sign(v_t)`
    (opposing the slip), with `N` the normal multiplier of the same saddle-point
    solve (the coupled system, not a lagged force). Where the slip velocity `v_t`
    comes back to zero, the contact sticks again if the sticking multipliers lie
    inside the cone there, and otherwise slips the other way.

    **Arguments:**

    - `tangent`: a `cjax.Pfaffian` or `cjax.Holonomic` with one row, whose velocity
        residual `A_t qdot + a_t` is the slip velocity `v_t` of the contact (the
        lecture's no-slip row of the two cylinders, the horizontal velocity of a
        block's contact point).
    - `mu_s`: the static coefficient, a float `>= 0` or a callable `mu_s(args)`
        (traced: differentiable and `vmap`-able).
    - `mu_k`: the kinetic coefficient, `0 <= mu_k <= mu_s`, a float or a callable
        `mu_k(args)`; default `mu_s`.

    Values out of range (a callable giving `mu_k > mu_s`, a negative or NaN
    coefficient) stop the run with `RESULTS.invalid_friction`. Friction acts
    during contact phases; the impulse of an impact is frictionless (normal rows
    only). One tangential row: planar contact.
    """

    tangent: AbstractConstraint
    mu_s: float | Callable
    mu_k: float | Callable

    def __init__(self, tangent, mu_s, mu_k=None):
        if not isinstance(tangent, (Holonomic, Pfaffian)):
            raise ValueError(
                "`cjax.Coulomb` takes the contact's tangential row as a "
                "`cjax.Pfaffian` (or `cjax.Holonomic`) with one row, its slip "
                f"velocity; got {type(tangent).__name__}."
            )
        mu_s = _parameter("mu_s", mu_s, upper=np.inf, owner="cjax.Coulomb")
        mu_k = mu_s if mu_k is None else mu_k
        # (A finite kinetic coefficient: `mu_s = inf` never slips, `mu_k = inf` would
        # be an infinite force.)
        mu_k = _parameter(
            "mu_k", mu_k, upper=float(np.finfo(float).max), owner="cjax.Coulomb"
        )
        if not callable(mu_s) and not callable(mu_k) and mu_k > mu_s:
            raise ValueError(
                f"The kinetic coefficient must not exceed the static one; got "
                f"mu_k = {mu_k!r} > mu_s = {mu_s!r}."
            )
        self.tangent = tangent
        self.mu_s = mu_s
        self.mu_k = mu_k

    def coefficients(self, args) -> tuple[Float[Array, ""], Float[Array, ""]]:
        """`(mu_s, mu_k)` (floats, or the callables at `args`)."""
        return _evaluate(self.mu_s, args), _evaluate(self.mu_k, args)


class Unilateral(AbstractConstraint):
    """Constraints that can push but not pull: they hold while the multiplier of their
    first row keeps the sign `sign`, and are released together when it crosses zero.

    A contact is the example: the two cylinders touch while the normal force
    `Q_r = lambda_1 >= 0`, and the no-slip condition ends with contact, so both rows
    go into one `Unilateral`:

    ```python
    contact = cjax.Unilateral(
        (cjax.Pfaffian(contact_row), cjax.Pfaffian(no_slip_row)),
        sign=1.0,
        gap=lambda q, t, args: q[0] - (args["R"] + args["a"]),
    )
    system = cjax.LagrangianSystem(L, constraints=contact)
    ```

    In a [`constrained_jax.LagrangianSystem`][] it acts like its member constraints
    (their rows stacked in order). [`constrained_jax.simulate`][] watches
    `sign * lambda_first_row`; when it falls through zero it ends the phase there
    (the event time found by a root find), drops all the member constraints, and
    continues with the others; with a `gap`, the free phase ends at re-contact, when
    `gap(q, t, args)` falls through zero.

    **Arguments:**

    - `constraints`: a constraint or a sequence of them (`Holonomic`, `Pfaffian`);
        the first row of the first one carries the watched multiplier.
    - `sign`: `+1.0` if the constraint can only push with a positive multiplier (in
        the convention `Q^c = A^T lambda`), `-1.0` for a negative one.
    - `gap`: `gap(q, t, args) -> scalar`, positive while separated, or `None` (the free
        phase then runs to the end). `simulate` checks the two agree at the start (the
        first row's force while it pushes opens the gap) and refuses a run where they
        do not with `RESULTS.contact_sign_mismatch`.
    - `restitution`: Newton's coefficient of restitution `e` in `[0, 1]` for contacts
        that come and go: a float, or a callable `e(args) -> scalar` (traced, so
        differentiable and `vmap`-able). `None` (default): the one release and the
        stop at re-contact described above. With a restitution (which needs a `gap`
        and `simulate(..., max_events=N)`), every re-contact is an impact: the
        velocity jumps by an impulse `M dqd = A^T Lambda` solved with the KKT matrix
        of the rows that hold, so that `A qd+ + a = -e (A qd- + a)` on this group's
        rows and `= 0` on the others; with `e = 0` the contact is re-made and the
        group is attached again (until its multiplier lets go once more).
    - `rest_speed`: the approach speed (`-d gap/dt` just before the impact) below
        which an impact is taken as inelastic (`e = 0`, resting contact): a float or
        a callable `rest_speed(args)`, default `0.0` (never). A bouncing ball with
        `e < 1` bounces infinitely often in finite time (Zeno); a positive
        `rest_speed` ends the series physically (the ball then rests on the floor)
        after about `log(rest_speed / v_1) / log(e)` bounces; without it the run
        stops with `RESULTS.max_events_reached`. (A re-contact is detected where the
        gap has fallen `delta = sqrt(eps) (1 + |q|)` below zero, and the impact acts
        where the gap closes, found back along the motion. Impact speeds below about
        `sqrt(2 g delta) / 64`, `g` the acceleration towards the contact, are not
        resolved: 1e-5 m/s for a ball under 9.81 m/s^2 in float64, 2e-3 m/s in
        float32. A `rest_speed` below that is never reached.)
    - `friction`: a [`constrained_jax.Coulomb`][] on the contact's tangential row,
        or `None` (default: no tangential row, or one held by any force as a
        member constraint). Its row is the group's last; its multiplier is the
        friction force, sticking or slipping. Stick-slip transitions are events:
        `simulate(..., max_events=N)` (with a `restitution`) runs it.
    """

    constraints: tuple[AbstractConstraint, ...]
    unilateral: ClassVar[bool] = True
    sign: float = 1.0
    gap: Callable | None = None
    restitution: float | Callable | None = None
    rest_speed: float | Callable = 0.0
    friction: Coulomb | None = None

    def __init__(
        self,
        constraints,
        sign: float = 1.0,
        gap: Callable | None = None,
        restitution: float | Callable | None = None,
        rest_speed: float | Callable = 0.0,
        friction: Coulomb | None = None,
    ):
        if isinstance(constraints, AbstractConstraint):
            constraints = (constraints,)
        if not isinstance(constraints, (tuple, list)) or not constraints:
            raise ValueError(
                "`Unilateral` groups `cjax.Holonomic` and `cjax.Pfaffian` constraints "
                f"(one, or a sequence of them); got {constraints!r}."
            )
        constraints = tuple(constraints)
        for c in constraints:
            if not isinstance(c, (Holonomic, Pfaffian)):
                raise ValueError(
                    "`Unilateral` groups `cjax.Holonomic` and `cjax.Pfaffian` "
                    f"constraints; got {type(c).__name__}."
                )
        if sign not in (1.0, -1.0):
            raise ValueError(f"`sign` must be +1.0 or -1.0, got {sign!r}.")
        if gap is not None:
            check_signature(gap, "The `gap` of `cjax.Unilateral`", "gap(q, t, args)")
        if restitution is not None:
            if gap is None:
                raise ValueError(
                    "A `restitution` needs a `gap(q, t, args)`: re-contact, where the "
                    "impact happens, is where the gap falls through zero."
                )
            restitution = _parameter("restitution", restitution, upper=1.0)
        rest_speed = _parameter("rest_speed", rest_speed, upper=np.inf)
        if friction is not None:
            if not isinstance(friction, Coulomb):
                raise ValueError(
                    "`friction` must be a `cjax.Coulomb(tangent, mu_s, mu_k)`; got "
                    f"{type(friction).__name__}."
                )
            constraints = constraints + (friction.tangent,)
        self.friction = friction
        self.constraints = constraints
        self.sign = float(sign)
        self.gap = gap
        self.restitution = restitution
        self.rest_speed = rest_speed

    def restitution_value(self, args) -> Float[Array, ""]:
        """`e`, from `restitution` (a float, or `restitution(args)`)."""
        return _evaluate(self.restitution, args)

    def rest_speed_value(self, args) -> Float[Array, ""]:
        """The rest speed, from `rest_speed` (a float, or `rest_speed(args)`)."""
        return _evaluate(self.rest_speed, args)

    def velocity_form(self, q, t, args):
        parts = [c.velocity_form(q, t, args) for c in self.constraints]
        return (
            jnp.concatenate([p[0] for p in parts]),
            jnp.concatenate([p[1] for p in parts]),
        )

    def velocity_residual(self, q, qd, t, args):
        return jnp.concatenate(
            [c.velocity_residual(q, qd, t, args) for c in self.constraints]
        )

    def jacobian_products(self, q, qd, t, args, directions):
        parts = [
            c.jacobian_products(q, qd, t, args, directions) for c in self.constraints
        ]
        return (
            jnp.concatenate([p[0] for p in parts]),
            jnp.concatenate([p[1] for p in parts]),
        )

    def acceleration_bias(self, q, qd, t, args):
        return jnp.concatenate(
            [c.acceleration_bias(q, qd, t, args) for c in self.constraints]
        )

    def position_residual(self, q, t, args):
        return jnp.concatenate(
            [c.position_residual(q, t, args) for c in self.constraints]
        )

    def holonomic_residual(self, q, t, args):
        return jnp.concatenate(
            [c.holonomic_residual(q, t, args) for c in self.constraints]
        )

    def discrete_residual(self, q0, q1, t0, h, args):
        return jnp.concatenate(
            [c.discrete_residual(q0, q1, t0, h, args) for c in self.constraints]
        )

    def num_constraints(self, n, args, dtype=None):
        return sum(c.num_constraints(n, args, dtype) for c in self.constraints)


def _parameter(name, value, upper, owner="cjax.Unilateral"):
    """A float in `[0, upper]` (checked here) or a callable of `args` (checked at run
    time, `RESULTS.invalid_restitution`, `RESULTS.invalid_friction`)."""
    if callable(value):
        check_signature(value, f"`{name}` of `{owner}`", f"{name}(args)")
        return value
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(
            f"`{name}` must be a float or a callable `{name}(args) -> scalar`; got "
            f"{value!r}."
        ) from None
    if not 0.0 <= value <= upper:  # (NaN fails too.)
        interval = "[0, 1]" if upper == 1.0 else "[0, inf)"
        raise ValueError(f"`{name}` must lie in {interval}; got {value!r}.")
    return value


def _evaluate(value, args):
    return jnp.asarray(value(args) if callable(value) else value)
