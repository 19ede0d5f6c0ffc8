"""Watching a `Unilateral`'s multiplier inside the steps, and finding event times:
the wrapped diffrax solver of the phases with attached contacts (`WatchedSolver`) and
the bracketed root finder of their events (`Illinois`)."""

from collections.abc import Callable

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float, Int

from ._compat import component_dense_info, runge_kutta_stages, stage_derivatives
from ._wrapped_solver import AbstractForwardingSolver


# Where the watched multiplier of a `Unilateral` is sampled inside each step of a
# phase with attached contacts (fractions of the step), besides its end, when the
# solver's stages cannot be read (see `WatchedSolver`).
_WATCH_SAMPLES = (1 / 3, 2 / 3)
# A step of the attached phase is refined while the multiplier at the samples departs
# from the chord between its end values by more than this fraction of the larger end
# value (it is then not resolved well enough to trust its sign between samples).
_WATCH_ROUGHNESS = 0.25
# The widest gap, as a fraction of the step, between the points at which the watched
# multiplier is known inside a step of a Runge-Kutta solver (its stage times and the
# extra samples on the dense output).
_WATCH_GAP = 0.3


class IllinoisState(eqx.Module):
    lower: Float[Array, ""]
    upper: Float[Array, ""]
    f_lower: Float[Array, ""]
    f_upper: Float[Array, ""]
    side: Int[Array, ""]
    t: Float[Array, ""]
    f: Float[Array, ""]
    stage: Int[Array, ""]  # 0: evaluate `lower`, 1: `upper`, 2: secant steps


class Illinois(optx.AbstractRootFinder):
    """The release (and re-contact) time: a bracketed secant (Illinois) root find
    along the dense output of the step where the event changed sign.

    Derivative-free (Newton would differentiate the KKT solve along the
    interpolation: a copy of its derivative in the program for nothing), and never
    leaves the bracket `[lower, upper]` that diffrax passes in `options`. The event
    function is evaluated once per step, at one point (the bracket's ends at the first
    two steps, the new iterate after), so that it is traced once and not batched (a
    `jax.vmap` over two points would turn the `lax.cond`s of the KKT solve inside it
    into selects that run, and compile, both branches). It stops when the bracket,
    which always holds the sign change, is narrower than `atol + rtol |t|` (or has
    shrunk to round-off, or at an exact zero), so the time returned is within that
    of a crossing. Never on a small value: the event function is a gap (a length) or
    a multiplier (a force), not a time, and a gap that starts a phase at `delta` below
    `atol` would pass such a test before any crossing. Illinois moves both ends, so
    the bracket shrinks superlinearly (order about 1.44). diffrax zeroes all event
    values but the triggered one's: their sum is the function whose root is found.
    """

    rtol: float
    atol: float
    norm: Callable = jnp.abs

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        del y, fn, args, f_struct, aux_struct, tags
        dtype = jnp.result_type(options["lower"])
        lower = jnp.asarray(options["lower"], dtype)
        upper = jnp.asarray(options["upper"], dtype)
        inf = jnp.asarray(jnp.inf, dtype)
        return IllinoisState(
            lower, upper, inf, inf, jnp.array(0), upper, inf, jnp.array(0)
        )

    @staticmethod
    def _secant(a, b, fa, fb):
        denominator = jnp.where(fb == fa, 1, fb - fa)
        # (A sign change, or a root at an end, is given; the clip guards round-off.)
        secant = jnp.clip(
            (a * fb - b * fa) / denominator, jnp.minimum(a, b), jnp.maximum(a, b)
        )
        return jnp.where(fb == 0, b, jnp.where(fa == 0, a, secant))

    def step(self, fn, y, args, options, state, tags):
        del y, options, tags
        a, b, fa, fb = state.lower, state.upper, state.f_lower, state.f_upper
        stage = state.stage
        t = jnp.where(
            stage == 0, a, jnp.where(stage == 1, b, self._secant(a, b, fa, fb))
        )
        values, aux = fn(t, args)
        f = sum(jnp.asarray(v, t.dtype) for v in jax.tree.leaves(values))
        # `t` replaces the end whose value has the same sign; an end kept twice in a
        # row has its value halved (Illinois), so that both ends converge.
        replace_upper = jnp.sign(f) == jnp.sign(fb)
        side = jnp.where(replace_upper, -1, 1)
        halve = jnp.where(side == state.side, 0.5, 1.0)
        update = IllinoisState(
            lower=jnp.where(replace_upper, a, t),
            upper=jnp.where(replace_upper, t, b),
            f_lower=jnp.where(replace_upper, halve * fa, f),
            f_upper=jnp.where(replace_upper, f, halve * fb),
            side=side,
            t=t,
            f=f,
            stage=jnp.array(2),
        )
        # The first two steps only record `f(lower)`, then `f(upper)`; a root found
        # at `lower` ends the search there (`f == 0`, `terminate`).
        at_lower = IllinoisState(a, b, f, fb, jnp.array(0), a, f, jnp.array(1))
        at_upper = IllinoisState(a, b, fa, f, jnp.array(0), b, f, jnp.array(2))
        new = jax.tree.map(
            lambda x, y_, z: jnp.where(stage == 0, x, jnp.where(stage == 1, y_, z)),
            at_lower,
            at_upper,
            update,
        )
        return t, new, aux

    def terminate(self, fn, y, args, options, state, tags):
        del fn, args, options, tags
        width = jnp.abs(state.upper - state.lower)
        narrow = width <= self.atol + self.rtol * jnp.abs(y)
        eps = jnp.finfo(jnp.result_type(y)).eps
        collapsed = width <= 4 * eps * jnp.maximum(
            jnp.abs(state.upper), jnp.abs(state.lower)
        )
        done = narrow | collapsed
        # (Before both ends are evaluated only an exact root stops it.)
        started = state.stage == 2
        return (started & done) | (state.f == 0), optx.RESULTS.successful

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return y, aux, {}


