"""Input validation, run before anything is traced.

Shapes and kinds are always checked (they are static); values only where they are
concrete. Traced values are checked inside jit and reported through ``Solution.status``.
"""

import jax
import jax.numpy as jnp
import numpy as np

from ._quadrature import QuadratureRule

_METHOD_MEMBERS = ("initial_guess", "residual", "end_state")


def _concrete(x):
    return not isinstance(x, jax.core.Tracer)


def check_function(H, name="H"):
    if not callable(H):
        raise TypeError(f"{name} must be a callable H(q, p) or H(q, p, args), got {type(H).__name__}.")


def check_method(method):
    if not all(callable(getattr(method, m, None)) for m in _METHOD_MEMBERS):
        raise TypeError(
            "method must be a galerkin_jax method such as gj.CG(1, gj.midpoint()), "
            f"got {type(method).__name__}."
        )
    for rule in jax.tree_util.tree_leaves(method, is_leaf=lambda x: isinstance(x, QuadratureRule)):
        if isinstance(rule, QuadratureRule) and (jnp.ndim(rule.points) != 1 or jnp.ndim(rule.weights) != 1):
            raise ValueError(
                "method.quadrature: points and weights must have shape (n_q,); to sweep "
                "stacked rules, vmap over the method."
            )


def check_state(q0, p0):
    """Convert q0, p0 to float arrays of one shape ``(d,)``; returns them."""
    q0, p0 = (x if isinstance(x, jax.Array) else jnp.asarray(x) for x in (q0, p0))
    for name, x in (("q0", q0), ("p0", p0)):
        if x.ndim != 1 or x.shape[0] == 0:
            raise ValueError(f"{name} must be a 1-D array of length d >= 1, got shape {x.shape}.")
    if q0.shape != p0.shape:
        raise ValueError(f"q0 and p0 must have the same shape, got {q0.shape} and {p0.shape}.")
    dtype = jnp.result_type(q0, p0, float)
    q0, p0 = q0.astype(dtype), p0.astype(dtype)
    for name, x in (("q0", q0), ("p0", p0)):
        if _concrete(x) and not np.all(np.isfinite(np.asarray(x))):
            raise ValueError(f"{name} must be finite, got {x}.")
    return q0, p0


def check_step_size(h):
    if jnp.ndim(h) != 0:
        raise ValueError(f"h must be a scalar, got shape {jnp.shape(h)}.")
    if _concrete(h):
        value = float(h)
        if not np.isfinite(value) or value <= 0.0:
            raise ValueError(f"h must be finite and > 0, got {value}.")


def check_counts(n_steps, save_every):
    for name, value, least in (("n_steps", n_steps, 0), ("save_every", save_every, 1)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
            raise ValueError(f"{name} must be an integer >= {least}, got {value!r}.")
    if n_steps % save_every:
        raise ValueError(f"n_steps ({n_steps}) must be a multiple of save_every ({save_every}).")


def check_iterations(max_newton_iterations):
    value = max_newton_iterations
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"max_newton_iterations must be an integer >= 1, got {value!r}.")


def check_scalar_output(fn, q0, p0, name="H"):
    """The bound function must return a real scalar; checked by ``jax.eval_shape``."""
    try:
        out = jax.eval_shape(fn, q0, p0)
    except TypeError as error:
        raise TypeError(f"{name} could not be called as {name}(q, p[, args]): {error}") from error
    if out.shape != ():
        raise ValueError(f"{name} must return a scalar, got shape {out.shape}.")
    if not jnp.issubdtype(out.dtype, jnp.floating):
        raise TypeError(f"{name} must return a real floating scalar, got dtype {out.dtype}.")
