"""Command line: `python -m constrained_jax` (also the `constrained-jax` script).

- `tour`: solve every built-in scene on its default parameters, print one table
  (scene, quantity, computed, closed form, relative error, tolerance, time), write the
  pictures into `--out` (default `./constrained_jax_tour/`) and a work-precision
  diagram of the pendulum. Exit status 1 if any check fails.
- `scene NAME [--param value ...]`: run one scene (and draw its picture, if it has
  one); `scene NAME --help` lists its parameters with their defaults.
- `list`: the scenes and their parameters.

Every check compares a computed number with the scene's closed form. The relative
error is `|computed - closed form| / |closed form|`, or, for a quantity whose closed
form is zero, divided by the scale named in the row (`/l`: a length, `/sqrt(gl)`: a
speed). Each row states its tolerance, chosen from the accuracy the method promises
(the integrator's tolerance, spectral accuracy), not from the result.

Times are wall clock: `time` is the median of a few runs of the compiled solve. The
tour first compiles every program (`--jobs` at a time, in threads: XLA compiles
without holding Python's lock), then runs them one by one; the first call of each
program (tracing, compilation and one run) is listed below the table. Compilation
dominates the tour's run time (seconds per program; the solves take milliseconds).

Pictures need matplotlib (`pip install "constrained_jax[plot]"`); without it the
checks still run, and the pictures are skipped with a message saying so.
"""

import argparse
import importlib.util
import math
import statistics
import sys
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any


_DEFAULT_OUT = "constrained_jax_tour"


@dataclass(frozen=True)
class _Row:
    scene: str
    quantity: str
    computed: float
    reference: float
    tolerance: float
    seconds: float
    scale: float | None = None  # for a closed form that vanishes

    @property
    def rel_error(self) -> float:
        scale = abs(self.reference) if self.scale is None else self.scale
        return abs(self.computed - self.reference) / max(scale, 1e-300)

    @property
    def passed(self) -> bool:
        # A NaN compares False: it never passes.
        return self.rel_error <= self.tolerance


@dataclass
class _Job:
    """One compiled solve and what to do with its output.

    `program` names the compiled function (jobs may share one: different inputs,
    traced, do not recompile); `finish(out, seconds)` returns the rows and the
    pictures (file name -> a function drawing on a `matplotlib.figure.Figure`).
    """

    label: str
    program: str
    inputs: tuple
    finish: Callable[[Any, float], tuple[list[_Row], dict[str, Callable]]]
    repeats: int = 3
    draw: bool = True  # keep its pictures


def _check(quantity, computed, reference, tolerance, scale=None):
    return quantity, computed, reference, tolerance, scale


def _rows(label: str, seconds: float, checks) -> list[_Row]:
    return [
        _Row(label, q, float(c), float(r), tol, seconds, scale)
        for q, c, r, tol, scale in checks
    ]


def _label(name: str, params: dict) -> str:
    defaults = {k: d for k, (d, _) in _SCENES[name].params.items()}
    changed = {k: v for k, v in params.items() if v != defaults[k]}
    if not changed:
        return name
    return f"{name}({', '.join(f'{k}={v:g}' for k, v in changed.items())})"


def _warn_failure(result, label: str) -> None:
    """A solver failure shows up in the checks (as a wrong number or NaN); say what
    the solver reported, too."""
    import constrained_jax as cjax

    if result != cjax.RESULTS.successful:
        print(f"warning: {label}: {cjax.RESULTS[result]}", file=sys.stderr)


def _arrays(*values):
    import jax.numpy as jnp

    return tuple(jnp.asarray(v, float) for v in values)


# ---------------------------------------------------------------------------------
# The compiled programs, built once per process (module-level cache): a second run
# with other parameters (traced) does not recompile.
# ---------------------------------------------------------------------------------


def _program_cylinder():
    from .scenes import cylinder_volume

    return lambda b, l: cylinder_volume.solve(b, l, throw=False)


def _pendulum_program(solver):
    """The Cartesian pendulum released from rest at `theta0`, over `periods` periods
    `T` (closed form), saved at `T/4, T/2` and the end; `rtol` (diffrax solvers) or
    `dt0` (the variational integrator) traced."""

    def run(theta0, periods, args, rtol, dt0):
        import diffrax
        import jax.numpy as jnp

        import constrained_jax as cjax
        from constrained_jax.scenes import pendulum

        q0, qd0 = pendulum.state(theta0, jnp.zeros_like(theta0), args)
        period = pendulum.period(theta0, args)
        variational = isinstance(solver, cjax.VariationalIntegrator)
        t1 = periods * period
        return cjax.simulate(
            pendulum.system(),
            (0.0, t1),
            q0,
            qd0,
            args,
            solver=solver,
            dt0=dt0 if variational else None,
            stepsize_controller=diffrax.PIDController(rtol=rtol, atol=rtol),
            saveat=cjax.SaveAt(
                ts=jnp.stack([period / 4, period / 2, t1]),
                energy=False,
                violation=False,
            ),
            max_steps=1 << 16,
            throw=False,
        )

    return run


