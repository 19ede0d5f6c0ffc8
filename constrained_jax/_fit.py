"""fit(): gradient-based inverse problems, an optax loop compiled in blocks.

An inverse problem asks which parameters `p` make a model reproduce data. Written as
a loss, e.g. the least-squares misfit `chi^2(p)/2 = sum_i ((model_i(p) - d_i) /
sigma_i)^2 / 2`, it is minimised by gradient steps; the gradient comes from autodiff
through whatever the model does (a simulation with release events, a variational
problem solved by Newton's method and differentiated by the implicit function
theorem, ...). `fit` runs the optimizer loop as compiled code (`jax.lax.scan` over a
block of steps), reporting progress between blocks, and stops with a status instead
of returning NaN when the loss or its gradient stops being finite.
"""

import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import optax
from jaxtyping import Array, Bool, Float, Int, PyTree

from ._custom_types import Args
from ._misc import (
    all_finite,
    as_traced_args,
    check_signature,
    default_float_dtype,
    full_precision,
    lists_as_arrays,
    progress_bar,
)
from ._results import raise_if_failed, RESULTS


DEFAULT_LEARNING_RATE = 1e-2
"""The learning rate of the default optimizer, `optax.adam(1e-2)`."""

# Module-level, so that every fit with the default optimizer shares one compiled
# program per loss: JAX hashes the optimizer's functions by identity, and a new
# `optax.adam(...)` is a new function to it.
_DEFAULT_OPTIMIZER = optax.adam(DEFAULT_LEARNING_RATE)

_BLOCK = 100
"""Optimizer steps per compiled block; the progress bar is updated between blocks."""


class FitResult(eqx.Module):
    """The result of [`constrained_jax.fit`][].

    **Attributes:**

    - `params`: the fitted parameters, with the structure of `params0`: the last
        ones evaluated. If the fit stopped because the loss or its gradient became
        non-finite, these are the last parameters at which both were finite; if it
        diverged (`RESULTS.fit_diverged`), `params0` (the better of the start and the
        end); if `params0` was not finite, `params0`.
    - `losses`: the loss history, shape `(steps + 1,)`: `losses[i]` is the loss after
        `i` optimizer steps (`losses[0]` at `params0`). Entries after the fit stopped
        (converged, or non-finite) repeat the final loss.
        With a non-finite `params0` every entry is `inf`.
    - `grad_norm`: the norm of the gradient at `params` (the 2-norm over all leaves).
    - `steps`: the number of optimizer steps taken to reach `params`.
    - `result`: a [`constrained_jax.RESULTS`][] member: `successful` (see
        [`constrained_jax.fit`][] for what it certifies); `invalid_input` (`params0`
        holds NaN or inf; nothing was evaluated); `nonfinite` (the loss, its
        gradient or the parameters became inf or NaN; `params` are the last finite
        ones); `fit_diverged` (the last loss is higher than the loss at `params0`, and
        the parameters moved: the optimizer made things worse; `params` are
        `params0`, `steps` 0); `nonlinear_max_steps_reached` (a tolerance `gtol`
        was given and not reached within `steps`).
    """

    params: PyTree[Array]
    losses: Float[Array, " steps_plus_one"]
    grad_norm: Float[Array, ""]
    steps: Int[Array, ""]
    result: RESULTS


class _State(eqx.Module):
    candidate: PyTree[Array]  # the parameters to evaluate next
    opt_state: Any
    params: PyTree[Array]  # the last evaluated parameters with finite loss and grad
    loss: Float[Array, ""]
    grad: PyTree[Array]
    evaluations: Int[Array, ""]  # of `params` so far; steps taken = evaluations - 1
    converged: Bool[Array, ""]
    result: RESULTS
    first_grad_norm: Float[Array, ""]  # at `params0` (returned if diverged)


