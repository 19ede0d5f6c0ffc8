"""Contact runs (`simulate(..., max_events=N)`) against plain runs of the same system:
the first call (trace, lower, compile) and the run, one trajectory and a batch.

Systems (float64, Tsit5, the default controller, `SaveAt(t1=True)`), `q = (x, y)`,
`L = m |qdot|^2 / 2 - m g y`:

- `plain 1`: the floor `y = 0` as a bilateral `Holonomic` (a ball sliding on it);
- `events 1`: the floor as a `Unilateral` with restitution 0.8 (the bouncing ball,
  dropped from 1 m), `max_events=16`;
- `plain 2`: the floor and a wall `x = 1`, both bilateral;
- `events 2`: the floor and the wall `1 - x >= 0`, both `Unilateral` with restitution
  (thrown towards the wall), `max_events=16`.

Every case is a fresh process (nothing cached), for each of two git revisions
exported by `git archive` (`--a`, `--b`), alternating. Each process measures the
first call of one trajectory (`jax.jit(fn).lower(...)`, `.compile()`), then the
median run time of the compiled program over 7 calls, and the same for
`jax.vmap` over 64 starts (the time per trajectory).

    python benchmarks/events.py --a 71caf5d --b HEAD [--processes 3] [--diffrax-patch]

`--diffrax-patch` opts in to `cjax.settings.use_diffrax_patch()` (revisions before it
patch diffrax always).

Writes `results/events.json` (every process, and the medians).
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path


HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "dev"))
from ab import export  # noqa: E402


_CHILD = r"""
import json, sys, time
sys.path.insert(0, {folder!r})
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import numpy as np
import constrained_jax as cjax
assert cjax.__file__.startswith({folder!r}), cjax.__file__
if {patch!r} and hasattr(cjax, "settings"):
    cjax.settings.use_diffrax_patch()
jax.jit(lambda x: jax.lax.fori_loop(0, 3, lambda i, c: jnp.sin(c) @ c, x))(
    jnp.ones((4, 4))
).block_until_ready()


def lagrangian(q, qd, t, args):
    return 0.5 * args["m"] * jnp.dot(qd, qd) - args["m"] * args["g"] * q[1]


floor = lambda q, t, args: q[1]
wall = lambda q, t, args: 1.0 - q[0]
args = {{"m": 1.0, "g": 9.81, "e": 0.8}}


def unilateral(gap):
    return cjax.Unilateral(
        cjax.Holonomic(gap), gap=gap, restitution=lambda a: a["e"]
    )


case = {case!r}
groups = 2 if case.endswith("2") else 1
gaps = (floor, wall)[:groups]
if case.startswith("plain"):
    system = cjax.LagrangianSystem(lagrangian, [cjax.Holonomic(g) for g in gaps])
    q0 = jnp.array([1.0, 0.0]) if groups == 2 else jnp.array([0.0, 0.0])
    qd0 = jnp.zeros(2) if groups == 2 else jnp.array([1.0, 0.0])
    extra = {{}}
else:
    system = cjax.LagrangianSystem(lagrangian, [unilateral(g) for g in gaps])
    q0, qd0 = jnp.array([0.0, 1.0]), jnp.array([0.7, 0.0])
    extra = {{"max_events": 16}}


def fn(q0, qd0, args):
    traj = cjax.simulate(system, (0.0, 2.0), q0, qd0, args, throw=False, **extra)
    return traj.q[-1], traj.result


def timed(f, *inputs):
    times = []
    for _ in range(7):
        start = time.perf_counter()
        jax.block_until_ready(f(*inputs))
        times.append(time.perf_counter() - start)
    return float(np.median(times))


start = time.perf_counter()
lowered = jax.jit(fn).lower(q0, qd0, args)
traced = time.perf_counter()
compiled = lowered.compile()
done = time.perf_counter()
out = {{"trace_lower_s": traced - start, "compile_s": done - traced}}
out["run_s"] = timed(compiled, q0, qd0, args)
batch = 64
q0s = jnp.tile(q0, (batch, 1))
if case.startswith("events"):
    q0s = q0s.at[:, 1].set(jnp.linspace(0.5, 1.5, batch))
