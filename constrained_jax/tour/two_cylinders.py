"""A cylinder rolling off a fixed one: the release where the normal force vanishes,
against the closed form, and the picture of the multipliers against the angle."""

import math

import jax.numpy as jnp
import numpy as np

import constrained_jax as cjax

from .. import plot
from ..scenes import two_cylinders as scene
from ._entry import arrays, Check, Job, Param, Program, Scene, simulate


def _run(theta0, args):
    q0, qd0 = scene.state(theta0, jnp.zeros_like(theta0), args)
    t_star = scene.detachment_time(theta0, args)
    ts = t_star * jnp.linspace(0.0, 1.2, 121)  # ts[50] = t*/2
    saveat = cjax.SaveAt(ts=ts, energy=False, violation=False)
    return simulate(scene.contact_system(), ts[-1], q0, qd0, args, saveat)


PROGRAM = Program("two_cylinders", lambda: _run)


def build(
    label: str, theta0: float, alpha: float, M: float, a: float, R: float, g: float
) -> list[Job]:
    if not (0 < theta0 < math.pi / 2 and alpha > 0 and M > 0 and a > 0 and R > 0):
        raise ValueError(
            "needs 0 < theta0 < pi/2 (at theta0 = 0 it balances on top "
            "forever), alpha > 0 (alpha = 0 leaves the spin of the free cylinder "
            "undetermined after detachment) and M, a, R > 0."
        )
    args = scene.default_args(M=M, alpha=alpha, a=a, R=R, g=g)

    def finish(traj):
        rel = traj.release
        angle = float(scene.detachment_angle(theta0, args))
        half = 50  # t*/2, attached
        theta_half = traj.q[half, 1]
        # Tsit5 at 1e-10; the release found by a root find on the multiplier.
        checks = [
            Check("detachment angle", rel.q[1], angle, 1e-8),
            Check(
                "detachment time",
                rel.time,
                scene.detachment_time(jnp.asarray(theta0), args),
                1e-8,
            ),
            Check(
                "rate at detachment",
                rel.qd[1],
                jnp.sqrt(scene.angular_velocity_squared(angle, theta0, args)),
                1e-8,
            ),
            Check(
                "normal force at t*/2",
                traj.multipliers[half, 0],
                scene.normal_force(theta_half, theta0, args),
                1e-8,
            ),
            Check(
                "no-slip lambda2 at t*/2",
                traj.multipliers[half, 1],
                scene.no_slip_multiplier(theta_half, args),
                1e-8,
            ),
        ]

        def draw(fig):
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

        return checks, {"two_cylinders_normal_force.png": draw}

    return [Job(label, PROGRAM, (*arrays(theta0), args), finish)]


SCENE = Scene(
    "two_cylinders",
    "a cylinder rolling off a fixed one: the contact releases where the normal "
    "force vanishes, theta* = arccos(2 cos theta0/(3 + alpha)), at the "
    "closed-form (elliptic) time",
    {
        "theta0": Param(0.2, "initial angle of the line of centres [rad], at rest"),
        "alpha": Param(0.5, "I / (M a^2) of the rolling cylinder"),
        "M": Param(1.0, "mass of the rolling cylinder"),
        "a": Param(0.3, "radius of the rolling cylinder"),
        "R": Param(1.0, "radius of the fixed cylinder"),
        "g": Param(9.81, "gravity"),
    },
    build,
    picture="the two cylinders' normal force against angle with the detachment point",
    title="a cylinder rolling off a fixed one, until it lets go",
)
