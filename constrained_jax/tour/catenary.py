"""The hanging rope of fixed length (isoperimetric): the catenary, its multiplier,
horizontal tension and energy against the closed form, and the picture of the
solution against it."""

import jax.numpy as jnp

from .. import plot
from ..scenes import catenary as scene
from ._entry import arrays, Check, Job, Param, Program, Scene


# Chebyshev(48) from `solve_functional`'s default start (the scene's `solve`), deep
# sags included.
PROGRAM = Program(
    "catenary",
    lambda: lambda *values: scene.solve(*values, throw=False),
)


def build(
    label: str,
    length: float,
    xl: float,
    yl: float,
    xr: float,
    yr: float,
    rho_g: float,
) -> list[Job]:
    ref = scene.closed_form(xl, yl, xr, yr, length, rho_g)  # ValueError: impossible

    def finish(sol):
        lam = sol.multipliers.integral[0]
        xm = 0.5 * (xl + xr)
        y_mid = sol(jnp.asarray(xm))
        slope_mid = sol.derivative(jnp.asarray(xm))
        tension = (rho_g * y_mid + lam) / jnp.sqrt(1 + slope_mid**2)
        # Chebyshev(48) on an entire function: spectral accuracy, ~1e-13.
        checks = [
            Check("multiplier lambda", lam, ref["multiplier"], 1e-10),
            Check("horizontal tension H", tension, ref["horizontal_tension"], 1e-10),
            Check("y((xL+xR)/2)", y_mid, ref["y"](xm), 1e-10),
            Check("energy U", sol.value, ref["value"], 1e-10),
        ]

        def draw(fig):
            top, bottom = fig.subplots(2, 1, sharex=True, height_ratios=[2, 1])
            plot.functional_solution(sol, reference=ref["y"], ax=top, error_ax=bottom)
            top.set_xlabel("")
            top.set_title(
                f"the hanging rope (length {length:g}): Chebyshev(48) against the "
                "closed-form catenary",
                fontsize="medium",
            )

        return checks, {"catenary.png": draw}

    inputs = arrays(xl, yl, xr, yr, length, rho_g)
    return [Job(label, PROGRAM, inputs, finish)]


SCENE = Scene(
    "catenary",
    "the hanging rope of fixed length (isoperimetric): the catenary, its "
    "multiplier, horizontal tension and energy",
    {
        "length": Param(1.5, "length of the rope (longer than the chord)"),
        "xl": Param(0.0, "x of the left end"),
        "yl": Param(0.0, "y of the left end"),
        "xr": Param(1.0, "x of the right end"),
        "yr": Param(0.0, "y of the right end"),
        "rho_g": Param(1.0, "weight per unit length"),
    },
    build,
    picture="the catenary against its closed form",
    title="a hanging rope of fixed length (an integral constraint)",
)
