"""What one trajectory pays per step: the equations of motion called inside a loop,
and a trajectory split into its per-step and fixed costs.

Issue 12's row "one two-cylinder trajectory, ours / diffrax on the hand-written
right-hand side" times a whole `simulate` of 16 steps. This script takes it apart.

1. **The equations of motion inside a loop.** A `lax.fori_loop` of `--calls` calls
   on a single state (as a Runge-Kutta stage calls them), nanoseconds per call, for
   each scene:

   - `solve_accelerations`: what `simulate`'s vector field calls
     (`LagrangianSystem._solve_accelerations_in_loop`), the structured solve with its
     `lax.cond` between the diagonal fast path and the general method;
   - `fast path, no cond` (ablation): the same equations and the diagonal fast path
     alone (`_solver.diagonal.diagonal_range_space`), no `lax.cond`;
   - `equations only` (ablation): `M`, `Q - c`, `A` and the bias, no solve;
   - `hand-written`: `dynamics.py`'s closed forms.

   The state moves a little at each call (`q += 1e-9 qdot`, ...), so that XLA cannot
   hoist the call out of the loop; values that depend on `args` only may be hoisted,
   as in `simulate`.
2. **One two-cylinder trajectory at two horizons** (`t1 = 0.8` and `1.6`: 16 and 32
   steps of Tsit5 at `rtol = atol = 1e-8`), ours and the hand-written right-hand
   side under `diffrax.diffeqsolve`, all four programs called in turn: the slope
   gives the cost of a step, the intercept the fixed cost of a run (checks, set-up,
   the end-state solve).

Medians of `--repeats` rounds (each round calls every program once, in turn).

    python benchmarks/eom_in_loop.py [--calls 2000] [--repeats 201]
        [--out benchmarks/results] [--loop-kernels]

Writes `eom_in_loop.json` and `eom_in_loop.png` (`--loop-kernels`, which measures with
`cjax.settings.use_loop_kernels()`: `eom_in_loop_loop_kernels.json`, `.png`).
"""

import argparse
from pathlib import Path

import jax


jax.config.update("jax_enable_x64", True)

import dynamics  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from _common import pyplot, time_jax_interleaved, write_cases  # noqa: E402
from jax import lax  # noqa: E402

from constrained_jax._solver.diagonal import diagonal_range_space  # noqa: E402


def _in_loop(fn, calls: int):
    """`jit` of `calls` calls of `fn(q, qd, t, args) -> (qdd, lam)` in a loop."""

    def run(q, qd, args):
        def body(i, state):
            q_, qd_ = state
            qdd, lam = fn(q_, qd_, i * 1e-3, args)
            return q_ + 1e-9 * qd_, qd_ + 1e-9 * qdd + 1e-12 * jnp.sum(lam)

        return lax.fori_loop(0, calls, body, (q, qd))

    return jax.jit(run)


def eom_in_loop(scene: str, calls: int, repeats: int) -> dict:
    module = dynamics.pend if scene == "pendulum" else dynamics.cyl
    system = module.system()
    args = module.default_args()
    q, qd = dynamics.random_states(scene, 1)
    q, qd = q[0], qd[0]
    by_hand = (
        dynamics.pendulum_accelerations_by_hand
        if scene == "pendulum"
        else dynamics.cylinders_accelerations_by_hand
    )

    def solve(q, qd, t, args):
        return system._solve_accelerations_in_loop(q, qd, t, args)[:2]

    def fast_path(q, qd, t, args):
        mass, rhs, jac, bias, _ = system._equations(q, qd, t, args)
        return diagonal_range_space(mass, jac, rhs, bias)[:2]

    def equations(q, qd, t, args):
        mass, rhs, jac, bias, _ = system._equations(q, qd, t, args)
        # (Every entry used, so that none of them is left out of the program.)
        entries = sum(jnp.sum(leaf) for leaf in jax.tree.leaves((mass, jac)))
        return rhs + entries, bias

    def hand(q, qd, t, args):
        return by_hand(q, qd, args)

    variants = {
        "solve_accelerations": solve,
        "fast path, no cond": fast_path,
        "equations only": equations,
        "hand-written": hand,
    }
    _, infos = time_jax_interleaved(
        {name: _in_loop(fn, calls) for name, fn in variants.items()},
        q,
        qd,
        args,
        repeats=repeats,
    )
    rows = {
        name: {"ns_per_call": info["median_s"] / calls * 1e9}
        for name, info in infos.items()
    }
    hand_ns = rows["hand-written"]["ns_per_call"]
    for row in rows.values():
        row["ratio_to_hand_written"] = row["ns_per_call"] / hand_ns
    return {"calls": calls, "repeats": repeats, "methods": rows}


