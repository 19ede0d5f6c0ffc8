r"""A constrained variational integrator: RATTLE for a general Lagrangian.

Instead of integrating the equations of motion, discretise the action. A *discrete
Lagrangian* `L_d(q_k, q_{k+1}, t_k, h)` approximates `\int_{t_k}^{t_k + h} L dt`
along the motion from `q_k` to `q_{k+1}`; here (with `v = (q_{k+1} - q_k)/h`)

- [`constrained_jax.Trapezoidal`][] (the default):
    `L_d = h/2 [L(q_k, v, t_k) + L(q_{k+1}, v, t_{k+1})]`. For a separable
    `L = qdot^T M qdot / 2 - V(q)` this is the Stoermer-Verlet method, and with
    holonomic constraints exactly SHAKE/RATTLE.
- [`constrained_jax.Midpoint`][]: `L_d = h L((q_k + q_{k+1})/2, v, t_k + h/2)`.

Stationarity of the discrete action `sum_k L_d(q_k, q_{k+1})` under variations that
respect the constraints gives the constrained discrete Euler-Lagrange equations

    D2 L_d(q_{k-1}, q_k) + D1 L_d(q_k, q_{k+1}) + h A(q_k, t_k)^T lambda_k = 0,
    G(q_{k+1}, t_{k+1}) = 0,

in the library's sign convention (`d/dt dL/dqdot - dL/dq = A^T lambda`). They are
solved in position-momentum form, splitting the impulse of constraint into two halves
as RATTLE does, so that the state `(q_k, p_k)` lies on the cotangent bundle of the
constraint manifold (`G(q_k) = 0` *and* the velocity constraint `A qdot_k + a = 0`
with `qdot_k` the velocity of momentum `p_k`). One step from `(q_k, p_k)`:

1. solve for `(q_{k+1}, nu)` (`nu = h lambda / 2`)

        p_k + D1 L_d(q_k, q_{k+1}) + A(q_k, t_k)^T nu = 0,
        G(q_{k+1}, t_{k+1}) = 0;

2. `p~ = D2 L_d(q_k, q_{k+1})`; solve for `(qdot_{k+1}, mu)` (the continuous Legendre
   transform with the velocity constraint enforced)

        dL/dqdot(q_{k+1}, qdot_{k+1}, t_{k+1}) = p~ + A(q_{k+1}, t_{k+1})^T mu,
        A(q_{k+1}, t_{k+1}) qdot_{k+1} + a(q_{k+1}, t_{k+1}) = 0,

   and `p_{k+1} = p~ + A^T mu`.

Each is a small `(n + k)`-square nonlinear system, solved by Newton's method with
autodiff Jacobians and the unrolled LU of `_solver/dense_lu.py` (LAPACK for
`n + k > 12`). For `L` quadratic in `qdot`, step 2 is linear (Newton converges in one
iteration, and a second confirms it).

**Properties.** For holonomic constraints and no forces the map
`(q_k, p_k) -> (q_{k+1}, p_{k+1})` is symplectic on the constrained cotangent bundle
and, when nothing depends on `t`, symmetric (time-reversible); it is of order 2. Hence
(backward error analysis) the energy error stays bounded, `O(h^2)`, over exponentially
long times instead of drifting, and the constraints hold to the Newton tolerance at
every step.

**Nonholonomic (Pfaffian) constraints** are handled by the discrete
Lagrange-d'Alembert principle: a Pfaffian row `g(q, t) qdot + h(q, t) = 0` is imposed in
step 1 at the midpoint, `g(q_{k+1/2}, t_{k+1/2}) (q_{k+1} - q_k)/h + h(...) = 0`, and
exactly at velocity level in step 2. The method is still second order and symmetric but
**not symplectic** (the nonholonomic flow is not), so there is no general guarantee
of bounded energy error; see McLachlan and Perlmutter, J. Nonlinear Sci. 16 (2006)
283-328, and Cortes and Martinez, Nonlinearity 14 (2001) 1365-1392.

**Forces** `Q(q, qdot, t)` enter by the discrete Lagrange-d'Alembert principle as
`f^- = f^+ = h/2 Q` evaluated by the discrete Lagrangian's own quadrature (Marsden and
West, section 3.2): the method stays second order, but a forced system is not
symplectic either.

**References:** J. E. Marsden and M. West, *Discrete mechanics and variational
integrators*, Acta Numerica 10 (2001) 357-514, sections 3.2 and 3.5; B. Leimkuhler and
S. Reich, *Simulating Hamiltonian Dynamics* (CUP 2004), chapter 7; E. Hairer, C. Lubich
and G. Wanner, *Geometric Numerical Integration* (2nd ed., Springer 2006), section VII.1
(RATTLE, Theorems 1.3 and 1.4), chapter IX (backward error analysis).
"""

