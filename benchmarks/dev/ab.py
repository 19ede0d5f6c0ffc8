"""A/B timing of two git revisions of `constrained_jax`, in one process, interleaved.

Each revision's `constrained_jax/` is exported with `git archive` into a temporary
folder under another name (`cjax_a`, `cjax_b`; the package imports itself only
relatively), so both are imported side by side. Every case is compiled once per
revision, then the calls alternate A, B, B, A, ... and each is timed by the CPU time
of the process (`time.process_time`, all threads), which a busy machine inflates far
less than wall time. The table gives medians and the ratio B / A.

Cases (float64, after compilation):

- `acc pendulum 10k`, `acc cylinders 10k`: `jit(vmap(solve_accelerations))` over
  10,000 states (the accelerations table of `dynamics.py`), with `args` closed over
  (constants: XLA folds the batch-level `lax.cond` of the diagonal fast path away);
  `..., traced args`: the same with `args` an argument, as `dynamics.py` passes them.
- `sim pendulum 20s`: one `simulate` (Tsit5, rtol = atol = 1e-8) of the Cartesian
  pendulum over 20 s.
- `sim release 1`, `sim release vmap 64`: the two cylinders with the contact
  unilateral over 3 s (release, then free flight), one run and a vmap over 64 angles.
- `sim release tour, 121 saves`: the tour's two-cylinder program (`compile_time.py`'s
  (b)): the release, 121 saves with the multipliers, `args` traced.
- `sim cylinders attached 1`: the two cylinders attached (no release) over 0.8 s.
- `sim pendulum 20s, traced args`, `sim cylinders attached 1, traced args`: the same
  runs with `args` an argument of the jitted function (the `sim` rows above close
  over them: constants, which XLA folds into the program).
- `extremize 10k`: `jit(vmap(extremize))` of 10,000 cylinder-volume problems.
- `functional Chebyshev(32)`, `functional PiecewiseLinear(1001)`: the catenary from
  the scene's parabola start.
- `sim chain N=4`, `sim chain N=64`: one `simulate` of the N-link chain over 1 s;
  `acc chain N=4 vmap 1000`, `acc chain N=64 vmap 100`: its accelerations (each
  revision's default saddle-point solver).

    python benchmarks/dev/ab.py --a REV --b HEAD [--reps 31] [--only REGEX]
        [--diffrax-patch]

Writes `benchmarks/dev/results/ab.json` and `ab.png`.
"""

import argparse
import importlib
import json
import os
import re
import subprocess
import sys
import tempfile
import time

import jax


jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402


def export(rev: str, name: str, folder: str) -> None:
    root = subprocess.check_output(["git", "rev-parse", "--show-toplevel"], text=True)
    archive = subprocess.check_output(
        ["git", "-C", root.strip(), "archive", rev, "constrained_jax"]
    )
    subprocess.run(["tar", "-x", "-C", folder], input=archive, check=True)
    os.rename(os.path.join(folder, "constrained_jax"), os.path.join(folder, name))


