"""``SolverOptions``: the implicit solve's options, one frozen object (``_solve`` reads them)."""

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class SolverOptions:
    """The implicit solve's options: one frozen, hashable object (a static argument under
    ``jax.jit``), passed as ``solver=`` to ``step``, ``integrate``, ``sweep`` and
    ``amplification_matrix``. ``integrate`` reads ``tolerance`` as a value of its program, so a
    run with another tolerance compiles nothing new; another value of any other field does. ``max_newton_iterations=`` and ``krylov=`` there are shorthands
    for the first two fields (``solver_from``). Units: "unknowns" are the entries of one
    element's unknown Z (k * 2d for cG(k), (k + 1) * 2d for dG(k)); "iterations" are updates
    of Z; "elements" are time elements.

    The first group decides what a member may return (correctness); the rest only how fast it
    gets there (speed): whatever their values, an element is accepted by the stopping rule
    (``_converged``) alone, and no value of them changes a root beyond round-off. The defaults
    suit most runs; the speed fields are for studies of the solver
    ([The implicit solve](solver.md)).

    Attributes:
        max_iterations: the iterations per element after which a member fails with status 1;
            default 48. The fixed-point iteration counts in blocks (``fixed_point_block``,
            ``first_block``), so a cap is rounded up to a block's end there.
        krylov: solve systems of more than ``dense_limit`` unknowns by Newton with GMRES on
            Jacobian-vector products; default False, the fixed point only there. A stiff large
            system (h omega >~ 1) needs it; it compiles a larger program.
        noise: the multiple of eps (of the dtype) below which updates of the state are round-off;
            default 100. Such updates may stop shrinking without that meaning a slow matrix; the
            stopping rule reads it.
        tolerance: the error of an element's unknowns, relative to their size, at which it stops
            iterating; default 0, their round-off (eps). Above eps the iteration error, below
            ``tolerance`` after the last update, adds to every element's error, and
            systematically (the predictor's miss is smooth from element to element): the
            conserved quantities of a method (energy, symplecticity, momentum) then hold to about
            that per element, not to round-off. For runs whose target error is far above
            round-off ([Iterating to a tolerance](solver.md#iterating-to-a-tolerance)).
        dense_limit: the largest system, in unknowns, that keeps a dense Newton matrix; default
            256. Such a matrix costs n^2 memory per member and an n^3 inverse per refresh; above
            the limit Newton is Newton-Krylov.
        small: the largest system, in unknowns, treated as small; default 32. Small systems solve
            their first element by Newton (the predictor has no history yet and a Newton update
            costs two to three fixed-point ones), stay with Newton once switched, and refresh
            their matrix at a low rate; under a ``PIDController`` (h changes in every element)
            and in a time-transformed run (its matrices serve few elements:
            ``_solve.Options.short_lived_matrices``) only the first.
        sweep_dimension: the number of degrees of freedom d above which partitioned methods
            iterate the Gauss-Seidel sweep's residual on a separable H
            (``_march.element_residual``); default 8. The sweep contracts at the square of the
            plain fixed point's rate there; below it the sweep's two half-residuals cost more
            than its rate saves. Any other H keeps the plain residual.
        theta_fixed_point: the rate (shrink factor per update) above which a fixed-point member
            switches to Newton; default 0.5.
        theta_newton: the rates above which a Newton member refreshes its matrix, for small and
            large systems; default (0.03, 0.25). A small system's refresh is cheap, a large
            one's costs an n^3 inverse.
        patience: the iterations with one Newton matrix in one element after which a member
            refreshes it, however it contracts; default 8.
        fixed_point_patience: the iterations in one element after which a fixed-point member
            switches to Newton, for small and large systems; default (12, 24). At most half of
            ``max_iterations`` (``fixed_point_patience_for``), so that Newton is always reached.
        newton_stretch: the elements a large system that switched to Newton stays with it before
            it tries the fixed point again; default 16. One hard element does not cost it the
            run; under a controller or a time transformation, where h or the state moves on
            fast, only while its matrix serves: an element of the stretch that needs a fresh one
            ends it.
        attempt_matrices: the fresh dense Newton matrices an attempt under a ``PIDController``
            may take; default 2 (Newton-Krylov directions are not counted). One that asks for
            another fails (status 1), and the controller retries it with a shorter h: a step the
            fixed point cannot take and Newton needs more matrices for is a step too long, and a
            shorter attempt costs less than more matrices at this one, which from the continued
            polynomial often end at another root of the element equations or at
            ``max_iterations``. Every step of the watchdog (``watch``) and every damped step asks
            for a fresh matrix, so under a controller they get at most this many.
        fixed_point_block: the fixed-point updates per convergence check; default 2 (a check
            costs more kernels than an update).
        first_block: the updates of the first block of an element of more than ``small``
            unknowns; default 4 (it needs four to six updates; the check after two never
            accepts).
        stragglers: the share, 1 / ``stragglers``, of a batch's slowest members that iterate
            apart, gathered; default 8. It applies to batches of at least ``8 * stragglers``
            members, so that a batch does not pay for its slowest members.
        refresh_share: a batch of B members refreshes at most ``max(8, B // refresh_share)``
            matrices per iteration; default 8 (gathered, so the work follows the members that
            ask).
        watch: the watchdog's allowance of Newton steps that raise the residual again; default 4.
            In an element whose predictor is the constant guess (a run's first, ``step``), a full
            Newton step with a fresh matrix that raises the residual is taken anyway, and so are
            the fresh steps after it until the residual is below where it started, of which at
            most ``watch`` may raise it again; then the steps are halved for the rest of the
            element (far from the root, plain Newton's first step can raise the residual and
            still lead to the root in a few more). 0: halving from the first such step.
        min_damping: the smallest fraction of a Newton step tried before the step is taken as it
            is (halving from 1); default 1/64.
        doubtful_start: the residual, as a fraction of the unknowns, at or above which a
            predictor competes with the constant guess; default 0.1 (a continued polynomial can
            overshoot at large h omega).
        miss_orders: the orders of extrapolation of the predictor's misses it chooses from
            (``_march.miss_correction``; one or more, the lowest first); default (2, 6). The high
            one serves where the misses are smooth, the low one where they are not.
        krylov_tolerance: GMRES's relative residual; default 1e-7. Each update leaves this much
            of the error, so the updates reach the floor in two or three.
        krylov_restart: GMRES's restart length; default 20.
        krylov_restarts: GMRES's number of restarts; default 10.
        explicit: compute an element in closed form, without iteration, where the method has an
            explicit form for the structure read from H (``gj.structure``); default True. E.g.
            ``GalerkinVI(1, gj.trapezoid())`` on a separable H is Stormer-Verlet
            ([Explicit elements](methods.md#explicit-elements-and-compositions)). The same root
            to round-off; False iterates it as any other.
    """

    max_iterations: int = 48
    krylov: bool = False
    noise: float = 100.0
    tolerance: float = 0.0
    dense_limit: int = 256
    small: int = 32
    sweep_dimension: int = 8
    theta_fixed_point: float = 0.5
    theta_newton: tuple = (0.03, 0.25)
    patience: int = 8
    fixed_point_patience: tuple = (12, 24)
    newton_stretch: int = 16
    attempt_matrices: int = 2
    fixed_point_block: int = 2
    first_block: int = 4
    stragglers: int = 8
    refresh_share: int = 8
    watch: int = 4
    min_damping: float = 1.0 / 64
    doubtful_start: float = 0.1
    miss_orders: tuple = (2, 6)
    krylov_tolerance: float = 1e-7
    krylov_restart: int = 20
    krylov_restarts: int = 10
    explicit: bool = True

    def __post_init__(self):
        for name in ("max_iterations", "dense_limit", "small", "sweep_dimension", "patience", "newton_stretch",
                     "attempt_matrices",
                     "fixed_point_block", "first_block", "stragglers", "refresh_share", "krylov_restart",
                     "krylov_restarts"):
            _check_count(name, getattr(self, name), 1)
        _check_count("watch", self.watch, 0)
        for name in ("theta_newton", "fixed_point_patience", "miss_orders"):
            value = getattr(self, name)
            if not isinstance(value, tuple) or len(value) != 2 and name != "miss_orders" or not value:
                raise ValueError(f"SolverOptions.{name} must be a tuple of two values (miss_orders: of one "
                                 f"or more), got {value!r}.")
        for name in ("fixed_point_patience", "miss_orders"):
            for value in getattr(self, name):
                _check_count(name, value, 1)
        for name in ("noise", "theta_fixed_point", "min_damping", "doubtful_start", "krylov_tolerance") + (
                "theta_newton",):
            values = getattr(self, name) if name == "theta_newton" else (getattr(self, name),)
            if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0 for v in values):
                raise ValueError(f"SolverOptions.{name} must be positive, got {getattr(self, name)!r}.")
        if isinstance(self.tolerance, bool) or not isinstance(self.tolerance, (int, float)) or not (
                0.0 <= self.tolerance < 1.0):
            raise ValueError(f"SolverOptions.tolerance must be a number in [0, 1), got {self.tolerance!r}.")
        for name in ("krylov", "explicit"):
            if not isinstance(getattr(self, name), bool):
                raise TypeError(f"SolverOptions.{name} must be a bool, got {getattr(self, name)!r}.")

    def fixed_point_patience_for(self, large):
        """Iterations a fixed-point member of a small (False) or large (True) system takes in
        one element before it switches to Newton: at most half the cap."""
        return max(1, min(self.fixed_point_patience[int(large)], self.max_iterations // 2))


def _check_count(name, value, least):
    if isinstance(value, bool) or not isinstance(value, int) or value < least:
        raise ValueError(f"SolverOptions.{name} must be an integer >= {least}, got {value!r}.")


def solver_from(solver=None, max_newton_iterations=None, krylov=None):
    """The ``SolverOptions`` of an entry point's ``solver=`` and its shorthands: the one place
    they are built. A shorthand given replaces its field of ``solver`` (default options where
    None)."""
    if solver is None:
        solver = SolverOptions()
    elif not isinstance(solver, SolverOptions):
        raise TypeError(f"solver must be a galerkin_jax.SolverOptions, got {type(solver).__name__}.")
    changes = {}
    if max_newton_iterations is not None:
        value = max_newton_iterations
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"max_newton_iterations must be an integer >= 1, got {value!r}.")
        changes["max_iterations"] = int(value)
    if krylov is not None:
        changes["krylov"] = bool(krylov)
    return dataclasses.replace(solver, **changes) if changes else solver
