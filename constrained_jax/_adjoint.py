"""The adjoint of [`constrained_jax.simulate`][] when the user does not choose one.

`simulate(..., adjoint=None)` (the default) calls `default_adjoint`, the one place
where the adjoint is chosen per case. What was measured (`benchmarks/gradients.py`,
two cylinders, `theta0 = 0.3`, Tsit5, `rtol = atol = 1e-8`), and why the choice is
what it is:

- `diffrax.RecursiveCheckpointAdjoint()`: with `checkpoints=None` diffrax sizes the
    checkpoints from `max_steps` (`O(sqrt(max_steps))`: 180 for `max_steps=16384`).
    The attached run takes 16 steps and the release run 35 over its phases, so every
    step is stored and computed once more in the backward pass; 16, 40 or 180
    checkpoints give the same time for the attached run, and 1,365 (every step of a
    long run of a small system) makes the release run 1.6x slower (larger buffers per
    phase). The cost of the gradient (about 6x the solve attached, 6x-16x through
    the release) is the reverse pass of each step itself: the Hessians and KKT solves
    of seven stages and the loop bookkeeping, not recomputation. So diffrax's default
    count is kept.
- `diffrax.BacksolveAdjoint` (the continuous adjoint) cannot be used: `simulate`
    saves through `diffrax.SaveAt(subs=...)` and stops at events (the release),
    neither of which it supports; nor are its gradients those of the discrete solve.
- `diffrax.ForwardMode()`: a forward-mode tangent of the attached run (`jax.jvp`)
    costs about 1.5x the solve, against about 6x for `jax.grad` in reverse mode. For
    derivatives with respect to one or a few parameters, pass
    `adjoint=diffrax.ForwardMode()` and use `jax.jvp` or `jax.jacfwd`.
"""

import diffrax


def default_adjoint(
    adjoint: diffrax.AbstractAdjoint | None,
) -> diffrax.AbstractAdjoint:
    """`adjoint` itself if given; otherwise the adjoint chosen for this case
    (`diffrax.RecursiveCheckpointAdjoint()`, see the module's docstring).

    **Arguments:**

    - `adjoint`: the user's diffrax adjoint, or `None`.

    **Returns:** a diffrax adjoint.
    """
    if adjoint is None:
        return diffrax.RecursiveCheckpointAdjoint()
    if not isinstance(adjoint, diffrax.AbstractAdjoint):
        raise ValueError(
            "`adjoint` must be a diffrax adjoint, e.g. "
            "`diffrax.RecursiveCheckpointAdjoint()` or `diffrax.ForwardMode()`, or "
            f"`None` (chosen per case), got {type(adjoint).__name__}."
        )
    return adjoint