def cases(cj) -> dict:
    scene = lambda s: importlib.import_module(f"{cj.__name__}.scenes.{s}")
    pend, cyl = scene("pendulum"), scene("two_cylinders")
    vol, cat = scene("cylinder_volume"), scene("catenary")
    rng = np.random.default_rng(0)
    num = 10_000
    out = {}

    p_sys, p_args = pend.system(), pend.default_args()
    radius, phi = rng.uniform(0.5, 1.5, num), rng.uniform(-np.pi, np.pi, num)
    q = jnp.asarray(np.stack([radius * np.sin(phi), -radius * np.cos(phi)], 1))
    qd = jnp.asarray(rng.normal(0, 3, (num, 2)))
    acc = lambda s, a: jax.jit(
        jax.vmap(lambda q_, qd_: s.solve_accelerations(q_, qd_, 0.0, a)[:2])
    )
    out["acc pendulum 10k"] = (acc(p_sys, p_args), (q, qd))
    c_sys, c_args = cyl.system(), cyl.default_args()
    th, thd = rng.uniform(-1, 1, num), rng.normal(0, 2, num)
    cq, cqd = jax.vmap(lambda a, b: cyl.state(a, b, c_args))(
        jnp.asarray(th), jnp.asarray(thd)
    )
    out["acc cylinders 10k"] = (acc(c_sys, c_args), (cq, cqd))
    # The same with `args` traced (as `dynamics.py` and most users pass them): above,
    # closed over, they are constants and XLA folds the batch's `lax.cond` away.
    traced = lambda s: jax.jit(
        jax.vmap(
            lambda q_, qd_, a_: s.solve_accelerations(q_, qd_, 0.0, a_)[:2],
            in_axes=(0, 0, None),
        )
    )
    out["acc pendulum 10k, traced args"] = (traced(p_sys), (q, qd, p_args))
    out["acc cylinders 10k, traced args"] = (traced(c_sys), (cq, cqd, c_args))

    controller = diffrax.PIDController(rtol=1e-8, atol=1e-8)

    def pendulum_traced(theta0, args):
        q0, qd0 = pend.state(theta0, jnp.zeros_like(theta0), args)
        saveat = cj.SaveAt(t1=True, multipliers=False, energy=False, violation=False)
        traj = cj.simulate(
            p_sys, (0.0, 20.0), q0, qd0, args, solver=diffrax.Tsit5(),
            stepsize_controller=controller, saveat=saveat,
        )  # fmt: skip
        return traj.q[-1]

    # `args` closed over (constants XLA folds into the program), and an argument.
    out["sim pendulum 20s"] = (
        jax.jit(lambda theta0: pendulum_traced(theta0, p_args)),
        (jnp.asarray(1.0),),
    )
    out["sim pendulum 20s, traced args"] = (
        jax.jit(pendulum_traced),
        (jnp.asarray(1.0), p_args),
    )

    def cylinders_run(system, t1):
        """One run of the two cylinders from rest at `theta0`, the state at `t1`."""

        def run(theta0, args):
            q0, qd0 = cyl.state(theta0, jnp.zeros_like(theta0), args)
            traj = cj.simulate(
                system, (0.0, t1), q0, qd0, args, solver=diffrax.Tsit5(),
                stepsize_controller=controller, saveat=cj.SaveAt(t1=True),
            )  # fmt: skip
            return traj.q[-1]

        return run

    contact_run = cylinders_run(cyl.contact_system(), 3.0)
    release_run = lambda theta0: contact_run(theta0, c_args)
    attached = cylinders_run(cyl.system(), 0.8)
    out["sim release 1"] = (jax.jit(release_run), (jnp.asarray(0.3),))
    out["sim cylinders attached 1"] = (
        jax.jit(lambda theta0: attached(theta0, c_args)),
        (jnp.asarray(0.3),),
    )
    out["sim cylinders attached 1, traced args"] = (
        jax.jit(attached),
        (jnp.asarray(0.3), c_args),
    )
    out["sim release vmap 64"] = (
        jax.jit(jax.vmap(release_run)),
        (jnp.linspace(0.2, 0.5, 64),),
    )

    # The tour's release program (`tour/two_cylinders.py`, written again here: the
    # tour imports `constrained_jax` by name): 121 saves with the multipliers.
    def tour_run(theta0, args):
        q0, qd0 = cyl.state(theta0, jnp.zeros_like(theta0), args)
        ts = cyl.detachment_time(theta0, args) * jnp.linspace(0.0, 1.2, 121)
        return cj.simulate(
            cyl.contact_system(), (0.0, ts[-1]), q0, qd0, args,
            saveat=cj.SaveAt(ts=ts, energy=False, violation=False),
            stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-10),
            throw=False,
        )  # fmt: skip

    out["sim release tour, 121 saves"] = (
        jax.jit(tour_run),
        (jnp.asarray(0.2), cyl.default_args()),
    )

    b = jnp.asarray(np.exp(rng.uniform(np.log(1e-2), np.log(1e2), num)))
    l_ = jnp.asarray(np.exp(rng.uniform(np.log(0.1), np.log(10), num)))

    def cylinder(b_, l__):
        sol = cj.extremize(
            vol.volume, vol.initial_guess(b_, l__), {"b": b_, "l": l__},
            constraints=vol.constraint,
        )  # fmt: skip
        return sol.x, sol.multipliers

    out["extremize 10k"] = (jax.jit(jax.vmap(cylinder)), (b, l_))
    fun = cat.functional(0.0, 0.0, 1.0, 0.0)
    for disc in (cj.Chebyshev(32), cj.PiecewiseLinear(1001)):

        def rope(length, disc=disc):
            args = {"length": length, "rho_g": jnp.asarray(1.0)}
            y0 = cat.initial_guess(0.0, 0.0, 1.0, 0.0, length)
            return cj.solve_functional(fun, args, discretization=disc, y0=y0).value

        label = f"functional {type(disc).__name__}({disc.num_nodes})"
        out[label] = (jax.jit(rope), (jnp.asarray(1.5),))
    out.update(chain_cases(cj))
    return out


def _chain_lagrangian(q, qd, t, args):
    return 0.5 * jnp.dot(qd, qd) - 9.81 * jnp.sum(q[1::2])


def _chain_rods(q, t, args):
    p = q.reshape(-1, 2)
    d = p - jnp.concatenate([jnp.zeros((1, 2), p.dtype), p[:-1]])
    return (jnp.sum(d * d, axis=1) - 1.0) / 2


