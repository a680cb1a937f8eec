"""Elements computed in closed form where the structure of H makes them explicit.

``GalerkinVI(1, rule)`` with every point of its rule at alpha = 0 or 1 (``gj.trapezoid()``,
``gj.gauss_lobatto(2)``) has, for a separable H = T(p) + V(q) (``gj.structure``), element
equations [Tang, eqs. (2.26), (2.32)] with s = 1, Q linear and P = p0 + mu constant:

    mu = h W0 g(q0),   c = h (W0 + W1) T'(p0 + mu),   q1 = q0 + c,
    p1 = p0 + h (W0 g(q0) + W1 g(q1)),   g = -V',

W0, W1 the weights at alpha = 0 and 1: a triangular system, solved in this order without
iteration. With the trapezoid (W0 = W1 = 1/2) it is the Stormer-Verlet scheme
(kick-drift-kick; Hairer, Lubich, Wanner, Geometric Numerical Integration, eq. (I.3.6)),
with W1 = 0 or W0 = 0 the two symplectic Euler schemes. The force g(q1) of one element is
g(q0) of the next (first same as last), so a step costs one gradient of V and one of T.

The protocol's members (``residual``, ``polynomial``, ...) are the wrapped method's: a run
whose elements the solver iterates (a controller, ``save_at``, events, a sweep) solves the same
equations from the same start; the fixed-step scan (``_march``) and ``step`` call ``explicit``.
"""

import dataclasses
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from ._method import AbstractMethod
from ._pytree import pytree_dataclass
from ._structure import Structure, structure


@pytree_dataclass
class ExplicitVI(AbstractMethod):
    """``GalerkinVI(1, rule)`` on a separable H, its element in closed form (module docstring).

    Args:
        method: the ``GalerkinVI(1, rule)``; its weights may be traced.
        start, end: static indices of the rule's points at alpha = 0 and at alpha = 1.
    """

    method: AbstractMethod
    start: tuple = dataclasses.field(metadata=dict(static=True))
    end: tuple = dataclasses.field(metadata=dict(static=True))

    fixed_point = True
    partition_axis = 0
    settle = 0
    hamiltonian = True
    forces_per_step = 1  # g(q1); g(q0) is the previous element's

    def initial_guess(self, q0, p0, previous=None, ratio=None):
        return self.method.initial_guess(q0, p0, previous, ratio=ratio)

    def residual(self, H, q0, p0, Z, h, part=None):
        return self.method.residual(H, q0, p0, Z, h, part=part)

    def increment(self, H, q0, p0, Z, h):
        return self.method.increment(H, q0, p0, Z, h)

    def polynomial(self, H, q0, p0, Z, h):
        return self.method.polynomial(H, q0, p0, Z, h)

    def local_error(self, H, q0, p0, Z, h):
        return self.method.local_error(H, q0, p0, Z, h)

    def explicit_start(self, H, q0, p0):
        """g(q0) = -dH/dq at the start of a run, the force the first element reuses."""
        return force(H, q0, p0)

    def explicit_field(self, H, q1, p1, memo):
        """F(z1) at the end of an element whose memo is ``memo`` (``end_field``)."""
        return end_field(H, q1, p1, memo)

    def explicit(self, H, q0, p0, h, g0):
        """The element from the force ``g0 = g(q0)``: ``(Z, (dq, dp), g(q1))``."""
        w = jnp.asarray(self.method.quadrature.weights, q0.dtype)
        W0, W1 = sum(w[i] for i in self.start), sum(w[i] for i in self.end)
        mu = h * W0 * g0
        P = p0 + mu
        c = h * (W0 + W1) * velocity(H, q0, P)  # T'(P): reads no q
        g1 = force(H, q0 + c, P)  # -V'(q1): reads no p
        Z = jnp.stack([c, mu])  # GalerkinVI's unknowns (c_0 | mu_0)
        return Z, (c, h * (W0 * g0 + W1 * g1)), g1


def end_field(H, q1, p1, g1):
    """Hamilton's field at an element's end, F(z1) = (T'(p1), g(q1)), from the force g1 = g(q1)
    that the element computed (its memo): one gradient of T, none of V."""
    return jnp.concatenate([velocity(H, q1, p1), g1])


def force(H, q, p):
    """g = -dH/dq, which for a separable H reads no p (-V'(q))."""
    return -jax.grad(H, argnums=0)(q, p)


def velocity(H, q, p):
    """dH/dp, which for a separable H reads no q (T'(p))."""
    return jax.grad(H, argnums=1)(q, p)


