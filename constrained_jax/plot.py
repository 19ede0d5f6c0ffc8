"""Plot helpers for the results of the library (matplotlib).

matplotlib is an optional dependency, imported only when a function here is called:
install it with `pip install constrained_jax[plot]`.

Every function takes `ax=None` (draw on a new figure when `None`, else on the given
`matplotlib.axes.Axes`) and returns the axes it drew on, so that pictures compose:

```python
import matplotlib.pyplot as plt
fig, (left, right) = plt.subplots(1, 2)
cjax.plot.trajectory(traj, ax=left)
cjax.plot.multipliers(traj, against=lambda q, qd, t: q[1], ax=right)
```

Results are plotted one at a time: a batched result (from `jax.vmap`) raises a
`ValueError` saying how to pick one (`jax.tree.map(lambda x: x[i], traj)`).
Saved times that are not finite (after a re-contact, see
[`constrained_jax.Release`][]) are left out.
"""

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


_INSTALL = (
    "The plot helpers need matplotlib, an optional dependency of constrained_jax: "
    'install it with `pip install "constrained_jax[plot]"` (or `pip install '
    "matplotlib`)."
)


def _pyplot():
    try:
        import matplotlib.pyplot as plt
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError(_INSTALL) from e
    return plt


def _axes(ax):
    if ax is None:
        _, ax = _pyplot().subplots()
    return ax


def _check_trajectory(traj, what: str):
    # Imported here to keep `import constrained_jax.plot` light and cycle-free.
    from ._simulate import Trajectory

    if not isinstance(traj, Trajectory):
        raise ValueError(
            f"`{what}` takes a `cjax.Trajectory` (from `cjax.simulate`), got "
            f"{type(traj).__name__}."
        )
    if np.ndim(traj.q) != 2:
        raise ValueError(
            f"`{what}` plots one trajectory, but this one is batched (q has shape "
            f"{np.shape(traj.q)}, expected (T, n)). Pick one, e.g. "
            "`jax.tree.map(lambda x: x[i], traj)`."
        )


def _finite_times(traj):
    ts = np.asarray(traj.ts)
    return np.isfinite(ts)


def _names(labels, count: int, default: Callable[[int], str], what: str):
    if labels is None:
        return [default(i) for i in range(count)]
    labels = list(labels)
    if len(labels) != count:
        raise ValueError(f"`labels` has {len(labels)} entries but {what} has {count}.")
    return labels


def _indices(indices, size: int, what: str) -> list[int]:
    if indices is None:
        return list(range(size))
    if isinstance(indices, int | np.integer):
        indices = [indices]
    indices = [int(i) for i in indices]
    for i in indices:
        if not -size <= i < size:
            raise ValueError(f"index {i} out of range: {what} has {size} components.")
    return indices


def trajectory(
    traj,
    *,
    coordinates: int | Sequence[int] | None = None,
    labels: Sequence[str] | None = None,
    ax=None,
):
    """The generalized coordinates `q_sigma(t)` of a [`constrained_jax.Trajectory`][]
    against time, one line per coordinate.

    **Arguments:**

    - `traj`: one trajectory (not batched).
    - `coordinates`: an index or a sequence of indices into `q`; all by default.
    - `labels`: a name per plotted coordinate (default `q_0`, `q_1`, ...).
    - `ax`: the axes to draw on (a new figure when `None`).

    **Returns:** the `matplotlib.axes.Axes`. If the run was released, a dotted
    vertical line marks the release time.
    """
    _check_trajectory(traj, "trajectory")
    ax = _axes(ax)
    keep = _finite_times(traj)
    ts, q = np.asarray(traj.ts)[keep], np.asarray(traj.q)[keep]
    index = _indices(coordinates, q.shape[1], "q")
    names = _names(labels, len(index), lambda i: f"$q_{{{index[i]}}}$", "coordinates")
    for i, name in zip(index, names, strict=True):
        ax.plot(ts, q[:, i], label=name)
    _mark_release_time(ax, traj)
    ax.set_xlabel("t")
    ax.set_ylabel("q")
    ax.legend()
    return ax


def _released(traj) -> bool:
    release = traj.release
    return release is not None and bool(np.asarray(release.released))


def _mark_release_time(ax, traj):
    if _released(traj):
        ax.axvline(
            float(traj.release.time),
            color="0.4",
            linestyle=":",
            label=f"release, t = {float(traj.release.time):.4g}",
        )