batched = jax.jit(jax.vmap(fn, in_axes=(0, None, None)))
jax.block_until_ready(batched(q0s, qd0, args))
out["vmap_s_per_trajectory"] = timed(batched, q0s, qd0, args) / batch
print("RESULT" + json.dumps(out))
"""

CASES = ("plain1", "events1", "plain2", "events2")
FIELDS = ("trace_lower_s", "compile_s", "run_s", "vmap_s_per_trajectory")


def run_child(folder: str, case: str, patch: bool) -> dict:
    code = _CHILD.format(folder=folder, case=case, patch=patch)
    env = {**os.environ, "JAX_ENABLE_COMPILATION_CACHE": "false"}
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env
    )
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT")]
    if proc.returncode or not lines:
        raise RuntimeError(proc.stderr[-3000:])
    return json.loads(lines[-1][len("RESULT") :])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--a", required=True)
    parser.add_argument("--b", default="HEAD")
    parser.add_argument("--processes", type=int, default=3)
    parser.add_argument("--cases", default=",".join(CASES))
    parser.add_argument(
        "--diffrax-patch",
        action="store_true",
        help="opt in to `cjax.settings.use_diffrax_patch()` where a revision has it "
        "(revisions before it always patch diffrax)",
    )
    parser.add_argument("--out", type=Path, default=HERE / "results" / "events.json")
    opts = parser.parse_args()
    cases = opts.cases.split(",")
    runs: dict = {rev: {case: [] for case in cases} for rev in ("a", "b")}
    with tempfile.TemporaryDirectory() as folder:
        for rev in ("a", "b"):
            os.makedirs(os.path.join(folder, rev))
            export(getattr(opts, rev), "constrained_jax", os.path.join(folder, rev))
        for _ in range(opts.processes):
            for case in cases:
                for rev in ("a", "b"):
                    row = run_child(os.path.join(folder, rev), case, opts.diffrax_patch)
                    runs[rev][case].append(row)
                    print(rev, case, json.dumps(row), flush=True)
    medians = {
        rev: {
            case: {k: statistics.median(r[k] for r in rows) for k in FIELDS}
            for case, rows in by_case.items()
        }
        for rev, by_case in runs.items()
    }
    print(
        "\n| case | first call A | first call B | B / A | run A | run B | B / A "
        "| vmap 64, per trajectory A | B | B / A |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for case in cases:
        a, b = medians["a"][case], medians["b"][case]
        first_a = a["trace_lower_s"] + a["compile_s"]
        first_b = b["trace_lower_s"] + b["compile_s"]
        print(
            f"| {case} | {first_a:.2f} s | {first_b:.2f} s | {first_b / first_a:.2f} "
            f"| {1e3 * a['run_s']:.2f} ms | {1e3 * b['run_s']:.2f} ms "
            f"| {b['run_s'] / a['run_s']:.2f} "
            f"| {1e3 * a['vmap_s_per_trajectory']:.3f} ms "
            f"| {1e3 * b['vmap_s_per_trajectory']:.3f} ms "
            f"| {b['vmap_s_per_trajectory'] / a['vmap_s_per_trajectory']:.2f} |"
        )
    for rev in ("a", "b"):
        for groups in ("1", "2"):
            plain, events = f"plain{groups}", f"events{groups}"
            if plain in cases and events in cases:
                m = medians[rev]
                ratio = (m[events]["trace_lower_s"] + m[events]["compile_s"]) / (
                    m[plain]["trace_lower_s"] + m[plain]["compile_s"]
                )
                print(f"{rev}: first call, events {groups} / plain: {ratio:.2f}")
    opts.out.parent.mkdir(parents=True, exist_ok=True)
    opts.out.write_text(
        json.dumps(
            {
                "a": opts.a,
                "b": opts.b,
                "diffrax_patch": opts.diffrax_patch,
                "runs": runs,
                "medians": medians,
            },
            indent=1,
        )
    )
    print(f"wrote {opts.out}")


if __name__ == "__main__":
    main()
