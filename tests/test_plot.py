"""The plot helpers draw what they are given: the data of every line is checked
against the inputs (hand-built results, no solves: fast), as are the labels, the
release marker and the errors written in the legends."""

import math
import sys

import jax.numpy as jnp
import matplotlib
import numpy as np
import pytest


matplotlib.use("Agg")

from matplotlib.figure import Figure  # noqa: E402

import constrained_jax as cjax  # noqa: E402


def _ax():
    return Figure().subplots()


def _lines(ax):
    """The lines with data (not the legend's empty proxies)."""
    return [line for line in ax.get_lines() if len(line.get_xdata()) > 0]


def _by_label(ax, label):
    (line,) = [line for line in ax.get_lines() if line.get_label() == label]
    return line


def _trajectory(release_time=None, ts=None, multipliers=True):
    """q = (sin t, cos t), qd = (cos t, -sin t), lambda = (1 - t, 2 t)."""
    ts = np.linspace(0.0, 1.0, 11) if ts is None else np.asarray(ts)
    ts_finite = np.where(np.isfinite(ts), ts, 0.0)  # saves after re-contact: inf
    q = np.stack([np.sin(ts_finite), np.cos(ts_finite)], axis=-1)
    qd = np.stack([np.cos(ts_finite), -np.sin(ts_finite)], axis=-1)
    lam = np.stack([1 - ts, 2 * ts], axis=-1)
    forces = np.stack([3 * ts, -ts], axis=-1)
    release = None
    if release_time is not None:
        tr = release_time
        release = cjax.Release(
            released=jnp.asarray(True),
            at_start=jnp.asarray(False),
            time=jnp.asarray(tr),
            q=jnp.asarray([np.sin(tr), np.cos(tr)]),
            qd=jnp.asarray([np.cos(tr), -np.sin(tr)]),
            recontact=jnp.asarray(False),
            recontact_time=jnp.asarray(1.0),
        )
    return cjax.Trajectory(
        ts=jnp.asarray(ts),
        q=jnp.asarray(q),
        qd=jnp.asarray(qd),
        multipliers=jnp.asarray(lam) if multipliers else None,
        constraint_forces=jnp.asarray(forces) if multipliers else None,
        energy=None,
        violation=None,
        result=cjax.RESULTS.successful,
        stats={},
        release=release,
    )


def test_trajectory_lines_are_the_coordinates():
    traj = _trajectory()
    ts = np.linspace(0.0, 1.0, 11)
    ax = cjax.plot.trajectory(traj, ax=_ax())
    lines = _lines(ax)
    assert [line.get_label() for line in lines] == ["$q_{0}$", "$q_{1}$"]
    np.testing.assert_allclose(lines[0].get_xdata(), ts)
    np.testing.assert_allclose(lines[0].get_ydata(), np.sin(ts))
    np.testing.assert_allclose(lines[1].get_ydata(), np.cos(ts))
    assert ax.get_xlabel() == "t"

    ax = cjax.plot.trajectory(traj, coordinates=1, labels=["y"], ax=_ax())
    (line,) = _lines(ax)
    assert line.get_label() == "y"
    np.testing.assert_allclose(line.get_ydata(), np.cos(ts))


def test_trajectory_marks_the_release_time():
    ax = cjax.plot.trajectory(_trajectory(release_time=0.55), ax=_ax())
    (marker,) = [line for line in ax.get_lines() if "release" in line.get_label()]
    np.testing.assert_allclose(marker.get_xdata(), [0.55, 0.55])


def test_multipliers_against_time_with_release_marker():
    traj = _trajectory(release_time=0.55)
    ts = np.linspace(0.0, 1.0, 11)
    ax = cjax.plot.multipliers(traj, ax=_ax())
    lam0 = _by_label(ax, "$\\lambda_{0}$")
    lam1 = _by_label(ax, "$\\lambda_{1}$")
    # The lines break at the release (a NaN between t = 0.5 and t = 0.6): the
    # multipliers jump there, no slope is drawn across the jump.
    broken = lambda a: np.insert(a, 6, np.nan)
    np.testing.assert_allclose(lam0.get_xdata(), broken(ts))
    np.testing.assert_allclose(lam0.get_ydata(), broken(1 - ts))
    np.testing.assert_allclose(lam1.get_ydata(), broken(2 * ts))
    vline = _by_label(ax, "release at 0.55")
    np.testing.assert_allclose(vline.get_xdata(), [0.55, 0.55])
    # A point where the multiplier vanishes: (release, 0).
    (dot,) = [
        line
        for line in ax.get_lines()
        if line.get_marker() == "o" and len(line.get_xdata()) == 1
    ]
    np.testing.assert_allclose([dot.get_xdata()[0], dot.get_ydata()[0]], [0.55, 0.0])


