"""Sharp edges of `simulate` (issue 11): each returns the right trajectory or says not.

- fixed-step Euler on the Cartesian pendulum, dt0 = 0.5 over [0, 100] (|q| reached
  1e84 with `successful`): `RESULTS.diverged`, detected at the first accepted step off
  the manifold; same for Heun + Projection, Baumgarte with huge gains at a fixed step.
- a `Unilateral` with t1 < t0: `ValueError` (concrete), `RESULTS.invalid_time_grid`
  (traced); t1 == t0: `successful`, the initial state. A plain system with t1 < t0
  integrates backwards, right (round trip back to the start).
- a floor contact under gravity 9.81 cos(t) (the state moves exactly linearly, the
  controller took one step over the release): released at pi/2 to the root finder's
  tolerance, multipliers of the attached phase >= 0, free flight as in closed form;
  also a shallow dip (cos t + 0.99, both ends of a long step positive) and a fast
  one (cos 40 t).
- the same with one fixed step over the sign change (both ends positive):
  `RESULTS.release_missed`; a fixed step that brackets it: released at pi/2.
- a sign change in a window narrower than the steps: found with `dtmax` (documented).
- NaN in q0 or args: `RESULTS.invalid_input` (in a batch, such a lane takes no step and
  does not hold up the others); save times outside t_span or unsorted:
  `ValueError` (concrete) / `RESULTS.invalid_time_grid` (traced); `max_steps` too
  small: `RESULTS.max_steps_reached`; dt0 pointing away from t1: `ValueError`.
"""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax
from constrained_jax.scenes import pendulum


FIXED = diffrax.ConstantStepSize()


@pytest.fixture(scope="module")
def pend():
    args = pendulum.default_args()
    q0, qd0 = pendulum.state(1.0, 0.0, args)
    return pendulum.system(), args, q0, qd0


@pytest.mark.parametrize(
    "solver, stabilization",
    [
        (diffrax.Euler(), cjax.Unstabilized()),
        (diffrax.Heun(), cjax.Projection()),
        (diffrax.Tsit5(), cjax.Baumgarte(alpha=1e3, beta=1e3)),
    ],
)
def test_fixed_step_blow_up_is_refused(pend, solver, stabilization):
    system, args, q0, qd0 = pend
    traj = cjax.simulate(
        system,
        (0.0, 100.0),
        q0,
        qd0,
        args,
        solver=solver,
        stabilization=stabilization,
        stepsize_controller=FIXED,
        dt0=0.5,
        saveat=cjax.SaveAt(t1=True),
        throw=False,
    )
    assert traj.result == cjax.RESULTS.diverged
    with pytest.raises(Exception, match="diverged"):
        cjax.simulate(
            system,
            (0.0, 100.0),
            q0,
            qd0,
            args,
            solver=solver,
            stabilization=stabilization,
            stepsize_controller=FIXED,
            dt0=0.5,
        )


def test_fixed_step_small_enough_is_successful(pend):
    """The divergence check does not flag an accurate fixed-step run: Tsit5 at
    dt0 = 0.01 keeps the rod length and matches the closed-form period."""
    system, args, q0, qd0 = pend
    period = pendulum.period(1.0, args)
    traj = cjax.simulate(
        system,
        (0.0, period),
        q0,
        qd0,
        args,
        stepsize_controller=FIXED,
        dt0=period / 400,
        saveat=cjax.SaveAt(t1=True),
    )
    assert traj.result == cjax.RESULTS.successful
    np.testing.assert_allclose(traj.q[-1], q0, atol=1e-7)


def _floor_system(gravity):
    """A particle on the floor y = 0 that can only push up: `L = |qd|^2/2 - g(t) y`.
    Attached, `y'' = 0` and the multiplier is `lambda = g(t)`."""

    def lagrangian(q, qd, t, args):
        return 0.5 * jnp.dot(qd, qd) - gravity(t, args) * q[1]

    floor = cjax.Unilateral(
        cjax.Holonomic(lambda q, t, args: q[1]), gap=lambda q, t, args: q[1]
    )
    return cjax.LagrangianSystem(lagrangian, constraints=floor)


def _gravity(t, args):
    """`g(t) = g (cos(omega t) + offset)`: every case below is this one function with
    its own `omega` and `offset` in `args`, so that they share one system and one
    compiled `simulate`."""
    return args["g"] * (jnp.cos(args["omega"] * t) + args["offset"])


def _gravity_args(omega, offset):
    return {
        "g": jnp.asarray(9.81),
        "omega": jnp.asarray(omega, float),
        "offset": jnp.asarray(offset, float),
    }


FLOOR = _floor_system(_gravity)
# name: (args of `_gravity`, release time t*)
GRAVITY = {
    "cos": (_gravity_args(1.0, 0.0), np.pi / 2),  # 9.81 cos t
    "shallow dip": (_gravity_args(1.0, 0.99), np.arccos(-0.99)),  # 9.81 (cos t + 0.99)
    "fast": (_gravity_args(40.0, 0.0), np.pi / 80),  # 9.81 cos 40 t
}
TS = jnp.linspace(0.0, 5.0, 51)


