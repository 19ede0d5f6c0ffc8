"""Structure of the equations of motion, found once at trace time.

The sparsity patterns of the mass matrix `M = d^2 L / dqdot^2` (n x n) and of the
constraint Jacobian `A` (k x n), and which rows of `A` are constant in `q` and `t`, are
first read from the traced programs (`constrained_jax._sparsity`): which momentum
`p_i` has data flow from which velocity `qdot_j`, which holonomic `G_i` from which
`q_j`, which entries of a Pfaffian `g` are exact zeros. Where every operation met has
an exact rule (all the scenes), these are the structural patterns: proven, no state can
fill another entry, and nothing is evaluated.

Otherwise (an operation the reading treats as opaque: `lax.cond`, loops, gathers,
custom derivatives; a product with an exact zero) they are found by evaluating `M`
and `A` concretely (outside the traced program) at two random states and taking the
union of the nonzeros (NaN and inf count as nonzero). Float parameters in `args` are
drawn at random too, so that a parameter that happens to be zero (a massless
coordinate, `I = 0`) does not hide an entry that another value fills; so are typed
PRNG keys (`jax.random.key`; a raw `uint32` key is an integer array, below). Such a
pattern can miss an entry that is nonzero at the actual state (a switch in `t` or in
a parameter): unless the reading's upper bound lies inside it (then it is proven all
the same), the structured evaluation in `LagrangianSystem` checks `M v` and `A v`
along a fixed probe `v` at run time and refuses the solve on a mismatch. Detection
itself never fails: if anything goes wrong (the Lagrangian closes over traced values,
raises, integer or boolean parameters are traced) the pattern is dense, which is
always right.

Results are cached per system and per shapes and dtypes of `q` and `args`, so the
several traces of one vector field (diffrax traces it more than once) detect once.
"""

import collections
import dataclasses
import functools
import threading

import jax
import jax.numpy as jnp
import numpy as np

from ._constraints import Holonomic, Pfaffian, Unilateral
from ._sparsity import dependency_pattern, nonzero_pattern


@dataclasses.dataclass(frozen=True, eq=False)
class Structure:
    """Static (trace-time) structure of the equations of motion of one system.

    **Attributes:**

    - `mass`: boolean `(n, n)` pattern of `M` (symmetric).
    - `jac`: boolean `(k, n)` pattern of `A`.
    - `constant_rows`: boolean `(k,)`, the rows of `A` found constant in `q` and `t`.
    - `detected`: `False` when detection gave up (then the patterns are dense).
    - `mass_proven`, `jac_proven`: whether the program itself shows that `M`, `A`
      have no entry outside `mass`, `jac` (see `constrained_jax._sparsity`); then
      the run-time check of that pattern could never fire, and is left out.
    """

    mass: np.ndarray
    jac: np.ndarray
    constant_rows: np.ndarray
    detected: bool
    mass_proven: bool = False
    jac_proven: bool = False

    @property
    def mass_is_dense(self) -> bool:
        return bool(self.mass.all())

    @property
    def jac_is_dense(self) -> bool:
        return bool(self.jac.all())


def dense_structure(n: int, k: int) -> Structure:
    """The always-right fallback: every entry may be nonzero."""
    return Structure(
        np.ones((n, n), bool), np.ones((k, n), bool), np.zeros((k,), bool), False
    )


def colouring(pattern: np.ndarray) -> np.ndarray:
    """Greedy column colouring (Curtis, Powell and Reid): columns whose row patterns
    are disjoint share a colour, so one directional derivative along the sum of their
    unit vectors gives all their nonzeros.

    Returns the colour of each column, `0 .. num_colours - 1`.

    **Reference:** A. R. Curtis, M. J. D. Powell and J. K. Reid, *On the estimation
    of sparse Jacobian matrices*, J. Inst. Maths Applics 13 (1974) 117-119.
    """
    pattern = np.asarray(pattern, bool)
    num_cols = pattern.shape[1]
    colours = np.zeros(num_cols, int)
    used_rows: list[np.ndarray] = []
    for j in range(num_cols):
        rows = pattern[:, j]
        for c, used in enumerate(used_rows):
            if not np.any(used & rows):
                colours[j] = c
                used_rows[c] = used | rows
                break
        else:
            colours[j] = len(used_rows)
            used_rows.append(rows.copy())
    return colours


