"""Inverse problems: physical parameters recovered from noisy observations.

Three problems, each with synthetic data (the scene's closed form plus Gaussian noise
of known standard deviation `sigma`), a model that computes the observations with the
library, and the least-squares loss for [`constrained_jax.fit`][],

    loss(p) = chi^2(p) / 2 = sum_i ((model_i(p) - data_i) / sigma)^2 / 2,

whose minimum is the maximum-likelihood estimate of `p`. The models differentiate
through the library's solvers: through a release event, through the implicit
function theorem on a KKT system, through an ODE solve.

1. **The rolling cylinder's inertia ratio** `alpha = I / (M a^2)` from the angles at
   which it leaves the fixed cylinder, released from rest at several `theta0`
   (closed form `theta* = arccos(2 cos theta0 / (3 + alpha))`, see
   `two_cylinders`). The model simulates the unilateral contact
   (`two_cylinders.contact_system()`) until the normal force falls through zero and
   reads the angle where it let go: the derivative `d theta*/d alpha` flows through
   the event's root find.
2. **A hanging chain's length** `C` **and the height** `yR` **of its right end**, from
   noisy heights `y(x_i)` of points on it (ends at `(0, 0)` and `(1, yR)`). The model
   hangs the chain with [`constrained_jax.solve_functional`][] (the catenary
   functional with its length constraint, Chebyshev nodes) and evaluates the
   solution at the observation points; derivatives with respect to `C` (a constraint
   value) and `yR` (a boundary value) come from the implicit function theorem on the
   discrete KKT system.
3. **A pendulum's length** `l` from noisy positions `(x, y)` of the bob at known times,
   released from rest at a known angle `theta0`. The model simulates the Cartesian
   pendulum with its rod constraint (`pendulum.system()`); `l` enters the
   constraint, the initial state and, through them, the period.

The models are written for forward-mode differentiation (`cjax.fit(...,
jac="fwd")`): one or two parameters, each behind a long computation, which forward
mode differentiates with one tangent per parameter and compiles in about half the
time of reverse mode. The simulations use `adjoint=diffrax.ForwardMode()` for that
reason (diffrax's default adjoint is reverse-mode only).
"""

import diffrax
import jax
import jax.numpy as jnp

from .._discretization import Chebyshev
from .._functional import solve_functional
from .._misc import float_tolerance
from .._results import RESULTS
from .._simulate import SaveAt, simulate
from . import catenary, pendulum, two_cylinders


# -- 1. The rolling cylinder: alpha from detachment angles -------------------------

DETACHMENT_HORIZON = 2.0
"""The simulated time span: longer than the time to detach from `theta0 >= 0.2` for
every `alpha <= 2` with the default sizes (at most 1.6)."""

_DETACHMENT_CONTROLLER = diffrax.PIDController(rtol=1e-6, atol=1e-6)
_T1_ONLY = SaveAt(t1=True, multipliers=False, energy=False, violation=False)


def detachment_angle(alpha, theta0, scene) -> jax.Array:
    """The angle `theta1` at which the rolling cylinder leaves the fixed one, released
    from rest at `theta0`, by simulation (`two_cylinders.contact_system()` with its
    release event; tolerances `1e-6`, so the angle is good to a few `1e-7`).

    `scene`: the other sizes, `{"M", "a", "R", "g"}` (see `two_cylinders`). Scalar
    `alpha` and `theta0`; forward-mode differentiable.
    """
    args = {**scene, "I": alpha * scene["M"] * scene["a"] ** 2}
    q0, qd0 = two_cylinders.state(theta0, jnp.zeros_like(theta0), args)
    traj = simulate(
        two_cylinders.contact_system(),
        (0.0, DETACHMENT_HORIZON),
        q0,
        qd0,
        args,
        stepsize_controller=_DETACHMENT_CONTROLLER,
        saveat=_T1_ONLY,
        adjoint=diffrax.ForwardMode(),
        max_steps=1024,
        throw=False,
    )
    # A failed simulation, or no release within the horizon, has no detachment
    # angle: NaN, which `fit` reports (RESULTS.nonfinite) instead of fitting to it.
    ok = (traj.result == RESULTS.successful) & traj.release.released
    return jnp.where(ok, traj.release.q[1], jnp.nan)


