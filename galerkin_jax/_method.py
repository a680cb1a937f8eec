"""The method protocol: every member of a method object that the solver reads (``AbstractMethod``).

A method maps one element's start state ``(q0, p0)`` and step size ``h`` to its unknowns
``Z`` (the root of ``residual``), and ``Z`` to the end state, the element polynomial and
an estimate of the local error. ``step``, ``integrate``, ``sweep`` and
``amplification_matrix`` use these members and nothing else, so a new method is one class
in one file; docs/methods_protocol.md walks through one.
"""

import abc
import dataclasses
import inspect

import jax
import jax.numpy as jnp
import numpy as np

from ._defect import local_error
from ._quadrature import QuadratureRule

MEMBERS = ("initial_guess", "residual", "increment", "polynomial", "local_error")


class AbstractMethod(abc.ABC):
    """A time-stepping method as the solver sees it: subclass it and decorate the subclass
    with ``@gj.pytree_dataclass``.

    Conventions of every member:
        ``H``: the user's function with ``args`` bound, ``H(q, p) -> scalar`` (``L(q, qdot)``
        for a method given a Lagrangian). ``q0, p0``: the element's start state, shape
        ``(d,)``, one float dtype. ``h``: the step size, a scalar that may be traced.
        ``Z``: the element's unknowns, an array of a shape the method fixes for a given d
        (its size n is the number of unknowns). Best are increments from the start state
        (e.g. ``z^h - z0``): they are accurate relative to themselves, and zero is the
        constant guess.

    Every member is a pure JAX function of its arguments (it is traced under ``jit``,
    ``vmap`` and ``grad``). The object is a pytree: its array fields (e.g. a quadrature
    rule) are leaves that may be traced, stacked by ``gj.stack_methods`` for a sweep and
    differentiated; fields declared static (``dataclasses.field(metadata=dict(static=True))``,
    e.g. a degree) are compile-time constants. ``__post_init__`` runs again on every
    unflatten, so it may check static fields only.

    Attributes:
        fixed_point: a Python bool. True where ``dR/dZ`` at ``h = 0`` is the identity, so that
            ``Z <- Z - R(Z)`` contracts for small h; the solver then starts every element
            with that iteration (no matrix) and turns to Newton where it is slow. False (the
            default, always safe): Newton on every element, with a dense matrix up to 256
            unknowns and Newton-Krylov above. A wrong True costs iterations, and above 256
            unknowns without ``krylov=True`` it fails with status 1.
        partition_axis: None (the default), or the axis along which ``Z`` is the
            concatenation of a q half and a p half of equal shape; then ``residual(...,
            part="q")`` and ``part="p"`` must return the equations of each half alone (those
            whose ``h = 0`` Jacobian is the identity on that half). A method with a fixed
            point on a separable H of more than ``SolverOptions.sweep_dimension`` (8) degrees of
            freedom is then solved through the Gauss-Seidel sweep of the two halves, which
            contracts at the square of the plain rate (``_march.element_residual``).
        settle: a Python int, 0 by default: the fixed-point updates, one residual each, that
            an element the fixed-point iteration accepted takes after its polish. The stopping
            rule leaves an iteration error below the round-off of ``Z`` that follows the
            predictor's smooth miss: where a method conserves a quantity to a small fraction of
            round-off a step, that error's part in it adds up over a long run.
            ``DiscreteGradient`` takes 1 ([Round-off](accuracy.md#round-off)).
        hamiltonian: a Python bool, True by default: the function the method is given is a
            Hamiltonian, whose field refines the element polynomial between the nodes (save
            times, events, dense output: ``_output.refined``); False for a method given a
            Lagrangian, whose polynomial is read as it is.
        embedded_alpha: a Python float in [0, 1], 1 by default: where in the element the
            embedded estimate (a ``PIDController``'s, and the default ``error_estimate``'s choice
            of elements) takes the defect of the polynomial (``_controllers.embedded_error``). A
            polynomial that matches Hamilton's field at the element's end has no defect there:
            compositions and splittings, whose polynomial is that Hermite cubic, take 1/4.

    Optional members (``_explicit``): ``explicit_form(structure)`` returns, for the structure
    of H that ``gj.structure`` read, a method whose element has a closed form, or None; that
    method has ``explicit_start(H, q0, p0) -> memo`` and ``explicit(H, q0, p0, h, memo) ->
    (Z, (dq, dp), memo)``, Z the root of its ``residual``, memo what one element hands the
    next (Stormer-Verlet: the force), and ``explicit_field(H, q1, p1, memo)``, Hamilton's field
    at the element's end from that memo (the embedded estimate's evaluation). Runs and
    ``step`` then call ``explicit`` instead of the solver.
    """

    fixed_point = False
    partition_axis = None
    settle = 0
    hamiltonian = True
    embedded_alpha = 1.0

    @abc.abstractmethod
    def initial_guess(self, q0, p0, previous=None, ratio=None):
        """The first iterate of an element's unknowns.

        Args:
            q0, p0: the element's start state, shape ``(d,)``.
            previous: None for the constant guess (the state held still: zero increments),
                or ``(q_prev, p_prev, Z_prev)``, the previous element's start state and
                unknowns, from which a method may continue its polynomial one element ahead
                (a better predictor: fewer iterations). On a run's first element it is
                ``(q0, p0, initial_guess(q0, p0))``. Ignoring it is correct, only slower.
            ratio: None where the element is as long as the previous one; else (adaptive
                steps) the ratio of its length to the previous one's, a traced scalar, over
                which the continuation should reach. A method without this parameter is
                continued over its own length (``_march.continued``).
        Returns:
            ``Z0``, the unknowns' shape, in ``q0``'s dtype.
        """

    @abc.abstractmethod
    def residual(self, H, q0, p0, Z, h, part=None):
        """The element equations: ``R(Z) = 0`` at the element's solution.

        Args:
            Z: the unknowns.
            part: only for a method with a ``partition_axis``: "q" or "p", the equations of
                that half of ``Z`` alone (their shape is that half's); None: all of them.
        Returns:
            ``R``, the shape of ``Z`` (of its half with ``part``). Its derivatives in ``Z``
            and in everything else give the Newton matrix and, by the implicit function
            theorem, every gradient through the solve.
        """

    @abc.abstractmethod
    def increment(self, H, q0, p0, Z, h):
        """``(dq, dp) = (q1 - q0, p1 - p0)``, each shape ``(d,)``: the element's end state less
        its start. The run adds the increments with compensated summation."""

    @abc.abstractmethod
    def polynomial(self, H, q0, p0, Z, h):
        """The element polynomial (dense output): ``W`` of shape ``(m, 2d)``, m >= 1 fixed by
        the method, with ``z^h(alpha) - z0 = sum_j W_j P_j(2 alpha - 1)`` for alpha in
        [0, 1], P_j the Legendre polynomials and columns ``(q | p)``. Its value at alpha = 1
        should be the increment, else dense output jumps at the nodes (``Solution.evaluate``
        takes the states there)."""

    def local_error(self, H, q0, p0, Z, h):
        """An estimate of the element's local error, max-norm over (q, p): a scalar, NaN
        where the method has none.

        The default is the estimate every built-in Hamiltonian method uses
        (``_defect.local_error``): the local error through the Alekseev-Groebner formula from
        the defect of ``polynomial`` and the jump to ``increment``, its series truncated
        after m terms. It needs Hamilton's field, so a method given a Lagrangian overrides
        it with NaN.
        """
        dz = jnp.concatenate(self.increment(H, q0, p0, Z, h))
        return local_error(H, q0, p0, self.polynomial(H, q0, p0, Z, h), dz, h)

    def polynomial_with(self, H, q0, p0, Z, h, increment, fields=None):
        """``polynomial`` of an element whose increment ``z1 - z0`` (shape ``(2d,)``) the run has
        already, and maybe Hamilton's field at both ends (``fields = (F(z0), F(z1))``, else
        None). The default ignores them; a method whose polynomial is built from its ends
        (compositions, splittings: the Hermite cubic) overrides it, so that the run does not
        compute its stages again."""
        return self.polynomial(H, q0, p0, Z, h)

    def local_error_with(self, H, q0, p0, Z, h, increment):
        """``local_error`` of an element whose increment the run has already
        (``polynomial_with``)."""
        return self.local_error(H, q0, p0, Z, h)