@pytest.fixture(scope="module", params=list(GRAVITY))
def floor_run(request):
    args, t_star = GRAVITY[request.param]
    traj = cjax.simulate(
        FLOOR,
        (0.0, 5.0),
        jnp.zeros(2),
        jnp.array([1.0, 0.0]),
        args,
        saveat=cjax.SaveAt(ts=TS),
        throw=False,
    )
    return request.param, t_star, traj


def test_release_inside_a_long_step(floor_run):
    name, t_star, traj = floor_run
    # Only the shallow dip's flight ends on the floor again (before t1): a release
    # run stops there, and says so (later saves are inf).
    lands = name == "shallow dip"
    assert bool(traj.release.recontact) == lands
    expected = cjax.RESULTS.recontact if lands else cjax.RESULTS.successful
    assert traj.result == expected
    assert bool(traj.release.released)
    np.testing.assert_allclose(traj.release.time, t_star, rtol=0, atol=1e-9)
    attached = np.asarray(traj.ts <= traj.release.time)
    lam = np.asarray(traj.multipliers[:, 0])
    gravity = np.asarray(_gravity(traj.ts, GRAVITY[name][0]))
    # Push-only: never negative while attached (lambda = g(t) there, >= 0).
    assert np.all(lam[attached] >= -1e-9)
    np.testing.assert_allclose(lam[attached], gravity[attached], atol=1e-8)
    np.testing.assert_allclose(lam[~attached], 0.0)
    # x = t until the run ends (at re-contact, for the dip: later saves are inf).
    reached = np.asarray(traj.ts <= traj.release.recontact_time)
    np.testing.assert_allclose(traj.q[reached, 0], traj.ts[reached], atol=1e-8)


def test_free_flight_after_release_closed_form(floor_run):
    """For g = 9.81 cos t: after t* = pi/2, y = 9.81 (t - pi/2 + cos t)."""
    name, t_star, traj = floor_run
    if name != "cos":
        pytest.skip("closed form for the cos case")
    t = np.asarray(traj.ts)
    y = np.where(t > t_star, 9.81 * (t - t_star + np.cos(t)), 0.0)
    yd = np.where(t > t_star, 9.81 * (1 - np.sin(t)), 0.0)
    np.testing.assert_allclose(traj.q[:, 1], y, atol=1e-6)
    np.testing.assert_allclose(traj.qd[:, 1], yd, atol=1e-6)
    assert not bool(traj.release.recontact)


def test_release_stepped_over_by_a_fixed_step_is_refused():
    traj = cjax.simulate(
        FLOOR,
        (0.0, 5.0),
        jnp.zeros(2),
        jnp.array([1.0, 0.0]),
        GRAVITY["cos"][0],
        stepsize_controller=FIXED,
        dt0=5.0,
        saveat=cjax.SaveAt(t1=True),
        throw=False,
    )
    # One step from 0 to 5: both ends have cos > 0, the samples inside do not.
    assert traj.result == cjax.RESULTS.release_missed


def test_release_bracketed_by_a_fixed_step_is_found():
    """A fixed step whose ends bracket the sign change (0 to 2.5: cos 2.5 < 0) is
    root-found as usual: release at pi/2."""
    traj = cjax.simulate(
        FLOOR,
        (0.0, 5.0),
        jnp.zeros(2),
        jnp.array([1.0, 0.0]),
        GRAVITY["cos"][0],
        stepsize_controller=FIXED,
        dt0=2.5,
        saveat=cjax.SaveAt(t1=True),
    )
    np.testing.assert_allclose(traj.release.time, np.pi / 2, rtol=0, atol=1e-9)


def test_unilateral_backwards_is_refused():
    system = FLOOR
    args = GRAVITY["cos"][0]
    with pytest.raises(ValueError, match="backwards"):
        cjax.simulate(system, (0.0, -1.0), jnp.zeros(2), jnp.zeros(2), args)

    @jax.jit
    def run(t1):
        return cjax.simulate(
            system, (0.0, t1), jnp.zeros(2), jnp.zeros(2), args, throw=False
        )

    assert run(jnp.asarray(-1.0)).result == cjax.RESULTS.invalid_time_grid
    empty = run(jnp.asarray(0.0))
    assert empty.result == cjax.RESULTS.successful
    np.testing.assert_array_equal(empty.q[-1], jnp.zeros(2))


def test_plain_system_backwards_round_trip(pend):
    """Without a `Unilateral`, t1 < t0 integrates backwards: running forwards again
    from the end returns to the start."""
    system, args, _, _ = pend
    q0, qd0 = pendulum.state(0.5, 1.0, args)
    back = cjax.simulate(system, (0.0, -1.3), q0, qd0, args)
    assert back.result == cjax.RESULTS.successful
    fwd = cjax.simulate(system, (-1.3, 0.0), back.q[-1], back.qd[-1], args)
    np.testing.assert_allclose(fwd.q[-1], q0, atol=1e-7)
    np.testing.assert_allclose(fwd.qd[-1], qd0, atol=1e-7)


