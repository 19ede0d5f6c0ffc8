"""The library's only reach-ins into other libraries' private internals, each guarded.

Where JAX, diffrax or equinox offer a public route, the library takes it; what is
here has none. Each access is guarded (by the version it was written for, or by the
presence of exactly what it uses) and has a fallback that keeps the library working,
maybe slower or less informative, on a version it was not written for:

- [`backends_started`][]: whether JAX's backends have started (`jax._src.xla_bridge`),
    for the XLA settings that must come before. Fallback: `None` (unknown).
- [`distributed_client`][]: the key-value store of JAX's coordination service
    (`jax._src.distributed`), through which the processes of a `sweep` tell each
    other of a failure. Fallback: `None` (a failure is seen through JAX's heartbeat).
- `CALLBACK_LOGGER`: the name of the logger under which JAX reports an exception
    raised in a host callback. Fallback: a logger nobody writes to (the messages are
    logged).
- `while_loop`, `buffer_at_set`, `unvmap_all`: `equinox.internal`'s checkpointed
    loop with write-only buffers, diffrax's own loop, and the predicate that is true
    when it holds in every lane of a `jax.vmap` batch (never batched itself, so a
    `lax.cond` on it stays a branch). Any equinox that the installed diffrax runs
    with has them (diffrax uses them), so they need no guard of their own.
- `lineax_internal`: `lineax.internal`'s flattening of operator structures, for the
    library's own linear solvers (`DenseLU`, `MINRES`), as lineax's solvers use it.
    diffrax and optimistix import `lineax.internal` too: no guard of its own.
- [`runge_kutta_stages`][], [`stage_derivatives`][], [`component_dense_info`][]: the
    layout of the dense output of diffrax's Runge-Kutta solvers (`dense_info["k"]`,
    the stage increments). Guarded by the diffrax version; fallback: `None` from
    `runge_kutta_stages` (sample the dense output instead).
- [`NamedEnumerationMeta`][]: the metaclass of the library's enumerations
    (`RESULTS`, `EXTREMUM`), whose items print as their names (`RESULTS.successful`)
    rather than as equinox's `RESULTS<message>`. equinox's item class is not public:
    its items are subclassed, with the fields equinox gives them (`_value`,
    `_enumeration`). Guarded by the presence of exactly those; fallback: equinox's
    own metaclass (its repr).
- [`patched_diffrax`][]: two scoped replacements in diffrax's private `_integrate`
    module while a solve is traced, opted into with
    [`constrained_jax.settings.use_diffrax_patch`][]. Guarded by the diffrax version;
    fallback: diffrax unchanged. `docs/upstream/diffrax.md` reports what it works
    around, with the change proposed to diffrax.

`tests/test_compat.py` checks that no other module of the package reaches into a
private module (`jax._src`, `diffrax._...`, `equinox.internal`, ...).
"""

import contextlib
import logging
import threading
import types
from typing import NamedTuple

import diffrax
import equinox as eqx
import equinox.internal as eqxi
import jax
import lineax.internal
import numpy as np


# --------------------------------------------------------------------------------------
# JAX


def backends_started() -> bool | None:
    """Whether JAX has started its backends (and so read `XLA_FLAGS`): `True`,
    `False`, or `None` where this JAX does not say (JAX has no public function for
    it; `jax.devices()` would start them)."""
    try:
        from jax._src import xla_bridge

        return bool(xla_bridge.backends_are_initialized())
    except Exception:
        return None


def distributed_client():
    """The client of JAX's coordination service when `jax.distributed` is
    initialised and the client has the key-value calls `sweep` uses
    (`key_value_set`, `key_value_dir_get`); else `None`."""
    try:
        from jax._src import distributed

        client = distributed.global_state.client
    except Exception:
        return None
    if client is None or not all(
        callable(getattr(client, name, None))
        for name in ("key_value_set", "key_value_dir_get")
    ):
        return None
    return client


# The logger of JAX's host callbacks (where an exception raised in one is logged).
CALLBACK_LOGGER = "jax._src.callback"


def quiet_callback_errors():
    """A context in which JAX does not log the exceptions raised in host callbacks
    (they are raised anyway)."""
    return _quiet(logging.getLogger(CALLBACK_LOGGER))


@contextlib.contextmanager
def _quiet(log: logging.Logger):
    level = log.level
    log.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        log.setLevel(level)