def _program_two_cylinders():
    def run(theta0, args):
        import diffrax
        import jax.numpy as jnp

        import constrained_jax as cjax
        from constrained_jax.scenes import two_cylinders

        q0, qd0 = two_cylinders.state(theta0, jnp.zeros_like(theta0), args)
        t_star = two_cylinders.detachment_time(theta0, args)
        ts = t_star * jnp.linspace(0.0, 1.2, 121)  # ts[50] = t*/2
        return cjax.simulate(
            two_cylinders.contact_system(),
            (0.0, ts[-1]),
            q0,
            qd0,
            args,
            stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-10),
            saveat=cjax.SaveAt(ts=ts, energy=False, violation=False),
            throw=False,
        )

    return run


def _program_rolling_disk():
    def run(theta0, nu, omega, t1, args):
        import diffrax

        import constrained_jax as cjax
        from constrained_jax.scenes import rolling_disk

        q0, qd0 = rolling_disk.initial_state(theta0, nu, omega, args)
        return cjax.simulate(
            rolling_disk.system(),
            (0.0, t1),
            q0,
            qd0,
            args,
            stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-10),
            saveat=cjax.SaveAt(t1=True, violation=False),
            throw=False,
        )

    return run


def _program_rotating_hoop():
    def run(theta0, t1, args):
        import diffrax
        import jax
        import jax.numpy as jnp

        import constrained_jax as cjax
        from constrained_jax.scenes import rotating_hoop

        zero = jnp.zeros_like(theta0)
        q0, qd0 = rotating_hoop.state(theta0, zero, zero, args)
        traj = cjax.simulate(
            rotating_hoop.system(),
            (0.0, t1),
            q0,
            qd0,
            args,
            stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-10),
            saveat=cjax.SaveAt(t1=True, multipliers=False, violation=False),
            throw=False,
        )
        # The angle on the hoop and its rate, d/dt angle(q(t), t).
        angle, rate = jax.jvp(
            lambda q, t: rotating_hoop.angle(q, t, args),
            (traj.q[-1], t1),
            (traj.qd[-1], jnp.ones_like(t1)),
        )
        return traj.result, angle, rate

    return run


def _program_catenary():
    """Chebyshev(48) from `solve_functional`'s default start (the scene's `solve`),
    deep sags included."""
    from .scenes import catenary

    return lambda *values: catenary.solve(*values, throw=False)


def _program_dido():
    from .scenes import dido

    return lambda a, length: dido.solve(a, length, throw=False)


def _program_sphere_geodesic():
    from .scenes import sphere_geodesic

    return lambda start, end, radius: sphere_geodesic.solve(
        start, end, radius, throw=False
    )


def _make_program(name: str) -> Callable:
    import diffrax

    import constrained_jax as cjax

    makers = {
        "cylinder_volume": _program_cylinder,
        "pendulum Tsit5": lambda: _pendulum_program(diffrax.Tsit5()),
        "pendulum Dopri8": lambda: _pendulum_program(diffrax.Dopri8()),
        "pendulum variational": lambda: _pendulum_program(cjax.VariationalIntegrator()),
        "two_cylinders": _program_two_cylinders,
        "rolling_disk": _program_rolling_disk,
        "rotating_hoop": _program_rotating_hoop,
        "catenary": _program_catenary,
        "dido": _program_dido,
        "sphere_geodesic": _program_sphere_geodesic,
    }
    return makers[name]()


_PROGRAMS: dict[str, Callable] = {}


def _program(name: str) -> Callable:
    if name not in _PROGRAMS:
        import equinox as eqx

        _PROGRAMS[name] = eqx.filter_jit(_make_program(name))
    return _PROGRAMS[name]


# ---------------------------------------------------------------------------------
# The scenes: each `_NAME(**params) -> list[_Job]`.
# ---------------------------------------------------------------------------------


def _cylinder_volume(b: float = 1.0, l: float = 1.0) -> list[_Job]:
    from .scenes import cylinder_volume as scene

    label = _label("cylinder_volume", {"b": b, "l": l})
    if not (b > 0 and l > 0):
        raise SystemExit(f"{label}: needs b > 0 and l > 0.")

    def finish(sol, seconds):
        _warn_failure(sol.result, label)
        ref = scene.closed_form(b, l)
        # Newton on the KKT system to rtol = atol = 1e-10 (relative to the scale).
        rows = _rows(
            label,
            seconds,
            [
                _check("radius a", sol.x[0], ref["a"], 1e-10),
                _check("height h", sol.x[1], ref["h"], 1e-10),
                _check(
                    "multiplier lambda", sol.multipliers[0], ref["multiplier"], 1e-10
                ),
                _check("volume V*", sol.value, ref["volume"], 1e-10),
            ],
        )

        def draw(fig):
            import jax.numpy as jnp

            from . import plot

            ax = fig.subplots()
            args = {"b": jnp.asarray(b, float), "l": jnp.asarray(l, float)}
            a, h = (float(v) for v in sol.x)
            plot.extremum_2d(
                scene.volume,
                scene.constraint,
                sol,
                args,
                span=(0.8 * a, 0.8 * h),
                levels=12,
                ax=ax,
            )
            ax.set_xlabel("radius a")
            ax.set_ylabel("height h")
            ax.set_title(
                f"the largest cylinder V = pi a^2 h on 2 pi a + h^2/b = l (b={b:g}, "
                f"l={l:g}):\nat the extremum grad V = -lambda grad G",
                fontsize="medium",
            )

        return rows, {"cylinder_extremum.png": draw}

    return [_Job(label, "cylinder_volume", _arrays(b, l), finish)]