def degree_and_rule(degree, least):
    """A base class for methods given by a polynomial degree and a quadrature rule: the frozen
    dataclass fields ``(<degree>: int, quadrature: QuadratureRule)`` and their checks.

    Args:
        degree: the degree's field name, as the papers write it ("k" for cG/dG, "s" for
            the variational integrators).
        least: its least value.
    Returns:
        A subclass of ``AbstractMethod`` for the method's class to derive from; the degree is
        static (a new degree means a new compilation), the rule's arrays are leaves.
    """

    def __post_init__(self):
        name, value = type(self).__name__, getattr(self, degree)
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
            raise ValueError(f"{name} needs an integer degree {degree} >= {least}, got {value!r}.")
        if not isinstance(self.quadrature, QuadratureRule):
            raise TypeError(f"{name} needs a QuadratureRule, got {type(self.quadrature).__name__}.")

    fields = [(degree, int, dataclasses.field(metadata=dict(static=True))), ("quadrature", QuadratureRule)]
    doc = f"A method given by a polynomial degree {degree} >= {least} (static) and a quadrature rule."
    namespace = {"__post_init__": __post_init__, "__doc__": doc, "__module__": __name__}
    return dataclasses.make_dataclass("DegreeAndRule", fields, bases=(AbstractMethod,), namespace=namespace,
                                      frozen=True)


