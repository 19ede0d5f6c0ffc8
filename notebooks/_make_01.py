"""Write `01_lagrange_multipliers.ipynb` (stored without outputs).

python notebooks/_make_01.py
"""

from _cells import code, md, write


CELLS = [
    md(
        r"""
# 1. Lagrange multipliers

Extremize $F(x_1, \dots, x_n)$ subject to $k$ constraints $G_j(x) = 0$. At a
constrained extremum $x^*$ the gradient $\nabla F$ is a linear combination of the
$\nabla G_j$: any displacement along which $F$ would change to first order breaks a
constraint. So there are real numbers $\lambda_j$ with

$$\nabla F + \sum_{j=1}^k \lambda_j \nabla G_j = 0 \qquad (n \text{ equations}),
\qquad G_j = 0 \qquad (k \text{ equations}).$$

Equivalently, freely extremize $F^*(x; \lambda) = F(x) + \sum_j \lambda_j G_j(x)$
over all $n + k$ variables. `cjax.extremize(F, x0, args, constraints=G)` builds
these $n + k$ equations by automatic differentiation and solves them by Newton's
method; `sol.kind` classifies the result by the second-order conditions (the
Hessian of $F^*$ on the tangent space of the constraints).

This chapter: the lecture's cylinder, with every closed form checked, the envelope
theorem, the classification of all stationary points, a cap on its height (an
inequality); then a larger problem, the
hanging chain of $N$ rigid links, whose multipliers are the tensions in the links.
"""
    ),
    code(
        """
import jax

import constrained_jax as cjax


# Compiled programs are kept on disk (`~/.cache/constrained_jax/jax`): a second run
# of the notebook skips most of the compilation. CONSTRAINED_JAX_COMPILATION_CACHE=0
# turns it off.
cjax.enable_compilation_cache()
jax.config.update("jax_enable_x64", True)
"""
    ),
    code(
        """
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
import scipy.optimize

import constrained_jax as cjax
from constrained_jax.scenes import catenary
"""
    ),
    md(
        r"""
## The lecture's cylinder

Extremize the volume $V = \pi a^2 h$ of a cylinder of radius $a$ and height $h$
subject to

$$G(a, h) = 2\pi a + \frac{h^2}{b} - l = 0 \qquad (b, l \text{ fixed}).$$

With $V^* = \pi a^2 h + \lambda\,(2\pi a + h^2/b - l)$:

$$\frac{\partial V^*}{\partial a} = 2\pi a h + 2\pi\lambda = 0, \qquad
\frac{\partial V^*}{\partial h} = \pi a^2 + \frac{2}{b}\lambda h = 0, \qquad
\frac{\partial V^*}{\partial \lambda} = G = 0.$$

The first gives $\lambda = -ah$, the second then $a = 2h^2/(\pi b)$, and the
constraint $h^2 (4 + 1)/b = l$:

$$h = \sqrt{\frac{bl}{5}}, \qquad a = \frac{2l}{5\pi}, \qquad
\lambda = -\frac{2\, b^{1/2} l^{3/2}}{5^{3/2}\pi}, \qquad
V^* = \frac{4\, b^{1/2} l^{5/2}}{5^{5/2}\pi}.$$
"""
    ),
    code(
        """
def volume(x, args):
    a, h = x[0], x[1]
    return jnp.pi * a**2 * h


def constraint(x, args):
    a, h = x[0], x[1]
    return 2 * jnp.pi * a + h**2 / args["b"] - args["l"]


args = {"b": jnp.asarray(2.0), "l": jnp.asarray(1.5)}
sol = cjax.extremize(volume, jnp.array([0.1, 0.4]), args, constraints=constraint)
a, h = sol.x
(lam,) = sol.multipliers
print(f"a = {a:.15f}, h = {h:.15f}, lambda = {lam:.15f}, V = {sol.value:.15f}")
print(cjax.EXTREMUM[sol.kind])
"""
    ),
    code(
        """
b, l = float(args["b"]), float(args["l"])
closed = {
    "a": 2 * l / (5 * np.pi),
    "h": np.sqrt(b * l / 5),
    "lambda": -2 * b**0.5 * l**1.5 / (5**1.5 * np.pi),
    "V": 4 * b**0.5 * l**2.5 / (5**2.5 * np.pi),
}
assert sol.result == cjax.RESULTS.successful
np.testing.assert_allclose(a, closed["a"], rtol=1e-13)
np.testing.assert_allclose(h, closed["h"], rtol=1e-13)
np.testing.assert_allclose(lam, closed["lambda"], rtol=1e-12)
np.testing.assert_allclose(lam, -a * h, rtol=1e-12)  # from dV*/da = 0
np.testing.assert_allclose(sol.value, closed["V"], rtol=1e-13)
assert sol.kind == cjax.EXTREMUM.maximum
"""
    ),
    md(
        r"""
### Sign convention

The library solves $\nabla F + \sum_j \lambda_j \nabla G_j = 0$: the lecture's
convention, $F^* = F + \lambda \cdot G$, so its $\lambda$ is the lecture's,
$\lambda = -ah < 0$ here. Many optimization texts write the Lagrangian as
$F - \lambda \cdot G$ (stationarity $\nabla F = \lambda \nabla G$); their multiplier
is $-\lambda$. In the picture below, $\nabla V$ and $-\lambda \nabla G$ are the same
arrow, perpendicular to the constraint curve and to the level set of $V$ through the
extremum, which touch there.
"""
    ),
    code(
        """
grad_v = jax.grad(volume)(sol.x, args)
grad_g = jax.grad(constraint)(sol.x, args)
print("grad V =", grad_v, "  -lambda grad G =", -lam * grad_g)
np.testing.assert_allclose(grad_v + lam * grad_g, 0.0, atol=1e-13)

ax = cjax.plot.extremum_2d(volume, constraint, sol, args, span=(0.12, 0.35))
ax.set_xlabel("radius $a$")
ax.set_ylabel("height $h$")
ax.set_title("level sets of $V = \\\\pi a^2 h$ and the constraint $G = 0$");
"""
    ),
    md(
        r"""
### The envelope theorem

The extremal volume $V^*(b, l) = V(x^*(b, l))$ depends on the parameters. Since
$x^*$ is stationary for $F^*$, only the explicit dependence counts:

$$\frac{dV^*}{dl} = \frac{\partial F^*}{\partial l}
= \lambda \frac{\partial G}{\partial l} = -\lambda, \qquad
\frac{dV^*}{db} = \lambda \frac{\partial G}{\partial b} = -\lambda\frac{h^2}{b^2}.$$

The multiplier is the price of the constraint: the volume gained per unit of extra
budget $l$. From the closed form, $dV^*/dl = \tfrac52 V^*/l$ and
$dV^*/db = \tfrac12 V^*/b$. `extremize` is differentiable with respect to `args`
(by the implicit function theorem on the KKT system, not by unrolling Newton's
iterations), so `jax.grad` gives both derivatives.
"""
    ),
    code(
        """
def extremal_volume(args):
    return cjax.extremize(
        volume, jnp.array([0.1, 0.4]), args, constraints=constraint
    ).value


grads = jax.grad(extremal_volume)(args)
print("dV*/dl =", grads["l"], "  -lambda =", -lam)
print("dV*/db =", grads["b"], "  -lambda h^2/b^2 =", -lam * h**2 / b**2)
np.testing.assert_allclose(grads["l"], -lam, rtol=1e-11)
np.testing.assert_allclose(grads["l"], 2.5 * closed["V"] / l, rtol=1e-11)
np.testing.assert_allclose(grads["b"], -lam * h**2 / b**2, rtol=1e-11)
np.testing.assert_allclose(grads["b"], 0.5 * closed["V"] / b, rtol=1e-11)
"""
    ),
    md(
        r"""
### All the stationary points, and their kind

Nothing in the equations forbids $h < 0$ or $a \le 0$. Solving the constraint for
$a$, $a(h) = (l - h^2/b)/(2\pi)$, the volume along the constraint curve is a
function of one variable,

$$v(h) = \pi a(h)^2 h = \frac{h\,(l - h^2/b)^2}{4\pi}, \qquad
v'(h) = \frac{(l - h^2/b)(l - 5h^2/b)}{4\pi},$$

so there are four stationary points: $h = \pm\sqrt{bl/5}$ and $h = \pm\sqrt{bl}$
(where $a = 0$ and $\lambda = 0$). The sign of $v''(h)$ classifies each one. Newton's
method typically converges to the stationary point nearest its start; `sol.kind` is
judged from the reduced Hessian of $F^*$, independently of $v$.
"""
    ),
    code(
        """
def v(h):
    return h * (l - h**2 / b) ** 2 / (4 * jnp.pi)


expected = {1: cjax.EXTREMUM.minimum, -1: cjax.EXTREMUM.maximum}
for start in ([0.1, 0.4], [0.1, -0.4], [0.05, 1.9], [0.05, -1.9]):
    s = cjax.extremize(volume, jnp.array(start), args, constraints=constraint)
    curvature = jax.grad(jax.grad(v))(s.x[1])
    print(
        f"start {start}: (a, h) = ({s.x[0]: .6f}, {s.x[1]: .6f}), "
        f"lambda = {s.multipliers[0]: .6f}, v'' = {curvature: .4f}, "
        f"{cjax.EXTREMUM[s.kind]}"
    )
    assert s.result == cjax.RESULTS.successful
    np.testing.assert_allclose(jax.grad(v)(s.x[1]), 0.0, atol=1e-12)
    assert s.kind == expected[int(np.sign(curvature))]
"""
    ),
    md(
        r"""
### Inequalities: a cap on the height

Bounds and inequality constraints $H_i(x) \le 0$ get multipliers $\mu_i$ in the same
convention, $\nabla F + \lambda \cdot \nabla G + \mu \cdot \nabla H = 0$, with
complementarity $\mu_i H_i = 0$: an inequality that does not bind has $\mu_i = 0$.
Since the stationarity formula is the same whether $F$ is minimized or maximized,
$\mu \ge 0$ for `sense="minimize"` and $\mu \le 0$ for `sense="maximize"`.

Cap the height, $h \le h_{\max}$. Below $h^* = \sqrt{bl/5}$ the cap binds:
$h = h_{\max}$, $a = (l - h^2/b)/(2\pi)$ from $G$, and stationarity gives
$\lambda = -ah$ and $\mu = a(2h^2/b - \pi a) < 0$. Above it, the lecture's answer with
$\mu = 0$. By the envelope theorem, $dV^*/dh_{\max} = -\mu$: the multiplier is the
volume lost per unit of cap. `scenes.cylinder_volume.solve_capped` passes the cap as
`upper=(inf, h_max)`; below, a batch of caps under `jax.vmap` (the active set differs
between its members) and the envelope theorem by `jax.grad`.
"""
    ),
    code(
        """
from constrained_jax.scenes import cylinder_volume


h_star = np.sqrt(b * l / 5)
caps = jnp.linspace(0.3, 1.5, 12) * h_star  # no cap exactly at h*


def capped_volume(h_max):
    return cylinder_volume.solve_capped(b, l, h_max).value


capped = jax.jit(jax.vmap(lambda c: cylinder_volume.solve_capped(b, l, c)))(caps)
ref = cylinder_volume.capped_closed_form(b, l, caps)
mu = capped.inequality_multipliers[:, 1]  # rows: upper bounds on (a, h)
assert np.all(capped.result == cjax.RESULTS.successful)
np.testing.assert_allclose(capped.x[:, 1], ref["h"], rtol=1e-10)
np.testing.assert_allclose(capped.multipliers[:, 0], ref["multiplier"], rtol=1e-10)
np.testing.assert_allclose(mu, ref["cap_multiplier"], rtol=1e-9, atol=1e-13)
np.testing.assert_array_equal(capped.active[:, 1], caps < h_star)
assert np.all(mu <= 0)  # maximizing
dv = jax.jit(jax.vmap(jax.grad(capped_volume)))(caps)
np.testing.assert_allclose(dv, -mu, rtol=1e-9, atol=1e-13)  # envelope theorem

fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.5), layout="constrained")
left.plot(caps / h_star, capped.value, "o-")
left.axhline(closed["V"], color="k", ls="--", label="no cap")
left.set_xlabel("$h_{\\\\max} / h^*$")
left.set_ylabel("$V^*$")
left.legend()
right.plot(caps / h_star, -mu, "o", label="$-\\\\mu$")
right.plot(caps / h_star, dv, "x", label="$dV^*/dh_{\\\\max}$ (jax.grad)")
right.set_xlabel("$h_{\\\\max} / h^*$")
right.legend();
"""
    ),
    md(
        r"""
## A larger problem: the hanging chain

A chain of $N$ rigid links of length $\ell = L/N$ hangs between the fixed points
$(0, 0)$ and $(D, 0)$, $D < L$. Each link weighs $W/N$; lumping half of each link's
weight at either end puts a weight $w = W/N$ on each of the $N - 1$ joints
$p_j = (x_j, y_j)$. Minimize the potential energy subject to $N$ constraints, one per
link:

$$F = w \sum_{j=1}^{N-1} y_j, \qquad G_i = |p_{i+1} - p_i| - \ell = 0
\quad (i = 0, \dots, N - 1;\ p_0, p_N \text{ the fixed ends}).$$

With $u_i$ the unit vector along link $i$, $\nabla_{p_j} G_{j-1} = u_{j-1}$ and
$\nabla_{p_j} G_j = -u_j$, so the stationarity condition at joint $j$ reads

$$w\,\hat y + \lambda_{j-1} u_{j-1} - \lambda_j u_j = 0 ,$$

the balance of forces on the joint if link $i$ pulls on its ends with the tension
$T_i = \lambda_i$: **the multipliers are the tensions**. Their horizontal components
are all equal, $\lambda_i \cos\theta_i = H$, and the vertical balance gives
$H(\tan\theta_j - \tan\theta_{j-1}) = w$: the slopes of the links form an arithmetic
progression. With level ends the chain is symmetric, so

$$\tan\theta_i = \frac{w}{H}\left(i - \frac{N-1}{2}\right), \qquad
\lambda_i = \frac{H}{\cos\theta_i}, \qquad
\sum_{i=0}^{N-1} \ell\cos\theta_i = D,$$

one equation for the horizontal tension $H$, solved below with
`scipy.optimize.brentq`: an answer that shares nothing with the library's Newton
solve on $2(N-1) + N$ unknowns. The chain is solved for nine spans $D$ at once with
`jax.vmap`, each from the same kind of start: the chain pulled down into a V
(feasible, but far from the answer).
"""
    ),
    code(
        """
N, L, W = 20, 1.0, 1.0


def energy(p, args):
    return args["w"] * jnp.sum(p[:, 1])


def links(p, args):
    ends = jnp.stack([jnp.zeros(2), jnp.stack([args["span"], 0.0])])
    points = jnp.concatenate([ends[:1], p, ends[1:]])
    return jnp.linalg.norm(jnp.diff(points, axis=0), axis=1) - args["length"] / N


def vee(span, length):
    \"""A feasible start: the chain pulled down at its middle into a V.\"""
    cos, i = span / length, jnp.arange(1, N)
    x = i * (length / N) * cos
    y = -(length / N) * jnp.sqrt(1 - cos**2) * jnp.minimum(i, N - i)
    return jnp.stack([x, y], axis=1)


def hang(span):
    args = {"span": span, "length": jnp.asarray(L), "w": jnp.asarray(W / N)}
    return cjax.extremize(energy, vee(span, L), args, constraints=links)


spans = jnp.linspace(0.15, 0.95, 9)
chains = jax.vmap(hang)(spans)
print("Newton steps per span:", chains.stats["num_steps"])
"""
    ),
    code(
        """
def chain_closed_form(span):
    w, ell = W / N, L / N
    offsets = np.arange(N) - (N - 1) / 2

    def excess(tension):
        return ell * np.sum(1 / np.sqrt(1 + (w * offsets / tension) ** 2)) - span

    tension = scipy.optimize.brentq(excess, 1e-9, 1e9, xtol=1e-300, rtol=1e-15)
    slopes = w * offsets / tension
    return tension, slopes, tension * np.sqrt(1 + slopes**2)


assert np.all(chains.result == cjax.RESULTS.successful)
assert np.all(chains.kind == cjax.EXTREMUM.minimum)
for i, span in enumerate(np.asarray(spans)):
    tension, slopes, tensions = chain_closed_form(span)
    points = np.concatenate([[[0.0, 0.0]], np.asarray(chains.x[i]), [[span, 0.0]]])
    d = np.diff(points, axis=0)
    np.testing.assert_allclose(d[:, 1] / d[:, 0], slopes, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(chains.multipliers[i], tensions, rtol=1e-9)
    horizontal = chains.multipliers[i] * d[:, 0] / np.linalg.norm(d, axis=1)
    np.testing.assert_allclose(horizontal, tension, rtol=1e-9)
print("all spans agree with the closed form")
"""
    ),
    md(
        r"""
As $N \to \infty$ the chain becomes the continuous hanging rope of the next chapter,
the catenary with weight per unit length $\rho g = W/L$ (computed here by
`cjax.scenes.catenary.closed_form`); its horizontal tension is the limit of $H$.
"""
    ),
    code(
        """
fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
for i in range(0, len(spans), 2):
    span = float(spans[i])
    p = np.concatenate([[[0.0, 0.0]], np.asarray(chains.x[i]), [[span, 0.0]]])
    (line,) = left.plot(p[:, 0], p[:, 1], ".-", label=f"D = {span:.2f}")
    rope = catenary.closed_form(0.0, 0.0, span, 0.0, L, rho_g=W / L)
    xs = np.linspace(0.0, span, 200)
    left.plot(xs, rope["y"](xs), "--", color=line.get_color(), linewidth=0.8)
left.set_aspect("equal")
left.set_title(f"{N}-link chains (dots) and the catenary (dashed)")
left.legend(fontsize="small")

# H from the library: the horizontal component of the tension in the first link.
first_link = np.asarray(chains.x[:, 0, 0]) / (L / N)  # cos(theta_0)
right.plot(
    spans,
    [chain_closed_form(s)[0] for s in np.asarray(spans)],
    "k-",
    label="chain, closed form (brentq)",
)
right.plot(
    spans, chains.multipliers[:, 0] * first_link, "o", label="chain, extremize (vmap)"
)
rope = [
    catenary.closed_form(0, 0, s, 0, L, W / L)["horizontal_tension"]
    for s in np.asarray(spans)
]
right.plot(spans, rope, "--", label="catenary")
right.set_xlabel("span D")
right.set_yscale("log")
right.set_ylabel("horizontal tension H")
right.legend();
"""
    ),
]


if __name__ == "__main__":
    write(CELLS, "01_lagrange_multipliers.ipynb")
