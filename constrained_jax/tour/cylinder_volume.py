"""The largest cylinder: a, h, lambda and V* against the closed form, and the picture
of the constrained extremum; then with the height capped (an inequality that binds):
a, h, lambda, the cap's multiplier mu and V* against the closed form by hand."""

import jax.numpy as jnp

from .. import plot
from ..scenes import cylinder_volume as scene
from ._entry import arrays, Check, Job, Param, Program, Scene


PROGRAM = Program(
    "cylinder_volume",
    lambda: lambda b, l: scene.solve(b, l, throw=False),
)
CAPPED = Program(
    "cylinder_volume_capped",
    lambda: lambda b, l, h_max: scene.solve_capped(b, l, h_max, throw=False),
)


def build(label: str, b: float, l: float, h_max: float) -> list[Job]:
    if not (b > 0 and l > 0 and h_max > 0):
        raise ValueError("needs b > 0, l > 0 and h_max > 0.")

    def finish(sol):
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

    def finish_capped(sol):
        ref = scene.capped_closed_form(b, l, h_max)
        # mu vanishes when the cap does not bind: measured against the volume's scale.
        mu_scale = None if bool(ref["active"]) else float(ref["volume"])
        checks = [
            Check("radius a", sol.x[0], ref["a"], 1e-10),
            Check("height h", sol.x[1], ref["h"], 1e-10),
            Check("multiplier lambda", sol.multipliers[0], ref["multiplier"], 1e-10),
            Check(
                "cap multiplier mu",
                sol.inequality_multipliers[1],
                ref["cap_multiplier"],
                1e-9,
                mu_scale,
            ),
            Check("volume V*", sol.value, ref["volume"], 1e-10),
        ]
        return checks, {}

    return [
        Job(label, PROGRAM, arrays(b, l), finish),
        Job(
            f"{label}, capped h <= {h_max:g}",
            CAPPED,
            arrays(b, l, h_max),
            finish_capped,
            note="an inequality constraint, with its multiplier mu",
        ),
    ]


SCENE = Scene(
    "cylinder_volume",
    "extremize the volume pi a^2 h subject to 2 pi a + h^2/b - l = 0: a, h, "
    "lambda and V* against the closed form; then with the cap h <= h_max: a, h, "
    "lambda, the cap's multiplier mu and V*",
    {
        "b": Param(1.0, "shape parameter b of the constraint 2 pi a + h^2/b = l"),
        "l": Param(1.0, "budget l of the constraint 2 pi a + h^2/b = l"),
        "h_max": Param(
            0.4, "cap on the height, h <= h_max (it binds below sqrt(b l / 5))"
        ),
    },
    build,
    picture="the cylinder's constrained extremum",
    title="the largest cylinder V = pi a^2 h for a budget 2 pi a + h^2/b = l",
)