def detachment_residuals(params, data) -> jax.Array:
    """`(theta*_sim(alpha, theta0_i) - observed_i) / sigma`; `params = {"alpha"}`.

    The release angles are simulated one after the other (`jax.lax.map`): a batch
    (`jax.vmap`) of event-driven simulations compiles more slowly for a small gain."""
    angles = jax.lax.map(
        lambda theta0: detachment_angle(params["alpha"], theta0, data["scene"]),
        data["theta0"],
    )
    return (angles - data["angle"]) / data["sigma"]


def detachment_loss(params, data) -> jax.Array:
    """`chi^2 / 2` of the detachment angles."""
    return 0.5 * jnp.sum(detachment_residuals(params, data) ** 2)


def detachment_data(key, alpha, theta0, sigma, **sizes) -> dict:
    """Synthetic observations: the closed-form detachment angles at `theta0` plus
    Gaussian noise of standard deviation `sigma`. `sizes`: `M`, `a`, `R`, `g` as in
    `two_cylinders.default_args`."""
    theta0 = jnp.asarray(theta0, float)
    args = two_cylinders.default_args(alpha=alpha, **sizes)
    exact = two_cylinders.detachment_angle(theta0, args)
    noise = sigma * jax.random.normal(key, theta0.shape, exact.dtype)
    scene = {k: args[k] for k in ("M", "a", "R", "g")}
    return {
        "theta0": theta0,
        "angle": exact + noise,
        "sigma": jnp.asarray(sigma, float),
        "scene": scene,
    }


# -- 2. The hanging chain: length and right-end height from points on it -----------

CATENARY_NODES = 24
"""Chebyshev nodes of the chain's shape (error ~1e-11 for moderate sags)."""


def chain_heights(params, x) -> jax.Array:
    """The heights `y(x)` of the chain of length `params["length"]` hanging between
    `(0, 0)` and `(1, params["yr"])`, by `solve_functional` (started from
    `catenary.initial_guess`). Differentiable in both parameters (implicit function
    theorem), forward and reverse mode."""
    length, yr = params["length"], params["yr"]
    zero, one = jnp.zeros_like(yr), jnp.ones_like(yr)
    sol = solve_functional(
        catenary.functional(zero, zero, one, yr),
        {"rho_g": one, "length": length},
        discretization=Chebyshev(CATENARY_NODES),
        y0=catenary.initial_guess(zero, zero, one, yr, length),
        throw=False,
    )
    # A failed solve (e.g. a length shorter than the chord) has no shape: NaN.
    return jnp.where(sol.result == RESULTS.successful, sol(x), jnp.nan)


def chain_residuals(params, data) -> jax.Array:
    """`(y(x_i) - observed_i) / sigma`; `params = {"length", "yr"}`."""
    return (chain_heights(params, data["x"]) - data["y"]) / data["sigma"]


def chain_loss(params, data) -> jax.Array:
    """`chi^2 / 2` of the chain's heights."""
    return 0.5 * jnp.sum(chain_residuals(params, data) ** 2)


def chain_data(key, length, yr, x, sigma) -> dict:
    """Synthetic observations: the closed-form catenary (`catenary.closed_form`)
    at the points `x` plus Gaussian noise of standard deviation `sigma`."""
    x = jnp.asarray(x, float)
    exact = catenary.closed_form(0.0, 0.0, 1.0, yr, length)["y"](x)
    noise = sigma * jax.random.normal(key, x.shape, x.dtype)
    return {"x": x, "y": jnp.asarray(exact) + noise, "sigma": jnp.asarray(sigma, float)}


# -- 3. The pendulum: length from a noisy trajectory -------------------------------