def trajectory_split(repeats: int) -> dict:
    """Per-step and fixed cost of one two-cylinder trajectory, ours and by hand."""
    theta0 = jnp.asarray(dynamics.CYLINDERS_THETA0)
    args = dynamics.cyl.default_args()
    tol = dynamics.JAX_TOLERANCES["cylinders"]
    horizons = (0.8, 1.6)

    def at(t1, make):
        # `_final_state` reads the horizon when it is traced.
        fn = make("cylinders", tol)

        def final_state(theta0, args):
            saved = dynamics.CYLINDERS_T1
            dynamics.CYLINDERS_T1 = t1
            try:
                return fn(theta0, args)
            finally:
                dynamics.CYLINDERS_T1 = saved

        return final_state

    fns = {}
    for t1 in horizons:
        fns[f"ours {t1}"] = at(t1, dynamics._final_state)
        fns[f"hand {t1}"] = at(t1, dynamics._final_state_by_hand)
    outputs, infos = time_jax_interleaved(fns, theta0, args, repeats=repeats)
    medians = {name: info["median_s"] for name, info in infos.items()}
    steps = {t1: int(outputs[f"ours {t1}"][2]) for t1 in horizons}
    out: dict = {"steps": {str(t1): steps[t1] for t1 in horizons}}
    for who in ("ours", "hand"):
        (t_a, t_b) = (medians[f"{who} {t1}"] for t1 in horizons)
        per_step = (t_b - t_a) / (steps[horizons[1]] - steps[horizons[0]])
        out[who] = {
            "median_s": {str(t1): medians[f"{who} {t1}"] for t1 in horizons},
            "per_step_s": per_step,
            "fixed_s": t_a - per_step * steps[horizons[0]],
        }
    return out


def _plot(cases: dict, path: Path) -> None:
    plt = pyplot()
    if plt is None:
        return
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.6))
    ax = axes[0]
    labels, values = [], []
    for scene in ("pendulum", "cylinders"):
        for name, row in cases[scene]["methods"].items():
            labels.append(f"{scene}: {name}")
            values.append(row["ns_per_call"])
    ax.barh(range(len(values)), values, color="tab:blue")
    ax.set_yticks(range(len(values)), labels, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("ns per call, inside a fori_loop")
    ax.set_title("Equations of motion in a loop")
    ax = axes[1]
    split = cases["trajectory"]
    for who, colour in (("ours", "tab:blue"), ("hand", "tab:orange")):
        xs = [split["steps"][t1] for t1 in split[who]["median_s"]]
        ys = [v * 1e3 for v in split[who]["median_s"].values()]
        ax.plot(xs, ys, "o-", color=colour, label=who)
    ax.set_xlabel("accepted steps")
    ax.set_ylabel("ms per trajectory")
    ax.set_xlim(left=0)
    ax.set_ylim(bottom=0)
    ax.legend()
    ax.set_title("One two-cylinder trajectory")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"wrote {path}")


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--calls", type=int, default=2000)
    parser.add_argument("--repeats", type=int, default=201)
    parser.add_argument("--out", default=str(Path(__file__).parent / "results"))
    parser.add_argument("--loop-kernels", action="store_true")
    opts = parser.parse_args()
    if opts.loop_kernels:
        import constrained_jax as cjax

        assert cjax.settings.use_loop_kernels()
    cases = {}
    for scene in ("pendulum", "cylinders"):
        cases[scene] = eom_in_loop(scene, opts.calls, opts.repeats)
        for name, row in cases[scene]["methods"].items():
            print(
                f"{scene:9s} {name:22s} {row['ns_per_call']:8.1f} ns/call "
                f"({row['ratio_to_hand_written']:.2f}x hand-written)"
            )
    cases["trajectory"] = split = trajectory_split(opts.repeats)
    for who in ("ours", "hand"):
        print(
            f"trajectory {who:4s}: {split[who]['per_step_s'] * 1e6:6.2f} us/step, "
            f"fixed {split[who]['fixed_s'] * 1e3:6.3f} ms "
            f"(steps {split['steps']})"
        )
    out = Path(opts.out)
    stem = "eom_in_loop_loop_kernels" if opts.loop_kernels else "eom_in_loop"
    write_cases(out / f"{stem}.json", cases)
    _plot(cases, out / f"{stem}.png")


if __name__ == "__main__":
    main()
