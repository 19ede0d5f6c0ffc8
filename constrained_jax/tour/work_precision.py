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
    """Its `jobs()` record each method's errors and settings; once they have run
    and been timed (`Job.seconds`), `rows()`, `pictures()` and `summary()` report
    them."""

    picture = (
        "a work-precision diagram of the pendulum for Tsit5, Dopri8 and the "
        "variational integrator"
    )
    note = "the variational integrator's order, from the work-precision runs"

    def __init__(self):
        # method -> (tag, job) of each setting; (method, tag) -> its error, once run
        self.runs: dict[str, list[tuple[str, Job]]] = {}
        self.errors: dict[tuple[str, str], float] = {}

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
            self.runs[method] = []
            for setting in settings:
                rtol = setting if kind == "rtol" else 1e-10
                dt0 = period / setting if kind == "steps" else 0.0
                tag = f"{kind}={setting:g}"

                def finish(traj, method=method, tag=tag):
                    self.errors[method, tag] = max(
                        float(np.max(np.abs(np.asarray(traj.q[-1]) - q0))) / l,
                        float(np.max(np.abs(np.asarray(traj.qd[-1]))))
                        / math.sqrt(g * l),
                    )
                    return [], {}

                inputs = (theta, *arrays(PERIODS), args, *arrays(rtol, dt0))
                label = f"work-precision {method} {tag}"
                job = Job(label, program, inputs, finish, repeats=5, note=self.note)
                self.runs[method].append((tag, job))
                jobs.append(job)
        return jobs

    @property
    def records(self) -> dict[str, tuple[list, list, list]]:
        """method -> (errors, seconds, tags), for `plot.work_precision`."""
        records = {}
        for method, runs in self.runs.items():
            # An exact zero (never seen) would not fit a log scale: floor it.
            errors = [
                max(self.errors[method, tag], np.finfo(np.float64).eps)
                for tag, _ in runs
            ]
            records[method] = (
                errors,
                [job.seconds for _, job in runs],
                [t for t, _ in runs],
            )
        return records

    def rows(self) -> list[Row]:
        """The variational integrator's convergence order, the slope of log(error)
        against log(steps), against its theory (2)."""
        errors, _, tags = self.records["variational (RATTLE, order 2)"]
        steps = np.asarray([float(t.split("=")[1]) for t in tags])
        slope = float(-np.polyfit(np.log(steps), np.log(np.asarray(errors)), 1)[0])
        return [Row("work-precision", "RATTLE order (slope)", slope, 2.0, 0.05)]

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
        lines = [
            f"  {method:<30} {tag:<12} error {self.errors[method, tag]:9.2e} "
            f"{job.seconds * 1e3:9.3f} ms"
            for method, runs in self.runs.items()
            for tag, job in runs
        ]
        return (
            f"\nwork-precision (pendulum from theta0 = {THETA0:g}, state error "
            f"after {PERIODS} periods, median of 5 runs):\n" + "\n".join(lines)
        )