@full_precision
def fit(
    loss,
    params0: PyTree,
    *,
    optimizer: optax.GradientTransformation = _DEFAULT_OPTIMIZER,
    steps: int = 1000,
    args: Args = None,
    gtol=None,
    jac: str = "bwd",
    progress: bool = True,
    throw: bool = True,
) -> FitResult:
    """Minimise `loss(params, args)` over `params` with an optax optimizer.

    **Arguments:**

    - `loss`: `loss(params, args) -> scalar`, differentiable in `params` (e.g.
        `0.5 * jnp.sum(((model(params, args) - data) / sigma) ** 2)`). Keep the data in
        `args`: they are traced, so fitting new data never recompiles. Pass the same
        function object to repeated fits (a new lambda is a new program to JAX).
    - `params0`: the starting parameters: an array or any pytree of floating arrays
        (Python numbers, lists of them and integer arrays become floats; a complex
        or text leaf is refused, named by its path).
    - `optimizer`: any `optax.GradientTransformation`; by default
        `optax.adam(1e-2)`. Adam moves each parameter by about its learning rate per
        step whatever the gradient's scale, so with the default, parameters of order
        one move by at most ~10 in 1000 steps: scale the parameters to order one (fit
        `log l` rather than `l` if `l` spans decades), or pass an optimizer with
        another rate or a schedule (`optax.adam(optax.exponential_decay(...))`).
        Optimizers that take the loss value or a line search (`optax.lbfgs()`) get
        `value`, `grad` and `value_fn` at every step. Create the optimizer once and
        reuse it: a new optimizer object compiles anew.
    - `steps`: the most optimizer steps.
    - `args`: data and fixed parameters, passed last to `loss`; traced (Python numbers
        in it become arrays).
    - `gtol`: optional convergence test: stop when the gradient's 2-norm (over all
        leaves of `params`) is at most `gtol`. Then not reaching it within `steps` is
        a failure, `RESULTS.nonlinear_max_steps_reached`. With `gtol=None` (default)
        the fit runs all `steps` and succeeds unless something becomes non-finite
        or it diverges: `successful` then means "ran the requested steps, stayed
        finite, and ended lower than it started", NOT "converged" (a fit whose loss
        is still falling fast is `successful`). Pass `gtol` to have convergence
        checked, and look at `losses` and `grad_norm`.
    - `jac`: how the gradient is computed: `"bwd"` (default), reverse mode (one
        backward pass, whatever the number of parameters); `"fwd"`, forward mode
        (`jax.jacfwd`: one forward pass per parameter, cheaper for a few parameters
        and a long computation, e.g. a simulation with
        `adjoint=diffrax.ForwardMode()`, whose default adjoint supports only reverse
        mode). The same convention as optimistix's `options=dict(jac=...)`. A line
        search inside the optimizer (`optax.lbfgs`) differentiates `value_fn` itself,
        in reverse mode.
    - `progress`: show a progress bar (tqdm) with the loss, updated every block of
        100 steps. Also off when the environment variable `TQDM_DISABLE` is set to
        any non-empty value (as tqdm reads it: `0` and `off` disable it too), and
        inside `jax.jit` / `jax.vmap`.
    - `throw`: raise on failure if `True`; otherwise report it in `result`. A
        run-time error inside `loss` (a solve called with `throw=True` that failed)
        is raised with `throw=True`; with `throw=False` the fit stops there with
        `RESULTS.nonfinite` and the last parameters evaluated without error (the
        block of steps is run again one step at a time up to the failing
        evaluation). Inside `jax.jit` / `jax.vmap` such an error cannot be caught:
        call the solves in `loss` with `throw=False` there.

    **Returns:** a [`constrained_jax.FitResult`][] (`params`, `losses`, `grad_norm`,
    `steps`, `result`).

    Each step evaluates the loss and its gradient once (as `jac` says) and then
    takes the optimizer's step. If the loss, the gradient or the parameters become
    non-finite, the fit stops there with `RESULTS.nonfinite` and returns the last
    finite parameters: a NaN is never returned silently. A `params0` with NaN or
    inf is refused (`RESULTS.invalid_input`) before the loss is evaluated.

    An optimizer that diverges while staying finite (e.g. gradient descent with a
    learning rate above `2 / curvature`: `optax.sgd(1.5)` on `sum((p - 1)**2)`
    takes the loss from 2 to 3e60 in 100 steps) ends with `RESULTS.fit_diverged`:
    the test, made once at the end, is that the last loss exceeds the loss at
    `params0` (beyond rounding) while the parameters moved (beyond rounding, so
    that a start at an exact minimum, where the gradient is rounding noise, is
    not flagged). Normal training ends below its start, however noisy its
    losses on the way (Adam's overshoots included); a fit started so near a
    minimum that the optimizer's step size only rattles around it can end above
    its start, and is then flagged too, honestly. A diverged fit returns
    `params0` (with its gradient norm and `steps=0`): the better of its start and
    its end. It does not return the best parameters seen on the way, which would
    cost a copy of the parameters at every step; `losses` shows where they were.

    The loop runs in blocks of 100 evaluations, each one `jax.lax.scan`; between
    blocks the progress bar is updated and a converged or failed fit stops. It
    compiles once for a given loss function, optimizer, `jac`, structure of
    `params0` and `args`, and block length `min(steps + 1, 100)`: new values of
    `params0`, `args` or `gtol`, or any `steps >= 99`, reuse the compiled program.
    Called inside `jax.jit` or `jax.vmap` (when `params0` or `args` are traced), the
    whole loop is one scan over `steps + 1` evaluations with no progress bar; under
    `jax.vmap` every member of the batch stops on its own (the others go on).

    !!! note

        Gradient-based fits find a local minimum near `params0`. For a least-squares
        loss, the parameters' standard errors follow from the Jacobian `J` of the
        weighted residuals at the minimum, `cov = (J^T J)^{-1}`
        (`jax.jacfwd`/`jax.jacrev` of the residuals), valid when the noise is small
        enough for the model to be linear over its scale.

    !!! note "Which optimizer"

        A least-squares loss in a few parameters has a narrow valley (curvature
        `~1/sigma^2`). Adam's steps have a fixed size: it creeps towards such a
        minimum and then rattles around it. A quasi-Newton method learns the
        curvature: `optax.lbfgs(optax.linear_schedule(0.1, 1.0, 4), linesearch=None)`
        (no line search, its first steps damped: the first one has unit length, so
        parameters should be of order one) reached the minimum in about ten steps in
        `notebooks/05_inverse_fits.ipynb`. `optax.lbfgs()` with its default line
        search is safer far from the minimum, but the line search differentiates the
        loss again (in reverse mode), so a fit compiles two to three times longer.
    """
    check_signature(loss, "`loss`", "loss(params, args)")
    if not isinstance(optimizer, optax.GradientTransformation):
        raise ValueError(
            "`optimizer` must be an optax GradientTransformation, e.g. "
            f"`optax.adam(1e-2)`, got {type(optimizer).__name__}."
        )
    if not isinstance(steps, int) or isinstance(steps, bool) or steps < 0:
        raise ValueError(f"`steps` must be a non-negative int, got {steps!r}.")
    if jac not in ("bwd", "fwd"):
        raise ValueError(
            f'`jac` must be "bwd" (reverse mode) or "fwd" (forward mode), got {jac!r}.'
        )
    params0 = _as_params(params0)
    args = as_traced_args(args)
    if gtol is not None:
        if isinstance(gtol, (int, float)) and not gtol > 0:
            raise ValueError(f"`gtol` must be positive (or None), got {gtol!r}.")
        gtol = jnp.asarray(gtol, default_float_dtype())

    traced = any(
        isinstance(leaf, jax.core.Tracer) for leaf in jtu.tree_leaves((params0, args))
    )
    if traced:
        res = _fit_traced(loss, optimizer, gtol, jac, steps, params0, args)
    else:
        res = _fit_blocks(
            loss, optimizer, gtol, jac, steps, params0, args, progress, throw
        )
    return raise_if_failed(res, throw)


