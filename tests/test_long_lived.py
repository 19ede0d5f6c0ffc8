"""Long-lived processes: compiled programs hold memory mappings, and XLA:CPU aborts a
process at a compilation past Linux's `vm.max_map_count` (docs/upstream/xla.md).

- the mechanism the suite's `_release_compiled_programs` fixture relies on: held
  programs keep mappings, and `jax.clear_caches()` returns those JAX's caches held;
- a solve traced past three quarters of the limit warns, naming the limit and
  `jax.clear_caches()`; below it, no warning.
"""

import gc
import os
import sys
import warnings

import jax
import jax.numpy as jnp
import pytest

import constrained_jax as cjax
from constrained_jax import _misc


linux_only = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="reads /proc/self/maps"
)


def _mappings() -> int:
    with open(f"/proc/{os.getpid()}/maps", "rb") as f:
        return sum(1 for _ in f)


@linux_only
def test_held_programs_keep_mappings_until_the_caches_are_cleared():
    x = jnp.ones(4)
    gc.collect()
    before = _mappings()
    held = []
    for i in range(40):
        f = jax.jit(lambda x, i=i: jnp.sin(x) * i + jnp.cumsum(x) ** 2)
        f(x).block_until_ready()
        held.append(f)
    grown = _mappings() - before
    # Each loaded program maps its code, read-only data and data: three or more.
    assert grown >= 3 * 40, grown
    del held, f
    jax.clear_caches()
    gc.collect()
    assert _mappings() - before < grown / 4


def _new_solve(c):
    return cjax.extremize(
        lambda x, a: c * jnp.sum(x**2),
        jnp.full((2,), 0.3),
        None,
        constraints=lambda x, a: jnp.sum(x) - 1.0,
    )


@linux_only
def test_a_solve_traced_near_the_limit_warns(monkeypatch):
    monkeypatch.setattr(_misc, "_mapping_count_and_limit", lambda: (60_000, 65_530))
    with pytest.warns(RuntimeWarning, match=r"vm\.max_map_count.*clear_caches"):
        sol = _new_solve(2.0)
    assert sol.result == cjax.RESULTS.successful
    monkeypatch.setattr(_misc, "_mapping_count_and_limit", lambda: (1_000, 65_530))
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        _new_solve(3.0)


def test_the_count_is_read_where_linux_gives_it():
    found = _misc._mapping_count_and_limit()
    if sys.platform.startswith("linux"):
        count, limit = found
        assert 0 < count < limit
    else:
        assert found is None