import abc
import functools as ft
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
from jaxtyping import Array, Bool, Float, Int

from ._compat import buffer_at_set, while_loop
from ._implicit import nan_derivatives_if_failed
from ._kkt import kkt_solve, KKTProblem
from ._misc import (
    all_finite,
    check_consistency_tol,
    check_max_steps,
    CONSISTENCY_TOLERANCE,
    default_float_dtype,
    float_tolerance,
    full_precision,
)
from ._results import raise_if_failed, RESULTS
from ._solver.dense_lu import dense_factor, dense_solve, DenseLU
from ._solver.kkt_solver import AbstractKKTSolver
from ._system import LagrangianSystem, off_constraints


_UNROLL_MAX = 12


# ---------------------------------------------------------------- discrete Lagrangians


class AbstractDiscreteLagrangian(eqx.Module):
    """A quadrature rule `L_d(q_k, q_{k+1}, t_k, h) ~ int_{t_k}^{t_k+h} L dt`, and the
    matching discrete forces."""

    @abc.abstractmethod
    def __call__(self, lagrangian: Callable, q0, q1, t0, h, args) -> Float[Array, ""]:
        """`L_d(q0, q1, t0, h)` for the Lagrangian `L(q, qd, t, args)`."""

    @abc.abstractmethod
    def forces(
        self, forces: Callable, q0, q1, t0, h, args
    ) -> tuple[Float[Array, " n"], Float[Array, " n"]]:
        """The discrete forces `(f^-, f^+)` of `Q(q, qd, t, args)` over the step."""


class Trapezoidal(AbstractDiscreteLagrangian):
    """`L_d = h/2 [L(q_k, v, t_k) + L(q_{k+1}, v, t_k + h)]`, `v = (q_{k+1} - q_k)/h`.

    Gives Stoermer-Verlet for `L = qdot^T M qdot / 2 - V(q)`, and SHAKE/RATTLE with
    holonomic constraints (Hairer, Lubich and Wanner, GNI, section VII.1.4). The
    discrete forces are `f^- = h/2 Q(q_k, v, t_k)`, `f^+ = h/2 Q(q_{k+1}, v, t_{k+1})`.
    """

    def __call__(self, lagrangian, q0, q1, t0, h, args):
        v = (q1 - q0) / h
        return 0.5 * h * (lagrangian(q0, v, t0, args) + lagrangian(q1, v, t0 + h, args))

    def forces(self, forces, q0, q1, t0, h, args):
        v = (q1 - q0) / h
        return 0.5 * h * forces(q0, v, t0, args), 0.5 * h * forces(q1, v, t0 + h, args)


class Midpoint(AbstractDiscreteLagrangian):
    """`L_d = h L((q_k + q_{k+1})/2, (q_{k+1} - q_k)/h, t_k + h/2)`.

    For `L = qdot^T M qdot / 2 - V(q)` without constraints this is the implicit
    midpoint rule in disguise (Marsden and West, section 2.6). The discrete forces are
    `f^- = f^+ = h/2 Q(q_{k+1/2}, v, t_{k+1/2})`.
    """

    def __call__(self, lagrangian, q0, q1, t0, h, args):
        return h * lagrangian(0.5 * (q0 + q1), (q1 - q0) / h, t0 + 0.5 * h, args)

    def forces(self, forces, q0, q1, t0, h, args):
        f = 0.5 * h * forces(0.5 * (q0 + q1), (q1 - q0) / h, t0 + 0.5 * h, args)
        return f, f


