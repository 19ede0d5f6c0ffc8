"""Errors that name the cause (issue 41, section 4): each careless input is refused
with a `ValueError` that says what is wrong and what to do, or accepted and right.

- a user function with the wrong number of arguments (`Holonomic(lambda q, args:
  ...)`, and every other user function of the library): a `ValueError` naming the
  call expected and the signature given; `functools.partial`, callable objects,
  `eqx.Module`s, jitted functions, `*args` and defaulted extra arguments accepted.
- a bare function as `constraints=` of `LagrangianSystem`: says to wrap it.
- Python lists as `q0`, `qd0`, `x0`, bounds, a constraint's value or `params0`: the
  arrays they spell, the same answers.
- string, integer, boolean or complex leaves of `x0`, text in `args`, in a sweep's
  inputs or in a fit's `params0`: refused, naming the leaf's path; integer and
  complex parameters in `args` are parameters like any other (traced).
- float32 state and float64 parameters in `simulate` under strict promotion: runs in
  float32, and its derivative with respect to the float64 parameter is right.
- negative or NaN `consistency_tol`: `ValueError`.
- an inner `throw=True` solve failing inside `fit(throw=False)`: the fit stops
  `nonfinite` with its last good parameters, as with an inner `throw=False` solve.
- two sweeps on one checkpoint folder: the second is refused and touches nothing;
  a stale lock (its process gone) is taken over; a folder whose manifest was lost is
  refused to another sweep without writing one, and resumes for its own.
- `np.int64` `max_steps`, also inside `jax.jit`: accepted.
- a failure raised by an already-compiled program: its traceback and message lead
  to the current call, not to the call that compiled it.
"""

import functools
import json
import os
import socket
import subprocess
import sys
import threading
import traceback

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import constrained_jax as cjax
from constrained_jax._misc import check_max_steps


CPU = jax.devices("cpu")[:1]
KW = dict(batch_size=4, devices=CPU, progress=False)


def lagrangian(q, qd, t, args):
    return 0.5 * jnp.sum(qd**2) - args["g"] * q[1]


def rod(q, t, args):
    return q[0] ** 2 + q[1] ** 2 - args["l"] ** 2


ARGS = {"g": jnp.array(9.81), "l": jnp.array(1.0)}
Q0, QD0 = jnp.array([1.0, 0.0]), jnp.array([0.0, 0.0])
PENDULUM = cjax.LagrangianSystem(lagrangian, cjax.Holonomic(rod))


@pytest.fixture(scope="module")
def pendulum_run():
    """The pendulum from the horizontal, to t = 0.3 (compiled once)."""
    return cjax.simulate(PENDULUM, (0.0, 0.3), Q0, QD0, ARGS)


# --------------------------------------------------------------------------------------
# User functions with the wrong number of arguments


F2 = lambda x, args: jnp.sum(x**2)


@pytest.mark.parametrize(
    "build, call",
    [
        (lambda: cjax.Holonomic(lambda q, args: q[0]), "G(q, t, args)"),
        (lambda: cjax.Pfaffian(lambda q, t: q[None]), "g(q, t, args)"),
        (lambda: cjax.Pfaffian(lambda q, t, a: q[None], lambda q, a: 0.0), "h(q, t,"),
        (
            lambda: cjax.Unilateral(cjax.Holonomic(rod), gap=lambda q, t: q[0]),
            "gap(q, t, args)",
        ),
        (
            lambda: cjax.Unilateral(
                cjax.Holonomic(rod), gap=rod, restitution=lambda: 0.5
            ),
            "restitution(args)",
        ),
        (lambda: cjax.LagrangianSystem(lambda q, qd, t: 0.0), "L(q, qd, t, args)"),
        (
            lambda: cjax.LagrangianSystem(lagrangian, forces=lambda q, qd, a: q),
            "Q(q, qd, t, args)",
        ),
        (lambda: cjax.extremize(lambda x: jnp.sum(x**2), jnp.ones(2)), "F(x, args)"),
        (
            lambda: cjax.extremize(F2, jnp.ones(2), constraints=lambda x: x[0]),
            "G(x, args)",
        ),
        (
            lambda: cjax.extremize(
                F2, jnp.ones(2), inequalities=lambda x: x[0], sense="minimize"
            ),
            "H(x, args)",
        ),
        (
            lambda: cjax.Functional(lambda y, yp, x: yp**2, (0.0, 1.0), (0.0, 1.0)),
            "L(y, yp, x, args)",
        ),
        (
            lambda: cjax.Functional(
                lambda y, yp, x, a: yp**2, (0.0, 1.0), (0.0, 1.0), holonomic=len
            ),
            "G(y, x, args)",
        ),
        (lambda: cjax.IntegralConstraint(lambda y, yp, a: y, 1.0), "N(y, yp, x, args)"),
        (
            lambda: cjax.IntegralConstraint(lambda y, yp, x, a: y, lambda: 1.0),
            "C(args)",
        ),
        (lambda: cjax.fit(lambda p: jnp.sum(p**2), jnp.ones(2)), "loss(params, args)"),
        (lambda: cjax.sweep(lambda x, a: x, np.ones(3), **KW), "fn(inputs)"),
    ],
)
def test_wrong_number_of_arguments_is_named(build, call):
    with pytest.raises(ValueError, match="signature") as info:
        build()
    message = str(info.value)
    assert call in message
    assert "is called as" in message


