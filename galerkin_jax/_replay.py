"""Derivatives of a run whose steps a controller chose: the steps are constants of the trajectory.

A controller's run is a ``lax.while_loop`` (``_adaptive``), which reverse mode cannot
differentiate. Its accepted steps h_1, ..., h_n are recorded, and the derivatives of its
outputs are those of the run that takes exactly these steps (as diffrax's default adjoint
does): ``attach`` returns the loop's values with the tangents of ``replay``, a ``lax.scan``
over the recorded steps whose elements are solved again and differentiated by the implicit
function theorem (``_solve.implicit``). Reverse mode transposes that scan. The step sizes and
the events carry no derivative; a time-transformed run's states are differentiated at their
fixed times t (``_at_fixed_time``), not at fixed fictive times.
"""

import jax
import jax.numpy as jnp

from . import _adaptive, _output
from ._defect import symplectic_field
from ._march import bind_args, element_residual, state_scale
from ._solve import Status, initial_matrix, solve


def replay(H, controller, options, inputs, t0, hs, places):
    """The end state and the saved states of the run that takes the steps ``hs`` (0: none).

    Args:
        inputs: ``(method, q0, p0, args)``, what the derivatives are taken with respect to.
        hs: ``(max_steps,)`` the accepted steps, zero past the last.
        places: ``(elements, alphas)`` of the save times (``fill_saves``), or None.
    Returns:
        ``(z_end, saved)``, saved None without save times; NaN where an element fails again.
    """
    method, q0, p0, args = inputs
    fn, q0, p0, args, _, clock = _adaptive.problem(H, controller, q0, p0, t0, args)
    residual, H_bound = element_residual(fn, options.solver.sweep_dimension), bind_args(fn, args)
    z0 = jnp.concatenate([q0, p0])

    def element(carry, h):
        z, matrix = carry
        active = h > 0
        h = jnp.where(active, h, 1.0)
        q, p = jnp.split(z, 2)
        guess = method.initial_guess(q, p)
        Z, matrix, _, status, _, _ = solve(residual, (method, q, p, h, args), guess, guess, matrix, state_scale(z),
                                           ~active, True, options)
        z1 = z + jnp.concatenate(method.increment(H_bound, q, p, Z, h))
        z1 = jnp.where(active, jnp.where(status == Status.SUCCESS, z1, jnp.nan), z)
        kept = None if places is None else (z, method.polynomial(H_bound, q, p, Z, h), z1)
        return (z1, matrix), kept

    start = (z0, initial_matrix(method.initial_guess(q0, p0), options))
    (z_end, _), kept = jax.lax.scan(element, start, hs)
    saved = None if places is None else _output.saved_states(places, z0, *kept)
    if clock is not None:
        at_time = _at_fixed_time(symplectic_field(H_bound), clock)
        z_end = at_time(z_end)
        saved = None if saved is None else jax.vmap(at_time)(saved)
    return z_end, saved


def _at_fixed_time(field, clock):
    """A time-transformed run's state z~ with the derivative it has at a fixed t, not at a fixed
    fictive time: dz~ - (dz~/dt) dt, with dz~/dt = J DK / (dt/dtau) and dt the tangent of the
    time coordinate (its value is z~ itself)."""

    def at_time(z):
        rate = jax.lax.stop_gradient(field(z))
        t = z[clock]
        return z - rate / rate[clock] * (t - jax.lax.stop_gradient(t))

    return at_time


def attach(H, controller, options, inputs, t0, hs, places, z_end, saved):
    """``(z_end, saved)``, the loop's values, with the tangents of ``replay`` (module docstring)."""

    @jax.custom_jvp
    def values(inputs, t0, controller, hs, places, z_end, saved):
        return z_end, saved

    @values.defjvp
    def values_jvp(primals, tangents):
        inputs, t0, controller, hs, places, z_end, saved = primals
        run = lambda inputs: replay(H, controller, options, inputs, t0, hs, places)
        _, derivatives = jax.jvp(run, (inputs,), (tangents[0],))
        return (z_end, saved), derivatives

    return values(inputs, t0, controller, hs, places, z_end, saved)
