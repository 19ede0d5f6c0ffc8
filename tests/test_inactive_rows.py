"""Inactive constraint rows (`SaddlePointSystem.active`): every saddle-point solver
solves an inactive row as `lambda_j = 0` and ignores its entries of `A` and `b`, so
the solution is that of the system without those rows (solved here by NumPy), with
zeros at their multipliers; its derivatives are those of that smaller system.
"""

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax
from constrained_jax._solver.saddle_point import solve as solve_saddle_point
from constrained_jax._solver.sparse import SparseMatrix

from .helpers import finite_difference_grad


class Case(NamedTuple):
    """A solver and a problem for it: dense NumPy blocks and the static patterns in
    which the solver receives them (`None`: a dense block)."""

    solver: cjax.AbstractSaddlePointSolver
    mass: np.ndarray
    jac: np.ndarray
    rhs: np.ndarray
    bias: np.ndarray
    mass_pattern: np.ndarray | None
    jac_pattern: np.ndarray | None
    # Whether the system needs an active row (`M` singular): every mask below then
    # keeps one.
    needs_row: bool


def _psd(rng, n, rank):
    basis = rng.normal(size=(n, rank))
    return basis @ basis.T


def _case(name) -> Case:
    rng = np.random.default_rng(sum(map(ord, name)))
    if name.startswith("automatic"):
        # A structurally diagonal `M` (the fast path); a coupled zero mass sends
        # the solve to the general method (`RangeSpaceLDL`).
        n, k = 3, 3
        masses = rng.uniform(0.5, 2.0, size=n)
        if name == "automatic-general":
            masses[0] = 0.0
        mass, mass_pattern = np.diag(masses), np.eye(n, dtype=bool)
        jac, jac_pattern = rng.normal(size=(k, n)), None
        return Case(
            cjax.Automatic(), mass, jac, *_rhs(rng, n, k), mass_pattern, jac_pattern,
            name == "automatic-general",
        )  # fmt: skip
    if name == "range-space":
        # Detected patterns: `M` block diagonal (blocks {0, 1} and {2, 3, 4}, the
        # second singular), a sparse `A` (row 1's pattern holds row 0's).
        n, k = 5, 3
        mass = np.zeros((n, n))
        mass[:2, :2] = _psd(rng, 2, 2)
        mass[2:, 2:] = _psd(rng, 3, 2)
        jac_pattern = np.array(
            [[1, 0, 1, 0, 0], [1, 1, 1, 0, 1], [0, 1, 0, 1, 1]], bool
        )
        jac = rng.normal(size=(k, n)) * jac_pattern
        return Case(
            cjax.RangeSpaceLDL(), mass, jac, *_rhs(rng, n, k), mass != 0,
            jac_pattern, True,
        )  # fmt: skip
    if name == "range-space-dense":
        n, k = 4, 3
        return Case(
            cjax.RangeSpaceLDL(sparse=False), _psd(rng, n, n - 1),
            rng.normal(size=(k, n)), *_rhs(rng, n, k), None, None, True,
        )  # fmt: skip
    if name == "full-lu":
        n, k = 4, 3
        return Case(
            cjax.FullKKTLU(), _psd(rng, n, n - 1), rng.normal(size=(k, n)),
            *_rhs(rng, n, k), None, None, True,
        )  # fmt: skip
    if name == "lapack":
        n, k = 5, 3
        return Case(
            cjax.FullKKTLU(unroll_max=0), _psd(rng, n, n), rng.normal(size=(k, n)),
            *_rhs(rng, n, k), None, None, False,
        )  # fmt: skip
    if name.startswith("sparse-schur"):
        # A chain of 4 particles in the plane: 2 x 2 blocks of `M`, rod `r` joins
        # particle `r` to particle `r - 1` (row 0 to the pivot).
        num, dim = 4, 2
        n, k = num * dim, num
        mass = np.zeros((n, n))
        for p in range(num):
            mass[dim * p : dim * (p + 1), dim * p : dim * (p + 1)] = _psd(rng, 2, 2)
        jac_pattern = np.zeros((k, n), bool)
        for r in range(k):
            jac_pattern[r, dim * max(r - 1, 0) : dim * (r + 1)] = True
        jac = rng.normal(size=(k, n)) * jac_pattern
        method = "levels" if name == "sparse-schur-levels" else "auto"
        return Case(
            cjax.SparseSchur(method=method), mass, jac, *_rhs(rng, n, k),
            mass != 0, jac_pattern, False,
        )  # fmt: skip
    raise ValueError(name)


