"""Wrapping a diffrax solver: the base of `ProjectedSolver` and of the release watch.

`diffrax.diffeqsolve` adjusts a bare solver before it runs it (an implicit solver's
root-finder tolerances from the step-size controller, a Runge-Kutta solver's
`scan_kind` for the adjoint). Through a wrapper it cannot, so `prepare_to_wrap` does it
first; [`AbstractForwardingSolver`][] then forwards everything but `init` and `step` to
the wrapped solver.
"""

import functools

import diffrax
import equinox as eqx


@functools.cache
def _stepsize_tol():
    """diffrax's "take it from the step-size controller" marker: the `rtol` of a
    root finder made by the public `diffrax.with_stepsize_controller_tols` (the
    default of diffrax's implicit solvers)."""
    return diffrax.with_stepsize_controller_tols(diffrax.VeryChord)().rtol


def _is_stepsize_tol(value) -> bool:
    """Whether a root finder's `rtol`/`atol`/`norm` is diffrax's "take it from the
    step-size controller" marker. `diffeqsolve` replaces it for a bare implicit
    solver only, so a wrapper must do the same (`_resolve_implicit_tolerances`;
    tests/test_simulate.py::test_projection_with_an_implicit_solver)."""
    return value is _stepsize_tol()


def _resolve_implicit_tolerances(solver, stepsize_controller):
    """Give an implicit solver's root finder the step-size controller's tolerances, as
    `diffrax.diffeqsolve` does for a bare implicit solver."""
    if not isinstance(solver, diffrax.AbstractImplicitSolver) or not isinstance(
        stepsize_controller, diffrax.AbstractAdaptiveStepSizeController
    ):
        return solver
    names = [
        name
        for name in ("rtol", "atol", "norm")
        if _is_stepsize_tol(getattr(solver.root_finder, name))
    ]
    if not names:
        return solver
    return eqx.tree_at(
        lambda s: tuple(getattr(s.root_finder, name) for name in names),
        solver,
        tuple(getattr(stepsize_controller, name) for name in names),
    )


def _fix_scan_kind(solver, adjoint):
    """Set a Runge-Kutta solver's `scan_kind` before wrapping it.

    diffrax's adjoints set `scan_kind` (for forward-mode autodiff through the stages)
    on a Runge-Kutta solver whose `scan_kind` is `None`, with `eqx.tree_at`; diffrax
    forwards `isinstance` through a wrapped solver, so it would try that on the
    wrapper, which has no such field. Setting it on the inner solver, as the adjoint
    would, keeps the wrapper out of it (the wrappers forward `scan_kind`)."""
    rk = (diffrax.AbstractRungeKutta, diffrax.AbstractSRK)
    if isinstance(solver, rk) and getattr(solver, "scan_kind", "") is None:
        kind = "lax" if isinstance(adjoint, diffrax.ForwardMode) else "bounded"
        solver = eqx.tree_at(
            lambda s: s.scan_kind, solver, kind, is_leaf=lambda x: x is None
        )
    return solver


def prepare_to_wrap(
    solver: diffrax.AbstractSolver,
    stepsize_controller: diffrax.AbstractStepSizeController,
    adjoint: diffrax.AbstractAdjoint,
) -> diffrax.AbstractSolver:
    """`solver` with what `diffrax.diffeqsolve` would set on it itself, done before it
    is wrapped (diffrax cannot reach into a wrapper). Wrapping twice is fine: a solver
    already prepared is returned as it is."""
    solver = _fix_scan_kind(solver, adjoint)
    return _resolve_implicit_tolerances(solver, stepsize_controller)


class AbstractForwardingSolver(diffrax.AbstractWrappedSolver):
    """A diffrax solver around `solver` that changes only `init` and `step`: the rest
    of the solver protocol is forwarded to `solver`.

    Build one around `prepare_to_wrap(solver, ...)`.
    """

    solver: eqx.AbstractVar[diffrax.AbstractSolver]

    @property
    def term_structure(self):
        return self.solver.term_structure

    @property
    def scan_kind(self):
        return getattr(self.solver, "scan_kind", None)

    @property
    def root_finder(self):
        # diffrax forwards `isinstance(..., AbstractImplicitSolver)` to the wrapped
        # solver and then reads `root_finder`; `prepare_to_wrap` has already filled in
        # its tolerances.
        return self.solver.root_finder  # pyright: ignore

    @property
    def interpolation_cls(self):  # pyright: ignore
        return self.solver.interpolation_cls

    @property
    def term_compatible_contr_kwargs(self):
        return self.solver.term_compatible_contr_kwargs

    def order(self, terms):
        return self.solver.order(terms)

    def strong_order(self, terms):
        return self.solver.strong_order(terms)

    def error_order(self, terms):
        return self.solver.error_order(terms)

    def func(self, terms, t0, y0, args):
        return self.solver.func(terms, t0, y0, args)