def _as_params(params0):
    """`params0` with lists of numbers as arrays and every leaf a strongly typed
    real floating array (Python numbers and integer arrays become floats); a complex
    or text leaf is refused, named by its path."""
    params0 = lists_as_arrays(params0)
    leaves = jtu.tree_flatten_with_path(params0)[0]
    if not leaves:
        raise ValueError("`params0` has no arrays in it: pass the starting parameters.")
    converted = []
    for path, leaf in leaves:
        where = f"params0{jtu.keystr(path)}" if path else "`params0`"
        try:
            if isinstance(leaf, (str, bytes)):
                raise TypeError
            leaf = jnp.asarray(leaf)
        except TypeError:
            raise ValueError(
                f"{where} is a {type(leaf).__name__}, not a number or an array: "
                "every leaf of `params0` is a parameter to fit. Pass fixed settings "
                "by closure or in `args`."
            ) from None
        if jnp.issubdtype(leaf.dtype, jnp.complexfloating):
            raise ValueError(
                f"{where} is complex ({leaf.dtype}): `params0` must be real: fit the "
                "real and imaginary parts of a complex parameter as two real ones."
            )
        if not jnp.issubdtype(leaf.dtype, jnp.floating):
            if not jnp.issubdtype(leaf.dtype, jnp.number):
                raise ValueError(
                    f"{where} has the dtype {leaf.dtype}: `params0` must hold numbers."
                )
            leaf = leaf.astype(default_float_dtype())
        # A strong type: a weakly typed start would recompile on every new value.
        converted.append(jnp.asarray(leaf, leaf.dtype))
    return jtu.tree_unflatten(jtu.tree_structure(params0), converted)


