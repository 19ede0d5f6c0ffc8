"""Benchmark the cost of reverse-mode gradients against the forward solves.

Four rows, each timed in one run (forward and gradient compiled first, then called in
turn, medians of the post-compilation times; `_common.time_jax_interleaved`):

1. **Two cylinders, attached** (`constrained_jax.scenes.two_cylinders`, `theta0 = 0.3`,
   `t` in `[0, 0.8]`, Tsit5, `rtol = atol = 1e-8` as in `benchmarks/dynamics.py`):
   `theta1(t1)` by `cjax.simulate` against `jax.grad` of it with respect to `I`
   (`args["I"]`), with the default adjoint (`adjoint=None`: chosen per case,
   `constrained_jax._adjoint`: forward-mode tangents for a few inputs), with
   `diffrax.RecursiveCheckpointAdjoint()`, and the same derivative in forward mode
   (`adjoint=diffrax.ForwardMode()`, `jax.jvp`).
2. **Two cylinders through the release** (`contact_system`, `t` in `[0, 1.2]`): the
   release time and `r(t1)` in free flight, and their gradients with respect to `I`
   (checked against the closed form of the detachment time).
3. **`extremize`**: 10,000 cylinder-volume problems (`scenes.cylinder_volume`) under
   `jax.vmap`; the gradient of the volumes `V*` with respect to `(b, l)` (one
   `jax.grad` of their sum: each volume depends on its own `(b, l)` only).
4. **`solve_functional`**: the catenary (`scenes.catenary`, `Chebyshev(48)`); the
   gradient of the potential energy with respect to `(rho_g, length)`.

Reported: the ratio gradient / forward per row. For `extremize` and
`solve_functional` the forward solve is also timed with `throw=False`: with
`throw=True` the forward pass checks the status (and so computes what the status
depends on, e.g. the classification of the extremum), which `jax.grad` drops. Writes
`benchmarks/results/gradients.json` and `gradients.png`.

    python benchmarks/gradients.py [--quick]
"""

import argparse
import json
import os

import diffrax
import jax
import jax.numpy as jnp
import numpy as np


jax.config.update("jax_enable_x64", True)

from _common import machine_info, time_jax_interleaved  # noqa: E402

import constrained_jax as cjax  # noqa: E402
from constrained_jax.scenes import (  # noqa: E402
    catenary as cat,
    cylinder_volume as cv,
    two_cylinders as cyl,
)


SEED = 0
THETA0 = 0.3
T1_ATTACHED = 0.8
T1_RELEASE = 1.2
TOL = 1e-8  # benchmarks/dynamics.py: JAX_TOLERANCES["cylinders"]
NUM_EXTREMIZE = 10_000
CATENARY = (0.0, 0.0, 1.0, 0.5, 2.0, 2.5)  # xl, yl, xr, yr, length, rho_g
RECURSIVE = diffrax.RecursiveCheckpointAdjoint()  # diffrax's default adjoint


def _cylinder_run(system, t1, adjoint):
    saveat = cjax.SaveAt(t1=True, multipliers=False, energy=False, violation=False)
    controller = diffrax.PIDController(rtol=TOL, atol=TOL)

    def run(inertia):
        args = {**cyl.default_args(), "I": inertia}
        q0, qd0 = cyl.state(jnp.asarray(THETA0), jnp.asarray(0.0), args)
        return cjax.simulate(
            system,
            (0.0, t1),
            q0,
            qd0,
            args,
            solver=diffrax.Tsit5(),
            stepsize_controller=controller,
            saveat=saveat,
            adjoint=adjoint,
        )

    return run


def _row(fns: dict, inputs, repeats: int, forward: str = "forward") -> dict:
    outputs, infos = time_jax_interleaved(fns, inputs, repeats=repeats)
    base = infos[forward]["median_s"]
    for name, info in infos.items():
        info["ratio_to_forward"] = info["median_s"] / base
        info.pop("lapack_calls_in_hlo", None)
        print(
            f"  {name:28s} {info['median_s'] * 1e3:9.3f} ms  "
            f"{info['ratio_to_forward']:5.2f}x forward  "
            f"(compile {info['compile_s']:.1f} s)"
        )
    return {"methods": infos, "outputs": outputs}


def cylinders_attached(repeats: int) -> dict:
    system = cyl.system()
    theta1 = lambda adjoint: (
        lambda i: _cylinder_run(system, T1_ATTACHED, adjoint)(i).q[-1, 1]
    )
    fns = {
        "forward": theta1(None),
        "grad (adjoint=None)": jax.grad(theta1(None)),
        "grad (RecursiveCheckpoint)": jax.grad(theta1(RECURSIVE)),
        "jvp (ForwardMode)": lambda i: jax.jvp(
            theta1(diffrax.ForwardMode()), (i,), (jnp.ones_like(i),)
        ),
    }
    inertia = cyl.default_args()["I"]
    row = _row(fns, inertia, repeats)
    outputs = row.pop("outputs")
    row["theta1_t1"] = float(outputs["forward"])
    row["dtheta1_dI"] = float(outputs["grad (adjoint=None)"])
    return row


