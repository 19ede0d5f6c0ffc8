"""Write `05_inverse_fits.ipynb` (stored without outputs).

python notebooks/_make_05.py
"""

from _cells import code, md, write


CELLS = [
    md(
        r"""
# 5. Inverse fits

The other chapters go from parameters to observations: given the inertia of a
cylinder, where does it leave the surface? An inverse problem goes back: given
observations, which parameters made them? With observations $d_i$ of known noise
$\sigma$ and a model $m_i(p)$, the maximum-likelihood parameters minimise

$$\mathcal{L}(p) = \tfrac12 \chi^2(p) = \tfrac12 \sum_i
\left(\frac{m_i(p) - d_i}{\sigma}\right)^2 .$$

`cjax.fit(loss, params0, args=data, optimizer=...)` minimises it with an optax
optimizer. The gradient $\nabla_p \mathcal{L}$ comes from automatic differentiation
*through the library's solvers*: through the release event of a simulation, through
the implicit function theorem on a KKT system, through an ODE solve. The loop runs
compiled (blocks of steps in one `jax.lax.scan`), with a progress bar between
blocks, and stops with a status instead of returning NaN if the loss stops being
finite.

**How well are the parameters determined?** Near the minimum the model is linear,
$r(p) \approx r(\hat p) + J (p - \hat p)$ with $J$ the Jacobian of the weighted
residuals $r_i = (m_i - d_i)/\sigma$, and the covariance of $\hat p$ is
$(J^\top J)^{-1}$: the standard errors are the square roots of its diagonal. Each
chapter below makes data from a closed form at known parameters plus Gaussian noise,
fits the library's model, and checks that the truth lies within three standard
errors, and that an independent least-squares solve on the closed form
(`scipy.optimize.least_squares`) lands on the same minimum.

**The optimizer.** These losses are sums of squares in one or two parameters with a
steep, narrow valley (the curvature is $\sim 1/\sigma^2$). Adam's steps have a fixed
size, so it creeps and then rattles around such a minimum; a quasi-Newton method
(L-BFGS) learns the curvature from successive gradients and converges in about ten
steps. We use it without a line search, the first steps damped (its first step has
unit length, so parameters should be of order one). Each parameter sits behind a
long computation, so the gradient is taken in forward mode (`jac="fwd"`, one
tangent per parameter), which compiles in about half the time of reverse mode.
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
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
import optax
import scipy.optimize

import constrained_jax as cjax
from constrained_jax.scenes import catenary, inverse, two_cylinders


QUASI_NEWTON = optax.lbfgs(optax.linear_schedule(0.1, 1.0, 4), linesearch=None)
FIT = dict(optimizer=QUASI_NEWTON, steps=40, gtol=1e-6, jac="fwd")


def jacobian(residuals, p, h=1e-6):
    \"\"\"Central differences of the weighted residuals (NumPy closed forms).\"\"\"
    p = np.asarray(p, dtype=float)
    columns = []
    for i in range(p.size):
        step = np.zeros_like(p)
        step[i] = h * max(abs(p[i]), 1.0)
        columns.append((residuals(p + step) - residuals(p - step)) / (2 * step[i]))
    return np.stack(columns, axis=-1)


def standard_errors(residuals, p):
    jac = jacobian(residuals, p)
    return np.sqrt(np.diag(np.linalg.inv(jac.T @ jac)))


def least_squares(residuals, p0):
    \"\"\"The independent solve: SciPy's Levenberg-Marquardt on the closed form.\"\"\"
    return scipy.optimize.least_squares(
        residuals, p0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15
    ).x
"""
    ),
    md(
        r"""
## 5.1 The rolling cylinder's inertia ratio, from where it lets go

A cylinder of mass $M$, radius $a$ and moment of inertia $I$ rolls without slipping
on a fixed cylinder of radius $R$, released from rest at the angle $\theta_0$ from
the top (chapter 3). The normal force
$Q_r = Mg\,[(3+\alpha)\cos\theta_1 - 2\cos\theta_0]/(1+\alpha)$, with the inertia
ratio $\alpha = I/(Ma^2)$, falls to zero at the detachment angle

$$\theta^* = \arccos\frac{2\cos\theta_0}{3+\alpha}.$$

A solid cylinder has $\alpha = 1/2$, a thin ring $\alpha = 1$. Watching where it
lets go from several starting angles measures $\alpha$: eight observed angles with
noise $\sigma = 0.005$ rad ($0.3°$).

**The model** does not use the formula. It simulates the unilateral contact
(`two_cylinders.contact_system()`: the contact and no-slip rows are released
together when the normal-force multiplier falls through zero, found by a root find
on the event) and reads the angle at release, `traj.release.q[1]`
(`inverse.detachment_angle`, the releases one after the other with `jax.lax.map`).
So $\partial\theta^*/\partial\alpha$ flows through the event.
"""
    ),
    code(
        """
alpha_true, sigma_angle = 0.5, 0.005
theta0 = np.linspace(0.2, 1.0, 8)
cylinder_data = inverse.detachment_data(
    jax.random.key(0), alpha_true, theta0, sigma_angle
)

cylinder_fit = cjax.fit(
    inverse.detachment_loss, {"alpha": 0.2}, args=cylinder_data, **FIT
)
alpha_fit = float(cylinder_fit.params["alpha"])
print(f"alpha = {alpha_fit:.5f} after {int(cylinder_fit.steps)} steps")
"""
    ),
    code(
        """
observed_angle = np.asarray(cylinder_data["angle"])


def cylinder_residuals(p):
    return (np.arccos(2 * np.cos(theta0) / (3 + p[0])) - observed_angle) / sigma_angle


(alpha_se,) = standard_errors(cylinder_residuals, [alpha_fit])
(alpha_lsq,) = least_squares(cylinder_residuals, [0.2])
print(f"alpha = {alpha_fit:.4f} +- {alpha_se:.4f} (truth {alpha_true})")
print(f"least squares {alpha_lsq:.8f}: fit - lsq = {alpha_fit - alpha_lsq:.0e}")
assert cylinder_fit.result == cjax.RESULTS.successful
assert abs(alpha_fit - alpha_true) < 3 * alpha_se
# The simulation (tolerances 1e-6) moves the minimum by ~1e-6 at most.
assert abs(alpha_fit - alpha_lsq) < 1e-5
"""
    ),
    code(
        """
fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.8))
grid = np.linspace(0.0, 1.1, 200)
for alpha, style, label in [
    (alpha_true, "k--", f"truth, alpha = {alpha_true}"),
    (alpha_fit, "C0-", f"fit, alpha = {alpha_fit:.3f}"),
]:
    args = two_cylinders.default_args(alpha=alpha)
    curve = two_cylinders.detachment_angle(jnp.asarray(grid), args)
    left.plot(grid, curve, style, label=label)
left.errorbar(theta0, observed_angle, sigma_angle, fmt="o", c="C1", label="observed")
left.set_xlabel(r"release angle $\\theta_0$")
left.set_ylabel(r"detachment angle $\\theta^*$")
left.legend()
right.semilogy(cylinder_fit.losses[: int(cylinder_fit.steps) + 1], "o-")
right.set_xlabel("L-BFGS step")
right.set_ylabel(r"loss $\\chi^2/2$")
fig.tight_layout()
"""
    ),
    md(
        r"""
## 5.2 A hanging chain's length and endpoint, from points on it

A chain of length $C$ hangs from $(0, 0)$ to $(1, y_R)$ (chapter 2): it minimises
its potential energy $\rho g \int y\,ds$ at fixed length $\int ds = C$, so it is the
catenary
$y = -\lambda/\rho g + (H/\rho g)\cosh(\rho g (x - a)/H)$, whose three constants
follow from the two ends and the length. Given noisy heights $y(x_i)$ at twelve
points (noise $\sigma = 0.005$), fit the length $C$ and the height $y_R$ of the
right end. (Not all three of $C$, $x_R$, $y_R$: the points only see the curve, and
the same curve ends anywhere along itself with the matching length.)

**The model** (`inverse.chain_heights`) hangs the chain with
`cjax.solve_functional` (the catenary functional with its length constraint,
`Chebyshev(24)` nodes) and evaluates the solution at the $x_i$. Its derivatives
with respect to $C$ (a constraint value) and $y_R$ (a boundary value) come from the
implicit function theorem on the discrete KKT system: no differentiation through
Newton's iterations.
"""
    ),
    code(
        """
chain_true, sigma_y = {"length": 1.5, "yr": 0.3}, 0.005
x_obs = np.linspace(0.05, 0.95, 12)
chain_data = inverse.chain_data(
    jax.random.key(2), chain_true["length"], chain_true["yr"], x_obs, sigma_y
)
chain_start = {"length": 1.3, "yr": 0.0}
chain_fit = cjax.fit(inverse.chain_loss, chain_start, args=chain_data, **FIT)
chain_p = np.array([float(chain_fit.params["length"]), float(chain_fit.params["yr"])])
print(f"C = {chain_p[0]:.5f}, yR = {chain_p[1]:.5f} after {int(chain_fit.steps)} steps")
"""
    ),
    code(
        """
observed_y = np.asarray(chain_data["y"])


def chain_curve(p, x):
    return catenary.closed_form(0.0, 0.0, 1.0, p[1], p[0])["y"](x)


def chain_residuals(p):
    return (chain_curve(p, x_obs) - observed_y) / sigma_y


chain_se = standard_errors(chain_residuals, chain_p)
chain_lsq = least_squares(chain_residuals, [1.3, 0.0])
truth = np.array([chain_true["length"], chain_true["yr"]])
rows = zip(["C", "yR"], chain_p, chain_se, truth, chain_lsq, strict=True)
for name, value, se, t, lsq in rows:
    print(f"{name} = {value:.4f} +- {se:.4f} (truth {t}); fit - lsq: {value - lsq:.0e}")
assert chain_fit.result == cjax.RESULTS.successful
assert np.all(np.abs(chain_p - truth) < 3 * chain_se)
# Chebyshev(24) is exact to ~1e-12 here: the same minimum to the solver's precision.
assert np.all(np.abs(chain_p - chain_lsq) < 1e-8)
"""
    ),
    code(
        """
fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.8))
x_fine = np.linspace(0.0, 1.0, 200)
left.plot(x_fine, chain_curve(truth, x_fine), "k--", label="truth")
left.plot(x_fine, chain_curve(chain_p, x_fine), "C0-", label="fit")
left.errorbar(x_obs, observed_y, yerr=sigma_y, fmt="o", color="C1", label="observed")
left.set_xlabel("x")
left.set_ylabel("y")
left.set_aspect("equal")
left.legend()
right.semilogy(chain_fit.losses[: int(chain_fit.steps) + 1], "o-")
right.set_xlabel("L-BFGS step")
right.set_ylabel(r"loss $\\chi^2/2$")
fig.tight_layout()
"""
    ),
    md(
        r"""
(The curves are the closed forms at the true and the fitted parameters; the
library's model agrees with the closed form to about $10^{-12}$ here, and the
simulations of 5.1 and 5.3 to their tolerances: see `tests/test_fit.py`.)

## 5.3 A pendulum's length, from its trajectory

A pendulum of length $l$ released from rest at $\theta_0 = 0.8$ rad swings with the
angle $\sin(\theta/2) = k\,\mathrm{sn}(K(k) - \sqrt{g/l}\,t \mid k^2)$,
$k = \sin(\theta_0/2)$ (Jacobi's elliptic sine; period $4\sqrt{l/g}\,K(k)$). A
camera records the bob at twenty times over about one period, each coordinate with
noise $\sigma = 0.01$ m. The length enters twice: the size of the arc and, through
$\sqrt{g/l}$, the timing.

**The model** (`inverse.bob_positions`) simulates the pendulum in Cartesian
coordinates with the rod constraint $\sqrt{x^2+y^2} - l = 0$ (`pendulum.system()`)
and returns the positions at the observation times.
"""
    ),
    code(
        """
l_true, theta0_pendulum, sigma_q = 1.0, 0.8, 0.01
ts = np.linspace(0.1, 2.0, 20)
key = jax.random.key(1)
pendulum_data = inverse.pendulum_data(key, l_true, theta0_pendulum, ts, sigma_q)
pendulum_fit = cjax.fit(inverse.bob_loss, {"l": 0.8}, args=pendulum_data, **FIT)
l_fit = float(pendulum_fit.params["l"])
print(f"l = {l_fit:.5f} after {int(pendulum_fit.steps)} steps")
"""
    ),
    code(
        """
observed_q = np.asarray(pendulum_data["q"])


def bob_curve(l, t):
    theta = np.asarray(inverse.pendulum_angle(t, l, theta0_pendulum, 9.81))
    return l * np.stack([np.sin(theta), -np.cos(theta)], axis=-1)


def bob_residuals(p):
    return np.ravel((bob_curve(p[0], ts) - observed_q) / sigma_q)


(l_se,) = standard_errors(bob_residuals, [l_fit])
(l_lsq,) = least_squares(bob_residuals, [0.8])
print(f"l = {l_fit:.4f} +- {l_se:.4f} (truth {l_true}); fit-lsq {l_fit - l_lsq:.0e}")
assert pendulum_fit.result == cjax.RESULTS.successful
assert abs(l_fit - l_true) < 3 * l_se
# The simulation (tolerances 1e-8) moves the minimum by ~1e-8 at most.
assert abs(l_fit - l_lsq) < 1e-7
"""
    ),
    code(
        """
fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.8))
t_fine = np.linspace(0.0, 2.0, 300)
for i, name in enumerate(["x", "y"]):
    left.plot(t_fine, bob_curve(l_true, t_fine)[:, i], "k--", lw=1)
    left.plot(t_fine, bob_curve(l_fit, t_fine)[:, i], f"C{i}-", label=f"{name}, fit")
    left.errorbar(ts, observed_q[:, i], yerr=sigma_q, fmt="o", color=f"C{i}", ms=4)
left.set_xlabel("t")
left.set_ylabel("position (dashed: truth)")
left.legend()
right.semilogy(pendulum_fit.losses[: int(pendulum_fit.steps) + 1], "o-")
right.set_xlabel("L-BFGS step")
right.set_ylabel(r"loss $\\chi^2/2$")
fig.tight_layout()
"""
    ),
    md(
        r"""
## Notes

- `fit` compiles its loop once per loss function, optimizer and parameter structure;
  `args` (the data) and `params0` are traced, so fitting new data does not
  recompile. Keep the loss a module-level function and the optimizer one object.
- If the model fails (a simulation that does not release within its horizon, a
  chain shorter than the distance between its ends), the models here return NaN,
  and `fit` stops with `RESULTS.nonfinite` and the last finite parameters, instead
  of fitting garbage.
- Under `jax.vmap` (e.g. many synthetic data sets at once, to check the standard
  errors by Monte Carlo) the loop runs as one scan, without a progress bar.
"""
    ),
]


if __name__ == "__main__":
    write(CELLS, "05_inverse_fits.ipynb")
