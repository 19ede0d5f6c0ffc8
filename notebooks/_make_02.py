"""Write `02_catenary_isoperimetric.ipynb` (stored without outputs).

python notebooks/_make_02.py
"""

from _cells import code, md, write


CELLS = [
    md(
        r"""
# 2. The catenary and an isoperimetric problem

Extremize a functional $F[y] = \int_{x_L}^{x_R} L(y, y', x)\,dx$ with fixed ends,
subject to

- **integral constraints** $\int N_j(y, y', x)\,dx = C_j$: one constant multiplier
  $\lambda_j$ each, and the Euler-Lagrange equation of
  $L^* = L + \sum_j \lambda_j N_j$;
- **holonomic constraints** $G_j(y, x) = 0$ at every $x$: one multiplier *function*
  $\lambda_j(x)$ each, with (the lecture's convention, also the library's)
  $$\frac{d}{dx}\frac{\partial L}{\partial y'_\sigma} -
  \frac{\partial L}{\partial y_\sigma} = \sum_j \lambda_j(x)
  \frac{\partial G_j}{\partial y_\sigma}.$$

`cjax.solve_functional` uses the direct method: $y$ becomes its values at $N$ nodes
(one Chebyshev polynomial, `cjax.Chebyshev(N)`, or a piecewise-linear mesh,
`cjax.PiecewiseLinear(N)`), the integrals become quadratures, and the finite
constrained extremum is solved with the same KKT machinery as `cjax.extremize`. The
discrete multipliers converge to $\lambda_j$ and $\lambda_j(x)$.
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
import matplotlib.pyplot as plt
import numpy as np

import constrained_jax as cjax
from constrained_jax.scenes import catenary, dido, sphere_geodesic
"""
    ),
    md(
        r"""
## The hanging rope

A rope of length $C$ and weight $\rho g$ per unit length hangs between
$(x_L, y_L)$ and $(x_R, y_R)$. Its potential energy and its length are

$$U[y] = \rho g \int_{x_L}^{x_R} y\sqrt{1 + y'^2}\,dx, \qquad
\int_{x_L}^{x_R} \sqrt{1 + y'^2}\,dx = C,$$

so $L^* = (\rho g y + \lambda)\sqrt{1 + y'^2}$. It does not depend on $x$, so the
"Hamiltonian"
$y'\,\partial L^*/\partial y' - L^* = -(\rho g y + \lambda)/\sqrt{1 + y'^2} = -H$ is
constant, and integrating once more gives the catenary

$$y(x) = -\frac{\lambda}{\rho g} + \frac{H}{\rho g}
\cosh\left(\frac{\rho g}{H}(x - a)\right),$$

with $\lambda$, $H$ and $a$ fixed by the two ends and the length
(`cjax.scenes.catenary.closed_form` solves the one transcendental equation that
remains by bisection). The scene module holds the Lagrangian, the length constraint
and a starting guess (a parabola of the right length); the solve takes the length
as a traced argument, so changing it never recompiles.
"""
    ),
    code(
        """
xl, yl, xr, yr, rho_g = 0.0, 0.0, 1.0, 0.5, 2.5
length = 2.0
rope = catenary.functional(xl, yl, xr, yr)  # U[y], the ends, and int ds = C


def hanging(discretization):
    @jax.jit
    def solve(length):
        guess = catenary.initial_guess(xl, yl, xr, yr, length)
        return cjax.solve_functional(
            rope,
            {"rho_g": rho_g, "length": length},
            discretization=discretization,
            y0=guess,
        )

    return solve


hang16 = hanging(cjax.Chebyshev(16))
sol = hang16(length)
ref = catenary.closed_form(xl, yl, xr, yr, length, rho_g)
(lam,) = sol.multipliers.integral
print(f"lambda = {lam:.15f}  (closed form {ref['multiplier']:.15f})")
print(f"U      = {sol.value:.15f}  (closed form {ref['value']:.15f})")
"""
    ),
    code(
        """
xs = np.linspace(xl, xr, 401)
assert sol.result == cjax.RESULTS.successful
np.testing.assert_allclose(sol(xs), ref["y"](xs), atol=1e-11)
np.testing.assert_allclose(lam, ref["multiplier"], rtol=1e-11)
np.testing.assert_allclose(sol.value, ref["value"], rtol=1e-12)
"""
    ),
    md(
        r"""
### What the multiplier means

The first integral says $\rho g y + \lambda = H\sqrt{1 + y'^2}$. The right-hand side
is the **tension** $T(x)$: its horizontal component $T\cos\phi = H$ is the same
everywhere (nothing pushes the rope sideways). So

$$T(x) = \rho g\,y(x) + \lambda :$$

the tension grows linearly with height, and $\lambda$ is the tension the rope would
have at height $y = 0$; the tension would vanish at the height $y_0 = -\lambda/(\rho g)$
(the directrix of the catenary). The multiplier is also a price: by the envelope
theorem,

$$\frac{dU^*}{dC} = \lambda\,\frac{\partial}{\partial C}\left(\int ds - C\right)
= -\lambda .$$

Paying out a length $\delta C$ of rope at a support at height $y_s$ adds the
potential energy $\rho g y_s\,\delta C$ of the new piece, while the rope already
hanging, pulled through the support by the tension $T(y_s) = \rho g y_s + \lambda$,
sags and loses $T\,\delta C$: the net change is $-\lambda\,\delta C$, the same at
either support. Below, $dU^*/dC$ by central differences (the solve with a
different length reuses the compiled program).
"""
    ),
    code(
        """
tension = rho_g * np.asarray(sol(xs)) + float(lam)
slope = np.asarray(sol.derivative(xs))
horizontal = tension / np.sqrt(1 + slope**2)
print("H from the solution:", horizontal.min(), horizontal.max())
print("H, closed form:     ", ref["horizontal_tension"])
np.testing.assert_allclose(horizontal, ref["horizontal_tension"], rtol=1e-9)

delta = 1e-4
dU_dC = (hang16(length + delta).value - hang16(length - delta).value) / (2 * delta)
print("dU*/dC =", dU_dC, "  -lambda =", -lam)
np.testing.assert_allclose(dU_dC, -lam, rtol=1e-6)
"""
    ),
    code(
        """
fig, (top, err, right) = plt.subplots(1, 3, figsize=(14, 4))
cjax.plot.functional_solution(sol, reference=ref["y"], error_ax=err, ax=top)
top.axhline(-lam / rho_g, color="0.6", linestyle=":", label="$-\\\\lambda/\\\\rho g$")
top.legend(fontsize="small", loc="lower right")
top.set_title("the rope (Chebyshev, 16 nodes)")
err.set_title("error against the closed form")
right.plot(xs, tension, label="tension $T = \\\\rho g y + \\\\lambda$")
right.plot(xs, horizontal, label="horizontal part $T\\\\cos\\\\phi = H$")
right.plot(xs, tension * slope / np.sqrt(1 + slope**2), label="vertical part")
right.set_xlabel("x")
right.legend(fontsize="small")
right.set_title("forces along the rope");
"""
    ),
    md(
        r"""
## Convergence with the number of nodes

The catenary is analytic (an entire function), so the Chebyshev interpolant converges
exponentially: the error falls by a roughly constant factor per added node, a
straight line on a semi-log plot, until round-off. The piecewise-linear mesh
evaluates each element's integrand once, at its midpoint; its stationarity
conditions are a second-order difference scheme, so the nodal values and the
multiplier converge like $h^2$: slope 2 on a log-log plot. Each number of nodes is a
new program (compiled once).
"""
    ),
    code(
        """
def errors(discretization):
    s = hanging(discretization)(length)
    assert s.result == cjax.RESULTS.successful
    y_error = np.max(np.abs(np.asarray(s.y) - ref["y"](np.asarray(s.x))))
    return y_error, abs(float(s.multipliers.integral[0]) - ref["multiplier"])


spectral_nodes = [4, 8, 12, 16]
mesh_nodes = [26, 51, 101]
spectral = np.array([errors(cjax.Chebyshev(n)) for n in spectral_nodes])
mesh = np.array([errors(cjax.PiecewiseLinear(n)) for n in mesh_nodes])
for n, (e_y, e_l) in zip(spectral_nodes, spectral, strict=True):
    print(f"Chebyshev({n:3d}):       |y| error {e_y:.1e}, |lambda| error {e_l:.1e}")
for n, (e_y, e_l) in zip(mesh_nodes, mesh, strict=True):
    print(f"PiecewiseLinear({n:3d}): |y| error {e_y:.1e}, |lambda| error {e_l:.1e}")
"""
    ),
    code(
        """
h = (xr - xl) / (np.array(mesh_nodes) - 1)
slope_y = np.polyfit(np.log(h), np.log(mesh[:, 0]), 1)[0]
slope_lam = np.polyfit(np.log(h), np.log(mesh[:, 1]), 1)[0]
print(f"mesh: slope {slope_y:.3f} (y), {slope_lam:.3f} (lambda)")
assert 1.9 < slope_y < 2.1 and 1.9 < slope_lam < 2.1

# Spectral: digits gained per added node, before round-off (4 -> 8 -> 12 nodes).
rate = -np.diff(np.log10(spectral[:3, 0])) / np.diff(spectral_nodes[:3])
print("Chebyshev: digits per node", rate)
assert np.all(rate > 0.6)  # exponential: ~1 digit per node, not slowing down
assert abs(rate[1] - rate[0]) < 0.5 * rate[0]
assert spectral[-1, 0] < 1e-11 and spectral[-1, 1] < 1e-11
assert spectral[-1, 0] < 1e-5 * mesh[-1, 0]  # 16 polynomial nodes beat 101 mesh nodes
"""
    ),
    code(
        """
fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
left.semilogy(spectral_nodes, spectral[:, 0], "o-", label="y (max at the nodes)")
left.semilogy(spectral_nodes, spectral[:, 1], "s--", label="$\\\\lambda$")
left.set_xlabel("nodes N")
left.set_title("Chebyshev: exponential (semi-log)")
left.legend()
right.loglog(mesh_nodes, mesh[:, 0], "o-", label="y (max at the nodes)")
right.loglog(mesh_nodes, mesh[:, 1], "s--", label="$\\\\lambda$")
guide = mesh[0, 0] * (np.array(mesh_nodes) / mesh_nodes[0]) ** -2.0
right.loglog(mesh_nodes, guide, ":", color="0.5", label="$\\\\propto N^{-2}$")
right.set_xlabel("nodes N")
right.set_title("piecewise linear: second order (log-log)")
right.legend();
"""
    ),
    md(
        r"""
## Dido's problem

Enclose the largest area between a straight shore and a curve of given length $C$
from $(-a, 0)$ to $(a, 0)$:

$$A[y] = \int_{-a}^{a} y\,dx, \qquad \int_{-a}^{a}\sqrt{1 + y'^2}\,dx = C .$$

With $L^* = y + \lambda\sqrt{1 + y'^2}$ the Euler-Lagrange equation is
$\frac{d}{dx}\big(\lambda y'/\sqrt{1 + y'^2}\big) = 1$: the curvature is constant,
$|\kappa| = 1/|\lambda|$, and the curve is an arc of a circle of radius
$R = -\lambda$. With the half-opening angle $\theta$,

$$R\sin\theta = a, \quad 2R\theta = C, \qquad
A = R^2(\theta - \sin\theta\cos\theta).$$

The envelope theorem now reads $dA/dC = -\lambda = R$: one more unit of rope buys
$R$ units of area. (The Chebyshev interpolant of the arc $\sqrt{R^2 - x^2}$ is
limited by its branch points at $x = \pm R$, just outside the interval: the error
falls like $\rho^{-N}$ with $\rho = R + \sqrt{R^2 - a^2}$, about $5\times 10^{-7}$
at $N = 32$. Integrals such as the area converge faster.)
"""
    ),
    code(
        """
a = 1.0
shore = dido.functional(a)


@jax.jit
def enclose(length):
    return cjax.solve_functional(
        shore,
        {"length": length},
        discretization=cjax.Chebyshev(32),
        y0=dido.initial_guess(a, length),
    )


C = 2.5
arc = enclose(C)
arc_ref = dido.closed_form(a, C)
R = arc_ref["radius"]
dA_dC = (enclose(C + delta).value - enclose(C - delta).value) / (2 * delta)
print(f"lambda = {arc.multipliers.integral[0]:.12f}, -R = {-R:.12f}")
print(f"A = {arc.value:.12f} (closed form {arc_ref['value']:.12f})")
print(f"dA/dC = {dA_dC:.9f}, R = {R:.9f}")
"""
    ),
    code(
        """
xs = np.linspace(-a, a, 401)
rho = R + np.sqrt(R**2 - a**2)
assert arc.result == cjax.RESULTS.successful
np.testing.assert_allclose(arc(xs), arc_ref["y"](xs), atol=rho**-32)
np.testing.assert_allclose(arc.multipliers.integral[0], -R, rtol=1e-10)
np.testing.assert_allclose(arc.value, arc_ref["value"], rtol=1e-12)
np.testing.assert_allclose(dA_dC, R, rtol=1e-6)

ax = cjax.plot.functional_solution(arc, reference=arc_ref["y"])
centre = -R * np.cos(arc_ref["theta"])
phi = np.linspace(0, 2 * np.pi, 200)
ax.plot(R * np.cos(phi), centre + R * np.sin(phi), ":", color="0.6", label="circle")
ax.axhline(0.0, color="k", linewidth=0.8)
ax.set_aspect("equal")
ax.set_ylim(centre - 0.1, R + centre + 0.2)
ax.legend(fontsize="small")
ax.set_title(f"Dido: C = {C}, radius R = -lambda = {R:.4f}");
"""
    ),
    md(
        r"""
## A holonomic constraint: the geodesic on a sphere

The shortest curve $(x, Y(x), Z(x))$ between two points of the unit sphere that
stays on it:

$$F[Y, Z] = \int \sqrt{1 + Y'^2 + Z'^2}\,dx, \qquad
G(Y, Z, x) = x^2 + Y^2 + Z^2 - R^2 = 0 \text{ for every } x .$$

The multiplier is now a function. Along the great circle, with arc length $s$,
$d^2\mathbf r/ds^2 = -\mathbf r/R^2$ and $\partial L/\partial Y' = dY/ds$, so
$\frac{d}{dx}\frac{dY}{ds} = -\frac{ds}{dx}\frac{Y}{R^2} = 2\lambda(x)\,Y$:

$$\lambda(x) = -\frac{1}{2R^2}\frac{ds}{dx},$$

the force that bends the curve onto the sphere, per unit of $\partial G/\partial y$;
it varies along the curve because the curve is parametrized by $x$, not by its arc
length. `sol.multipliers.holonomic` is that function, evaluable at any $x$.
"""
    ),
    code(
        """
geodesic = sphere_geodesic.solve(discretization=cjax.Chebyshev(24))
geo_ref = sphere_geodesic.closed_form(sphere_geodesic.START, sphere_geodesic.END)
xs = np.linspace(sphere_geodesic.START[0], sphere_geodesic.END[0], 201)
lam_x = np.asarray(geodesic.multipliers.holonomic(xs))
print(f"length {geodesic.value:.14f} (great circle {geo_ref['value']:.14f})")
print("largest error in lambda(x):", np.max(np.abs(lam_x - geo_ref["multiplier"](xs))))

assert geodesic.result == cjax.RESULTS.successful
np.testing.assert_allclose(geodesic.value, geo_ref["value"], rtol=1e-12)
np.testing.assert_allclose(geodesic(xs), geo_ref["y"](xs), atol=1e-11)
np.testing.assert_allclose(lam_x, geo_ref["multiplier"](xs), rtol=1e-8)
"""
    ),
    code(
        """
fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
cjax.plot.functional_solution(
    geodesic, reference=geo_ref["y"], labels=["Y", "Z"], ax=left
)
left.set_title("the geodesic: Y(x), Z(x)")
right.plot(xs, lam_x, label="$\\\\lambda(x)$, solve_functional")
right.plot(xs, geo_ref["multiplier"](xs), "k--", label="$-(ds/dx)/(2R^2)$")
right.set_xlabel("x")
right.legend()
right.set_title("the multiplier function");
"""
    ),
]


if __name__ == "__main__":
    write(CELLS, "02_catenary_isoperimetric.ipynb")
