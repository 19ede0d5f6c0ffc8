"""What the library's XLA:CPU settings trade: compile time against run time, each
measured in fresh processes, the settings alternating.

Settings (`--settings`, comma-separated; the first is the reference of the ratios):
`default` (XLA's defaults), `fast` (`cjax.settings.use_fast_compilation()`: the
older code generator), `loops` (`cjax.settings.use_loop_kernels()`: small `while`
loops compiled into one function), `fast+loops` (both, as the command line sets
them).

XLA reads its flags once per process, so each measurement is a child process (this
script with `--child SETTING`); the parent runs `--rounds` rounds, each one child per
setting, in rotating order, and reports the medians over the rounds and their ratio
to the first setting. Each child measures (float64, after compilation; medians of
`--repeats` calls):

- compile: trace + lower + compile of the first `jit(simulate)` of the two cylinders
  and of the tour's pendulum program (`compile_time.py` (a), (c); one each, cache off,
  caches cleared), and of the tour's release program ((b)) unless `--no-release`;
- run: the equations of motion of the two cylinders and of the pendulum, `jit(vmap)`
  over 10,000 states (`dynamics.accelerations_benchmark`), ours and hand-written; one
  two-cylinder trajectory and a batch of 1,000 (`dynamics.jax_trajectories`), ours
  and diffrax on the hand-written field; `d theta1(t1)/dI` by the default adjoint and
  the forward solve (`gradients.cylinders_attached`); the N-link chain's equations of
  motion at N = 256 over 1,000 states (`chain.eom`); one trajectory of the 4- and
  16-link chains (`chain.trajectory`); the pendulum over 20 s and the two cylinders
  with the release event over 3 s (`dev/ab.py`'s `sim pendulum 20s`, `sim release 1`).

    python benchmarks/code_generator.py [--rounds 3] [--repeats 15] [--no-release]
        [--settings default,fast]

Writes `benchmarks/results/code_generator.json` and `code_generator.png` (with
`--settings` other than `default,fast`: `code_generator_<settings>.json`, `.png`).
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path


RESULTS = Path(__file__).parent / "results"
SETTINGS = ("default", "fast", "loops", "fast+loops")


def child(setting: str, repeats: int, release: bool) -> dict:
    import constrained_jax as cjax

    if "fast" in setting:
        assert cjax.settings.use_fast_compilation()
    if "loops" in setting:
        assert cjax.settings.use_loop_kernels()
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
    for links in (4, 16):
        run = chain.trajectory(links, None, repeats)
        out[f"chain N = {links}, one trajectory ms"] = run["median_s"] * 1e3
    sys.path.insert(0, str(Path(__file__).resolve().parent / "dev"))
    import ab
    from _common import time_jax

    cases = ab.cases(cjax)
    for name in ("sim pendulum 20s", "sim release 1"):
        fn, inputs = cases[name]
        out[f"{name} ms"] = time_jax(fn, *inputs, repeats=repeats)[1]["median_s"] * 1e3
    return out


def plot(summary: dict, settings: tuple, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(summary)
    others = settings[1:]
    fig, ax = plt.subplots(figsize=(8, 0.35 * len(names) * len(others) + 1.2))
    height = 0.8 / len(others)
    for j, setting in enumerate(others):
        ratios = [summary[n][f"ratio_{setting}"] for n in names]
        ys = [i + j * height for i in range(len(names))]
        ax.barh(ys, ratios, height=height, color=f"C{j}", label=setting)
    ax.axvline(1.0, color="k", lw=0.8)
    ax.set_yticks([i + 0.4 - height / 2 for i in range(len(names))], names, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel(f"setting / {settings[0]} (medians; < 1: faster)")
    ax.set_title("XLA:CPU settings: compile and run time")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"wrote {path}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--no-release", action="store_true")
    parser.add_argument("--settings", default="default,fast")
    parser.add_argument("--child", choices=SETTINGS)
    parser.add_argument("--out", type=Path, default=RESULTS)
    ns = parser.parse_args()
    if ns.child:
        print(json.dumps(child(ns.child, ns.repeats, not ns.no_release)))
        return
    settings = tuple(ns.settings.split(","))
    if not settings or any(s not in SETTINGS for s in settings):
        parser.error(f"--settings: a comma-separated subset of {', '.join(SETTINGS)}")

    runs = {s: [] for s in settings}
    for i in range(ns.rounds):
        shift = i % len(settings)
        for setting in settings[shift:] + settings[:shift]:
            cmd = [sys.executable, __file__, "--child", setting]
            cmd += ["--repeats", str(ns.repeats)]
            cmd += ["--no-release"] if ns.no_release else []
            env = dict(os.environ)
            env.pop("XLA_FLAGS", None)  # each child: XLA's defaults, or the flags
            done = subprocess.run(
                cmd, capture_output=True, text=True, env=env, check=False
            )
            if done.returncode != 0:
                raise RuntimeError(f"{setting} child failed:\n{done.stderr[-3000:]}")
            runs[setting].append(json.loads(done.stdout.strip().splitlines()[-1]))
            print(f"round {i + 1}, {setting}: done", flush=True)
    reference = settings[0]
    summary = {}
    for name in runs[reference][0]:
        row = {s: statistics.median(r[name] for r in runs[s]) for s in settings}
        for s in settings[1:]:
            row[f"ratio_{s}"] = row[s] / row[reference]
        summary[name] = row
    print("\n| figure | " + " | ".join(settings) + " | "
          + " | ".join(f"{s} / {reference}" for s in settings[1:]) + " |")  # fmt: skip
    print("|---|" + "---:|" * (2 * len(settings) - 1))
    for name, r in summary.items():
        values = " | ".join(f"{r[s]:.4g}" for s in settings)
        ratios = " | ".join(f"{r[f'ratio_{s}']:.2f}" for s in settings[1:])
        print(f"| {name} | {values} | {ratios} |")
    sys.path.insert(0, str(Path(__file__).parent))
    from _common import write_cases

    stem = "code_generator"
    if settings != ("default", "fast"):
        stem += "_" + "_".join(s.replace("+", "-") for s in settings)
    write_cases(ns.out / f"{stem}.json", {"summary": summary, "runs": runs})
    plot(summary, settings, ns.out / f"{stem}.png")


if __name__ == "__main__":
    main()