def cylinders_release(repeats: int) -> dict:
    system = cyl.contact_system()

    def outputs(adjoint):
        def fn(inertia):
            traj = _cylinder_run(system, T1_RELEASE, adjoint)(inertia)
            return traj.release.time, traj.q[-1, 0]

        return fn

    def summed(adjoint):
        return lambda i: sum(outputs(adjoint)(i))

    fns = {
        "forward": outputs(None),
        "grad (adjoint=None)": jax.grad(summed(None)),
        "grad (RecursiveCheckpoint)": jax.grad(summed(RECURSIVE)),
        "jvp (ForwardMode)": lambda i: jax.jvp(
            summed(diffrax.ForwardMode()), (i,), (jnp.ones_like(i),)
        ),
    }
    inertia = cyl.default_args()["I"]
    row = _row(fns, inertia, repeats)
    row.pop("outputs")
    release_grad = jax.jit(jax.grad(lambda i: outputs(None)(i)[0]))(inertia)
    closed = jax.grad(
        lambda i: cyl.detachment_time(
            jnp.asarray(THETA0), {**cyl.default_args(), "I": i}
        )
    )(inertia)
    row["dtrelease_dI"] = float(release_grad)
    row["dtrelease_dI_closed_form"] = float(closed)
    return row


def extremize_batch(repeats: int, num: int) -> dict:
    rng = np.random.default_rng(SEED)
    b = jnp.asarray(10.0 ** rng.uniform(-2.0, 2.0, num))
    l = jnp.asarray(10.0 ** rng.uniform(-1.0, 1.0, num))

    def volumes(bl, throw=True):
        b, l = bl
        one = lambda b, l: (
            cjax.extremize(
                cv.volume,
                cv.initial_guess(b, l),
                {"b": b, "l": l},
                constraints=cv.constraint,
                throw=throw,
            ).value
        )
        return jax.vmap(one)(b, l)

    fns = {
        "forward": volumes,
        "forward (throw=False)": lambda bl: volumes(bl, throw=False),
        "grad": jax.grad(lambda bl: jnp.sum(volumes(bl))),
    }
    row = _row(fns, (b, l), repeats)
    outputs = row.pop("outputs")
    ref = jax.grad(lambda bl: jnp.sum(cv.closed_form(*bl)["volume"]))((b, l))
    row["grad_rel_error_vs_closed_form"] = max(
        float(jnp.max(jnp.abs(g - r) / jnp.abs(r)))
        for g, r in zip(outputs["grad"], ref, strict=True)
    )
    row["num_problems"] = num
    return row


def catenary(repeats: int) -> dict:
    xl, yl, xr, yr, length, rho_g = CATENARY
    fun = cat.functional(xl, yl, xr, yr)
    guess = cat.initial_guess(xl, yl, xr, yr, length)

    def energy(p, throw=True):
        args = {"rho_g": p[0], "length": p[1]}
        sol = cjax.solve_functional(
            fun, args, discretization=cjax.Chebyshev(48), y0=guess, throw=throw
        )
        return sol.value

    fns = {
        "forward": energy,
        "forward (throw=False)": lambda p: energy(p, throw=False),
        "grad": jax.grad(energy),
    }
    row = _row(fns, jnp.array([rho_g, length]), repeats)
    row.pop("outputs")
    return row


def plot(results: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels, ratios = [], []
    for row_name, row in results["rows"].items():
        for name, info in row["methods"].items():
            if name != "forward":
                labels.append(f"{row_name}\n{name}")
                ratios.append(info["ratio_to_forward"])
    fig, ax = plt.subplots(figsize=(8, 0.6 * len(labels) + 1.5))
    y = np.arange(len(labels))
    ax.barh(y, ratios, color="tab:blue")
    ax.axvline(3.0, color="tab:red", ls="--", label="target: 3x")
    ax.set_yticks(y, labels, fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel("reverse-mode gradient time / forward solve time")
    ax.legend()
    ax.set_title("Gradients against their forward solves (after compilation)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats")
    parser.add_argument("--out", default=os.path.join("benchmarks", "results"))
    opts = parser.parse_args()
    repeats = 5 if opts.quick else 31
    num = 1_000 if opts.quick else NUM_EXTREMIZE
    os.makedirs(opts.out, exist_ok=True)
    results = {
        "machine": machine_info(diffrax=diffrax.__version__),
        "quick": opts.quick,
        "settings": {
            "theta0": THETA0,
            "t1_attached": T1_ATTACHED,
            "t1_release": T1_RELEASE,
            "rtol_atol": TOL,
            "solver": "Tsit5",
            "catenary": CATENARY,
            "seed": SEED,
        },
        "rows": {},
    }
    steps = [
        ("cylinders attached: d theta1(t1)/dI", lambda: cylinders_attached(repeats)),
        ("cylinders release: d(t_rel + r(t1))/dI", lambda: cylinders_release(repeats)),
        (f"extremize x{num}: dV*/d(b, l)", lambda: extremize_batch(repeats, num)),
        ("solve_functional catenary: dE/d(rho_g, L)", lambda: catenary(repeats)),
    ]
    for name, step in steps:
        print(f"\n== {name} ==")
        results["rows"][name] = step()
    with open(os.path.join(opts.out, "gradients.json"), "w") as f:
        json.dump(results, f, indent=1)
    plot(results, os.path.join(opts.out, "gradients.png"))


if __name__ == "__main__":
    main()
