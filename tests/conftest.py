import importlib.metadata
import os


# XLA's CPU compilation is most of this suite's time (61 % of the worker seconds in
# `benchmarks/suite_profile.py`), and XLA:CPU's newer fusion emitters compile our
# programs about 2x slower than its older code generator (`benchmarks/compile_time.py`:
# the tour's pendulum 1.24 -> 0.71 s, the release program 4.23 -> 3.04 s). The
# tests therefore compile with the older one: a clean 2-core run took 11 min 31 s of
# pytest instead of 16 min 51 s - 18 min 08 s. Results agree to round-off; the tests
# compare against closed forms, finite differences and invariants, never bit
# patterns. The notebooks (`test_notebooks.py`) and the fresh processes that set
# their own `XLA_FLAGS` run the default code generator, so the code users run stays
# tested end to end. `CONSTRAINED_JAX_TEST_XLA_DEFAULTS=1` runs every test with
# XLA's defaults. (Set before JAX starts its CPU backend, which reads `XLA_FLAGS`
# once.) Each compilation is also one LLVM module, not split for parallel code
# generation: with two workers on two cores the threads only compete (10 min 48 s ->
# 9 min 48 s of pytest in one run each; alone, one split is slower).
# XLA aborts the process on a flag it does not know (jaxlib 0.11.2 no longer has the
# first one), so they are set only for the jaxlib they were measured with; any other
# runs XLA's defaults (slower, the same results).
USER_XLA_FLAGS = os.environ.get("XLA_FLAGS", "")
_FLAGS_KNOWN = importlib.metadata.version("jaxlib") in ("0.10.2",)
if _FLAGS_KNOWN and os.environ.get("CONSTRAINED_JAX_TEST_XLA_DEFAULTS", "0") != "1":
    os.environ["XLA_FLAGS"] = (
        USER_XLA_FLAGS
        + " --xla_cpu_use_fusion_emitters=false"
        + " --xla_cpu_parallel_codegen_split_count=1"
    ).strip()
elif _FLAGS_KNOWN:
    # XLA's default said out loud, so that the tour run in-process
    # (`test_cli.py`), whose `main` turns on the older code generator unless the
    # user's `XLA_FLAGS` choose, leaves this worker on the default.
    os.environ["XLA_FLAGS"] = (
        USER_XLA_FLAGS + " --xla_cpu_use_fusion_emitters=true"
    ).strip()

import jax  # noqa: E402
import pytest  # noqa: E402


# The tests never write JAX's persistent compilation cache: the tour run in-process
# (`test_cli.py`) and the notebooks' kernels call `cjax.enable_compilation_cache()`,
# which would turn it on for the rest of the worker and fill the user's
# `~/.cache/constrained_jax` (an xdist worker crashed inside XLA while compiling with
# the cache on). `test_compilation_cache.py` turns it on where it is the subject, in
# subprocesses and under `monkeypatch`.
os.environ["CONSTRAINED_JAX_COMPILATION_CACHE"] = "0"


# Tests run in float64 with strict dtype promotion (no silent float32 <-> float64
# mixing); float32 checks opt back in explicitly.
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")


@pytest.fixture
def getkey():
    """Fresh PRNG keys on demand, deterministic per test."""
    key = jax.random.key(5678)

    def _getkey():
        nonlocal key
        key, subkey = jax.random.split(key)
        return subkey

    return _getkey


@pytest.fixture
def diffrax_patch():
    """`set(on)`: the library's opt-in diffrax patch on or off
    (`cjax.settings.use_diffrax_patch`), with JAX's caches cleared so that the
    programs traced next see it (a cached trace keeps what it was traced with). The
    worker's setting is restored afterwards (the in-process tour of `test_cli.py`
    turns the patch on)."""
    from constrained_jax import _diffrax_integrate

    before = _diffrax_integrate.diffrax_patch_on()

    def set_patch(on: bool) -> bool:
        now = _diffrax_integrate.use_diffrax_patch(on)
        jax.clear_caches()
        return now

    yield set_patch
    _diffrax_integrate.use_diffrax_patch(before)


# The files whose tests are long single items (subprocesses, kernels, the tour, big
# reverse-mode programs) run first, whole files together (module fixtures stay set
# up once), so that the two xdist workers do not end on one long item while the other
# idles (longest first: the classic schedule for balancing).
_LONG_FIRST = (
    "test_notebooks.py",
    "test_sharp_edges_gauge_float32.py",
    "test_cli.py",
    "test_impacts.py",
    "test_kkt_derivative.py",
    "test_release.py",
    "test_gradients.py",
)


def pytest_collection_modifyitems(config, items):
    def rank(item):
        name = item.path.name
        return _LONG_FIRST.index(name) if name in _LONG_FIRST else len(_LONG_FIRST)

    items.sort(key=rank)  # (stable: the order within each file is kept)
