"""Long contact series against closed forms (issue 41, section 3: never `successful`
with a wrong answer): a ball bouncing on a floor for 60 impacts and more, in float64
and float32, every impact's time and approach speed against the geometric series,
the impact at which it comes to rest, Zeno without a rest speed, and careless
variants (a stiff gravity, `e = 0`, `e = 1`, a rest speed above the first impact's,
starting on the floor, a `Unilateral` with the wrong `sign`).

The closed form (`constrained_jax.scenes.bouncing_ball`, generalised to a start at
height `h` with vertical velocity `w`, up positive): the first impact at
`t_1 = (w + v_1) / g` with approach speed `v_1 = sqrt(w^2 + 2 g h)`, then
`v_k = e^(k-1) v_1` and `t_(k+1) = t_k + 2 e v_k / g` (the flight after impact `k`
leaves at `e v_k`). With a rest speed `v_r`, the ball rests at the first impact with
`v_k < v_r` (with `e = 0`, at the first). Without, it has infinitely many impacts
before `t_inf = t_1 + 2 e v_1 / (g (1 - e))` (Zeno), and a run past `t_inf` can only
end with `RESULTS.max_events_reached`.

Tolerances, from the solver's tolerances, not from its output. Tsit5 (order 5)
integrates a free flight (a parabola) exactly, so the step-size controller's
tolerance does not enter; what is left is where each impact is located and
round-off. Each impact is located (a bracketing root find along the dense output)
to within `tau(t) = tol (1 + |t|)` of the time the gap closes, `tol` the event
root find's tolerance (`1e-12` in float64, `100 eps` in float32: `_event_run`).
Located `dt` late or early, the approach speed is off by `g dt`, a relative error
`g tau / v_k`, which the rebounds carry on (a flight leaves at `e` times the speed it
came in with, and lands at the speed it left with); each impact also rounds, `64 eps`
relative. So the relative speed error of impact `k` is at most
`r_k = sum_(j <= k) (g tau(t_j) / v_j + 64 eps)`, and its time error at most
`sum_(j <= k) tau(t_j) + sum_(j < k) 2 e v_j r_j / g` (the flights lengthened or
shortened by their launch speeds' errors). The bound grows as the speeds shrink
(`1 / v_k`): the slow end of a series is where a mislocated impact shows.
"""

import json
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax
from constrained_jax.scenes import bouncing_ball as ball

from .helpers import run_python


G = 9.81
# The budget of events of the float64 batch: the longest series below needs 66
# (g = 1000), the Zeno run spends all of them.
MAX_EVENTS = 70
NUM_SAVES = 25


def _flight_end(h, w, g):
    """`(t_1, v_1)`: the first impact from height `h` moving up at `w`."""
    v1 = np.sqrt(w**2 + 2 * g * h)
    return (w + v1) / g, v1


# Float64 cases, one `jax.vmap` lane each: (e, rest_speed, g, h, w, u, t1), `u` the
# horizontal speed.
T_ELASTIC = (
    _flight_end(1.0, 0.0, G)[0]
    + 59 * 2 * _flight_end(1.0, 0.0, G)[1] / G
    + _flight_end(1.0, 0.0, G)[1] / G
)  # at the apex after the 60th impact
CASES = {
    # The series: rests at the 59th impact (v_59 = 0.00983 < 0.01 <= v_58).
    "e=0.9": (0.9, 0.01, G, 1.0, 0.0, 0.0, 12.0),
    # A stiff gravity: v_1 = 44.7, rests at the 66th (v_66 = 0.0475); the
    # rebounds of a few m/s last a few milliseconds.
    "g=1000": (0.9, 0.05, 1000.0, 1.0, 0.0, 0.0, 1.0),
    # No rest speed, t1 past t_inf = 8.578: 70 impacts (the budget), all before
    # t_inf, then `max_events_reached`.
    "zeno": (0.9, 0.0, G, 1.0, 0.0, 0.0, 12.0),
    # Elastic: 60 impacts at v_1, the energy kept.
    "e=1": (1.0, 0.0, G, 1.0, 0.0, 0.0, T_ELASTIC),
    # Inelastic: rests at the first impact.
    "e=0": (0.0, 0.0, G, 1.0, 0.0, 0.0, 2.0),
    # A rest speed above the first impact's: rests at the first impact.
    "rest_speed>v_1": (0.5, 5.0, G, 1.0, 0.0, 0.0, 2.0),
    # At rest on the floor (exactly at the gap, zero speed): attached, no event.
    "on_the_floor": (0.5, 0.0, G, 0.0, 0.0, 0.5, 2.0),
    # On the floor moving into it at 1 m/s: an impact at t0, then 0.5^(k-1) m/s,
    # rests at the 8th.
    "into_the_floor": (0.5, 0.01, G, 0.0, -1.0, 0.0, 2.0),
    # On the floor moving up at 1 m/s: the first impact at 2 / g, rests at the 8th.
    "off_the_floor": (0.5, 0.01, G, 0.0, 1.0, 0.0, 2.0),
    # A sweep over restitutions: rests at the 10th, 19th, 29th impact (the last
    # moving sideways, to x = 4: the event's gap margin, which grows with |q|, must
    # not show in the impacts).
    "e=0.5": (0.5, 0.01, G, 1.0, 0.0, 0.0, 4.0),
    "e=0.7": (0.7, 0.01, G, 1.0, 0.0, 0.0, 6.0),
    "e=0.8": (0.8, 0.01, G, 1.0, 0.0, 0.5, 8.0),
}
NAMES = list(CASES)