def _pendulum(
    theta0: float = 1.0,
    periods: float = 1.0,
    m: float = 1.0,
    g: float = 9.81,
    l: float = 1.0,
) -> list[_Job]:
    import jax.numpy as jnp

    from .scenes import pendulum

    params = {"theta0": theta0, "periods": periods, "m": m, "g": g, "l": l}
    label = _label("pendulum", params)
    if not (0 < abs(theta0) < math.pi and m > 0 and g > 0 and l > 0):
        raise SystemExit(f"{label}: needs 0 < |theta0| < pi and m, g, l > 0.")
    if not (periods >= 1 and periods == int(periods)):
        raise SystemExit(f"{label}: `periods` must be a whole number >= 1.")
    args = pendulum.default_args(m=m, g=g, l=l)

    def finish(traj, seconds):
        _warn_failure(traj.result, label)
        speed = math.sqrt(2 * g * l * (1 - math.cos(theta0)))
        bottom, half, end = 0, 1, 2
        # Tsit5 at rtol = atol = 1e-10 over one period: global error ~1e-9 per
        # period (it grows linearly with the number of periods).
        n = f"{periods:g}T" if periods != 1 else "T"
        tol = 1e-7 * periods
        rows = _rows(
            label,
            seconds,
            [
                _check(
                    "tension at T/4",
                    -traj.multipliers[bottom, 0],
                    m * g * (3 - 2 * math.cos(theta0)),
                    1e-7,
                ),
                _check("x at T/4 (/l)", traj.q[bottom, 0], 0.0, 1e-7, l),
                _check("speed at T/4", jnp.linalg.norm(traj.qd[bottom]), speed, 1e-7),
                _check("x at T/2", traj.q[half, 0], -l * math.sin(theta0), 1e-7),
                _check(f"x at {n}", traj.q[end, 0], l * math.sin(theta0), tol),
                _check(
                    f"xdot at {n} (/sqrt(gl))",
                    traj.qd[end, 0],
                    0.0,
                    tol,
                    math.sqrt(g * l),
                ),
            ],
        )
        return rows, {}

    inputs = (*_arrays(theta0, periods), args, *_arrays(1e-10, 0.0))
    return [_Job(label, "pendulum Tsit5", inputs, finish)]


def _two_cylinders(
    theta0: float = 0.2,
    alpha: float = 0.5,
    M: float = 1.0,
    a: float = 0.3,
    R: float = 1.0,
    g: float = 9.81,
) -> list[_Job]:
    import jax.numpy as jnp

    from .scenes import two_cylinders as scene

    params = {"theta0": theta0, "alpha": alpha, "M": M, "a": a, "R": R, "g": g}
    label = _label("two_cylinders", params)
    if not (0 < theta0 < math.pi / 2 and alpha > 0 and M > 0 and a > 0 and R > 0):
        raise SystemExit(
            f"{label}: needs 0 < theta0 < pi/2 (at theta0 = 0 it balances on top "
            "forever), alpha > 0 (alpha = 0 leaves the spin of the free cylinder "
            "undetermined after detachment) and M, a, R > 0."
        )
    args = scene.default_args(M=M, alpha=alpha, a=a, R=R, g=g)

    def finish(traj, seconds):
        _warn_failure(traj.result, label)
        rel = traj.release
        angle = float(scene.detachment_angle(theta0, args))
        half = 50  # t*/2, attached
        theta_half = traj.q[half, 1]
        # Tsit5 at 1e-10; the release found by a root find on the multiplier.
        rows = _rows(
            label,
            seconds,
            [
                _check("detachment angle", rel.q[1], angle, 1e-8),
                _check(
                    "detachment time",
                    rel.time,
                    scene.detachment_time(jnp.asarray(theta0), args),
                    1e-8,
                ),
                _check(
                    "rate at detachment",
                    rel.qd[1],
                    jnp.sqrt(scene.angular_velocity_squared(angle, theta0, args)),
                    1e-8,
                ),
                _check(
                    "normal force at t*/2",
                    traj.multipliers[half, 0],
                    scene.normal_force(theta_half, theta0, args),
                    1e-8,
                ),
                _check(
                    "no-slip lambda2 at t*/2",
                    traj.multipliers[half, 1],
                    scene.no_slip_multiplier(theta_half, args),
                    1e-8,
                ),
            ],
        )

        def draw(fig):
            import numpy as np

            from . import plot

            ax = fig.subplots()
            plot.multipliers(
                traj,
                against=lambda q, qd, t: q[1],
                against_label="angle of the line of centres theta1 [rad]",
                labels=["normal force $Q_r = \\lambda_1$", "no slip $\\lambda_2$"],
                ax=ax,
            )
            th = np.linspace(theta0, angle, 200)
            ax.plot(
                th,
                scene.normal_force(th, theta0, args),
                "k--",
                lw=1,
                label="closed form",
            )
            ax.plot(th, scene.no_slip_multiplier(th, args), "k--", lw=1)
            ax.plot(
                [angle],
                [0.0],
                marker="x",
                markersize=10,
                color="C3",
                linestyle="none",
                label=f"closed form theta* = {angle:.6g}",
            )
            ax.legend(fontsize="small")
            ax.set_title(
                "two cylinders: the rolling one leaves where the normal force "
                f"vanishes\n(released from rest at theta0 = {theta0:g}, alpha = "
                f"{alpha:g})",
                fontsize="medium",
            )

        return rows, {"two_cylinders_normal_force.png": draw}

    return [_Job(label, "two_cylinders", (*_arrays(theta0), args), finish)]


