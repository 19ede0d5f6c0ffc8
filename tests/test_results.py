"""Status codes read as words: an item of `RESULTS` (or `EXTREMUM`) prints as its
name, inside and outside `jit`/`vmap`, and behaves as an equinox enumeration item
(`==`, `where`, `promote`, `error_if`, its message by `RESULTS[item]`); public
objects name their public module, and survive a pickle."""

import pickle
import types

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import constrained_jax as cjax


RESULTS = cjax.RESULTS


def test_an_item_prints_as_its_name():
    assert str(RESULTS.successful) == "successful"
    assert repr(RESULTS.successful) == "RESULTS.successful"
    assert repr(RESULTS.singular_kkt) == "RESULTS.singular_kkt"
    assert repr(cjax.EXTREMUM.maximum) == "EXTREMUM.maximum"
    # An item named like the placeholders is still an item.
    assert repr(cjax.EXTREMUM.unknown) == "EXTREMUM.unknown"
    # Every item, by the name it is looked up by.
    for enumeration in (RESULTS, cjax.EXTREMUM):
        for name in enumeration._name_to_item:
            item = getattr(enumeration, name)
            assert str(item) == name
            assert repr(item) == f"{enumeration.__name__}.{name}"
    # Its message is still the enumeration's, by indexing.
    assert RESULTS[RESULTS.successful] == ""
    assert RESULTS[RESULTS.diverged].startswith("The simulation diverged")
    # A solution's repr shows its status by name.
    sol = cjax.extremize(
        lambda x, args: x @ x,
        jnp.array([1.0, 2.0]),
        None,
        constraints=lambda x, args: x[0] + x[1] - 1.0,
    )
    assert "result=RESULTS.successful" in repr(sol)
    assert "kind=EXTREMUM.minimum" in repr(sol)


def test_items_through_jit_vmap_cond_and_loops():
    pick = jax.jit(lambda p: RESULTS.where(p, RESULTS.successful, RESULTS.diverged))
    assert repr(pick(jnp.array(True))) == "RESULTS.successful"
    assert repr(pick(jnp.array(False))) == "RESULTS.diverged"
    assert bool(pick(jnp.array(False)) == RESULTS.diverged)

    batch = jax.vmap(pick)(jnp.array([True, False, True]))
    assert repr(batch) == "RESULTS[successful, diverged, successful]"
    assert str(batch) == "[successful, diverged, successful]"
    np.testing.assert_array_equal(batch == RESULTS.successful, [True, False, True])

    seen = []
    jax.jit(lambda p: seen.append(repr(pick(p))))(jnp.array(True))
    assert seen == ["RESULTS(traced)"]

    # Items from `where`, `promote` and the class have one pytree type, as
    # `lax.cond` and `lax.while_loop` need.
    promoted = RESULTS.promote(optx.RESULTS.max_steps_reached)
    assert repr(promoted) == "RESULTS.max_steps_reached"
    assert repr(RESULTS.promote(diffrax.RESULTS.event_occurred)) == (
        "RESULTS.event_occurred"
    )
    out = jax.lax.cond(jnp.array(False), lambda: RESULTS.successful, lambda: promoted)
    assert bool(out == RESULTS.max_steps_reached)

    def body(carry):
        i, result = carry
        return i + 1, RESULTS.where(i < 2, result, RESULTS.singular_kkt)

    _, result = jax.lax.while_loop(lambda c: c[0] < 4, body, (0, RESULTS.successful))
    assert repr(result) == "RESULTS.singular_kkt"


def test_items_raise_their_message():
    with pytest.raises(eqx.EquinoxRuntimeError, match="KKT matrix"):
        eqx.filter_jit(lambda x: RESULTS.singular_kkt.error_if(x, x > 0))(jnp.ones(()))
    with pytest.raises(ValueError):
        RESULTS.successful == diffrax.RESULTS.successful  # noqa: B015


def _public(module: types.ModuleType):
    for name, obj in sorted(vars(module).items()):
        if not name.startswith("_") and isinstance(obj, (type, types.FunctionType)):
            if obj.__module__.startswith("constrained_jax"):
                yield name, obj


@pytest.mark.parametrize("module", [cjax, cjax.settings])
def test_public_objects_name_their_public_module(module):
    """Reprs, `help()` and pickles of the exported classes and functions say
    `constrained_jax.X`, never the private module that defines them."""
    found = list(_public(module))
    assert len(found) > (40 if module is cjax else 2)
    for name, obj in found:
        assert obj.__module__ == module.__name__, name
        assert "._" not in repr(obj), (name, repr(obj))
        assert getattr(module, obj.__qualname__) is obj
    assert repr(cjax.Holonomic) == "<class 'constrained_jax.Holonomic'>"


def test_public_objects_survive_a_pickle():
    for obj in (
        cjax.extremize,
        cjax.Holonomic,
        cjax.RESULTS,
        cjax.settings.use_loop_kernels,
    ):
        assert pickle.loads(pickle.dumps(obj)) is obj
    for value in (
        cjax.DenseLU(),
        cjax.Baumgarte(alpha=1.0, beta=2.0),
        RESULTS.diverged,
        jax.vmap(lambda p: RESULTS.where(p, RESULTS.successful, RESULTS.diverged))(
            jnp.array([True, False])
        ),
    ):
        again = pickle.loads(pickle.dumps(value))
        assert type(again) is type(value)
        assert repr(again) == repr(value)
