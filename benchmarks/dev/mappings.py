"""Memory mappings held by compiled programs (Linux): how many a distinct program of
the library keeps while JAX's caches hold it, and that `jax.clear_caches()` returns
them. Past `vm.max_map_count` XLA:CPU's next compilation fails and the process dies
(docs/upstream/xla.md). Set `XLA_FLAGS` to compare code generators.

    python benchmarks/dev/mappings.py [--programs 6]
"""

import argparse
import gc
import os

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

import constrained_jax as cjax  # noqa: E402


def mappings() -> int:
    with open(f"/proc/{os.getpid()}/maps", "rb") as f:
        return sum(1 for _ in f)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--programs", type=int, default=6)
    opts = parser.parse_args()
    x0 = jnp.full((3,), 0.3)
    total = lambda x, a: jnp.sum(x) - 1.0
    cjax.extremize(lambda x, a: jnp.sum(x**2), x0, None, constraints=total)
    before = mappings()
    for i in range(opts.programs):
        c = float(i + 2)  # a new objective each time: a new program
        cjax.extremize(lambda x, a, c=c: jnp.sum(c * x**2), x0, None, constraints=total)
    gc.collect()
    held = (mappings() - before) / opts.programs
    jax.clear_caches()
    gc.collect()
    print(f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}")
    print(f"mappings held per distinct extremize (closures dropped): {held:.0f}")
    print(f"after jax.clear_caches(): {mappings() - before:+d}")
    with open("/proc/sys/vm/max_map_count") as f:
        print(f"vm.max_map_count: {int(f.read())}")


if __name__ == "__main__":
    main()
