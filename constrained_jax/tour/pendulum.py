"""The Cartesian pendulum over whole periods: the tension and speed at the bottom,
the return to the start. Its programs (one per integrator) also serve the
work-precision diagram."""

import math

import diffrax
import jax.numpy as jnp

import constrained_jax as cjax

from ..scenes import pendulum as scene
from ._entry import arrays, Check, Job, Param, Program, Scene, simulate


def _program(solver):
    """The pendulum released from rest at `theta0`, over `periods` periods `T` (closed
    form), saved at `T/4, T/2` and the end; `rtol` (diffrax solvers) or `dt0` (the
    variational integrator) traced."""

    def run(theta0, periods, args, rtol, dt0):
        q0, qd0 = scene.state(theta0, jnp.zeros_like(theta0), args)
        period = scene.period(theta0, args)
        variational = isinstance(solver, cjax.VariationalIntegrator)
        t1 = periods * period
        return simulate(
            scene.system(),
            t1,
            q0,
            qd0,
            args,
            cjax.SaveAt(
                ts=jnp.stack([period / 4, period / 2, t1]),
                energy=False,
                violation=False,
            ),
            solver=solver,
            dt0=dt0 if variational else None,
            stepsize_controller=diffrax.PIDController(rtol=rtol, atol=rtol),
            max_steps=1 << 16,
        )

    return run


TSIT5 = Program("pendulum Tsit5", lambda: _program(diffrax.Tsit5()))
DOPRI8 = Program("pendulum Dopri8", lambda: _program(diffrax.Dopri8()))
VARIATIONAL = Program(
    "pendulum variational",
    lambda: _program(cjax.VariationalIntegrator()),
)


def build(
    label: str, theta0: float, periods: float, m: float, g: float, l: float
) -> list[Job]:
    if not (0 < abs(theta0) < math.pi and m > 0 and g > 0 and l > 0):
        raise ValueError("needs 0 < |theta0| < pi and m, g, l > 0.")
    if not (periods >= 1 and periods == int(periods)):
        raise ValueError("`periods` must be a whole number >= 1.")
    args = scene.default_args(m=m, g=g, l=l)

    def finish(traj):
        speed = math.sqrt(2 * g * l * (1 - math.cos(theta0)))
        bottom, half, end = 0, 1, 2
        # Tsit5 at rtol = atol = 1e-10 over one period: global error ~1e-9 per
        # period (it grows linearly with the number of periods).
        n = f"{periods:g}T" if periods != 1 else "T"
        tol = 1e-7 * periods
        tension = m * g * (3 - 2 * math.cos(theta0))
        checks = [
            Check("tension at T/4", -traj.multipliers[bottom, 0], tension, 1e-7),
            Check("x at T/4 (/l)", traj.q[bottom, 0], 0.0, 1e-7, l),
            Check("speed at T/4", jnp.linalg.norm(traj.qd[bottom]), speed, 1e-7),
            Check("x at T/2", traj.q[half, 0], -l * math.sin(theta0), 1e-7),
            Check(f"x at {n}", traj.q[end, 0], l * math.sin(theta0), tol),
            Check(
                f"xdot at {n} (/sqrt(gl))", traj.qd[end, 0], 0.0, tol, math.sqrt(g * l)
            ),
        ]
        return checks, {}

    inputs = (*arrays(theta0, periods), args, *arrays(1e-10, 0.0))
    return [Job(label, TSIT5, inputs, finish)]


SCENE = Scene(
    "pendulum",
    "Cartesian pendulum with the constraint r = l over one period T (elliptic "
    "closed form): the tension and speed at the bottom, the return to the start",
    {
        "theta0": Param(1.0, "release angle from the downward vertical [rad], at rest"),
        "periods": Param(1.0, "number of periods T to integrate (a whole number)"),
        "m": Param(1.0, "mass"),
        "g": Param(9.81, "gravity"),
        "l": Param(1.0, "length of the rod (the constraint r = l)"),
    },
    build,
    title="a pendulum in Cartesian coordinates, its rod a constraint r = l",
)