def _rolling_disk(
    theta0: float = 0.3,
    nu: float = 2.0,
    omega: float = 0.7,
    t1: float = 6.0,
    m: float = 1.0,
    R: float = 0.5,
    I_roll: float = 0.125,
    I_turn: float = 0.0625,
) -> list[_Job]:
    import jax.numpy as jnp

    from .scenes import rolling_disk as scene

    params = {"theta0": theta0, "nu": nu, "omega": omega, "t1": t1, "m": m, "R": R}
    params |= {"I_roll": I_roll, "I_turn": I_turn}
    label = _label("rolling_disk", params)
    if not (omega != 0 and t1 > 0 and m > 0 and R > 0 and I_roll > 0 and I_turn > 0):
        raise SystemExit(
            f"{label}: needs omega != 0 (the closed form is a circle of radius "
            "R nu / omega), t1 > 0 and positive m, R, I_roll, I_turn."
        )
    args = scene.default_args(m=m, R=R, I_roll=I_roll, I_turn=I_turn)

    def finish(traj, seconds):
        _warn_failure(traj.result, label)
        q_ref, lam_ref = scene.closed_form(jnp.asarray(t1), theta0, nu, omega, args)
        energy = 0.5 * ((m * R**2 + I_roll) * nu**2 + I_turn * omega**2)
        radius = abs(R * nu / omega)
        rows = _rows(
            label,
            seconds,
            [
                _check("x(t1) (/radius)", traj.q[-1, 0], q_ref[0], 1e-7, radius),
                _check("y(t1) (/radius)", traj.q[-1, 1], q_ref[1], 1e-7, radius),
                _check(
                    "|lambda| centripetal",
                    jnp.linalg.norm(traj.multipliers[-1]),
                    jnp.linalg.norm(lam_ref),
                    1e-7,
                ),
                _check("energy(t1)", traj.energy[-1], energy, 1e-8),
            ],
        )
        return rows, {}

    inputs = (*_arrays(theta0, nu, omega, t1), args)
    return [_Job(label, "rolling_disk", inputs, finish)]


def _rotating_hoop(
    theta0: float = 0.4,
    t1: float = 3.0,
    omega: float = 6.0,
    rho: float = 0.5,
    m: float = 1.0,
    g: float = 9.81,
) -> list[_Job]:
    from .scenes import rotating_hoop as scene

    params = {"theta0": theta0, "t1": t1, "omega": omega, "rho": rho, "m": m, "g": g}
    label = _label("rotating_hoop", params)
    if not (rho > 0 and m > 0 and g > 0 and t1 > 0 and g < rho * omega**2):
        raise SystemExit(
            f"{label}: needs omega^2 > g/rho (for the relative equilibrium "
            "cos(theta*) = g/(rho omega^2) off the bottom), t1 > 0 and positive rho, "
            "m, g."
        )
    args = scene.default_args(m=m, rho=rho, omega=omega, g=g)
    theta_star = math.acos(g / (rho * omega**2))

    def finish_oscillation(out, seconds):
        result, angle, rate = out
        _warn_failure(result, label)
        # Tsit5 at 1e-10, no stabilization: the invariant to ~1e-9.
        h0 = scene.jacobi_integral(theta0, 0.0, args)
        h1 = scene.jacobi_integral(angle, rate, args)
        return _rows(
            label, seconds, [_check("Jacobi integral h(t1)", h1, h0, 1e-8)]
        ), {}

    def finish_equilibrium(out, seconds):
        result, angle, _ = out
        _warn_failure(result, label)
        check = _check("theta(t1) from theta*", angle, theta_star, 1e-8)
        return _rows(label, seconds, [check]), {}

    return [
        _Job(label, "rotating_hoop", (*_arrays(theta0, t1), args), finish_oscillation),
        _Job(
            label, "rotating_hoop", (*_arrays(theta_star, t1), args), finish_equilibrium
        ),
    ]


