"""`diffeqsolve`: `diffrax.diffeqsolve` for the library's solves, and `step_floor`, the
smallest step of an adaptive controller.

By default `diffeqsolve` is `diffrax.diffeqsolve`. A process that opts in with
[`constrained_jax.settings.use_diffrax_patch`][] traces the library's solves with two
scoped changes to diffrax's private `_integrate` module (`_compat.patched_diffrax`;
only for the diffrax version they were written for, otherwise diffrax runs
unchanged):

1. diffrax's `t1 - 100 ULP` floor (100 chained `nextafter`s when `t1` is traced)
   computed by a loop, bit for bit the same;
2. with `save_times_checked=True`, without diffrax's run-time checks of
   `SaveAt(ts=...)` (sorted, inside `[t0, t1]`), for callers that have made the save
   times valid themselves (`simulate` checks them, reports
   `RESULTS.invalid_time_grid` and clips them to each phase's span;
   `solve_shooting` saves at sorted nodes inside its span). diffrax's checks are
   `equinox.error_if`s, host callbacks in the compiled program, which JAX 0.10 never
   writes to its persistent compilation cache.

`docs/upstream/diffrax.md` describes both, with reproducers and the changes proposed
to diffrax.
"""

import warnings

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from . import _compat


_patch = False  # the process's choice (`use_diffrax_patch`)


def use_diffrax_patch(enable: bool = True) -> bool:
    """Trace the library's diffrax solves with two changes to diffrax's private
    internals, for the rest of the process (off by default):

    1. diffrax's `t1 - 100 ULP` floor, 100 chained `nextafter`s in every compiled
        solve whose end time is traced (`jax.vmap` over end times, the release run's
        second phase, a gradient with respect to `t1`), computed by a loop instead:
        the same floor bit for bit, in a smaller program that compiles faster;
    2. without diffrax's run-time checks of `SaveAt(ts=...)` where the library has
        checked the save times itself: these checks are host callbacks, and JAX
        (0.10) never writes a program with host callbacks to its persistent
        compilation cache, so with the patch `simulate` and `solve_shooting`
        programs are cached ([`constrained_jax.enable_compilation_cache`][]).

    The values are the same with and without it. It changes diffrax's private
    module `diffrax._integrate` while one of the library's solves is traced (nothing
    else sees it), and only for the diffrax release it was written for:
    `docs/upstream/diffrax.md` reports the behaviour upstream, with the change
    proposed to diffrax that would make the patch unnecessary.

    Call it at the top of a script, before the first solve: a program traced before
    the call (or before `use_diffrax_patch(False)`) is kept as it was traced.

    **Arguments:**

    - `enable`: `True` to turn the patch on, `False` to turn it off again.

    **Returns:** whether the patch is on: `False`, with a warning, where the
    installed diffrax is not the release the patch was written for (diffrax runs
    unchanged).
    """
    global _patch
    if not enable:
        _patch = False
        return False
    if not _compat.diffrax_patch_available():
        warnings.warn(
            "use_diffrax_patch: the patch is written for diffrax "
            f"{', '.join(sorted(_compat.DIFFRAX_TESTED))}; this is diffrax "
            f"{_compat._diffrax_version()}, which runs unchanged.",
            stacklevel=2,
        )
        _patch = False
        return False
    _patch = True
    return True


def diffrax_patch_on() -> bool:
    """Whether the library's solves are traced with the diffrax patch."""
    return _patch


def diffeqsolve(*args, save_times_checked: bool = False, **kwargs):
    """`diffrax.diffeqsolve(*args, **kwargs)`; with the opt-in patch
    ([`use_diffrax_patch`][]), with the `t1` floor in a loop and, if
    `save_times_checked`, without diffrax's run-time checks of the save times (the
    caller guarantees them: sorted in the direction of integration and inside the
    span, as diffrax compares them)."""
    if not _patch:
        return diffrax.diffeqsolve(*args, **kwargs)
    with _compat.patched_diffrax(save_times_checked):
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