def test_the_message_gives_the_signature_and_the_fix():
    with pytest.raises(ValueError) as info:
        cjax.Holonomic(lambda q, args: q[0])
    message = str(info.value)
    assert "G(q, t, args)" in message and "(q, args)" in message
    assert "lambda q, t, args: ..." in message


class _RodModule(eqx.Module):
    length: float = 1.0

    def __call__(self, q, t, args):
        return q[0] ** 2 + q[1] ** 2 - self.length**2


class _RodObject:
    def __call__(self, q, t, args):
        return q[0] ** 2 + q[1] ** 2 - 1.0


def _rod_with_length(length, q, t, args):
    return q[0] ** 2 + q[1] ** 2 - length**2


def _rod_with_default(q, t, args, length=1.0):
    return q[0] ** 2 + q[1] ** 2 - length**2


@pytest.mark.parametrize(
    "fn",
    [
        _RodModule(),
        _RodObject(),
        functools.partial(_rod_with_length, 1.0),
        _rod_with_default,
        lambda *a: a[0][0] ** 2 + a[0][1] ** 2 - 1.0,
        jax.jit(lambda q, t, args: q[0] ** 2 + q[1] ** 2 - 1.0),
        eqx.filter_jit(lambda q, t, args: q[0] ** 2 + q[1] ** 2 - 1.0),
    ],
    ids=["module", "object", "partial", "default", "star", "jit", "filter_jit"],
)
def test_callables_of_every_kind_are_accepted(fn):
    constraint = cjax.Holonomic(fn)
    q = jnp.array([0.6, 0.5])
    np.testing.assert_allclose(
        constraint.position_residual(q, jnp.array(0.0), None), [0.61 - 1.0]
    )
    assert constraint.num_constraints(2, None) == 1


# --------------------------------------------------------------------------------------
# A bare function as `constraints=`


@pytest.mark.parametrize("constraints", [rod, [rod], (cjax.Holonomic(rod), rod)])
def test_bare_constraint_function_says_to_wrap_it(constraints):
    with pytest.raises(ValueError, match=r"cjax\.Holonomic\(G\)") as info:
        cjax.LagrangianSystem(lagrangian, constraints)
    assert "got a function" in str(info.value)


def test_a_non_constraint_object_is_named():
    with pytest.raises(ValueError, match="got a float"):
        cjax.LagrangianSystem(lagrangian, 1.0)


# --------------------------------------------------------------------------------------
# Python lists are the arrays they spell


def test_simulate_takes_lists_as_q0_qd0(pendulum_run):
    traj = cjax.simulate(PENDULUM, (0.0, 0.3), [1.0, 0.0], [0.0, 0.0], ARGS)
    assert traj.q.dtype == pendulum_run.q.dtype
    np.testing.assert_array_equal(traj.q, pendulum_run.q)
    np.testing.assert_array_equal(traj.qd, pendulum_run.qd)


