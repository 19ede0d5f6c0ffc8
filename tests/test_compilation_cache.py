"""`cjax.enable_compilation_cache`: JAX's persistent compilation cache in a folder of
the user's cache directory, the switch that turns it off, and a second process that
reads the entry the first one wrote."""

import pathlib

import jax
import pytest
from jax.experimental.compilation_cache import compilation_cache

import constrained_jax as cjax

from .helpers import run_python


@pytest.fixture
def restore_cache_config():
    names = (
        "jax_compilation_cache_dir",
        "jax_persistent_cache_min_compile_time_secs",
        "jax_persistent_cache_min_entry_size_bytes",
        "jax_enable_compilation_cache",
    )
    saved = {name: getattr(jax.config, name) for name in names}
    yield
    for name, value in saved.items():
        jax.config.update(name, value)
    # JAX decides once per process whether (and where) the cache is used: back to
    # undecided, so that the rest of the worker compiles without it.
    compilation_cache.reset_cache()


def test_default_folder_follows_xdg(tmp_path, monkeypatch, restore_cache_config):
    monkeypatch.delenv("CONSTRAINED_JAX_COMPILATION_CACHE", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    path = cjax.enable_compilation_cache()
    assert path == tmp_path / "constrained_jax" / "jax"
    assert path.is_dir()
    assert jax.config.jax_compilation_cache_dir == str(path)
    assert jax.config.jax_persistent_cache_min_compile_time_secs == 0.5


def test_explicit_folder_and_environment_folder(
    tmp_path, monkeypatch, restore_cache_config
):
    monkeypatch.setenv("CONSTRAINED_JAX_COMPILATION_CACHE", str(tmp_path / "env"))
    assert cjax.enable_compilation_cache() == tmp_path / "env"
    assert cjax.enable_compilation_cache(tmp_path / "arg") == tmp_path / "arg"
    assert jax.config.jax_compilation_cache_dir == str(tmp_path / "arg")


@pytest.mark.parametrize("value", ["0", "false", "OFF", "no"])
def test_switch_turns_it_off(tmp_path, monkeypatch, restore_cache_config, value):
    before = jax.config.jax_compilation_cache_dir
    monkeypatch.setenv("CONSTRAINED_JAX_COMPILATION_CACHE", value)
    assert cjax.enable_compilation_cache(tmp_path / "cache") is None
    assert jax.config.jax_compilation_cache_dir == before
    assert not (tmp_path / "cache").exists()


def test_not_enabled_by_import(tmp_path):
    """Importing the library leaves JAX's cache folder unset."""
    code = "import jax, constrained_jax; print(jax.config.jax_compilation_cache_dir)"
    assert _python(code, tmp_path).strip() == "None"


_PROGRAM = """
import sys, jax, jax.numpy as jnp
import constrained_jax as cjax
from jax import monitoring
hits = []
monitoring.register_event_listener(
    lambda event, **kw: hits.append(event) if event.endswith("cache_hits") else None
)
path = cjax.enable_compilation_cache(min_compile_time_secs=0.0)
f = jax.jit(lambda x: jnp.sin(x) * jnp.cos(x) + x**3)
f(jnp.arange(3.0)).block_until_ready()
print(path, len(hits))
"""


def _python(code, tmp_path) -> str:
    """The standard output of `code` run by a new Python process, with this
    checkout's `constrained_jax` and `XDG_CACHE_HOME=tmp_path`."""
    run = run_python(
        code,
        timeout=600,
        XDG_CACHE_HOME=str(tmp_path),
        CONSTRAINED_JAX_COMPILATION_CACHE=None,
    )
    assert run.returncode == 0, run.stderr
    return run.stdout


def test_second_process_reads_the_entry(tmp_path):
    """A first process writes the compiled program into the folder; a second one
    compiling the same program finds it there (a cache hit) and writes nothing new."""

    def run():
        out = _python(_PROGRAM, tmp_path).split()
        return pathlib.Path(out[0]), int(out[1])

    path, hits = run()
    assert path == tmp_path / "constrained_jax" / "jax"
    first = sorted(p.name for p in path.iterdir())
    assert first and hits == 0
    _, hits = run()
    assert hits >= 1
    assert sorted(p.name for p in path.iterdir()) == first