def endpoint_indices(rule):
    """``(start, end)``: the indices of a concrete rule's points at 0 and at 1, or None where a
    point lies inside (0, 1) or the points are traced. A sweep's stacked rules (``(B, n)``,
    ``stack_methods``) count where every member has the same points."""
    if isinstance(rule.points, jax.core.Tracer):
        return None
    points = np.asarray(rule.points)
    if points.ndim == 2 and points.shape[0] >= 1 and np.all(points == points[:1]):
        points = points[0]
    if points.ndim != 1 or not np.all((points == 0.0) | (points == 1.0)):
        return None
    return tuple(int(i) for i in np.flatnonzero(points == 0.0)), tuple(int(i) for i in np.flatnonzero(points == 1.0))


def explicit_form(method, H, q0, p0, args, solver):
    """``method``'s explicit form for the structure of ``H`` (its ``explicit_form(structure)``
    member), or ``method`` itself where it has none or ``solver.explicit`` is False. Where it
    would have one but H's structure cannot be read (an effect, a callback, a loop the analysis
    does not follow), an ``UndecidedStructureWarning`` says so: the elements then iterate.

    Args:
        H: the user's function (flattened states, ``_shape``), args unbound.
        q0, p0: the start state, shape ``(d,)`` (a sweep's: ``(B, d)``, read at member 0).
        args: H's third argument or None (a sweep's: leaves with the leading axis B).
    """
    form = getattr(method, "explicit_form", None)
    if not solver.explicit or form is None or not method.hamiltonian:
        return method
    found = cached_structure(H, q0, p0, args)
    explicit = form(found)
    if explicit is None and found.reason.startswith("undecidable") and form(_SEPARABLE) is not None:
        warnings.warn(f"{type(method).__name__} could run without iteration on a separable H, but whether this H "
                      f"is separable cannot be read from its program ({found.reason}; gj.structure): its elements "
                      "are solved iteratively, at several evaluations of H's gradient each instead of one. Move "
                      "the callback or effect out of H, or pass solver=gj.SolverOptions(explicit=False) to choose "
                      "the iteration knowingly.", UndecidedStructureWarning, stacklevel=4)
    return method if explicit is None else explicit


class UndecidedStructureWarning(UserWarning):
    """A method with an explicit form runs iteratively: H's structure could not be read."""


_SEPARABLE = Structure(True, False, False, "", True)


def sweep_form(method, H, q0, p0, args, solver):
    """``explicit_form`` for a sweep's stacked members: the structure read at member 0 (it reads
    shapes and dtypes alone, which the members share)."""
    member = lambda tree: jax.tree.map(lambda x: x[0], tree)
    return explicit_form(method, H, member(q0), member(p0), None if args is None else member(args), solver)


def shape_spec(tree):
    """A hashable description of a pytree's structure, shapes and dtypes."""
    leaves, treedef = jax.tree.flatten(tree)
    return treedef, tuple((jnp.shape(x), str(jnp.result_type(x))) for x in leaves)


def _program(H, q0, p0, args):
    """H's program at these shapes, as text: what the structure is read from. H may read Python
    state that changes between calls (a flag that adds a coupling term); its program then
    changes, and so does this key."""
    shape = lambda x: jax.ShapeDtypeStruct(jnp.shape(x), jnp.result_type(x))
    operands = jax.tree.map(shape, (q0, p0) if args is None else (q0, p0, args))
    try:
        # through a new function: JAX keeps the traces of H itself, whose Python state may have changed
        return str(jax.make_jaxpr(lambda *xs: H(*xs))(*operands).jaxpr)
    except Exception:  # noqa: BLE001 -- what cannot be traced is read anew (``structure`` says why)
        return None


# structures read so far, oldest first: (H, state and args' shapes and dtypes, H's program) -> Structure
_STRUCTURES = {}
_KEPT = 256


def cached_structure(H, q0, p0, args=None):
    """``structure(H, q0, p0, args)``, read once per H, state shapes and dtypes, args' structure
    and H's program (it reads nothing else), so that a loop of ``step`` calls traces H but not
    its gradient at every call. An H that cannot be hashed or traced is read anew."""
    program = _program(H, q0, p0, args)
    try:
        key = (H, shape_spec(q0), shape_spec(p0), None if args is None else shape_spec(args), program)
        found = None if program is None else _STRUCTURES.get(key)
    except TypeError:
        return structure(H, q0, p0, args)
    if found is None:
        if len(_STRUCTURES) >= _KEPT:
            _STRUCTURES.pop(next(iter(_STRUCTURES)))
        found = _STRUCTURES[key] = structure(H, q0, p0, args)
    return found


def is_explicit(method):
    """Whether the method computes its element in closed form (``explicit``)."""
    return callable(getattr(method, "explicit", None))
