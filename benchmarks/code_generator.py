"""What XLA:CPU's older code generator (`cjax.use_fast_compilation()`) trades: compile
time against run time, each measured in fresh processes, the two settings alternating.

XLA reads its flags once per process, so each measurement is a child process (this
script with `--child default` or `--child fast`); the parent runs `--rounds` rounds,
each one child per setting, in alternating order, and reports the medians over the
rounds and their ratio fast / default. Each child measures (float64, after
compilation; medians of `--repeats` calls):

- compile: trace + lower + compile of the first `jit(simulate)` of the two cylinders
  and of the tour's pendulum program (`compile_time.py` (a), (c); one each, cache off,
  caches cleared), and of the tour's release program ((b)) unless `--no-release`;
- run: the equations of motion of the two cylinders and of the pendulum, `jit(vmap)`
  over 10,000 states (`dynamics.accelerations_benchmark`), ours and hand-written; one
  two-cylinder trajectory and a batch of 1,000 (`dynamics.jax_trajectories`), ours
  and diffrax on the hand-written field; `d theta1(t1)/dI` by the default adjoint and
  the forward solve (`gradients.cylinders_attached`); the N-link chain's equations of
  motion at N = 256 over 1,000 states (`chain.eom`).

    python benchmarks/code_generator.py [--rounds 3] [--repeats 15] [--no-release]

Writes `benchmarks/results/code_generator.json` and `code_generator.png`.
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path


RESULTS = Path(__file__).parent / "results"
SETTINGS = ("default", "fast")


def child(setting: str, repeats: int, release: bool) -> dict:
    import constrained_jax as cjax

    if setting == "fast":
        assert cjax.use_fast_compilation()
    import jax

    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_enable_compilation_cache", False)
    import chain
    import compile_time
    import dynamics
    import gradients
    import numpy as np

    out = {}
    for key in ("a", "c") + (("b",) if release else ()):
        r = compile_time.measure(compile_time.CASES[key][1], 1)
        out[f"compile ({key}) s"] = r["trace_lower_s"] + r["compile_s"]
        out[f"compile ({key}), XLA only s"] = r["compile_s"]
    for scene in ("cylinders", "pendulum"):
        methods = dynamics.accelerations_benchmark(scene, 10_000, repeats)["methods"]
        out[f"EOM {scene} 1e4, ours ms"] = (
            methods["autodiff solve_accelerations"]["median_s"] * 1e3
        )
        out[f"EOM {scene} 1e4, hand-written ms"] = (
            methods["hand-written"]["median_s"] * 1e3
        )
    theta0 = dynamics.CYLINDERS_THETA0
    thetas = dynamics.batch_theta0("cylinders", 1000)
    for label, by_hand in (("ours", False), ("hand-written diffrax", True)):
        one = dynamics.jax_trajectories(
            "cylinders", np.float64(theta0), repeats, by_hand=by_hand
        )
        out[f"one trajectory, {label} ms"] = one["median_s"] * 1e3
        batch = dynamics.jax_trajectories("cylinders", thetas, 3, by_hand=by_hand)
        out[f"1,000 trajectories, {label} ms"] = batch["median_s"] * 1e3
    grad = gradients.cylinders_attached(repeats)["methods"]
    out["d theta1/dI: forward solve ms"] = grad["forward"]["median_s"] * 1e3
    out["d theta1/dI: grad (adjoint=None) ms"] = (
        grad["grad (adjoint=None)"]["median_s"] * 1e3
    )
    out["chain N = 256, EOM per state us"] = (
        chain.eom(256, 1000, repeats)["default"]["per_state_s"] * 1e6
    )
    return out


def plot(summary: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(summary)
    ratios = [summary[n]["ratio_fast_to_default"] for n in names]
    fig, ax = plt.subplots(figsize=(8, 0.35 * len(names) + 1.2))
    ax.barh(range(len(names)), ratios, color=["C0" if r < 1 else "C3" for r in ratios])
    ax.axvline(1.0, color="k", lw=0.8)
    ax.set_yticks(range(len(names)), names, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("older code generator / XLA's default (medians; < 1: faster)")
    ax.set_title("cjax.use_fast_compilation(): compile and run time")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"wrote {path}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--no-release", action="store_true")
    parser.add_argument("--child", choices=SETTINGS)
    parser.add_argument("--out", type=Path, default=RESULTS)
    ns = parser.parse_args()
    if ns.child:
        print(json.dumps(child(ns.child, ns.repeats, not ns.no_release)))
        return

    runs = {s: [] for s in SETTINGS}
    for i in range(ns.rounds):
        for setting in SETTINGS if i % 2 == 0 else SETTINGS[::-1]:
            cmd = [sys.executable, __file__, "--child", setting]
            cmd += ["--repeats", str(ns.repeats)]
            cmd += ["--no-release"] if ns.no_release else []
            env = dict(os.environ)
            env.pop("XLA_FLAGS", None)  # each child: XLA's defaults, or the flag
            done = subprocess.run(
                cmd, capture_output=True, text=True, env=env, check=False
            )
            if done.returncode != 0:
                raise RuntimeError(f"{setting} child failed:\n{done.stderr[-3000:]}")
            runs[setting].append(json.loads(done.stdout.strip().splitlines()[-1]))
            print(f"round {i + 1}, {setting}: done", flush=True)
    summary = {}
    for name in runs["default"][0]:
        default = statistics.median(r[name] for r in runs["default"])
        fast = statistics.median(r[name] for r in runs["fast"])
        summary[name] = {"default": default, "fast": fast,
                         "ratio_fast_to_default": fast / default}  # fmt: skip
    print("\n| figure | XLA's default | older generator | older / default |")
    print("|---|---:|---:|---:|")
    for name, r in summary.items():
        print(f"| {name} | {r['default']:.4g} | {r['fast']:.4g} | "
              f"{r['ratio_fast_to_default']:.2f} |")  # fmt: skip
    sys.path.insert(0, str(Path(__file__).parent))
    from _common import write_cases

    write_cases(ns.out / "code_generator.json", {"summary": summary, "runs": runs})
    plot(summary, ns.out / "code_generator.png")


if __name__ == "__main__":
    main()