def _catenary(
    length: float = 1.5,
    xl: float = 0.0,
    yl: float = 0.0,
    xr: float = 1.0,
    yr: float = 0.0,
    rho_g: float = 1.0,
) -> list[_Job]:
    import jax.numpy as jnp

    from .scenes import catenary as scene

    params = {"length": length, "xl": xl, "yl": yl, "xr": xr, "yr": yr, "rho_g": rho_g}
    label = _label("catenary", params)
    try:
        ref = scene.closed_form(xl, yl, xr, yr, length, rho_g)
    except ValueError as e:
        raise SystemExit(f"{label}: {e}") from None

    def finish(sol, seconds):
        _warn_failure(sol.result, label)
        lam = sol.multipliers.integral[0]
        xm = 0.5 * (xl + xr)
        y_mid = sol(jnp.asarray(xm))
        slope_mid = sol.derivative(jnp.asarray(xm))
        tension = (rho_g * y_mid + lam) / jnp.sqrt(1 + slope_mid**2)
        # Chebyshev(48) on an entire function: spectral accuracy, ~1e-13.
        rows = _rows(
            label,
            seconds,
            [
                _check("multiplier lambda", lam, ref["multiplier"], 1e-10),
                _check(
                    "horizontal tension H", tension, ref["horizontal_tension"], 1e-10
                ),
                _check("y((xL+xR)/2)", y_mid, ref["y"](xm), 1e-10),
                _check("energy U", sol.value, ref["value"], 1e-10),
            ],
        )

        def draw(fig):
            from . import plot

            top, bottom = fig.subplots(2, 1, sharex=True, height_ratios=[2, 1])
            plot.functional_solution(sol, reference=ref["y"], ax=top, error_ax=bottom)
            top.set_xlabel("")
            top.set_title(
                f"the hanging rope (length {length:g}): Chebyshev(48) against the "
                "closed-form catenary",
                fontsize="medium",
            )

        return rows, {"catenary.png": draw}

    inputs = _arrays(xl, yl, xr, yr, length, rho_g)
    return [_Job(label, "catenary", inputs, finish)]


def _dido(a: float = 1.0, length: float = 2.5) -> list[_Job]:
    import jax.numpy as jnp

    from .scenes import dido as scene

    label = _label("dido", {"a": a, "length": length})
    try:
        ref = scene.closed_form(a, length)
    except ValueError as e:
        raise SystemExit(f"{label}: {e}") from None

    def finish(sol, seconds):
        _warn_failure(sol.result, label)
        # Chebyshev(32) on the arc, whose branch points x = +-R lie at a distance
        # rho = (R + sqrt(R^2 - a^2))/a (Bernstein ellipse): pointwise values converge
        # like rho^-32 (as in the tests), integrals like rho^-64 (a-priori rates,
        # constants ~1). Near the semicircle (C -> pi a) rho -> 1: no accuracy left.
        radius = ref["radius"]
        rho = (radius + math.sqrt(max(radius**2 - a**2, 0.0))) / a
        pointwise = max(rho**-32 / abs(ref["y"](0.0)), 1e-12)
        integral = rho**-64
        rows = _rows(
            label,
            seconds,
            [
                _check("area A", sol.value, ref["value"], max(integral, 1e-10)),
                _check(
                    "multiplier (-R)",
                    sol.multipliers.integral[0],
                    ref["multiplier"],
                    max(integral, 1e-9),
                ),
                _check("height y(0)", sol(jnp.asarray(0.0)), ref["y"](0.0), pointwise),
            ],
        )
        return rows, {}

    return [_Job(label, "dido", _arrays(a, length), finish)]


def _sphere_geodesic(radius: float = 1.0, angle: float = 0.8) -> list[_Job]:
    import jax.numpy as jnp

    from .scenes import sphere_geodesic as scene

    label = _label("sphere_geodesic", {"radius": radius, "angle": angle})
    s = math.sqrt(0.75) * radius
    start = (-0.5 * radius, s, 0.0)
    end = (0.5 * radius, s * math.cos(angle), s * math.sin(angle))
    try:
        if not (radius > 0 and 0 < abs(angle) < math.pi):
            raise ValueError("needs radius > 0 and 0 < |angle| < pi.")
        ref = scene.closed_form(start, end, radius)
    except ValueError as e:
        raise SystemExit(f"{label}: {e}") from None

    def finish(sol, seconds):
        _warn_failure(sol.result, label)
        mid = jnp.asarray(0.0)
        y_mid, ref_mid = sol(mid), ref["y"](0.0)
        # Chebyshev(24) on an analytic arc: the curve ~1e-13; multiplier functions
        # (a second derivative) lose a few digits.
        rows = _rows(
            label,
            seconds,
            [
                _check("length R phi", sol.value, ref["value"], 1e-12),
                _check("Y(0) (/R)", y_mid[0], ref_mid[0], 1e-10, radius),
                _check("Z(0) (/R)", y_mid[1], ref_mid[1], 1e-10, radius),
                _check(
                    "lambda(0)",
                    sol.multipliers.holonomic(mid),
                    ref["multiplier"](0.0),
                    1e-8,
                ),
            ],
        )
        return rows, {}

    inputs = (jnp.asarray(start), jnp.asarray(end), *_arrays(radius))
    return [_Job(label, "sphere_geodesic", inputs, finish)]


# ---------------------------------------------------------------------------------
# The work-precision diagram: the pendulum's error after `_WP_PERIODS` periods.
# ---------------------------------------------------------------------------------

_WP_THETA0 = 1.0
_WP_PERIODS = 10
_WP_METHODS = {
    # label: (program, "rtol" or "steps" per period, settings)
    "Tsit5 (diffrax, order 5)": ("pendulum Tsit5", "rtol", [1e-4, 1e-6, 1e-8, 1e-10]),
    "Dopri8 (diffrax, order 8)": ("pendulum Dopri8", "rtol", [1e-4, 1e-6, 1e-8, 1e-10]),
    "variational (RATTLE, order 2)": ("pendulum variational", "steps", [50, 100, 200]),
}