# ------------------------------------------------ Newton with implicit derivatives


class _NewtonChord(AbstractKKTSolver):
    """Newton's method for the (unsymmetric) residuals of a variational step.

    Each iteration is a Newton step followed by a chord step with the same LU factors
    (one more residual evaluation and triangular solve, no new Jacobian): from an
    error `e` this reaches `O(e^3)`, and a problem affine in `z` (step 2 for `L`
    quadratic in `qdot`) is solved in one iteration. The iteration stops when the
    chord step satisfies `|dz_i| <= atol + rtol |z_i|` for every `i` (the error is then
    of the order of its square), or on a singular Jacobian / non-finite iterate
    (`RESULTS.variational_step_failed`). Run by the loop of every KKT solve, with the
    first iteration unrolled (straight-line code that XLA fuses with the rest of the
    step); derivatives by the implicit function theorem with `linear_solver`.
    """

    rtol: float
    atol: float
    linear_solver: lx.AbstractLinearSolver = DenseLU(unroll_max=_UNROLL_MAX)

    def init(self, residual, z, args):
        del residual, z, args
        return jnp.array(False), jnp.array(False)

    def step(self, residual, z, args, state):
        del state

        def value_and_value(z):
            value = residual(z, args)
            return value, value

        jac, value = jax.jacfwd(value_and_value, has_aux=True)(z)
        factors = dense_factor(jac, _UNROLL_MAX)
        z_newton = z - dense_solve(factors, value, _UNROLL_MAX)
        dz = -dense_solve(factors, residual(z_newton, args), _UNROLL_MAX)
        z_new = z_newton + dz
        scale = self.atol + self.rtol * jnp.abs(z_new)
        done = jnp.all(jnp.abs(dz) <= scale)
        failed = factors[2] | jnp.invert(jnp.all(jnp.isfinite(z_new)))
        return jnp.where(failed, z, z_new), (done, failed)

    def terminate(self, residual, z, args, state):
        del residual, z, args
        done, failed = state
        result = RESULTS.where(
            failed, RESULTS.variational_step_failed, RESULTS.successful
        )
        return done | failed, result

    def postprocess(self, residual, z, args, state):
        del residual, args, state
        return z, {}


def _root(fn, params, z0, *, rtol, atol, max_iter):
    """The root `z` of `fn(z, params)` by `_NewtonChord` from `z0`, differentiable in
    `params` by the implicit function theorem (`constrained_jax._kkt.kkt_solve`):
    `dz = -(dF/dz)^{-1} (dF/dparams . dparams)`. The system is square and
    unsymmetric, without complementarity rows; the initial guess `z0` does not affect
    the root. Returns `(z, converged, iterations)`."""
    problem = KKTProblem(fn, None, n=z0.shape[0], k=0, symmetric=False)
    solver = _NewtonChord(rtol=rtol, atol=atol)
    true = jnp.array(True)
    sol = kkt_solve(problem, solver, z0, params, max_iter, true, unrolled=1)
    return sol.z, sol.result == RESULTS.successful, sol.stats["num_steps"]


# ---------------------------------------------------------------- the two stages


def _discrete_constraints(system: LagrangianSystem, q0, q1, t0, h, args):
    """Holonomic rows `G(q1, t0 + h)`; Pfaffian rows at the midpoint,
    `g(q_m, t_m) (q1 - q0)/h + h(q_m, t_m)`."""
    parts = [c.discrete_residual(q0, q1, t0, h, args) for c in system.constraints]
    if not parts:
        return jnp.zeros((0,), q0.dtype)
    return jnp.concatenate(parts)