def test_invalid_inputs(pend):
    system, args, q0, qd0 = pend
    bad_q0 = q0.at[0].set(jnp.nan)
    traj = cjax.simulate(system, (0.0, 1.0), bad_q0, qd0, args, throw=False)
    assert traj.result == cjax.RESULTS.invalid_input
    bad_args = dict(args, g=jnp.asarray(jnp.nan))
    traj = cjax.simulate(system, (0.0, 1.0), q0, qd0, bad_args, throw=False)
    assert traj.result == cjax.RESULTS.invalid_input
    traj = cjax.simulate(system, (0.0, 10.0), q0, qd0, args, max_steps=2, throw=False)
    assert traj.result == cjax.RESULTS.max_steps_reached


@jax.jit
@jax.vmap
def _pendulums(g, t1, dt0):
    """A batch of pendulums (a sweep over `g`, the end time and the first step)."""
    args = dict(pendulum.default_args(), g=g)
    q0, qd0 = pendulum.state(1.0, 0.0, args)
    return cjax.simulate(
        pendulum.system(), (0.0, t1), q0, qd0, args, dt0=dt0, throw=False
    )


def test_invalid_lane_of_a_batch_runs_no_step():
    """A lane with NaN in `args`, an infinite end time or a NaN first step (traced:
    a concrete one raises) is `invalid_input` and takes no step: it does not hold up
    the batch (under `jax.vmap` the loop runs until the slowest lane is done; it used
    to reject steps until `max_steps`, 16,384, for every lane's 100). The other lanes
    are as without it."""
    g = jnp.array([9.81, jnp.nan, 9.0, 9.81, 9.5])
    t1 = jnp.array([2.0, 2.0, 2.0, jnp.inf, 2.0])
    dt0 = jnp.array([0.01, 0.01, 0.01, 0.01, jnp.nan])
    bad = _pendulums(g, t1, dt0)
    good = _pendulums(
        jnp.array([9.81, 9.5, 9.0, 9.81, 9.5]),
        jnp.full((5,), 2.0),
        jnp.full((5,), 0.01),
    )
    invalid, ok = cjax.RESULTS.invalid_input._value, cjax.RESULTS.successful._value
    np.testing.assert_array_equal(
        bad.result._value, [ok, invalid, ok, invalid, invalid]
    )
    np.testing.assert_array_equal(bad.stats["num_steps"][np.array([1, 3, 4])], 0)
    for i in (0, 2):
        assert int(bad.stats["num_steps"][i]) == int(good.stats["num_steps"][i]) > 0
        np.testing.assert_allclose(bad.q[i], good.q[i], rtol=1e-14, atol=1e-14)


@jax.jit
def _run_with_saves(args, q0, qd0, ts):
    """The pendulum saved at traced times `ts`: one compiled program for the three
    grids below."""
    return cjax.simulate(
        pendulum.system(),
        (0.0, 1.0),
        q0,
        qd0,
        args,
        saveat=cjax.SaveAt(ts=ts),
        throw=False,
    )


@pytest.mark.parametrize(
    "ts", [jnp.array([0.5, 2.0]), jnp.array([-0.5, 0.5]), jnp.array([0.7, 0.3])]
)
def test_bad_save_times_are_refused(pend, ts):
    system, args, q0, qd0 = pend
    with pytest.raises(ValueError, match="SaveAt"):
        cjax.simulate(system, (0.0, 1.0), q0, qd0, args, saveat=cjax.SaveAt(ts=ts))

    assert _run_with_saves(args, q0, qd0, ts).result == cjax.RESULTS.invalid_time_grid


@pytest.mark.parametrize(
    "dt0, message",
    [(-0.1, "points away"), (0.0, "finite and nonzero"), (float("nan"), "finite")],
)
def test_dt0_pointing_away_or_not_a_step_is_refused(pend, dt0, message):
    system, args, q0, qd0 = pend
    with pytest.raises(ValueError, match=message):
        cjax.simulate(
            system, (0.0, 1.0), q0, qd0, args, stepsize_controller=FIXED, dt0=dt0
        )


def test_narrow_pulse_found_with_bounded_steps():
    """A sign change in a window narrower than the steps the state allows (a Gaussian
    dip of width 0.05 in g; the state is exactly linear) is found once the steps are
    bounded, as the docstring of `simulate` advises: release at the closed form
    t* = 2 - 0.05 sqrt(ln 1.5)."""
    width = 0.05

    def gravity(t, a):
        return a["g"] * (1 - 1.5 * jnp.exp(-(((t - 2) / width) ** 2)))

    traj = cjax.simulate(
        _floor_system(gravity),
        (0.0, 2.5),
        jnp.zeros(2),
        jnp.array([1.0, 0.0]),
        {"g": jnp.asarray(9.81)},
        stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-8, dtmax=0.02),
        saveat=cjax.SaveAt(t1=True),
        throw=False,
    )
    # (Gravity comes back after the dip: the particle lands before t1.)
    assert traj.result == cjax.RESULTS.recontact
    t_star = 2 - width * np.sqrt(np.log(1.5))
    np.testing.assert_allclose(traj.release.time, t_star, rtol=0, atol=1e-9)