def test_multipliers_against_a_function_marks_release_exactly():
    """`against(q, qd, t)` is evaluated at every save and at the release state."""
    traj = _trajectory(release_time=0.55)
    ts = np.linspace(0.0, 1.0, 11)
    ax = cjax.plot.multipliers(
        traj, against=lambda q, qd, t: q[0], against_label="x", indices=0, ax=_ax()
    )
    (line, *_) = _lines(ax)
    broken = lambda a: np.insert(a, 6, np.nan)  # the break at the release
    np.testing.assert_allclose(line.get_xdata(), broken(np.sin(ts)))
    np.testing.assert_allclose(line.get_ydata(), broken(1 - ts))
    assert ax.get_xlabel() == "x"
    vline = [line for line in ax.get_lines() if "release" in line.get_label()][0]
    np.testing.assert_allclose(vline.get_xdata(), [math.sin(0.55)] * 2, rtol=1e-15)


def test_multipliers_against_an_array_interpolates_the_release():
    traj = _trajectory(release_time=0.55)
    ts = np.linspace(0.0, 1.0, 11)
    ax = cjax.plot.multipliers(traj, against=2 * ts + 1, ax=_ax())
    vline = [line for line in ax.get_lines() if "release" in line.get_label()][0]
    # Linear in time: the interpolation is exact, 2 * 0.55 + 1.
    np.testing.assert_allclose(vline.get_xdata(), [2.1, 2.1], rtol=1e-14)


def test_constraint_forces_and_no_marker_without_release():
    traj = _trajectory()
    ts = np.linspace(0.0, 1.0, 11)
    ax = cjax.plot.multipliers(traj, forces=True, labels=["Qx", "Qy"], ax=_ax())
    np.testing.assert_allclose(_by_label(ax, "Qx").get_ydata(), 3 * ts)
    np.testing.assert_allclose(_by_label(ax, "Qy").get_ydata(), -ts)
    assert not [line for line in ax.get_lines() if "release" in line.get_label()]
    assert "force" in ax.get_ylabel()


def test_saves_after_recontact_are_left_out():
    ts = np.array([0.0, 0.25, 0.5, np.inf, np.inf])
    traj = _trajectory(ts=ts)
    ax = cjax.plot.multipliers(traj, ax=_ax())
    np.testing.assert_allclose(_lines(ax)[0].get_xdata(), ts[:3])
    ax = cjax.plot.trajectory(traj, ax=_ax())
    assert all(len(line.get_xdata()) == 3 for line in _lines(ax))


def test_phase_portrait():
    traj = _trajectory()
    ts = np.linspace(0.0, 1.0, 11)
    ax = cjax.plot.phase_portrait(traj, index=1, label="bob", ax=_ax())
    curve = _by_label(ax, "bob")
    np.testing.assert_allclose(curve.get_xdata(), np.cos(ts))
    np.testing.assert_allclose(curve.get_ydata(), -np.sin(ts))
    start = [line for line in _lines(ax) if len(line.get_xdata()) == 1][0]
    np.testing.assert_allclose([start.get_xdata()[0], start.get_ydata()[0]], [1, 0])
    assert ax.get_xlabel() == "$q_{1}$"


def test_bad_trajectories_are_refused_with_a_fix():
    traj = _trajectory()
    batched = cjax.Trajectory(
        ts=jnp.stack([traj.ts, traj.ts]),
        q=jnp.stack([traj.q, traj.q]),
        qd=jnp.stack([traj.qd, traj.qd]),
        multipliers=None,
        constraint_forces=None,
        energy=None,
        violation=None,
        result=traj.result,
        stats={},
    )
    with pytest.raises(ValueError, match="batched.*jax.tree.map"):
        cjax.plot.trajectory(batched, ax=_ax())
    with pytest.raises(ValueError, match="SaveAt"):
        cjax.plot.multipliers(_trajectory(multipliers=False), ax=_ax())
    with pytest.raises(ValueError, match="one value per saved time"):
        cjax.plot.multipliers(traj, against=np.zeros(3), ax=_ax())
    with pytest.raises(ValueError, match="labels"):
        cjax.plot.trajectory(traj, labels=["only one"], ax=_ax())
    with pytest.raises(ValueError, match="out of range"):
        cjax.plot.phase_portrait(traj, index=5, ax=_ax())
    with pytest.raises(ValueError, match="Trajectory"):
        cjax.plot.trajectory({"q": traj.q}, ax=_ax())