def _check_loss_value(value) -> None:
    if not isinstance(value, (jax.Array, jax.ShapeDtypeStruct)):
        raise ValueError(
            "`loss(params, args)` must return one scalar array, got a "
            f"{type(value).__name__}. If it also returns diagnostics, leave them out "
            "(compute them afterwards from `FitResult.params`)."
        )
    if value.shape != ():
        raise ValueError(
            f"`loss(params, args)` must return a scalar, got shape {value.shape}. "
            "Reduce it to one number, e.g. `0.5 * jnp.sum(residuals**2)`."
        )
    if not jnp.issubdtype(value.dtype, jnp.floating):
        raise ValueError(
            f"`loss(params, args)` must return a real floating-point scalar, got "
            f"{value.dtype}."
        )


def _optax_promotion():
    """optax mixes Python floats with integer step counts (`decay**count`), which
    `jax_numpy_dtype_promotion="strict"` refuses: run the optimizer under the standard
    rules whatever the user's setting."""
    return jax.numpy_dtype_promotion("standard")


def _value_and_grad(loss, params, args, opt_state, jac):
    """The loss and its gradient at `params` (one trace of `loss`), reusing those a
    line search stored in the optimizer state (e.g. `optax.lbfgs`) when it holds
    exactly one of each."""
    try:
        stored = optax.tree.get(opt_state, "value"), optax.tree.get(opt_state, "grad")
    except (KeyError, ValueError):
        stored = (None, None)
    if stored[0] is None or stored[1] is None:
        if jac == "fwd":

            def value_twice(p):
                value = loss(p, args)
                _check_loss_value(value)
                return value, value

            return tuple(reversed(jax.jacfwd(value_twice, has_aux=True)(params)))
        value, vjp = jax.vjp(lambda p: loss(p, args), params)
        _check_loss_value(value)
        (grad,) = vjp(jnp.ones_like(value))
        return value, grad
    _check_loss_value(jax.eval_shape(loss, params, args))
    return optax.value_and_grad_from_state(loss)(params, args, state=opt_state)


def _loss_dtype(params0, args):
    """The dtype the loss history is kept in: that of the parameters and data."""
    leaves = [
        leaf
        for leaf in jtu.tree_leaves((params0, args))
        if eqx.is_inexact_array(leaf) and jnp.issubdtype(leaf.dtype, jnp.floating)
    ]
    with jax.numpy_dtype_promotion("standard"):
        return jnp.result_type(*leaves)


def _grad_norm(grad) -> Float[Array, ""]:
    return optax.tree.norm(grad)