class WatchedSolver(AbstractForwardingSolver):
    """The attached phase's solver: samples the watched multiplier inside each step.

    diffrax evaluates an event condition only at the ends of the steps, and the state
    of an attached motion can be so smooth (even exactly linear: a body resting on a
    floor) that the controller takes steps far longer than the time the multiplier
    stays of one sign. So each step also looks at the multiplier inside the step, and

    - a step whose ends keep the sign but a sample does not is rejected (adaptive
        controllers then shrink it until an end lies past the sign change, where the
        release event brackets it and root-finds); under a fixed-step controller, which
        cannot reject, it fails with `RESULTS.release_missed` (signalled as diffrax's
        `dt_min_reached`, which a fixed-step controller never reports);
    - a step along which the samples depart from the chord of the end values by more
        than `_WATCH_ROUGHNESS` of the larger end value is rejected (adaptive only), so
        that the steps resolve the multiplier where it comes near zero.

    The samples. A Runge-Kutta solver (not wrapped by `Projection`) integrates the
    state together with a dummy component whose derivative is the watched multiplier
    (`stages`: the vector field and the multipliers from one KKT solve), so its
    stages hand over the multiplier at every stage time for free, and at the end of
    the step too for a first-same-as-last tableau. Where the stage times leave a gap
    wider than `_WATCH_GAP` of the step (Tsit5: between 0.327 and 0.9), the
    multiplier is also evaluated on the dense output there (`gap_samples`). Other
    solvers sample the dense output at `_WATCH_SAMPLES`. The dummy component takes no
    part in the error estimate, so the steps, and the state, are the same as without
    it.

    The multiplier at the start of the step is carried in the solver state; at the
    start of the phase it is `start` (computed once, when the phase starts).
    """

    solver: diffrax.AbstractSolver
    watch: Callable
    start: Float[Array, ""]
    adaptive: bool = eqx.field(static=True)
    stages: Callable | None = None

    def _stages(self):
        """The Runge-Kutta stages that carry the multiplier, or `None`."""
        return None if self.stages is None else runge_kutta_stages(self.solver)

    def init(self, terms, t0, t1, y0, args):
        w0 = self.start
        if self._stages() is None:
            return self.solver.init(terms, t0, t1, y0, args), w0
        stages = diffrax.ODETerm(self.stages)
        return self.solver.init(stages, t0, t1, (y0, w0), args), w0

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        inner_state, w0 = solver_state
        stages = self._stages()
        dtype = jnp.result_type(t0)
        if stages is None:
            y1, y_error, dense_info, inner_state, result = self.solver.step(
                terms, t0, t1, y0, args, inner_state, made_jump
            )
            theta = np.asarray(_WATCH_SAMPLES)
            w1 = self.watch(t1, y1, args)
            ws = jnp.zeros((0,), dtype)
            theta_stages = np.zeros((0,))
        else:
            (y1, _), y_error, dense, inner_state, result = self.solver.step(
                diffrax.ODETerm(self.stages),
                t0,
                t1,
                (y0, w0),
                args,
                inner_state,
                made_jump,
            )
            # The dummy component is dropped: from the error (so that it does not
            # steer the step size) and from the dense output.
            y_error = None if y_error is None else y_error[0]
            dense_info = component_dense_info(dense, 0)
            # The multiplier at the stages.
            ws = stage_derivatives(dense, t0, t1)[1]
            theta_stages = stages.times
            w1 = ws[-1] if stages.fsal else self.watch(t1, y1, args)
            theta = gap_samples(theta_stages)
        if theta.size:
            interpolation = self.solver.interpolation_cls(t0=t0, t1=t1, **dense_info)
            ts = t0 + jnp.asarray(theta, dtype) * (t1 - t0)
            sample = lambda t: self.watch(t, interpolation.evaluate(t), args)
            # Unbatched (`each`): the solve traced already for the stages, not a
            # batched copy of it; Tsit5 has one sample.
            ws = jnp.concatenate([ws, each(sample, ts)])
        theta = jnp.asarray(np.concatenate([theta_stages, theta]), dtype)
        dipped = (w0 >= 0) & (w1 >= 0) & jnp.any(ws < 0)
        if self.adaptive:
            chord = w0 + theta * (w1 - w0)
            rough = (w0 > 0) & (
                jnp.max(jnp.abs(ws - chord))
                > _WATCH_ROUGHNESS * jnp.maximum(jnp.abs(w0), jnp.abs(w1))
            )
            reject = dipped | rough
            if y_error is not None:
                y_error = jax.tree.map(lambda e: jnp.where(reject, jnp.inf, e), y_error)
        else:
            # (A fixed-step controller never reports `dt_min_reached`: the phase
            # reads it back as `RESULTS.release_missed`.)
            result = diffrax.RESULTS.where(
                dipped, diffrax.RESULTS.dt_min_reached, result
            )
        return y1, y_error, dense_info, (inner_state, w1), result


