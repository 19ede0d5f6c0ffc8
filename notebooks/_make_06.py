"""Write `06_friction.ipynb` (stored without outputs).

python notebooks/_make_06.py
"""

from _cells import code, md, write


CELLS = [
    md(
        r"""
# 6. Friction: the two cylinders slip before they part

Chapter 3 let the upper cylinder roll *without slipping* until it leaves the lower
one. Rolling without slipping is a constraint, and its multiplier $\lambda_t$ is the
friction force that holds it. A real contact holds it only while that force stays
inside the friction cone,

$$|\lambda_t| \le \mu_s N, \qquad N = \lambda_1 \ge 0 \text{ the normal force}.$$

While rolling from rest at $\theta_0$ (chapter 3),
$N = Mg\,[(3+\alpha)\cos\theta - 2\cos\theta_0]/(1+\alpha)$ falls and
$|\lambda_t| = \alpha M g \sin\theta/(1+\alpha)$ grows, so the contact reaches the
cone's edge where

$$\alpha \sin\theta_s = \mu_s \left[(3+\alpha)\cos\theta_s - 2\cos\theta_0\right],$$

before the frictionless detachment angle $\theta^* = \arccos(2\cos\theta_0/(3+\alpha))$
for every finite $\mu_s$ (there $N = 0 < |\lambda_t|/\mu_s$). From $\theta_s$ on it
slides: the no-slip row is dropped and the kinetic force $\lambda_t = -\mu_k N$
opposes the slip, with $N$ the normal multiplier of the same solve. It leaves the
surface later, where $N$ falls through zero.

`cjax.Coulomb(tangent, mu_s, mu_k)` on the contact's `cjax.Unilateral` declares
this (`scenes.two_cylinders_friction`): `cjax.simulate` finds the slip (where
$|\lambda_t|$ reaches $\mu_s N$) and the release by root finds on the multipliers, as
it found the release in chapter 3.
"""
    ),
    code(
        """
import jax

import constrained_jax as cjax


# Compiled programs are kept on disk (`~/.cache/constrained_jax/jax`), see chapter 5.
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
import optax
import scipy.optimize

import constrained_jax as cjax
from constrained_jax import plot
from constrained_jax.scenes import two_cylinders_friction as cyl


CONTROLLER = diffrax.PIDController(rtol=1e-11, atol=1e-11)


def run(mu_s, mu_k, theta0, t1=1.2, ts=jnp.linspace(0.0, 1.2, 121), **kwargs):
    args = cyl.default_args(mu_s=mu_s, mu_k=mu_k)
    q0, qd0 = cyl.state(jnp.asarray(theta0), jnp.asarray(0.0), args)
    return cjax.simulate(
        cyl.system(),
        (0.0, t1),
        q0,
        qd0,
        args,
        saveat=cjax.SaveAt(ts=ts, multipliers=True),
        max_events=4,
        stepsize_controller=CONTROLLER,
        throw=False,
        **kwargs,
    )


mu_s, mu_k, theta0 = 0.3, 0.2, 0.3
args = cyl.default_args(mu_s=mu_s, mu_k=mu_k)
traj = run(mu_s, mu_k, theta0)
events = traj.events
theta_s = float(cyl.slip_angle(theta0, args))
theta_star = float(cyl.detachment_angle(theta0, args))
print(f"slip at theta = {float(events.q[0, 1]):.10f} (closed form {theta_s:.10f})")
print(f"released at {float(events.q[1, 1]):.6f} (frictionless {theta_star:.6f})")
assert traj.result == cjax.RESULTS.successful
assert float(events.slip[0]) == 1.0 and not bool(events.attached[1])
assert abs(float(events.q[0, 1]) - theta_s) < 1e-9
assert float(events.q[0, 1]) < float(events.q[1, 1]) < theta_star
"""
    ),
    code(
        """
fig, ax = plt.subplots(figsize=(7, 4))
plot.multipliers(
    traj,
    against=lambda q, qd, t: q[1],
    against_label=r"angle of the line of centres $\\theta_1$",
    labels=[r"normal force $N$", r"friction force $\\lambda_t$"],
    ax=ax,
)
th = np.linspace(theta0, theta_s, 100)
ax.plot(th, -mu_s * cyl.normal_force(th, theta0, args), "k:", label=r"$-\\mu_s N$")
ax.axvline(theta_s, color="C3", lw=1, label=r"slip $\\theta_s$")
ax.axvline(theta_star, color="0.5", ls="--", lw=1, label=r"frictionless $\\theta^*$")
ax.legend(fontsize="small");
"""
    ),
    md(
        r"""
## 6.1 The slip angle against $\mu_s$, in one batch

`jax.vmap` over the coefficients runs contacts that slip early and contacts that
roll almost to $\theta^*$ in one compiled call (the contact mode is data, not a
branch). Each lane's first event is its slip; the release is the event after which
the group is no longer attached. The sliding phase is checked against an
independent integration of the hand-derived sliding equations
(`cyl.slip_and_detachment`, SciPy's DOP853 at $10^{-13}$).
"""
    ),
    code(
        """
mus = jnp.geomspace(0.12, 20.0, 16)


def angles(mu):
    ev = run(mu, 0.7 * mu, theta0, ts=jnp.array([1.2])).events
    released = jnp.argmax(jnp.invert(ev.attached) & (jnp.arange(4) < ev.count))
    return ev.q[0, 1], ev.q[released, 1]


slip, detach = jax.jit(jax.vmap(angles))(mus)
closed = jax.vmap(lambda m: cyl.slip_angle(theta0, cyl.default_args(mu_s=m)))(mus)
print("largest slip-angle error:", float(jnp.max(jnp.abs(slip - closed))))
assert float(jnp.max(jnp.abs(slip - closed))) < 1e-8
assert bool(jnp.all((slip < detach) & (slip < theta_star)))
for i in (0, 8):
    m = float(mus[i])
    reference = cyl.slip_and_detachment(theta0, cyl.default_args(mu_s=m, mu_k=0.7 * m))
    assert abs(float(detach[i]) - reference.theta_detach) < 1e-7, i

fig, ax = plt.subplots(figsize=(7, 4))
ax.semilogx(mus, slip, "o", label=r"slip $\\theta_s$ (simulated)")
ax.semilogx(mus, closed, "k-", lw=1, label="closed form")
ax.semilogx(mus, detach, "s", label=r"release, $\\mu_k = 0.7 \\mu_s$ (simulated)")
ax.axhline(theta_star, color="0.5", ls="--", label=r"frictionless $\\theta^*$")
ax.set_xlabel(r"$\\mu_s$")
ax.set_ylabel("angle [rad]")
ax.legend(fontsize="small");
"""
    ),
    md(
        r"""
## 6.2 Fitting $\mu_s$ to observed slip angles

Where a cylinder starts to slip measures $\mu_s$. Five slip angles, observed from
five starting angles with noise $\sigma = 0.002$ rad, are fitted with `cjax.fit`
(quasi-Newton, forward-mode derivatives, as in chapter 5). The model simulates each
run and reads its first event: $\partial\theta_s/\partial\mu_s$ flows through the
event's root find. The fit is checked against the truth (within three standard
errors) and against SciPy's least squares on the closed form.
"""
    ),
    code(
        """
mu_true, sigma = 0.4, 0.002
starts = jnp.linspace(0.1, 0.5, 5)
truth = jax.vmap(lambda t0: cyl.slip_angle(t0, cyl.default_args(mu_s=mu_true)))(starts)
noise = sigma * jax.random.normal(jax.random.key(6), starts.shape)
data = {"theta0": starts, "angle": truth + noise}


def loss(params, data):
    def one(t0):
        # (Forward-mode derivatives: diffrax's default adjoint is reverse-mode only.)
        return run(
            params["mu_s"], 0.5 * params["mu_s"], t0, ts=jnp.array([1.2]),
            adjoint=diffrax.ForwardMode(),
        )  # fmt: skip

    model = jax.vmap(one)(data["theta0"]).events.q[:, 0, 1]
    return 0.5 * jnp.sum(((model - data["angle"]) / sigma) ** 2)


QUASI_NEWTON = optax.lbfgs(optax.linear_schedule(0.1, 1.0, 4), linesearch=None)
fitted = cjax.fit(
    loss, {"mu_s": 0.2}, args=data, optimizer=QUASI_NEWTON, steps=40, gtol=1e-6,
    jac="fwd",
)  # fmt: skip
mu_fit = float(fitted.params["mu_s"])


def residuals(p):
    model = [cyl.slip_angle(t0, cyl.default_args(mu_s=p[0])) for t0 in starts]
    return (np.asarray(model) - np.asarray(data["angle"])) / sigma


slope = jax.vmap(jax.grad(lambda m, t0: cyl.slip_angle(t0, cyl.default_args(mu_s=m))),
                 in_axes=(None, 0))(mu_fit, starts)  # fmt: skip
standard_error = sigma / float(jnp.sqrt(jnp.sum(slope**2)))
mu_lsq = scipy.optimize.least_squares(residuals, [0.2], xtol=1e-15, ftol=1e-15).x[0]
print(f"mu_s = {mu_fit:.5f} +- {standard_error:.5f} (truth {mu_true}) after "
      f"{int(fitted.steps)} steps; least squares {mu_lsq:.8f}")  # fmt: skip
assert fitted.result == cjax.RESULTS.successful
assert abs(mu_fit - mu_true) < 3 * standard_error
assert abs(mu_fit - mu_lsq) < 1e-6
"""
    ),
]


if __name__ == "__main__":
    write(CELLS, "06_friction.ipynb")
