"""`diffeqsolve`: `diffrax.diffeqsolve`, traced with two scoped changes to diffrax's
private `_integrate` module (the one place this library touches it):

1. its `t1 - 100 ULP` floor computed in a loop instead of 100 unrolled steps, bit for
   bit the same (below);
2. with `save_times_checked=True`, without its run-time checks of `SaveAt(ts=...)`
   (sorted, inside `[t0, t1]`), for callers that have already made the save times
   valid (`simulate` checks them, reports `RESULTS.invalid_time_grid` and clips
   them to each phase's span). diffrax's checks are `equinox.error_if`s, host
   callbacks in the compiled program, and JAX never writes a program with host
   callbacks to its persistent compilation cache: without them every `simulate`
   program is cached (`constrained_jax.enable_compilation_cache`), and a second
   `constrained-jax tour` reads the dynamics scenes' programs from disk too.
   (diffrax's check of a traced `dt0`'s sign stays: nothing else checks it.)

The `t1` floor. At the start of every solve, diffrax 0.7's `_integrate.loop` computes
the threshold at which it rounds a step to `t1` as

    t1_clip_floor = t1
    for _ in range(100):
        t1_clip_floor = eqxi.prevbefore(t1_clip_floor)

For a traced `t1` (every `simulate` whose end time is an array, e.g. under `jax.vmap`
or from a detachment time) that is 100 chained `nextafter`s, about 1,500 scalar HLO
instructions that XLA cannot fold: 0.3-0.7 s of the XLA compile of the tour's
pendulum and release programs (`benchmarks/compile_time.py`, (c) 1.37-1.43 -> 1.02-1.04
s and (b) 4.5-4.8 -> 3.7-4.0 s). Here the 100th call, recognised by the identity of
its input (the 99th call's output, which was the 98th's ...), returns `prevbefore`
applied 100 times to the first call's input by a `lax.fori_loop` (one small loop);
the 99 calls before it return their input, which nothing but the next call uses
(tracing 99 `prevbefore`s that `jit` then drops cost 0.1-0.15 s of each first trace
of the tour's pendulum and release programs; the lowered program is byte for byte the
same). The floor is diffrax's, bit for bit (the same operations; checked in
`tests/test_simulate.py::test_t1_floor_is_bitwise_diffrax`), and the derivative is
`prevbefore`'s (the identity). Only diffrax's one use (the 100 calls above, and
nothing else in `diffrax._integrate`) sees this function. (A `lax.scan` that also
returned the 99 intermediate values made the pendulum's run 10 % slower; the loop
that returns only the last one does not, within this machine's noise.)

Scoped: both replacements are installed on `diffrax._integrate` (a private module; its
module-level name `eqxi`) only while one of this library's solves is being traced, and
only for the diffrax version they were written against (`_TESTED`): another version
runs diffrax unchanged (and its `simulate` programs are not cached). A lazily traced
backward pass that runs outside the scope uses diffrax's own chain: the same values,
the old compile time.
"""

import contextlib
import threading
import types

import diffrax
import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp


_TESTED = ("0.7.2",)
_LENGTH = 100  # the chain's length in diffrax's `_integrate.loop`

_state = threading.local()
_lock = threading.Lock()
_depth = 0


def _chain(x):
    return jax.lax.fori_loop(0, _LENGTH, lambda _, y: eqxi.prevbefore(y), x)


def prevbefore(x):
    """The floor of diffrax's chain of `_LENGTH` calls, each on the previous one's
    output: the last call returns `eqxi.prevbefore` applied `_LENGTH` times to the
    first one's input, by a loop (the same value); the calls before it return their
    input, only ever passed on to the next call. Not `prevbefore` for a lone call: it
    replaces diffrax's chain and nothing else."""
    if not isinstance(x, jax.core.Tracer):
        return eqxi.prevbefore(x)  # a constant: computed now, or folded by XLA
    last = getattr(_state, "last", None)
    if last is not None and last[0] is x:
        _, start, k = last
    else:
        start, k = x, 0
    k = k + 1
    out = _chain(start) if k == _LENGTH else x
    # Forget the chain once it is complete (no tracer is kept past its trace).
    _state.last = (out, start, k) if k < _LENGTH else None
    return out


