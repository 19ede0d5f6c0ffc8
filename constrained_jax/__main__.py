"""Command line: `python -m constrained_jax tour` (also the `constrained-jax` script).

- `tour`: solve every built-in scene on its default parameters and print one table
  (scene, quantity, computed, closed form, relative error, time). Exit status 1 if any
  check fails.
- `scene NAME [--param value ...]`: run one scene; `scene NAME --help` lists its
  parameters.
"""

import argparse
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class _Row:
    scene: str
    quantity: str
    computed: float
    reference: float
    seconds: float

    @property
    def rel_error(self) -> float:
        scale = max(abs(self.reference), 1e-300)
        return abs(self.computed - self.reference) / scale


def _cylinder_volume(b: float = 1.0, l: float = 1.0) -> list[_Row]:
    from .scenes import cylinder_volume as scene

    start = time.perf_counter()
    sol = scene.solve(b, l)
    sol.value.block_until_ready()
    seconds = time.perf_counter() - start
    ref = scene.closed_form(b, l)
    name = f"cylinder_volume(b={b:g}, l={l:g})"
    computed = {
        "radius a": sol.x[0],
        "height h": sol.x[1],
        "multiplier lambda": sol.multipliers[0],
        "volume V*": sol.value,
    }
    keys = {"radius a": "a", "height h": "h", "multiplier lambda": "multiplier"}
    keys["volume V*"] = "volume"
    return [
        _Row(name, q, float(v), float(ref[keys[q]]), seconds)
        for q, v in computed.items()
    ]


# name -> (function, {parameter: (default, help)}, tolerance, one-line description)
_SCENES: dict[str, tuple[Callable[..., list[_Row]], dict, float, str]] = {
    "cylinder_volume": (
        _cylinder_volume,
        {
            "b": (1.0, "shape parameter b of the constraint 2 pi a + h^2/b = l"),
            "l": (1.0, "budget l of the constraint 2 pi a + h^2/b = l"),
        },
        1e-10,
        "extremize the volume pi a^2 h subject to 2 pi a + h^2/b - l = 0",
    ),
}

_TOUR = [
    ("cylinder_volume", {}),
    ("cylinder_volume", {"b": 1e-3, "l": 1e3}),
]


def _print_table(rows: list[_Row], tolerance: dict[str, float]) -> bool:
    header = (
        f"{'scene':<36} {'quantity':<18} {'computed':>16} {'closed form':>16} "
        f"{'rel. error':>10} {'time [s]':>9}  check"
    )
    print(header)
    print("-" * len(header))
    ok = True
    for row in rows:
        passed = row.rel_error <= tolerance[row.scene]
        ok &= passed
        print(
            f"{row.scene:<36} {row.quantity:<18} {row.computed:>16.10g} "
            f"{row.reference:>16.10g} {row.rel_error:>10.2e} {row.seconds:>9.3f}  "
            f"{'ok' if passed else 'FAIL'}"
        )
    return ok


def _setup_jax() -> None:
    import jax

    jax.config.update("jax_enable_x64", True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="constrained-jax",
        description="Constrained extremization and mechanics in JAX: built-in scenes.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("tour", help="solve every built-in scene and check closed forms")
    scene_parser = sub.add_parser("scene", help="run one scene")
    scene_sub = scene_parser.add_subparsers(dest="name", required=True)
    for name, (_, params, _, doc) in _SCENES.items():
        p = scene_sub.add_parser(name, help=doc, description=doc)
        for param, (default, help_) in params.items():
            p.add_argument(f"--{param}", type=float, default=default, help=help_)
    sub.add_parser("list", help="list the built-in scenes")
    ns = parser.parse_args(argv)

    if ns.command == "list":
        for name, (_, _, _, doc) in _SCENES.items():
            print(f"{name:<20} {doc}")
        return 0

    _setup_jax()
    if ns.command == "tour":
        runs = _TOUR
    else:
        params = {k: getattr(ns, k) for k in _SCENES[ns.name][1]}
        runs = [(ns.name, params)]
    rows, tolerance = [], {}
    for name, params in runs:
        fn, _, tol, _ = _SCENES[name]
        new = fn(**params)
        rows += new
        tolerance.update({row.scene: tol for row in new})
    ok = _print_table(rows, tolerance)
    print("(time: wall clock per scene; a first solve includes compilation)")
    print("\nall checks passed" if ok else "\nSOME CHECKS FAILED")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