def _pendulum_controller(dtype) -> diffrax.PIDController:
    """`rtol = atol = 1e-8`, raised to `100 eps` in float32 (where 1e-8 cannot be
    met)."""
    tol = float_tolerance(1e-8, 100.0, dtype)
    return diffrax.PIDController(rtol=tol, atol=tol)


def bob_positions(params, data) -> jax.Array:
    """The bob's positions `(x, y)` at the times `data["ts"]`, shape `(T, 2)`, by
    simulating `pendulum.system()` with length `params["l"]` from rest at
    `data["theta0"]` (gravity `data["g"]`, mass 1)."""
    args = {"m": jnp.ones_like(params["l"]), "g": data["g"], "l": params["l"]}
    theta0 = data["theta0"]
    q0, qd0 = pendulum.state(theta0, jnp.zeros_like(theta0), args)
    traj = simulate(
        pendulum.system(),
        (0.0, data["ts"][-1]),
        q0,
        qd0,
        args,
        stepsize_controller=_pendulum_controller(q0.dtype),
        saveat=SaveAt(ts=data["ts"], multipliers=False, energy=False, violation=False),
        adjoint=diffrax.ForwardMode(),
        max_steps=4096,
        throw=False,
    )
    return jnp.where(traj.result == RESULTS.successful, traj.q, jnp.nan)


def bob_residuals(params, data) -> jax.Array:
    """`((x, y)(t_i) - observed_i) / sigma`, flattened; `params = {"l"}`."""
    return jnp.ravel((bob_positions(params, data) - data["q"]) / data["sigma"])


def bob_loss(params, data) -> jax.Array:
    """`chi^2 / 2` of the bob's positions."""
    return 0.5 * jnp.sum(bob_residuals(params, data) ** 2)


def pendulum_angle(t, l, theta0, g):
    """The exact angle from rest at `theta0`: `sin(theta/2) = k sn(K(k) - omega t, k)`
    with `k = sin(theta0/2)`, `omega = sqrt(g/l)` (Jacobi's elliptic `sn`, by the
    descending Landen / AGM transformation; NumPy-free, traceable)."""
    t = jnp.asarray(t, float)
    k = jnp.sin(jnp.asarray(theta0, float) / 2)
    m = k**2
    u = _complete_k(m) - jnp.sqrt(g / l) * t
    return 2 * jnp.arcsin(k * _jacobi_sn(u, m))


def _complete_k(m, iterations: int = 30):
    a, b = jnp.ones_like(m), jnp.sqrt(1 - m)
    for _ in range(iterations):
        a, b = (a + b) / 2, jnp.sqrt(a * b)
    return jnp.pi / (2 * a)


def _jacobi_sn(u, m, iterations: int = 12):
    """`sn(u | m)` by the arithmetic-geometric mean (Abramowitz & Stegun 16.4)."""
    a, b = jnp.ones_like(m), jnp.sqrt(1 - m)
    cs = []
    for _ in range(iterations):
        c = (a - b) / 2
        a, b = (a + b) / 2, jnp.sqrt(a * b)
        cs.append(c / a)
    phi = 2**iterations * a * u
    for c_over_a in reversed(cs):
        phi = (phi + jnp.arcsin(c_over_a * jnp.sin(phi))) / 2
    return jnp.sin(phi)


def pendulum_data(key, l, theta0, ts, sigma, g=9.81) -> dict:
    """Synthetic observations: the exact positions `(l sin theta, -l cos theta)` at
    the times `ts` (from `pendulum_angle`) plus Gaussian noise of standard deviation
    `sigma` in each coordinate."""
    ts = jnp.asarray(ts, float)
    theta = pendulum_angle(ts, l, theta0, g)
    exact = l * jnp.stack([jnp.sin(theta), -jnp.cos(theta)], axis=-1)
    noise = sigma * jax.random.normal(key, exact.shape, exact.dtype)
    return {
        "ts": ts,
        "q": exact + noise,
        "sigma": jnp.asarray(sigma, float),
        "theta0": jnp.asarray(theta0, float),
        "g": jnp.asarray(g, float),
    }
