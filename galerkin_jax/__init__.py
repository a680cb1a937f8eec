"""galerkin_jax: Galerkin time finite elements and variational integrators for Hamiltonian systems.

References: [GBS] Gross, Betsch, Steinmann, Comparison of Galerkin methods applied to
classical mechanics; [Tang] W. Tang, Two types of variational integrators and their
equivalence.
"""

__version__ = "0.2.0"  # the version in pyproject.toml (the docs build checks they agree)

from ._controllers import (
    Event as Event,
    Events as Events,
    PIDController as PIDController,
    TimeTransform as TimeTransform,
)
from ._output import DenseOutput as DenseOutput
from ._composition import Composition as Composition
from ._splitting import Splitting as Splitting
from ._tao import Tao as Tao
from ._structure import Structure as Structure, structure as structure
from ._explicit import UndecidedStructureWarning as UndecidedStructureWarning
from ._galerkin import CG as CG, DG as DG
from ._method import AbstractMethod as AbstractMethod
from ._pytree import pytree_dataclass as pytree_dataclass
from ._integrate import (
    Solution as Solution,
    amplification_matrix as amplification_matrix,
    integrate as integrate,
    step as step,
)
from ._midpoint import DiscreteGradient as DiscreteGradient, ModifiedMidpoint as ModifiedMidpoint
from ._solve import (
    SolverError as SolverError,
    SolverOptions as SolverOptions,
    Status as Status,
    status_message as status_message,
)
from ._accuracy import suggest_step_size as suggest_step_size
from ._cache import use_compilation_cache as use_compilation_cache
from ._checks import Float32Warning as Float32Warning
from ._configs import Configs as Configs, grid as grid, pad_rule as pad_rule, stack_methods as stack_methods
from ._sweep import SweepResult as SweepResult, sweep as sweep
from ._tune import (
    asymmetry as asymmetry,
    params_from_rule as params_from_rule,
    rule_from_params as rule_from_params,
    tune_rule as tune_rule,
)
from ._variational import GalerkinVI as GalerkinVI, LagrangianVI as LagrangianVI
from ._quadrature import (
    QuadratureRule as QuadratureRule,
    gauss_legendre as gauss_legendre,
    gauss_lobatto as gauss_lobatto,
    gauss_radau as gauss_radau,
    midpoint as midpoint,
    trapezoid as trapezoid,
)

__all__ = [
    "AbstractMethod",
    "CG",
    "Composition",
    "Configs",
    "DG",
    "DenseOutput",
    "DiscreteGradient",
    "Event",
    "Events",
    "Float32Warning",
    "GalerkinVI",
    "LagrangianVI",
    "ModifiedMidpoint",
    "PIDController",
    "QuadratureRule",
    "Solution",
    "SolverError",
    "SolverOptions",
    "Splitting",
    "Status",
    "Structure",
    "SweepResult",
    "Tao",
    "TimeTransform",
    "UndecidedStructureWarning",
    "amplification_matrix",
    "asymmetry",
    "gauss_legendre",
    "gauss_lobatto",
    "gauss_radau",
    "grid",
    "integrate",
    "midpoint",
    "pad_rule",
    "params_from_rule",
    "pytree_dataclass",
    "rule_from_params",
    "stack_methods",
    "status_message",
    "suggest_step_size",
    "step",
    "structure",
    "sweep",
    "trapezoid",
    "tune_rule",
    "use_compilation_cache",
]