def test_constraints_returning_lists():
    q, t = jnp.array([0.6, 0.5]), jnp.array(0.0)
    stacked = cjax.Holonomic(lambda q, t, a: jnp.stack([q[0] - 0.5, q[0] * q[1]]))
    listed = cjax.Holonomic(lambda q, t, a: [q[0] - 0.5, q[0] * q[1]])
    assert listed.num_constraints(2, None) == 2
    np.testing.assert_array_equal(
        listed.position_residual(q, t, None), stacked.position_residual(q, t, None)
    )
    for a, b in zip(
        listed.velocity_form(q, t, None), stacked.velocity_form(q, t, None), strict=True
    ):
        np.testing.assert_array_equal(a, b)
    # A Pfaffian's rows as nested lists, with a Python zero among them.
    pfaffian = cjax.Pfaffian(lambda q, t, a: [[q[1], 0]], lambda q, t, a: [1.0])
    assert pfaffian.num_constraints(2, None) == 1
    jac, bias = pfaffian.velocity_form(q, t, None)
    assert jac.dtype == q.dtype and bias.dtype == q.dtype
    np.testing.assert_array_equal(jac, [[0.5, 0.0]])
    np.testing.assert_array_equal(bias, [1.0])


def test_simulate_with_a_list_constraint(pendulum_run):
    """The pendulum's rod returned as a one-element list: the same motion."""
    system = cjax.LagrangianSystem(
        lagrangian, cjax.Holonomic(lambda q, t, a: [rod(q, t, a)])
    )
    traj = cjax.simulate(system, (0.0, 0.3), Q0, QD0, ARGS)
    np.testing.assert_allclose(traj.q, pendulum_run.q, rtol=1e-12, atol=1e-12)


def test_extremize_takes_lists():
    """min x^2 + y^2 subject to x + y = 1: (1/2, 1/2), lambda = -1; with the bound
    x >= 0.7 (a list of bounds): x = 0.7, y = 0.3."""
    sol = cjax.extremize(F2, [1.0, 2.0], constraints=lambda x, a: x[0] + x[1] - 1.0)
    assert isinstance(sol.x, jax.Array) and sol.x.shape == (2,)
    np.testing.assert_allclose(sol.x, [0.5, 0.5], rtol=1e-12)
    np.testing.assert_allclose(sol.multipliers, [-1.0], rtol=1e-12)
    sol = cjax.extremize(
        F2,
        [1.0, 0.0],
        constraints=lambda x, a: x[0] + x[1] - 1.0,
        lower=[0.7, -np.inf],
        sense="minimize",
    )
    np.testing.assert_allclose(sol.x, [0.7, 0.3], atol=1e-9)
    # A list of Python integers is a float array, as SciPy reads `x0=[1, 2]`.
    sol = cjax.extremize(F2, [1, 2], constraints=lambda x, a: x[0] + x[1] - 1.0)
    assert jnp.issubdtype(sol.x.dtype, jnp.floating)
    np.testing.assert_allclose(sol.x, [0.5, 0.5], rtol=1e-12)


# --------------------------------------------------------------------------------------
# Leaves that cannot be what they are used as, named by their path


@pytest.mark.parametrize(
    "x0, named, says",
    [
        ({"a": 1.0, "b": 2}, r"x0\['b'\]", "Pass floats"),
        (jnp.array([1, 2]), "`x0`", "Pass floats"),
        ({"a": jnp.ones(2), "on": True}, r"x0\['on'\]", "Pass floats"),
        ({"a": 1.0, "label": "start"}, r"x0\['label'\]", "str"),
        ((jnp.ones(2), jnp.array([1.0 + 1.0j])), r"x0\[1\]", "complex"),
    ],
)
def test_x0_leaves_that_are_not_unknowns(x0, named, says):
    objective = lambda x, a: sum(
        jnp.sum(jnp.abs(leaf) ** 2) for leaf in jax.tree.leaves(x)
    )
    with pytest.raises(ValueError, match=named) as info:
        cjax.extremize(objective, x0)
    assert says in str(info.value)


def test_text_in_args_is_named():
    with pytest.raises(ValueError, match=r"args\['name'\] is a str") as info:
        cjax.extremize(F2, jnp.ones(2), args={"name": "run 1", "c": 1.0})
    assert "close over them" in str(info.value)
    with pytest.raises(ValueError, match=r"args\['labels'\]"):
        cjax.simulate(
            PENDULUM, (0.0, 0.1), Q0, QD0, {**ARGS, "labels": np.array(["x", "y"])}
        )


def test_integer_and_complex_args_are_parameters():
    """min (x - n)^2 |c|^2 over x: x = n, with an integer `n` and a complex `c` in
    `args` (traced: another n reuses the program)."""
    objective = lambda x, a: jnp.abs(a["c"]) ** 2 * jnp.sum((x - a["n"]) ** 2)
    for n in (3, 5):
        sol = cjax.extremize(objective, jnp.zeros(2), {"n": n, "c": 1.0 + 2.0j})
        np.testing.assert_allclose(sol.x, [n, n], rtol=1e-12)