def _rhs(rng, n, k):
    return rng.normal(size=n), rng.normal(size=k)


NAMES = [
    "automatic-fast",
    "automatic-general",
    "range-space",
    "range-space-dense",
    "full-lu",
    "lapack",
    "sparse-schur",
    "sparse-schur-levels",
]
CASES = pytest.mark.parametrize("name", NAMES)


def _blocks(case, mass, jac):
    mass = mass if case.mass_pattern is None else SparseMatrix.from_dense(
        mass, case.mass_pattern
    )  # fmt: skip
    jac = jac if case.jac_pattern is None else SparseMatrix.from_dense(
        jac, case.jac_pattern
    )  # fmt: skip
    return mass, jac


def _solve_fn(case, fill=0.0, masked=True):
    """`(mass, jac, rhs, bias, active) -> (x, lambda, singular)` on dense arrays, in
    the case's patterns, through the library's one solve; `masked=False` ignores
    `active` (`active=None`)."""

    def fn(mass, jac, rhs, bias, active):
        mass, jac = _blocks(case, mass, jac)
        system = cjax.SaddlePointSystem(
            mass, jac, rhs, bias, active=active if masked else None
        )
        return solve_saddle_point(case.solver, system, fill)

    return fn


@functools.cache
def _jitted(name, fill=0.0, masked=True):
    return jax.jit(_solve_fn(_case(name), fill, masked))


def _reference(mass, jac, rhs, bias, active):
    """NumPy's solve of the system without the inactive rows, zeros inserted, and
    the condition number of its KKT matrix."""
    n = mass.shape[0]
    keep = np.asarray(active, bool)
    jac_r, bias_r = jac[keep], bias[keep]
    k = jac_r.shape[0]
    kkt = np.block([[mass, -jac_r.T], [jac_r, np.zeros((k, k))]])
    sol = np.linalg.solve(kkt, np.concatenate([rhs, -bias_r]))
    lam = np.zeros(jac.shape[0])
    lam[keep] = sol[n:]
    return sol[:n], lam, np.linalg.cond(kkt)


def _poisoned(jac, bias, active, value=np.nan):
    """`A` and `b` with `value` in the inactive rows."""
    jac, bias = np.array(jac), np.array(bias)
    jac[~np.asarray(active)] = value
    bias[~np.asarray(active)] = value
    return jac, bias


def _masks(case):
    """Masks with some rows inactive (at least one active where `M` needs one)."""
    k = case.jac.shape[0]
    masks = [np.array([(m >> r) & 1 for r in range(k)], bool) for m in range(2**k)]
    return [m for m in masks if not m.all() and (m.any() or not case.needs_row)]


def _assert_close(out, ref):
    """Within `1e-11`, or `1000 eps cond(K)` for an ill-conditioned draw, of the
    largest entry (at least 1)."""
    x, lam, singular = out
    x_ref, lam_ref, cond = ref
    assert not singular
    tol = max(1e-11, 1000 * np.finfo(np.float64).eps * cond)
    scale = 1 + np.max(np.abs(np.concatenate([x_ref, lam_ref])))
    np.testing.assert_allclose(x, x_ref, rtol=0, atol=tol * scale)
    np.testing.assert_allclose(lam, lam_ref, rtol=0, atol=tol * scale)