def _position_residual(quadrature, n, z, params):
    """Step 1: `p0 + D1 L_d(q0, q1) + f^- + A(q0)^T nu` and the discrete constraints,
    for `z = (q1, nu)`."""
    system, q0, p0, t0, h, args = params
    q1, nu = z[:n], z[n:]
    d1 = jax.grad(lambda a: quadrature(system.lagrangian, a, q1, t0, h, args))(q0)
    momentum = p0 + d1 + system.constraint_jacobian(q0, t0, args).T @ nu
    if system.forces is not None:
        momentum = momentum + quadrature.forces(system.forces, q0, q1, t0, h, args)[0]
    constraints = _discrete_constraints(system, q0, q1, t0, h, args)
    return jnp.concatenate([momentum, constraints])


def _velocity_residual(n, z, params):
    """Step 2: `dL/dqdot(q1, v1) - p~ - A(q1)^T mu` and `A(q1) v1 + a(q1)`, for
    `z = (v1, mu)`."""
    system, q1, p_tilde, t1, args = params
    v1, mu = z[:n], z[n:]
    jac = system.constraint_jacobian(q1, t1, args)
    momentum = system.momentum(q1, v1, t1, args) - p_tilde - jac.T @ mu
    return jnp.concatenate([momentum, system.velocity_residual(q1, v1, t1, args)])


# ----------------------------------------------------------------- the integrators


class VariationalState(eqx.Module):
    """The state carried from step to step: positions `q`, momenta `p`, the velocity
    `qd` of `p` (used for output and as the next initial guess), and the last scaled
    multipliers (initial guesses)."""

    q: Float[Array, " n"]
    p: Float[Array, " n"]
    qd: Float[Array, " n"]
    nu: Float[Array, " k"]


class AbstractVariationalIntegrator(eqx.Module):
    """A fixed-step integrator of a [`constrained_jax.LagrangianSystem`][] that works
    on the discrete action instead of the equations of motion.

    Pass one to `cjax.simulate(..., solver=..., dt0=h)` (a fixed step `dt0` is
    required), or call [`constrained_jax.integrate_variational`][] directly. The
    protocol is `init` (the state from `(q0, qd0)`) and `step` (one step of size `h`).
    """

    @abc.abstractmethod
    def init(self, system: LagrangianSystem, t0, q0, qd0, args) -> VariationalState:
        """The state at `t0` from positions `q0` and velocities `qd0`."""

    @abc.abstractmethod
    def step(
        self, system: LagrangianSystem, t0, h, state: VariationalState, args
    ) -> tuple[VariationalState, Bool[Array, ""], Int[Array, ""]]:
        """One step from `t0` to `t0 + h`: `(state, converged, newton_iterations)`."""


