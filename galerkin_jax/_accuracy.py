"""Choosing h for a tolerance on the local error, from the a posteriori estimate of a pilot run."""

import jax
import jax.numpy as jnp
import numpy as np

from ._integrate import integrate


def suggest_step_size(H, q0, p0, *, method, tolerance, h, span, args=None, safety=0.8, max_halvings=8) -> tuple[float, dict]:
    """The largest h whose estimated local error (``Solution.error_estimate``) meets ``tolerance``.

    Two pilot runs over ``span`` (from t = 0, with steps ``h`` and ``h / 2``) give the estimate
    ``e(h)`` and its order ``r = log2(e(h) / e(h / 2))`` (2k + 1 for cG(k) with exact enough
    quadrature, 2k + 2 for dG(k), 3 for the midpoint schemes); then
    ``h_new = safety h (tolerance / e(h))^(1 / r)``. A pilot whose solves fail, or whose
    estimate has not yet reached its asymptotic order (``r`` outside [1, 16]), is repeated at
    half the step, up to ``max_halvings`` times; a pilot already at the estimate's round-off
    floor and below the tolerance returns its own h.

    The tolerance is on the local error of one element; the global error after n elements is
    up to n times that for a dissipative method and typically ~sqrt(n) to n times for the
    symplectic ones. Make ``span`` cover the hardest part of the motion (e.g. a perihelion).

    Args:
        H: the Hamiltonian, ``H(q, p)`` or ``H(q, p, args)``; required.
        q0: the initial position, as in ``integrate``; required.
        p0: the initial momentum, of q0's shape; required.
        method: the method whose step to choose, as in ``integrate``; required.
        tolerance: the local (one-element) error wanted, > 0; required.
        h: the pilot step, > 0; required. Take one near the answer, small enough for the
            estimate to show its order.
        span: the time the pilot runs cover, from t = 0; required.
        args: the extra input of ``H``, passed as its third argument; default None.
        safety: the factor < 1 on the predicted h; default 0.8.
        max_halvings: the most times a pilot is repeated at half the step; default 8.

    Returns:
        ``(h, info)`` with ``info = {"order": r, "estimate": e(h_pilot), "pilot_h": h_pilot}``.
    """
    if not (np.isfinite(tolerance) and tolerance > 0):
        raise ValueError(f"tolerance must be finite and > 0, got {tolerance!r}.")
    if not (np.isfinite(span) and span > 0):
        raise ValueError(f"span must be finite and > 0, got {span!r}.")
    for _ in range(max_halvings + 1):
        e1, e2 = _pilots(H, q0, p0, method, h, span, args)
        order = np.log2(e1 / e2) if e1 > 0 and e2 > 0 else np.nan
        if np.isfinite(order) and 1.0 <= order <= 16.0:
            return safety * h * (tolerance / e1) ** (1.0 / order), {"order": order, "estimate": e1, "pilot_h": h}
        if e1 <= tolerance:  # already at the round-off floor of the estimate: h meets the tolerance
            return h, {"order": order, "estimate": e1, "pilot_h": h}
        h = h / 2
    raise ValueError(
        f"suggest_step_size: no pilot run down to h = {2 * h:g} converged with an estimate in its "
        "asymptotic range; start from a smaller h."
    )


def _pilots(H, q0, p0, method, h, span, args):
    """The estimates of the pilot runs over ``span`` with steps h and h / 2 (NaN where one failed):
    one compiled program for both (a vmap over h, the elements of the finer reserved for both)."""
    reserved = max(2, int(np.ceil(span / (h / 2) * (1 - 4 * np.finfo(float).eps))))
    run = lambda h: integrate(H, q0, p0, method=method, h=h, t1=span, max_steps=reserved, args=args)
    sols = jax.vmap(run)(jnp.asarray([h, h / 2]))
    estimates = np.where(np.asarray(sols.status) == 0, np.asarray(sols.error_estimate), np.nan)
    return float(estimates[0]), float(estimates[1])