def test_text_in_sweep_inputs_and_fit_params_is_named():
    with pytest.raises(ValueError, match=r"inputs\['label'\] holds text"):
        inputs = {"label": np.array(["a", "b"]), "v": np.ones(2)}
        cjax.sweep(lambda x: x["v"], inputs, **KW)
    loss = lambda p, a: jnp.sum(p["v"] ** 2)
    with pytest.raises(ValueError, match=r"params0\['label'\] is a str"):
        cjax.fit(loss, {"v": jnp.ones(2), "label": "a"}, progress=False)
    with pytest.raises(ValueError, match=r"params0\['w'\] is complex"):
        cjax.fit(loss, {"v": jnp.ones(2), "w": jnp.array(1.0j)}, progress=False)


# --------------------------------------------------------------------------------------
# float32 state, float64 parameters


@pytest.fixture(scope="module")
def float64_gradient():
    """d q_x(0.3) / d g of the float64 pendulum, and a central finite difference."""

    def end(g):
        return cjax.simulate(PENDULUM, (0.0, 0.3), Q0, QD0, {**ARGS, "g": g}).q[-1, 0]

    step = 1e-4
    fd = (end(9.81 + step) - end(9.81 - step)) / (2 * step)
    return jax.grad(end)(jnp.array(9.81)), fd


def test_float32_state_with_float64_parameters(pendulum_run, float64_gradient):
    """Under strict promotion (the test configuration): the run is float32, right to
    float32's tolerance, and so is its derivative with respect to the float64 `g`."""
    q0, qd0 = Q0.astype(jnp.float32), QD0.astype(jnp.float32)

    def end(g):
        traj = cjax.simulate(PENDULUM, (0.0, 0.3), q0, qd0, {**ARGS, "g": g})
        return traj.q[-1, 0], traj

    (value, traj), grad = jax.value_and_grad(end, has_aux=True)(jnp.array(9.81))
    assert traj.q.dtype == jnp.float32
    assert traj.result == cjax.RESULTS.successful
    np.testing.assert_allclose(traj.q, pendulum_run.q, atol=1e-4)
    exact, fd = float64_gradient
    np.testing.assert_allclose(exact, fd, rtol=1e-6)
    np.testing.assert_allclose(grad, exact, rtol=1e-3)


# --------------------------------------------------------------------------------------
# consistency_tol


@pytest.mark.parametrize("tol", [-1e-8, float("nan"), "1e-8"])
def test_consistency_tol_must_be_a_nonnegative_number(tol):
    with pytest.raises(ValueError, match="consistency_tol"):
        cjax.simulate(PENDULUM, (0.0, 0.1), Q0, QD0, ARGS, consistency_tol=tol)
    with pytest.raises(ValueError, match="consistency_tol"):
        cjax.consistent_initial_state(PENDULUM, Q0, QD0, 0.0, ARGS, consistency_tol=tol)
    with pytest.raises(ValueError, match="consistency_tol"):
        cjax.linearize(PENDULUM, Q0, QD0, 0.0, ARGS, consistency_tol=tol)
    with pytest.raises(ValueError, match="consistency_tol"):
        cjax.integrate_variational(
            cjax.VariationalIntegrator(),
            PENDULUM,
            0.0,
            0.1,
            0.01,
            Q0,
            QD0,
            ARGS,
            ts_save=jnp.array([0.1]),
            consistency_tol=tol,
        )


# --------------------------------------------------------------------------------------
# max_steps: NumPy integers are integers


def test_numpy_integer_max_steps(pendulum_run):
    assert (
        check_max_steps(np.int64(7)) == 7 and type(check_max_steps(np.int32(7))) is int
    )
    for bad in (7.0, True, 0, np.float64(7.0), "7"):
        with pytest.raises(ValueError, match="max_steps"):
            check_max_steps(bad)
    traj = cjax.simulate(PENDULUM, (0.0, 0.3), Q0, QD0, ARGS, max_steps=np.int64(4096))
    np.testing.assert_allclose(traj.q, pendulum_run.q, rtol=1e-12)

    @jax.jit
    def solve(c):
        return cjax.extremize(
            lambda x, a: jnp.sum((x - a) ** 2), jnp.zeros(2), c, max_steps=np.int64(8)
        ).x

    np.testing.assert_allclose(solve(jnp.array([1.0, 2.0])), [1.0, 2.0], rtol=1e-12)

    @jax.jit
    def traced(n):
        return cjax.extremize(F2, jnp.ones(2), max_steps=n).x

    with pytest.raises(ValueError, match="cannot be traced"):
        traced(jnp.array(8))


