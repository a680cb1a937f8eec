"""Reversible gradients of a fixed-step run: memory O(1) in the number of elements
(``integrate(..., checkpoint="reversible")``).

A symmetric one-step method is reversible: Phi_{-h} o Phi_h = id [HLW, Def. V.1.4], so the
state at node n is rebuilt from node n + 1 by one element of step -h, z_n = Phi_{-h}(z_{n+1}),
to the solve's round-off. The run is a ``jax.custom_vjp``: its forward pass is ``march``
unchanged and keeps only the saved states (which the user asked for) and the inputs; its
backward pass walks each saved block backwards from the block's saved end state, rebuilding
z_n and pulling the cotangent lambda_{n+1} back through the forward element at z_n,

    lambda_n = (d Phi_h / d z)(z_n)^T lambda_{n+1},   g_theta += (d Phi_h / d theta)(z_n)^T lambda_{n+1},

with the element's derivative from the implicit function theorem (``_solve.implicit``), theta
= (h, args, the method's arrays). The element of step -h is the element of -H with step +h:
every Galerkin residual holds H through h DH, and (-h) DH = h D(-H) exactly in floating point,
as in a run backwards in time (``_integrate._directed``). The cost is two element solves and
one transposed linear solve per element, against one solve and one linear solve of the stored
gradient; the memory is one block's carry, whatever the number of elements.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ._composition import _is_symmetric_rule
from ._march import compensated_add, march, solve_element, time_reversed
from ._method import layers
from ._quadrature import QuadratureRule
from ._solve import Status

REVERSIBLE = "reversible"


def check_checkpoint(checkpoint):
    """``checkpoint`` is True, False or ``"reversible"``; a ValueError naming it otherwise."""
    if checkpoint is True or checkpoint is False or checkpoint == REVERSIBLE:
        return checkpoint
    raise ValueError(f"checkpoint must be True, False or 'reversible', got {checkpoint!r}.")


def check_reversible(method, *, controller=None, save_at=None, events=None, dense=False, traced_end=False):
    """A ValueError naming the combination where ``checkpoint="reversible"`` cannot be given:
    a method known not to be symmetric (dG(k): its upwind flux; ``LagrangianVI``: given L; a
    concrete rule not symmetric about alpha = 1/2), or a run whose elements are not fixed in
    advance (a controller, ``save_at``, events, a reserve of ``max_steps``: a traced t1 or h,
    or n_steps given with it) or that keeps them (dense)."""
    what = "checkpoint='reversible'"
    for name, given in (("a controller", controller is not None), ("save_at", save_at is not None),
                        ("events", events is not None), ("dense=True", bool(dense)),
                        ("fixed steps in a reserve of max_steps elements (a traced t1 or h needs one)", traced_end)):
        if given:
            raise ValueError(f"{what} is for fixed-step runs of n_steps (or to a concrete t1); not with {name}. "
                             "Use checkpoint=True there.")
    name = type(method).__name__
    inexact = [type(m).__name__ for m in layers(method) if getattr(m, "symmetric", True) is False]
    if inexact:
        raise ValueError(f"{what} needs a method whose step with -h undoes its step with h to round-off; "
                         f"{inexact[-1]} is symmetric to high order only: use checkpoint=True.")
    if name == "DG":
        raise ValueError(f"{what} needs a symmetric method; DG(k) is not (its upwind flux): use CG(k, "
                         "gauss_legendre(k)), GalerkinVI(s, rule) with a symmetric rule, or checkpoint=True.")
    if not getattr(method, "hamiltonian", True):
        raise ValueError(f"{what} needs a method given a Hamiltonian; {name} is given a Lagrangian.")
    rule = getattr(method, "quadrature", None)
    traced = any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(rule))
    if isinstance(rule, QuadratureRule) and not traced:
        if np.ndim(rule.points) == 1 and not _is_symmetric_rule(rule):
            raise ValueError(f"{what} needs a symmetric method; {name}'s rule is not symmetric about alpha = 1/2 "
                             "(points and weights), so its step with -h does not undo its step with h.")


def back_step(method, H, z, comp, h, args, options):
    """One element of step -h from z (``_march.time_reversed``), Kahan-compensated (``compensated_add``):
    ``(z_prev, comp, status)``, z_prev = Phi_{-h}(z), the previous node of a symmetric method."""
    d = z.shape[0] // 2
    q, p, _, _, status = solve_element(method, time_reversed(H), z[:d], z[d:], h, args, options)
    z_prev, comp = compensated_add(z, jnp.concatenate([q, p]) - z, comp)
    return z_prev, comp, status


def rebuild(method, H, z_end, h, args, options, n):
    """z_0 rebuilt from z_n by n elements of step -h (``back_step``): the backward pass's
    reconstruction, whose distance to the true z_0 is its round-off. Returns ``(z_0, status)``."""
    def body(c, _):
        z, comp, status = c
        z, comp, s = back_step(method, H, z, comp, h, args, options)
        return (z, comp, jnp.maximum(status, s)), None

    (z, _, status), _ = jax.lax.scan(body, (z_end, jnp.zeros_like(z_end), jnp.int32(0)), None, length=n)
    return z, status


def _inexact(tree):
    return [jnp.issubdtype(jnp.result_type(x), jnp.inexact) for x in jax.tree.leaves(tree)]


def _element_vjp(method, H, z, h, args, options, lam):
    """The transposed derivative of the forward element at z (``solve_element``, the implicit
    function theorem's): ``(dz, dh, dargs, dmethod)`` = ``(d Phi_h)^T lam`` with respect to
    each, zero for integer leaves."""
    d = z.shape[0] // 2
    leaves, tree = jax.tree.flatten((args, method))
    floats = _inexact((args, method))

    def phi(z, h, inexact):
        it = iter(inexact)
        args, method = jax.tree.unflatten(tree, [next(it) if f else x for x, f in zip(leaves, floats)])
        q1, p1, _, _, status = solve_element(method, H, z[:d], z[d:], h, args, options)
        return jnp.concatenate([q1, p1]), status

    inexact = [x for x, f in zip(leaves, floats) if f]
    _, pull, status = jax.vjp(phi, z, h, inexact, has_aux=True)
    dz, dh, dinexact = pull(lam)
    return dz, dh, dinexact, status


def _run(method, H, q0, p0, h, h_last, args, statics):
    options, n_blocks, block_size, estimate, progress = statics
    return march(method, H, q0, p0, h, args, n_blocks=n_blocks, block_size=block_size, options=options,
                 estimate=estimate, progress=progress, h_last=h_last)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0, 7))
def reversible_march(H, method, q0, p0, h, h_last, args, statics):
    """``march``'s ``(results, saved)`` of a fixed-step run, whose reverse mode rebuilds the
    states backwards (module docstring) instead of storing them. ``statics = (options,
    n_blocks, block_size, estimate, progress)``; ``h_last``: the last element's size or None."""
    return _run(method, H, q0, p0, h, h_last, args, statics)[:2]


def _fwd(H, method, q0, p0, h, h_last, args, statics):
    results, saved, _ = _run(method, H, q0, p0, h, h_last, args, statics)
    return (results, saved), (method, q0, p0, h, h_last, args, saved, results["status"])


def _bwd(H, statics, residuals, cotangents):
    options, n_blocks, block_size, _, _ = statics
    method, q0, p0, h, h_last, args, (qs, ps), status_fwd = residuals
    (results_bar, (qs_bar, ps_bar)) = cotangents
    total = n_blocks * block_size
    ends = jnp.concatenate([qs, ps], axis=1)  # z at the end of each block
    lam_saved = jnp.concatenate([qs_bar, ps_bar], axis=1)
    lam_saved = lam_saved.at[-1].add(jnp.concatenate([results_bar["q"], results_bar["p"]]))
    floats = _inexact((args, method))
    zeros = [jnp.zeros_like(x) for x, f in zip(jax.tree.leaves((args, method)), floats) if f]
    h_bar0 = jnp.zeros_like(h), None if h_last is None else jnp.zeros_like(h_last)

    def element(c, j, b):
        z, comp, lam, h_bar, theta_bar, status = c
        n = b * block_size + j  # the element from node n to n + 1
        last = n == total - 1
        h_el = h if h_last is None else jnp.where(last, h_last, h)
        z_prev, comp, s_back = back_step(method, H, z, comp, h_el, args, options)
        lam, dh, dtheta, s_fwd = _element_vjp(method, H, z_prev, h_el, args, options, lam)
        if h_last is None:
            h_bar = (h_bar[0] + dh, None)
        else:
            h_bar = (h_bar[0] + jnp.where(last, 0.0, dh), h_bar[1] + jnp.where(last, dh, 0.0))
        theta_bar = [a + x for a, x in zip(theta_bar, dtheta)]
        return (z_prev, comp, lam, h_bar, theta_bar, jnp.maximum(status, jnp.maximum(s_back, s_fwd))), None

    def block(c, xs):
        b, z_end, lam_end = xs
        lam, h_bar, theta_bar, status = c
        inner = (z_end, jnp.zeros_like(z_end), lam + lam_end, h_bar, theta_bar, status)
        inner, _ = jax.lax.scan(lambda c, j: element(c, j, b), inner, jnp.arange(block_size), reverse=True)
        return inner[2:], None

    c0 = (jnp.zeros_like(ends[0]), h_bar0, zeros, jnp.int32(Status.SUCCESS))
    (lam, h_bar, theta_bar, status), _ = jax.lax.scan(block, c0, (jnp.arange(n_blocks), ends, lam_saved),
                                                      reverse=True)
    # a failed run (or a failed rebuild) has no derivative: NaN, never a plausible number
    bad = (status_fwd != Status.SUCCESS) | (status != Status.SUCCESS)
    nan = lambda x: jnp.where(bad, jnp.nan, x)
    d = q0.shape[0]
    it = iter(theta_bar)
    args_bar, method_bar = jax.tree.unflatten(jax.tree.structure((args, method)), [
        nan(next(it)) if f else np.zeros(np.shape(x), jax.dtypes.float0)
        for x, f in zip(jax.tree.leaves((args, method)), floats)])
    h_bar = tuple(None if x is None else nan(x) for x in h_bar)
    return method_bar, nan(lam[:d]), nan(lam[d:]), h_bar[0], h_bar[1], args_bar


reversible_march.defvjp(_fwd, _bwd)

FORWARD_MODE = ("checkpoint='reversible' gives reverse-mode derivatives (jax.grad, jax.vjp, jax.jacrev): its "
                "backward pass rebuilds the states instead of storing them. Forward mode (jax.jvp, jax.jacfwd) "
                "stores no states anyway: use checkpoint=False for it.")


def reverse_mode_only(run):
    """``run`` (a call that reaches ``reversible_march``), whose forward mode (a ``jax.custom_vjp``
    has none) raises a TypeError that says what to use instead. Where JAX transforms the run
    after tracing it (``jax.linearize``; ``jax.jvp`` of a ``jax.jit`` around the call) JAX
    raises its own TypeError, "can't apply forward-mode autodiff (jvp) to a custom_vjp function"."""

    def refusing(*args):
        try:
            return run(*args)
        except TypeError as error:
            if "forward-mode" not in str(error):
                raise
            raise TypeError(FORWARD_MODE) from None

    return refusing