def _same_bits(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


@CASES
def test_some_rows_inactive(name):
    """Against NumPy's solve of the smaller system, one compiled program for every
    mask; whatever the inactive rows hold (NaN, inf, `1e300`), the answer is the
    same, bit for bit, and their multipliers are zero."""
    case = _case(name)
    solve = _jitted(name)
    for active in _masks(case):
        ref = _reference(case.mass, case.jac, case.rhs, case.bias, active)
        clean = solve(case.mass, case.jac, case.rhs, case.bias, active)
        _assert_close(clean, ref)
        assert np.all(np.asarray(clean[1])[~active] == 0)
        for value in (np.nan, np.inf, -1e300):
            jac, bias = _poisoned(case.jac, case.bias, active, value)
            out = solve(case.mass, jac, case.rhs, bias, active)
            for a, b in zip(out, clean, strict=True):
                assert _same_bits(a, b), (active, value)


@CASES
def test_every_row_inactive(name):
    """No row holds: `M x = f`, `lambda = 0` (with NaN in `A` and `b`); where `M` is
    singular and the force has a component along its null space, `singular`."""
    case = _case(name)
    k = case.jac.shape[0]
    active = np.zeros((k,), bool)
    jac, bias = _poisoned(case.jac, case.bias, active)
    x, lam, singular = _jitted(name)(case.mass, jac, case.rhs, bias, active)
    if case.needs_row:
        assert singular and np.all(x == 0) and np.all(lam == 0)
        return
    assert not singular
    x_ref = np.linalg.solve(case.mass, case.rhs)
    np.testing.assert_allclose(x, x_ref, rtol=0, atol=1e-12 * np.max(np.abs(x_ref)))
    assert np.all(lam == 0)


@CASES
def test_every_row_active_is_none(name):
    """`active` all true computes what `active=None` computes, bit for bit, alone
    and in a batch: evaluated operation by operation (`jax.disable_jit`). Compiled,
    they are two programs, in which XLA's code generation may contract products and
    sums differently (it does for the sparse `RangeSpaceLDL`; without LLVM's
    optimisations the two agree bit for bit): to a few units of round-off."""
    case = _case(name)
    k = case.jac.shape[0]
    args = (case.mass, case.jac, case.rhs, case.bias, np.ones((k,), bool))
    rng = np.random.default_rng(1)
    rhs = case.rhs + rng.normal(size=(3, case.rhs.shape[0]))
    batch = (case.mass, case.jac, rhs, case.bias, args[-1])
    axes = (None, None, 0, None, None)
    outs = {}
    for masked in (True, False):
        fn = _solve_fn(case, masked=masked)
        with jax.disable_jit():
            outs[masked, "eager"] = fn(*args)
            outs[masked, "eager batch"] = jax.vmap(fn, in_axes=axes)(*batch)
        outs[masked, "jit"] = jax.jit(fn)(*args)
        outs[masked, "jit batch"] = jax.jit(jax.vmap(fn, in_axes=axes))(*batch)
    for how in ("eager", "eager batch"):
        for a, b in zip(outs[True, how], outs[False, how], strict=True):
            assert _same_bits(a, b), how
    for how in ("jit", "jit batch"):
        for a, b in zip(outs[True, how], outs[False, how], strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-14, atol=1e-14)


@CASES
def test_mixed_batch_under_vmap(name):
    """A batch whose elements have different masks (and NaN in their inactive
    rows), every argument batched, and with `M` and `A` shared: each element as the
    smaller system."""
    case = _case(name)
    masks = _masks(case)
    k = case.jac.shape[0]
    masks = ([np.ones((k,), bool)] + masks)[:6]
    rng = np.random.default_rng(2)
    num = len(masks)
    active = np.stack(masks)
    rhs = case.rhs + rng.normal(size=(num, case.rhs.shape[0]))
    bias = case.bias + rng.normal(size=(num, k))
    jacs = case.jac + 0.1 * rng.normal(size=(num, *case.jac.shape))
    if case.jac_pattern is not None:
        jacs = jacs * case.jac_pattern
    masses = np.stack([case.mass * (1 + 0.1 * i) for i in range(num)])
    poisoned = [_poisoned(jacs[i], bias[i], masks[i]) for i in range(num)]
    jac_p = np.stack([p[0] for p in poisoned])
    bias_p = np.stack([p[1] for p in poisoned])
    out = jax.jit(jax.vmap(_solve_fn(case)))(masses, jac_p, rhs, bias_p, active)
    for i in range(num):
        ref = _reference(masses[i], jacs[i], rhs[i], bias[i], masks[i])
        _assert_close([v[i] for v in out], ref)
    # `M` and `A` shared by the batch (the masks still differ): inactive rows hold
    # the same finite values in every element.
    axes = (None, None, 0, 0, 0)
    out = jax.jit(jax.vmap(_solve_fn(case), in_axes=axes))(
        case.mass, case.jac, rhs, bias_p, active
    )
    for i in range(num):
        ref = _reference(case.mass, case.jac, rhs[i], bias[i], masks[i])
        _assert_close([v[i] for v in out], ref)


@CASES
@pytest.mark.parametrize(
    "mass_scale, jac_scale", [(1e-300, 1), (1e300, 1), (1, 1e-150), (1, 1e150)]
)
def test_extreme_scales(name, mass_scale, jac_scale):
    """`(s M, t A, s f, t b)` has the solution `(x, s lambda / t)` of `(M, A, f, b)`:
    with masses of `1e-300` or `1e300`, or a Jacobian of `1e-150` or `1e150`, the
    inactive rows' entry `c` follows the units of the Schur complement (or of the
    scaled KKT matrix), so no pivot is mistaken for zero nor for a breakdown (with
    `c = 1` every solver fails here)."""
    case = _case(name)
    solve = _jitted(name)
    for active in _masks(case):
        x_ref, lam_ref, _ = _reference(case.mass, case.jac, case.rhs, case.bias, active)
        jac, bias = _poisoned(jac_scale * case.jac, jac_scale * case.bias, active)
        x, lam, singular = solve(
            mass_scale * case.mass, jac, mass_scale * case.rhs, bias, active
        )
        assert not singular, active
        np.testing.assert_allclose(x, x_ref, rtol=1e-9, atol=1e-12 * np.max(abs(x_ref)))
        np.testing.assert_allclose(
            lam * jac_scale / mass_scale,
            lam_ref,
            rtol=1e-9,
            atol=1e-12 * np.max(abs(lam_ref)),
        )


def _parametrised(case, active, masked=True, nan_tangent=False):
    """`p -> (x, lambda)` for `M (1 + p0 / 10)`, `A + p1 A1 / 10`, `f + p2 f1`,
    `b + p3 b1`, the inactive rows of `A` and `b` NaN (`NaN + p1`; with
    `nan_tangent`, `sqrt(-1 - p1)`, whose derivative is NaN too); with
    `masked=False` the smaller system (the inactive rows removed, `active=None`).

    Reverse mode takes the finite derivative: the solve sends a zero cotangent to
    the inactive rows, but the chain rule then multiplies it by their partials, and
    `0 * NaN` is NaN (the `where` of any reverse-mode program). Forward mode takes
    NaN tangents: the solve drops them."""
    rng = np.random.default_rng(3)
    jac1 = 0.1 * rng.normal(size=case.jac.shape)
    if case.jac_pattern is not None:
        jac1 = jac1 * case.jac_pattern
    rhs1, bias1 = rng.normal(size=case.rhs.shape), rng.normal(size=case.bias.shape)
    keep = np.asarray(active)
    if not masked:
        reduced = case._replace(
            jac=case.jac[keep],
            bias=case.bias[keep],
            jac_pattern=None if case.jac_pattern is None else case.jac_pattern[keep],
        )
        jac1, bias1 = jac1[keep], bias1[keep]
        solve = _solve_fn(reduced, masked=False)
    else:
        reduced, solve = case, _solve_fn(case)

    def fn(p):
        poison = jnp.sqrt(-1.0 - p[1]) if nan_tangent else jnp.nan + p[1]
        jac = reduced.jac + p[1] * jac1
        bias = reduced.bias + p[3] * bias1
        if masked:
            jac = jnp.where(keep[:, None], jac, poison)
            bias = jnp.where(keep, bias, poison)
        mass = case.mass * (1 + p[0] / 10)
        x, lam, _ = solve(mass, jac, case.rhs + p[2] * rhs1, bias, keep)
        if not masked:
            lam = jnp.zeros(case.bias.shape, lam.dtype).at[np.nonzero(keep)[0]].set(lam)
        return x, lam

    return fn


@CASES
def test_derivatives(name):
    """`jax.grad` and `jax.jvp` against finite differences and against the smaller
    system's derivatives (the inactive rows NaN; in forward mode with NaN tangents):
    the tangent of an inactive multiplier is zero, and the cotangent of the inactive
    rows of `A` and `b` is zero."""
    case = _case(name)
    active = _masks(case)[-1]
    point = jnp.array([0.3, -0.2, 0.5, 0.1])
    direction = jnp.array([0.7, -1.1, 0.4, 0.9])
    masked, reduced = _parametrised(case, active), _parametrised(case, active, False)

    def loss(fn):
        return lambda p: sum(
            jnp.sum(jnp.sin(v) ** 2 + v) for v in fn(p)
        )  # fmt: skip

    grad = jax.jit(jax.grad(loss(masked)))(point)
    assert np.all(np.isfinite(grad))
    np.testing.assert_allclose(
        grad, finite_difference_grad(jax.jit(loss(masked)), point), rtol=1e-6
    )
    np.testing.assert_allclose(grad, jax.jit(jax.grad(loss(reduced)))(point), rtol=1e-9)

    masked = _parametrised(case, active, nan_tangent=True)
    jvp = jax.jit(lambda p, v: jax.jvp(masked, (p,), (v,)))
    (x, lam), (dx, dlam) = jvp(point, direction)
    _, (dx_r, dlam_r) = jax.jit(lambda p, v: jax.jvp(reduced, (p,), (v,)))(
        point, direction
    )
    assert np.all(np.asarray(dlam)[~active] == 0)
    np.testing.assert_allclose(dx, dx_r, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(dlam, dlam_r, rtol=1e-9, atol=1e-12)
    h = 1e-6
    up, down = (
        jax.jit(masked)(point + h * direction),
        jax.jit(masked)(point - h * direction),
    )
    for t, u, d in zip((dx, dlam), up, down, strict=True):
        np.testing.assert_allclose(t, (u - d) / (2 * h), rtol=1e-6, atol=1e-8)

    # The cotangent of `A` and `b` as arrays: zero on the inactive rows (NaN there).
    jac, bias = _poisoned(case.jac, case.bias, active)

    def on_blocks(jac, bias):
        x, lam, _ = _solve_fn(case)(case.mass, jac, case.rhs, bias, active)
        return jnp.sum(x**2) + jnp.sum(jnp.sin(lam))

    g_jac, g_bias = jax.jit(jax.grad(on_blocks, argnums=(0, 1)))(jac, bias)
    assert np.all(np.asarray(g_jac)[~active] == 0)
    assert np.all(np.asarray(g_bias)[~active] == 0)
    assert np.all(np.isfinite(g_jac)) and np.all(np.isfinite(g_bias))


def _redundant(case):
    """The case with row 1 twice row 0 (row 1's pattern holds row 0's)."""
    jac = np.array(case.jac)
    jac[1] = 2 * jac[0]
    return case._replace(jac=jac)


@CASES
def test_redundant_row(name):
    """Rows 0 and 1 redundant: singular while both are active, solvable (the
    smaller system) once either is inactive; `fill=nan` puts NaN in `x` only where
    the system is singular, in a batch."""
    case = _redundant(_case(name))
    k = case.jac.shape[0]
    ones = np.ones((k,), bool)
    masks = [ones, np.array([True, False] + [True] * (k - 2))]
    masks += [np.array([False, True] + [True] * (k - 2)), ones]
    x, lam, singular = _jitted(name)(case.mass, case.jac, case.rhs, case.bias, ones)
    assert singular and np.all(x == 0) and np.all(lam == 0)
    active = np.stack(masks)
    out = jax.jit(jax.vmap(_solve_fn(case, fill=np.nan), in_axes=(None,) * 4 + (0,)))(
        case.mass, case.jac, case.rhs, case.bias, active
    )
    for i, mask in enumerate(masks):
        x, lam, singular = (v[i] for v in out)
        if mask.all():
            assert singular and np.all(np.isnan(x)) and np.all(lam == 0)
        else:
            ref = _reference(case.mass, case.jac, case.rhs, case.bias, mask)
            _assert_close((x, lam, singular), ref)


@pytest.mark.parametrize("force", [0.0, 1.0])
def test_massless_coordinate_freed_by_an_inactive_row(force):
    """`M = diag(0, 1, 2)` and the row coupling coordinate 0 inactive: coordinate 0
    is then massless and free. Without a force on it, a free gauge (its acceleration
    zero, the rest the smaller system's); with one, `singular`. `Automatic` (its
    fast path falls back on the general method) as `RangeSpaceLDL` on the smaller
    system."""
    mass = SparseMatrix.from_dense(jnp.diag(jnp.array([0.0, 1.0, 2.0])), np.eye(3))
    pattern = np.array([[1, 1, 0], [0, 1, 1]], bool)
    jac = np.array([[1.0, 1.0, 0.0], [0.0, 1.0, -1.0]])
    rhs, bias = np.array([force, -1.0, 0.5]), np.array([np.nan, 0.3])
    active = np.array([False, True])
    x, lam, singular = jax.jit(
        lambda a, act: solve_saddle_point(
            cjax.Automatic(),
            cjax.SaddlePointSystem(
                mass, SparseMatrix.from_dense(a, pattern), rhs, bias, active=act
            ),
        )
    )(jac, active)
    if force:
        assert singular and np.all(x == 0) and np.all(lam == 0)
        return
    assert not singular
    reduced = cjax.SaddlePointSystem(
        mass, SparseMatrix.from_dense(jac[1:], pattern[1:]), rhs, bias[1:]
    )
    x_ref, lam_ref, singular_ref = jax.jit(
        lambda s: solve_saddle_point(cjax.RangeSpaceLDL(), s)
    )(reduced)
    assert not singular_ref and x_ref[0] == 0
    np.testing.assert_allclose(x, x_ref, rtol=1e-14)
    np.testing.assert_allclose(lam, [0.0, lam_ref[0]], rtol=1e-14)
