import gc
import importlib.metadata
import os


# The suite runs the configuration `import constrained_jax` gives: XLA's defaults.
# XLA's default code generator is said out loud (where the flag is known: XLA aborts
# the process on a flag it does not know), so that the command line's `main` called
# in the worker (`test_cli.py`), which turns on the older code generator unless the
# user's `XLA_FLAGS` choose, leaves this worker on the default.
# `CONSTRAINED_JAX_TEST_FAST_COMPILATION=1` runs the suite with the older code
# generator instead (`--xla_cpu_use_fusion_emitters=false`: faster compilation, the
# same results to round-off), for quick local iterations only.
USER_XLA_FLAGS = os.environ.get("XLA_FLAGS", "")
_FLAGS_KNOWN = importlib.metadata.version("jaxlib") in ("0.10.2",)
_FAST = os.environ.get("CONSTRAINED_JAX_TEST_FAST_COMPILATION", "0") == "1"
if _FLAGS_KNOWN and "xla_cpu_use_fusion_emitters" not in USER_XLA_FLAGS:
    os.environ["XLA_FLAGS"] = (
        USER_XLA_FLAGS
        + " --xla_cpu_use_fusion_emitters="
        + ("false" if _FAST else "true")
    ).strip()

import jax  # noqa: E402
import pytest  # noqa: E402


# The tests never write JAX's persistent compilation cache: the command line
# (`test_cli.py`) and the notebooks' kernels call `cjax.enable_compilation_cache()`,
# which would turn it on for the rest of the worker and fill the user's
# `~/.cache/constrained_jax`. `test_compilation_cache.py` turns it on where it is the
# subject, in subprocesses and under `monkeypatch`.
os.environ["CONSTRAINED_JAX_COMPILATION_CACHE"] = "0"


# Tests run in float64 with strict dtype promotion (no silent float32 <-> float64
# mixing); float32 checks opt back in explicitly.
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """JAX's caches are emptied after each test file, so that a worker's compiled
    programs do not pile up over the whole suite.

    Each XLA:CPU executable keeps memory mappings of its code while a cache holds it
    (hundreds for one of the library's solves), and at Linux's `vm.max_map_count`
    (65,530 by default) the next compilation aborts the process: an xdist worker died
    inside `backend_compile_and_load` ("Fatal Python error: Aborted") about once in
    six full runs, another held 31,000 mappings after 35 minutes. See
    docs/upstream/xla.md and "Long-lived processes" in docs/sharp-edges.md."""
    yield
    jax.clear_caches()
    gc.collect()


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
    worker's setting is restored afterwards (the command line's `main` turns the
    patch on)."""
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
    "test_batched_bounds.py",
    "test_contact_series.py",
    "test_inactive_rows.py",
    "test_kkt_derivative.py",
    "test_release.py",
    "test_gradients.py",
    "test_vmap_gradients.py",
)


def pytest_collection_modifyitems(config, items):
    def rank(item):
        name = item.path.name
        return _LONG_FIRST.index(name) if name in _LONG_FIRST else len(_LONG_FIRST)

    items.sort(key=rank)  # (stable: the order within each file is kept)