class VariationalIntegrator(AbstractVariationalIntegrator):
    """RATTLE generalised to any Lagrangian `L(q, qdot, t)`: the constrained discrete
    Euler-Lagrange equations in position-momentum form (see the module docstring for
    the equations, properties and references).

    Symplectic and, for a time-independent system, time-reversible, of order 2, with
    holonomic constraints satisfied to the Newton tolerance at every step and an
    energy error that stays bounded over long times. Pfaffian (nonholonomic)
    constraints and forces are supported, but then the method is not symplectic.

    Each step solves two `(n + k)`-square nonlinear systems by Newton's method with
    the Jacobian by autodiff. Derivatives (`jax.grad`) of a step are by the implicit
    function theorem, not through the Newton iterations.
    """

    quadrature: AbstractDiscreteLagrangian = Trapezoidal()
    newton_steps: int = 10
    rtol: float | None = None
    atol: float | None = None

    def __check_init__(self):
        if not isinstance(self.quadrature, AbstractDiscreteLagrangian):
            raise ValueError(
                "`quadrature` must be `cjax.Trapezoidal()` or `cjax.Midpoint()`, "
                f"got {type(self.quadrature).__name__}."
            )
        if (
            not isinstance(self.newton_steps, int)
            or isinstance(self.newton_steps, bool)
            or self.newton_steps < 1
        ):
            raise ValueError(
                f"`newton_steps` must be a positive int, got {self.newton_steps!r}."
            )

    def _tolerances(self, dtype) -> tuple[float, float]:
        default = float(jnp.finfo(dtype).eps) ** (2 / 3)
        rtol = default if self.rtol is None else self.rtol
        atol = default if self.atol is None else self.atol
        return rtol, atol

    def init(self, system, t0, q0, qd0, args):
        k = system.constraint_jacobian(q0, t0, args).shape[0]
        return VariationalState(
            q=q0,
            p=system.momentum(q0, qd0, t0, args),
            qd=qd0,
            nu=jnp.zeros((k,), q0.dtype),
        )

    def step(self, system, t0, h, state, args):
        rtol, atol = self._tolerances(state.q.dtype)
        n = state.q.shape[0]
        solve = ft.partial(_root, rtol=rtol, atol=atol, max_iter=self.newton_steps)
        q0, p0, t1 = state.q, state.p, t0 + h
        # Step 1: positions and the first half of the impulse of constraint.
        guess = jnp.concatenate([q0 + h * state.qd, state.nu])
        z, ok1, it1 = solve(
            ft.partial(_position_residual, self.quadrature, n),
            (system, q0, p0, t0, h, args),
            guess,
        )
        q1, nu = z[:n], z[n:]
        # Step 2: the momentum at q1, and the velocity it implies, on the velocity
        # constraint (the second half of the impulse).
        p_tilde = jax.grad(
            lambda b: self.quadrature(system.lagrangian, q0, b, t0, h, args)
        )(q1)
        if system.forces is not None:
            p_tilde = (
                p_tilde + self.quadrature.forces(system.forces, q0, q1, t0, h, args)[1]
            )
        guess = jnp.concatenate([2 * (q1 - q0) / h - state.qd, nu])
        z, ok2, it2 = solve(
            ft.partial(_velocity_residual, n), (system, q1, p_tilde, t1, args), guess
        )
        qd1, mu = z[:n], z[n:]
        p1 = p_tilde + system.constraint_jacobian(q1, t1, args).T @ mu
        new = VariationalState(q=q1, p=p1, qd=qd1, nu=mu)
        return new, ok1 & ok2, it1 + it2


VariationalIntegrator.__init__.__doc__ = """**Arguments:**

- `quadrature`: the discrete Lagrangian, [`constrained_jax.Trapezoidal`][]
    (default; RATTLE for separable Lagrangians) or [`constrained_jax.Midpoint`][].
- `newton_steps`: the most Newton iterations per nonlinear solve (two per step). A
    solve that has not converged by then fails the integration with
    `RESULTS.variational_step_failed`.
- `rtol`, `atol`: a Newton solve stops when its last step `dz` satisfies
    `|dz_i| <= atol + rtol |z_i|` for every unknown (positions and scaled
    multipliers, or velocities and multipliers). Newton converges quadratically, so
    the error after that step is of the order of its square. `None` (default) means
    `eps**(2/3)` of the dtype: 3.7e-11 in float64, 2.4e-5 in float32.
"""


# ----------------------------------------------------------------- the driver


def _num_steps(span, dt0):
    """Steps for a save interval of length `span`: the fewest with `h <= dt0`, up to a
    relative slack of `sqrt(eps)` (so that a span that is a whole number of `dt0` up to
    round-off gets exactly that number, the same in every interval)."""
    slack = jnp.sqrt(jnp.finfo(span.dtype).eps)
    count = jnp.ceil(span / dt0 - slack)
    count = jnp.where(span > 0, jnp.maximum(count, 1), 0)
    return count.astype(jnp.result_type(int))


