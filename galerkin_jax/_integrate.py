"""One time element (``step``), many (``integrate``), and the one-step Jacobian (``amplification_matrix``)."""

import functools

import jax
import jax.numpy as jnp

from . import _basis, _checks
from ._march import bind_args, input_status, march, nan_if_failed, solve_element, solver_options
from ._pytree import pytree_dataclass
from ._solve import SolverOptions, throw_if_failed

DEFAULT_MAX_NEWTON_ITERATIONS = SolverOptions.max_iterations


@pytree_dataclass
class DenseOutput:
    """Every element's polynomial: ``z(t_n + alpha h) = z_n + sum_j W[n, j] P_j(2 alpha - 1)``.

    Attributes:
        h: the step size.
        z: ``(N + 1, 2d)``, the states at the nodes t_n = n h.
        W: ``(N, m, 2d)``, Legendre coefficients of each element's polynomial minus its start.
    """

    h: jax.Array
    z: jax.Array
    W: jax.Array


@pytree_dataclass
class Solution:
    """Saved states of ``integrate``.

    Attributes:
        t: shape ``(m,)``, ``m = n_steps // save_every + 1``, starting at 0.
        q, p: shape ``(m, d)``, the initial state first.
        status: int32 ``Status`` code, 0 when every implicit solve converged. After the
            first failure the remaining states are NaN. Status 0 promises converged solves,
            not accurate steps: read ``error_estimate`` for that.
        stats: ``num_newton_iterations`` (total), ``max_newton_iterations`` (largest count in
            one element), ``batch_newton_iterations`` (the iterations the batch ran:
            under ``vmap`` each element waits for the batch's slowest member) and
            ``num_accepted_stalled`` (elements accepted other than at round-off: their updates
            stopped shrinking with the residual below sqrt(eps) of the state, see ``Status``).
        error_estimate: the largest estimated local (one-element) error of the run, max-norm
            over (q, p), shape () (see ``_defect``); NaN for a failed run and for
            ``LagrangianVI``.
        dense: ``DenseOutput`` with ``integrate(..., dense=True)``, else None.
    """

    t: jax.Array
    q: jax.Array
    p: jax.Array
    status: jax.Array
    stats: dict
    error_estimate: jax.Array
    dense: object = None

    def evaluate(self, t):
        """``(q, p)`` at the times ``t`` (scalar or 1-D) in ``[0, n_steps h]``: the saved states
        at the nodes t = n h, each element's polynomial in between (one run, dense output).

        Returns:
            ``(q, p)``, each shape ``t.shape + (d,)``.
        """
        if self.dense is None:
            raise ValueError("evaluate needs the element polynomials: integrate(..., dense=True).")
        h, z, W = self.dense.h, self.dense.z, self.dense.W
        if jnp.ndim(h) != 0:
            raise ValueError("evaluate works on one run; index a batched Solution first.")
        t = jnp.asarray(t, z.dtype)
        if t.ndim > 1:
            raise ValueError(f"t must be a scalar or 1-D, got shape {t.shape}.")
        end = W.shape[0] * h
        if not isinstance(t, jax.core.Tracer) and not isinstance(end, jax.core.Tracer):
            if not bool(jnp.all((t >= -1e-12 * end) & (t <= end * (1 + 1e-12)))):
                raise ValueError(f"t must lie in [0, {float(end)}] (n_steps h), got values outside.")
        q, p = _evaluate(h, z, W, jnp.atleast_1d(t))
        return q.reshape(t.shape + q.shape[-1:]), p.reshape(t.shape + p.shape[-1:])


@jax.jit
def _evaluate(h, z, W, t):
    N = W.shape[0]
    x = t / h
    node = jnp.round(x)
    at_node = jnp.abs(x - node) <= 4 * jnp.finfo(z.dtype).eps * jnp.maximum(1.0, x)
    n = jnp.clip(jnp.floor(x), 0, N - 1).astype(jnp.int32)
    P = _basis.legendre_values(jnp.clip(x - n, 0.0, 1.0), W.shape[1])
    inside = z[n] + jnp.einsum("tj,tjd->td", P, W[n])
    values = jnp.where(at_node[:, None], z[jnp.clip(node, 0, N).astype(jnp.int32)], inside)
    return jnp.split(values, 2, axis=-1)


