"""The batched equations of motion on XLA's threads and on one, from 1e3 to 1e6 states.

`jax.jit(jax.vmap(...))` of the equations of motion over a batch of states, ours
(`solve_accelerations`) against the hand-written closed forms of `dynamics.py`. On a
small machine these programs are small enough that XLA:CPU's threading decides their
time: a loop that XLA splits across its threads waits for the slowest one, and the
ratio swings from run to run. This script measures both settings in fresh processes,
alternating, `--rounds` each:

- `threads`: XLA's default (as many threads as the process may use);
- `one thread`: the process pinned to one CPU (`os.sched_setaffinity`, before JAX
  starts its backend, so that XLA:CPU sizes its thread pool to one).

For each scene (pendulum, two cylinders) and batch size (`--sizes`), the variants are
timed in turn (`time_jax_interleaved`), `--block` calls in a row each (10; 1: single
calls in turn): ours, the checked `accelerations` (which raises on a singular system)
and the hand-written closed form. Reported: nanoseconds per state and the ratio to the
hand-written program of the same process; medians over the rounds.

Why blocks: with XLA's threads a single call's time depends on the program called
before it. Blocks time each program in its own steady state, as a sweep calling it
sees it; the rounds alternate their order. Identical programs can still differ within
one process with XLA's threads: read the medians over processes.

    python benchmarks/eom_threads.py [--sizes 1000,10000,100000,1000000]
        [--rounds 3] [--block 10] [--out benchmarks/results]

Writes `eom_threads.json` and `eom_threads.png`. `targets.py` uses `run_child` for its
one-thread rows.
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path


SETTINGS = ("threads", "one thread")
# Calls in a row per variant (`time_jax_interleaved`): each program in its own steady
# state. Called singly in turn, a program's time with XLA's threads depends on the
# program called before it.
BLOCK = 10
VARIANTS = ("autodiff solve_accelerations", "autodiff accelerations (checked)")


def _child(sizes: list[int], pin: bool, block: int = BLOCK) -> dict:
    """Runs in a fresh process: `{scene: {size: {variant: ns per state}}}`, timed in
    blocks of `block` calls (`time_jax_interleaved`; `block=1`: single calls in
    turn)."""
    if pin:
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    import jax

    jax.config.update("jax_enable_x64", True)
    sys.path.insert(0, str(Path(__file__).parent))
    import dynamics
    import jax.numpy as jnp
    from _common import time_jax_interleaved

    out: dict = {}
    for scene in ("pendulum", "cylinders"):
        module = dynamics.pend if scene == "pendulum" else dynamics.cyl
        args = module.default_args()
        variants = dynamics.eom_variants(scene, jnp.asarray(0.0))
        out[scene] = {}
        for num in sizes:
            q, qd = dynamics.random_states(scene, num)
            # About 0.2 s of calls per variant, at least 9 rounds of single calls or
            # 5 rounds of blocks.
            if block == 1:
                repeats = max(9, min(201, int(2e7 / num)))
            else:
                repeats = max(5, min(41, int(2e7 / num / block)))
            outputs, infos = time_jax_interleaved(
                variants, q, qd, args, repeats=repeats, block=block
            )
            ref = outputs["hand-written"][0]
            for name in VARIANTS:
                diff = jnp.max(jnp.abs(outputs[name][0] - ref) / (1 + jnp.abs(ref)))
                if not float(diff) <= 1e-12:
                    raise AssertionError(f"{scene} {num}: {name} differs by {diff}")
            out[scene][str(num)] = {
                name: info["median_s"] / num * 1e9 for name, info in infos.items()
            }
    return out


def run_child(sizes: list[int], pin: bool, block: int = BLOCK) -> dict:
    """`_child` in a fresh Python process (pinned to one CPU with `pin`). The process
    inherits `XLA_FLAGS`, so a parent that called
    `cjax.settings.use_fast_compilation()` or `cjax.settings.use_loop_kernels()`
    measures with the same settings."""
    cmd = [sys.executable, __file__, "--child", "--sizes", ",".join(map(str, sizes))]
    cmd += ["--block", str(block)]
    if pin:
        cmd.append("--pin")
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def summarize(runs: list[dict]) -> dict:
    """Medians over the rounds of ns per state and of the ratio to hand-written."""
    out: dict = {}
    for scene, by_size in runs[0].items():
        out[scene] = {}
        for num, by_name in by_size.items():
            row = {}
            for name in by_name:
                per_state = [run[scene][num][name] for run in runs]
                ratios = [
                    run[scene][num][name] / run[scene][num]["hand-written"]
                    for run in runs
                ]
                row[name] = {
                    "ns_per_state": statistics.median(per_state),
                    "ratio_to_hand_written": statistics.median(ratios),
                    "ratios": ratios,
                }
            out[scene][num] = row
    return out


def _plot(cases: dict, path: Path) -> None:
    sys.path.insert(0, str(Path(__file__).parent))
    from _common import pyplot

    plt = pyplot()
    if plt is None:
        return
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8), sharey=True)
    styles = {"threads": "-", "one thread": "--"}
    colours = {
        "autodiff solve_accelerations": "tab:blue",
        "autodiff accelerations (checked)": "tab:green",
        "hand-written": "tab:orange",
    }
    for ax, scene in zip(axes, ("pendulum", "cylinders"), strict=True):
        for setting in SETTINGS:
            rows = cases[setting][scene]
            sizes = sorted(rows, key=int)
            for name, colour in colours.items():
                ax.loglog(
                    [int(s) for s in sizes],
                    [rows[s][name]["ns_per_state"] for s in sizes],
                    styles[setting],
                    color=colour,
                    marker="o",
                    label=f"{name}, {setting}",
                )
        ax.set_xlabel("states in the batch")
        ax.set_title(scene)
    axes[0].set_ylabel("ns per state")
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"wrote {path}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="1000,10000,100000,1000000")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--out", default=str(Path(__file__).parent / "results"))
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--pin", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument(
        "--block",
        type=int,
        default=BLOCK,
        help="calls in a row per variant (1: single calls in turn)",
    )
    opts = parser.parse_args()
    sizes = [int(s) for s in opts.sizes.split(",")]
    if opts.child:
        print(json.dumps(_child(sizes, opts.pin, opts.block)))
        return
    if not hasattr(os, "sched_setaffinity"):
        raise SystemExit("needs os.sched_setaffinity (Linux)")
    runs: dict = {setting: [] for setting in SETTINGS}
    for r in range(opts.rounds):
        for setting in SETTINGS:
            runs[setting].append(
                run_child(sizes, pin=setting == "one thread", block=opts.block)
            )
            print(f"round {r + 1}, {setting}: done", flush=True)
    cases = {setting: summarize(runs[setting]) for setting in SETTINGS}
    cases["raw"] = runs
    for scene in ("pendulum", "cylinders"):
        for num in map(str, sizes):
            line = [f"{scene:9s} {int(num):>9,d}"]
            for setting in SETTINGS:
                row = cases[setting][scene][num]
                line.append(
                    f"{setting}: ours {row[VARIANTS[0]]['ns_per_state']:6.2f} "
                    f"hand {row['hand-written']['ns_per_state']:6.2f} ns "
                    f"({row[VARIANTS[0]]['ratio_to_hand_written']:.2f}x, checked "
                    f"{row[VARIANTS[1]]['ratio_to_hand_written']:.2f}x)"
                )
            print(" | ".join(line))
    sys.path.insert(0, str(Path(__file__).parent))
    from _common import write_cases

    out = Path(opts.out)
    write_cases(out / "eom_threads.json", cases)
    _plot(cases, out / "eom_threads.png")


if __name__ == "__main__":
    main()