def _work_precision_jobs() -> tuple[list[_Job], dict, list[str]]:
    """Jobs that time the pendulum over `_WP_PERIODS` periods from `theta0 = 1`, for
    each method and setting. The error is the state's, `max(|q(nT) - q0| / l,
    |qdot(nT)| / sqrt(g l))`: after whole periods the pendulum is back at rest where
    it started (a turning point, where the position alone would hide a phase error,
    since dx/dt = 0 there)."""
    import numpy as np

    from .scenes import pendulum

    args = pendulum.default_args()
    g, l = float(args["g"]), float(args["l"])
    theta = _arrays(_WP_THETA0)[0]
    q0 = np.asarray(pendulum.state(theta, 0.0 * theta, args)[0])
    period = float(pendulum.period(theta, args))
    records: dict[str, tuple[list, list, list]] = {}
    lines: list[str] = []
    jobs = []
    for method, (program, kind, settings) in _WP_METHODS.items():
        records[method] = ([], [], [])
        for setting in settings:
            rtol = setting if kind == "rtol" else 1e-10
            dt0 = period / setting if kind == "steps" else 0.0
            tag = f"{kind}={setting:g}"

            def finish(traj, seconds, method=method, tag=tag):
                _warn_failure(traj.result, f"work-precision {method} {tag}")
                err = max(
                    float(np.max(np.abs(np.asarray(traj.q[-1]) - q0))) / l,
                    float(np.max(np.abs(np.asarray(traj.qd[-1])))) / math.sqrt(g * l),
                )
                ms = seconds * 1e3
                lines.append(f"  {method:<30} {tag:<12} error {err:9.2e} {ms:9.3f} ms")
                errors, times, tags = records[method]
                # An exact zero (never seen) would not fit a log scale: floor it.
                errors.append(max(err, np.finfo(np.float64).eps))
                times.append(seconds)
                tags.append(tag)
                return [], {}

            inputs = (theta, *_arrays(_WP_PERIODS), args, *_arrays(rtol, dt0))
            jobs.append(_Job(f"{method} {tag}", program, inputs, finish, repeats=5))
    return jobs, records, lines


def _order_rows(records) -> list[_Row]:
    """The variational integrator's convergence order, the slope of log(error)
    against log(steps), against its theory (2)."""
    import numpy as np

    errors, times, tags = records["variational (RATTLE, order 2)"]
    steps = np.asarray([float(t.split("=")[1]) for t in tags])
    slope = float(-np.polyfit(np.log(steps), np.log(np.asarray(errors)), 1)[0])
    return [
        _Row("work-precision", "RATTLE order (slope)", slope, 2.0, 0.05, sum(times))
    ]


def _draw_work_precision(records):
    def draw(fig):
        from . import plot

        ax = fig.subplots()
        plot.work_precision(records, annotate=True, ax=ax)
        ax.set_ylabel(f"state error after {_WP_PERIODS} periods")
        ax.set_xlabel("wall time per solve [s] (compiled, median of 5)")
        ax.set_title(
            f"pendulum (Cartesian, r = l), {_WP_PERIODS} periods from theta0 = "
            f"{_WP_THETA0:g}:\n"
            "error of (q/l, qdot/sqrt(gl)) against cost",
            fontsize="medium",
        )

    return draw


# ---------------------------------------------------------------------------------
# Running jobs
# ---------------------------------------------------------------------------------


# Programs by decreasing compilation time (measured), so that the longest starts
# first and the threads finish together.
_COMPILE_ORDER = [
    "two_cylinders",
    "catenary",
    "rolling_disk",
    "pendulum variational",
    "sphere_geodesic",
    "rotating_hoop",
    "pendulum Tsit5",
    "pendulum Dopri8",
    "dido",
    "cylinder_volume",
]


def _compile(jobs: list[_Job], workers: int) -> dict[str, float]:
    """Call each program once (tracing, compilation, one run), `workers` at a time
    in threads; returns the seconds of each first call."""
    import jax

    first = {}
    for job in jobs:
        first.setdefault(job.program, job)
    order = sorted(first, key=_COMPILE_ORDER.index)
    for program in order:
        _program(program)  # build the jitted functions in this thread

    def call(program):
        job = first[program]
        start = time.perf_counter()
        jax.block_until_ready(_program(program)(*job.inputs))
        return time.perf_counter() - start

    if workers <= 1:
        return {program: call(program) for program in order}
    with ThreadPoolExecutor(max_workers=workers) as pool:
        futures = {program: pool.submit(call, program) for program in order}
        return {program: future.result() for program, future in futures.items()}


def _run(job: _Job):
    """The job's compiled solve, checked: its output is timed by the median of
    `repeats` calls."""
    import jax

    fn = _program(job.program)
    out = jax.block_until_ready(fn(*job.inputs))
    times = []
    for _ in range(job.repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*job.inputs))
        times.append(time.perf_counter() - start)
    return job.finish(out, statistics.median(times))


# ---------------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Scene:
    jobs: Callable[..., list[_Job]]
    params: dict  # name -> (default, help)
    doc: str


