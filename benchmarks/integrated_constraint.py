"""What a constraint integrated by `integrate_pfaffian` costs in `simulate`.

A bead slides under gravity on the wire `sin(k x) + y = 0` (`k = 1.3`, Baumgarte
stabilization, so that `G` itself is evaluated at every stage). The wire is given
three ways, timed in turn in one process (`time_jax_interleaved`, medians):

- `closed form`: `cjax.Holonomic(lambda q, t, a: sin(k x) + y)`;
- `integrated`: the exact form `d(sin(k x) + y)` through
  `cjax.integrate_pfaffian` with its defaults (16 nodes, and the 15-node rule that
  checks them: `G` is refused, NaN, where they differ by more than `sqrt(eps)`
  times the integral of `|omega|`);
- `integrated, unchecked`: the same with `rtol=inf` (no refusal, and no second
  rule: 16 evaluations of the form per value of `G`).

The derivatives of an integrated `G` are the form itself (a `custom_jvp`), so its
Jacobian and acceleration bias cost one evaluation of the form; the value `G` costs
31 (16 + 15). Two workloads: one trajectory over `t in [0, 1]`, and a
`jit(vmap)` batch of 1,000 starts. Also reported: the largest difference between
the integrated and the closed-form trajectories (the same equations to round-off).

    python benchmarks/integrated_constraint.py [--repeats 21]

Writes `benchmarks/results/integrated_constraint.json`.
"""

import argparse
from pathlib import Path

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
from _common import time_jax_interleaved, write_cases  # noqa: E402

import constrained_jax as cjax  # noqa: E402


RESULTS = Path(__file__).parent / "results" / "integrated_constraint.json"

FORM = cjax.Pfaffian(
    lambda q, t, a: jnp.stack([a["k"] * jnp.cos(a["k"] * q[0]), jnp.ones_like(q[1])])[
        None
    ]
)


def _bead(q, qd, t, args):
    return 0.5 * qd @ qd - args["g"] * q[1]


def _constraint(kind, args):
    if kind == "closed form":
        return cjax.Holonomic(lambda q, t, a: jnp.sin(a["k"] * q[0]) + q[1])
    rtol = None if kind == "integrated" else float("inf")
    return cjax.integrate_pfaffian(FORM, jnp.zeros(2), 0.0, args, rtol=rtol)


def _run(kind):
    def run(x0, args):
        system = cjax.LagrangianSystem(_bead, _constraint(kind, args))
        q0 = jnp.stack([x0, -jnp.sin(args["k"] * x0)])
        qd0 = jnp.stack([jnp.ones_like(x0), -args["k"] * jnp.cos(args["k"] * x0)])
        traj = cjax.simulate(
            system,
            (0.0, 1.0),
            q0,
            qd0,
            args,
            stabilization=cjax.Baumgarte(alpha=5.0, beta=5.0),
            saveat=cjax.SaveAt(t1=True, multipliers=False, energy=False),
            throw=False,
        )
        return traj.q, traj.result._value

    return run


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=21)
    parser.add_argument("--batch", type=int, default=1000)
    ns = parser.parse_args()
    args = {"k": jnp.asarray(1.3), "g": jnp.asarray(9.81)}
    kinds = ("closed form", "integrated", "integrated, unchecked")
    cases = {}
    for workload, x0, wrap in (
        ("one trajectory", jnp.asarray(0.4), lambda f: f),
        (
            f"batch of {ns.batch}",
            jnp.linspace(-0.5, 0.5, ns.batch),
            lambda f: jax.vmap(f, in_axes=(0, None)),
        ),
    ):
        fns = {kind: wrap(_run(kind)) for kind in kinds}
        outputs, infos = time_jax_interleaved(fns, x0, args, repeats=ns.repeats)
        reference = outputs["closed form"][0]
        base = infos["closed form"]["median_s"]
        for kind in kinds:
            q, result = outputs[kind]
            info = infos[kind]
            info["successful"] = bool(jnp.all(result == 0))
            info["max_abs_difference_from_closed_form"] = float(
                jnp.max(jnp.abs(q - reference))
            )
            info["ratio_to_closed_form"] = info["median_s"] / base
            cases[f"{workload}: {kind}"] = info
            print(
                f"{workload:>16}, {kind:<22}: median {info['median_s'] * 1e3:8.3f} ms "
                f"({info['ratio_to_closed_form']:.2f}x), first call "
                f"{info['first_call_s']:.2f} s, |dq| "
                f"{info['max_abs_difference_from_closed_form']:.1e}, "
                f"successful {info['successful']}"
            )
    write_cases(RESULTS, cases)


if __name__ == "__main__":
    main()
