"""`diffeqsolve`: `diffrax.diffeqsolve`, with its `t1 - 100 ULP` floor computed in a
loop instead of 100 unrolled steps, bit for bit the same.

At the start of every solve, diffrax 0.7's `_integrate.loop` computes the threshold
at which it rounds a step to `t1` as

    t1_clip_floor = t1
    for _ in range(100):
        t1_clip_floor = eqxi.prevbefore(t1_clip_floor)

For a traced `t1` (every `simulate` whose end time is an array, e.g. under `jax.vmap`
or from a detachment time) that is 100 chained `nextafter`s, about 1,500 scalar HLO
instructions that XLA cannot fold: 0.5-0.7 s of the XLA compile of the tour's
pendulum and release programs (`benchmarks/compile_time.py`, (c) 1.52 -> 1.04 s and (b)
4.46 -> 3.74 s). Here the first of the 100 calls computes all 100 values by a
`lax.scan` of the same `prevbefore` (one small loop) and every call returns its own
element, recognising the chain by the identity of its input, the previous call's
output; anything else is an ordinary `prevbefore` chain of its own. The values are
those of diffrax's loop, bit for bit (the same operations, run in a loop; checked in
`tests/test_simulate.py::test_t1_floor_is_bitwise_diffrax`), and their derivative is
`prevbefore`'s (the identity).

Scoped: the replacement is installed on `diffrax._integrate` (a private module; its
module-level name `eqxi`) only while one of this library's solves is being traced, and
only for the diffrax version it was written against (`_TESTED`): another version runs
diffrax unchanged. A lazily traced backward pass that runs outside the scope uses
diffrax's own chain: the same values, the old compile time.
"""

import contextlib
import threading
import types

import diffrax
import equinox.internal as eqxi
import jax


_TESTED = ("0.7.2",)
_LENGTH = 100  # the chain's length in diffrax's `_integrate.loop`

_state = threading.local()
_lock = threading.Lock()
_depth = 0


def _chain(x):
    def step(y, _):
        y = eqxi.prevbefore(y)
        return y, y

    _, ys = jax.lax.scan(step, x, None, length=_LENGTH)
    return ys


def prevbefore(x):
    """`eqxi.prevbefore(x)`; consecutive calls on each other's outputs are served from
    one scanned chain of `_LENGTH` values."""
    if not isinstance(x, jax.core.Tracer):
        return eqxi.prevbefore(x)  # a constant: computed now, or folded by XLA
    last = getattr(_state, "last", None)
    if last is not None and last[0] is x:
        _, ys, k = last
        k = k + 1
    else:
        ys, k = _chain(x), 0
    out = ys[k]
    # Forget the chain once it is used up (no tracer is kept past its trace).
    _state.last = (out, ys, k) if k + 1 < _LENGTH else None
    return out


class _Eqxi(types.ModuleType):
    """`equinox.internal`, with `prevbefore` replaced."""

    def __getattr__(self, name):
        return getattr(eqxi, name)


_EQXI = _Eqxi("equinox.internal (constrained_jax's t1 floor)")
_EQXI.prevbefore = prevbefore


def _integrate_module():
    if diffrax.__version__ not in _TESTED:
        return None
    from diffrax import _integrate

    return _integrate if getattr(_integrate, "eqxi", None) in (eqxi, _EQXI) else None


def active() -> bool:
    """Whether the replacement applies to the installed diffrax."""
    return _integrate_module() is not None


@contextlib.contextmanager
def _scan_t1_floor():
    global _depth
    module = _integrate_module()
    if module is None:
        yield
        return
    with _lock:
        _depth += 1
        module.eqxi = _EQXI
    try:
        yield
    finally:
        _state.last = None
        with _lock:
            _depth -= 1
            if _depth == 0:
                module.eqxi = eqxi


def diffeqsolve(*args, **kwargs):
    """`diffrax.diffeqsolve(*args, **kwargs)`, with the `t1` floor scanned (above)."""
    with _scan_t1_floor():
        return diffrax.diffeqsolve(*args, **kwargs)