def multipliers(
    traj,
    *,
    against: Any = None,
    against_label: str | None = None,
    indices: int | Sequence[int] | None = None,
    labels: Sequence[str] | None = None,
    forces: bool = False,
    mark_release: bool = True,
    ax=None,
):
    """The multipliers `lambda_j` (or the constraint forces `Q^c = A^T lambda`) of a
    [`constrained_jax.Trajectory`][], against time or against another quantity.

    **Arguments:**

    - `traj`: one trajectory, simulated with `SaveAt(..., multipliers=True)`.
    - `against`: the horizontal axis. `None`: time. An array of shape `(T,)` (one
        value per saved time), or a function `against(q, qd, t) -> scalar` (e.g.
        `lambda q, qd, t: q[1]` for an angle) evaluated at every saved state.
    - `against_label`: the horizontal axis' label (default `t`, or `x`).
    - `indices`: which multipliers (or force components) to plot; all by default.
    - `labels`: a name per plotted line (default `lambda_j`, or `Q^c_sigma`).
    - `forces`: plot `traj.constraint_forces` (one line per coordinate) instead of
        the multipliers (one per constraint row).
    - `mark_release`: if the run has a [`constrained_jax.Release`][] that released,
        mark it: a dashed vertical line and a point on the axis (the multiplier
        vanishes there). Its horizontal position is the release time, `against`
        evaluated at the release state if `against` is a function (exact), or
        `against` interpolated linearly in time at the release time if it is an
        array (as accurate as the save grid).
    - `ax`: the axes to draw on (a new figure when `None`).

    **Returns:** the `matplotlib.axes.Axes`.
    """
    _check_trajectory(traj, "multipliers")
    values = traj.constraint_forces if forces else traj.multipliers
    if values is None:
        raise ValueError(
            "This trajectory has no multipliers: simulate with "
            "`saveat=cjax.SaveAt(ts=..., multipliers=True)`."
        )
    ax = _axes(ax)
    keep = _finite_times(traj)
    values = np.asarray(values)[keep]
    ts = np.asarray(traj.ts)
    if against is None:
        x, default_label = ts[keep], "t"
        release_x = lambda rel: float(rel.time)
    elif callable(against):
        fn = jax.vmap(against)
        x = np.asarray(fn(traj.q[keep], traj.qd[keep], traj.ts[keep]))
        default_label = "x"

        def release_x(rel):
            return float(np.asarray(against(rel.q, rel.qd, rel.time)))
    else:
        x = np.asarray(against)
        if x.shape != ts.shape:
            raise ValueError(
                f"`against` has shape {x.shape}, but the trajectory has {ts.shape[0]} "
                "saved times: pass one value per saved time, or a function "
                "`against(q, qd, t)`."
            )
        x, default_label = x[keep], "x"

        def release_x(rel):
            return float(np.interp(float(rel.time), ts[keep], x))

    if x.shape != (values.shape[0],):
        raise ValueError(
            f"`against` must give one scalar per saved time, got shape {x.shape}."
        )
    symbol = (
        (lambda i: f"$Q^c_{{{i}}}$") if forces else (lambda i: f"$\\lambda_{{{i}}}$")
    )
    index = _indices(indices, values.shape[1], "the forces" if forces else "lambda")
    names = _names(labels, len(index), lambda i: symbol(index[i]), "the selection")
    released = _released(traj)
    xr = release_x(traj.release) if released else None
    if released:
        # The multipliers jump at the release (the released rows drop to zero):
        # break the lines there instead of drawing a slope across the jump.
        cut = int(np.searchsorted(ts[keep], float(traj.release.time), side="right"))
        if 0 < cut < x.shape[0]:
            x = np.insert(np.asarray(x, float), cut, np.nan)
            values = np.insert(np.asarray(values, float), cut, np.nan, axis=0)
    for i, name in zip(index, names, strict=True):
        ax.plot(x, values[:, i], label=name)
    ax.axhline(0.0, color="0.8", linewidth=0.8, zorder=0)
    if mark_release and released:
        ax.axvline(xr, color="0.3", linestyle="--", label=f"release at {xr:.6g}")
        ax.plot([xr], [0.0], marker="o", color="k", linestyle="none")
    ax.set_xlabel(against_label or default_label)
    ax.set_ylabel("constraint force $Q^c$" if forces else "multiplier $\\lambda$")
    ax.legend()
    return ax


