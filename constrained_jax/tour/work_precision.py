"""The work-precision diagram of the tour: the pendulum's state error after
`PERIODS` periods against the wall time of a solve, for Tsit5, Dopri8 and the
variational integrator, and the latter's convergence order against its theory."""

import math

import numpy as np

from .. import plot
from ..scenes import pendulum
from . import pendulum as tour_pendulum
from ._entry import arrays, Job, Pictures, Row


THETA0 = 1.0
PERIODS = 10
METHODS = {
    # label: (program, "rtol" or "steps" per period, settings)
    "Tsit5 (diffrax, order 5)": (
        tour_pendulum.TSIT5,
        "rtol",
        [1e-4, 1e-6, 1e-8, 1e-10],
    ),
    "Dopri8 (diffrax, order 8)": (
        tour_pendulum.DOPRI8,
        "rtol",
        [1e-4, 1e-6, 1e-8, 1e-10],
    ),
    "variational (RATTLE, order 2)": (
        tour_pendulum.VARIATIONAL,
        "steps",
        [50, 100, 200],
    ),
}


class WorkPrecision:
    """Its `jobs()` record each method's errors, times and settings; once they have
    run, `rows()`, `pictures()` and `summary()` report them."""

    picture = (
        "a work-precision diagram of the pendulum for Tsit5, Dopri8 and the "
        "variational integrator"
    )

    def __init__(self):
        # method -> (errors, times, tags)
        self.records: dict[str, tuple[list, list, list]] = {}
        self.lines: list[str] = []

    def jobs(self) -> list[Job]:
        """Jobs that time the pendulum over `PERIODS` periods from `theta0 = 1`, for
        each method and setting. The error is the state's, `max(|q(nT) - q0| / l,
        |qdot(nT)| / sqrt(g l))`: after whole periods the pendulum is back at rest
        where it started (a turning point, where the position alone would hide a
        phase error, since dx/dt = 0 there)."""
        args = pendulum.default_args()
        g, l = float(args["g"]), float(args["l"])
        theta = arrays(THETA0)[0]
        q0 = np.asarray(pendulum.state(theta, 0.0 * theta, args)[0])
        period = float(pendulum.period(theta, args))
        jobs = []
        for method, (program, kind, settings) in METHODS.items():
            self.records[method] = ([], [], [])
            for setting in settings:
                rtol = setting if kind == "rtol" else 1e-10
                dt0 = period / setting if kind == "steps" else 0.0
                tag = f"{kind}={setting:g}"

                def finish(traj, seconds, method=method, tag=tag):
                    err = max(
                        float(np.max(np.abs(np.asarray(traj.q[-1]) - q0))) / l,
                        float(np.max(np.abs(np.asarray(traj.qd[-1]))))
                        / math.sqrt(g * l),
                    )
                    ms = seconds * 1e3
                    self.lines.append(
                        f"  {method:<30} {tag:<12} error {err:9.2e} {ms:9.3f} ms"
                    )
                    errors, times, tags = self.records[method]
                    # An exact zero (never seen) would not fit a log scale: floor it.
                    errors.append(max(err, np.finfo(np.float64).eps))
                    times.append(seconds)
                    tags.append(tag)
                    return [], {}

                inputs = (theta, *arrays(PERIODS), args, *arrays(rtol, dt0))
                label = f"work-precision {method} {tag}"
                jobs.append(Job(label, program, inputs, finish, repeats=5))
        return jobs

    def rows(self) -> list[Row]:
        """The variational integrator's convergence order, the slope of log(error)
        against log(steps), against its theory (2)."""
        errors, times, tags = self.records["variational (RATTLE, order 2)"]
        steps = np.asarray([float(t.split("=")[1]) for t in tags])
        slope = float(-np.polyfit(np.log(steps), np.log(np.asarray(errors)), 1)[0])
        return [
            Row("work-precision", "RATTLE order (slope)", slope, 2.0, 0.05, sum(times))
        ]

    def pictures(self) -> Pictures:
        def draw(fig):
            ax = fig.subplots()
            plot.work_precision(self.records, annotate=True, ax=ax)
            ax.set_ylabel(f"state error after {PERIODS} periods")
            ax.set_xlabel("wall time per solve [s] (compiled, median of 5)")
            ax.set_title(
                f"pendulum (Cartesian, r = l), {PERIODS} periods from theta0 = "
                f"{THETA0:g}:\n"
                "error of (q/l, qdot/sqrt(gl)) against cost",
                fontsize="medium",
            )

        return {"work_precision.png": draw}

    def summary(self) -> str:
        return (
            f"\nwork-precision (pendulum from theta0 = {THETA0:g}, state error "
            f"after {PERIODS} periods, median of 5 runs):\n" + "\n".join(self.lines)
        )
