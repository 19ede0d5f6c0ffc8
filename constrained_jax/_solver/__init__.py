"""The linear solvers of the library, one per module (as in `lineax/_solver/`):
Lineax solvers for the KKT matrices of extremization and of discretized functionals,
saddle-point solvers for constrained mechanics, and the nonlinear solvers of the KKT
residual (the protocol in `kkt_solver.py`, Newton and semismooth Newton)."""

from .automatic import Automatic as Automatic
from .block_tridiagonal import BorderedBlockTridiagonal as BorderedBlockTridiagonal
from .dense_lu import DenseLU as DenseLU
from .equilibrated_lu import EquilibratedDenseLU as EquilibratedDenseLU
from .full_kkt_lu import FullKKTLU as FullKKTLU
from .kkt_solver import AbstractKKTSolver as AbstractKKTSolver
from .minres import MINRES as MINRES
from .newton import Newton as Newton
from .range_space_ldl import RangeSpaceLDL as RangeSpaceLDL
from .saddle_point import (
    AbstractSaddlePointSolver as AbstractSaddlePointSolver,
    KKTForm as KKTForm,
    SaddlePointSystem as SaddlePointSystem,
)
from .semismooth_newton import SemismoothNewton as SemismoothNewton
from .sparse_schur import SparseSchur as SparseSchur