def chain_cases(cj) -> dict:
    """The N-link chain of `scenes.chain` (m = l = 1), written here so that a
    revision without that scene runs it too, with each revision's default solver."""
    system = cj.LagrangianSystem(_chain_lagrangian, (cj.Holonomic(_chain_rods),))
    out = {}

    def straight(num_links, theta0):
        radius = jnp.arange(1, num_links + 1, dtype=float)
        q = jnp.stack([radius * jnp.sin(theta0), -radius * jnp.cos(theta0)], 1)
        return q.reshape(-1), jnp.zeros(2 * num_links)

    for num_links in (4, 64):

        def run(theta0, num_links=num_links):
            q0, qd0 = straight(num_links, theta0)
            traj = cj.simulate(
                system, (0.0, 1.0), q0, qd0, None, solver=diffrax.Tsit5(),
                stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-8),
                saveat=cj.SaveAt(t1=True),
            )  # fmt: skip
            return traj.q[-1]

        out[f"sim chain N={num_links}"] = (jax.jit(run), (jnp.asarray(0.5),))
    rng = np.random.default_rng(1)
    for num_links, num in ((4, 1000), (64, 100)):
        phi = rng.uniform(-1, 1, (num, num_links))
        q = jnp.asarray(
            np.stack([np.cumsum(np.sin(phi), 1), -np.cumsum(np.cos(phi), 1)], 2)
        ).reshape(num, -1)
        qd = jnp.asarray(rng.normal(0, 1, q.shape))
        fn = jax.jit(
            jax.vmap(lambda q_, qd_: system.solve_accelerations(q_, qd_, 0.0, None)[:2])
        )
        out[f"acc chain N={num_links} vmap {num}"] = (fn, (q, qd))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--a", required=True, help="the base revision")
    parser.add_argument("--b", default="HEAD", help="the revision compared with it")
    parser.add_argument("--reps", type=int, default=31)
    parser.add_argument("--only", default=".", help="a regex on the case names")
    parser.add_argument(
        "--diffrax-patch",
        action="store_true",
        help="opt in to `settings.use_diffrax_patch()` in a revision that has it "
        "(revisions before it always patch diffrax)",
    )
    here = os.path.dirname(os.path.abspath(__file__))
    parser.add_argument("--out", default=os.path.join(here, "results"))
    opts = parser.parse_args()
    folder = tempfile.mkdtemp(prefix="cjax_ab_")
    export(opts.a, "cjax_a", folder)
    export(opts.b, "cjax_b", folder)
    sys.path.insert(0, folder)
    names = ("cjax_a", "cjax_b")
    pattern = re.compile(opts.only)
    compiled: dict = {}
    for name in names:
        module = importlib.import_module(name)
        if opts.diffrax_patch and hasattr(module, "settings"):
            module.settings.use_diffrax_patch()
        for label, (fn, args) in cases(module).items():
            if pattern.search(label):
                jax.block_until_ready(fn(*args))
                compiled.setdefault(label, {})[name] = (fn, args)
    times = {label: {name: [] for name in names} for label in compiled}
    for rep in range(opts.reps):
        order = names if rep % 2 == 0 else names[::-1]
        for label, by_name in compiled.items():
            for name in order:
                fn, args = by_name[name]
                start = time.process_time()
                jax.block_until_ready(fn(*args))
                times[label][name].append(time.process_time() - start)
    rows = {}
    print(f"{'case':36s} {'A':>10s} {'B':>10s}  B/A   (A = {opts.a}, B = {opts.b})")
    for label, by_name in times.items():
        a, b = (float(np.median(by_name[n])) for n in names)
        rows[label] = {"a_s": a, "b_s": b, "ratio": b / a}
        print(f"{label:36s} {a * 1e3:8.3f}ms {b * 1e3:8.3f}ms  {b / a:.2f}")
    os.makedirs(opts.out, exist_ok=True)
    path = os.path.join(opts.out, "ab.json")
    with open(path, "w") as f:
        json.dump(
            {
                "a": opts.a,
                "b": opts.b,
                "diffrax_patch": opts.diffrax_patch,
                "reps": opts.reps,
                "rows": rows,
            },
            f,
            indent=1,
        )
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print(f"wrote {path} (no matplotlib: no plot)")
        return
    fig, ax = plt.subplots(figsize=(7, 0.4 * len(rows) + 1))
    labels = list(rows)
    ax.barh(labels, [rows[k]["ratio"] for k in labels])
    ax.axvline(1.0, color="k", lw=0.8)
    ax.axvline(1.1, color="r", lw=0.8, ls="--")
    ax.set_xlabel(f"CPU time ratio {opts.b} / {opts.a} (median of {opts.reps})")
    ax.invert_yaxis()
    fig.tight_layout()
    fig.savefig(os.path.join(opts.out, "ab.png"), dpi=120)
    print(f"wrote {path} and ab.png")


if __name__ == "__main__":
    main()
