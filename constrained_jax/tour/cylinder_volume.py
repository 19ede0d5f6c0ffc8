"""The largest cylinder: a, h, lambda and V* against the closed form, and the picture
of the constrained extremum."""

import jax.numpy as jnp

from .. import plot
from ..scenes import cylinder_volume as scene
from ._entry import arrays, Check, Job, Param, Program, Scene


PROGRAM = Program(
    "cylinder_volume",
    lambda: lambda b, l: scene.solve(b, l, throw=False),
    compile_cost=3,
)


def build(label: str, b: float, l: float) -> list[Job]:
    if not (b > 0 and l > 0):
        raise ValueError("needs b > 0 and l > 0.")

    def finish(sol, seconds):
        ref = scene.closed_form(b, l)
        # Newton on the KKT system to rtol = atol = 1e-10 (relative to the scale).
        checks = [
            Check("radius a", sol.x[0], ref["a"], 1e-10),
            Check("height h", sol.x[1], ref["h"], 1e-10),
            Check("multiplier lambda", sol.multipliers[0], ref["multiplier"], 1e-10),
            Check("volume V*", sol.value, ref["volume"], 1e-10),
        ]

        def draw(fig):
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

        return checks, {"cylinder_extremum.png": draw}

    return [Job(label, PROGRAM, arrays(b, l), finish)]


SCENE = Scene(
    "cylinder_volume",
    "extremize the volume pi a^2 h subject to 2 pi a + h^2/b - l = 0: a, h, "
    "lambda and V* against the closed form",
    {
        "b": Param(1.0, "shape parameter b of the constraint 2 pi a + h^2/b = l"),
        "l": Param(1.0, "budget l of the constraint 2 pi a + h^2/b = l"),
    },
    build,
    picture="the cylinder's constrained extremum",
)