# --------------------------------------------------------------------------------------
# equinox: diffrax's loop primitives (a checkpointed `while` with write-only buffers,
# and a predicate over the lanes of a batch).

while_loop = eqxi.while_loop
buffer_at_set = eqxi.buffer_at_set
unvmap_all = eqxi.unvmap_all


# --------------------------------------------------------------------------------------
# equinox: enumeration items that print as their names.

_EnumerationMeta = type(eqx.Enumeration)
_EnumerationItem = type(diffrax.RESULTS.successful)


def _item_names(enumeration, value) -> str:
    """The names of the items `value` (an item's `_value`) of `enumeration`: one
    name, a bracketed array of names (a `vmap`ped result), `(traced)` inside a
    transformation, or `(unknown)` for a leaf that is not an array."""
    if isinstance(value, jax.core.Tracer):
        return "(traced)"
    if not isinstance(value, (np.ndarray, np.generic, jax.Array)):
        return "(unknown)"
    names = {int(item._value): name for name, item in enumeration._name_to_item.items()}
    indices = np.asarray(value)
    if indices.ndim == 0:
        return names.get(int(indices), f"({int(indices)})")
    return np.array2string(
        indices,
        separator=", ",
        formatter={"int": lambda i: names.get(int(i), f"({int(i)})")},
        threshold=20,
    )


class _NamedItem(_EnumerationItem):
    """An item of a `NamedEnumerationMeta` enumeration: `str` is its name
    (`successful`), `repr` the name on its enumeration (`RESULTS.successful`; a
    batch: `RESULTS[successful, singular_kkt]`; inside a transformation:
    `RESULTS(traced)`). Its message is `RESULTS[item]`, as for any equinox
    enumeration."""

    def __repr__(self):
        names = _item_names(self._enumeration, self._value)
        separator = "" if names.startswith(("[", "(")) else "."
        return f"{self._enumeration.__qualname__}{separator}{names}"

    def __str__(self):
        return _item_names(self._enumeration, self._value)


def _named(item):
    if isinstance(item, _NamedItem):
        return item
    return _NamedItem(item._value, item._enumeration)


_equinox_where = eqx.Enumeration.where.__func__
_equinox_promote = eqx.Enumeration.promote.__func__


def _where(cls, pred, a, b):
    return _named(_equinox_where(cls, pred, a, b))


def _promote(cls, item):
    return _named(_equinox_promote(cls, item))


def _named_items_supported() -> bool:
    fields = getattr(_EnumerationItem, "__dataclass_fields__", {})
    item = diffrax.RESULTS.successful
    return (
        list(fields) == ["_value", "_enumeration"]
        and isinstance(getattr(item, "_value", None), np.ndarray)
        and isinstance(getattr(diffrax.RESULTS, "_name_to_item", None), dict)
    )


class _NamedEnumerationMeta(_EnumerationMeta):
    """equinox's enumeration metaclass, whose items are `_NamedItem`s: the items
    named in the class body and inherited, and those `where` and `promote` build
    (so that every item of one enumeration has the same pytree type, as `lax.cond`
    and `lax.while_loop` need)."""

    def __new__(mcs, cls_name, bases, namespace):
        cls = super().__new__(mcs, cls_name, bases, namespace)
        for name, item in cls._name_to_item.items():
            cls._name_to_item[name] = _named(item)
        # equinox's metaclass refuses these names in a class body: set after it.
        cls.where = classmethod(_where)
        cls.promote = classmethod(_promote)
        return cls


NamedEnumerationMeta = (
    _NamedEnumerationMeta if _named_items_supported() else _EnumerationMeta
)


# --------------------------------------------------------------------------------------
# lineax: the flattening of operator structures, for the library's linear solvers.

lineax_internal = lineax.internal


# --------------------------------------------------------------------------------------
# diffrax


# The diffrax releases whose internals the code below was written against.
DIFFRAX_TESTED = frozenset({"0.7.2"})


def _diffrax_version() -> str:
    return getattr(diffrax, "__version__", "unknown")


def _diffrax_known() -> bool:
    return _diffrax_version() in DIFFRAX_TESTED


class RungeKuttaStages(NamedTuple):
    """The stages of a Runge-Kutta step: their times as fractions of the step (the
    first stage at 0) and whether the last stage is at the end of the step with the
    step's end state (first same as last)."""

    times: np.ndarray
    fsal: bool


