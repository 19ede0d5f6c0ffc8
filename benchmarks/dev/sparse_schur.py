"""The structured saddle-point solve (`SparseSchur`, its two eliminations of the Schur
complement: `method="levels"` and `method="scan"`) on the N-link chain against the
dense `FullKKTLU(unroll_max=0)` and a hand-written `lax.scan` tridiagonal LDL (Thomas)
of the same Schur complement: CPU time medians after compilation (variants timed in
alternating rounds), single state and vmap over a batch, compile time, XLA temp
memory; fitted growth exponents. With `--eom`: the whole chain EOM
`jit(vmap(system.solve_accelerations))` over a batch and one `simulate` (Tsit5,
rtol = atol = 1e-8, t in [0, 1]) at the given N (default 256), default solver choice
against `SparseSchur(method="levels")`.

    python benchmarks/dev/sparse_schur.py [N ...]
    python benchmarks/dev/sparse_schur.py --eom [N]
    python benchmarks/dev/sparse_schur.py --band

`--band`: `method="levels"` against `method="scan"` (vmap over 200 states, compile)
on patterns of growing bandwidth: 2D trusses (particle j joined to j - 1 .. j - r)
and r-ary trees of rods, to check `method="auto"`'s rule (scan up to bandwidth 8).
"""

import sys
import time

import diffrax
import jax
import jax.numpy as jnp
import numpy as np


jax.config.update("jax_enable_x64", True)

import constrained_jax as cjax  # noqa: E402
from constrained_jax import FullKKTLU, SaddlePointSystem  # noqa: E402
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


def compile_(fn, *args):
    t = time.process_time()
    compiled = jax.jit(fn).lower(*args).compile()
    compile_s = time.process_time() - t
    jax.block_until_ready(compiled(*args))
    return compiled, compile_s, compiled.memory_analysis().temp_size_in_bytes


def alternating(cases, repeat=7):
    """CPU time medians of `{name: (compiled, args)}`, timed in alternating rounds
    (each round times every case once, `number` calls each)."""
    numbers = {}
    for name, (fn, args) in cases.items():
        number = 1
        while True:
            t = time.process_time()
            for _ in range(number):
                jax.block_until_ready(fn(*args))
            if time.process_time() - t > 0.02 or number > 1e5:
                break
            number *= 4
        numbers[name] = number
    times = {name: [] for name in cases}
    for _ in range(repeat):
        for name, (fn, args) in cases.items():
            t = time.process_time()
            for _ in range(numbers[name]):
                jax.block_until_ready(fn(*args))
            times[name].append((time.process_time() - t) / numbers[name])
    return {name: float(np.median(ts)) for name, ts in times.items()}


def _solve(solver, m, a, f, b):
    return solver.solve(SaddlePointSystem(m, a, f, b), 0.0)


def main(sizes):
    rows = []
    for num_links in sizes:
        mass, jac, (ms, js, rhs, bias) = problem(num_links, BATCH)
        one = lambda t: jax.tree.map(lambda x: x[0], t)  # noqa: E731
        dense = lambda m, a, f, b: _solve(FullKKTLU(unroll_max=0), m, a, f, b)  # noqa: E731
        levels = lambda m, a, f, b: _solve(SparseSchur(method="levels"), m, a, f, b)  # noqa: E731
        scan = lambda m, a, f, b: _solve(SparseSchur(method="scan"), m, a, f, b)  # noqa: E731
        variants = {
            "levels": (levels, ms, js),
            "scan": (scan, ms, js),
            "thomas": (thomas, ms, js),
        }
        if num_links <= 64:
            todense = jax.vmap(lambda x: x.todense())  # noqa: E731
            variants["dense"] = (dense, todense(ms), todense(js))
        elif num_links <= 1024:
            variants["dense"] = (dense, mass[None], jac[None])
        single, batched = {}, {}
        for name, (fn, m, a) in variants.items():
            args = (one(m), one(a), rhs[0], bias[0])
            single[name] = (*compile_(fn, *args), args)
            if name != "dense" or num_links <= 64:
                args = (m, a, rhs, bias)
                batched[name] = (*compile_(jax.vmap(fn), *args), args)
        t_single = alternating({k: (v[0], v[3]) for k, v in single.items()})
        t_batched = alternating({k: (v[0], v[3]) for k, v in batched.items()})
        for name in variants:
            s1 = (t_single[name], *single[name][1:3])
            if name in batched:
                s2 = (t_batched[name], *batched[name][1:3])
            else:
                s2 = (float("nan"),) * 3
            rows.append((num_links, name, *s1, *s2))
            print(
                f"N={num_links:5d} {name:6s} single {s1[0] * 1e6:10.1f} us "
                f"compile {s1[1]:6.2f} s temp {s1[2] / 1e6:9.3f} MB | "
                f"vmap{BATCH} {s2[0] / BATCH * 1e6:8.2f} us/state "
                f"compile {s2[1]:6.2f} s temp {s2[2] / 1e6:9.3f} MB",
                flush=True,
            )
    for name in ("levels", "scan", "thomas", "dense"):
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