def _fsol(nodes=11):
    """y = x^2 on a piecewise-linear mesh of [0, 1]."""
    x = jnp.linspace(0.0, 1.0, nodes)
    return cjax.FunctionalSolution(
        x=x,
        y=x**2,
        multipliers=cjax.FunctionalMultipliers(integral=jnp.zeros(0), holonomic=None),
        value=jnp.asarray(0.0),
        result=cjax.RESULTS.successful,
        stats={},
        interval=(jnp.asarray(0.0), jnp.asarray(1.0)),
        discretization=cjax.PiecewiseLinear(nodes),
    )


def test_functional_solution_with_reference_and_error():
    """Linear interpolation of x^2 with spacing h errs by h^2/4 at the midpoints
    (hit by the 401-point grid): the legend says 2.5e-03."""
    fsol = _fsol()
    fig = Figure()
    top, bottom = fig.subplots(2, 1)
    ax = cjax.plot.functional_solution(
        fsol, reference=lambda x: x**2, points=401, ax=top, error_ax=bottom
    )
    xs = np.linspace(0.0, 1.0, 401)
    curve = _by_label(ax, "$y$")
    np.testing.assert_allclose(curve.get_xdata(), xs)
    np.testing.assert_allclose(curve.get_ydata(), np.interp(xs, fsol.x, fsol.y))
    nodes = _by_label(ax, "nodes (11)")
    np.testing.assert_allclose(nodes.get_xdata(), fsol.x)
    np.testing.assert_allclose(nodes.get_ydata(), fsol.y)
    (ref,) = [line for line in ax.get_lines() if "closed form" in line.get_label()]
    np.testing.assert_allclose(ref.get_ydata(), xs**2)
    assert "max error 2.5e-03" in ref.get_label()
    (err,) = bottom.get_lines()
    expected = np.abs(np.interp(xs, fsol.x, fsol.y) - xs**2)
    # (Exact zeros, at the nodes, are left out: NaN on a log scale.)
    np.testing.assert_allclose(np.nan_to_num(err.get_ydata()), expected, atol=1e-15)
    assert bottom.get_yscale() == "log"


def test_functional_solution_vector_valued_and_errors():
    x = jnp.linspace(0.0, 1.0, 5)
    fsol = cjax.FunctionalSolution(
        x=x,
        y=jnp.stack([x, 1 - x], axis=-1),
        multipliers=cjax.FunctionalMultipliers(integral=jnp.zeros(0), holonomic=None),
        value=jnp.asarray(0.0),
        result=cjax.RESULTS.successful,
        stats={},
        interval=(jnp.asarray(0.0), jnp.asarray(1.0)),
        discretization=cjax.PiecewiseLinear(5),
    )
    ax = cjax.plot.functional_solution(fsol, points=11, ax=_ax())
    np.testing.assert_allclose(
        _by_label(ax, "$y_{1}$").get_ydata(), 1 - np.linspace(0, 1, 11)
    )
    with pytest.raises(ValueError, match="reference"):
        cjax.plot.functional_solution(fsol, reference=lambda x: x, points=11, ax=_ax())
    with pytest.raises(ValueError, match="needs a `reference`"):
        cjax.plot.functional_solution(fsol, error_ax=_ax(), ax=_ax())
    with pytest.raises(ValueError, match="FunctionalSolution"):
        cjax.plot.functional_solution(_trajectory(), ax=_ax())


def test_work_precision():
    records = {
        "A": ([1e-3, 1e-6], [0.1, 0.2], ["tol 1e-3", "tol 1e-6"]),
        "B": ([1e-2, 1e-4], [0.05, 0.3]),
    }
    ax = cjax.plot.work_precision(records, annotate=True, ax=_ax())
    a, b = _by_label(ax, "A"), _by_label(ax, "B")
    np.testing.assert_allclose(a.get_xdata(), [0.1, 0.2])
    np.testing.assert_allclose(a.get_ydata(), [1e-3, 1e-6])
    np.testing.assert_allclose(b.get_xdata(), [0.05, 0.3])
    assert ax.get_xscale() == ax.get_yscale() == "log"
    assert sorted(t.get_text() for t in ax.texts) == ["tol 1e-3", "tol 1e-6"]
    for bad, match in [
        ({}, "non-empty"),
        ({"A": ([1e-3], [0.1, 0.2])}, "same length"),
        ({"A": ([0.0], [0.1])}, "zero, negative or not finite"),
        ({"A": ([np.nan], [0.1])}, "zero, negative or not finite"),
        ({"A": ([1e-3],)}, "errors, seconds"),
    ]:
        with pytest.raises(ValueError, match=match):
            cjax.plot.work_precision(bad, ax=_ax())