def probe_vector(n: int) -> np.ndarray:
    """A fixed vector with distinct entries in `[1, 2)` (the fractional parts of
    multiples of the golden ratio): the run-time check of the patterns compares the
    products with it."""
    golden = (np.sqrt(5.0) - 1) / 2
    return 1 + np.mod(golden * np.arange(1, n + 1), 1.0)


# ---------------------------------------------------------------------------------
# Detection


_CACHE: collections.OrderedDict = collections.OrderedDict()
_CACHE_SIZE = 256
_LOCK = threading.Lock()


def _is_tracer(x) -> bool:
    return isinstance(x, jax.core.Tracer)


def _is_prng_key(leaf) -> bool:
    return hasattr(leaf, "dtype") and jax.dtypes.issubdtype(
        leaf.dtype, jax.dtypes.prng_key
    )


def _random_like(leaf, rng):
    """A random value of a leaf's shape and dtype: floats (and typed PRNG keys, as
    `jax.random.key` makes them) are drawn, concrete integers and booleans kept, and
    a traced integer or boolean gives up."""
    if isinstance(leaf, (bool, int)) and not _is_tracer(leaf):
        return leaf
    if _is_prng_key(leaf):
        impl = jax.random.key_impl(leaf)
        base = jax.eval_shape(lambda: jax.random.key_data(jax.random.key(0, impl=impl)))
        bits = rng.integers(0, 2**32, size=tuple(leaf.shape) + base.shape)
        return jax.random.wrap_key_data(np.asarray(bits, base.dtype), impl=impl)
    if isinstance(leaf, float):
        return float(rng.uniform(0.5, 1.5))
    if isinstance(leaf, complex):
        return complex(rng.uniform(0.5, 1.5), rng.uniform(0.5, 1.5))
    if not hasattr(leaf, "dtype") or not hasattr(leaf, "shape"):
        return leaf  # a static leaf (a string, a callable): used as it is
    dtype = np.dtype(leaf.dtype)
    if jnp.issubdtype(dtype, jnp.inexact):
        value = rng.uniform(0.5, 1.5, leaf.shape)
        if jnp.issubdtype(dtype, jnp.complexfloating):
            value = value + 1j * rng.uniform(0.5, 1.5, leaf.shape)
        return np.asarray(value, dtype)
    if _is_tracer(leaf):
        raise _GiveUp("a traced integer or boolean parameter")
    return np.asarray(leaf)


class _GiveUp(Exception):
    pass


def _leaf_key(leaf):
    if hasattr(leaf, "shape") and hasattr(leaf, "dtype"):
        key = (tuple(leaf.shape), str(leaf.dtype))
        if _is_prng_key(leaf):
            return key  # drawn at random, like a float
        if not _is_tracer(leaf) and not jnp.issubdtype(leaf.dtype, jnp.inexact):
            # Concrete integer/boolean parameters are used as they are: part of the key.
            key = key + (np.asarray(leaf).tobytes(),)
        return key
    if isinstance(leaf, (bool, int, str)):
        return (type(leaf).__name__, leaf)
    return (type(leaf).__name__,)


def _system_key(system):
    """Identity of the user functions (the solver does not change the structure)."""
    parts = [system.lagrangian, system.forces]
    parts.extend(jax.tree_util.tree_leaves(system.constraints))
    return tuple(id(p) for p in parts), parts


def detect(system, q, t, args, n: int, k: int) -> Structure:
    """The `Structure` of `system` for coordinates like `q` and parameters like
    `args` (cached). Never raises: on any failure the patterns are dense."""
    try:
        ids, keep_alive = _system_key(system)
        leaves, treedef = jax.tree_util.tree_flatten(args)
        key = (
            ids,
            (n, k, str(q.dtype)),
            treedef,
            tuple(_leaf_key(leaf) for leaf in leaves),
        )
        hash(key)
    except Exception:
        return dense_structure(n, k)
    with _LOCK:
        if key in _CACHE:
            _CACHE.move_to_end(key)
            return _CACHE[key][0]
    structure = _detect(system, q, args, n, k)
    with _LOCK:
        _CACHE[key] = (structure, keep_alive)
        while len(_CACHE) > _CACHE_SIZE:
            _CACHE.popitem(last=False)
    return structure


def _detect(system, q, args, n, k) -> Structure:
    try:
        return _evaluate(system, q.dtype, args, n, k)
    except Exception:
        return dense_structure(n, k)