def _series(e, rest_speed, g, h, w, t1, max_events):
    """The closed form: impact times and approach speeds (at most `max_events`),
    whether the ball rests at the last of them, and the expected result."""
    if h == 0 and w == 0:
        return np.zeros(0), np.zeros(0), True, cjax.RESULTS.successful
    t, v = _flight_end(h, w, g)
    times, speeds = [], []
    while t <= t1:
        if len(times) == max_events:
            return (
                np.asarray(times),
                np.asarray(speeds),
                False,
                cjax.RESULTS.max_events_reached,
            )
        times.append(t)
        speeds.append(v)
        if e == 0 or v < rest_speed:
            return np.asarray(times), np.asarray(speeds), True, cjax.RESULTS.successful
        t, v = t + 2 * e * v / g, e * v
    return np.asarray(times), np.asarray(speeds), False, cjax.RESULTS.successful


def _bounds(times, speeds, e, g, dtype):
    """The relative speed errors and the time errors the impacts may have (see the
    module docstring)."""
    eps = float(np.finfo(dtype).eps)
    tol = max(1e-12, 100 * eps)
    tau = tol * (1 + np.abs(times))
    speed = np.cumsum(g * tau / speeds + 64 * eps)
    flights = np.concatenate([[0.0], np.cumsum(2 * e * speeds * speed / g)[:-1]])
    return speed, np.cumsum(tau) + flights


def _drop(e, rest_speed, g, h, w, u, t1):
    args = {
        "e": e,
        "m": jnp.ones_like(e),
        "g": g,
        "rest_speed": rest_speed,
    }
    q0 = jnp.stack([jnp.zeros_like(h), h])
    qd0 = jnp.stack([u, w])
    return cjax.simulate(
        ball.system(),
        (0.0, t1),
        q0,
        qd0,
        args,
        saveat=cjax.SaveAt(ts=t1 * jnp.linspace(0.0, 1.0, NUM_SAVES)),
        max_events=MAX_EVENTS,
        throw=False,
    )


@pytest.fixture(scope="module")
def batch():
    """Every float64 case in one `jax.vmap` (one compilation), default tolerances."""
    columns = [jnp.asarray(c, float) for c in zip(*CASES.values(), strict=True)]
    return jax.jit(jax.vmap(_drop))(*columns)


@pytest.fixture(scope="module")
def single():
    """The issue's series, unbatched (under `jax.jit` alone only the taken branch of
    each phase runs: the path a single run takes)."""
    return jax.jit(_drop)(*(jnp.asarray(x, float) for x in CASES["e=0.9"]))


def _lane(traj, i):
    return jax.tree.map(lambda x: x[i], traj)