def phase_portrait(traj, index: int = 0, *, label: str | None = None, ax=None):
    """The phase portrait `(q_index, qdot_index)` of a
    [`constrained_jax.Trajectory`][]; the start is marked with a point.

    **Returns:** the `matplotlib.axes.Axes`.
    """
    _check_trajectory(traj, "phase_portrait")
    (i,) = _indices(index, np.shape(traj.q)[1], "q")
    ax = _axes(ax)
    keep = _finite_times(traj)
    q, qd = np.asarray(traj.q)[keep, i], np.asarray(traj.qd)[keep, i]
    (line,) = ax.plot(q, qd, label=label)
    ax.plot(q[:1], qd[:1], marker="o", color=line.get_color(), linestyle="none")
    ax.set_xlabel(f"$q_{{{i}}}$")
    ax.set_ylabel(f"$\\dot q_{{{i}}}$")
    if label is not None:
        ax.legend()
    return ax


def functional_solution(
    fsol,
    *,
    reference: Callable | None = None,
    points: int = 400,
    labels: Sequence[str] | None = None,
    error_ax=None,
    ax=None,
):
    """`y(x)` of a [`constrained_jax.FunctionalSolution`][]: the interpolant on a fine
    grid (`points` values) and the nodes as dots; with a closed form, overlaid
    (dashed) and its error.

    **Arguments:**

    - `fsol`: one solution (not batched); `y` of shape `(N,)` or `(N, n)` (one line
        per component).
    - `reference`: the closed form, `reference(x) -> (len(x),)` or `(len(x), n)`
        (NumPy or JAX). The largest deviation on the grid is written in the legend.
    - `labels`: a name per component (default `y`, or `y_0`, `y_1`, ...).
    - `error_ax`: if given (and `reference` too), the pointwise error
        `|y(x) - reference(x)|` is drawn there on a log scale.
    - `ax`: the axes to draw on (a new figure when `None`).

    **Returns:** the `matplotlib.axes.Axes` of `y(x)`.
    """
    from ._functional import FunctionalSolution

    if not isinstance(fsol, FunctionalSolution):
        raise ValueError(
            "`functional_solution` takes a `cjax.FunctionalSolution` (from "
            f"`cjax.solve_functional`), got {type(fsol).__name__}."
        )
    if np.ndim(fsol.x) != 1:
        raise ValueError(
            "`functional_solution` plots one solution, but this one is batched (x has "
            f"shape {np.shape(fsol.x)}). Pick one, e.g. "
            "`jax.tree.map(lambda a: a[i], fsol)`."
        )
    if error_ax is not None and reference is None:
        raise ValueError("`error_ax` needs a `reference` to compare with.")
    ax = _axes(ax)
    nodes = np.asarray(fsol.x)
    y_nodes = np.asarray(fsol.y).reshape(nodes.shape[0], -1)
    n = y_nodes.shape[1]
    xs = np.linspace(nodes[0], nodes[-1], points)
    ys = np.asarray(fsol(jnp.asarray(xs, fsol.y.dtype))).reshape(points, n)
    default = (lambda i: "$y$") if np.ndim(fsol.y) == 1 else (lambda i: f"$y_{{{i}}}$")
    names = _names(labels, n, default, "y")
    ref = None
    if reference is not None:
        ref = np.asarray(reference(xs), dtype=np.float64)
        if ref.size != ys.size:
            raise ValueError(
                f"`reference(x)` returned shape {ref.shape} for {points} points; "
                f"expected ({points},) or ({points}, {n})."
            )
        ref = ref.reshape(points, n)
    for i, name in enumerate(names):
        (line,) = ax.plot(xs, ys[:, i], label=name)
        ax.plot(
            nodes,
            y_nodes[:, i],
            marker=".",
            linestyle="none",
            color=line.get_color(),
            label=f"nodes ({nodes.shape[0]})" if i == 0 else None,
        )
        if ref is not None:
            err = float(np.max(np.abs(ys[:, i] - ref[:, i])))
            ax.plot(
                xs,
                ref[:, i],
                linestyle="--",
                color="k",
                linewidth=1.0,
                label=f"closed form (max error {err:.1e})",
            )
    if error_ax is not None:
        for i, name in enumerate(names):
            err = np.abs(ys[:, i] - ref[:, i])
            # Exact zeros (at the fixed ends) cannot be drawn on a log scale.
            error_ax.semilogy(xs, np.where(err > 0, err, np.nan), label=name)
        error_ax.set_xlabel("x")
        error_ax.set_ylabel("|y - closed form|")
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.legend()
    return ax