def _nonzero(x) -> np.ndarray:
    x = np.asarray(x)
    return (x != 0) | ~np.isfinite(x)


def _jacobian(system, q, t, args):
    return system.constraint_jacobian(q, t, args)


def _is_dynamic(leaf) -> bool:
    """The leaves of the drawn `args` that the program takes as inputs (arrays and
    Python floats, weakly typed as `jax.jit` takes them); the others (Python ints and
    bools, strings, callables) are built into it, usable in Python control flow."""
    return isinstance(leaf, (np.ndarray, np.generic, jax.Array, float, complex))


# It runs twice, on a few numbers: compilation is all its cost.
_DRAW_OPTIONS = {
    "xla_backend_optimization_level": 0,
    "xla_llvm_disable_expensive_passes": True,
}


# Marks, in the leaves of `args` given to `_draw_program`, those that are inputs.
_DYNAMIC = object()


def _draw_program(system, treedef, kinds, with_constraints: bool):
    """`(q, qd, t, dynamic leaves of args, dq, dt) -> (M, A, dA along (dq, dt))`
    (`A` and `dA` only `with_constraints`) at one state. `kinds`: the leaves of
    `args`, `_DYNAMIC` where the program takes the leaf as an input."""

    def draw(q_r, qd_r, t_r, dynamic, dq, dt):
        dynamic = iter(dynamic)
        args_r = jax.tree_util.tree_unflatten(
            treedef,
            [next(dynamic) if leaf is _DYNAMIC else leaf for leaf in kinds],
        )
        mass_r = jax.jacfwd(system.momentum, argnums=1)(q_r, qd_r, t_r, args_r)
        if not with_constraints:
            return mass_r, None, None
        jac_fn = functools.partial(_jacobian, system, args=args_r)
        jac_r, djac_r = jax.jvp(jac_fn, (q_r, t_r), (dq, dt))
        return mass_r, jac_r, djac_r

    return jax.jit(draw)


def _evaluate(system, dtype, args, n, k) -> Structure:
    """Evaluates `M`, `A` and the derivative of `A` at two random states by one
    program, compiled ahead of time and called on concrete NumPy inputs. This works
    inside the trace of the caller's program (its result is concrete), and, unlike
    evaluating under `jax.ensure_compile_time_eval`, it does not evaluate the
    constants of the trace (the basis of `jax.jacfwd`, say) as separate eager
    operations, each compiled on its own."""
    rng = np.random.default_rng(20260512)
    leaves, treedef = jax.tree_util.tree_flatten(args)
    dtype = np.dtype(dtype)
    draws, kinds = [], None
    for _ in range(2):
        leaves_r = [_random_like(leaf, rng) for leaf in leaves]
        q_r = np.asarray(rng.normal(size=n), dtype)
        qd_r = np.asarray(rng.normal(size=n), dtype)
        t_r = np.asarray(rng.uniform(0.1, 1.0), dtype)
        # A, and its derivative along a random direction in (q, t): a row whose
        # derivative vanishes at both draws is constant in q and t.
        dq = np.asarray(rng.normal(size=n), dtype) if k else None
        dt = np.asarray(rng.normal(), dtype) if k else None
        dynamic = [leaf for leaf in leaves_r if _is_dynamic(leaf)]
        draws.append((q_r, qd_r, t_r, dynamic, dq, dt))
        kinds = [_DYNAMIC if _is_dynamic(leaf) else leaf for leaf in leaves_r]
    static = _read_structure(system, treedef, kinds, draws[0], n, k)
    if static is not None:
        return static
    program = _draw_program(system, treedef, kinds, bool(k))
    compiled = program.lower(*draws[0]).compile(compiler_options=_DRAW_OPTIONS)
    mass = np.zeros((n, n), bool)
    jac = np.zeros((k, n), bool)
    constant = np.ones((k,), bool)
    for draw in draws:
        mass_r, jac_r, djac_r = compiled(*draw)
        mass = mass | _nonzero(mass_r)
        if k:
            jac = jac | _nonzero(jac_r)
            constant = constant & ~np.any(_nonzero(djac_r), axis=1)
    mass = np.asarray(mass | mass.T, bool)
    jac = np.asarray(jac, bool)
    mass_proven, jac_proven = _proofs(system, treedef, kinds, draws[0], mass, jac)
    return Structure(
        mass, jac, np.asarray(constant, bool), True, mass_proven, jac_proven
    )