def _evaluate_and_step(
    loss, optimizer, gtol, jac, steps, args, state: _State
) -> _State:
    """Evaluate the loss and gradient at the candidate; if finite, accept it and (if
    not converged and steps remain) take the optimizer's step to the next candidate."""

    def advance(state: _State) -> _State:
        value, grad = _value_and_grad(loss, state.candidate, args, state.opt_state, jac)
        value = value.astype(state.loss.dtype)
        finite = all_finite((state.candidate, value, grad))
        evaluations = state.evaluations + finite.astype(state.evaluations.dtype)
        first = state.evaluations == 0
        if gtol is None:
            converged = jnp.array(False)
            # Computed at the first evaluation only (a branch, not every step).
            first_grad_norm = jax.lax.cond(
                first,
                lambda: _grad_norm(grad).astype(state.first_grad_norm.dtype),
                lambda: state.first_grad_norm,
            )
        else:
            norm = _grad_norm(grad)
            converged = finite & (norm <= gtol.astype(norm.dtype))
            first_grad_norm = jnp.where(
                first, norm.astype(state.first_grad_norm.dtype), state.first_grad_norm
            )
        keep = lambda new, old: jtu.tree_map(
            lambda a, b: jnp.where(finite, a, b), new, old
        )
        accepted = _State(
            candidate=state.candidate,
            opt_state=state.opt_state,
            params=keep(state.candidate, state.params),
            loss=jnp.where(finite, value, state.loss),
            grad=keep(grad, state.grad),
            evaluations=evaluations,
            converged=converged,
            result=RESULTS.where(finite, state.result, RESULTS.nonfinite),
            first_grad_norm=first_grad_norm,
        )

        def update(s: _State) -> _State:
            if isinstance(optimizer, optax.GradientTransformationExtraArgs):
                extra = dict(
                    value=s.loss, grad=s.grad, value_fn=lambda p: loss(p, args)
                )
            else:
                extra = {}
            with _optax_promotion():
                updates, opt_state = optimizer.update(
                    s.grad, s.opt_state, s.params, **extra
                )
            candidate = optax.apply_updates(s.params, updates)
            candidate = jtu.tree_map(
                lambda c, p: c.astype(p.dtype), candidate, s.params
            )
            return eqx.tree_at(
                lambda t: (t.candidate, t.opt_state), s, (candidate, opt_state)
            )

        more = finite & ~converged & (evaluations <= steps)
        return jax.lax.cond(more, update, lambda s: s, accepted)

    return jax.lax.cond(_active(state, steps), advance, lambda s: s, state)


def _active(state: _State, steps) -> Bool[Array, ""]:
    return (
        (state.result == RESULTS.successful)
        & ~state.converged
        & (state.evaluations <= steps)
    )


@eqx.filter_jit
def _start(optimizer, params0, loss_dtype) -> _State:
    with _optax_promotion():
        opt_state = optimizer.init(params0)
    inf = jnp.array(jnp.inf, loss_dtype)
    zeros = jtu.tree_map(jnp.zeros_like, params0)
    return _State(
        candidate=params0,
        opt_state=opt_state,
        params=params0,
        loss=inf,
        grad=zeros,
        evaluations=jnp.zeros((), jnp.result_type(int)),
        converged=jnp.array(False),
        # A NaN or inf start is refused before the loss is evaluated.
        result=RESULTS.where(
            all_finite(params0), RESULTS.successful, RESULTS.invalid_input
        ),
        first_grad_norm=jnp.array(jnp.inf, _grad_norm(zeros).dtype),  # set at 1st
    )


@eqx.filter_jit
def _run_block(loss, optimizer, gtol, jac, block, steps, state, args):
    def body(state, _):
        state = _evaluate_and_step(loss, optimizer, gtol, jac, steps, args, state)
        return state, state.loss

    return jax.lax.scan(body, state, length=block)


def _diverged(state: _State, first_loss, params0) -> Bool[Array, ""]:
    """The fit ended worse than it started: the last loss exceeds the loss at
    `params0` by more than rounding, and the parameters moved by more than rounding
    (a start at an exact minimum, where the gradient is rounding noise, is not
    flagged). Normal training, noisy or not, ends below its start."""
    eps = jnp.finfo(state.loss.dtype).eps
    rise = state.loss - first_loss
    worse = rise > 8 * eps * (jnp.abs(first_loss) + jnp.abs(state.loss))
    moved = jtu.tree_map(lambda a, b: a - b.astype(a.dtype), state.params, params0)
    scale = optax.tree.norm(params0).astype(eps.dtype)
    moved = optax.tree.norm(moved).astype(eps.dtype) > jnp.sqrt(eps) * (1 + scale)
    return worse & moved