_SCENES: dict[str, _Scene] = {
    "cylinder_volume": _Scene(
        _cylinder_volume,
        {
            "b": (1.0, "shape parameter b of the constraint 2 pi a + h^2/b = l"),
            "l": (1.0, "budget l of the constraint 2 pi a + h^2/b = l"),
        },
        "extremize the volume pi a^2 h subject to 2 pi a + h^2/b - l = 0: a, h, "
        "lambda and V* against the closed form",
    ),
    "pendulum": _Scene(
        _pendulum,
        {
            "theta0": (1.0, "release angle from the downward vertical [rad], at rest"),
            "periods": (1.0, "number of periods T to integrate (a whole number)"),
            "m": (1.0, "mass"),
            "g": (9.81, "gravity"),
            "l": (1.0, "length of the rod (the constraint r = l)"),
        },
        "Cartesian pendulum with the constraint r = l over one period T (elliptic "
        "closed form): the tension and speed at the bottom, the return to the start",
    ),
    "two_cylinders": _Scene(
        _two_cylinders,
        {
            "theta0": (0.2, "initial angle of the line of centres [rad], at rest"),
            "alpha": (0.5, "I / (M a^2) of the rolling cylinder"),
            "M": (1.0, "mass of the rolling cylinder"),
            "a": (0.3, "radius of the rolling cylinder"),
            "R": (1.0, "radius of the fixed cylinder"),
            "g": (9.81, "gravity"),
        },
        "a cylinder rolling off a fixed one: the contact releases where the normal "
        "force vanishes, theta* = arccos(2 cos theta0/(3 + alpha)), at the "
        "closed-form (elliptic) time",
    ),
    "rolling_disk": _Scene(
        _rolling_disk,
        {
            "theta0": (0.3, "initial heading [rad]"),
            "nu": (2.0, "rolling rate phidot"),
            "omega": (0.7, "turning rate thetadot (nonzero)"),
            "t1": (6.0, "final time"),
            "m": (1.0, "mass"),
            "R": (0.5, "radius of the disk"),
            "I_roll": (0.125, "moment of inertia about the axle"),
            "I_turn": (0.0625, "moment of inertia about the vertical"),
        },
        "a vertical disk rolling without slipping (nonholonomic): a circle of radius "
        "R nu/omega, the centripetal multipliers, the energy",
    ),
    "rotating_hoop": _Scene(
        _rotating_hoop,
        {
            "theta0": (0.4, "initial angle from the bottom [rad], at rest on the hoop"),
            "t1": (3.0, "final time"),
            "omega": (6.0, "spin rate of the hoop (omega^2 > g/rho)"),
            "rho": (0.5, "radius of the hoop"),
            "m": (1.0, "mass of the bead"),
            "g": (9.81, "gravity"),
        },
        "a bead on a spinning hoop (rheonomic): the Jacobi integral is conserved, the "
        "relative equilibrium cos theta* = g/(rho omega^2) stays put",
    ),
    "catenary": _Scene(
        _catenary,
        {
            "length": (1.5, "length of the rope (longer than the chord)"),
            "xl": (0.0, "x of the left end"),
            "yl": (0.0, "y of the left end"),
            "xr": (1.0, "x of the right end"),
            "yr": (0.0, "y of the right end"),
            "rho_g": (1.0, "weight per unit length"),
        },
        "the hanging rope of fixed length (isoperimetric): the catenary, its "
        "multiplier, horizontal tension and energy",
    ),
    "dido": _Scene(
        _dido,
        {
            "a": (1.0, "half-width of the shore [-a, a]"),
            "length": (
                2.5,
                "length of the curve, 2a < length <= pi a (towards pi a the arc gets "
                "vertical end tangents and the spectral accuracy, hence the "
                "tolerances, degrades)",
            ),
        },
        "Dido's problem: the largest area for a given length is a circular arc, with "
        "multiplier lambda = -R",
    ),
    "sphere_geodesic": _Scene(
        _sphere_geodesic,
        {
            "radius": (1.0, "radius of the sphere"),
            "angle": (0.8, "angle about the x-axis between the two ends [rad]"),
        },
        "shortest path on a sphere (holonomic constraint): the great circle and the "
        "multiplier function lambda(x)",
    ),
}

# The tour: every scene on its defaults, and the cylinder on a badly scaled budget
# (without its picture). Entries: (scene, parameters, draw its pictures).
_TOUR = [(name, {}, True) for name in _SCENES]
_TOUR += [("cylinder_volume", {"b": 1e-3, "l": 1e3}, False)]


def _print_table(rows: list[_Row]) -> bool:
    """One line per row, columns separated by at least two spaces."""
    width = max(len("scene"), *(len(row.scene) for row in rows))
    qwidth = max(len(row.quantity) for row in rows)
    header = (
        f"{'scene':<{width}}  {'quantity':<{qwidth}}  {'computed':>17}  "
        f"{'closed form':>17}  {'rel. error':>10}  {'tolerance':>9}  {'time [s]':>9}  "
        "check"
    )
    print(header)
    print("-" * len(header))
    ok = True
    for row in rows:
        ok &= row.passed
        print(
            f"{row.scene:<{width}}  {row.quantity:<{qwidth}}  {row.computed:>17.11g}  "
            f"{row.reference:>17.11g}  {row.rel_error:>10.2e}  {row.tolerance:>9.0e}  "
            f"{row.seconds:>9.4f}  {'ok' if row.passed else 'FAIL'}"
        )
    return ok


