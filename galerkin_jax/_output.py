"""What a run gives besides its nodes: states between them, from the element polynomials.

Every element n carries ``w(alpha) = z_n + sum_j W[n, j] P_j(2 alpha - 1)``, alpha in [0, 1]
(the method's ``polynomial``). Its time is ``t_n + alpha h_n``, or, in a time-transformed run
(``TimeTransform``), the time coordinate of w itself. This module evaluates w at chosen
times (``save_at``, ``Solution.evaluate``), locates the sign changes of an event function on
it, and holds the dense output of a run.
"""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from . import _basis, _interpolate
from ._pytree import pytree_dataclass


def refined(method, H_bound, z0, z1, W, h):
    """The element polynomial ``W`` refined between the nodes (``_interpolate.refine`` at local
    order 2m - 1, m = W's coefficients: cG(k)'s 2k + 1, the nodes' own; one below the nodes'
    for dG(k) and GalerkinVI), for
    save times, events and dense output; a method given a Lagrangian: ``W`` as it is, padded to
    the same shape. Returns ``(2m - 1, 2d)`` coefficients of the same form as W's."""
    if not method.hamiltonian:
        return padded(W)
    return _interpolate.refine(H_bound, z0, z1, W, h, order=refined_size(W.shape[0]))


def padded(W):
    """``W`` as it is, with zero coefficients up to ``refined``'s shape."""
    m = W.shape[0]
    return jnp.concatenate([W, jnp.zeros((refined_size(m) - m,) + W.shape[1:], W.dtype)])


def refined_size(m):
    """The coefficients of ``refined`` for an element polynomial of m."""
    return max(2 * m - 1, m + 1)


def on_polynomial(z0, W, alpha):
    """w(alpha) for one element: ``z0`` (2d,), ``W`` (m, 2d), ``alpha`` (n,) -> (n, 2d)."""
    return z0[None, :] + _basis.combine(_basis.legendre_values(alpha, W.shape[0]), W)


def time_at(z0, W, alpha, t0, h, clock):
    """The time at ``alpha`` (scalar): ``t0 + alpha h``, or w's coordinate ``clock``."""
    if clock is None:
        return t0 + alpha * h
    return on_polynomial(z0, W, alpha[None])[0, clock]


def state_at(z0, W, z1, alpha, node):
    """The state at ``alpha`` of one element: w(alpha), or at a node (``node`` -1 its start, +1
    its end) the node's state, which a discontinuous w need not reach, exactly, with the
    tangent of w's change from there: so a state at a node has w's slope in alpha. The
    one definition of a state between nodes that ``save_at``, ``Solution.evaluate`` and their
    derivatives read."""
    m = W.shape[0]
    here = _basis.legendre_values(jnp.reshape(alpha, (1,)).astype(W.dtype), m)[0]
    ends = np.polynomial.legendre.legvander(np.array([-1.0, 1.0]), m - 1)  # P_j at alpha = 0, 1: +-1
    at = jnp.where(node < 0, ends[0], jnp.where(node > 0, ends[1], 0.0)).astype(W.dtype)
    delta = _basis.combine(here - at, W)  # w(alpha) - w(node), or w(alpha) - z0 inside
    # at a node: zero in value (the node's state exactly), with w's tangent
    delta = jnp.where(node == 0, delta, delta - jax.lax.stop_gradient(delta))
    return jnp.where(node > 0, z1, z0) + delta


def truncated(W, beta):
    """The coefficients of a -> w(beta a) - z0, the element polynomial on [0, beta] mapped onto
    [0, 1] (the element a terminal event ends at beta): its values at m Gauss points, fitted
    again (exact: the same degree); differentiable in beta."""
    m = W.shape[0]
    points = jnp.asarray(np.polynomial.legendre.leggauss(m)[0] / 2 + 0.5, W.dtype)
    V = _basis.legendre_values(points, m)
    values = _basis.combine(_basis.legendre_values(beta * points, m), W)
    return jnp.linalg.solve(V, values.reshape(m, -1)).reshape(W.shape)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def root(f, alpha, f_args):
    """``alpha``, a root of ``f(alpha, *f_args)`` located beforehand, with its tangent by the
    implicit function theorem: d alpha = -(df/dargs . dargs) / (df/dalpha)."""
    return alpha


@root.defjvp
def _root_jvp(f, primals, tangents):
    alpha, f_args = primals
    _, df = jax.jvp(lambda a: f(alpha, *a), (f_args,), (tangents[1],))
    return alpha, -df / jax.grad(f)(alpha, *f_args)


