"""The cost of friction: contact runs with `cjax.Coulomb` against the same runs
without it, the first call (trace, lower, compile) and the run, one trajectory and a
`jax.vmap` batch.

Cases (float64, Tsit5, the default controller, `SaveAt(t1=True)`, `max_events=4`):

- `disk, frictionless`: the disk of `scenes.sliding_disk` launched at `v0` on a floor
  that is a `Unilateral` normal row only (it slides for ever);
- `disk, friction`: the scene itself (`cjax.Coulomb`, mu_k = 0.3): it slips, then
  rolls from `t* = v0 / (3 mu_k g)` (one stick-slip event);
- `cylinders, rolling`: the lecture's two cylinders with both rows (contact, no slip)
  in one `Unilateral` (friction as large as needed): it rolls, then lets go;
- `cylinders, friction`: `scenes.two_cylinders_friction` (mu_s = 0.3, mu_k = 0.2):
  it rolls, slips, then lets go.

Each run is 1.2 s long from one start; the batch is 64 starts (`v0` from 1 to 4, or
`theta0` from 0.1 to 0.5). Every case is a fresh process (nothing cached); each
measures the first call of one trajectory (`jax.jit(fn).lower(...)`, `.compile()`),
then the median run time of the compiled program over 7 calls, and the same for the
batch (the time per trajectory). Medians over `--processes` processes.

    python benchmarks/friction.py [--processes 3]

Writes `results/friction.json` and `results/friction.png`.
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path


HERE = Path(__file__).resolve().parent
ROOT = HERE.parent

_CHILD = r"""
import json, sys, time
sys.path.insert(0, {root!r})
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import numpy as np
import constrained_jax as cjax
from constrained_jax.scenes import sliding_disk, two_cylinders, two_cylinders_friction

case = {case!r}
if case.startswith("disk"):
    args = sliding_disk.default_args()
    if case.endswith("friction"):
        system = sliding_disk.system()
    else:
        floor = cjax.Unilateral(cjax.Holonomic(sliding_disk.gap),
                                gap=sliding_disk.gap, restitution=0.0)
        system = cjax.LagrangianSystem(sliding_disk.lagrangian, floor)

    def start(p):
        return sliding_disk.state(p, args)

    batch = jnp.linspace(1.0, 4.0, 64)
    p0 = jnp.asarray(3.0)
else:
    args = two_cylinders_friction.default_args()
    if case.endswith("friction"):
        system = two_cylinders_friction.system()
    else:
        gap = two_cylinders_friction.gap
        contact = cjax.Unilateral(cjax.Pfaffian(two_cylinders.pfaffian_rows),
                                  gap=gap, restitution=0.0)
        system = cjax.LagrangianSystem(two_cylinders.lagrangian, contact)

    def start(p):
        return two_cylinders.state(p, jnp.zeros_like(p), args)

    batch = jnp.linspace(0.1, 0.5, 64)
    p0 = jnp.asarray(0.3)


def fn(p, args):
    q0, qd0 = start(p)
    traj = cjax.simulate(system, (0.0, 1.2), q0, qd0, args, max_events=4,
                         throw=False)
    return traj.q[-1], traj.result, traj.events.count


def timed(f, *inputs):
    times = []
    for _ in range(7):
        t = time.perf_counter()
        jax.block_until_ready(f(*inputs))
        times.append(time.perf_counter() - t)
    return float(np.median(times))


t = time.perf_counter()
lowered = jax.jit(fn).lower(p0, args)
traced = time.perf_counter()
compiled = lowered.compile()
done = time.perf_counter()
out = {{"trace_lower_s": traced - t, "compile_s": done - traced}}
_, result, count = compiled(p0, args)
assert result == cjax.RESULTS.successful, result
out["events"] = int(count)
out["run_s"] = timed(compiled, p0, args)
batched = jax.jit(jax.vmap(fn, in_axes=(0, None)))
_, results, _ = jax.block_until_ready(batched(batch, args))
assert bool(jnp.all(results == cjax.RESULTS.successful))
out["vmap_s_per_trajectory"] = timed(batched, batch, args) / batch.shape[0]
print("RESULT" + json.dumps(out))
"""

CASES = (
    "disk, frictionless",
    "disk, friction",
    "cylinders, rolling",
    "cylinders, friction",
)
FIELDS = ("trace_lower_s", "compile_s", "run_s", "vmap_s_per_trajectory")


def run_child(case: str) -> dict:
    code = _CHILD.format(root=str(ROOT), case=case)
    env = {**os.environ, "JAX_ENABLE_COMPILATION_CACHE": "false"}
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env
    )
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT")]
    if proc.returncode or not lines:
        raise RuntimeError(proc.stderr[-3000:])
    return json.loads(lines[-1][len("RESULT") :])


def plot(medians: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.6))
    labels = list(medians)
    colours = ["C0", "C1", "C0", "C1"]
    panels = [
        ("first call [s]", lambda m: m["trace_lower_s"] + m["compile_s"]),
        ("one run [ms]", lambda m: 1e3 * m["run_s"]),
        ("vmap 64, per run [ms]", lambda m: 1e3 * m["vmap_s_per_trajectory"]),
    ]
    for ax, (title, value) in zip(axes, panels, strict=True):
        ax.barh(labels, [value(medians[c]) for c in labels], color=colours)
        ax.set_title(title, fontsize="medium")
        ax.invert_yaxis()
    for ax in axes[1:]:
        ax.set_yticklabels([])
    fig.suptitle("the cost of friction (cjax.Coulomb): the same runs without it")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--processes", type=int, default=3)
    parser.add_argument("--out", type=Path, default=HERE / "results" / "friction.json")
    opts = parser.parse_args()
    runs: dict = {case: [] for case in CASES}
    for _ in range(opts.processes):
        for case in CASES:
            row = run_child(case)
            runs[case].append(row)
            print(case, json.dumps(row), flush=True)
    medians = {
        case: {k: statistics.median(r[k] for r in rows) for k in FIELDS}
        | {"events": rows[0]["events"]}
        for case, rows in runs.items()
    }
    print("\n| case | events | first call | one run | vmap 64, per run |")
    print("|---|---:|---:|---:|---:|")
    for case, m in medians.items():
        print(
            f"| {case} | {m['events']} | {m['trace_lower_s'] + m['compile_s']:.1f} s "
            f"| {1e3 * m['run_s']:.2f} ms | {1e3 * m['vmap_s_per_trajectory']:.3f} ms |"
        )
    for pair in (CASES[:2], CASES[2:]):
        a, b = medians[pair[0]], medians[pair[1]]
        first = (b["trace_lower_s"] + b["compile_s"]) / (
            a["trace_lower_s"] + a["compile_s"]
        )
        print(
            f"{pair[1]} / {pair[0]}: first call {first:.2f}, "
            f"run {b['run_s'] / a['run_s']:.2f}, "
            f"vmap {b['vmap_s_per_trajectory'] / a['vmap_s_per_trajectory']:.2f}"
        )
    opts.out.parent.mkdir(parents=True, exist_ok=True)
    opts.out.write_text(json.dumps({"runs": runs, "medians": medians}, indent=1))
    plot(medians, opts.out.with_suffix(".png"))
    print(f"wrote {opts.out} and {opts.out.with_suffix('.png')}")


if __name__ == "__main__":
    main()