def runge_kutta_stages(solver) -> RungeKuttaStages | None:
    """The stages of `solver`'s steps when its dense output holds the derivative at
    every stage in a layout this module reads ([`stage_derivatives`][]): a diffrax
    Runge-Kutta solver with a `ButcherTableau`, on a diffrax of `DIFFRAX_TESTED`.
    `None` otherwise (another solver, or a diffrax whose dense output is not known
    here): the caller falls back to evaluating what it needs on the dense output."""
    if not _diffrax_known() or not isinstance(solver, diffrax.AbstractRungeKutta):
        return None
    tableau = getattr(solver, "tableau", None)
    if not isinstance(tableau, diffrax.ButcherTableau):
        return None
    times = np.concatenate([[0.0], np.asarray(tableau.c, dtype=float)])
    return RungeKuttaStages(times=times, fsal=bool(tableau.fsal))


def stage_derivatives(dense_info: dict, t0, t1):
    """The derivative of the state at each stage of the step from `t0` to `t1`, as a
    pytree shaped like the state with a leading axis of stages, read from the dense
    output (`dense_info`) of a solver for which [`runge_kutta_stages`][] is not
    `None` (diffrax keeps the stage increments: derivative times step)."""
    return jax.tree.map(lambda k: k / (t1 - t0), dense_info["k"])


def component_dense_info(dense_info: dict, index: int) -> dict:
    """The dense output of component `index` of a tuple state, from the dense output
    of a solver for which [`runge_kutta_stages`][] is not `None`."""
    return {key: value[index] for key, value in dense_info.items()}


# The patch of diffrax's private `_integrate` module (opt-in).
#
# 1. The `t1` floor. At the start of every solve, diffrax 0.7.2's `_integrate.loop`
#    computes the threshold at which it rounds a step to `t1` as
#
#        t1_clip_floor = t1
#        for _ in range(100):
#            t1_clip_floor = eqxi.prevbefore(t1_clip_floor)
#
#    For a traced `t1` that is 100 chained `nextafter`s in the program, which XLA
#    cannot fold. Here the 100th call, recognised by the identity of its input (the
#    99th call's output, which was the 98th's ...), returns `prevbefore` applied 100
#    times to the first call's input by a `lax.fori_loop`; the 99 calls before it
#    return their input, which nothing but the next call uses. The floor is
#    diffrax's, bit for bit (the same operations), and the derivative is
#    `prevbefore`'s (the identity). Only diffrax's one use sees this function.
#
# 2. The save times. With `save_times_checked=True`, diffrax's two run-time checks of
#    `SaveAt(ts=...)` (`equinox.error_if`s: host callbacks in the compiled program,
#    which JAX 0.10 never writes to its persistent compilation cache) return their
#    input, for callers that have made the save times valid themselves.
#
# Both are installed on `diffrax._integrate` (its module-level name `eqxi`) only while
# a solve is traced, and only for `DIFFRAX_TESTED`.

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
    inside a solve traced with `save_times_checked=True`, which return `x`."""
    if getattr(_state, "save_times_checked", False) and msg in _SAVE_TIME_MESSAGES:
        return x
    return eqxi.error_if(x, pred, msg)


class _Eqxi(types.ModuleType):
    """`equinox.internal`, with `prevbefore` and `error_if` replaced."""

    def __getattr__(self, name):
        return getattr(eqxi, name)


_EQXI = _Eqxi("equinox.internal (constrained_jax's diffrax patch)")
_EQXI.prevbefore = prevbefore
_EQXI.error_if = error_if


def _integrate_module():
    if not _diffrax_known():
        return None
    try:
        from diffrax import _integrate
    except ImportError:
        return None
    return _integrate if getattr(_integrate, "eqxi", None) in (eqxi, _EQXI) else None


def diffrax_patch_available() -> bool:
    """Whether the installed diffrax is one the patch was written for."""
    return _integrate_module() is not None


@contextlib.contextmanager
def patched_diffrax(save_times_checked: bool):
    """While the block runs (a `diffrax.diffeqsolve` being traced), diffrax's `t1`
    floor is computed by a loop and, with `save_times_checked`, its checks of the
    save times are dropped. On a diffrax the patch was not written for, nothing
    changes."""
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