def _unit(alpha):
    """alpha held in [0, 1], its derivative kept at the ends (``jnp.clip`` halves it there)."""
    return jnp.where(alpha < 0, jnp.zeros_like(alpha), jnp.where(alpha > 1, jnp.ones_like(alpha), alpha))


def locate(f, lo, hi, f_lo, iterations=48):
    """The root of ``f`` in [lo, hi], where f(lo) = ``f_lo`` and f(hi) have opposite signs (or
    f(hi) = 0): Newton's method safeguarded by bisection (the Newton point replaces the bracket's
    midpoint when it lies inside the bracket), a fixed number of iterations, so that the root
    is found to round-off of alpha and the loop's length does not depend on the data.

    Returns alpha, a scalar in [lo, hi]."""
    f_and_slope = jax.value_and_grad(f)

    def body(_, bracket):
        lo, hi, f_lo, x = bracket
        value, slope = f_and_slope(x)
        same = jnp.sign(value) == jnp.sign(f_lo)
        lo, hi = jnp.where(same, x, lo), jnp.where(same, hi, x)
        f_lo = jnp.where(same, value, f_lo)
        newton = x - value / jnp.where(slope == 0, jnp.inf, slope)
        # closed: at the root (value 0, or a Newton point on the bracket's end) x stays, where
        # an open bracket would bisect away from it for the rest of the iterations
        inside = (newton >= lo) & (newton <= hi) & jnp.isfinite(newton)
        return lo, hi, f_lo, jnp.where(inside, newton, 0.5 * (lo + hi))

    lo, hi, _, x = jax.lax.fori_loop(0, iterations, body, (lo, hi, f_lo, 0.5 * (lo + hi)))
    return jnp.clip(x, lo, hi)


def alpha_at_time(z0, W, t, t0, h, clock, node=0):
    """alpha in [0, 1] with time(alpha) = t on one element (``t`` between its ends; ``node`` -1
    or +1: t is its start or its end, alpha 0 or 1, where w's time may miss the node's by
    round-off), differentiable in t and the element (a time-transformed run's by the implicit
    function theorem, ``root``)."""
    if clock is None:
        return _unit((t - t0) / h)
    f = lambda a, z0, W, t: time_at(z0, W, a, t0, h, clock) - t
    zero, one = jnp.zeros((), W.dtype), jnp.ones((), W.dtype)
    located = locate(lambda a: f(a, z0, W, t), zero, one, f(zero, z0, W, t), iterations=24)
    located = jnp.where(node < 0, zero, jnp.where(node > 0, one, located))
    return root(f, jax.lax.stop_gradient(located), (z0, W, t))


class Direction:
    """The run's direction sigma = sign(t1 - t0) as a pytree: it runs forwards in tau = sigma t
    (``_integrate``). A Python +1 or -1, where the direction was known while tracing, is
    auxiliary data (the program is built for it, as a constant); a traced one, the run's order
    known only when it runs (``jit``, ``vmap`` over t1), is a leaf."""

    __slots__ = ("sigma",)

    def __init__(self, sigma):
        self.sigma = sigma

    def __repr__(self):
        return f"Direction({self.sigma!r})"

    def __eq__(self, other):
        """Equal to its sigma: ``dense.direction == -1`` for a run backwards, as when it was an int."""
        return self.sigma == (other.sigma if isinstance(other, Direction) else other)

    def __hash__(self):
        return hash(self.sigma)


def _static(sigma):
    return isinstance(sigma, int) and not isinstance(sigma, bool)


jax.tree_util.register_pytree_node(
    Direction, lambda d: ((), d.sigma) if _static(d.sigma) else ((d.sigma,), None),
    lambda sigma, leaves: Direction(sigma if sigma is not None else leaves[0]))

FORWARDS = Direction(1)


def directed(x, sigma):
    """sigma x: a time t in the run's time tau = sigma t, or back (sigma^2 = 1); x itself for
    a known sigma = 1, -x for -1, so that a known direction's program has no sigma in it."""
    if _static(sigma):
        return x if sigma == 1 else -x
    return sigma * x


# where a save time lies, besides an element's index: at t0 (the initial state), or not reached
AT_START, NOT_WRITTEN = -1, -2