# --------------------------------------------------------------------------------------
# fit(throw=False) with an inner solve that raises


def _inner_loss(throw):
    """`(log(2 - p) + 10)^2`, with `log(2 - p)` the minimiser of `(x - log(2 - p))^2`
    found by `extremize`: NaN parameters (an invalid input) once `p > 2`."""

    def loss(p, args):
        c = jnp.log(2.0 - p)
        sol = cjax.extremize(
            lambda x, a: jnp.sum((x - a) ** 2), jnp.zeros(1), c, throw=throw
        )
        return jnp.sum((sol.x + 10.0) ** 2)

    return loss


SGD_RATE = 0.05
SGD = optax.sgd(SGD_RATE)
# One function object each: every fit of it shares its compiled blocks.
INNER_LOSS = {True: _inner_loss(True), False: _inner_loss(False)}


def _by_hand(p0, steps):
    """Gradient descent on `(log(2 - p) + 10)^2` until `p` leaves `p < 2`: the last
    iterate inside, its index, and the losses up to it."""
    p, losses = p0, []
    for k in range(steps + 1):
        losses.append((np.log(2.0 - p) + 10.0) ** 2)
        nxt = p - SGD_RATE * 2.0 * (np.log(2.0 - p) + 10.0) * (-1.0 / (2.0 - p))
        if not nxt < 2.0:
            return p, k, np.array(losses)
        p = nxt
    raise AssertionError("never left the domain")


@pytest.mark.parametrize("inner_throw", [True, False])
def test_fit_keeps_its_result_when_an_inner_solve_fails(inner_throw):
    p0, steps = jnp.array(0.0), 20
    expected, taken, losses = _by_hand(0.0, steps)
    assert taken >= 2  # a few good steps, then a step out of the domain
    res = cjax.fit(
        INNER_LOSS[inner_throw],
        p0,
        optimizer=SGD,
        steps=steps,
        progress=False,
        throw=False,
    )
    assert res.result == cjax.RESULTS.nonfinite
    assert int(res.steps) == taken
    np.testing.assert_allclose(res.params, expected, rtol=1e-10)
    np.testing.assert_allclose(res.losses[: taken + 1], losses, rtol=1e-10)
    if inner_throw:  # with throw=True, the inner solve's own message
        with pytest.raises(eqx.EquinoxRuntimeError, match="NaN or inf"):
            cjax.fit(INNER_LOSS[True], p0, optimizer=SGD, steps=steps, progress=False)


# --------------------------------------------------------------------------------------
# Two sweeps on one checkpoint folder


def _double(x):
    return 2.0 * x


