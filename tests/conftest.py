import jax
import pytest


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