def fill_saves(saved, index, ts, element, z_end, n):
    """Write the states at the times ``ts[index:]`` that lie in the element ``(t_a, t_b]``.

    Args:
        saved: ``(values, elements, alphas)``: the states ``(len(ts), 2d)``, and where each lies:
            the element's index and alpha (1 at its end, where the node value is taken);
            ``AT_START`` a save at t0, ``NOT_WRITTEN`` one the run did not reach.
        index: the first time not yet written.
        ts: the sorted save times.
        element: ``(z0, W, t_a, t_b, h, clock)`` of the element.
        z_end: its end state (the node value, which a discontinuous w need not reach).
        n: the element's index.
    Returns:
        ``(saved, index)``.
    """
    z0, W, t_a, t_b, h, clock = element
    size = ts.shape[0]

    def more(c):
        return (c[1] < size) & (ts[jnp.minimum(c[1], size - 1)] <= t_b)

    def write(c):
        (values, elements, alphas), i = c
        t = ts[i]
        at_end = t == t_b
        alpha = jnp.where(at_end, 1.0, alpha_at_time(z0, W, t, t_a, h, clock))
        value = state_at(z0, W, z_end, alpha, at_end.astype(jnp.int32))
        return (values.at[i].set(value), elements.at[i].set(n), alphas.at[i].set(alpha)), i + 1

    return jax.lax.while_loop(more, write, (saved, index))


@pytree_dataclass
class DenseOutput:
    """Every element's polynomial: ``z(t) = z_n + sum_j W[n, j] P_j(2 alpha - 1)`` on element n.

    ``integrate(..., dense=True)`` returns it as ``Solution.dense``; read states from it with
    ``Solution.evaluate(t)``.

    Attributes:
        t: the node times, ``(N + 1,)`` (inf past the last element of a controller's run).
        z: the states at the nodes, ``(N + 1, 2d)``.
        W: the Legendre coefficients of each element's polynomial minus its start, ``(N, m, 2d)``:
            the method's polynomial refined to the nodes' accuracy (``refined``; m = 2k + 1 for
            cG(k)), not the polynomial the element equations solve for.
        t_end: the time up to which the run holds valid states (a failed run's last good node, a
            terminal event's time); NaN after it.
        t1: the end of the requested span.
        clock: None where alpha = (t - t_n) / h_n, else the index d of the time coordinate in
            z = (q, t, p, p_t) (a time-transformed run), dropped by ``view``. Static.
        direction: the run's ``Direction``, sigma = sign(t1 - t0): ``.sigma`` is -1 for a run
            backwards in time (t1 < t0), whose times decrease; a Python int where the direction
            was known while tracing, else an array, e.g. one per member under ``vmap``.
    """

    t: jax.Array
    z: jax.Array
    W: jax.Array
    t_end: jax.Array
    t1: jax.Array
    clock: object = dataclasses.field(default=None, metadata=dict(static=True))
    direction: Direction = FORWARDS

    def view(self, z):
        """``(q, p)`` of states z (..., 2d) or, time-transformed, (..., 2d + 2)."""
        return user_view(z, self.clock)


def user_view(z, clock):
    """``(q, p)`` from z = (q, p), or from z = (q, t, p, p_t) when ``clock`` = d."""
    if clock is None:
        return tuple(jnp.split(z, 2, axis=-1))
    d = clock
    return z[..., :d], z[..., d + 1 : 2 * d + 1]


def evaluate(dense, t):
    """States at the times ``t`` (1-D) from ``dense``; NaN outside ``[t_0, t_end]``, in the run's
    own increasing time tau = sigma t, where its elements were solved (``Direction``)."""
    sigma = dense.direction.sigma
    if not _static(sigma) or sigma != 1:
        into = lambda x: directed(x, sigma)
        dense, t = dataclasses.replace(dense, t=into(dense.t), t_end=into(dense.t_end), t1=into(dense.t1),
                                       direction=FORWARDS), into(t)
    N = dense.W.shape[0]
    starts = dense.t[:-1]
    n = jnp.clip(jnp.searchsorted(starts, t, side="left") - 1, 0, N - 1)  # a node: the element it ends
    clock = dense.clock

    def one(t, n):
        z0, W, t_a, t_b = dense.z[n], dense.W[n], dense.t[n], dense.t[n + 1]
        node = jnp.where(t == t_a, -1, jnp.where(t == t_b, 1, 0))
        alpha = alpha_at_time(z0, W, t, t_a, t_b - t_a, clock, node)
        return state_at(z0, W, dense.z[n + 1], alpha, node)

    values = jax.vmap(one)(t, n)
    inside = (t >= dense.t[0]) & (t <= dense.t_end)
    return jnp.where(inside[:, None], values, jnp.nan)