class VariationalTrajectory(eqx.Module):
    """The result of [`constrained_jax.integrate_variational`][].

    **Attributes:**

    - `ts`: the save times, shape `(T,)`.
    - `q`, `qd`: positions and velocities at `ts`, shape `(T, n)` each; `inf` at
        save times that were not reached (after a failure).
    - `result`: a [`constrained_jax.RESULTS`][] member.
    - `stats`: `{"num_steps": ..., "num_newton_iterations": ...}`.

    [`constrained_jax.simulate`][] with `solver=cjax.VariationalIntegrator()` runs the
    same integration and returns a [`constrained_jax.Trajectory`][], with the
    multipliers, energy and constraint violation at the save times as well.
    """

    ts: Float[Array, " T"]
    q: Float[Array, "T n"]
    qd: Float[Array, "T n"]
    result: RESULTS
    stats: dict


@full_precision
def integrate_variational(
    integrator: AbstractVariationalIntegrator,
    system: LagrangianSystem,
    t0,
    t1,
    dt0,
    q0,
    qd0,
    args=None,
    *,
    ts_save,
    max_steps: int = 16384,
    consistency_tol: float | None = None,
    throw: bool = True,
) -> VariationalTrajectory:
    """Integrate with a variational integrator and save at `ts_save`.

    **Arguments:**

    - `integrator`: an [`constrained_jax.AbstractVariationalIntegrator`][], e.g.
        `cjax.VariationalIntegrator()`.
    - `system`: a [`constrained_jax.LagrangianSystem`][].
    - `t0`, `t1`: the time span (scalars, may be traced), `t0 <= t1`.
    - `dt0`: the step size `h` (a Python float or a traced scalar); required.
    - `q0`, `qd0`: the initial state, shape `(n,)`, consistent with the constraints
        (`G(q0, t0) = 0` and `A qd0 + a = 0` within `consistency_tol`, as in
        [`constrained_jax.simulate`][]; else `RESULTS.inconsistent_initial_state`
        and no step is taken: the first step would silently move the state onto the
        constraints and drop the velocity they forbid).
    - `args`: parameters passed to every user function.
    - `ts_save`: nondecreasing save times in `[t0, t1]`, shape `(T,)` with `T >= 1`
        static (values may be traced).
    - `max_steps`: a static bound on the total number of steps.
    - `consistency_tol`: the tolerance of the start's test, relative to
        `1 + max|q0|` and `1 + max|qd0|`; `None` (default) follows the dtype as in
        `simulate` (`1e-8` in float64); `float("inf")` skips the test.
    - `throw`: raise on failure if `True`; otherwise report it in `result`.

    **Returns:** a [`constrained_jax.VariationalTrajectory`][]: positions and
    velocities at `ts_save`, the `result` and the `stats` (steps, Newton iterations).

    **Save times are hit exactly.** The interval between consecutive save times
    (and from `t0` to the first) is divided into the fewest equal steps
    `h_i <= dt0` (up to a relative `sqrt(eps)`), so that step boundaries fall on the
    save times and no interpolation is needed. Every step is symplectic, so their
    composition is too. When the save times are equally spaced (and the first is `t0`
    or one spacing after it), all steps are equal up to round-off, as backward error
    analysis wants for the bounded energy error; unequal spacings give a step size that
    changes between intervals, which is still symplectic but exchanges one modified
    energy for another at each change. Choose `dt0` to divide the spacing. The
    integration ends at the last save time (there is nothing to compute after it).

    **Failures** raise with `throw=True`; with `throw=False` they are reported in
    `result`: `RESULTS.max_steps_reached` when more than `max_steps` steps would be
    needed; `RESULTS.variational_step_failed` when a Newton solve does not converge
    (the step is too large, or the constraints are dependent);
    `RESULTS.invalid_time_grid` when `dt0 <= 0` or the save times are not nondecreasing
    in `[t0, t1]`; `RESULTS.inconsistent_initial_state` for a start off the
    constraints; `RESULTS.invalid_input` for non-finite inputs. States at save
    times not reached are `inf`.

    Composes with `jax.jit` and `jax.vmap`; reverse-mode differentiable (`jax.grad`)
    with respect to `q0`, `qd0`, `args`, `t0`, `t1` and `dt0` (the outer loop is
    equinox's checkpointed while loop, as in diffrax's `RecursiveCheckpointAdjoint`;
    each Newton solve is differentiated implicitly). Forward-mode (`jax.jvp`,
    `jax.jacfwd`) is not supported, as with diffrax's default adjoint.
    """
    if not isinstance(integrator, AbstractVariationalIntegrator):
        raise ValueError(
            "`integrator` must be a `cjax.AbstractVariationalIntegrator`, e.g. "
            f"`cjax.VariationalIntegrator()`; got {type(integrator).__name__}."
        )
    if not isinstance(system, LagrangianSystem):
        raise ValueError("`system` must be a `cjax.LagrangianSystem`.")
    if dt0 is None:
        raise ValueError(
            "A variational integrator takes fixed steps: pass the step size, e.g. "
            "`simulate(..., solver=cjax.VariationalIntegrator(), dt0=0.01)`."
        )
    max_steps = check_max_steps(max_steps)
    q0 = jnp.asarray(q0)
    if not jnp.issubdtype(q0.dtype, jnp.inexact):
        q0 = q0.astype(default_float_dtype())
    dtype = q0.dtype
    qd0 = jnp.asarray(qd0, dtype)
    system.check(q0, qd0, jnp.asarray(t0, dtype), args)
    ts_save = jnp.asarray(ts_save, dtype)
    if ts_save.ndim != 1 or ts_save.shape[0] < 1:
        raise ValueError(
            "`ts_save` must be a 1-dimensional array of at least one save time, got "
            f"shape {ts_save.shape}."
        )
    t0 = jnp.asarray(t0, dtype)
    t1 = jnp.asarray(t1, dtype)
    dt0 = jnp.asarray(dt0, dtype)
    if t0.shape != () or t1.shape != () or dt0.shape != ():
        raise ValueError("`t0`, `t1` and `dt0` must be scalars.")
    if consistency_tol is None:
        consistency_tol = float_tolerance(*CONSISTENCY_TOLERANCE, dtype)
    else:
        consistency_tol = check_consistency_tol(consistency_tol)
    if isinstance(consistency_tol, (int, float)) and consistency_tol == float("inf"):
        consistent = jnp.asarray(True)  # not tested (`simulate` tests it itself)
    else:
        consistent = jnp.invert(
            off_constraints(system, q0, qd0, t0, args, consistency_tol)
        )
    sol = _integrate(
        integrator, system, t0, t1, dt0, q0, qd0, args, ts_save, max_steps, consistent
    )
    # NaN derivatives for a failed run (see `nan_derivatives_if_failed`).
    sol = nan_derivatives_if_failed(
        sol, (system, q0, qd0, args, t0, t1), sol.result != RESULTS.successful
    )
    return raise_if_failed(sol, throw)