def prepare(H, q0, p0, method, h, args):
    _checks.check_function(H)
    _checks.check_method(method)
    q0, p0 = _checks.check_state(q0, p0)
    _checks.check_step_size(h)
    fn = bind_args(H, args)
    _checks.check_scalar_output(fn, q0, p0)
    _checks.check_premise(method, fn, q0, p0)
    return q0, p0, jnp.asarray(h, q0.dtype)


def step(H, q, p, *, method, h, args=None, max_newton_iterations=None, krylov=None, solver=None, throw=False,
         return_status=False):
    """One time element: ``(q, p) -> (q1, p1)``.

    A failed solve returns NaN states (never a plausible one).

    Args:
        H: ``H(q, p)`` or ``H(q, p, args)`` returning a scalar (``L(q, qdot)`` for LagrangianVI).
        q, p: shape ``(d,)``.
        method: e.g. ``CG(k, rule)``, ``DG(k, rule)``.
        h: step size, scalar > 0.
        max_newton_iterations, krylov, solver, throw: as in ``integrate``.
        return_status: also return the int32 ``Status`` code (works under jit).
    Returns:
        ``(q1, p1)``, each shape ``(d,)``; ``(q1, p1, status)`` with ``return_status``.
    """
    q, p, h = prepare(H, q, p, method, h, args)
    options = solver_options(method, max_newton_iterations, krylov, solver)
    q1, p1, status = _step(H, q, p, method, h, args, options)
    if throw:
        throw_if_failed(status)
    q1, p1 = nan_if_failed(q1, status), nan_if_failed(p1, status)
    return (q1, p1, status) if return_status else (q1, p1)


@functools.partial(jax.jit, static_argnums=(0, 6))
def _step(H, q, p, method, h, args, options):
    q1, p1, _, _, status = solve_element(method, H, q, p, h, args, options)
    return q1, p1, jnp.maximum(status, input_status(q, p, h))


def integrate(
    H,
    q0,
    p0,
    *,
    method,
    h,
    n_steps,
    args=None,
    save_every=1,
    max_newton_iterations=None,
    krylov=None,
    solver=None,
    throw=False,
    checkpoint=False,
    dense=False,
    progress=False,
    error_estimate=True,
):
    """Integrate Hamilton's equations over ``n_steps`` elements of size ``h``.

    The elements are chained by a nested ``lax.scan`` (outer over saves, inner over
    ``save_every`` elements), so memory is O(n_steps / save_every).

    Args:
        H: ``H(q, p)`` or ``H(q, p, args)`` (``L(q, qdot)`` for LagrangianVI).
        q0, p0: shape ``(d,)`` (p0 is the initial momentum for LagrangianVI too).
        method: a method object (CG, DG, GalerkinVI, ...).
        h: step size > 0; may be traced (vmap over step sizes).
        n_steps: number of elements, a multiple of ``save_every``. Static.
        args: pytree passed to ``H`` as third argument; may be traced.
        save_every: store every ``save_every``-th state. Static.
        max_newton_iterations: iteration cap per element, a shorthand for
            ``SolverOptions.max_iterations`` (default 48; the fixed-point iteration counts in
            blocks of two, an element of more than 32 unknowns starting with four, so a cap is
            rounded up to a block's end there). Static.
        krylov: a shorthand for ``SolverOptions.krylov`` (default False): solve by
            Newton-Krylov (GMRES on Hessian-vector products) where the fixed-point iteration is
            too slow in a system of more than 256 unknowns per element (k * 2d for cG(k),
            (k + 1) * 2d for dG(k)), which without it has the fixed point only: stiff large
            systems, h omega >~ 1, need it. dG(k >= 1) has no fixed point and always uses it.
            Static.
        solver: ``SolverOptions``, the implicit solve's options (default ``SolverOptions()``);
            the two shorthands above replace their fields. Static.
        throw: raise ``SolverError`` with the status's message when the status is nonzero.
            Only outside ``jit``/``vmap``/``grad``: there the status is traced, and ``throw=True``
            raises a ``TypeError`` before anything runs (read ``Solution.status`` instead).
        checkpoint: rematerialise each saved block in reverse mode: a gradient then stores
            one state per save instead of every element's residuals. Static.
        dense: keep every element's polynomial (``Solution.evaluate``); memory O(n_steps). Static.
        progress: show a progress bar (tqdm if installed, else lines on stderr), ticked from
            inside the compiled loop 50 times per run (~1 ms each). Static.
        error_estimate: compute ``Solution.error_estimate``; False leaves it NaN and saves its
            cost (a third to a half of the run time on small systems). Static.
    Returns:
        ``Solution`` with ``m = n_steps // save_every + 1`` saved states.
    """
    q0, p0, h = prepare(H, q0, p0, method, h, args)
    _checks.check_counts(n_steps, save_every)
    options = solver_options(method, max_newton_iterations, krylov, solver)
    sol = _integrate(H, q0, p0, method, h, args, n_steps, save_every, options, checkpoint, bool(dense),
                     bool(progress), bool(error_estimate))
    if throw:
        throw_if_failed(sol.status)
    return sol


