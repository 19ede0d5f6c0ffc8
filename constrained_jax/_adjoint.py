"""The adjoint of [`constrained_jax.simulate`][] when the user does not choose one.

`simulate(..., adjoint=None)` (the default) calls `default_adjoint`, the one place
where the adjoint is chosen per case: `ForwardJacobianAdjoint`, which computes the
reverse-mode derivative (`jax.grad`, `jax.vjp`, `jax.jacrev`) in forward mode when
few inputs are differentiated, and by `diffrax.RecursiveCheckpointAdjoint()`
otherwise. Why (`benchmarks/gradients.py` measures it):

- `diffrax.RecursiveCheckpointAdjoint()`: the backward pass recomputes each step and
    runs its reverse, whatever the number of checkpoints: the reverse of the vector
    field (the Hessians and the KKT solve of each stage; the KKT solve itself is
    differentiated by its implicit rule, `_solver/saddle_point.py`) and diffrax's loop
    machinery in reverse. Its cost is several solves, and does not grow with the
    number of differentiated inputs.
- `diffrax.ForwardMode()` with `jax.jvp`: about the cost of the solve, and under
    `jax.vmap` over tangents the cost hardly grows with their number for a small
    state. `ForwardJacobianAdjoint` uses it under `jax.grad` too: with `p`
    differentiated input scalars (counted at trace time, over the leaves actually
    perturbed: the parameters, and the closed-over scalars and initial state of a
    phase), the forward pass also pushes the `p` unit tangents through the solve (one
    batched `jax.jvp`) and keeps the Jacobian of the final state; the backward pass
    is its product with the cotangent, and no checkpoints are stored. Forward mode is
    used up to `p = 16` and `p` times the size of the state up to 256 (a large
    system's tangents cost in proportion to their number); above that
    `diffrax.RecursiveCheckpointAdjoint()`, whose forward pass is the plain solve
    and whose backward pass runs the solve again under `jax.vjp` (the residuals keep
    one structure whichever inputs are perturbed: see `_loop_fwd`).
- `diffrax.BacksolveAdjoint` (the continuous adjoint) cannot be used: `simulate`
    saves through `diffrax.SaveAt(subs=...)` and stops at events (the release),
    neither of which it supports; nor are its gradients those of the discrete solve.

The derivatives are those of the discrete solve in every case (the same to
round-off). Forward-mode autodiff (`jax.jvp`, `jax.jacfwd`) needs
`adjoint=diffrax.ForwardMode()`, as with diffrax's own reverse-mode adjoints.
"""

import functools
import inspect
import types

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np


