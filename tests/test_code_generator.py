"""`use_fast_compilation`: XLA:CPU's older code generator, opted into before the
first computation, never against the user's own `XLA_FLAGS`, refused when too late.

Its effect on compile and run time is measured in `benchmarks/code_generator.py` and
`benchmarks/compile_time.py --fast-compilation` (not in timed tests)."""

import importlib.metadata
import os

import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax
from constrained_jax import _code_generator

from .helpers import run_python


_FLAG = "--xla_cpu_use_fusion_emitters=false"
_KNOWN = importlib.metadata.version("jaxlib") in _code_generator._KNOWN_JAXLIB


@pytest.mark.skipif(not _KNOWN, reason="the flag is only set for a known jaxlib")
def test_appended_after_import_and_read_by_xla():
    """In a fresh process, after `import constrained_jax` (which does not start JAX's
    backend), the flag is appended to the user's `XLA_FLAGS`; XLA then reads the whole
    string at its start (the user's flag asks for 2 CPU devices, and an unknown or
    malformed flag would abort the process). A second call changes nothing."""
    code = """
import os, jax, jax.numpy as jnp
import constrained_jax as cjax
assert cjax.settings.use_fast_compilation() is True
flags = os.environ["XLA_FLAGS"]
print(flags)
print(float(jax.jit(lambda x: jnp.sum(jnp.sin(x) ** 2))(jnp.arange(3.0))))
print(len(jax.devices("cpu")))
assert cjax.settings.use_fast_compilation() is True
assert os.environ["XLA_FLAGS"] == flags
"""
    run = run_python(
        code, timeout=300, XLA_FLAGS="--xla_force_host_platform_device_count=2"
    )
    assert run.returncode == 0, run.stderr
    flags, value, devices = run.stdout.split("\n")[:3]
    assert flags == f"--xla_force_host_platform_device_count=2 {_FLAG}"
    assert float(value) == pytest.approx(sum(float(jnp.sin(x) ** 2) for x in range(3)))
    assert int(devices) == 2


@pytest.mark.parametrize(
    "flags, expected",
    [(_FLAG, True), ("--xla_cpu_use_fusion_emitters=true", False)],
)
def test_the_users_own_setting_is_kept(monkeypatch, flags, expected):
    """Whatever the user's `XLA_FLAGS` says about the code generator wins, even after
    the backend started (then nothing needs to change); asking for the fusion
    emitters gives `False` and a warning."""
    warning = "user's setting is kept"
    _assert_keeps(
        monkeypatch, cjax.settings.use_fast_compilation, flags, expected, warning
    )


def _assert_keeps(monkeypatch, use, flags, expected, warning):
    """`use()` after the backend started, with the user's `flags` in `XLA_FLAGS`:
    `True` if they already ask for the setting, else `False` with `warning`; either
    way `XLA_FLAGS` is left as it was."""
    monkeypatch.setenv("XLA_FLAGS", f"--xla_cpu_multi_thread_eigen=true {flags}")
    jnp.zeros(1).block_until_ready()  # the backend has started
    if expected:
        assert use() is True
    else:
        with pytest.warns(UserWarning, match=warning):
            assert use() is False
    assert os.environ["XLA_FLAGS"] == f"--xla_cpu_multi_thread_eigen=true {flags}"


def test_too_late_is_refused(monkeypatch):
    """After the first computation XLA has read its flags: the call raises, with the
    remedy, and leaves `XLA_FLAGS` as it was (JAX's persistent cache keys its entries
    by it, so a flag set but not in effect would mislabel them)."""
    if not _KNOWN:
        pytest.skip("the flag is only set for a known jaxlib")
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=true")
    jnp.zeros(1).block_until_ready()
    with pytest.raises(RuntimeError, match="before the first JAX computation"):
        cjax.settings.use_fast_compilation()
    assert os.environ["XLA_FLAGS"] == "--xla_cpu_multi_thread_eigen=true"


def test_an_unknown_jaxlib_keeps_xlas_defaults(monkeypatch):
    """XLA aborts the process on a flag it does not know (jaxlib 0.11 dropped this
    one), so another jaxlib gets a warning and `False`, and no flag."""
    monkeypatch.setattr(_code_generator, "_jaxlib_version", lambda: "0.11.2")
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    with pytest.warns(UserWarning, match="jaxlib 0.11.2"):
        assert cjax.settings.use_fast_compilation() is False
    assert "XLA_FLAGS" not in os.environ


# ---------------------------------------------------------------------------------
# use_loop_kernels
# ---------------------------------------------------------------------------------

_LOOP = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold"

