"""A bead on a spinning hoop (rheonomic): the Jacobi integral is conserved, the
relative equilibrium stays put."""

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

import constrained_jax as cjax

from ..scenes import rotating_hoop as scene
from ._entry import arrays, Check, Job, Param, Program, Scene, simulate


class _Out(NamedTuple):
    result: cjax.RESULTS
    angle: jax.Array  # on the hoop, at t1
    rate: jax.Array  # d/dt angle(q(t), t) at t1


def _run(theta0, t1, args):
    zero = jnp.zeros_like(theta0)
    q0, qd0 = scene.state(theta0, zero, zero, args)
    saveat = cjax.SaveAt(t1=True, multipliers=False, violation=False)
    traj = simulate(scene.system(), t1, q0, qd0, args, saveat)
    angle, rate = jax.jvp(
        lambda q, t: scene.angle(q, t, args),
        (traj.q[-1], t1),
        (traj.qd[-1], jnp.ones_like(t1)),
    )
    return _Out(traj.result, angle, rate)


PROGRAM = Program("rotating_hoop", lambda: _run)


def build(
    label: str, theta0: float, t1: float, omega: float, rho: float, m: float, g: float
) -> list[Job]:
    if not (rho > 0 and m > 0 and g > 0 and t1 > 0 and g < rho * omega**2):
        raise ValueError(
            "needs omega^2 > g/rho (for the relative equilibrium "
            "cos(theta*) = g/(rho omega^2) off the bottom), t1 > 0 and positive rho, "
            "m, g."
        )
    args = scene.default_args(m=m, rho=rho, omega=omega, g=g)
    theta_star = math.acos(g / (rho * omega**2))

    def finish_oscillation(out):
        # Tsit5 at 1e-10, no stabilization: the invariant to ~1e-9.
        h0 = scene.jacobi_integral(theta0, 0.0, args)
        h1 = scene.jacobi_integral(out.angle, out.rate, args)
        return [Check("Jacobi integral h(t1)", h1, h0, 1e-8)], {}

    def finish_equilibrium(out):
        return [Check("theta(t1) from theta*", out.angle, theta_star, 1e-8)], {}

    return [
        Job(label, PROGRAM, (*arrays(theta0, t1), args), finish_oscillation),
        Job(label, PROGRAM, (*arrays(theta_star, t1), args), finish_equilibrium),
    ]


SCENE = Scene(
    "rotating_hoop",
    "a bead on a spinning hoop (rheonomic): the Jacobi integral is conserved, the "
    "relative equilibrium cos theta* = g/(rho omega^2) stays put",
    {
        "theta0": Param(
            0.4, "initial angle from the bottom [rad], at rest on the hoop"
        ),
        "t1": Param(3.0, "final time"),
        "omega": Param(6.0, "spin rate of the hoop (omega^2 > g/rho)"),
        "rho": Param(0.5, "radius of the hoop"),
        "m": Param(1.0, "mass of the bead"),
        "g": Param(9.81, "gravity"),
    },
    build,
    title="a bead on a spinning hoop (a constraint that moves)",
)
