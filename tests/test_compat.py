"""The library's reach-ins into other libraries' private internals: all in one adapter
module (`constrained_jax/_compat.py`), each with a fallback for the versions it was
not written for; the diffrax patch is opt-in (`cjax.settings.use_diffrax_patch`)."""

import ast
import os
import pathlib

import diffrax
import equinox.internal as eqxi
import jax
import jax.extend as jex
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax
from constrained_jax import _code_generator, _compat, _diffrax_integrate
from constrained_jax.scenes import pendulum

from .helpers import run_python


PACKAGE = pathlib.Path(cjax.__file__).parent
_LIBRARIES = ("jax", "diffrax", "equinox", "optimistix", "lineax")
_ALIASES = {"jax", "diffrax", "dfx", "eqx", "equinox", "optx", "optimistix", "lx"}


def _private(module: str) -> bool:
    """Whether `module` names a private module of one of `_LIBRARIES`."""
    parts = module.split(".")
    return parts[0] in _LIBRARIES and (
        any(p.startswith("_") for p in parts[1:]) or "internal" in parts[1:]
    )


def _reach_ins(path: pathlib.Path) -> list[str]:
    """The imports of private modules, attribute reads of private names on the
    libraries' modules (`diffrax._integrate`) and strings naming `jax._src` in one
    source file."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found += [a.name for a in node.names if _private(a.name)]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [f"{node.module}.{a.name}" for a in node.names]
            found += [n for n in [node.module, *names] if _private(n)][:1]
        elif (
            isinstance(node, ast.Attribute)
            and isinstance(node.value, ast.Name)
            and node.value.id in _ALIASES
            and node.attr.startswith("_")
            and not node.attr.startswith("__")
        ):
            found.append(f"{node.value.id}.{node.attr}")
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            if node.value.startswith("jax._src"):
                found.append(node.value)
    return found


def test_no_private_reach_ins_outside_the_adapter():
    """Only `_compat.py` imports or reads another library's private modules; and it
    imports JAX's private modules only inside the functions that guard them (so that
    `import constrained_jax` never depends on them)."""
    offenders = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        if path.name == "_compat.py":
            continue
        if found := _reach_ins(path):
            offenders[str(path.relative_to(PACKAGE))] = found
    assert not offenders, offenders
    tree = ast.parse((PACKAGE / "_compat.py").read_text())
    top = [n for n in tree.body if isinstance(n, (ast.Import, ast.ImportFrom))]
    names = [a.name for n in top if isinstance(n, ast.Import) for a in n.names]
    names += [n.module for n in top if isinstance(n, ast.ImportFrom) and n.module]
    assert [n for n in names if _private(n)] == ["equinox.internal", "lineax.internal"]


def test_the_reach_in_check_finds_reach_ins(tmp_path):
    """The check above finds each kind of reach-in it looks for."""
    source = tmp_path / "x.py"
    source.write_text(
        "import equinox.internal as eqxi\n"
        "import lineax.internal as lxi\n"
        "from jax._src import xla_bridge\n"
        "from diffrax._root_finder import use_stepsize_tol\n"
        "import diffrax\n"
        "m = diffrax._integrate\n"
        "name = 'jax._src.callback'\n"
        "ok = diffrax.__version__\n"
        "from jax.extend.core import Literal\n"
    )
    assert _reach_ins(source) == [
        "equinox.internal",
        "lineax.internal",
        "jax._src",
        "diffrax._root_finder",
        "diffrax._integrate",
        "jax._src.callback",
    ]


def _callbacks(jaxpr) -> list[str]:
    """The host-callback primitives in a closed jaxpr, nested ones included."""
    found = []
    for eqn in jaxpr.eqns:
        if "callback" in eqn.primitive.name:
            found.append(eqn.primitive.name)
        for sub in jex.core.jaxprs_in_params(eqn.params):
            found += _callbacks(sub)
    return found


def _decay(t1, ts):
    """`y' = -y` from 0 to `t1`, saved at `ts` (checked) and at `t1`, by the
    library's `diffeqsolve`."""
    sol = _diffrax_integrate.diffeqsolve(
        diffrax.ODETerm(lambda t, y, args: -y),
        diffrax.Tsit5(),
        jnp.zeros_like(t1),
        t1,
        None,
        jnp.ones(()),
        saveat=diffrax.SaveAt(
            subs=[diffrax.SubSaveAt(t1=True), diffrax.SubSaveAt(ts=ts)]
        ),
        stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-10),
        throw=False,
        save_times_checked=True,
    )
    return sol.ys, sol.ts


