"""Sparsity patterns read from the traced program (the jaxpr), not sampled.

- `dependency_pattern(fn, x, ...)`: which outputs of `fn` depend on which entries of
  `x`, by following the data flow of every operation. An output with no path from
  `x_j` has a derivative along `x_j` that autodiff never forms (no term of the
  linearised program carries it), so the forward products with any direction agree
  with the pattern exactly.
- `nonzero_pattern(fn, ...)`: which outputs may be nonzero. An entry counts as zero
  only where the program makes it an exact zero: a literal or constant zero moved
  by data movement (`broadcast`, `stack`, `pad`, slices, ...) and sums, negations of
  such zeros. A product with zero counts as possibly nonzero (`0 * inf` is NaN).

Both are upper bounds: an operation without a rule here makes each of its outputs
depend on every input (and possibly nonzero); nested programs (`jax.jit`,
`jax.checkpoint`) are followed; control flow (`lax.cond`, loops), gathers and custom
derivatives are opaque. A reading is *exact* when no opaque operation and no product
with an exact zero (whose derivative the rules keep) was met: the pattern is then
the program's structural pattern. `constrained_jax._structure` uses an exact reading
as the pattern (no evaluation at random states), and a bound to prove a pattern
sampled at random states (bound inside sample: the two are equal, and the run-time
check of the pattern can never fire). Anything unexpected gives `None`, never an
error.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend.core import Literal


# Beyond this many booleans in one dependency array the analysis gives up.
_MAX_ENTRIES = 4_000_000


class _GiveUp(Exception):
    pass


_ZERO_PRESERVING_UNARY = frozenset(
    {
        "neg",
        "sin",
        "tan",
        "sinh",
        "tanh",
        "asin",
        "atan",
        "asinh",
        "atanh",
        "sqrt",
        "cbrt",
        "abs",
        "sign",
        "expm1",
        "log1p",
        "erf",
        "square",
        "floor",
        "ceil",
        "round",
        "convert_element_type",
        "copy",
        "copy_p",
        "reduce_precision",
        "real",
        "conj",
        "optimization_barrier",
    }
)

_OTHER_UNARY = frozenset(
    {
        "cos",
        "acos",
        "acosh",
        "cosh",
        "exp",
        "exp2",
        "log",
        "rsqrt",
        "logistic",
        "erfc",
        "erf_inv",
        "lgamma",
        "digamma",
        "is_finite",
        "not",
        "imag",
        "integer_pow",
    }
)

# Binary (or n-ary) elementwise: zero when every operand is zero.
_SUM_LIKE = frozenset({"add", "sub", "add_any", "max", "min"})

_OTHER_ELEMENTWISE = frozenset(
    {
        "mul",
        "div",
        "pow",
        "atan2",
        "rem",
        "nextafter",
        "eq",
        "ne",
        "lt",
        "le",
        "gt",
        "ge",
        "and",
        "or",
        "xor",
        "clamp",
        "select_n",
    }
)

# Nested programs whose inputs and outputs are those of the equation (`jax.jit`,
# `jax.checkpoint`): followed inside. Loops, `lax.cond` and custom derivatives are not.
_CALLS = frozenset({"jit", "pjit", "closed_call", "core_call", "remat2", "checkpoint"})


class _State:
    """What is known of one array: `nz[i]` whether entry `i` may be nonzero, and
    `dep[i, j]` whether it may depend on entry `j` of the input followed."""

    __slots__ = ("nz", "dep")

    def __init__(self, nz, dep):
        self.nz = nz
        self.dep = dep


def _differentiable(aval) -> bool:
    return jnp.issubdtype(aval.dtype, jnp.inexact)


def _check_size(shape, n):
    if math.prod(shape) * max(n, 1) > _MAX_ENTRIES:
        raise _GiveUp


def _opaque(in_states, out_avals, n, ctx):
    """Every output entry possibly nonzero and depending on every input entry."""
    ctx["exact"] = False
    dep = np.zeros((n,), bool)
    for s in in_states:
        dep = dep | s.dep.reshape(s.nz.size, n).any(axis=0)
    out = []
    for aval in out_avals:
        _check_size(aval.shape, n)
        d = np.broadcast_to(dep, (*aval.shape, n)).copy()
        if not _differentiable(aval):
            d[...] = False
        out.append(_State(np.ones(aval.shape, bool), d))
    return out


def _index_map(name, params, in_shapes, out_shape):
    """For data movement: the flat index (into the inputs concatenated) that each
    output entry copies, `-1` for a fill; `None` for other operations."""
    sizes = [math.prod(s) for s in in_shapes]
    offsets = np.cumsum([0, *sizes])
    iotas = [
        np.arange(offsets[i], offsets[i + 1]).reshape(s)
        for i, s in enumerate(in_shapes)
    ]
    x = iotas[0] if iotas else None
    if name == "broadcast_in_dim":
        dims = params["broadcast_dimensions"]
        shape = [1] * len(out_shape)
        for i, d in enumerate(dims):
            shape[d] = in_shapes[0][i]
        return np.broadcast_to(x.reshape(shape), out_shape)
    if name == "reshape":
        if params.get("dimensions") is not None:
            return None
        return x.reshape(out_shape)
    if name == "squeeze":
        return x.reshape(out_shape)
    if name == "transpose":
        return np.transpose(x, params["permutation"])
    if name == "rev":
        return np.flip(x, axis=tuple(params["dimensions"]))
    if name == "slice":
        strides = params["strides"] or (1,) * x.ndim
        index = tuple(
            slice(a, b, s)
            for a, b, s in zip(
                params["start_indices"], params["limit_indices"], strides, strict=True
            )
        )
        return x[index]
    if name == "concatenate":
        return np.concatenate(iotas, axis=params["dimension"])
    if name == "stack":
        return np.stack(iotas, axis=params["axis"])
    if name == "expand_dims":
        return x.reshape(out_shape)
    if name == "pad":
        out = np.full(out_shape, -1, int)
        source = []
        target = []
        for size, (lo, _, interior), length in zip(
            in_shapes[0], params["padding_config"], out_shape, strict=True
        ):
            positions = lo + np.arange(size) * (interior + 1)
            keep = (positions >= 0) & (positions < length)
            source.append(np.nonzero(keep)[0])
            target.append(positions[keep])
        out[np.ix_(*target)] = x[np.ix_(*source)]
        return out
    return None


def _eqn_states(eqn, in_states, n, ctx):
    name = eqn.primitive.name
    params = eqn.params
    out_avals = [v.aval for v in eqn.outvars]
    if name in _CALLS:
        sub = params.get("jaxpr", params.get("call_jaxpr"))
        closed = sub if hasattr(sub, "consts") else None
        jaxpr = sub.jaxpr if hasattr(sub, "jaxpr") else sub
        consts = closed.consts if closed is not None else []
        return _interpret(jaxpr, consts, in_states, n, ctx)
    if len(out_avals) != 1:
        return _opaque(in_states, out_avals, n, ctx)
    aval = out_avals[0]
    shape = tuple(aval.shape)
    _check_size(shape, n)
    differentiable = _differentiable(aval)
    in_shapes = [tuple(s.nz.shape) for s in in_states]

    def finish(nz, dep):
        if not differentiable:
            dep = np.zeros((*shape, n), bool)
        return [_State(np.asarray(nz, bool).reshape(shape), dep.reshape(*shape, n))]

    if name == "pad":
        value = in_states[1]
        index = _index_map(name, params, in_shapes[:1], shape)
        src = in_states[0]
        nz = np.where(index >= 0, src.nz.reshape(-1)[index], value.nz.reshape(()))
        dep = np.where(
            (index >= 0)[..., None],
            src.dep.reshape(src.nz.size, n)[index],
            value.dep.reshape(n),
        )
        return finish(nz, dep)
    index = _index_map(name, params, in_shapes, shape)
    if index is not None:
        nz = np.concatenate([s.nz.reshape(-1) for s in in_states])[index]
        dep = np.concatenate([s.dep.reshape(s.nz.size, n) for s in in_states])[index]
        return finish(nz, dep)
    if name in ("reduce_sum", "reduce_max", "reduce_min", "reduce_prod"):
        axes = tuple(params["axes"])
        src = in_states[0]
        nz = src.nz.any(axis=axes) if axes else src.nz
        if name == "reduce_prod":
            nz = np.ones(shape, bool)
        dep = src.dep.any(axis=axes) if axes else src.dep
        return finish(nz, dep)
    if name in ("dot_general", "mul", "div"):
        # A product with an exact zero is zero (but for `0 * inf`) and carries no
        # derivative, which the rules here do not exploit: not exact.
        if any(not s.nz.all() for s in in_states) and any(
            s.dep.any() for s in in_states
        ):
            ctx["exact"] = False
    if name == "dot_general":
        return finish(*_dot_general(params, in_states, shape, n))
    elementwise = (
        name in _ZERO_PRESERVING_UNARY
        or name in _OTHER_UNARY
        or name in _SUM_LIKE
        or name in _OTHER_ELEMENTWISE
    )
    if elementwise and all(s in (shape, ()) for s in in_shapes):
        nzs = [np.broadcast_to(s.nz, shape) for s in in_states]
        deps = [np.broadcast_to(s.dep, (*shape, n)) for s in in_states]
        if name == "select_n":
            # The predicate picks; the value comes from one of the cases.
            nz = np.logical_or.reduce(nzs[1:])
            dep = np.logical_or.reduce(deps[1:])
            return finish(nz, dep)
        dep = np.logical_or.reduce(deps) if deps else np.zeros((*shape, n), bool)
        if name in _ZERO_PRESERVING_UNARY or name in _SUM_LIKE:
            nz = np.logical_or.reduce(nzs)
        else:
            nz = np.ones(shape, bool)
        return finish(nz, dep)
    return _opaque(in_states, out_avals, n, ctx)


def _dot_general(params, in_states, shape, n):
    """Entry `(batch, lhs free, rhs free)` may be nonzero unless both operands are
    zero along its contraction, and depends on both along it."""
    (lc, rc), (lb, rb) = params["dimension_numbers"]
    lhs, rhs = in_states
    lfree = [d for d in range(lhs.nz.ndim) if d not in lc and d not in lb]
    rfree = [d for d in range(rhs.nz.ndim) if d not in rc and d not in rb]

    def arrange(x, batch, free, contract, extra):
        order = [*batch, *free, *contract]
        x = np.transpose(x, order + list(range(x.ndim - extra, x.ndim)))
        b = math.prod(x.shape[: len(batch)])
        f = math.prod(x.shape[len(batch) : len(batch) + len(free)])
        c = math.prod(x.shape[len(batch) + len(free) : len(order)])
        return x.reshape(b, f, c, *x.shape[len(order) :])

    l_nz = arrange(lhs.nz, lb, lfree, lc, 0).any(axis=2)
    r_nz = arrange(rhs.nz, rb, rfree, rc, 0).any(axis=2)
    l_dep = arrange(lhs.dep, lb, lfree, lc, 1).any(axis=2)
    r_dep = arrange(rhs.dep, rb, rfree, rc, 1).any(axis=2)
    # `0 * inf` is NaN: a term is zero only when both its factors are.
    nz = l_nz[:, :, None] | r_nz[:, None, :]
    dep = l_dep[:, :, None, :] | r_dep[:, None, :, :]
    return nz.reshape(shape), dep.reshape(*shape, n)


def _literal_state(value, n):
    value = np.asarray(value)
    _check_size(value.shape, n)
    nz = (value != 0) | ~np.isfinite(value) if value.dtype.kind in "fc" else value != 0
    return _State(np.asarray(nz, bool), np.zeros((*value.shape, n), bool))


def _interpret(jaxpr, consts, in_states, n, ctx):
    env = {}

    def read(v):
        if isinstance(v, Literal):
            return _literal_state(v.val, n)
        return env[v]

    for v, c in zip(jaxpr.constvars, consts, strict=True):
        env[v] = _literal_state(c, n)
    for v, s in zip(jaxpr.invars, in_states, strict=True):
        env[v] = s
    for eqn in jaxpr.eqns:
        outs = _eqn_states(eqn, [read(v) for v in eqn.invars], n, ctx)
        for v, s in zip(eqn.outvars, outs, strict=True):
            env[v] = s
    return [read(v) for v in jaxpr.outvars]


def _analyse(fn, example_args, wrt):
    """`(states, exact)`: the `_State` of each output leaf of `fn(*example_args)`,
    following the entries of `example_args[wrt]` (`None`: no input followed), and
    whether every rule applied was exact (no opaque operation, no product with an
    exact zero): then the patterns are the program's structural patterns, not only
    bounds of them."""
    closed = jax.make_jaxpr(fn)(*example_args)
    flat_in = [jax.tree_util.tree_leaves(a) for a in example_args]
    n = int(np.size(example_args[wrt])) if wrt is not None else 0
    states = []
    for i, leaves in enumerate(flat_in):
        for leaf in leaves:
            shape = tuple(np.shape(leaf))
            _check_size(shape, n)
            if i == wrt:
                dep = np.eye(n, dtype=bool).reshape(*shape, n)
            else:
                dep = np.zeros((*shape, n), bool)
            states.append(_State(np.ones(shape, bool), dep))
    ctx = {"exact": True}
    return _interpret(closed.jaxpr, closed.consts, states, n, ctx), ctx["exact"]


def dependency_pattern(fn, example_args, wrt: int, exact: bool = False):
    """Boolean `(m, n)`: whether output entry `i` of `fn` (one array, `m` entries)
    may depend on entry `j` of `example_args[wrt]` (`n` entries); `None` when the
    analysis gives up, or, with `exact`, when a rule only bounded the pattern."""
    try:
        (out,), is_exact = _analyse(fn, example_args, wrt)
        if exact and not is_exact:
            return None
        n = int(np.size(example_args[wrt]))
        return np.asarray(out.dep.reshape(out.nz.size, n), bool)
    except Exception:
        return None


def nonzero_pattern(fn, example_args, exact: bool = False):
    """Boolean, the shape of `fn`'s output (one array): whether each entry may be
    nonzero; `None` when the analysis gives up, or, with `exact`, when a rule only
    bounded the pattern."""
    try:
        (out,), is_exact = _analyse(fn, example_args, None)
        if exact and not is_exact:
            return None
        return np.asarray(out.nz, bool)
    except Exception:
        return None