def _contents(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_a_folder_in_use_is_refused_and_left_alone(tmp_path):
    folder = tmp_path / "ckpt"
    x = np.arange(10.0)
    np.testing.assert_array_equal(
        cjax.sweep(_double, x, checkpoint=folder, **KW), 2 * x
    )
    assert not list(folder.glob("*.lock"))  # released
    # Another sweep (alive: this test's parent process) holds it, mid-write.
    lock = folder / "sweep.p0.lock"
    lock.write_text(json.dumps({"pid": os.getppid(), "host": socket.gethostname()}))
    (folder / ".chunk_000000.npz.abc.p0.tmp").write_bytes(b"being written")
    (folder / "chunk_000001.npz").unlink()
    before = _contents(folder)
    with pytest.raises(ValueError, match="in use by process") as info:
        cjax.sweep(_double, x, checkpoint=folder, **KW)
    assert "sweep.p0.lock" in str(info.value)
    with pytest.raises(ValueError, match="in use"):  # another sweep too
        cjax.sweep(_double, x + 1.0, checkpoint=folder, **KW)
    assert _contents(folder) == before
    # Its process gone (a pid that has ended): the lock is stale and taken over.
    ended = subprocess.Popen([sys.executable, "-c", "pass"])
    ended.wait()
    lock.write_text(json.dumps({"pid": ended.pid, "host": socket.gethostname()}))
    np.testing.assert_array_equal(
        cjax.sweep(_double, x, checkpoint=folder, **KW), 2 * x
    )
    assert not list(folder.glob("*.lock")) and not list(folder.glob(".*.tmp"))


def test_a_running_sweep_refuses_a_second_one(tmp_path):
    """A sweep in a thread, held inside its first chunk: a second sweep of the same
    folder is refused, and the first finishes right."""
    folder = tmp_path / "ckpt"
    inside, release = threading.Event(), threading.Event()

    def wait(x):
        inside.set()
        release.wait(60)
        return x

    def slow(x):
        y = jax.pure_callback(
            wait, jax.ShapeDtypeStruct(x.shape, x.dtype), x, vmap_method="broadcast_all"
        )
        return 3.0 * y

    x = np.arange(8.0)
    out = {}
    first = threading.Thread(
        target=lambda: out.update(y=cjax.sweep(slow, x, checkpoint=folder, **KW))
    )
    first.start()
    try:
        assert inside.wait(120)
        with pytest.raises(ValueError, match="another sweep of this process"):
            cjax.sweep(_double, x, checkpoint=folder, **KW)
    finally:
        release.set()
        first.join(120)
    np.testing.assert_array_equal(out["y"], 3.0 * x)
    assert not list(folder.glob("*.lock"))


def test_lost_manifest_is_not_taken_over(tmp_path):
    folder = tmp_path / "ckpt"
    x = np.arange(10.0)
    cjax.sweep(_double, x, checkpoint=folder, **KW)
    (folder / "manifest.json").unlink()
    before = _contents(folder)
    with pytest.raises(ValueError, match="another sweep"):
        cjax.sweep(_double, x + 1.0, checkpoint=folder, **KW)
    assert _contents(folder) == before  # no manifest written, no lock left
    # The original sweep resumes from its chunks.
    np.testing.assert_array_equal(
        cjax.sweep(_double, x, checkpoint=folder, **KW), 2 * x
    )
    assert (folder / "manifest.json").exists()
    # A refusal by the manifest leaves no lock either.
    with pytest.raises(ValueError, match="different sweep"):
        cjax.sweep(_double, x + 1.0, checkpoint=folder, **KW)
    assert not list(folder.glob("*.lock"))


# --------------------------------------------------------------------------------------
# A failure raised by an already-compiled program


def _failing_extremize():
    return cjax.extremize(F2, jnp.ones(2), jnp.array(jnp.nan))


def _first_caller():
    return _failing_extremize()


def _second_caller():
    return _failing_extremize()


def _frames(error):
    return [frame.name for frame in traceback.extract_tb(error.__traceback__)]


def test_failure_points_at_the_current_call():
    """The second failure of the same compiled solve: its traceback leads to the
    second caller, and its message does not name the first one."""
    with pytest.raises(eqx.EquinoxRuntimeError, match="NaN or inf") as first:
        _first_caller()
    assert "_first_caller" in _frames(first.value)
    with pytest.raises(eqx.EquinoxRuntimeError, match="NaN or inf") as second:
        _second_caller()
    assert "_second_caller" in _frames(second.value)
    assert "_first_caller" not in _frames(second.value)
    assert "_first_caller" not in str(second.value)
    # The same for simulate (an inconsistent start), and for the check of a
    # singular KKT matrix in `LagrangianSystem.accelerations` (a force along the
    # massless q_1, which the rod leaves free at q = (1, 0)).
    off = jnp.array([1.1, 0.0])
    massless = cjax.LagrangianSystem(
        lambda q, qd, t, a: 0.5 * qd[0] ** 2 - q[1], cjax.Holonomic(rod)
    )

    def simulate_a():
        return cjax.simulate(PENDULUM, (0.0, 0.3), off, QD0, ARGS)

    def simulate_b():
        return cjax.simulate(PENDULUM, (0.0, 0.3), off, QD0, ARGS)

    def accelerations_a():
        return massless.accelerations(Q0, QD0, 0.0, ARGS)

    def accelerations_b():
        return massless.accelerations(Q0, QD0, 0.0, ARGS)

    for (a, b), says in [
        ((simulate_a, simulate_b), "consistent_initial_state"),
        ((accelerations_a, accelerations_b), "singular"),
    ]:
        with pytest.raises(eqx.EquinoxRuntimeError, match=says):
            a()
        with pytest.raises(eqx.EquinoxRuntimeError, match=says) as info:
            b()
        assert b.__name__ in _frames(info.value)
        assert a.__name__ not in _frames(info.value) + [str(info.value)]
        assert a.__name__ not in str(info.value)