def _have_matplotlib() -> bool:
    return importlib.util.find_spec("matplotlib") is not None


def _save(out: Path, name: str, draw: Callable) -> Path:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 5.5), layout="constrained")
    draw(fig)
    out.mkdir(parents=True, exist_ok=True)
    path = out / name
    fig.savefig(path, dpi=100)
    return path


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="constrained-jax",
        description=(
            "Constrained extremization, variational problems and constrained "
            "mechanics in JAX: the built-in scenes, each checked against its closed "
            "form."
        ),
        epilog=(
            "Each row of the table compares a computed number with the closed form "
            "and states its tolerance on the relative error (divided by the named "
            "scale where the closed form is zero); the exit status is 1 if any check "
            "fails. Pictures need matplotlib: pip install 'constrained_jax[plot]'."
        ),
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def output_options(p):
        p.add_argument(
            "--out",
            type=Path,
            default=Path(_DEFAULT_OUT),
            help=f"folder for the pictures (default ./{_DEFAULT_OUT}/)",
        )
        p.add_argument("--no-plots", action="store_true", help="draw no pictures")
        p.add_argument(
            "--jobs",
            type=int,
            default=2,
            help="programs compiled at a time, in threads (default 2; 1: one by one)",
        )

    tour = sub.add_parser(
        "tour",
        help="solve every built-in scene, check the closed forms, draw the pictures",
        description=(
            "Solve every built-in scene on its default parameters, print one table "
            "(scene, quantity, computed, closed form, relative error, tolerance, "
            "time of the compiled solve), write the pictures (the cylinder's "
            "constrained extremum, the catenary against its closed form, the two "
            "cylinders' normal force against angle with the detachment point, a "
            "work-precision diagram of the pendulum for Tsit5, Dopri8 and the "
            "variational integrator) and exit with status 1 if any check fails. "
            "Compilation dominates the run time (seconds per program; the solves "
            "take milliseconds)."
        ),
    )
    output_options(tour)
    scene_parser = sub.add_parser(
        "scene",
        help="run one scene with chosen parameters",
        description="Run one scene; `scene NAME --help` lists its parameters.",
    )
    scene_sub = scene_parser.add_subparsers(dest="name", required=True, metavar="NAME")
    for name, scene in _SCENES.items():
        p = scene_sub.add_parser(name, help=scene.doc, description=scene.doc)
        for param, (default, help_) in scene.params.items():
            p.add_argument(
                f"--{param}",
                type=float,
                default=default,
                help=f"{help_} (default {default:g})",
            )
        output_options(p)
    sub.add_parser("list", help="list the built-in scenes and their parameters")
    return parser


def main(argv: list[str] | None = None) -> int:
    ns = _parser().parse_args(argv)

    if ns.command == "list":
        for name, scene in _SCENES.items():
            params = " ".join(f"--{k} {d:g}" for k, (d, _) in scene.params.items())
            print(f"{name}\n    {scene.doc}\n    parameters: {params}")
        return 0

    start = time.perf_counter()
    import jax

    jax.config.update("jax_enable_x64", True)
    if ns.command == "tour":
        runs = _TOUR
    else:
        params = {k: getattr(ns, k) for k in _SCENES[ns.name].params}
        runs = [(ns.name, params, True)]
    plots = not ns.no_plots
    if plots and not _have_matplotlib():
        print(
            "matplotlib is not installed: the checks run, the pictures are skipped.\n"
            "For the pictures: pip install 'constrained_jax[plot]'\n"
        )
        plots = False

    jobs = []
    for name, params, draw in runs:
        for job in _SCENES[name].jobs(**params):
            job.draw = draw
            jobs.append(job)
    records, wp_lines = None, []
    if ns.command == "tour":
        wp_jobs, records, wp_lines = _work_precision_jobs()
        jobs += wp_jobs
    first_calls = _compile(jobs, ns.jobs)
    rows, pictures = [], {}
    for job in jobs:
        new_rows, new_pictures = _run(job)
        rows += new_rows
        if job.draw:
            pictures |= new_pictures
    if records is not None:
        rows += _order_rows(records)
        pictures["work_precision.png"] = _draw_work_precision(records)

    ok = _print_table(rows)
    print(
        "time: median wall clock of the compiled solve. Compilation (first call of "
        f"each program, {ns.jobs} at a time):\n  "
        + ", ".join(f"{p} {s:.1f} s" for p, s in first_calls.items())
    )
    if wp_lines:
        print(
            f"\nwork-precision (pendulum from theta0 = {_WP_THETA0:g}, state error "
            f"after {_WP_PERIODS} periods, median of 5 runs):"
        )
        print("\n".join(wp_lines))
    if plots and pictures:
        print()
        for name, draw in pictures.items():
            print(f"picture: {_save(ns.out, name, draw)}")
    print(f"\ntotal {time.perf_counter() - start:.1f} s (compilation included)")
    print("all checks passed" if ok else "SOME CHECKS FAILED")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
