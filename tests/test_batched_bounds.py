"""`jax.jit(jax.vmap(extremize(..., lower=, upper=)))` over batches of 100, 200, 300
and 1000 problems of n = 10 finishes (a fresh process under a time limit: a hang
fails the test instead of stalling the suite) and gives the closed form, under XLA's
defaults and under the settings scripts may opt into (`cjax.settings`, as the
command line turns them on).

The problem: a weighted box QP, `min sum w (x - t)^2` on `lo <= x <= up`, with the
closed form `x = clip(t, lo, up)`."""

import json
import textwrap

import pytest

from .helpers import run_python


_CODE = textwrap.dedent(
    """
    import json, sys
    import jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    import constrained_jax as cjax
    if OPT_IN:
        cjax.settings.use_fast_compilation()
        cjax.settings.use_loop_kernels()
    n = 10
    w = jnp.linspace(0.5, 2.0, n)
    lo, up = -0.5 * jnp.ones(n), jnp.linspace(0.2, 1.0, n)

    def solve(t):
        out = cjax.extremize(
            lambda x, a: jnp.sum(w * (x - a) ** 2), jnp.zeros(n), t,
            lower=lo, upper=up, sense="minimize", throw=False,
        )
        return out.x, out.result == cjax.RESULTS.successful

    run = jax.jit(jax.vmap(solve))
    report = {}
    for size in (100, 200, 300, 1000):
        t = jax.random.uniform(jax.random.key(size), (size, n), minval=-2, maxval=2)
        x, ok = jax.block_until_ready(run(t))
        err = float(np.max(np.abs(np.asarray(x) - np.clip(t, lo, up))))
        report[size] = [bool(np.all(ok)), err]
    print("REPORT" + json.dumps(report))
    """
)


@pytest.mark.parametrize("opt_in", [False, True], ids=["xla-defaults", "opt-in"])
def test_vmapped_bounds_batches_finish(opt_in):
    code = f"OPT_IN = {opt_in}\n" + _CODE
    out = run_python(code, timeout=600, XLA_FLAGS=None)
    assert out.returncode == 0, out.stderr[-3000:]
    line = next(s for s in out.stdout.splitlines() if s.startswith("REPORT"))
    report = json.loads(line[len("REPORT") :])
    for size, (ok, err) in report.items():
        assert ok, f"batch of {size}: not every problem successful"
        assert err < 1e-10, f"batch of {size}: error {err}"