def test_extremum_2d_on_the_circle():
    """Maximize x + y on the unit circle: x* = (s, s), s = 1/sqrt(2), lambda = -s;
    grad F = (1, 1) = -lambda grad G. The constraint curve is the circle, the level
    through x* the tangent line x + y = sqrt(2)."""
    s = 1 / math.sqrt(2)
    fn = lambda x, args: x[0] + x[1]
    circle = lambda x, args: x[0] ** 2 + x[1] ** 2 - 1
    sol = cjax.Extremum(
        x=jnp.asarray([s, s]),
        multipliers=jnp.asarray([-s]),
        value=jnp.asarray(2 * s),
        kind=cjax.EXTREMUM.maximum,
        result=cjax.RESULTS.successful,
        stats={},
    )
    ax = cjax.plot.extremum_2d(
        fn, circle, sol, None, span=0.6, equal_aspect=True, ax=_ax()
    )
    star = [line for line in ax.get_lines() if line.get_marker() == "*"][0]
    np.testing.assert_allclose([star.get_xdata()[0], star.get_ydata()[0]], [s, s])
    contour_sets = [c for c in ax.collections if hasattr(c, "levels")]
    (constraint,) = [c for c in contour_sets if list(c.levels) == [0.0]]
    vertices = np.concatenate([p.vertices for p in constraint.get_paths()])
    assert len(vertices) > 10
    # Linear interpolation on a 121-point grid of width 1.2: error ~ h^2 = 1e-4.
    np.testing.assert_allclose(np.hypot(*vertices.T), 1.0, atol=1e-3)
    (level,) = [c for c in contour_sets if np.allclose(list(c.levels), [math.sqrt(2)])]
    vertices = np.concatenate([p.vertices for p in level.get_paths()])
    np.testing.assert_allclose(vertices.sum(axis=1), math.sqrt(2), atol=1e-12)
    # Two arrows from x*, both along (1, 1), with the same head (they are equal).
    arrows = [t for t in ax.texts if getattr(t, "arrow_patch", None) is not None]
    assert len(arrows) == 2
    heads = np.array([a.xy for a in arrows])
    tails = np.array([a.xyann for a in arrows])
    np.testing.assert_allclose(tails, [[s, s], [s, s]])
    np.testing.assert_allclose(heads[0], heads[1], atol=1e-12)
    direction = heads[0] - tails[0]
    np.testing.assert_allclose(direction / np.linalg.norm(direction), [s, s])
    assert ax.get_aspect() == 1.0
    # By default each axis has its own scale, and its own span (80% of |x_i|).
    ax = cjax.plot.extremum_2d(fn, circle, sol, None, ax=_ax())
    assert ax.get_aspect() == "auto"
    np.testing.assert_allclose(ax.get_xlim(), [0.2 * s, 1.8 * s])


def test_extremum_2d_needs_a_flat_point():
    sol = cjax.Extremum(
        x={"a": jnp.asarray(1.0)},
        multipliers=jnp.asarray([1.0]),
        value=jnp.asarray(0.0),
        kind=cjax.EXTREMUM.maximum,
        result=cjax.RESULTS.successful,
        stats={},
    )
    with pytest.raises(ValueError, match="1-D array"):
        cjax.plot.extremum_2d(lambda x, a: 0.0, lambda x, a: 0.0, sol, None)


def test_without_matplotlib_the_message_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib.pyplot", None)
    with pytest.raises(ImportError, match=r"constrained_jax\[plot\]"):
        cjax.plot.trajectory(_trajectory())


def test_a_new_figure_when_no_axes_are_given():
    import matplotlib.pyplot as plt

    try:
        ax = cjax.plot.phase_portrait(_trajectory())
        assert ax.figure is not None and len(_lines(ax)) == 2
    finally:
        plt.close("all")