def _accepts_part(residual):
    try:
        parameters = inspect.signature(residual).parameters.values()
    except (TypeError, ValueError):
        return True  # no signature to read (a builtin or C function): the trace will tell
    return any(p.name == "part" or p.kind is p.VAR_KEYWORD for p in parameters)


def check_method(method):
    """That ``method`` implements the protocol, before anything is traced: its members, a bool
    ``fixed_point``, a valid ``partition_axis`` with a ``residual(..., part=)``, a pytree, and
    rules of shape ``(n_q,)``. Raises TypeError or ValueError naming what is wrong."""
    name = type(method).__name__
    missing = [m for m in MEMBERS if not callable(getattr(method, m, None))]
    missing += [] if hasattr(method, "fixed_point") else ["fixed_point"]
    if missing:
        raise TypeError(
            "method must be a galerkin_jax method such as gj.CG(1, gj.midpoint()), or implement "
            f"gj.AbstractMethod; {name} lacks {', '.join(missing)}."
        )
    if not isinstance(method.fixed_point, (bool, np.bool_)):
        raise TypeError(f"{name}.fixed_point must be a Python bool (static), got {method.fixed_point!r}.")
    axis = getattr(method, "partition_axis", None)
    if axis is not None:
        if isinstance(axis, bool) or not isinstance(axis, (int, np.integer)):
            raise TypeError(f"{name}.partition_axis must be None or an int axis of the unknowns, got {axis!r}.")
        if not _accepts_part(method.residual):
            raise TypeError(f"{name} has a partition_axis, so its residual must take part=None, 'q' or 'p'.")
    leaves = jax.tree_util.tree_leaves(method, is_leaf=lambda x: isinstance(x, QuadratureRule))
    if len(leaves) == 1 and leaves[0] is method:
        raise TypeError(
            f"{name} must be a pytree (its arrays are traced): decorate the class with @gj.pytree_dataclass."
        )
    for rule in leaves:
        if isinstance(rule, QuadratureRule) and (jnp.ndim(rule.points) != 1 or jnp.ndim(rule.weights) != 1):
            raise ValueError(
                "method.quadrature: points and weights must have shape (n_q,); to sweep "
                "stacked rules, vmap over the method."
            )


def describe_method(method):
    """``CG(k=2)``: a method's class and static fields, which one batch must share."""
    fields = dataclasses.fields(method) if dataclasses.is_dataclass(method) else ()
    static = ", ".join(f"{f.name}={getattr(method, f.name)!r}" for f in fields if f.metadata.get("static"))
    return f"{type(method).__name__}({static})"


def layers(method):
    """``method`` and the methods it wraps, outermost first (``method.method``: a composition's
    method, an explicit form's iterated one)."""
    while method is not None:
        yield method
        method = getattr(method, "method", None)