def test_diffrax_patch_off_by_default():
    """A fresh process that imports the library runs diffrax unchanged."""
    code = (
        "import constrained_jax as cjax\n"
        "from constrained_jax import _diffrax_integrate as d\n"
        "print(d.diffrax_patch_on())\n"
    )
    run = run_python(code, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["False"]


def test_diffrax_patch_on_and_off(diffrax_patch):
    """Off: the library's `diffeqsolve` is diffrax's (its save-time checks are host
    callbacks; 100 `nextafter`s for a traced `t1`). On: no host callbacks, the floor
    in a loop, and the same values bit for bit; diffrax's module is left as it
    was."""
    t1 = jnp.asarray(1.7)
    ts = jnp.linspace(0.0, 1.7, 7)
    fn = jax.jit(_decay)
    out = {}
    for on in (False, True):
        assert diffrax_patch(on) is on
        with jax.numpy_dtype_promotion("standard"):
            jaxpr = jax.make_jaxpr(_decay)(t1, ts)
            text = fn.lower(t1, ts).as_text()
        assert bool(_callbacks(jaxpr.jaxpr)) is not on
        assert (text.count("next_after") < 10) is on
        assert (text.count("next_after") >= 100) is not on
        with jax.numpy_dtype_promotion("standard"):
            out[on] = fn(t1, ts)
        from diffrax import _integrate

        assert _integrate.eqxi is eqxi
    (end_off, saved_off), ts_off = out[False]
    (end_on, saved_on), ts_on = out[True]
    np.testing.assert_array_equal(saved_on, saved_off)
    np.testing.assert_array_equal(end_on, end_off)
    np.testing.assert_allclose(saved_on, np.exp(-np.asarray(ts)), rtol=1e-8)


def test_simulate_without_the_patch_is_plain_diffrax(diffrax_patch):
    """Without the opt-in, a `simulate` program with traced save times holds
    diffrax's own save-time checks (host callbacks): the library leaves diffrax as it
    is."""
    assert diffrax_patch(False) is False
    args = pendulum.default_args()
    q0, qd0 = pendulum.state(jnp.asarray(0.5), jnp.asarray(0.0), args)

    def run(ts):
        return cjax.simulate(
            pendulum.system(), (0.0, 1.0), q0, qd0, args, saveat=cjax.SaveAt(ts=ts)
        ).q

    with jax.numpy_dtype_promotion("standard"):
        jaxpr = jax.make_jaxpr(run)(jnp.linspace(0.0, 1.0, 4))
    assert _callbacks(jaxpr.jaxpr)


def test_an_unknown_diffrax_runs_unchanged(monkeypatch, diffrax_patch):
    """On a diffrax release the adapter was not written for: the opt-in warns and
    stays off, the patch's scope changes nothing, and the Runge-Kutta stages are not
    read (the caller samples the dense output instead)."""
    monkeypatch.setattr(_compat, "_diffrax_version", lambda: "0.0.1")
    diffrax_patch(False)
    with pytest.warns(UserWarning, match="diffrax 0.0.1, which runs unchanged"):
        assert cjax.settings.use_diffrax_patch() is False
    assert not _diffrax_integrate.diffrax_patch_on()
    assert not _compat.diffrax_patch_available()
    from diffrax import _integrate

    with _compat.patched_diffrax(True):
        assert _integrate.eqxi is eqxi
    assert _compat.runge_kutta_stages(diffrax.Tsit5()) is None
    monkeypatch.undo()
    assert _compat.runge_kutta_stages(diffrax.Tsit5()) is not None


@pytest.mark.parametrize(
    "solver, fsal",
    [(diffrax.Tsit5(), True), (diffrax.Dopri5(), True), (diffrax.Heun(), False)],
)
def test_runge_kutta_stage_derivatives(solver, fsal):
    """For `(y, w, z)' = (cos(t), 2t, -z)` the derivatives read from a step's dense
    output are the vector field at the stage times, to round-off; a
    first-same-as-last tableau's last stage is at the end of the step, with the
    step's end state; the dense output of one component is that component's."""
    stages = _compat.runge_kutta_stages(solver)
    assert stages is not None and stages.fsal is fsal
    assert stages.times[0] == 0.0 and np.all((stages.times >= 0) & (stages.times <= 1))
    term = diffrax.ODETerm(lambda t, y, args: (jnp.cos(t), 2 * t, -y[2]))
    t0, t1 = jnp.asarray(0.3), jnp.asarray(0.55)
    y0 = (jnp.asarray(0.1), jnp.asarray(-2.0), jnp.asarray(1.5))
    state = solver.init(term, t0, t1, y0, None)
    y1, _, dense, _, _ = solver.step(term, t0, t1, y0, None, state, False)
    derivatives = _compat.stage_derivatives(dense, t0, t1)
    times = np.asarray(t0) + stages.times * np.asarray(t1 - t0)
    np.testing.assert_allclose(derivatives[0], np.cos(times), rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(derivatives[1], 2 * times, rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(derivatives[2][0], -y0[2], rtol=1e-14)
    if fsal:
        assert stages.times[-1] == 1.0
        np.testing.assert_allclose(derivatives[2][-1], -y1[2], rtol=1e-14)
    first = _compat.component_dense_info(dense, 0)
    interpolation = solver.interpolation_cls(t0=t0, t1=t1, **first)
    np.testing.assert_allclose(interpolation.evaluate(t1), y1[0], rtol=1e-14)
    np.testing.assert_allclose(interpolation.evaluate(t0), y0[0], rtol=1e-14)


def test_no_stages_for_other_solvers():
    """Solvers without a Butcher tableau (or not Runge-Kutta) give `None`."""
    assert _compat.runge_kutta_stages(diffrax.Euler()) is None
    assert _compat.runge_kutta_stages(diffrax.ReversibleHeun()) is None


def test_jax_fallbacks(monkeypatch):
    """Where JAX's private functions are missing, the adapter answers "unknown"
    (`None`) instead of failing, and the XLA settings go on with a warning."""
    from jax._src import distributed, xla_bridge

    assert _compat.backends_started() is True  # this worker has computed
    assert _compat.distributed_client() is None  # not initialised
    monkeypatch.delattr(xla_bridge, "backends_are_initialized")
    monkeypatch.delattr(distributed, "global_state")
    assert _compat.backends_started() is None
    assert _compat.distributed_client() is None
    monkeypatch.setattr(_code_generator, "_jaxlib_version", lambda: "0.10.2")
    monkeypatch.setattr(_code_generator, "_KNOWN_JAXLIB", frozenset({"0.10.2"}))
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=true")
    with pytest.warns(UserWarning, match="does not say whether its backend"):
        assert cjax.settings.use_loop_kernels(4096) is True
    assert "xla_cpu_small_while_loop_byte_threshold=4096" in os.environ["XLA_FLAGS"]


def test_quiet_callback_errors_restores_the_level():
    import logging

    log = logging.getLogger(_compat.CALLBACK_LOGGER)
    before = log.level
    with _compat.quiet_callback_errors():
        assert log.level == logging.CRITICAL
    assert log.level == before


def test_the_upstream_reproducers_run():
    """The reproducers of `docs/upstream/diffrax.md` (JAX and diffrax only) run and
    their checks hold: the traced floor is the larger program, the looped floor is
    the same bit for bit, and a solve saving at `ts` holds host callbacks and is not
    cached where one saving at `t1` is; the third reproduces its `TypeError` (a
    float32 event under x64). When it stops failing, diffrax has the fix: remove
    the `xfail` of `test_contact_series.py::test_float32_state_with_x64_enabled`."""
    import re

    page = PACKAGE.parent / "docs" / "upstream" / "diffrax.md"
    blocks = re.findall(r"```python\n(.*?)```", page.read_text(), flags=re.S)
    assert len(blocks) == 3
    for block in blocks[:2]:
        run = run_python(block, timeout=600, CONSTRAINED_JAX_COMPILATION_CACHE=None)
        assert run.returncode == 0, run.stdout + run.stderr
    run = run_python(blocks[2], timeout=600, CONSTRAINED_JAX_COMPILATION_CACHE=None)
    assert run.returncode != 0
    assert "cond branches must have equal output types" in run.stderr, run.stderr
