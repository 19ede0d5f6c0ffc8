"""cjax.fit: the optimizer loop (against closed-form iterates and minima), its
statuses, progress bar, compilation and jit/vmap; and three inverse problems that
recover known parameters from synthetic noisy data."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
import scipy.optimize
import scipy.special

import constrained_jax as cjax
from constrained_jax.scenes import catenary, inverse

from .helpers import TraceCounter, tree_allclose


# A quadratic with a known minimum: f(x) = (x - x*)^T A (x - x*) / 2 + c, with
# x* = A^{-1} b. A is symmetric positive definite with eigenvalues in [0.9, 4].
_A = np.array([[3.0, 1.0, 0.0], [1.0, 2.0, 0.5], [0.0, 0.5, 1.5]])
_EIGS = np.linalg.eigvalsh(_A)
assert 0.9 <= _EIGS[0] and _EIGS[-1] <= 4.0


def quadratic(x, b):
    a = jnp.asarray(_A)
    return 0.5 * x @ a @ x - b @ x


def quadratic_minimum(b):
    return np.linalg.solve(_A, np.asarray(b))


B1 = jnp.array([1.0, -2.0, 0.5])
B2 = jnp.array([-0.3, 0.7, 2.0])
X0 = jnp.zeros(3)
SGD = optax.sgd(0.2)  # created once: a new optimizer object compiles anew
LBFGS = optax.lbfgs()


def test_gradient_descent_iterates_match_closed_form():
    """Plain gradient descent on a quadratic: x_k - x* = (I - h A)^k (x_0 - x*), so
    the loss history is known exactly at every step (and decreases, h < 2/4)."""
    steps = 100
    res = cjax.fit(quadratic, X0, args=B1, optimizer=SGD, steps=steps, progress=False)
    x_star = quadratic_minimum(B1)
    f_star = -0.5 * B1 @ x_star
    step = np.eye(3) - 0.2 * _A
    err = -x_star
    expected = []
    for _ in range(steps + 1):
        expected.append(f_star + 0.5 * err @ _A @ err)
        x = x_star + err
        err = step @ err
    assert res.losses.shape == (steps + 1,)
    np.testing.assert_allclose(res.losses, expected, rtol=1e-13, atol=1e-15)
    assert np.all(np.diff(res.losses[:40]) < 0)  # later: differences at round-off
    np.testing.assert_allclose(res.params, x, rtol=1e-13)
    assert res.steps == steps
    assert res.result == cjax.RESULTS.successful
    grad = _A @ x - np.asarray(B1)
    assert 1e-11 < np.linalg.norm(grad) < 1e-8  # not at round-off
    np.testing.assert_allclose(res.grad_norm, np.linalg.norm(grad), rtol=1e-4)
    # Forward-mode gradients: the same iterates.
    fwd = cjax.fit(
        quadratic, X0, args=B1, optimizer=SGD, steps=steps, jac="fwd", progress=False
    )
    np.testing.assert_allclose(fwd.losses, expected, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(fwd.params, x, rtol=1e-13)


def test_default_adam_reaches_the_minimum():
    res = cjax.fit(quadratic, X0, args=B1, steps=3000, progress=False)
    np.testing.assert_allclose(res.params, quadratic_minimum(B1), atol=1e-6)
    np.testing.assert_allclose(res.losses[0], 0.0)
    np.testing.assert_allclose(res.losses[-1], quadratic(res.params, B1), rtol=1e-14)


def test_pytree_params():
    """Parameters as a nested pytree (dict of a tuple and a scalar), with an int and a
    Python float in the start: structure kept, leaves become floats."""

    def loss(p, args):
        (u, v), w = p["uv"], p["w"]
        return (u - args[0]) ** 2 + jnp.sum((v - args[1]) ** 2) + 3.0 * (w + 1.0) ** 2

    params0 = {"uv": (0, jnp.zeros(2)), "w": 0.5}
    args = (jnp.asarray(2.0), jnp.array([1.0, -1.0]))
    res = cjax.fit(
        loss, params0, args=args, optimizer=SGD, steps=100, gtol=1e-10, progress=False
    )
    assert jax.tree.structure(res.params) == jax.tree.structure(params0)
    assert res.params["uv"][0].dtype == jnp.float64
    assert res.result == cjax.RESULTS.successful and res.steps < 100
    np.testing.assert_allclose(res.params["uv"][0], 2.0, atol=1e-10)
    np.testing.assert_allclose(res.params["uv"][1], [1.0, -1.0], atol=1e-10)
    np.testing.assert_allclose(res.params["w"], -1.0, atol=1e-10)
    assert res.grad_norm <= 1e-10


def test_gtol_stops_early_and_reports_not_reaching_it():
    res = cjax.fit(
        quadratic, X0, args=B1, optimizer=SGD, steps=1000, gtol=1e-8, progress=False
    )
    assert res.result == cjax.RESULTS.successful
    # By hand: the first gradient-descent iterate with |A x_k - b| <= 1e-8.
    x, k = np.zeros(3), 0
    while np.linalg.norm(_A @ x - B1) > 1e-8:
        x, k = x - 0.2 * (_A @ x - B1), k + 1
    assert res.steps == k
    np.testing.assert_allclose(res.params, x, rtol=1e-12)
    assert res.grad_norm <= 1e-8
    # After stopping, the history repeats the final loss.
    np.testing.assert_array_equal(res.losses[k:], res.losses[-1])

    # By hand: gtol = 1e-12 is not reached in 100 steps.
    x = np.zeros(3)
    for _ in range(100):
        x = x - 0.2 * (_A @ x - B1)
    assert np.linalg.norm(_A @ x - B1) > 1e-11
    kw = dict(args=B1, optimizer=SGD, steps=100, gtol=1e-12, progress=False)
    res = cjax.fit(quadratic, X0, throw=False, **kw)
    assert res.result == cjax.RESULTS.nonlinear_max_steps_reached
    assert res.steps == 100
    np.testing.assert_allclose(res.params, x, rtol=1e-12)
    with pytest.raises(Exception, match="maximum number of steps"):
        cjax.fit(quadratic, X0, **kw)


def test_lbfgs_on_rosenbrock():
    """A line-search optimizer (value, grad and value_fn passed through) reaches the
    Rosenbrock minimum (1, 1) from the classic start (-1.2, 1)."""

    def rosenbrock(x, args):
        return (args - x[0]) ** 2 + 100.0 * (x[1] - x[0] ** 2) ** 2

    res = cjax.fit(
        rosenbrock,
        jnp.array([-1.2, 1.0]),
        args=1.0,
        optimizer=LBFGS,
        steps=200,
        gtol=1e-10,
        progress=False,
    )
    assert res.result == cjax.RESULTS.successful
    assert res.steps < 100
    np.testing.assert_allclose(res.params, [1.0, 1.0], atol=1e-9)


def _log_barrier(x, args):
    """Minimum at x = 1/sqrt(2); NaN for x <= 0."""
    return x**2 - jnp.log(x)


def test_nonfinite_loss_stops_with_last_finite_params():
    """Gradient descent with too large a step jumps to x < 0 where log(x) is NaN: the
    fit stops there, with the last parameters where loss and gradient were finite."""
    h = 0.55
    # By hand: x_{k+1} = x_k - h (2 x_k - 1/x_k), until x <= 0 (at x_3).
    xs = [2.0]
    while xs[-1] > 0 and len(xs) < 50:
        xs.append(xs[-1] - h * (2 * xs[-1] - 1 / xs[-1]))
    assert len(xs) == 4 and xs[-1] < 0
    res = cjax.fit(
        _log_barrier,
        jnp.asarray(2.0),
        optimizer=optax.sgd(h),
        steps=50,
        progress=False,
        throw=False,
    )
    assert res.result == cjax.RESULTS.nonfinite
    assert res.steps == len(xs) - 2
    np.testing.assert_allclose(res.params, xs[-2], rtol=1e-12)
    assert np.all(np.isfinite(res.losses))
    np.testing.assert_allclose(res.losses[-1], xs[-2] ** 2 - np.log(xs[-2]))
    with pytest.raises(Exception, match="Nonfinite"):
        cjax.fit(
            _log_barrier,
            jnp.asarray(2.0),
            optimizer=optax.sgd(h),
            steps=50,
            progress=False,
        )


def test_nonfinite_at_the_start():
    res = cjax.fit(_log_barrier, -1.0, steps=10, progress=False, throw=False)
    assert res.result == cjax.RESULTS.nonfinite
    assert res.steps == 0
    assert res.params == -1.0


def test_progress_bar(capsys, monkeypatch):
    """progress=True draws a tqdm bar on stderr; progress=False or TQDM_DISABLE=1
    draws nothing; the results do not depend on it."""
    monkeypatch.delenv("TQDM_DISABLE", raising=False)
    kw = dict(args=B1, optimizer=SGD, steps=250)
    on = cjax.fit(quadratic, X0, progress=True, **kw)
    err = capsys.readouterr().err
    assert "fit" in err and "250/250" in err and "loss=" in err
    off = cjax.fit(quadratic, X0, progress=False, **kw)
    assert capsys.readouterr().err == ""
    monkeypatch.setenv("TQDM_DISABLE", "1")
    env_off = cjax.fit(quadratic, X0, progress=True, **kw)
    assert capsys.readouterr().err == ""
    assert tree_allclose(on, off, rtol=0, atol=0)
    assert tree_allclose(on, env_off, rtol=0, atol=0)


@pytest.mark.parametrize(
    "value, shown", [("", True), ("0", False), ("off", False), ("1", False)]
)
def test_tqdm_disable_read_as_tqdm_reads_it(monkeypatch, value, shown):
    """`fit` and `sweep` share one reading of `TQDM_DISABLE`, tqdm's own: any
    non-empty value (even `0` or `off`) turns the bar off."""
    from constrained_jax._misc import progress_bar

    monkeypatch.setenv("TQDM_DISABLE", value)
    bar = progress_bar(True, total=1)
    assert bar.disable == (not shown)
    bar.close()
    assert progress_bar(False, total=1).disable


def test_args_and_params_are_traced():
    """A new `args` (the data) or a new start never recompiles: the loss is traced
    only for the first fit."""
    counted = TraceCounter(quadratic)
    first = cjax.fit(counted, X0, args=B1, optimizer=SGD, steps=300, progress=False)
    traces = counted.count
    assert traces > 0
    second = cjax.fit(
        counted, X0 + 1.0, args=B2, optimizer=SGD, steps=300, progress=False
    )
    assert counted.count == traces
    np.testing.assert_allclose(first.params, quadratic_minimum(B1), atol=1e-12)
    np.testing.assert_allclose(second.params, quadratic_minimum(B2), atol=1e-12)


def test_jit_and_vmap_match_the_eager_fit():
    """Under jit or vmap (traced params/args) the loop is one scan; every batch
    member stops on its own and agrees with its own eager fit."""
    kw = dict(optimizer=SGD, steps=300, gtol=1e-6, progress=False)
    bs = jnp.stack([B1, B2, 10.0 * B1])
    eager = [cjax.fit(quadratic, X0, args=b, **kw) for b in bs]
    batched = jax.jit(jax.vmap(lambda b: cjax.fit(quadratic, X0, args=b, **kw)))(bs)
    for i, single in enumerate(eager):
        member = jax.tree.map(lambda x, i=i: x[i], batched)
        assert member.result == cjax.RESULTS.successful
        assert member.steps == single.steps
        assert tree_allclose(member.params, single.params, rtol=1e-12, atol=1e-14)
        assert tree_allclose(member.losses, single.losses, rtol=1e-12, atol=1e-14)
    # Larger b, larger initial gradient: more steps to reach gtol.
    assert eager[2].steps > eager[0].steps


def test_float32():
    """float32 parameters and data stay float32; the minimum to float32 accuracy."""
    b = B1.astype(jnp.float32)
    res = cjax.fit(
        quadratic_f32,
        jnp.zeros(3, jnp.float32),
        args=b,
        optimizer=SGD,
        steps=100,
        gtol=1e-5,
        progress=False,
    )
    assert res.params.dtype == jnp.float32 and res.losses.dtype == jnp.float32
    assert res.result == cjax.RESULTS.successful and res.steps < 100
    np.testing.assert_allclose(res.params, quadratic_minimum(B1), atol=2e-5)


def quadratic_f32(x, b):
    a = jnp.asarray(_A, jnp.float32)
    return 0.5 * x @ a @ x - b @ x


def test_zero_steps():
    res = cjax.fit(quadratic, X0, args=B1, steps=0, progress=False)
    assert res.losses.shape == (1,) and res.steps == 0
    np.testing.assert_array_equal(res.params, X0)


def test_bad_input():
    with pytest.raises(ValueError, match="scalar"):
        cjax.fit(lambda x, a: x**2, X0, progress=False)
    with pytest.raises(ValueError, match="one scalar array"):
        cjax.fit(lambda x, a: (jnp.sum(x**2), x), X0, progress=False)
    with pytest.raises(ValueError, match="real floating"):
        cjax.fit(lambda x, a: jnp.sum(x**2).astype(int), X0, progress=False)
    with pytest.raises(ValueError, match="callable"):
        cjax.fit(1.0, X0)
    with pytest.raises(ValueError, match="GradientTransformation"):
        cjax.fit(quadratic, X0, args=B1, optimizer=optax.adam)
    with pytest.raises(ValueError, match="non-negative int"):
        cjax.fit(quadratic, X0, args=B1, steps=-1)
    with pytest.raises(ValueError, match="non-negative int"):
        cjax.fit(quadratic, X0, args=B1, steps=10.0)
    with pytest.raises(ValueError, match="gtol"):
        cjax.fit(quadratic, X0, args=B1, gtol=0.0)
    with pytest.raises(ValueError, match="jac"):
        cjax.fit(quadratic, X0, args=B1, jac="central")
    with pytest.raises(ValueError, match="no arrays"):
        cjax.fit(quadratic, {}, args=B1)
    with pytest.raises(ValueError, match="real"):
        cjax.fit(quadratic, X0.astype(complex), args=B1)


# -- Inverse problems ----------------------------------------------------------------
#
# Each recovers known parameters from synthetic data (closed form + Gaussian noise,
# fixed seed) by fitting a model that goes through the library. Two checks each:
# (1) the fit is within 3 standard errors of the truth, the standard errors from
# linearised error propagation on the closed form, cov = (J^T J)^{-1} with J the
# Jacobian of the weighted residuals; (2) the fit agrees with an independent
# least-squares solve (scipy on the closed form) to within what the model's own
# discretization error allows, |dp| <= |model error / sigma| / |J| (the linearised
# shift of the minimum), which proves the optimizer found the minimum of the loss.

# L-BFGS without a line search: quasi-Newton steps, the first few damped (its first
# step has unit length in parameter space). Every fit below compiles once.
QUASI_NEWTON = optax.lbfgs(optax.linear_schedule(0.1, 1.0, 4), linesearch=None)


def _scipy_fit(residuals, p0):
    """SciPy's Levenberg-Marquardt on the closed form's residuals (central
    differences: its default forward differences stalled 2.8e-10 short of the chain's
    minimum on one machine), then one Gauss-Newton step with central differences.

    Returns the parameters and the size of that last step, per parameter: how far
    they may still be from the minimum (the finite differences' noise sets its floor,
    about 5e-12 here)."""
    sol = scipy.optimize.least_squares(
        residuals, p0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15, jac="3-point"
    )
    assert sol.success
    jac, r = _jacobian(residuals, sol.x), residuals(sol.x)
    step = np.linalg.solve(jac.T @ jac, jac.T @ r)
    return sol.x - step, np.abs(step)


def _jacobian(residuals, p, rel_step=1e-6):
    """Central differences of the (closed-form) weighted residuals."""
    p = np.asarray(p, dtype=np.float64)
    columns = []
    for i in range(p.size):
        h = rel_step * max(abs(p[i]), 1.0)
        up, down = p.copy(), p.copy()
        up[i] += h
        down[i] -= h
        columns.append((residuals(up) - residuals(down)) / (2 * h))
    return np.stack(columns, axis=-1)


def _standard_errors(jac):
    return np.sqrt(np.diag(np.linalg.inv(jac.T @ jac)))


def _minimum_shift_bound(jac, model_error_norm, grad_norm):
    """|dp| between the fitted parameters and the minimum of the closed form's
    |r|^2 / 2, linearised: the model error e moves the minimum by (J^T J)^{-1} J^T e,
    at most |e| / sigma_min(J); the fit stops where its gradient J^T r has norm
    `grad_norm` (below `gtol`), at most grad_norm / sigma_min(J)^2 from its minimum."""
    smallest = np.linalg.svd(jac, compute_uv=False)[-1]
    return model_error_norm / smallest + float(grad_norm) / smallest**2


def test_inertia_ratio_from_detachment_angles():
    """alpha = I/(M a^2) of the rolling cylinder from 8 detachment angles with noise
    0.005 rad; the model simulates the release event (forward-mode gradients through
    the event's root find)."""
    alpha_true, sigma = 0.5, 0.005
    theta0 = np.linspace(0.2, 1.0, 8)
    data = inverse.detachment_data(jax.random.key(0), alpha_true, theta0, sigma)
    kw = dict(optimizer=QUASI_NEWTON, steps=40, gtol=1e-6, jac="fwd", progress=False)
    res = cjax.fit(inverse.detachment_loss, {"alpha": 0.2}, args=data, **kw)
    assert res.result == cjax.RESULTS.successful and res.steps < 40
    alpha = float(res.params["alpha"])

    # The closed form, written here independently: theta* = arccos(2 cos/(3+alpha)).
    observed = np.asarray(data["angle"])

    def closed_form_residuals(p):
        return (np.arccos(2 * np.cos(theta0) / (3 + p[0])) - observed) / sigma

    jac = _jacobian(closed_form_residuals, [alpha_true])
    (se,) = _standard_errors(jac)
    assert 0.005 < se < 0.05  # the data constrain alpha, but not perfectly
    assert abs(alpha - alpha_true) < 3 * se, (alpha, alpha_true, se)

    # The simulation's error at the fit (tolerances 1e-6) bounds how far its minimum
    # may be from the closed form's. It is read off the already compiled fit: fitted
    # to the closed-form angles at alpha, its initial loss is |model error|^2 / 2.
    exact = {**data, "angle": jnp.arccos(2 * jnp.cos(data["theta0"]) / (3 + alpha))}
    check = cjax.fit(inverse.detachment_loss, res.params, args=exact, **kw)
    model_error = np.sqrt(2 * float(check.losses[0]))
    assert model_error * sigma < 2e-6
    bound = _minimum_shift_bound(jac, model_error, res.grad_norm)
    (alpha_lsq,), (ref_error,) = _scipy_fit(closed_form_residuals, [0.2])
    assert ref_error < 1e-11
    assert abs(alpha - alpha_lsq) <= 2 * bound + ref_error + 1e-12, (
        alpha,
        alpha_lsq,
        bound,
    )
    assert bound < 1e-3 * se


def test_chain_length_and_endpoint_from_points():
    """The length C and the right end's height yR of a chain hanging from (0, 0) to
    (1, yR), from 12 heights with noise 0.005; the model solves the variational
    problem (gradients by the implicit function theorem on its KKT system)."""
    truth, sigma = np.array([1.5, 0.3]), 0.005
    x = np.linspace(0.05, 0.95, 12)
    data = inverse.chain_data(jax.random.key(2), *truth, x, sigma)
    kw = dict(optimizer=QUASI_NEWTON, steps=40, gtol=1e-6, jac="fwd", progress=False)
    res = cjax.fit(inverse.chain_loss, {"length": 1.3, "yr": 0.0}, args=data, **kw)
    assert res.result == cjax.RESULTS.successful and res.steps < 40
    fitted = np.array([float(res.params["length"]), float(res.params["yr"])])

    observed = np.asarray(data["y"])

    def closed_form_heights(p):
        return catenary.closed_form(0.0, 0.0, 1.0, p[1], p[0])["y"](x)

    def closed_form_residuals(p):
        return (closed_form_heights(p) - observed) / sigma

    jac = _jacobian(closed_form_residuals, truth)
    se = _standard_errors(jac)
    assert np.all(np.abs(fitted - truth) < 3 * se), (fitted, truth, se)

    exact = {**data, "y": jnp.asarray(closed_form_heights(fitted))}
    check = cjax.fit(inverse.chain_loss, res.params, args=exact, **kw)
    model_error = np.sqrt(2 * float(check.losses[0]))
    assert model_error * sigma < 1e-10  # Chebyshev(24): spectral accuracy
    bound = _minimum_shift_bound(jac, model_error, res.grad_norm)
    lsq, ref_error = _scipy_fit(closed_form_residuals, [1.3, 0.0])
    assert np.all(ref_error < 1e-11)
    assert np.all(np.abs(fitted - lsq) <= 2 * bound + ref_error + 1e-10), (fitted, lsq)
    assert np.all(2 * bound + 1e-10 < 1e-4 * se)


def _pendulum_positions(ts, l, theta0, g):
    """The exact motion from rest, with SciPy's Jacobi sn (independent of the JAX
    version in the scene): sin(theta/2) = k sn(K(k) - sqrt(g/l) t | k^2)."""
    k = np.sin(theta0 / 2)
    sn = scipy.special.ellipj(scipy.special.ellipk(k**2) - np.sqrt(g / l) * ts, k**2)[0]
    theta = 2 * np.arcsin(k * sn)
    return l * np.stack([np.sin(theta), -np.cos(theta)], axis=-1)


def test_pendulum_length_from_trajectory():
    """The length l of a pendulum released from rest at 0.8 rad, from 20 noisy
    positions (noise 0.01 in each coordinate) over about one period; the model
    simulates the constrained Cartesian pendulum."""
    l_true, theta0, g, sigma = 1.0, 0.8, 9.81, 0.01
    ts = np.linspace(0.1, 2.0, 20)
    data = inverse.pendulum_data(jax.random.key(1), l_true, theta0, ts, sigma, g)
    # The scene's closed form (JAX, AGM) against SciPy's.
    theta = np.asarray(inverse.pendulum_angle(ts, 1.3, theta0, g))
    np.testing.assert_allclose(
        1.3 * np.stack([np.sin(theta), -np.cos(theta)], axis=-1),
        _pendulum_positions(ts, 1.3, theta0, g),
        atol=1e-13,
    )
    kw = dict(optimizer=QUASI_NEWTON, steps=40, gtol=1e-6, jac="fwd", progress=False)
    res = cjax.fit(inverse.bob_loss, {"l": 0.8}, args=data, **kw)
    assert res.result == cjax.RESULTS.successful and res.steps < 40
    l_fit = float(res.params["l"])

    observed = np.asarray(data["q"])

    def closed_form_residuals(p):
        return np.ravel((_pendulum_positions(ts, p[0], theta0, g) - observed) / sigma)

    jac = _jacobian(closed_form_residuals, [l_true])
    (se,) = _standard_errors(jac)
    assert abs(l_fit - l_true) < 3 * se, (l_fit, l_true, se)

    exact = {**data, "q": jnp.asarray(_pendulum_positions(ts, l_fit, theta0, g))}
    check = cjax.fit(inverse.bob_loss, res.params, args=exact, **kw)
    model_error = np.sqrt(2 * float(check.losses[0]))
    assert model_error * sigma < 1e-6  # tolerances 1e-8 over one period
    bound = _minimum_shift_bound(jac, model_error, res.grad_norm)
    (l_lsq,), (ref_error,) = _scipy_fit(closed_form_residuals, [0.8])
    assert ref_error < 1e-11
    assert abs(l_fit - l_lsq) <= 2 * bound + ref_error + 1e-12, (l_fit, l_lsq, bound)
    assert bound < 1e-3 * se
