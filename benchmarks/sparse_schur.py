"""The structured saddle-point solve (`SparseSchur`) on the N-link chain against the
dense `FullKKTLU(unroll_max=0)` and a `lax.scan` tridiagonal LDL (Thomas) of the same
Schur complement: CPU time medians after compilation, single state and vmap over a
batch, compile time, XLA temp memory; fitted growth exponents.

    python benchmarks/sparse_schur.py [N ...]
"""

import sys
import time

import jax
import jax.numpy as jnp
import numpy as np


jax.config.update("jax_enable_x64", True)

from constrained_jax._solver.saddle_point import FullKKTLU  # noqa: E402
from constrained_jax._solver.sparse import SparseMatrix  # noqa: E402
from constrained_jax._solver.sparse_schur import (  # noqa: E402
    _apply_blocks,
    _factor_mass,
    _gather_sum,
    _plan,
    _spmv,
    SparseSchur,
)
from constrained_jax.scenes import chain  # noqa: E402


BATCH = 1000


def problem(num_links, batch):
    """`batch` perturbed states: the dense M and A of the first (for the patterns and
    the dense solver) and the batched values of the sparse ones (built one state at
    a time: a batch of dense matrices would not fit at large N)."""
    args = chain.default_args()
    keys = jax.random.split(jax.random.key(0), batch)

    def one(key):
        k1, k2, k3 = jax.random.split(key, 3)
        q, _ = chain.state(num_links, 0.3, args, 0.7)
        q = q + 0.01 * jax.random.normal(k1, q.shape)
        mass = jnp.eye(2 * num_links) * args["m"]
        jac = jax.jacfwd(chain.rods)(q, 0.0, args)
        rhs, bias = jax.random.normal(k2, q.shape), jax.random.normal(k3, (num_links,))
        return mass, jac, rhs, bias

    mass, jac, _, _ = one(keys[0])
    pm, pa = np.asarray(mass) != 0, np.asarray(jac) != 0

    def values(key):
        mass, jac, rhs, bias = one(key)
        m, a = SparseMatrix.from_dense(mass, pm), SparseMatrix.from_dense(jac, pa)
        return m, a, rhs, bias

    return mass, jac, jax.lax.map(values, keys)


def thomas(mass, jac, rhs, bias):
    """Same assembly as SparseSchur, then a sequential tridiagonal LDL by lax.scan."""
    plan = _plan((mass.rows, mass.cols, mass.shape), (jac.rows, jac.cols, jac.shape))
    k = plan.k
    minv, _ = _factor_mass(plan, mass.values, 0.0)
    u = _apply_blocks(plan, minv, rhs)
    s_values = _gather_sum(
        jac.values[plan.s_a1] * minv[plan.s_minv] * jac.values[plan.s_a2], plan.s_sum
    )
    diag = s_values[:k]
    position = {key: q for q, key in enumerate(plan.s_keys)}
    off = s_values[np.array([position[(i, i + 1)] for i in range(k - 1)], int)]
    g = -bias - _spmv(jac.values, plan.a_cols, u, plan.a_by_row)

    def fwd(carry, inp):
        d_prev, y_prev = carry
        a, e, gi = inp
        l = e / d_prev
        d = a - l * e
        y = gi - l * y_prev
        return (d, y), (d, l, y)

    zero = jnp.zeros((), rhs.dtype)
    e_in = jnp.concatenate([zero[None], off])
    one = jnp.ones((), rhs.dtype)
    _, (d, l, y) = jax.lax.scan(fwd, (one, zero), (diag, e_in, g))

    def bwd(x_next, inp):
        d, l_next, y = inp
        x = y / d - l_next * x_next
        return x, x

    l_next = jnp.concatenate([l[1:], zero[None]])
    _, lam = jax.lax.scan(bwd, zero, (d, l_next, y), reverse=True)
    at_lam = _spmv(jac.values, plan.a_rows, lam, plan.a_by_col)
    return u + _apply_blocks(plan, minv, at_lam), lam


def cpu_median(fn, *args, repeat=7):
    jax.block_until_ready(fn(*args))
    times = []
    number = 1
    while True:
        t = time.process_time()
        for _ in range(number):
            jax.block_until_ready(fn(*args))
        dt = time.process_time() - t
        if dt > 0.05 or number > 1e5:
            break
        number *= 4
    for _ in range(repeat):
        t = time.process_time()
        for _ in range(number):
            jax.block_until_ready(fn(*args))
        times.append((time.process_time() - t) / number)
    return float(np.median(times))


def measure(fn, *args):
    t = time.process_time()
    compiled = jax.jit(fn).lower(*args).compile()
    compile_s = time.process_time() - t
    temp = compiled.memory_analysis().temp_size_in_bytes
    return cpu_median(compiled, *args), compile_s, temp


def main(sizes):
    rows = []
    for num_links in sizes:
        mass, jac, (ms, js, rhs, bias) = problem(num_links, BATCH)
        one = lambda t: jax.tree.map(lambda v: v[0], t)  # noqa: E731
        sparse = lambda m, a, f, b: SparseSchur().solve(m, a, f, b)  # noqa: E731
        dense = lambda m, a, f, b: FullKKTLU(unroll_max=0).solve(m, a, f, b)  # noqa: E731
        variants = {"sparse": (sparse, ms, js), "scan": (thomas, ms, js)}
        if num_links <= 64:
            todense = jax.vmap(lambda x: x.todense())  # noqa: E731
            variants["dense"] = (dense, todense(ms), todense(js))
        elif num_links <= 1024:
            variants["dense"] = (dense, mass[None], jac[None])
        for name, (fn, m, a) in variants.items():
            single = measure(fn, one(m), one(a), rhs[0], bias[0])
            if name != "dense" or num_links <= 64:
                batched = measure(jax.vmap(fn), m, a, rhs, bias)
            else:
                batched = (float("nan"),) * 3
            rows.append((num_links, name, *single, *batched))
            print(
                f"N={num_links:5d} {name:6s} single {single[0] * 1e6:10.1f} us "
                f"compile {single[1]:6.2f} s temp {single[2] / 1e6:9.3f} MB | "
                f"vmap{BATCH} {batched[0] / BATCH * 1e6:8.2f} us/state "
                f"compile {batched[1]:6.2f} s temp {batched[2] / 1e6:9.3f} MB",
                flush=True,
            )
    for name in ("sparse", "scan", "dense"):
        for label, cols in (("single", (2, 3, 4)), ("vmap", (5, 6, 7))):
            sub = [r for r in rows if r[1] == name and np.isfinite(r[cols[0]])]
            if len(sub) >= 2:
                x = np.log([r[0] for r in sub])
                slopes = [
                    np.polyfit(x, np.log([r[c] for r in sub]), 1)[0] for c in cols
                ]
                print(
                    f"{name} {label}: growth exponents time {slopes[0]:.2f}, "
                    f"compile {slopes[1]:.2f}, temp {slopes[2]:.2f}"
                )


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or [4, 16, 64, 256, 1024])