class ForwardJacobianAdjoint(diffrax.AbstractAdjoint):
    """Reverse-mode autodiff of `diffrax.diffeqsolve` by forward mode when few input
    scalars are differentiated, by `fallback` otherwise.

    At trace time the scalars of the solve's inputs that are differentiated (the
    perturbed floating-point leaves of `args`, `y0`, the terms and the closures they
    hold) are counted. At most `max_tangents` of them, and at most `max_tangent_size`
    scalars of state tangents: the forward pass runs
    `diffrax.ForwardMode()` with their `p` unit tangents batched (the Jacobian of the
    final state, `p` tangents of it, is the only residual) and the backward pass
    contracts it with the cotangent. More: `fallback` (by default
    `diffrax.RecursiveCheckpointAdjoint()`), the plain solve forward and the
    fallback's solve again, differentiated, backward. Without differentiation it is
    the plain solve.

    **Arguments:**

    - `max_tangents`: the most differentiated scalars done in forward mode.
    - `max_tangent_size`: the most scalars of state tangents (differentiated scalars
        times the size of the state) done in forward mode.
    - `fallback`: the adjoint above these.
    """

    max_tangents: int = eqx.field(static=True, default=16)
    max_tangent_size: int = eqx.field(static=True, default=256)
    fallback: diffrax.AbstractAdjoint = diffrax.RecursiveCheckpointAdjoint()

    def loop(self, **kwargs):
        # (Integer and boolean arrays are inputs too where nothing else is closed
        # over; when closure conversion runs, they stay in `static`, as it needs.)
        convert = may_hold_tracers(eqx.filter(kwargs, eqx.is_array, inverse=True))
        is_input = eqx.is_inexact_array if convert else eqx.is_array
        dynamic, static = eqx.partition(kwargs, is_input)

        def forward(dynamic_):
            return diffrax.ForwardMode().loop(**eqx.combine(dynamic_, static))

        def reverse(dynamic_):
            return self.fallback.loop(**eqx.combine(dynamic_, static))

        if convert:
            # Closure conversion makes every array the loop closes over (in the
            # vector field, the events: a user's Lagrangian closing over a traced
            # parameter, say) an input, so that `perturbed` sees it. It traces both
            # loops now.
            forward = eqx.filter_closure_convert(forward, dynamic)
            reverse = eqx.filter_closure_convert(reverse, dynamic)
        # Else the loops close over no traced value (the library passes its own
        # arrays as leaves: `jax.tree_util.Partial` events, modules), and each is
        # traced only where it runs: `forward` once, `reverse` only when the
        # fallback differentiates. (Closure conversion would trace both, each time.)
        state_size = sum(np.size(y) for y in jtu.tree_leaves(kwargs["init_state"].y))
        most = min(self.max_tangents, self.max_tangent_size // max(state_size, 1))
        return _loop((forward, reverse, dynamic), most)


# Objects that hold no JAX value (checked by type, not searched).
_INERT = (
    bool,
    int,
    float,
    complex,
    str,
    bytes,
    type(None),
    type(Ellipsis),
    type,
    types.ModuleType,
    types.CodeType,
    np.ndarray,
    np.generic,
    np.dtype,
    inspect.Signature,
    jtu.PyTreeDef,
    jax.Array,  # (concrete: a tracer is caught first)
)


def may_hold_tracers(tree, *, max_depth: int = 64) -> bool:
    """Whether a JAX tracer may be reachable from the non-array parts `tree` of a
    solve (functions and their closures, `functools.partial`, bound methods,
    containers, objects' attributes). `True` as soon as one is found, and for
    anything it cannot look into (conservative: the caller then closure-converts,
    which is always correct)."""
    seen: set[int] = set()
    stack = [(tree, 0)]
    while stack:
        obj, depth = stack.pop()
        if isinstance(obj, jax.core.Tracer):
            return True
        if isinstance(obj, _INERT) or id(obj) in seen:
            continue
        if depth > max_depth:
            return True
        seen.add(id(obj))
        children: list = []
        if isinstance(obj, list | tuple | set | frozenset):
            children = list(obj)
        elif isinstance(obj, dict):
            children = [*obj.keys(), *obj.values()]
        elif isinstance(obj, functools.partial):
            children = [obj.func, obj.args, obj.keywords]
        elif isinstance(obj, types.FunctionType):
            for cell in obj.__closure__ or ():
                try:
                    children.append(cell.cell_contents)
                except ValueError:  # (an empty cell)
                    pass
            children += [obj.__defaults__, obj.__kwdefaults__]
        elif isinstance(obj, types.MethodType):
            children = [obj.__self__, obj.__func__]
        elif isinstance(obj, types.BuiltinFunctionType | types.BuiltinMethodType):
            children = [getattr(obj, "__self__", None)]
        else:
            wrapped = getattr(obj, "__wrapped__", None)
            attributes = getattr(obj, "__dict__", None)
            slots = [
                getattr(obj, name)
                for cls in type(obj).__mro__
                for name in getattr(cls, "__slots__", ())
                if isinstance(name, str) and hasattr(obj, name)
            ]
            if wrapped is None and attributes is None and not slots:
                return True  # (opaque: may hold anything)
            children = [wrapped, *(attributes or {}).values(), *slots]
        stack.extend((child, depth + 1) for child in children)
    return False


@eqx.filter_custom_vjp
def _loop(vjp_arg, max_tangents):
    forward, _, dynamic = vjp_arg
    return forward(dynamic)


def _differentiated(perturbed, vjp_arg, which: int):
    """`(solve, inputs, chosen)`: the perturbed leaves `inputs` of the solve `which`
    (0: forward mode, 1: the fallback) and of the loop's arrays, `solve` as a function
    of them, and the flags of those leaves among the leaves of `vjp_arg`."""
    fn, dynamic = vjp_arg[which], vjp_arg[2]
    leaves, treedef = jtu.tree_flatten((fn, dynamic))
    flags = jtu.tree_leaves((perturbed[which], perturbed[2]))
    inputs = [x for x, f in zip(leaves, flags, strict=True) if f]

    def solve(values):
        values = iter(values)
        full = [next(values) if f else x for x, f in zip(leaves, flags, strict=True)]
        fn_, dynamic_ = jtu.tree_unflatten(treedef, full)
        return fn_(dynamic_)

    chosen = [
        jtu.tree_map(lambda f: f and which == 0, perturbed[0]),
        jtu.tree_map(lambda f: f and which == 1, perturbed[1]),
        perturbed[2],
    ]
    return solve, inputs, chosen


def _forward_mode(perturbed, vjp_arg, max_tangents: int) -> bool:
    _, inputs, _ = _differentiated(perturbed, vjp_arg, 0)
    return sum(int(np.size(x)) for x in inputs) <= max_tangents


@_loop.def_fwd
def _loop_fwd(perturbed, vjp_arg, max_tangents):
    # The residuals have the same structure whichever inputs are perturbed: the
    # Jacobian (a leading axis of tangents on every leaf of the final state), with
    # no tangents (an empty axis) for the fallback, which recomputes in the backward
    # pass. JAX memoizes the traced forward rule per pattern of perturbed inputs,
    # but keeps the residuals' structure of the pattern traced last: a structure
    # that changed with the pattern (the fallback's `jax.vjp` closure against the
    # forward mode's Jacobian, or two closures) would be unflattened wrongly when a
    # memoized pattern is used again (a `lax.scan` whose carry becomes perturbed
    # after its first iteration traces two patterns; the next transformation of the
    # same cached program then fails with `StopIteration` in JAX's
    # `process_custom_vjp_call`, or reads the residuals of the other pattern).
    if not _forward_mode(perturbed, vjp_arg, max_tangents):
        forward, _, dynamic = vjp_arg
        out = forward(dynamic)
        return out, jtu.tree_map(_no_tangents, out)
    solve, inputs, _ = _differentiated(perturbed, vjp_arg, 0)
    count = sum(int(np.size(x)) for x in inputs)
    ends = np.cumsum([int(np.size(x)) for x in inputs])

    def column(i):
        basis = jnp.arange(count) == i
        tangents = [
            basis[end - x.size : end].reshape(x.shape).astype(x.dtype)
            for x, end in zip(inputs, ends, strict=True)
        ]
        return jax.jvp(solve, (inputs,), (tangents,))

    return jax.vmap(column, out_axes=(None, 0))(jnp.arange(count))


def _no_tangents(x):
    """The Jacobian leaf of `x` with no tangents (the fallback's residual)."""
    if jnp.issubdtype(jnp.result_type(x), jnp.inexact):
        return jnp.zeros((0, *jnp.shape(x)), jnp.result_type(x))
    return np.zeros((0, *jnp.shape(x)), jax.dtypes.float0)


@_loop.def_bwd
def _loop_bwd(residuals, grad_out, perturbed, vjp_arg, max_tangents):
    forward = _forward_mode(perturbed, vjp_arg, max_tangents)
    _, inputs, chosen = _differentiated(perturbed, vjp_arg, 0 if forward else 1)
    if forward:
        # The Jacobian against the cotangent, with `None` for the leaves not
        # differentiated. An entry whose cotangent is zero adds zero, also where its
        # Jacobian is not finite: under `jax.vmap` a lane whose result is discarded
        # (a contact run that is over while others go on) runs the solve anyway,
        # from a state that need not make sense, and receives a zero cotangent.
        def contract(g, j):
            if g is None or j.dtype == jax.dtypes.float0:
                return None
            return jnp.tensordot(jnp.where(g != 0, j, 0), g, axes=g.ndim)

        terms = jtu.tree_leaves(
            jtu.tree_map(contract, grad_out, residuals, is_leaf=_none)
        )
        flat = sum(terms) if terms else jnp.zeros(sum(x.size for x in inputs))
        ends = np.cumsum([int(np.size(x)) for x in inputs])
        grads = [
            flat[end - x.size : end].reshape(x.shape).astype(x.dtype)
            for x, end in zip(inputs, ends, strict=True)
        ]
    else:
        grads = _fallback_vjp(perturbed, vjp_arg, inputs, grad_out)
    grads = iter(grads)
    return jtu.tree_map(lambda c: next(grads) if c else None, tuple(chosen))


def _fallback_vjp(perturbed, vjp_arg, inputs, grad_out):
    """The fallback's reverse pass: its solve again, differentiated (`jax.vjp`) with
    respect to its perturbed `inputs`, only through the leaves of the final state
    that have a cotangent (the others, `None`, are left out of the program, as they
    are from diffrax's own reverse pass: a zero cotangent through a derivative that
    is not finite, on a lane of a `jax.vmap` batch whose result is discarded, would
    be NaN)."""
    solve, _, _ = _differentiated(perturbed, vjp_arg, 1)
    cotangents = jtu.tree_leaves(grad_out)
    if not cotangents:
        return [jnp.zeros_like(x) for x in inputs]

    def used(values):
        kept = []
        jtu.tree_map(
            lambda g, y: None if g is None else kept.append(y),
            grad_out,
            solve(values),
            is_leaf=_none,
        )
        return kept

    _, vjp = jax.vjp(used, inputs)
    (grads,) = vjp(cotangents)
    return grads


def _none(x) -> bool:
    return x is None


def default_adjoint(
    adjoint: diffrax.AbstractAdjoint | None,
) -> diffrax.AbstractAdjoint:
    """`adjoint` itself if given; otherwise the adjoint chosen for this case
    (`ForwardJacobianAdjoint()`, see the module's docstring).

    **Arguments:**

    - `adjoint`: the user's diffrax adjoint, or `None`.

    **Returns:** a diffrax adjoint.
    """
    if adjoint is None:
        return ForwardJacobianAdjoint()
    if not isinstance(adjoint, diffrax.AbstractAdjoint):
        raise ValueError(
            "`adjoint` must be a diffrax adjoint, e.g. "
            "`diffrax.RecursiveCheckpointAdjoint()` or `diffrax.ForwardMode()`, or "
            f"`None` (chosen per case), got {type(adjoint).__name__}."
        )
    return adjoint
