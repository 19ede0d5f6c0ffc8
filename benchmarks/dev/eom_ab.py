"""The batched equations of motion of two git revisions, in fresh processes.

`jit(vmap(solve_accelerations))` over a batch of states of a scene (10,000 unless
`--states`), against the
hand-written closed form (`dynamics.py`), each revision's `constrained_jax/` exported
with `git archive` into a folder of its own and imported by a child process (the
benchmark code, states and hand-written functions are this checkout's). Each child
times the two programs in blocks of 10 calls, alternating (`time_jax_interleaved`),
pinned to one CPU unless `--threads`; the revisions alternate over `--processes`
rounds. Prints and stores the medians over the processes of the ratio ours /
hand-written and of each time.

    python benchmarks/dev/eom_ab.py --a REV --b HEAD [--scene pendulum]
        [--states 10000] [--processes 5] [--threads] [--out benchmarks/dev/results]

A revision may also be a folder holding a `constrained_jax/` (a patched copy).
"""

import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile


HERE = os.path.dirname(os.path.abspath(__file__))
BENCHMARKS = os.path.dirname(HERE)  # `_common.py`, `dynamics.py`


def child(folder: str, scene: str, pin: bool, repeats: int, states: int) -> None:
    sys.path.insert(0, folder)
    if pin:
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import constrained_jax

    if not os.path.abspath(constrained_jax.__file__).startswith(folder):
        raise RuntimeError(f"imported {constrained_jax.__file__}, not {folder}")
    sys.path.insert(1, BENCHMARKS)
    import dynamics
    from _common import time_jax_interleaved

    module = dynamics.pend if scene == "pendulum" else dynamics.cyl
    hand = (
        dynamics.pendulum_accelerations_by_hand
        if scene == "pendulum"
        else dynamics.cylinders_accelerations_by_hand
    )
    system, args = module.system(), module.default_args()
    q, qd = dynamics.random_states(scene, states)
    t = jnp.asarray(0.0)
    fns = {
        "ours": jax.jit(
            lambda q, qd, args: jax.vmap(
                lambda a, b: system.solve_accelerations(a, b, t, args)[:2]
            )(q, qd)
        ),
        "hand": jax.jit(
            lambda q, qd, args: jax.vmap(lambda a, b: hand(a, b, args))(q, qd)
        ),
    }
    out, infos = time_jax_interleaved(fns, q, qd, args, repeats=repeats, block=10)
    err = float(jnp.max(jnp.abs(out["ours"][0] - out["hand"][0])))
    print(
        json.dumps(
            {
                "ratio": infos["ours"]["median_s"] / infos["hand"]["median_s"],
                "ours_s": infos["ours"]["median_s"],
                "hand_s": infos["hand"]["median_s"],
                "max_abs_qdd_difference": err,
            }
        )
    )


def _is_checkout(rev: str) -> bool:
    return os.path.isdir(os.path.join(rev, "constrained_jax"))


def export(rev: str) -> str:
    """A folder holding `rev`'s `constrained_jax/` (`rev` itself if it is one; else
    a new temporary folder, removed after the run)."""
    if _is_checkout(rev):
        return os.path.abspath(rev)
    folder = tempfile.mkdtemp(prefix=f"eom_ab_{re.sub(r'[^0-9A-Za-z]', '_', rev)}_")
    top = subprocess.check_output(
        ["git", "-C", HERE, "rev-parse", "--show-toplevel"], text=True
    ).strip()
    archive = subprocess.check_output(
        ["git", "-C", top, "archive", rev, "constrained_jax"]
    )
    subprocess.run(["tar", "-x", "-C", folder], input=archive, check=True)
    return folder


def _compare(opts, folders) -> tuple[dict, str]:
    """Alternate the revisions' child processes; print and return the medians."""
    runs: dict = {opts.a: [], opts.b: []}
    for i in range(opts.processes):
        order = (opts.a, opts.b) if i % 2 == 0 else (opts.b, opts.a)
        for rev in order:
            done = subprocess.run(
                [sys.executable, __file__, "--a", opts.a, "--b", opts.b, "--child",
                 folders[rev], opts.scene, "0" if opts.threads else "1",
                 str(opts.repeats), str(opts.states)],
                capture_output=True, text=True,
            )  # fmt: skip
            if done.returncode:
                raise RuntimeError(done.stderr[-3000:])
            runs[rev].append(json.loads(done.stdout.strip().splitlines()[-1]))
    setting = "XLA's threads" if opts.threads else "one thread"
    summary = {}
    for rev, rs in runs.items():
        summary[rev] = {
            "ratio": statistics.median(r["ratio"] for r in rs),
            "ratios": [r["ratio"] for r in rs],
            "ours_s": statistics.median(r["ours_s"] for r in rs),
            "hand_s": statistics.median(r["hand_s"] for r in rs),
            "max_abs_qdd_difference": max(r["max_abs_qdd_difference"] for r in rs),
        }
        s = summary[rev]
        print(
            f"{rev}: {opts.scene}, {opts.states:,} states, {setting}, "
            f"ours / hand-written "
            f"{s['ratio']:.3f}x (processes: "
            f"{', '.join(f'{x:.3f}' for x in s['ratios'])}), ours "
            f"{s['ours_s'] * 1e6:.1f} us, hand-written {s['hand_s'] * 1e6:.1f} us, "
            f"max |qdd difference| {s['max_abs_qdd_difference']:.1e}"
        )
    return summary, setting


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--a", required=True)
    parser.add_argument("--b", required=True)
    parser.add_argument(
        "--scene", default="pendulum", choices=["pendulum", "cylinders"]
    )
    parser.add_argument("--processes", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=15, help="blocks per program")
    parser.add_argument("--threads", action="store_true", help="XLA's threads")
    parser.add_argument("--states", type=int, default=10_000, help="batch size")
    parser.add_argument("--out", default=os.path.join(HERE, "results"))
    parser.add_argument("--child", nargs=5, help=argparse.SUPPRESS)
    opts = parser.parse_args()
    if opts.child:
        folder, scene, pin, repeats, states = opts.child
        child(folder, scene, pin == "1", int(repeats), int(states))
        return
    folders = {rev: export(rev) for rev in (opts.a, opts.b)}
    exported = [f for rev, f in folders.items() if not _is_checkout(rev)]
    try:
        summary, setting = _compare(opts, folders)
    finally:
        for folder in exported:  # made by `export`, never a folder of the user's
            shutil.rmtree(folder, ignore_errors=True)
    sys.path.insert(0, BENCHMARKS)
    from _common import machine_info

    os.makedirs(opts.out, exist_ok=True)
    path = os.path.join(opts.out, "eom_ab.json")
    with open(path, "w") as f:
        json.dump(
            {"machine": machine_info(), "scene": opts.scene, "states": opts.states,
             "setting": setting,
             "a": opts.a, "b": opts.b, "processes": opts.processes,
             "results": summary},
            f, indent=1,
        )  # fmt: skip
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
