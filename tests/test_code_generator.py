"""`use_fast_compilation`: XLA:CPU's older code generator, opted into before the
first computation, never against the user's own `XLA_FLAGS`, refused when too late.

Its effect on compile and run time is measured in `benchmarks/code_generator.py` and
`benchmarks/compile_time.py --fast-compilation` (not in timed tests)."""

import importlib.metadata
import os

import jax.numpy as jnp
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
assert cjax.use_fast_compilation() is True
flags = os.environ["XLA_FLAGS"]
print(flags)
print(float(jax.jit(lambda x: jnp.sum(jnp.sin(x) ** 2))(jnp.arange(3.0))))
print(len(jax.devices("cpu")))
assert cjax.use_fast_compilation() is True
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
    monkeypatch.setenv("XLA_FLAGS", f"--xla_cpu_multi_thread_eigen=true {flags}")
    jnp.zeros(1).block_until_ready()  # the backend has started
    if expected:
        assert cjax.use_fast_compilation() is True
    else:
        with pytest.warns(UserWarning, match="user's setting is kept"):
            assert cjax.use_fast_compilation() is False
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
        cjax.use_fast_compilation()
    assert os.environ["XLA_FLAGS"] == "--xla_cpu_multi_thread_eigen=true"


def test_an_unknown_jaxlib_keeps_xlas_defaults(monkeypatch):
    """XLA aborts the process on a flag it does not know (jaxlib 0.11 dropped this
    one), so another jaxlib gets a warning and `False`, and no flag."""
    monkeypatch.setattr(_code_generator, "_jaxlib_version", lambda: "0.11.2")
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    with pytest.warns(UserWarning, match="jaxlib 0.11.2"):
        assert cjax.use_fast_compilation() is False
    assert "XLA_FLAGS" not in os.environ