# A loop whose body touches about 5 kB (a float64 vector of 300 entries, read and
# written): above XLA's default limit (1 kB), below the library's (1 MB). Printed:
# whether XLA compiled the loop into one function, and the result.
_LOOP_PROGRAM = """
import os, jax, jax.numpy as jnp
jax.config.update("jax_enable_x64", True)
import constrained_jax as cjax
if os.environ.get("TURN_ON"):
    assert cjax.settings.use_loop_kernels() is True
    assert cjax.settings.use_loop_kernels() is True  # a second call changes nothing
def run(x):
    body = lambda i, x: jnp.sin(x * 1.001 + i) * jnp.cos(x[::-1]) + 0.5 * x
    return jax.lax.fori_loop(0, 100, body, x)
x = jnp.linspace(0.0, 1.0, 300)
compiled = jax.jit(run).lower(x).compile()
print(os.environ.get("XLA_FLAGS", ""))
print("xla_cpu_small_call" in compiled.as_text())
print(repr([float(v) for v in compiled(x)]))
"""


def _run_loop_program(turn_on: bool, flags: str | None = None):
    run = run_python(
        _LOOP_PROGRAM, timeout=300, TURN_ON="1" if turn_on else None, XLA_FLAGS=flags
    )
    assert run.returncode == 0, run.stderr
    flags_seen, small_call, values = run.stdout.strip().split("\n")[-3:]
    return flags_seen, small_call == "True", eval(values)


@pytest.mark.skipif(not _KNOWN, reason="the pass's limit is measured for jaxlib 0.10.2")
def test_loop_kernels_compile_the_loop_into_one_function():
    """In a fresh process the option is appended after the imports and XLA reads it:
    a loop over about 5 kB, which XLA's default limit (1 kB) leaves to the thunk
    runtime, becomes one function, with the same results to round-off. The user's
    other flags are kept (2 CPU devices)."""
    user = "--xla_force_host_platform_device_count=2"
    flags, small, on = _run_loop_program(True, user)
    assert flags == f"{user} {_LOOP}={cjax.settings.LOOP_KERNEL_BYTES}"
    assert small
    flags, small, off = _run_loop_program(False, user)
    assert flags == user
    assert not small
    assert on == pytest.approx(off, rel=1e-13, abs=1e-13)


def test_loop_kernels_merge_with_the_users_backend_options(monkeypatch):
    """The option joins the user's own `--xla_backend_extra_options` (XLA reads only
    the last such flag), and the rest of `XLA_FLAGS` is left as it is. (No backend
    starts here: XLA aborts on a backend option it does not know.)"""
    monkeypatch.setattr(_code_generator, "backends_started", lambda: False)
    user = (
        "--xla_cpu_multi_thread_eigen=true  "
        "--xla_backend_extra_options=xla_cpu_disable_loop_unrolling"
    )
    monkeypatch.setenv("XLA_FLAGS", user)
    assert cjax.settings.use_loop_kernels(np.int64(4096)) is True  # any integer type
    assert os.environ["XLA_FLAGS"] == (
        f"{user},xla_cpu_small_while_loop_byte_threshold=4096"
    )


@pytest.mark.parametrize("value, expected", [("2048", True), ("0", False)])
def test_loop_kernels_keep_the_users_own_limit(monkeypatch, value, expected):
    """A limit the user set wins, even after the backend started (nothing needs to
    change); a limit of 0 (the pass turned off) gives `False` and a warning."""
    flags = (
        f"--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold={value}"
    )
    _assert_keeps(
        monkeypatch,
        cjax.settings.use_loop_kernels,
        flags,
        expected,
        "turns the pass off",
    )


def test_loop_kernels_too_late_or_a_bad_limit_is_refused(monkeypatch):
    """After the first computation the call raises, with the remedy, and leaves
    `XLA_FLAGS` as it was; a limit that is not a positive integer is refused first."""
    jnp.zeros(1).block_until_ready()
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=true")
    with pytest.raises(RuntimeError, match="before the first JAX computation"):
        cjax.settings.use_loop_kernels()
    for bad in (0, -5, 1.5, True, "65536"):
        with pytest.raises(ValueError, match="positive integer"):
            cjax.settings.use_loop_kernels(bad)
    assert os.environ["XLA_FLAGS"] == "--xla_cpu_multi_thread_eigen=true"


def test_loop_kernels_an_unknown_jaxlib_keeps_xlas_defaults(monkeypatch):
    """XLA aborts on a backend option it does not know: another jaxlib gets a
    warning and `False`, and no flag."""
    monkeypatch.setattr(_code_generator, "_jaxlib_version", lambda: "0.11.2")
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    with pytest.warns(UserWarning, match="jaxlib 0.11.2"):
        assert cjax.settings.use_loop_kernels() is False
    assert "XLA_FLAGS" not in os.environ
