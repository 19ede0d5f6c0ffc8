"""The default saddle-point solver, chosen at trace time from the structure and size
of the system ([`constrained_jax.Automatic`][])."""

import numpy as np

from .diagonal import coupled_columns, diagonal_solve, is_diagonal
from .full_kkt_lu import FullKKTLU
from .range_space_ldl import RangeSpaceLDL
from .saddle_point import AbstractSaddlePointSolver, KKTForm, SaddlePointSystem
from .sparse_schur import SparseSchur


class Automatic(AbstractSaddlePointSolver):
    """The default: a method chosen at trace time from the structure and size.

    - `n + k <= unroll_max` with a structurally diagonal `M` (Cartesian coordinates,
        the scenes' pendulum and cylinders): the range-space method with the
        reciprocals of the masses, unrolled on the nonzeros of `A`
        (`constrained_jax._solver.diagonal`; under `jax.vmap` about as fast as
        hand-written equations). A mass that vanishes at run time while `A` couples
        it (the rolling cylinder with `I = 0`) is solved by `RangeSpaceLDL` instead,
        for the whole batch, and only when some state of the batch needs it.
    - other `n + k <= unroll_max`: [`constrained_jax.RangeSpaceLDL`][], unrolled on
        the nonzeros of the detected patterns (fused under `jax.vmap`; the fastest
        for the small systems of the scenes).
    - larger, with a mass matrix that is block diagonal with a structurally nonzero
        diagonal (Cartesian and maximal coordinates, e.g. `scenes.chain`): the sparse
        range-space method [`constrained_jax.SparseSchur`][], whose cost follows the
        nonzeros.
    - otherwise: [`constrained_jax.FullKKTLU`][] with LAPACK's LU.

    Every choice reports singular systems (never a wrong answer). The unrolled
    `RangeSpaceLDL` also solves free gauge directions (a massless coordinate that
    nothing couples to); `FullKKTLU` solves those along a coordinate; `SparseSchur`
    needs every mass pivot nonzero at run time and reports a zero mass (set through
    `args`, say) as singular: pass `saddle_point_solver=cjax.FullKKTLU()` for such
    systems. For an indefinite `M` (not a kinetic energy) choose `FullKKTLU()`
    explicitly.

    The threshold `unroll_max = 6` is where the unrolled solve stops being the faster
    one for a single trajectory (`benchmarks/chain.py`); for large batches of
    mid-sized systems pass `RangeSpaceLDL()` (unrolled up to 12).

    **Arguments:**

    - `unroll_max`: the largest `n + k` solved by the unrolled elimination.
    """

    unroll_max: int = 6

    def form(self, n: int, k: int) -> KKTForm:
        # Above `unroll_max`: `SparseSchur` or LAPACK's LU, on arrays.
        return KKTForm(sparse=True, unroll=n + k <= self.unroll_max)

    def choose(self, system: SaddlePointSystem) -> AbstractSaddlePointSolver:
        """The solver used for `system` (besides the diagonal fast path, which falls
        back on it): from the static patterns and sizes."""
        if system.n + system.k <= self.unroll_max:
            return RangeSpaceLDL(unroll_max=self.unroll_max)
        if not system.mass.is_dense and _block_diagonal(system.mass.pattern()):
            return SparseSchur()
        return FullKKTLU(unroll_max=0)

    def solve(self, system, fill):
        general = self.choose(system)
        if not self._diagonal_fast_path(system):
            return general.solve(system, fill)

        def general_solve(mass, jac, rhs, bias, active):
            return general.solve(
                SaddlePointSystem(mass, jac, rhs, bias, active=active), fill
            )

        return diagonal_solve(
            system.mass,
            system.jac,
            system.rhs,
            system.bias,
            general_solve,
            fill,
            system.active,
        )

    def _diagonal_fast_path(self, system: SaddlePointSystem) -> bool:
        """Whether the unrolled diagonal range-space method applies: a structurally
        diagonal `M` whose every diagonal entry that `A` couples is structurally
        nonzero, with `n + k <= unroll_max`."""
        n, mass = system.n, system.mass
        if n + system.k > self.unroll_max or not is_diagonal(mass):
            return False
        present = np.zeros((n,), bool)
        present[list(mass.rows)] = True
        return bool(np.all(present | ~coupled_columns(system.jac, n)))


def _block_diagonal(pattern: np.ndarray) -> bool:
    """Whether a symmetric pattern is block diagonal (its connected components are
    contiguous ranges of indices, each block not larger than 6) with a nonzero
    diagonal. Dense blocks are assumed (each is factored as a whole)."""
    n = pattern.shape[0]
    if not np.all(np.diagonal(pattern)):
        return False
    start = 0
    while start < n:
        end = start + 1
        while end < n and np.any(pattern[start:end, end:]):
            reach = np.nonzero(np.any(pattern[start:end], axis=0))[0]
            end = int(reach.max()) + 1
        if end - start > 6:
            return False
        start = end
    return True