@eqx.filter_jit
def _finish(state: _State, losses, gtol, params0) -> FitResult:
    result = state.result
    # losses[0] is the loss at params0 (when finite; else the fit failed already).
    diverged = (result == RESULTS.successful) & _diverged(state, losses[0], params0)
    result = RESULTS.where(diverged, RESULTS.fit_diverged, result)
    if gtol is not None:
        result = RESULTS.where(
            (result == RESULTS.successful) & ~state.converged,
            RESULTS.nonlinear_max_steps_reached,
            result,
        )
    # A diverged fit returns `params0`, the better of its start and its end (keeping
    # the best parameters seen would cost a copy of them at every step).
    params = jtu.tree_map(
        lambda a, b: jnp.where(diverged, a.astype(b.dtype), b), params0, state.params
    )
    grad_norm = _grad_norm(state.grad)
    grad_norm = jnp.where(
        diverged, state.first_grad_norm.astype(grad_norm.dtype), grad_norm
    )
    return FitResult(
        params=params,
        losses=losses,
        grad_norm=grad_norm,
        steps=jnp.where(diverged, 0, jnp.maximum(state.evaluations - 1, 0)),
        result=result,
    )


def _fit_traced(loss, optimizer, gtol, jac, steps, params0, args) -> FitResult:
    state = _start(optimizer, params0, _loss_dtype(params0, args))
    state, losses = _run_block(
        loss, optimizer, gtol, jac, steps + 1, steps, state, args
    )
    return _finish(state, losses, gtol, params0)


def _fit_blocks(
    loss, optimizer, gtol, jac, steps, params0, args, progress, throw
) -> FitResult:
    state = _start(optimizer, params0, _loss_dtype(params0, args))
    # steps + 1 evaluations (the start and after each step), in blocks.
    block = min(steps + 1, _BLOCK)
    num_blocks = math.ceil((steps + 1) / block)
    history = []
    bar = progress_bar(progress, total=steps, desc="fit", unit="step")
    try:
        done = 0
        for _ in range(num_blocks):
            try:
                state, losses = _run_block(
                    loss, optimizer, gtol, jac, block, jnp.asarray(steps), state, args
                )
            except eqx.EquinoxRuntimeError:
                # A run-time error inside `loss` (a solve with `throw=True` that
                # failed): with `throw=False` the fit stops as for a non-finite loss.
                if throw:
                    raise
                state, losses = _until_error(
                    loss, optimizer, gtol, jac, steps, state, args
                )
                history.append(losses)
                break
            history.append(losses)
            taken = max(int(state.evaluations) - 1, 0)
            bar.update(taken - done)
            done = taken
            if not bar.disable:
                bar.set_postfix(loss=f"{float(state.loss):.6g}", refresh=True)
            if not bool(_active(state, steps)):
                break
    finally:
        bar.close()
    losses = jnp.concatenate(history)[: steps + 1]
    if losses.shape[0] < steps + 1:  # stopped early: the loss stays where it stopped
        pad = jnp.full((steps + 1 - losses.shape[0],), state.loss, losses.dtype)
        losses = jnp.concatenate([losses, pad])
    return _finish(state, losses, gtol, params0)


def _until_error(loss, optimizer, gtol, jac, steps, state, args):
    """The steps of a block that raised, again one at a time from its start `state`
    (the same evaluations: the loop is deterministic), up to the evaluation that
    raises: the state before it, marked `RESULTS.nonfinite` (its `params` are the
    last ones evaluated without error), and the losses of the steps that passed."""
    losses = [jnp.zeros((0,), state.loss.dtype)]
    while bool(_active(state, steps)):
        try:
            next_state, loss_value = _run_block(
                loss, optimizer, gtol, jac, 1, jnp.asarray(steps), state, args
            )
        except eqx.EquinoxRuntimeError:
            failed = RESULTS.where(jnp.array(True), RESULTS.nonfinite, state.result)
            state = eqx.tree_at(lambda s: s.result, state, failed)
            break
        state = next_state
        losses.append(loss_value)
    return state, jnp.concatenate(losses)