def _check_series(traj, case, dtype, max_events=MAX_EVENTS):
    """Every recorded impact against the closed form, the count, the rest, the
    result and the final state."""
    e, rest_speed, g, h, w, u, t1 = case
    times, speeds, rests, result = _series(e, rest_speed, g, h, w, t1, max_events)
    ev = traj.events
    count = int(ev.count)
    assert _value(traj.result) == _value(result), (traj.result, count, times.size)
    assert count == times.size
    assert np.all(np.asarray(ev.impact[:count])) and np.all(ev.group[:count] == 0)
    # An impact approaches: its speed is positive.
    assert np.all(np.asarray(ev.speed[:count]) > 0)
    speed_error, time_error = _bounds(times, speeds, e, g, dtype)
    np.testing.assert_array_less(
        np.abs(np.asarray(ev.speed[:count], float) - speeds), speeds * speed_error
    )
    np.testing.assert_array_less(
        np.abs(np.asarray(ev.time[:count], float) - times), time_error
    )
    # Only the last impact rests (when the ball rests).
    attached = np.zeros(count, bool)
    if rests and count:
        attached[-1] = True
    np.testing.assert_array_equal(ev.attached[:count], attached)
    assert int(ev.mode) == int(rests)
    eps = float(np.finfo(dtype).eps)
    if rests:
        # At rest on the floor from the rest impact on: y = 0, no vertical speed,
        # the floor pushing with m g (m = 1), x moving on at u.
        t_rest = times[-1] + time_error[-1] if count else 0.0
        after = np.asarray(traj.ts) >= t_rest
        assert after.any()
        np.testing.assert_allclose(traj.q[after, 1], 0.0, atol=64 * eps)
        np.testing.assert_allclose(traj.qd[after, 1], 0.0, atol=64 * eps)
        np.testing.assert_allclose(traj.qd[after, 0], u, rtol=64 * eps)
        np.testing.assert_allclose(traj.multipliers[after, 0], g, rtol=64 * eps)
    # Sideways the ball moves on at u: the impulses are normal to the floor.
    reached = np.all(np.isfinite(np.asarray(traj.q)), axis=1)
    ts = np.asarray(traj.ts)[reached]
    np.testing.assert_allclose(
        traj.q[reached, 0], u * ts, rtol=0, atol=64 * eps * (1 + u * t1)
    )
    if _value(traj.result) == _value(cjax.RESULTS.successful):
        # Never `successful` with saved states that are not finite.
        assert np.all(np.isfinite(np.asarray(traj.q)))
        assert np.all(np.isfinite(np.asarray(traj.qd)))


def _value(result) -> int:
    """The status as an integer (a `RESULTS` member, or its value)."""
    return int(getattr(result, "_value", result))


@pytest.mark.parametrize("name", NAMES)
def test_series_against_the_closed_form(batch, name):
    """Each case, batched: every impact's time and approach speed, the count, the
    impact at which the ball rests, the result, the state at rest."""
    _check_series(_lane(batch, NAMES.index(name)), CASES[name], np.float64)


def test_unbatched_series_rests_at_the_59th_impact(single):
    """The issue's case as a single run: 58 rebounds on the closed form, at rest
    from the 59th impact (v_59 = 0.00983 < rest_speed = 0.01 <= v_58 = 0.0109)."""
    _check_series(single, CASES["e=0.9"], np.float64)
    assert int(single.events.count) == 59


def test_every_impact_approaches(batch):
    """No impact has a non-positive approach speed, and events are in order."""
    for i, name in enumerate(NAMES):
        ev = _lane(batch, i).events
        count = int(ev.count)
        speeds = np.asarray(ev.speed[:count])
        impacts = np.asarray(ev.impact[:count])
        assert np.all(speeds[impacts] > 0), (name, speeds[impacts].min())
        assert np.all(np.diff(np.asarray(ev.time[:count])) >= 0), name


def test_stiff_gravity_is_not_glued_while_rebounding(batch):
    """g = 1000, rest_speed = 0.05: the ball rests at an impact that approaches
    slower than 0.05 m/s (the 66th: v_66 = 0.0475 < 0.05 <= v_65 = 0.0527), never
    while it rebounds at metres per second."""
    ev = _lane(batch, NAMES.index("g=1000")).events
    count = int(ev.count)
    speed = np.asarray(ev.speed[:count])
    rest = np.asarray(ev.attached[:count])
    assert count == 66 and rest[-1] and not rest[:-1].any()
    assert 0 < speed[-1] < 0.05
    assert np.all(speed[:-1] >= 0.05)


def test_zeno_without_rest_speed_spends_the_budget(batch):
    """No rest speed, t1 past t_inf: the documented `max_events_reached`, every
    event before t_inf, nothing saved past the last event, never `successful`."""
    traj = _lane(batch, NAMES.index("zeno"))
    e, _, g, h, w, _, _ = CASES["zeno"]
    t_1, v_1 = _flight_end(h, w, g)
    t_inf = t_1 + 2 * e * v_1 / (g * (1 - e))
    assert traj.result == cjax.RESULTS.max_events_reached
    assert int(traj.events.count) == MAX_EVENTS
    last = float(traj.events.time[-1])
    assert last < t_inf
    after = np.asarray(traj.ts) > last
    assert after.any() and np.all(np.isinf(np.asarray(traj.q[after])))
    assert np.all(np.isfinite(np.asarray(traj.q[~after])))