def _read_structure(system, treedef, kinds, draw, n, k) -> Structure | None:
    """The structure read from the traced programs alone, without evaluating
    anything, where every rule of `constrained_jax._sparsity` was exact (the
    patterns are then the structural ones, proven); `None` otherwise (an operation
    it treats as opaque, a product with an exact zero: the random states decide,
    and a pattern not proven is checked at run time)."""
    mass, jac = _reading(system, treedef, kinds, draw, exact=True)
    if mass is None or jac is None or mass.shape != (n, n) or jac.shape != (k, n):
        return None
    # Rows of `A` with no data flow from `q` or `t` (conservative: a row the
    # reading cannot clear counts as varying).
    q_r, _, t_r, dynamic, _, _ = draw
    args_of = functools.partial(_args_of, treedef, kinds)
    varying = np.zeros((k,), bool)
    if k:
        jac_of = lambda q_, t_, d_: system.constraint_jacobian(q_, t_, args_of(d_))
        for wrt in (0, 1):
            dep = dependency_pattern(jac_of, (q_r, t_r, dynamic), wrt)
            if dep is None:
                varying[:] = True
                break
            varying |= dep.reshape(k, -1).any(axis=1)
    mass = np.asarray(mass | mass.T, bool)
    return Structure(mass, np.asarray(jac, bool), ~varying, True, True, True)


def _args_of(treedef, kinds, dynamic):
    """`args` from its dynamic leaves (the others as in `kinds`)."""
    dynamic = iter(dynamic)
    return jax.tree_util.tree_unflatten(
        treedef, [next(dynamic) if leaf is _DYNAMIC else leaf for leaf in kinds]
    )


def _reading(system, treedef, kinds, draw, exact: bool):
    """`(mass, jac)`: the patterns of `M` and `A` read from the traced programs
    (the momenta's data flow from `qdot`, each holonomic `G`'s from `q`, the exact
    zeros of each Pfaffian `g`), each `None` where not read (or, with `exact`, only
    bounded)."""
    q_r, qd_r, t_r, dynamic, _, _ = draw
    args_of = functools.partial(_args_of, treedef, kinds)
    mass = dependency_pattern(
        lambda qd_, q_, t_, d_: system.momentum(q_, qd_, t_, args_of(d_)),
        (qd_r, q_r, t_r, dynamic),
        0,
        exact,
    )
    rows = [
        _rows_pattern(c, q_r, t_r, dynamic, args_of, exact) for c in system.constraints
    ]
    if any(r is None for r in rows):
        return mass, None
    jac = np.concatenate(rows) if rows else np.zeros((0, np.size(q_r)), bool)
    return mass, jac


def _proofs(system, treedef, kinds, draw, mass, jac) -> tuple[bool, bool]:
    """Whether the traced program bounds the patterns of `M` and `A` by the
    sampled `mass` and `jac` (then they are equal)."""
    bound_mass, bound_jac = _reading(system, treedef, kinds, draw, exact=False)
    mass_proven = (
        bound_mass is not None
        and bound_mass.shape == mass.shape
        and not np.any(bound_mass & ~mass)
    )
    jac_proven = (
        bound_jac is not None
        and bound_jac.shape == jac.shape
        and not np.any(bound_jac & ~jac)
    )
    return bool(mass_proven), bool(jac_proven)


def _rows_pattern(constraint, q_r, t_r, dynamic, args_of, exact=False):
    """The proven pattern of a constraint's rows of `A` (`None`: not proven). Only
    the library's own constraint types: their products at run time are those of the
    functions analysed here."""
    kind = type(constraint)
    if kind is Unilateral:
        rows = [
            _rows_pattern(c, q_r, t_r, dynamic, args_of, exact)
            for c in constraint.constraints
        ]
        if any(r is None for r in rows):
            return None
        return np.concatenate(rows) if rows else None
    if kind is Holonomic:
        return dependency_pattern(
            lambda q_, t_, d_: constraint.position_residual(q_, t_, args_of(d_)),
            (q_r, t_r, dynamic),
            0,
            exact,
        )
    if kind is Pfaffian:
        return nonzero_pattern(
            lambda q_, t_, d_: constraint.velocity_form(q_, t_, args_of(d_))[0],
            (q_r, t_r, dynamic),
            exact,
        )
    return None
