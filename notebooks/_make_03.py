"""Write `03_two_cylinders.ipynb` (stored without outputs).

python notebooks/_make_03.py
"""

from _cells import code, md, write


CELLS = [
    md(
        r"""
# 3. Two cylinders: constraint forces and detachment

A cylinder of mass $M$, radius $a$ and moment of inertia $I = \alpha M a^2$ rolls
without slipping on a fixed cylinder of radius $R$, starting from rest at the angle
$\theta_0$ from the top. Coordinates $q = (r, \theta_1, \theta_2)$: the distance
between the axes, the angle of the line of centres from the upward vertical, and
the rotation angle of the rolling cylinder. We keep $r$ as a coordinate, although
it is constant while the cylinders touch, so that its multiplier is the force that
keeps it constant: the normal force.

$$L = \tfrac{M}{2}\left(\dot r^2 + r^2 \dot\theta_1^2\right)
 + \tfrac{I}{2}\dot\theta_2^2 - M g r \cos\theta_1 .$$

The constraints in Pfaffian form $\sum_\sigma g_{j\sigma}\, dq_\sigma + h_j\, dt = 0$:

$$\begin{aligned}
 j = 1 \text{ (contact)}: &\quad dr = 0, \\
 j = 2 \text{ (no slip)}: &\quad (R + a)\, d\theta_1 - a\, d\theta_2 = 0,
\end{aligned}
\qquad
g = \begin{pmatrix} 1 & 0 & 0 \\ 0 & R + a & -a \end{pmatrix}, \quad h = 0 .$$

Lagrange's equations with multipliers, in this library's convention
$\frac{d}{dt}\frac{\partial L}{\partial \dot q_\sigma}
 - \frac{\partial L}{\partial q_\sigma} = \sum_j \lambda_j g_{j\sigma}$:

$$\begin{aligned}
 M \ddot r - M r \dot\theta_1^2 + M g \cos\theta_1 &= \lambda_1, \\
 M r^2 \ddot\theta_1 + 2 M r \dot r \dot\theta_1 - M g r \sin\theta_1
   &= (R + a)\,\lambda_2, \\
 I \ddot\theta_2 &= -a\, \lambda_2 .
\end{aligned}$$

On the surface ($r = R + a$), energy conservation gives
$\dot\theta_1^2 = \dfrac{2 g (\cos\theta_0 - \cos\theta_1)}{(1 + \alpha)(R + a)}$,
and the first equation the normal force

$$Q_r = \lambda_1 = \frac{M g \left[(3 + \alpha)\cos\theta_1 - 2\cos\theta_0\right]}
{1 + \alpha}.$$

The contact can push but not pull: the cylinder leaves the surface where $Q_r$
falls to zero, at the detachment angle

$$\theta^* = \arccos\frac{2 \cos\theta_0}{3 + \alpha},$$

($\arccos(2/3) \approx 48.2^\circ$ for a particle, $\alpha = 0$, from the top), at
a time given by an elliptic integral (`cyl.detachment_time`).
`cyl.contact_system()` declares both rows `cjax.Unilateral`: `cjax.simulate` finds
the moment where $\lambda_1$ falls through zero (an event and a root find), releases
the constraints and continues with the free flight.
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
# cache does not store; the results are the same).
cjax.settings.use_diffrax_patch()
cjax.enable_compilation_cache()
jax.config.update("jax_enable_x64", True)
"""
    ),
    code(
        """
import diffrax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import constrained_jax as cjax
from constrained_jax.scenes import two_cylinders as cyl


args = cyl.default_args(alpha=0.5)  # M = 1, a = 0.3, R = 1, g = 9.81
q = jnp.array([1.3, 0.2, 0.2 * (1 + 1.0 / 0.3)])
cyl.pfaffian_rows(q, 0.0, args)  # the lecture's g_{j sigma}
"""
    ),
    md(
        r"""
## Simulations over a grid of $(\alpha, \theta_0)$

One run: from rest at $\theta_0$, integrated to $1.5\,t^*$ with the multipliers
saved at 61 times up to $1.2\,t^*$ (past the release). `cjax.sweep` runs the same
function over a grid of inputs: it evaluates `jax.jit(jax.vmap(roll_off))` in
chunks of `batch_size` rows, sharded over the local devices, with a progress bar;
one compilation serves every chunk, and the results come back as numpy arrays with
a leading axis over the grid (here a batched `cjax.Trajectory`). With
`checkpoint="some/folder"` each finished chunk is also written to disk and a killed
sweep resumes where it stopped.

We sweep solid-cylinder-like to hoop-like inertia ($\alpha = 0.25, 0.5, 1$); $\alpha
= 0$ (no inertia) releases too, but its free flight is singular (nothing fixes the
spin of a massless cylinder once the no-slip constraint is gone), see
`tests/test_release.py`.
"""
    ),
    code(
        """
def roll_off(p):
    args = cyl.default_args(alpha=p["alpha"])
    theta0 = p["theta0"]
    q0, qd0 = cyl.state(theta0, jnp.zeros_like(theta0), args)
    t_star = cyl.detachment_time(theta0, args)
    return cjax.simulate(
        cyl.contact_system(),
        (0.0, 1.5 * t_star),
        q0,
        qd0,
        args,
        stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-10),
        saveat=cjax.SaveAt(
            ts=jnp.linspace(0.0, 1.2, 61) * t_star,
            multipliers=True,
            energy=False,
            violation=False,
        ),
    )


alphas = np.array([0.25, 0.5, 1.0])
theta0s = np.linspace(0.1, 1.1, 6)
alpha_grid, theta0_grid = np.meshgrid(alphas, theta0s, indexing="ij")
grid = {"alpha": alpha_grid.ravel(), "theta0": theta0_grid.ravel()}

trajs = cjax.sweep(roll_off, grid, batch_size=6)
trajs.q.shape  # (runs, saved times, coordinates)
"""
    ),
    md(
        r"""
## The normal force of one run

The multiplier $\lambda_1$ is the normal force $Q_r$. Against the angle, for
$\alpha = 0.5$, $\theta_0 = 0.3$: it falls from $M g \cos\theta_0$ through zero at
$\theta^*$, where the constraints are released (dashed line); in the free flight it
is zero.
"""
    ),
    code(
        """
i = 1 * len(theta0s) + 1  # alpha = 0.5, theta0 = 0.3
one = jax.tree.map(lambda x: x[i], trajs)
alpha, theta0 = grid["alpha"][i], grid["theta0"][i]
args = cyl.default_args(alpha=alpha)
theta_star = float(cyl.detachment_angle(theta0, args))

ax = cjax.plot.multipliers(
    one,
    against=lambda q, qd, t: q[1],
    against_label=r"$\\theta_1$",
    indices=0,
    labels=[r"$Q_r = \\lambda_1$, simulated"],
)
theta = np.linspace(theta0, theta_star, 200)
ax.plot(theta, cyl.normal_force(theta, theta0, args), "k:", label="closed form")
ax.set_title(
    rf"$\\alpha = {alpha}$, $\\theta_0 = {theta0:.2g}$: release at "
    rf"$\\theta^* = {theta_star:.4f}$"
)
ax.legend();
"""
    ),
    md(
        r"""
Checks against the closed forms, for every run of the grid (the integrator's
tolerance is $10^{-10}$; the bounds below allow two orders of magnitude for the
accumulated error): before the release the multiplier is the normal force; the
release happens at $\theta^*$ and at the elliptic-integral time $t^*$; after it the
released multipliers are exactly zero.
"""
    ),
    code(
        """
Mg = float(args["M"] * args["g"])
release = trajs.release
assert np.all(release.released) and not np.any(release.at_start)
assert not np.any(release.recontact)

runs = [cyl.default_args(alpha=al) for al in grid["alpha"]]
attached = trajs.ts < release.time[:, None]
normal = np.stack(
    [
        cyl.normal_force(trajs.q[k, :, 1], grid["theta0"][k], runs[k])
        for k in range(len(runs))
    ]
)
force_error = np.max(
    np.abs(np.where(attached, trajs.multipliers[..., 0] - normal, 0.0))
)
assert force_error < 1e-8 * Mg, force_error
assert np.all(np.where(attached[..., None], 0.0, trajs.multipliers) == 0.0)

t_star = np.array(
    [cyl.detachment_time(th0, a) for th0, a in zip(grid["theta0"], runs, strict=True)]
)
time_error = np.max(np.abs(release.time - t_star) / t_star)
assert time_error < 1e-8, time_error
print(f"normal force error {force_error:.1e} (M g = {Mg})")
print(f"release time relative error {time_error:.1e}")
"""
    ),
    md(
        r"""
## Release angle against starting angle

The simulated release angles of the whole grid against the closed form
$\theta^* = \arccos\left(2\cos\theta_0 / (3 + \alpha)\right)$. More inertia means
less speed at a given angle, so the cylinder stays on longer. Starting at the top
($\theta_0 \to 0$) the release angle tends to $\arccos(2/(3 + \alpha))$.
"""
    ),
    code(
        """
closed_form = np.arccos(2 * np.cos(grid["theta0"]) / (3 + grid["alpha"]))
angle_error = np.max(np.abs(release.q[:, 1] - closed_form))
assert angle_error < 1e-8, angle_error
print(f"largest release-angle error over the grid: {angle_error:.1e} rad")

fig, ax = plt.subplots()
dense = np.linspace(0.0, 1.2, 200)
for al in alphas:
    (line,) = ax.plot(
        dense, np.arccos(2 * np.cos(dense) / (3 + al)), label=rf"$\\alpha = {al}$"
    )
    rows = grid["alpha"] == al
    ax.plot(
        grid["theta0"][rows],
        release.q[rows, 1],
        "o",
        color=line.get_color(),
        markerfacecolor="none",
    )
ax.set_xlabel(r"starting angle $\\theta_0$")
ax.set_ylabel(r"release angle $\\theta^*$")
ax.set_title("lines: closed form; circles: simulated")
ax.legend();
"""
    ),
    md(
        r"""
## Contacts that come and go: a bouncing ball

After detachment the cylinder flies free; if it met a floor, the contact would be
made again. At re-contact the velocity jumps: Newton's restitution law
$A\dot q^+ = -e\, A \dot q^-$ on the contact's rows, with an impulse
$\Lambda$ along them, $M \Delta\dot q = A^T \Lambda$: the same KKT matrix as the
equations of motion, solved at the velocity level. A `cjax.Unilateral` with a
`restitution` and `simulate(..., max_events=N)` release and re-make contacts as often
as they occur, in one compiled call; `traj.events` lists them.

A ball dropped from rest at height $h$ first hits the floor at $t_1 = \sqrt{2h/g}$
with speed $v_1 = \sqrt{2gh}$; each bounce leaves with $e$ times the speed, so the
impact times form a geometric series,
$t_k = t_1 + \tfrac{2 v_1}{g}(e + e^2 + \dots + e^{k-1})$, which converges to
$t_\infty = t_1 + \tfrac{2 e v_1}{g(1-e)}$: infinitely many bounces in finite time
(Zeno). No integrator can take them all; `rest_speed` ends the series physically: an
impact slower than it is inelastic, and the ball rests on the floor (its multiplier is
then $mg$).
"""
    ),
    code(
        """
from constrained_jax.scenes import bouncing_ball


h0, rest_speed = 1.0, 0.3
es = jnp.array([0.5, 0.7, 0.8])
ts = jnp.linspace(0.0, 5.0, 1001)


@jax.jit
@jax.vmap
def bounce(e):
    args = bouncing_ball.default_args(e=e, rest_speed=rest_speed)
    q0, qd0 = bouncing_ball.state(h0)
    return cjax.simulate(
        bouncing_ball.system(),
        (0.0, 5.0),
        q0,
        qd0,
        args,
        saveat=cjax.SaveAt(ts=ts),
        max_events=24,
        throw=False,
    )


runs = bounce(es)
assert np.all(runs.result == cjax.RESULTS.successful)
for i, e in enumerate(np.asarray(es)):
    ball_args = bouncing_ball.default_args(e=e)
    k_rest = bouncing_ball.rest_impact(h0, e, 9.81, rest_speed)
    t_rest = bouncing_ball.impact_time(k_rest, h0, ball_args)
    print(f"e = {e}: {int(runs.events.count[i])} impacts, rests at t = {t_rest:.6f}")
    assert int(runs.events.count[i]) == k_rest
    for k in (1, 2, 3, k_rest):
        np.testing.assert_allclose(
            runs.events.time[i, k - 1],
            bouncing_ball.impact_time(k, h0, ball_args),
            rtol=1e-9,
        )
    assert t_rest < bouncing_ball.zeno_time(h0, ball_args)
    # At rest on the floor: y = 0 and the floor pushes with m g.
    np.testing.assert_allclose(runs.q[i, -1, 1], 0.0, atol=1e-9)
    np.testing.assert_allclose(runs.multipliers[i, -1, 0], 9.81, rtol=1e-9)

fig, ax = plt.subplots(figsize=(8, 3.5), layout="constrained")
for i, e in enumerate(np.asarray(es)):
    ax.plot(ts, runs.q[i, :, 1], label=f"$e = {e}$")
ax.set_xlabel("$t$")
ax.set_ylabel("height $y$")
ax.legend();
"""
    ),
    md(
        r"""
## Larger sweeps

- `batch_size` sets the memory: only one chunk is on the devices at a time, however
  large the grid. It is rounded up to a multiple of the number of devices.
- Several devices (GPUs, or CPU devices forced with
  `XLA_FLAGS=--xla_force_host_platform_device_count=4`) share each chunk along its
  batch axis; pass `devices=` to choose them.
- `checkpoint="folder"` makes a long sweep resumable; the folder is refused (with a
  message) if it was written for other inputs, batch size, devices or function, and
  a damaged chunk file is recomputed.
- One long simulation has a progress meter of its own:
  `cjax.simulate(..., progress_meter=diffrax.TqdmProgressMeter())`.
"""
    ),
]


if __name__ == "__main__":
    write(CELLS, "03_two_cylinders.ipynb")