def work_precision(
    records: Mapping[str, Sequence],
    *,
    annotate: bool = False,
    ax=None,
):
    """A work-precision diagram: error against wall time, log-log, one line per
    method.

    **Arguments:**

    - `records`: maps a label (a method) to `(errors, seconds)`, two sequences of
        the same length (one point per tolerance or step size), or to
        `(errors, seconds, point_labels)` to name each point (e.g. the tolerance).
        Errors and times must be positive and finite (a log scale cannot show zero).
    - `annotate`: write the point labels next to the points.
    - `ax`: the axes to draw on (a new figure when `None`).

    **Returns:** the `matplotlib.axes.Axes`. Lower left is better.
    """
    if not isinstance(records, Mapping) or not records:
        raise ValueError(
            "`records` must be a non-empty mapping label -> (errors, seconds)."
        )
    checked = {}
    for label, record in records.items():
        if len(record) not in (2, 3):
            raise ValueError(
                f"records[{label!r}] must be (errors, seconds) or (errors, seconds, "
                f"point_labels), got {len(record)} entries."
            )
        errors = np.asarray(record[0], dtype=np.float64).reshape(-1)
        seconds = np.asarray(record[1], dtype=np.float64).reshape(-1)
        names = list(record[2]) if len(record) == 3 else None
        if errors.shape != seconds.shape or (
            names is not None and len(names) != errors.shape[0]
        ):
            raise ValueError(
                f"records[{label!r}]: errors, seconds (and point labels) must have "
                f"the same length, got {errors.shape[0]} and {seconds.shape[0]}."
            )
        bad = ~(np.isfinite(errors) & np.isfinite(seconds))
        bad |= (errors <= 0) | (seconds <= 0)
        if np.any(bad):
            raise ValueError(
                f"records[{label!r}] has errors or times that are zero, negative or "
                "not finite; a log-log diagram cannot show them (drop those points, "
                "or floor exact zeros at the round-off level)."
            )
        checked[label] = (errors, seconds, names)
    ax = _axes(ax)
    for label, (errors, seconds, names) in checked.items():
        ax.loglog(seconds, errors, marker="o", label=label)
        if annotate and names is not None:
            for e, s, name in zip(errors, seconds, names, strict=True):
                ax.annotate(
                    str(name),
                    (s, e),
                    textcoords="offset points",
                    xytext=(4, 4),
                    fontsize="small",
                )
    ax.set_xlabel("wall time [s]")
    ax.set_ylabel("error")
    ax.grid(True, which="major", alpha=0.3)
    ax.legend()
    return ax


