"""Contacts that stick and slip (Coulomb friction): a block stopping on an incline,
a disk launched sliding that starts to roll, the lecture's two cylinders slipping
before they part, and the Painleve rod refused above its critical coefficient, each
against its closed form."""

import math

import diffrax
import jax.numpy as jnp
import numpy as np

import constrained_jax as cjax

from .. import plot
from ..scenes import (
    incline_block,
    painleve_rod,
    sliding_disk,
    two_cylinders_friction as cylinders,
)
from ._entry import arrays, Check, Job, Param, Program, Scene


MAX_EVENTS = 4


def _simulate(scene, t1, q0, qd0, args, ts):
    """A contact run at rtol = atol = 1e-12 (the transition times to 1e-9)."""
    return cjax.simulate(
        scene.system(),
        (0.0, t1),
        q0,
        qd0,
        args,
        saveat=cjax.SaveAt(ts=ts, multipliers=True),
        max_events=MAX_EVENTS,
        stepsize_controller=diffrax.PIDController(rtol=1e-12, atol=1e-12),
        throw=False,
    )


def _incline(v0, t1, args):
    q0, qd0 = incline_block.state(0.0, v0)
    return _simulate(incline_block, t1, q0, qd0, args, t1[None])


def _disk(v0, t1, args):
    q0, qd0 = sliding_disk.state(v0, args)
    return _simulate(sliding_disk, t1, q0, qd0, args, t1[None])


def _cylinders(theta0, t1, args):
    q0, qd0 = cylinders.state(theta0, jnp.zeros_like(theta0), args)
    return _simulate(cylinders, t1, q0, qd0, args, t1 * jnp.linspace(0.0, 1.0, 121))


def _rod(theta, v, t1, args):
    q0, qd0 = painleve_rod.state(theta, v, args)
    return _simulate(painleve_rod, t1, q0, qd0, args, jnp.stack([0.0 * t1, t1]))


INCLINE = Program("friction_incline", lambda: _incline)
DISK = Program("friction_disk", lambda: _disk)
CYLINDERS = Program("friction_cylinders", lambda: _cylinders)
ROD = Program("friction_rod", lambda: _rod)