def eom(num_links):
    """The whole chain EOM over a batch and one trajectory, per solver choice."""
    args = chain.default_args()
    thetas = jnp.linspace(-1.0, 1.0, BATCH)
    q, qd = jax.vmap(lambda th: chain.state(num_links, th, args, 0.5))(thetas)
    q0, qd0 = chain.state(num_links, 0.5, args)
    choices = {
        "default": chain.system(),
        "levels": chain.system(saddle_point_solver=SparseSchur(method="levels")),
    }
    eoms, sims = {}, {}
    for name, system in choices.items():

        def accelerations(q, qd, system=system):
            return system.solve_accelerations(q, qd, 0.0, args)

        def run(q0, qd0, system=system):
            traj = cjax.simulate(
                system,
                (0.0, 1.0),
                q0,
                qd0,
                args,
                solver=diffrax.Tsit5(),
                stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-8),
            )
            return traj.q[-1], traj.stats["num_steps"]

        compiled, compile_s, _ = compile_(jax.vmap(accelerations), q, qd)
        assert not np.any(compiled(q, qd)[2])
        eoms[name] = (compiled, (q, qd), compile_s)
        compiled, compile_s, _ = compile_(run, q0, qd0)
        sims[name] = (compiled, (q0, qd0), compile_s, int(compiled(q0, qd0)[1]))
    t_eom = alternating({k: v[:2] for k, v in eoms.items()}, repeat=5)
    t_sim = alternating({k: v[:2] for k, v in sims.items()}, repeat=3)
    for name in choices:
        print(
            f"N={num_links} {name:8s} EOM vmap{BATCH} "
            f"{t_eom[name] / BATCH * 1e6:8.2f} us/state (compile "
            f"{eoms[name][2]:5.2f} s) | simulate {t_sim[name]:7.3f} s, "
            f"{sims[name][3]} steps (compile {sims[name][2]:5.2f} s)",
            flush=True,
        )


def rods_problem(num, pairs, batch):
    """Unit masses in 2D joined by the rods `pairs` (`-1`: the fixed pivot), random
    positions; a batch of scaled copies."""
    rng = np.random.default_rng(0)
    points = rng.normal(size=(num, 2))
    n, k = 2 * num, len(pairs)
    jac = np.zeros((k, n))
    for row, (a, b) in enumerate(pairs):
        d = points[a] - (points[b] if b >= 0 else 0)
        jac[row, 2 * a : 2 * a + 2] = d
        if b >= 0:
            jac[row, 2 * b : 2 * b + 2] = -d
    pm, pa = np.eye(n) != 0, jac != 0

    def make(s):
        m = SparseMatrix.from_dense(jnp.eye(n) * (1 + 0.1 * s), pm)
        return m, SparseMatrix.from_dense(jnp.asarray(jac) * (1 + 0.01 * s), pa)

    ms, js = jax.vmap(make)(jnp.linspace(0, 1, batch))
    return ms, js, jnp.ones((batch, n)), jnp.ones((batch, k))


def band(batch=200):
    num = 127
    cases = {
        f"truss r={r}": [(j, j - i) for j in range(num) for i in range(1, r + 1)]
        for r in (1, 2)
    }
    cases.update(
        {f"{r}-ary tree": [(j, (j - 1) // r) for j in range(num)] for r in (2, 4)}
    )
    for label, pairs in cases.items():
        pairs = [(a, b) for a, b in pairs if b >= -1]
        args = rods_problem(num, pairs, batch)
        m, a = (jax.tree.map(lambda x: x[0], t) for t in args[:2])
        plan = _plan((m.rows, m.cols, m.shape), (a.rows, a.cols, a.shape))
        compiled, compile_s = {}, {}
        for method in ("levels", "scan"):

            def fn(m, a, f, b, method=method):
                return _solve(SparseSchur(method=method), m, a, f, b)

            c, compile_s[method], _ = compile_(jax.vmap(fn), *args)
            assert not np.any(c(*args)[2])
            compiled[method] = (c, args)
        t = alternating(compiled, repeat=5)
        print(
            f"{label:12s} k={len(pairs)} bandwidth {plan.band_width:3d} "
            f"({len(plan.levels)} levels): "
            + ", ".join(
                f"{m} {t[m] / batch * 1e6:8.1f} us/state compile {compile_s[m]:5.2f} s"
                for m in t
            ),
            flush=True,
        )


if __name__ == "__main__":
    if sys.argv[1:2] == ["--band"]:
        band()
        sys.exit()
    if sys.argv[1:2] == ["--eom"]:
        eom(int(sys.argv[2]) if len(sys.argv) > 2 else 256)
    else:
        main([int(a) for a in sys.argv[1:]] or [4, 16, 64, 256, 1024])
