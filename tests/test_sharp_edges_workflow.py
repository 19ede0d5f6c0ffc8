"""Sharp edges of the workflow tools `cjax.sweep` and `cjax.fit` (issue 11): each
is right or refused, never a wrong answer reported as success.

sweep:
- same `fn` after a global scalar it reads changed: the new values (traced again).
- same `fn` after a global JAX array was reassigned / a numpy array written in place
  / a closure cell reassigned / an attribute of a closed-over object set: new values.
- the same through `jax.jit(fn)`, `eqx.filter_jit(fn)` (their own trace caches are
  cleared), `functools.partial`, a bound method, a callable object, a jitted helper.
- a changed global that `fn` does not read: no new trace (the kept program serves).
- with checkpoints: the new state is a different `fn` fingerprint (a folder written
  before the change is refused, a new folder gets the new values).
- a run-time error (`eqx.error_if`) in some rows with throw=True: a
  `JaxRuntimeError` naming the failing global row indices; the same `fn` then sweeps
  good inputs as before; an error in every row of a chunk says so.
- `cjax.extremize(..., throw=True)` failing on one row (NaN input): names that row.
- the throw=False pattern: `result` rows and NaN rows come back as they are,
  `np.flatnonzero(out["result"] != RESULTS.successful)` lists the failing rows.
- N = 0 inputs: ValueError ("length 0"); mismatched leading axes: ValueError naming
  each leaf and its length.

fit:
- `optax.sgd(1.5)` on `sum((p - 1)^2)` (loss 2 -> 3e60): RESULTS.fit_diverged, the best
  params0 back (steps 0, its gradient norm), raises with throw=True.
- the same under `jax.vmap`: only the member whose step is too large diverges.
- Adam on a noisy least-squares line: successful, the normal equations' solution.
- Adam started at the least-squares solution, and at an exact minimum: successful.
- gradient descent with a large but stable step (oscillating, shrinking): successful.
- params0 holding NaN or inf: RESULTS.invalid_input, nothing evaluated.
- steps = 0: successful, params0, one loss; with gtol not met: max steps reached.
- without gtol, successful means "ran the steps and ended lower", not converged (3
  steps, error still 0.512 of the start); with gtol the same run is max steps.
- a loss returning a vector: ValueError.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import constrained_jax as cjax
from constrained_jax.scenes import cylinder_volume as cylv


CPU = jax.devices("cpu")[:1]
KW = dict(batch_size=4, devices=CPU, progress=False)


# --------------------------------------------------------------------------------------
# sweep: a kept program is never reused for a changed Python state


SCALE = 2.0
OFFSET = jnp.array([1.0, 2.0])
TABLE = np.array([1.0, 10.0])
UNUSED = 0


def _reads_globals(x):
    return x * SCALE + jnp.sum(OFFSET) + jnp.asarray(TABLE)[1]


def test_sweep_sees_changed_globals():
    global SCALE, OFFSET, UNUSED
    x = np.arange(6.0)
    expected = lambda: x * SCALE + np.sum(np.asarray(OFFSET)) + TABLE[1]
    traces = []

    def fn(x):
        traces.append(None)
        return _reads_globals(x)

    np.testing.assert_array_equal(cjax.sweep(fn, x, **KW), expected())
    UNUSED += 1  # not read by fn: the kept program serves, no new trace
    np.testing.assert_array_equal(cjax.sweep(fn, x, **KW), expected())
    assert len(traces) == 1
    try:
        SCALE = 3.0  # a Python scalar: a literal of the jaxpr
        np.testing.assert_array_equal(cjax.sweep(fn, x, **KW), expected())
        OFFSET = jnp.array([10.0, 20.0])  # a JAX array reassigned: a constant
        np.testing.assert_array_equal(cjax.sweep(fn, x, **KW), expected())
        TABLE[1] = 100.0  # a numpy array written in place
        np.testing.assert_array_equal(cjax.sweep(fn, x, **KW), expected())
        assert len(traces) == 4
    finally:
        SCALE, OFFSET, TABLE[1] = 2.0, jnp.array([1.0, 2.0]), 10.0
    np.testing.assert_array_equal(cjax.sweep(fn, x, **KW), expected())


def test_sweep_sees_a_changed_closure_and_attribute():
    class Config:
        pass

    config = Config()
    config.k = 2.0
    power = 1.0

    def fn(x):
        return config.k * x**power

    x = np.arange(1.0, 6.0)
    np.testing.assert_array_equal(cjax.sweep(fn, x, **KW), 2.0 * x)
    power = 2.0  # the closure cell is reassigned
    np.testing.assert_array_equal(cjax.sweep(fn, x, **KW), 2.0 * x**2)
    config.k = 5.0  # an attribute of a closed-over object
    np.testing.assert_array_equal(cjax.sweep(fn, x, **KW), 5.0 * x**2)


def test_sweep_checkpoint_fingerprint_follows_the_state(tmp_path):
    state = {"c": 1.0}

    def fn(x):
        return x + state["c"]

    x = np.arange(7.0)
    np.testing.assert_array_equal(
        cjax.sweep(fn, x, checkpoint=tmp_path / "a", **KW), x + 1.0
    )
    state["c"] = 4.0
    np.testing.assert_array_equal(
        cjax.sweep(fn, x, checkpoint=tmp_path / "b", **KW), x + 4.0
    )
    with pytest.raises(ValueError, match="`fn`"):
        cjax.sweep(fn, x, checkpoint=tmp_path / "a", **KW)


# --------------------------------------------------------------------------------------
# sweep: run-time errors name their rows


def _fails_on_marked_rows(x):
    return eqx.error_if(x * 2.0, x < 0, "negative input")


@pytest.mark.parametrize(
    "bad, named",
    [([6], "row 6 "), ([5, 7], "rows 5, 7 "), ([0], "row 0 "), ([9], "row 9 ")],
)
def test_sweep_error_names_the_failing_rows(bad, named):
    x = np.arange(10.0)
    x[bad] = -1.0
    with pytest.raises(jax.errors.JaxRuntimeError, match="negative input") as info:
        cjax.sweep(_fails_on_marked_rows, x, **KW)
    assert named in str(info.value)
    # The same fn sweeps good inputs afterwards.
    good = np.arange(10.0)
    np.testing.assert_array_equal(
        cjax.sweep(_fails_on_marked_rows, good, **KW), 2 * good
    )


def _cylinder(x):
    sol = cylv.solve(x["b"], x["l"], throw=True)
    return sol.x


def test_sweep_extremize_with_throw_names_the_row():
    inputs = {"b": np.array([1.0, 2.0, np.nan, 0.5, 3.0]), "l": np.ones(5)}
    with pytest.raises(jax.errors.JaxRuntimeError, match=r"row 2 \(") as info:
        cjax.sweep(_cylinder, inputs, batch_size=8, devices=CPU, progress=False)
    assert "throw=False" in str(info.value)


def test_sweep_without_throw_keeps_failed_and_nan_rows():
    def fn(x):
        value = jnp.where(x > 2.5, jnp.nan, x**2)
        result = cjax.RESULTS.where(
            jnp.isfinite(value), cjax.RESULTS.successful, cjax.RESULTS.nonfinite
        )
        return {"value": value, "result": result}

    x = np.arange(6.0)
    out = cjax.sweep(fn, x, **KW)
    assert out["value"].shape == (6,)
    np.testing.assert_array_equal(out["value"][:3], x[:3] ** 2)
    assert np.all(np.isnan(out["value"][3:]))
    failing = np.flatnonzero(out["result"] != cjax.RESULTS.successful)
    np.testing.assert_array_equal(failing, [3, 4, 5])


def test_sweep_empty_and_mismatched_inputs():
    with pytest.raises(ValueError, match="length 0"):
        cjax.sweep(jnp.sin, np.zeros(0), **KW)
    with pytest.raises(ValueError, match=r"inputs\['a'\]: 3, inputs\['b'\]: 4"):
        cjax.sweep(lambda p: p["a"], {"a": np.zeros(3), "b": np.zeros(4)}, **KW)


# --------------------------------------------------------------------------------------
# fit: divergence, bad starts, degenerate requests

SGD_TOO_LARGE = optax.sgd(1.5)  # created once: a new optimizer compiles anew
SGD_STABLE = optax.sgd(0.9)


def _bowl(p, args):
    """`a * sum((p - 1)^2)`: gradient descent with rate h multiplies the error by
    `1 - 2 a h` per step (diverges when `|1 - 2 a h| > 1`)."""
    a = 1.0 if args is None else args
    return a * jnp.sum((p - 1.0) ** 2)


def test_fit_diverging_but_finite_is_refused():
    p0 = jnp.zeros(2)
    res = cjax.fit(
        _bowl, p0, optimizer=SGD_TOO_LARGE, steps=100, progress=False, throw=False
    )
    assert res.result == cjax.RESULTS.fit_diverged
    # By hand: the error p - 1 is multiplied by 1 - 2 * 1.5 = -2 per step.
    np.testing.assert_allclose(res.losses[-1], 2 * 4.0**100, rtol=1e-12)
    # params0 comes back (here also the best seen: every step made things worse).
    np.testing.assert_array_equal(res.params, p0)
    assert res.steps == 0
    np.testing.assert_allclose(res.grad_norm, 2 * np.sqrt(2), rtol=1e-14)
    with pytest.raises(Exception, match="learning rate"):
        cjax.fit(_bowl, p0, optimizer=SGD_TOO_LARGE, steps=100, progress=False)


def test_fit_divergence_under_vmap_is_per_member():
    curvature = jnp.array([1.0, 0.1])  # rates 2 a h = 3 (diverges), 0.3 (converges)
    res = jax.vmap(
        lambda a: cjax.fit(
            _bowl,
            jnp.zeros(2),
            args=a,
            optimizer=SGD_TOO_LARGE,
            steps=60,
            throw=False,
        )
    )(curvature)
    np.testing.assert_array_equal(
        res.result == cjax.RESULTS.fit_diverged, [True, False]
    )
    np.testing.assert_array_equal(res.result == cjax.RESULTS.successful, [False, True])
    np.testing.assert_array_equal(res.params[0], np.zeros(2))
    np.testing.assert_allclose(res.params[1], 1.0 - 0.7**60, rtol=1e-12)


def test_fit_stable_oscillating_descent_is_successful():
    """Rate 0.9 on curvature 2: the error flips sign and shrinks by 0.8 per step."""
    res = cjax.fit(_bowl, jnp.zeros(2), optimizer=SGD_STABLE, steps=50, progress=False)
    assert res.result == cjax.RESULTS.successful
    np.testing.assert_allclose(res.params, 1.0 - (-0.8) ** 50, rtol=1e-13)


@pytest.fixture(scope="module")
def noisy_line():
    t = jnp.linspace(0.0, 1.0, 50)
    sigma = 0.1
    y = 1.5 * t + 0.3 + sigma * jax.random.normal(jax.random.key(0), (50,))
    design = np.stack([np.asarray(t), np.ones(50)], axis=1)
    # The least-squares solution from the normal equations.
    exact = np.linalg.solve(design.T @ design, design.T @ np.asarray(y))
    return (t, y, sigma), exact


def _chi2(p, args):
    t, y, sigma = args
    return 0.5 * jnp.sum(((p[0] * t + p[1] - y) / sigma) ** 2)


def test_fit_noisy_adam_is_successful(noisy_line):
    args, exact = noisy_line
    res = cjax.fit(_chi2, jnp.zeros(2), args=args, steps=2000, progress=False)
    assert res.result == cjax.RESULTS.successful
    assert res.losses[-1] < res.losses[0]
    np.testing.assert_allclose(res.params, exact, rtol=1e-5)
    # Started at the solution, or near it, Adam rattles and comes back: not flagged.
    for start in (exact, exact + 1e-3):
        again = cjax.fit(
            _chi2, jnp.asarray(start), args=args, steps=300, progress=False
        )
        assert again.result == cjax.RESULTS.successful


def test_fit_started_at_an_exact_minimum_is_successful():
    res = cjax.fit(_bowl, jnp.ones(3), steps=100, progress=False)
    assert res.result == cjax.RESULTS.successful
    np.testing.assert_array_equal(res.params, np.ones(3))


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_fit_nonfinite_start_is_invalid_input(bad):
    calls = []

    def loss(p, args):
        calls.append(None)
        return _bowl(p, args)

    p0 = jnp.array([0.0, bad])
    res = cjax.fit(loss, p0, steps=10, progress=False, throw=False)
    assert res.result == cjax.RESULTS.invalid_input
    assert res.steps == 0 and np.all(np.isinf(res.losses))
    with pytest.raises(Exception, match="NaN or inf"):
        cjax.fit(loss, p0, steps=10, progress=False)


def test_fit_zero_steps():
    res = cjax.fit(_bowl, jnp.zeros(2), steps=0, progress=False)
    assert res.result == cjax.RESULTS.successful
    assert res.steps == 0 and res.losses.shape == (1,)
    np.testing.assert_array_equal(res.params, np.zeros(2))
    np.testing.assert_allclose(res.losses[0], 2.0)
    res = cjax.fit(_bowl, jnp.zeros(2), steps=0, gtol=1e-8, progress=False, throw=False)
    assert res.result == cjax.RESULTS.nonlinear_max_steps_reached


def test_fit_vector_loss_is_refused():
    with pytest.raises(ValueError, match="scalar"):
        cjax.fit(lambda p, a: (p - 1.0) ** 2, jnp.zeros(2), steps=5, progress=False)


FACTOR = 2.0


def _scaled(x, power):
    return FACTOR * x**power


_jitted_helper = jax.jit(lambda x: FACTOR * x)


class _Model:
    def __init__(self, k):
        self.k = k

    def __call__(self, x):
        return self.k * x


def test_sweep_sees_changes_through_wrappers():
    """`jax.jit` and `eqx.filter_jit` of fn (whose own trace caches are cleared),
    `functools.partial`, a bound method, a callable object, a jitted global helper."""
    global FACTOR
    import functools

    x = np.arange(1.0, 5.0)
    model = _Model(3.0)
    cases = [
        (jax.jit(lambda x: _scaled(x, 1.0)), lambda factor, k: factor * x),
        (eqx.filter_jit(lambda x: _scaled(x, 3.0)), lambda factor, k: factor * x**3),
        (functools.partial(_scaled, power=2.0), lambda factor, k: factor * x**2),
        (model.__call__, lambda factor, k: k * x),
        (model, lambda factor, k: k * x),
        (lambda x: _jitted_helper(x) + 1.0, lambda factor, k: factor * x + 1.0),
    ]
    for fn, expected in cases:
        try:
            np.testing.assert_array_equal(cjax.sweep(fn, x, **KW), expected(2.0, 3.0))
            FACTOR = 7.0
            model.k = 11.0
            np.testing.assert_array_equal(cjax.sweep(fn, x, **KW), expected(7.0, 11.0))
        finally:
            FACTOR, model.k = 2.0, 3.0


def test_sweep_error_in_every_row_says_so():
    x = -np.arange(1.0, 4.0)
    with pytest.raises(jax.errors.JaxRuntimeError, match="every row of the chunk"):
        cjax.sweep(_fails_on_marked_rows, x, **KW)


def test_fit_successful_without_gtol_means_ran_the_steps():
    """Three steps of rate 0.9 on curvature 2 leave the error at 0.8^3 = 0.512 of
    the start: `successful` (ran the steps, ended lower), not converged; asking for
    `gtol` turns the same run into `nonlinear_max_steps_reached`."""
    kw = dict(optimizer=SGD_STABLE, steps=3, progress=False, throw=False)
    res = cjax.fit(_bowl, jnp.zeros(2), **kw)
    assert res.result == cjax.RESULTS.successful
    np.testing.assert_allclose(res.params, 1.0 - (-0.8) ** 3, rtol=1e-14)
    np.testing.assert_allclose(res.grad_norm, 2 * np.sqrt(2) * 0.8**3, rtol=1e-14)
    res = cjax.fit(_bowl, jnp.zeros(2), gtol=1e-8, **kw)
    assert res.result == cjax.RESULTS.nonlinear_max_steps_reached