def extremum_2d(
    fn: Callable,
    constraints: Callable,
    sol,
    args=None,
    *,
    plane: tuple[int, int] = (0, 1),
    span: float | tuple[float, float] | None = None,
    equal_aspect: bool = False,
    resolution: int = 121,
    levels: int = 20,
    ax=None,
):
    """A constrained extremum in a plane: contours of `F`, the constraint curves
    `G_j = 0`, the level of `F` through the extremum (tangent to the constraint
    there), the extremum, and the gradients `grad F` and `-lambda_j grad G_j` there
    (with one constraint they are equal: the arrows coincide).

    **Arguments:**

    - `fn`, `constraints`: `F(x, args)` and `G(x, args)` as passed to
        [`constrained_jax.extremize`][]; `x` must be a 1-D array.
    - `sol`: the [`constrained_jax.Extremum`][].
    - `args`: the parameters used for the solve.
    - `plane`: the two coordinates spanning the picture; the others are held at
        `sol.x` (the picture is the slice through the extremum).
    - `span`: half-width of the box around the extremum, one number or one per
        axis (default: 80% of each coordinate's magnitude, at least 0.1; with
        `equal_aspect`, 80% of the larger one for both).
    - `equal_aspect`: draw both axes to the same scale, so that the gradients are
        seen perpendicular to the level curves (off by default: coordinates of
        different scales would give a thin strip).
    - `resolution`: grid points per side; `levels`: number of contour levels
        (spread between the 2nd and 98th percentiles of `F` in the box).
    - `ax`: the axes to draw on (a new figure when `None`).

    **Returns:** the `matplotlib.axes.Axes`.
    """
    x = sol.x
    if not (hasattr(x, "ndim") and x.ndim == 1):
        raise ValueError(
            "`extremum_2d` needs `sol.x` to be one 1-D array (not batched, not a "
            f"pytree); got {jax.tree.structure(x)} with shapes "
            f"{[np.shape(leaf) for leaf in jax.tree.leaves(x)]}."
        )
    i, j = _indices(plane, x.shape[0], "x")
    if len({i % x.shape[0], j % x.shape[0]}) != 2:
        raise ValueError(f"`plane` must name two different coordinates, got {plane}.")
    x_np = np.asarray(x, dtype=np.float64)
    if span is None and equal_aspect:
        span = max(0.8 * max(abs(x_np[i]), abs(x_np[j])), 0.1)
    elif span is None:
        span = (max(0.8 * abs(x_np[i]), 0.1), max(0.8 * abs(x_np[j]), 0.1))
    if np.ndim(span) == 0:
        span = (float(span), float(span))
    u = np.linspace(x_np[i] - span[0], x_np[i] + span[0], resolution)
    v = np.linspace(x_np[j] - span[1], x_np[j] + span[1], resolution)
    uu, vv = np.meshgrid(u, v)
    points = np.broadcast_to(x_np, (uu.size, x_np.shape[0])).copy()
    points[:, i], points[:, j] = uu.ravel(), vv.ravel()
    points = jnp.asarray(points, x.dtype)

    def g(z, args):
        return jnp.atleast_1d(constraints(z, args))

    @eqx.filter_jit
    def evaluate(points, x, args):
        # One compiled program (eager evaluation would compile every operation).
        f_grid = jax.vmap(lambda z: fn(z, args))(points)
        g_grid = jax.vmap(lambda z: g(z, args))(points)
        return f_grid, g_grid, jax.grad(fn)(x, args), jax.jacfwd(g)(x, args)

    f_grid, g_grid, grad_f, jac_g = (np.asarray(a) for a in evaluate(points, x, args))
    f_grid = f_grid.reshape(uu.shape)
    g_grid = g_grid.reshape(uu.shape + (-1,))
    lam = np.asarray(sol.multipliers).reshape(-1)

    ax = _axes(ax)
    value = float(fn(x, args))
    # Levels spread over the bulk of the values in the box (not its extremes).
    lo, hi = np.percentile(f_grid, [2, 98])
    contours = ax.contour(
        uu, vv, f_grid, levels=np.linspace(lo, hi, levels), cmap="viridis"
    )
    ax.clabel(contours, fontsize="x-small")
    # The level through the extremum: tangent to the constraint there.
    ax.contour(
        uu, vv, f_grid, levels=[value], colors="k", linewidths=1.5, linestyles="--"
    )
    ax.plot([], [], "k--", label=f"level F = {value:.4g}")
    for k in range(g_grid.shape[-1]):
        ax.contour(uu, vv, g_grid[..., k], levels=[0.0], colors="C3")
    ax.plot([], [], color="C3", label="constraint $G = 0$")
    ax.plot(
        [x_np[i]],
        [x_np[j]],
        marker="*",
        markersize=12,
        color="k",
        linestyle="none",
        label=f"extremum ({x_np[i]:.4g}, {x_np[j]:.4g})",
    )
    # Arrows scaled together so that the longer one is a quarter of the box.
    arrows = [grad_f[[i, j]]] + [-lam[k] * jac_g[k, [i, j]] for k in range(len(lam))]
    longest = max(float(np.hypot(*a)) for a in arrows) or 1.0
    scale = 0.25 * min(span) / longest
    names = ["$\\nabla F$"] + [
        f"$-\\lambda_{{{k}}} \\nabla G_{{{k}}}$" for k in range(len(lam))
    ]
    for k, (arrow, name) in enumerate(zip(arrows, names, strict=True)):
        ax.annotate(
            "",
            xy=(x_np[i] + scale * arrow[0], x_np[j] + scale * arrow[1]),
            xytext=(x_np[i], x_np[j]),
            arrowprops={
                "arrowstyle": "->",
                "color": f"C{k}",
                "linewidth": 2.5 - 1.0 * min(k, 1),
            },
        )
        ax.plot([], [], color=f"C{k}", label=name)
    ax.set_xlabel(f"$x_{{{i}}}$")
    ax.set_ylabel(f"$x_{{{j}}}$")
    if equal_aspect:
        ax.set_aspect("equal")
    ax.legend(fontsize="small")
    return ax