# The messages of diffrax 0.7.2's `_check_subsaveat_ts` (`diffeqsolve`).
_SAVE_TIME_MESSAGES = frozenset(
    {
        "saveat.ts must be increasing or decreasing.",
        "saveat.ts must lie between t0 and t1.",
    }
)


def error_if(x, pred, msg):
    """`eqxi.error_if(x, pred, msg)`, except for diffrax's checks of the save times
    inside a `diffeqsolve(..., save_times_checked=True)`, which return `x`."""
    if getattr(_state, "save_times_checked", False) and msg in _SAVE_TIME_MESSAGES:
        return x
    return eqxi.error_if(x, pred, msg)


class _Eqxi(types.ModuleType):
    """`equinox.internal`, with `prevbefore` and `error_if` replaced."""

    def __getattr__(self, name):
        return getattr(eqxi, name)


_EQXI = _Eqxi("equinox.internal (constrained_jax's diffrax adapter)")
_EQXI.prevbefore = prevbefore
_EQXI.error_if = error_if


def _integrate_module():
    if diffrax.__version__ not in _TESTED:
        return None
    from diffrax import _integrate

    return _integrate if getattr(_integrate, "eqxi", None) in (eqxi, _EQXI) else None


def active() -> bool:
    """Whether the replacement applies to the installed diffrax."""
    return _integrate_module() is not None


@contextlib.contextmanager
def _scoped(save_times_checked: bool):
    global _depth
    module = _integrate_module()
    if module is None:
        yield
        return
    outer = getattr(_state, "save_times_checked", False)
    _state.save_times_checked = save_times_checked
    with _lock:
        _depth += 1
        module.eqxi = _EQXI
    try:
        yield
    finally:
        _state.last = None
        _state.save_times_checked = outer
        with _lock:
            _depth -= 1
            if _depth == 0:
                module.eqxi = eqxi


def diffeqsolve(*args, save_times_checked: bool = False, **kwargs):
    """`diffrax.diffeqsolve(*args, **kwargs)`, with the `t1` floor in a loop and, if
    `save_times_checked`, without diffrax's run-time checks of the save times (the
    caller guarantees them: sorted in the direction of integration and inside the
    span, as diffrax compares them)."""
    with _scoped(save_times_checked):
        return diffrax.diffeqsolve(*args, **kwargs)


# The smallest step an adaptive controller may take, in units of eps |t|. (SciPy's
# `solve_ivp` stops at 10 ULP of `t` the same way.)
_STEP_FLOOR = 16


def step_floor(stepsize_controller, t0, t1):
    """A `PIDController` without `dtmin` gets one at `_STEP_FLOOR eps max(|t0|, |t1|)`,
    not forced: a step that shrinks below it fails (diffrax's `dt_min_reached`, which
    `simulate` reports as `RESULTS.step_size_underflow`; in `solve_shooting` the trial
    gives a NaN residual). A vector
    field that is NaN just ahead of the state (singular dynamics, a solution that
    blows up) has every step rejected and the step shrinking by `factormin` each time:
    without a floor the solve went on to `max_steps` (which a `jax.vmap` batch waits
    for), with it it stops after about 20 rejections. Returns the controller, and
    whether the floor is ours."""
    if not (
        isinstance(stepsize_controller, diffrax.PIDController)
        and stepsize_controller.dtmin is None
    ):
        return stepsize_controller, False
    eps = jnp.finfo(t0.dtype).eps
    dtmin = jax.lax.stop_gradient(
        _STEP_FLOOR * eps * jnp.maximum(jnp.abs(t0), jnp.abs(t1))
    )
    floored = eqx.tree_at(
        lambda c: (c.dtmin, c.force_dtmin),
        stepsize_controller,
        (dtmin, False),
        is_leaf=lambda x: x is None,
    )
    return floored, True