class _Carry(eqx.Module):
    state: VariationalState
    num_steps: Int[Array, ""]  # steps taken so far
    segment: Int[Array, ""]  # the save interval the next step belongs to
    newton_iterations: Int[Array, ""]
    newton_failed: Bool[Array, ""]
    q_out: Float[Array, "T n"]
    qd_out: Float[Array, "T n"]


def _integrate(
    integrator, system, t0, t1, dt0, q0, qd0, args, ts_save, max_steps, consistent
):
    num_saves = ts_save.shape[0]
    valid_grid = (
        (dt0 > 0)
        & jnp.all(jnp.diff(ts_save) >= 0)
        & (ts_save[0] >= t0)
        & (ts_save[-1] <= t1)
        & (t1 >= t0)
    )
    finite = all_finite((q0, qd0, args, t0, t1, dt0, ts_save))
    ok_input = valid_grid & finite & consistent

    # The grid: interval i runs from starts[i] to ts_save[i] in counts[i] steps of
    # size steps[i]; it ends after ends[i] steps in all. Bad inputs take no steps.
    starts = jnp.concatenate([t0[None], ts_save[:-1]])
    spans = jnp.where(ok_input, ts_save - starts, 0.0)
    counts = _num_steps(spans, jnp.where(ok_input, dt0, 1.0))
    sizes = spans / jnp.maximum(counts, 1).astype(spans.dtype)
    ends = jnp.cumsum(counts)
    total_steps = ends[-1]
    # Zero-length intervals (a save time equal to the previous one, or to t0) take
    # their state from the last nonempty interval before them (-1: the initial state).
    index = jnp.arange(num_saves)
    source = jax.lax.cummax(jnp.where(counts > 0, index, -1), axis=0)
    # The first nonempty interval at or after each one.
    next_nonempty = jnp.flip(
        jax.lax.cummin(jnp.flip(jnp.where(counts > 0, index, num_saves)), axis=0)
    )

    int_dtype = counts.dtype
    carry0 = _Carry(
        state=integrator.init(system, t0, q0, qd0, args),
        num_steps=jnp.array(0, int_dtype),
        segment=next_nonempty[0],
        newton_iterations=jnp.array(0, int_dtype),
        newton_failed=jnp.array(False),
        q_out=jnp.full((num_saves, q0.shape[0]), jnp.inf, q0.dtype),
        qd_out=jnp.full((num_saves, q0.shape[0]), jnp.inf, q0.dtype),
    )

    def cond(c):
        return (
            (c.num_steps < total_steps)
            & (c.num_steps < max_steps)
            & jnp.invert(c.newton_failed)
        )

    def body(c):
        seg = jnp.minimum(c.segment, num_saves - 1)
        h = sizes[seg]
        before = (ends[seg] - counts[seg]).astype(int_dtype)
        t_k = starts[seg] + (c.num_steps - before).astype(h.dtype) * h
        state, ok, iterations = integrator.step(system, t_k, h, c.state, args)
        num_steps = c.num_steps + 1
        at_save = num_steps == ends[seg]
        q_out = buffer_at_set(c.q_out, seg, state.q, pred=at_save)
        qd_out = buffer_at_set(c.qd_out, seg, state.qd, pred=at_save)
        next_seg = next_nonempty[jnp.minimum(seg + 1, num_saves - 1)]
        next_seg = jnp.where(seg + 1 < num_saves, next_seg, num_saves)
        return _Carry(
            state=state,
            num_steps=num_steps,
            segment=jnp.where(at_save, next_seg, c.segment),
            newton_iterations=c.newton_iterations + iterations.astype(int_dtype),
            newton_failed=c.newton_failed | jnp.invert(ok),
            q_out=q_out,
            qd_out=qd_out,
        )

    final = while_loop(
        cond,
        body,
        carry0,
        max_steps=max_steps,
        buffers=lambda c: (c.q_out, c.qd_out),
        kind="checkpointed",
    )
    # Fill the zero-length intervals.
    q_all = jnp.concatenate([final.q_out, q0[None]])
    qd_all = jnp.concatenate([final.qd_out, qd0[None]])
    q_saved, qd_saved = q_all[source], qd_all[source]

    result = RESULTS.where(
        final.newton_failed, RESULTS.variational_step_failed, RESULTS.successful
    )
    result = RESULTS.where(total_steps > max_steps, RESULTS.max_steps_reached, result)
    result = RESULTS.where(valid_grid, result, RESULTS.invalid_time_grid)
    result = RESULTS.where(consistent, result, RESULTS.inconsistent_initial_state)
    result = RESULTS.where(finite, result, RESULTS.invalid_input)
    stats = {
        "num_steps": final.num_steps,
        "num_newton_iterations": final.newton_iterations,
    }
    return VariationalTrajectory(
        ts=ts_save, q=q_saved, qd=qd_saved, result=result, stats=stats
    )