def test_elastic_series_keeps_the_energy(batch):
    """e = 1: sixty impacts at v_1 (on the closed form, above), and the energy
    m g y + m |qd|^2 / 2 at every save equal to m g h, to the speed bound."""
    traj = _lane(batch, NAMES.index("e=1"))
    e, _, g, h, w, _, t1 = CASES["e=1"]
    times, speeds, _, _ = _series(e, 0.0, g, h, w, t1, MAX_EVENTS)
    assert times.size == int(traj.events.count) == 60
    speed_error, _ = _bounds(times, speeds, e, g, np.float64)
    np.testing.assert_allclose(traj.energy, g * h, rtol=2 * speed_error[-1])


# ---------------------------------------------------------------------------------
# float32 (a subprocess with `jax_enable_x64` off, as a float32 user runs)
# ---------------------------------------------------------------------------------

FLOAT32_CASE = (0.8, 0.2, G, 1.0, 0.0, 0.0, 10.0)
FLOAT32_MAX_EVENTS = 20

_FLOAT32_SCRIPT = textwrap.dedent(
    """
    import json, warnings
    warnings.simplefilter("ignore")
    import jax, jax.numpy as jnp
    import constrained_jax as cjax
    from constrained_jax.scenes import bouncing_ball as ball
    e, rest, g, h, w, u, t1 = CASE
    args = {k: jnp.asarray(v, jnp.float32)
            for k, v in dict(e=e, m=1.0, g=g, rest_speed=rest).items()}
    q0 = jnp.asarray([0.0, h], jnp.float32)
    qd0 = jnp.asarray([u, w], jnp.float32)
    traj = cjax.simulate(ball.system(), (0.0, t1), q0, qd0, args,
        saveat=cjax.SaveAt(ts=jnp.linspace(0.0, t1, 11)), max_events=MAX_EVENTS,
        throw=False)
    ev = traj.events
    out = {"x64": bool(jax.config.jax_enable_x64), "dtype": str(traj.q.dtype),
           "result": int(traj.result._value),
           "ts": traj.ts.tolist(), "q": traj.q.tolist(), "qd": traj.qd.tolist(),
           "multipliers": traj.multipliers.tolist()}
    for k in ("count", "time", "group", "impact", "attached", "speed", "mode"):
        out[k] = getattr(ev, k).tolist()
    print("RESULT" + json.dumps(out))
    """
)


class _Namespace:
    def __init__(self, d):
        self.__dict__.update(d)


@pytest.fixture(scope="module")
def float32_series():
    code = _FLOAT32_SCRIPT.replace("CASE", repr(FLOAT32_CASE)).replace(
        "MAX_EVENTS", str(FLOAT32_MAX_EVENTS)
    )
    proc = run_python(code, timeout=600, JAX_ENABLE_X64="0")
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT")]
    assert proc.returncode == 0 and lines, proc.stderr[-3000:]
    out = json.loads(lines[-1][len("RESULT") :])
    assert not out["x64"] and out["dtype"] == "float32"
    events = _Namespace(
        {k: np.asarray(out[k]) for k in ("time", "group", "impact", "attached")}
    )
    events.speed = np.asarray(out["speed"], np.float32)
    events.count = np.asarray(out["count"])
    events.mode = np.asarray(out["mode"])
    traj = _Namespace({k: np.asarray(out[k]) for k in ("ts", "q", "qd", "multipliers")})
    traj.events, traj.result = events, out["result"]
    return traj


def test_float32_series_rests_at_the_15th_impact(float32_series):
    """float32, e = 0.8, rest_speed = 0.2: fourteen rebounds on the closed form
    (to float32's root-find tolerance), at rest from the 15th impact
    (v_15 = 0.1948 < 0.2 <= v_14 = 0.2435)."""
    _check_series(
        float32_series, FLOAT32_CASE, np.float32, max_events=FLOAT32_MAX_EVENTS
    )
    assert int(float32_series.events.count) == 15


# ---------------------------------------------------------------------------------
# A `Unilateral` with the wrong `sign`: the floor "pulls" at rest, so it lets go at
# once, and the ball falls through the floor.
# ---------------------------------------------------------------------------------


def _wrong_sign(restitution):
    floor = cjax.Unilateral(
        cjax.Holonomic(ball.height),
        sign=-1.0,
        gap=ball.height,
        restitution=restitution,
        rest_speed=0.01 if restitution is not None else 0.0,
    )
    system = cjax.LagrangianSystem(ball.lagrangian, constraints=floor)
    q0, qd0 = ball.state(0.0, 0.5)
    return cjax.simulate(
        system,
        (0.0, 2.0),
        q0,
        qd0,
        ball.default_args(),
        saveat=cjax.SaveAt(ts=jnp.linspace(0.0, 2.0, 5)),
        max_events=None if restitution is None else 8,
        throw=False,
    )