def each(fn, *points, loop: bool = True):
    """`fn` at each of `points` (arrays with a leading axis: the saved states, the
    samples of `WatchedSolver`): a plain call for one point; else with `loop` a loop
    around the unbatched function (`lax.map`), without it `jax.vmap`.

    The loop for the KKT solve: a batched KKT solve is a program of its own, with
    the batch's `lax.cond` and both branches, to trace and compile, while the steps
    have traced the unbatched one already. `jax.vmap` for `A`, the energy and the
    residuals, which compile batched about as fast. One point: a plain call, the
    smallest program."""
    if jax.tree.leaves(points)[0].shape[0] == 1:
        out = fn(*jax.tree.map(lambda x: x[0], points))
        return jax.tree.map(lambda x: x[None], out)
    if loop:
        return jax.lax.map(lambda point: fn(*point), points)
    return jax.vmap(fn)(*points)


def gap_samples(theta_stages: np.ndarray) -> np.ndarray:
    """Fractions of the step at which to sample the dense output, so that with the
    stage times no gap is wider than `_WATCH_GAP`: the midpoint of the widest gap,
    again and again (static, numpy)."""
    points = sorted({float(t) for t in theta_stages if 0.0 <= t <= 1.0} | {0.0, 1.0})
    extra = []
    while True:
        gaps = np.diff(points)
        i = int(np.argmax(gaps))
        if gaps[i] <= _WATCH_GAP:
            return np.asarray(extra, dtype=float)
        mid = 0.5 * (points[i] + points[i + 1])
        extra.append(mid)
        points = sorted(points + [mid])
