"""A ball bouncing on a floor (contacts that come and go): the impact times, a
geometric series in the restitution e, the apex after the first bounce, the impact
at which it comes to rest, and the floor's multiplier m g there, against the closed
forms."""

import jax.numpy as jnp

import constrained_jax as cjax

from ..scenes import bouncing_ball as scene
from ._entry import arrays, Check, Job, Param, Program, Scene, simulate


MAX_EVENTS = 24


def _run(h, t1, ts, args):
    q0, qd0 = scene.state(h)
    saveat = cjax.SaveAt(ts=ts, energy=False, violation=False)
    return simulate(scene.system(), t1, q0, qd0, args, saveat, max_events=MAX_EVENTS)


PROGRAM = Program("bouncing_ball", lambda: _run)


def build(label: str, h: float, e: float, rest_speed: float, m: float) -> list[Job]:
    if not (h > 0 and 0 < e < 1 and rest_speed > 0 and m > 0):
        raise ValueError("needs h > 0, 0 < e < 1, rest_speed > 0 and m > 0.")
    g = 9.81
    rest = scene.rest_impact(h, e, g, rest_speed)
    if rest > MAX_EVENTS:
        raise ValueError(
            f"the ball comes to rest at impact {rest}, beyond the tour's "
            f"{MAX_EVENTS} events: raise rest_speed or lower e."
        )
    args = scene.default_args(e=e, m=m, g=g, rest_speed=rest_speed)
    t_rest = float(scene.impact_time(rest, h, args))
    # Saved: the apex after the first impact, and (at rest) after the last one.
    t_apex = float(scene.impact_time(1, h, args) + scene.impact_speed(2, h, args) / g)
    t1 = t_rest + 1.0
    ts = jnp.array([t_apex, t1])

    def finish(traj):
        events = traj.events
        checks = [
            Check(
                f"impact time t_{k}",
                events.time[k - 1],
                scene.impact_time(k, h, args),
                1e-9,
            )
            for k in (1, 2, 3)
        ]
        checks += [
            Check(
                "apex after 1st impact",
                traj.q[0, 1],
                scene.apex_height(1, h, args),
                1e-9,
            ),
            Check("impacts until at rest (k_r)", events.count, rest, 0.0),
            Check(f"rest time t_{rest}", events.time[rest - 1], t_rest, 1e-9),
            Check(
                "floor multiplier at rest (m g)", traj.multipliers[1, 0], m * g, 1e-9
            ),
        ]
        return checks, {}

    return [Job(label, PROGRAM, (*arrays(h, t1), ts, args), finish)]


SCENE = Scene(
    "bouncing_ball",
    "a ball bouncing on a floor with restitution e (Unilateral with restitution, "
    "simulate(max_events=...)): impact times (a geometric series), the apex, the "
    "impact at which it rests (rest_speed) and the floor's multiplier",
    {
        "h": Param(1.0, "drop height"),
        "e": Param(0.8, "coefficient of restitution, 0 < e < 1"),
        "rest_speed": Param(0.5, "impacts slower than this re-make the contact (rest)"),
        "m": Param(1.0, "mass"),
    },
    build,
    title="a ball bouncing on a floor until it comes to rest",
)
