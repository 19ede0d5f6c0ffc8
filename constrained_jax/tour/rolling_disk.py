"""A vertical disk rolling without slipping (nonholonomic): the circle, the
centripetal multipliers and the energy against the closed form."""

import jax.numpy as jnp

import constrained_jax as cjax

from ..scenes import rolling_disk as scene
from ._entry import arrays, Check, Job, Param, Program, Scene, simulate


def _run(theta0, nu, omega, t1, args):
    q0, qd0 = scene.initial_state(theta0, nu, omega, args)
    saveat = cjax.SaveAt(t1=True, violation=False)
    return simulate(scene.system(), t1, q0, qd0, args, saveat)


PROGRAM = Program("rolling_disk", lambda: _run)


def build(
    label: str,
    theta0: float,
    nu: float,
    omega: float,
    t1: float,
    m: float,
    R: float,
    I_roll: float,
    I_turn: float,
) -> list[Job]:
    if not (omega != 0 and t1 > 0 and m > 0 and R > 0 and I_roll > 0 and I_turn > 0):
        raise ValueError(
            "needs omega != 0 (the closed form is a circle of radius "
            "R nu / omega), t1 > 0 and positive m, R, I_roll, I_turn."
        )
    args = scene.default_args(m=m, R=R, I_roll=I_roll, I_turn=I_turn)

    def finish(traj):
        q_ref, lam_ref = scene.closed_form(jnp.asarray(t1), theta0, nu, omega, args)
        energy = 0.5 * ((m * R**2 + I_roll) * nu**2 + I_turn * omega**2)
        radius = abs(R * nu / omega)
        checks = [
            Check("x(t1) (/radius)", traj.q[-1, 0], q_ref[0], 1e-7, radius),
            Check("y(t1) (/radius)", traj.q[-1, 1], q_ref[1], 1e-7, radius),
            Check(
                "|lambda| centripetal",
                jnp.linalg.norm(traj.multipliers[-1]),
                jnp.linalg.norm(lam_ref),
                1e-7,
            ),
            Check("energy(t1)", traj.energy[-1], energy, 1e-8),
        ]
        return checks, {}

    inputs = (*arrays(theta0, nu, omega, t1), args)
    return [Job(label, PROGRAM, inputs, finish)]


SCENE = Scene(
    "rolling_disk",
    "a vertical disk rolling without slipping (nonholonomic): a circle of radius "
    "R nu/omega, the centripetal multipliers, the energy",
    {
        "theta0": Param(0.3, "initial heading [rad]"),
        "nu": Param(2.0, "rolling rate phidot"),
        "omega": Param(0.7, "turning rate thetadot (nonzero)"),
        "t1": Param(6.0, "final time"),
        "m": Param(1.0, "mass"),
        "R": Param(0.5, "radius of the disk"),
        "I_roll": Param(0.125, "moment of inertia about the axle"),
        "I_turn": Param(0.0625, "moment of inertia about the vertical"),
    },
    build,
    title="a disk rolling without slipping (a nonholonomic constraint)",
)
