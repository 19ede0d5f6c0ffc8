"""The linear solvers of the library, one per module (as in `lineax/_solver/`):
Lineax solvers for the KKT matrices of extremization and of discretized functionals,
saddle-point solvers for constrained mechanics, and the nonlinear solvers of the KKT
residual (the protocol in `kkt_solver.py`, Newton and semismooth Newton)."""

from .block_tridiagonal import BorderedBlockTridiagonal as BorderedBlockTridiagonal
from .dense_lu import DenseLU as DenseLU
from .equilibrated_lu import EquilibratedDenseLU as EquilibratedDenseLU
from .kkt_solver import AbstractKKTSolver as AbstractKKTSolver
from .minres import MINRES as MINRES
from .newton import Newton as Newton
from .saddle_point import (
    AbstractSaddlePointSolver as AbstractSaddlePointSolver,
    Automatic as Automatic,
    FullKKTLU as FullKKTLU,
    RangeSpaceLDL as RangeSpaceLDL,
)
from .semismooth_newton import SemismoothNewton as SemismoothNewton
from .sparse_schur import SparseSchur as SparseSchur
