"""Dido's problem: the area, the multiplier -R and the height of the circular arc
against the closed form, to the accuracy Chebyshev(32) promises on it."""

import math

import jax.numpy as jnp

from ..scenes import dido as scene
from ._entry import arrays, Check, Job, Param, Program, Scene


PROGRAM = Program(
    "dido",
    lambda: lambda a, length: scene.solve(a, length, throw=False),
)


def build(label: str, a: float, length: float) -> list[Job]:
    ref = scene.closed_form(a, length)  # ValueError: impossible

    def finish(sol):
        # Chebyshev(32) on the arc, whose branch points x = +-R lie at a distance
        # rho = (R + sqrt(R^2 - a^2))/a (Bernstein ellipse): pointwise values converge
        # like rho^-32 (as in the tests), integrals like rho^-64 (a-priori rates,
        # constants ~1). Near the semicircle (C -> pi a) rho -> 1: no accuracy left.
        radius = ref["radius"]
        rho = (radius + math.sqrt(max(radius**2 - a**2, 0.0))) / a
        pointwise = max(rho**-32 / abs(ref["y"](0.0)), 1e-12)
        integral = rho**-64
        checks = [
            Check("area A", sol.value, ref["value"], max(integral, 1e-10)),
            Check(
                "multiplier (-R)",
                sol.multipliers.integral[0],
                ref["multiplier"],
                max(integral, 1e-9),
            ),
            Check("height y(0)", sol(jnp.asarray(0.0)), ref["y"](0.0), pointwise),
        ]
        return checks, {}

    return [Job(label, PROGRAM, arrays(a, length), finish)]


SCENE = Scene(
    "dido",
    "Dido's problem: the largest area for a given length is a circular arc, with "
    "multiplier lambda = -R",
    {
        "a": Param(1.0, "half-width of the shore [-a, a]"),
        "length": Param(
            2.5,
            "length of the curve, 2a < length <= pi a (towards pi a the arc gets "
            "vertical end tangents and the spectral accuracy, hence the "
            "tolerances, degrades)",
        ),
    },
    build,
    title="Dido's problem: the largest area for a given length",
)
