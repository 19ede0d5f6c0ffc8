"""Write `04_speed_accuracy.ipynb` (stored without outputs).

python notebooks/_make_04.py
"""

from _cells import code, md, write


CELLS = [
    md(
        r"""
# 4. Speed against accuracy

`cjax.simulate` integrates the constrained equations of motion at the level of
accelerations: at every evaluation of the vector field it solves

$$\begin{pmatrix} M & -A^T \\ A & 0 \end{pmatrix}
\begin{pmatrix} \ddot q \\ \lambda \end{pmatrix} =
\begin{pmatrix} b \\ -(\dot A \dot q + \dot a) \end{pmatrix}$$

and hands $(\dot q, \ddot q)$ to a diffrax solver. Three questions decide how to run
it:

1. **Which solver and which tolerance?** A work-precision diagram: the error at the
   final time against the wall time, for several solvers and tolerances.
2. **How to keep the constraints?** The equations above impose only
   $\ddot G = 0$, so truncation and round-off errors make $G$ drift. `Unstabilized`,
   `Baumgarte` and `Projection` handle that differently.
3. **What about long runs?** A symplectic, constraint-preserving variational
   integrator (RATTLE) keeps the energy error bounded for ever, where a standard
   solver's error grows.

The test problem is the pendulum in Cartesian coordinates, $q = (x, y)$,
$L = \tfrac12 m|\dot q|^2 - mgy$, $G = \sqrt{x^2 + y^2} - l = 0$
(`cjax.scenes.pendulum`), released from rest at $\theta_0$. Its period is known in
closed form,

$$T = 4\sqrt{l/g}\;K\big(\sin(\theta_0/2)\big),$$

with $K$ the complete elliptic integral of the first kind. A quarter period after the
release the pendulum passes through the bottom, $q(T/4) = (0, -l)$ exactly: the error
is $|q(T/4) - (0, -l)|$. (Not after a full period: there the pendulum is at a turning
point, where the position is stationary, so an $O(h^2)$ error in the phase shows only
as an $O(h^4)$ error in the position, and a second-order method looks fourth-order.)

Wall times are medians of a few runs after compilation, on whatever machine runs
this notebook (they are noisy on a busy one; the step counts are not).
"""
    ),
    code(
        """
import jax

import constrained_jax as cjax


# Compiled programs are kept on disk (`~/.cache/constrained_jax/jax`): a second run
# of the notebook skips most of the compilation. CONSTRAINED_JAX_COMPILATION_CACHE=0
# turns it off. The `simulate` programs are kept too with the library's diffrax patch
# (`use_diffrax_patch`: without it they hold diffrax's host callbacks, which the
# cache does not store; the results are the same). Where compilation dominates,
# `cjax.settings.use_fast_compilation()` here, before the first computation,
# compiles about 2x faster (XLA:CPU's older code generator; the programs run up to
# 27 % slower), and `cjax.settings.use_loop_kernels()` compiles each small
# integration loop into one function (one trajectory 1.7-5x faster, see the
# README's "Faster single trajectories"). This notebook keeps XLA's defaults: the
# wall times below are those of XLA's default settings.
cjax.settings.use_diffrax_patch()
cjax.enable_compilation_cache()
jax.config.update("jax_enable_x64", True)
"""
    ),
    code(
        """
import time

import diffrax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import constrained_jax as cjax
from constrained_jax.scenes import pendulum


system = pendulum.system()
args = pendulum.default_args(m=1.0, g=9.81, l=1.0)
theta0 = 1.0
q0, qd0 = pendulum.state(jnp.asarray(theta0), jnp.asarray(0.0), args)
period = float(pendulum.period(theta0, args))
bottom = jnp.array([0.0, -1.0])  # where the pendulum is at t = T/4
print(f"period T = {period:.15f} s (small angles: {2 * np.pi / 9.81**0.5:.15f} s)")


def timed(fn, *inputs, repeats=5):
    \"""`fn(*inputs)` once to compile, then the median wall time of `repeats` runs.\"""
    out = jax.block_until_ready(fn(*inputs))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*inputs))
        times.append(time.perf_counter() - start)
    return out, float(np.median(times))
"""
    ),
    md(
        r"""
## A work-precision diagram

Three explicit Runge-Kutta pairs of orders 3, 5 and 8 (`Bosh3`, `Tsit5`, `Dopri8`)
with an adaptive step, at tolerances `rtol = atol` from $10^{-4}$ to $10^{-10}$ (the
tolerance is a traced argument: one compilation per solver); and the variational
integrator at fixed steps $h = T/16, \dots, T/256$ (also traced). Higher order means
fewer steps for the same accuracy; the variational integrator is second order, so it
is not the tool for one accurate period (its strength is below).
"""
    ),
    code(
        """
tolerances = [1e-4, 1e-6, 1e-8, 1e-10]
solvers = {
    "Bosh3": diffrax.Bosh3(),
    "Tsit5": diffrax.Tsit5(),
    "Dopri8": diffrax.Dopri8(),
}
final_only = cjax.SaveAt(t1=True, multipliers=False, energy=False, violation=False)


def quarter_period(solver):
    @jax.jit
    def run(tol):
        traj = cjax.simulate(
            system,
            (0.0, period / 4),
            q0,
            qd0,
            args,
            solver=solver,
            stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol),
            saveat=final_only,
        )
        return jnp.linalg.norm(traj.q[-1] - bottom), traj.stats["num_steps"]

    return run


records, steps = {}, {}
for name, solver in solvers.items():
    run = quarter_period(solver)
    results = [timed(run, jnp.asarray(tol)) for tol in tolerances]
    errors = [float(out[0]) for out, _ in results]
    seconds = [s for _, s in results]
    steps[name] = [int(out[1]) for out, _ in results]
    records[name] = (errors, seconds, [f"{tol:.0e}" for tol in tolerances])
    print(f"{name:7s} errors {np.array(errors)}  steps {steps[name]}")


@jax.jit
def variational(h):
    traj = cjax.simulate(
        system,
        (0.0, period / 4),
        q0,
        qd0,
        args,
        solver=cjax.VariationalIntegrator(),
        dt0=h,
        saveat=final_only,
    )
    return jnp.linalg.norm(traj.q[-1] - bottom)


divisions = [16, 32, 64, 128, 256]  # steps per period
results = [timed(variational, jnp.asarray(period / n)) for n in divisions]
records["RATTLE"] = (
    [float(e) for e, _ in results],
    [s for _, s in results],
    [f"T/{n}" for n in divisions],
)
print("RATTLE  errors", np.array(records["RATTLE"][0]))
"""
    ),
    code(
        """
for name in solvers:
    errors = np.array(records[name][0])
    # Tighter tolerance, smaller error.
    assert np.all(np.diff(errors) < 0), (name, errors)
    assert errors[-1] < 1e-4 * errors[0], (name, errors)
# Higher order, fewer steps at the same tolerance.
assert steps["Dopri8"][-1] < steps["Tsit5"][-1] < steps["Bosh3"][-1], steps
# The variational integrator is second order: error ~ h^2.
rattle = np.array(records["RATTLE"][0])
order = np.polyfit(np.log(1 / np.array(divisions)), np.log(rattle), 1)[0]
print(f"RATTLE: observed order {order:.3f}")
assert 1.8 < order < 2.2

ax = cjax.plot.work_precision(records, annotate=True)
ax.set_ylabel("$|q(T/4) - (0, -l)|$")
ax.set_title(f"pendulum, theta0 = {theta0}: error against wall time");
"""
    ),
    md(
        r"""
## Keeping the constraint: stabilizations

Integrating $\ddot G = 0$ lets errors in $G$ and $\dot G$ grow (a constant error in
$\dot G$ makes $G$ grow linearly, and so on). Three strategies, each an object passed
to `simulate`:

- `cjax.Unstabilized()`: integrate as is; the drift is reported in
  `traj.violation`.
- `cjax.Baumgarte(alpha, beta)`: replace $\ddot G = 0$ by
  $\ddot G + 2\alpha\dot G + \beta^2 G = 0$, a damped oscillator for the violation.
- `cjax.Projection()`: after every step, project $q$ onto $G = 0$ and $\dot q$ onto
  $\dot G = 0$ (closest points in the kinetic-energy metric), so $|r - l|$ stays at
  round-off.

Tsit5 at `rtol = atol = 1e-6` for 50 periods:
"""
    ),
    code(
        """
periods = 50
ts = jnp.linspace(0.0, periods * period, 501)
stabilizations = {
    "Unstabilized": cjax.Unstabilized(),
    "Baumgarte(10, 10)": cjax.Baumgarte(alpha=10.0, beta=10.0),
    "Projection": cjax.Projection(),
}


def long_run(stabilization):
    @jax.jit
    def run(q0, qd0):
        return cjax.simulate(
            system,
            (0.0, ts[-1]),
            q0,
            qd0,
            args,
            solver=diffrax.Tsit5(),
            stabilization=stabilization,
            stepsize_controller=diffrax.PIDController(rtol=1e-6, atol=1e-6),
            saveat=cjax.SaveAt(ts=ts, multipliers=False),
        )

    return run


drift, energy_error = {}, {}
for name, stabilization in stabilizations.items():
    traj, seconds = timed(long_run(stabilization), q0, qd0, repeats=3)
    drift[name] = np.abs(np.asarray(traj.violation["position"][:, 0]))
    energy_error[name] = np.abs(np.asarray(traj.energy - traj.energy[0]))
    print(
        f"{name:18s} max |r - l| = {drift[name].max():.1e}, "
        f"max energy error = {energy_error[name].max():.1e}, "
        f"{int(traj.stats['num_steps'])} steps, {1e3 * seconds:.1f} ms"
    )
"""
    ),
    code(
        """
eps = np.finfo(np.float64).eps
tenth = len(ts) // 10
unstabilized = drift["Unstabilized"]
# Unstabilized: the violation keeps growing.
assert unstabilized[-tenth:].max() > 10 * unstabilized[:tenth].max()
# Baumgarte damps it: far below the unstabilized drift at the end.
assert drift["Baumgarte(10, 10)"][-1] < 1e-2 * unstabilized[-1]
# Projection: |r - l| at round-off all along.
assert drift["Projection"].max() <= 10 * eps

fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4))
for name in stabilizations:
    # Exact zeros (Projection) are drawn at the round-off floor eps.
    left.semilogy(ts / period, np.maximum(drift[name], eps), label=name)
    right.semilogy(ts[1:] / period, np.maximum(energy_error[name][1:], eps), label=name)
left.set_xlabel("t / T")
left.set_ylabel("|r - l|")
left.set_title("constraint violation (Tsit5, tol 1e-6)")
left.legend()
right.set_xlabel("t / T")
right.set_ylabel("|E(t) - E(0)|")
right.set_title("energy error")
right.legend();
"""
    ),
    md(
        r"""
## Long horizons: the variational integrator

`cjax.VariationalIntegrator()` (RATTLE) discretizes the action, not the equations of
motion: each step extremizes a discrete action subject to the constraints at the new
position, and the velocities are projected onto the tangent space. It is symplectic
and keeps $G = 0$ to round-off at every step. By backward error analysis it
conserves a modified energy $\tilde E = E + O(h^2)$ up to terms exponentially small
in $1/h$, so its energy error stays bounded over exponentially long times, whereas a
non-symplectic method (even with projection) accumulates a drift.

Both at the same fixed step $h = T/20$ for 200 periods. At this step Tsit5 is far more
accurate for a while (fifth order against second); but its error grows linearly,
while the variational integrator's oscillates in a fixed band.
"""
    ),
    code(
        """
h = period / 20
ts = jnp.linspace(0.0, 200 * period, 2001)
saveat = cjax.SaveAt(ts=ts, multipliers=False)
rattle = cjax.simulate(
    system,
    (0.0, ts[-1]),
    q0,
    qd0,
    args,
    solver=cjax.VariationalIntegrator(),
    dt0=h,
    saveat=saveat,
)
tsit5 = cjax.simulate(
    system,
    (0.0, ts[-1]),
    q0,
    qd0,
    args,
    solver=diffrax.Tsit5(),
    stabilization=cjax.Projection(),
    stepsize_controller=diffrax.ConstantStepSize(),
    dt0=h,
    saveat=saveat,
)
mgl = float(args["m"] * args["g"] * args["l"])
tenth = len(ts) // 10
growth = {}
for name, traj in [("RATTLE", rattle), ("Tsit5 + Projection", tsit5)]:
    error = np.abs(np.asarray(traj.energy - traj.energy[0])) / mgl
    growth[name] = error[-tenth:].max() / error[:tenth].max()
    print(
        f"{name:20s} energy error / mgl: first tenth {error[:tenth].max():.2e}, "
        f"last tenth {error[-tenth:].max():.2e} (x{growth[name]:.2f}); "
        f"max |r - l| = {np.abs(np.asarray(traj.violation['position'])).max():.1e}"
    )
"""
    ),
    code(
        """
assert rattle.result == cjax.RESULTS.successful
assert np.abs(np.asarray(rattle.violation["position"])).max() <= 10 * eps
assert growth["RATTLE"] < 1.2  # bounded: no drift over 200 periods
assert growth["Tsit5 + Projection"] > 5  # grows (about linearly in t)

fig, ax = plt.subplots(figsize=(7, 4))
for name, traj in [("RATTLE", rattle), ("Tsit5 + Projection", tsit5)]:
    error = np.abs(np.asarray(traj.energy - traj.energy[0])) / mgl
    ax.semilogy(ts[1:] / period, np.maximum(error[1:], eps), label=name)
ax.set_xlabel("t / T")
ax.set_ylabel("|E(t) - E(0)| / mgl")
ax.set_title("energy error at the fixed step h = T/20")
ax.legend();
"""
    ),
    md(
        r"""
**Reading the diagrams.** Lower left is better in the work-precision diagram. The
step counts are deterministic (and asserted above); the wall times depend on the
machine. When this chapter was written (a 2-core CPU), Tsit5 was the cheapest at
every accuracy on this small problem: Dopri8 takes the fewest steps, but each step
(14 stages against 7) and each call cost more. `Projection` keeps the constraint at
round-off for the price of one extra linear solve per step; Baumgarte's extra terms
make the equations stiffer (more steps at the same tolerance). For very long runs at a
coarse step, the variational integrator's bounded energy error is the qualitative
property to have; its error band shrinks like $h^2$. The benchmarks in `benchmarks/`
(`dynamics.py`, `long_horizon.py`) measure the same trade-offs at a larger scale,
against SciPy and hand-written JAX.
"""
    ),
]


if __name__ == "__main__":
    write(CELLS, "04_speed_accuracy.ipynb")
