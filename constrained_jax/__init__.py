"""constrained_jax: constrained extremization, variational problems and mechanics.

Write a function (or a Lagrangian) as plain JAX; the library builds the saddle-point
(KKT) system by autodiff and solves it. See `README.md` and the documentation
site (`docs/`, its architecture page for the design).
"""

import importlib.metadata

from . import plot as plot, scenes as scenes, settings as settings
from ._compilation_cache import (
    enable_compilation_cache as enable_compilation_cache,
)
from ._constraints import (
    AbstractConstraint as AbstractConstraint,
    Coulomb as Coulomb,
    Holonomic as Holonomic,
    Pfaffian as Pfaffian,
    Unilateral as Unilateral,
)
from ._contact import Events as Events
from ._discretization import (
    AbstractDiscretization as AbstractDiscretization,
    Chebyshev as Chebyshev,
    Graded as Graded,
    PiecewiseLinear as PiecewiseLinear,
)
from ._extremize import (
    extremize as extremize,
    EXTREMUM as EXTREMUM,
    Extremum as Extremum,
)
from ._fit import fit as fit, FitResult as FitResult
from ._functional import (
    euler_lagrange as euler_lagrange,
    first_integral as first_integral,
    Functional as Functional,
    FunctionalMultipliers as FunctionalMultipliers,
    FunctionalSolution as FunctionalSolution,
    IntegralConstraint as IntegralConstraint,
    MultiplierFunction as MultiplierFunction,
    solve_functional as solve_functional,
)
from ._integrability import (
    exterior_derivative as exterior_derivative,
    integrate_pfaffian as integrate_pfaffian,
    is_exact as is_exact,
    is_integrable as is_integrable,
)
from ._misc import publish as _publish
from ._reduce import (
    Linearization as Linearization,
    linearize as linearize,
    reduce as reduce,
    Reduction as Reduction,
)
from ._results import RESULTS as RESULTS
from ._shooting import solve_shooting as solve_shooting
from ._simulate import (
    consistent_initial_state as consistent_initial_state,
    Release as Release,
    SaveAt as SaveAt,
    simulate as simulate,
    Trajectory as Trajectory,
)
from ._solver import (
    AbstractKKTSolver as AbstractKKTSolver,
    AbstractSaddlePointSolver as AbstractSaddlePointSolver,
    Automatic as Automatic,
    BorderedBlockTridiagonal as BorderedBlockTridiagonal,
    DenseLU as DenseLU,
    EquilibratedDenseLU as EquilibratedDenseLU,
    FullKKTLU as FullKKTLU,
    KKTForm as KKTForm,
    MINRES as MINRES,
    Newton as Newton,
    RangeSpaceLDL as RangeSpaceLDL,
    SaddlePointSystem as SaddlePointSystem,
    SemismoothNewton as SemismoothNewton,
    SparseSchur as SparseSchur,
)
from ._stabilization import (
    AbstractStabilization as AbstractStabilization,
    Baumgarte as Baumgarte,
    Projection as Projection,
    Unstabilized as Unstabilized,
)
from ._sweep import sweep as sweep
from ._system import LagrangianSystem as LagrangianSystem
from ._variational_integrator import (
    AbstractDiscreteLagrangian as AbstractDiscreteLagrangian,
    AbstractVariationalIntegrator as AbstractVariationalIntegrator,
    integrate_variational as integrate_variational,
    Midpoint as Midpoint,
    Trapezoidal as Trapezoidal,
    VariationalIntegrator as VariationalIntegrator,
    VariationalState as VariationalState,
    VariationalTrajectory as VariationalTrajectory,
)


_publish(globals(), __name__)

try:
    __version__ = importlib.metadata.version("constrained_jax")
except importlib.metadata.PackageNotFoundError:  # a source tree on `PYTHONPATH`
    __version__ = "0+unknown"
