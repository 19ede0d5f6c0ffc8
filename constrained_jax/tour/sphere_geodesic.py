"""The shortest path on a sphere (holonomic constraint): the great circle and the
multiplier function against the closed form."""

import math

import jax.numpy as jnp

from ..scenes import sphere_geodesic as scene
from ._entry import arrays, Check, Job, Param, Program, Scene


PROGRAM = Program(
    "sphere_geodesic",
    lambda: lambda start, end, radius: scene.solve(start, end, radius, throw=False),
)


def build(label: str, radius: float, angle: float) -> list[Job]:
    s = math.sqrt(0.75) * radius
    start = (-0.5 * radius, s, 0.0)
    end = (0.5 * radius, s * math.cos(angle), s * math.sin(angle))
    if not (radius > 0 and 0 < abs(angle) < math.pi):
        raise ValueError("needs radius > 0 and 0 < |angle| < pi.")
    ref = scene.closed_form(start, end, radius)  # ValueError: impossible

    def finish(sol):
        mid = jnp.asarray(0.0)
        y_mid, ref_mid = sol(mid), ref["y"](0.0)
        # Chebyshev(24) on an analytic arc: the curve ~1e-13; multiplier functions
        # (a second derivative) lose a few digits.
        checks = [
            Check("length R phi", sol.value, ref["value"], 1e-12),
            Check("Y(0) (/R)", y_mid[0], ref_mid[0], 1e-10, radius),
            Check("Z(0) (/R)", y_mid[1], ref_mid[1], 1e-10, radius),
            Check(
                "lambda(0)",
                sol.multipliers.holonomic(mid),
                ref["multiplier"](0.0),
                1e-8,
            ),
        ]
        return checks, {}

    inputs = (jnp.asarray(start), jnp.asarray(end), *arrays(radius))
    return [Job(label, PROGRAM, inputs, finish)]


SCENE = Scene(
    "sphere_geodesic",
    "shortest path on a sphere (holonomic constraint): the great circle and the "
    "multiplier function lambda(x)",
    {
        "radius": Param(1.0, "radius of the sphere"),
        "angle": Param(0.8, "angle about the x-axis between the two ends [rad]"),
    },
    build,
    title="the shortest path on a sphere",
)