def _floor_run(constraint, sign, h):
    floor = cjax.Unilateral(
        constraint, sign=sign, gap=ball.height, restitution=0.5, rest_speed=0.01
    )
    system = cjax.LagrangianSystem(ball.lagrangian, constraints=floor)
    q0, qd0 = ball.state(h, 0.5)
    return cjax.simulate(
        system, (0.0, 1.0), q0, qd0, ball.default_args(), max_events=4, throw=False
    )


def test_wrong_sign_of_a_free_start_is_refused():
    """The check is of the `Unilateral`, not of the start: a ball dropped from
    above a floor whose `sign` is wrong is refused before it falls."""
    traj = _floor_run(cjax.Holonomic(ball.height), -1.0, 1.0)
    assert traj.result == cjax.RESULTS.contact_sign_mismatch


def test_a_row_written_the_other_way_with_its_sign_runs():
    """`-y = 0` pushes with a negative multiplier: `sign=-1` is its right sign, and
    the ball bounces as with `y = 0` and `sign=+1` (first impact at sqrt(2 h / g)
    with speed sqrt(2 g h), h = 1)."""
    traj = _floor_run(cjax.Holonomic(lambda q, t, args: -q[1]), -1.0, 1.0)
    assert traj.result == cjax.RESULTS.successful
    g = 9.81
    np.testing.assert_allclose(traj.events.time[0], np.sqrt(2 / g), rtol=1e-9)
    np.testing.assert_allclose(traj.events.speed[0], np.sqrt(2 * g), rtol=1e-9)
    # The rebound at e v = v / 2 flies for 2 e v / g = sqrt(2 h / g) again.
    np.testing.assert_allclose(traj.events.time[1], 2 * np.sqrt(2 / g), rtol=1e-8)


def test_wrong_sign_release_is_not_successful():
    """Without `max_events`: refused at the start, naming the sign, never
    `successful` with saved states that are not finite."""
    traj = _wrong_sign(None)
    assert traj.result == cjax.RESULTS.contact_sign_mismatch


def test_wrong_sign_events_name_the_cause():
    """With `max_events`: never `successful`, and not `max_events_reached` either
    (a larger budget does not help)."""
    traj = _wrong_sign(0.5)
    assert traj.result == cjax.RESULTS.contact_sign_mismatch


@pytest.mark.xfail(
    strict=True,
    raises=TypeError,
    reason=(
        "a float32 event run with `jax_enable_x64` on: diffrax's event root find "
        "does `lax.cond(mask, value, lambda: 0.0)`, float32 against float64 "
        "(docs/upstream/diffrax.md, report 3)"
    ),
)
def test_float32_state_with_x64_enabled():
    """float32 inputs keep their precision under `jax_enable_x64` (as `simulate`
    documents): the contact run must run, not raise from inside diffrax."""
    e, rest, g, h, w, u, t1 = FLOAT32_CASE
    args = {
        k: jnp.asarray(v, jnp.float32)
        for k, v in dict(e=e, m=1.0, g=g, rest_speed=rest).items()
    }
    traj = cjax.simulate(
        ball.system(),
        (0.0, 1.0),
        jnp.asarray([0.0, h], jnp.float32),
        jnp.asarray([u, w], jnp.float32),
        args,
        max_events=2,
        throw=False,
    )
    assert traj.q.dtype == jnp.float32
    assert traj.result == cjax.RESULTS.successful


def test_step_gap_is_refused():
    """A careless gap, `jnp.where(y > 0, 1, -1)` ("positive while separated"): its
    rate is zero where it falls through zero, so no impact law applies. Never
    `successful`: refused as `impact_not_approaching` at the step."""
    floor = cjax.Unilateral(
        cjax.Holonomic(ball.height),
        gap=lambda q, t, args: jnp.where(q[1] > 0, 1.0, -1.0),
        restitution=0.5,
    )
    q0, qd0 = ball.state(1.0, 0.5)
    traj = cjax.simulate(
        cjax.LagrangianSystem(ball.lagrangian, constraints=floor),
        (0.0, 2.0),
        q0,
        qd0,
        ball.default_args(),
        saveat=cjax.SaveAt(ts=jnp.linspace(0.0, 2.0, 5)),
        max_events=4,
        throw=False,
    )
    assert traj.result == cjax.RESULTS.impact_not_approaching
    ev = traj.events
    assert int(ev.count) == 1 and not ev.speed[0] > 0