def build(label: str, mu_s: float, mu_k: float, theta0: float, v0: float) -> list:
    if not (0 < mu_k <= mu_s < 4 / 3 and 0 < theta0 < math.pi / 2 and v0 > 0):
        raise ValueError(
            "needs 0 < mu_k <= mu_s < 4/3 (the Painleve rod runs below its critical "
            "coefficient 4/3), 0 < theta0 < pi/2 and v0 > 0."
        )
    jobs = []

    # The block, launched uphill on a slope it cannot stay on (tan > mu_s) or can.
    theta = float(np.arctan(1.5 * mu_s))
    block = incline_block.default_args(theta=theta, mu_s=mu_s, mu_k=mu_k)
    t_stop = float(incline_block.stop_time(-v0, block))
    t_end = 2 * t_stop

    def finish_incline(traj):
        events = traj.events
        x = incline_block.displacement(jnp.asarray(t_end), -v0, block)
        return [
            Check("incline: stop time", events.time[0], t_stop, 1e-9),
            Check("incline: slips back (slip +1)", events.slip[0], 1.0, 0.0),
            Check("incline: position at 2 t_stop", traj.q[0, 0], x, 1e-9),
            Check(
                "incline: friction force -mu_k N",
                traj.multipliers[0, 1],
                incline_block.kinetic_friction(1.0, block),
                1e-9,
            ),
        ], {}

    jobs.append(Job(label, INCLINE, (*arrays(-v0, t_end), block), finish_incline))

    # The disk launched sliding without spin.
    disk = sliding_disk.default_args(mu_s=mu_s, mu_k=mu_k)
    t_roll = float(sliding_disk.slip_time(v0, 0.0, disk))

    def finish_disk(traj):
        return [
            Check(
                "disk: rolling from v0/(3 mu_k g)", traj.events.time[0], t_roll, 1e-9
            ),
            Check("disk: rolling speed 2 v0/3", traj.qd[0, 0], 2 * v0 / 3, 1e-9),
        ], {}

    jobs.append(Job(label, DISK, (*arrays(v0, 2 * t_roll), disk), finish_disk))

    # The lecture's two cylinders: slip before the frictionless detachment angle.
    args = cylinders.default_args(mu_s=mu_s, mu_k=mu_k)
    theta_s = float(cylinders.slip_angle(theta0, args))
    t_slip = float(cylinders.slip_time(theta0, args))
    theta_star = float(cylinders.detachment_angle(theta0, args))
    t_cylinders = 1.1 * float(cylinders.detachment_time(theta0, args))

    def finish_cylinders(traj):
        events = traj.events
        checks = [
            Check("cylinders: slip angle", events.q[0, 1], theta_s, 1e-9),
            Check("cylinders: slip time", events.time[0], t_slip, 1e-9),
            Check(
                "cylinders: slips before theta*",
                float(events.q[0, 1] < theta_star),
                1.0,
                0.0,
            ),
        ]

        def draw(fig):
            ax = fig.subplots()
            plot.multipliers(
                traj,
                against=lambda q, qd, t: q[1],
                against_label="angle of the line of centres theta1 [rad]",
                labels=["normal force $N$", "friction force $\\lambda_t$"],
                ax=ax,
            )
            th = np.linspace(theta0, theta_s, 100)
            ax.plot(th, -mu_s * cylinders.normal_force(th, theta0, args), "k:", lw=1,
                    label="$-\\mu_s N$ (the cone's edge)")  # fmt: skip
            ax.axvline(theta_s, color="C3", lw=1, label=f"slip at {theta_s:.6g}")
            ax.axvline(theta_star, color="0.5", lw=1, ls="--",
                       label=f"frictionless detachment {theta_star:.6g}")  # fmt: skip
            ax.legend(fontsize="small")
            ax.set_title(
                "two cylinders with friction: the contact slips before it lets go\n"
                f"(mu_s = {mu_s:g}, mu_k = {mu_k:g}, from rest at theta0 = "
                f"{theta0:g})",
                fontsize="medium",
            )

        return checks, {"friction_two_cylinders.png": draw}

    jobs.append(
        Job(
            label,
            CYLINDERS,
            (*arrays(theta0, t_cylinders), args),
            finish_cylinders,
        )
    )

    # The Painleve rod at tan(theta) = 2 (critical coefficient 4/3), its lower end
    # leading: run below (normal force at the start in closed form), refused above.
    theta = float(np.arctan(2.0))
    for mu, paradox in ((mu_k, False), (1.5, True)):
        rod = painleve_rod.default_args(mu_s=max(mu, mu_s), mu_k=mu)
        q0, qd0 = painleve_rod.state(theta, 1.0, rod)

        def finish_rod(traj, paradox=paradox, rod=rod, q0=q0, qd0=qd0, mu=mu):
            if paradox:
                status = traj.result == cjax.RESULTS.painleve_paradox
                return [
                    Check(f"rod: mu = {mu:g} > 4/3 refused", float(status), 1.0, 0.0)
                ], {}
            normal = painleve_rod.normal_force(q0, qd0, rod)
            return [
                Check(
                    f"rod: mu = {mu:g} runs, N(0)", traj.multipliers[0, 0], normal, 1e-9
                )
            ], {}

        jobs.append(
            Job(
                f"{label}(rod mu={mu:g})" if paradox else label,
                ROD,
                (*arrays(theta, 1.0, 0.05), rod),
                finish_rod,
                note="above the rod's critical coefficient 4/3: refused"
                if paradox
                else "",
                refused=paradox,
            )
        )
    return jobs


SCENE = Scene(
    "friction",
    "contacts with Coulomb friction (cjax.Coulomb on a Unilateral): a block stops on "
    "an incline and slides back, a disk launched sliding rolls from v0/(3 mu_k g), "
    "the two cylinders slip where alpha sin = mu_s((3 + alpha) cos - 2 cos theta0), "
    "the Painleve rod is refused above mu = 4/3",
    {
        "mu_s": Param(0.3, "static friction coefficient of every contact"),
        "mu_k": Param(0.2, "kinetic friction coefficient, 0 < mu_k <= mu_s"),
        "theta0": Param(0.3, "the cylinders' initial angle [rad], at rest"),
        "v0": Param(3.0, "launch speed of the block (uphill) and of the disk"),
    },
    build,
    picture="the two cylinders' normal and friction forces against the angle",
    title="contacts that stick and slip",
)
