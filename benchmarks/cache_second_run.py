"""What JAX's persistent compilation cache saves a second process.

Each line of the table is a fresh Python process that turns the cache on in one new
folder (`cjax.enable_compilation_cache(folder)`) and times the first call (tracing,
lowering, compilation or a cache read, and the run) of two `simulate` programs of
the two cylinders: attached (Tsit5, 9 saves) and the release run (`contact_system`).
The first process fills the folder, the next ones read it. The processes opt into the
library's diffrax patch (`cjax.settings.use_diffrax_patch()`, as the command line
does), without which the `simulate` programs hold diffrax's host callbacks and are not
stored; `--diffrax-defaults` measures without it. With `--tour`, also the wall time of
`constrained-jax tour --no-plots` (with `--diffrax-defaults` if given), run twice on
another new folder.

    python benchmarks/cache_second_run.py [--processes 3] [--tour] [--diffrax-defaults]

Writes `benchmarks/results/cache_second_run.json`.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path


RESULTS = Path(__file__).parent / "results" / "cache_second_run.json"

_PROGRAM = """
import json, sys, time
import jax, jax.numpy as jnp
jax.config.update("jax_enable_x64", True)
import constrained_jax as cjax
from constrained_jax.scenes import two_cylinders as cyl

if sys.argv[2] == "patch":
    assert cjax.settings.use_diffrax_patch()
cjax.enable_compilation_cache(sys.argv[1])
args = cyl.default_args()
q0, qd0 = cyl.state(jnp.asarray(0.2), jnp.asarray(0.0), args)
out = {}
for name, system, t1 in (
    ("attached", cyl.system(), 0.8),
    ("release", cyl.contact_system(), 1.5),
):
    start = time.perf_counter()
    traj = cjax.simulate(
        system, (0.0, t1), q0, qd0, args, saveat=cjax.SaveAt(ts=jnp.linspace(0, t1, 9))
    )
    traj.q.block_until_ready()
    out[name] = time.perf_counter() - start
print(json.dumps(out))
"""


def _first_calls(folder: str, processes: int, patch: bool) -> list[dict]:
    rows = []
    for _ in range(processes):
        run = subprocess.run(
            [sys.executable, "-c", _PROGRAM, folder, "patch" if patch else "plain"],
            capture_output=True,
            text=True,
            check=True,
        )
        rows.append(json.loads(run.stdout.strip().splitlines()[-1]))
    return rows


def _tour_twice(folder: str, patch: bool) -> list[float]:
    env = {**os.environ, "CONSTRAINED_JAX_COMPILATION_CACHE": folder}
    command = [sys.executable, "-m", "constrained_jax", "tour", "--no-plots"]
    if not patch:
        command.append("--diffrax-defaults")
    walls = []
    for _ in range(2):
        start = time.perf_counter()
        subprocess.run(
            command,
            env=env,
            capture_output=True,
            check=True,
        )
        walls.append(time.perf_counter() - start)
    return walls


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--processes", type=int, default=3)
    parser.add_argument("--tour", action="store_true")
    parser.add_argument("--diffrax-defaults", action="store_true")
    opts = parser.parse_args()
    patch = not opts.diffrax_defaults
    result = {"diffrax_patch": patch}
    with tempfile.TemporaryDirectory() as folder:
        result["first_calls_s"] = _first_calls(folder, opts.processes, patch)
    for i, row in enumerate(result["first_calls_s"]):
        print(
            f"process {i + 1}: attached {row['attached']:.2f} s, "
            f"release {row['release']:.2f} s"
        )
    if opts.tour:
        with tempfile.TemporaryDirectory() as folder:
            result["tour_s"] = _tour_twice(folder, patch)
        print("tour: first {:.1f} s, second {:.1f} s".format(*result["tour_s"]))
    RESULTS.parent.mkdir(exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=1))
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