def solution(final, saved, kept, q0, p0, h, block_size):
    """The ``Solution`` of one run from ``march``'s outputs."""
    qs, ps = saved
    n_saves = qs.shape[0]
    dense = None
    if kept is not None:
        starts, W = kept
        z_end = jnp.concatenate([final["q"], final["p"]])
        dense = DenseOutput(h=h, z=jnp.concatenate([starts, z_end[None]]), W=W)
    return Solution(
        t=jnp.arange(n_saves + 1, dtype=q0.dtype) * (block_size * h),
        q=jnp.concatenate([q0[None], qs]),
        p=jnp.concatenate([p0[None], ps]),
        status=final["status"],
        stats={"num_newton_iterations": final["total"], "max_newton_iterations": final["most"],
               "batch_newton_iterations": final["trips"], "num_accepted_stalled": final["lenient"]},
        error_estimate=final["estimate"],
        dense=dense,
    )


@functools.partial(jax.jit, static_argnums=(0, 6, 7, 8, 9, 10, 11, 12))
def _integrate(H, q0, p0, method, h, args, n_steps, save_every, options, checkpoint, dense, progress, estimate):
    final, saved, kept = march(
        method, H, q0, p0, h, args, n_blocks=n_steps // save_every, block_size=save_every,
        options=options, checkpoint=checkpoint, dense=dense, progress=progress, estimate=estimate,
    )
    return solution(final, saved, kept, q0, p0, h, save_every)


def amplification_matrix(H, q, p, *, method, h, args=None, solver=None):
    """A = d z_1 / d z_0 of one element, by ``jax.jacfwd`` through the implicit solve [GBS, eq. (48)].

    For a quadratic H this is the amplification matrix of the two-level scheme
    ``z_{k+1} = A z_0``; in general it is the Jacobian of the one-step map. A failed solve
    gives a matrix of NaN. ``solver``: ``SolverOptions``, as in ``integrate``.

    Returns:
        shape ``(2d, 2d)`` in the ordering ``z = (q, p)``.
    """
    q, p, h = prepare(H, q, p, method, h, args)
    d = q.shape[0]
    options = solver_options(method, solver=solver)

    def one_step(z):
        q1, p1, status = _step(H, z[:d], z[d:], method, h, args, options)
        return jnp.concatenate([q1, p1]), status

    A, status = jax.jacfwd(one_step, has_aux=True)(jnp.concatenate([q, p]))
    return nan_if_failed(A, status)
